//! Building a [`FemSystem`] from a [`FemDesc`]: validation, lumped masses, templates.

use std::collections::HashMap;

use nalgebra::Matrix3;

use super::caches::Caches;
use super::execution::Execution;
use super::rotations::{ExtractCount, RotationState, Source};
use super::{Element, FemSystem, MatData, MeshData, V3, gather};
use crate::FemError;
use crate::element::{Mat12, Template, TetGeometry};
use crate::system::FemDesc;

impl FemSystem {
    /// Build from arrays. Errors on out-of-range ids, non-positive rest volumes, bad
    /// materials, or an element whose geometry does not match its shape template.
    pub fn new(desc: &FemDesc) -> Result<Self, FemError> {
        let n = desc.rest.len();
        if !desc.fixed.is_empty() && desc.fixed.len() != n {
            return Err(FemError::Size {
                what: "fixed",
                expected: n,
                got: desc.fixed.len(),
            });
        }
        let mut materials = Vec::with_capacity(desc.materials.len());
        for (i, m) in desc.materials.iter().enumerate() {
            if !(m.young > 0.0 && m.poisson > -1.0 && m.poisson < 0.5 && m.density > 0.0)
                || m.rayleigh_mass < 0.0
                || m.rayleigh_stiffness < 0.0
            {
                return Err(FemError::BadMaterial {
                    material: i,
                    reason: format!("{m:?}: need E > 0, −1 < ν < 0.5, ρ > 0, α, β ≥ 0"),
                });
            }
            let (lambda, mu) = m.lame();
            materials.push(MatData {
                lambda,
                mu,
                beta: m.rayleigh_stiffness,
            });
        }
        let mut sources = Vec::with_capacity(desc.rotation_sources.len() + desc.elements.len());
        for (i, s) in desc.rotation_sources.iter().enumerate() {
            if s.nodes.iter().any(|&k| k >= n) {
                return Err(FemError::BadSource {
                    index: i,
                    reason: "node id out of range".into(),
                });
            }
            let dm_inv = match s.rest_inverse_edges {
                Some(m) => m,
                None => {
                    TetGeometry::new(&gather(&desc.rest, &s.nodes))
                        .map_err(|e| FemError::BadSource {
                            index: i,
                            reason: e.to_string(),
                        })?
                        .dm_inv
                }
            };
            sources.push(Source {
                nodes: s.nodes,
                dm_inv,
                rotation: Matrix3::identity(),
                x_last: gather(&desc.rest, &s.nodes),
                sigma: None,
                valid: false,
                fresh: false,
                users: 0,
                pass: 0,
            });
        }
        let mut templates: Vec<Template> = Vec::new();
        let mut template_uses = Vec::new();
        let mut by_key: HashMap<u64, usize> = HashMap::new();
        let mut combos: Vec<Mat12> = Vec::new();
        let mut by_combo: HashMap<(usize, usize), usize> = HashMap::new();
        let mut elements = Vec::with_capacity(desc.elements.len());
        let mut mass = vec![0.0; n];
        let mut mass_damping = vec![0.0; n];
        for (ei, e) in desc.elements.iter().enumerate() {
            if e.nodes.iter().any(|&k| k >= n) {
                return Err(FemError::BadElement {
                    element: ei,
                    reason: "node id out of range".into(),
                });
            }
            let Some(mat) = desc.materials.get(e.material) else {
                return Err(FemError::BadElement {
                    element: ei,
                    reason: format!("material {} out of range", e.material),
                });
            };
            let xr = gather(&desc.rest, &e.nodes);
            let geom = TetGeometry::new(&xr).map_err(|err| match err {
                FemError::BadElement { reason, .. } => FemError::BadElement {
                    element: ei,
                    reason,
                },
                other => other,
            })?;
            let template = match e.shape {
                None => None,
                Some(s) => {
                    let ti = match by_key.get(&s.key) {
                        Some(&t) => t,
                        None => {
                            templates.push(Template::new(s.key, &xr, s.scale)?);
                            template_uses.push(0);
                            by_key.insert(s.key, templates.len() - 1);
                            templates.len() - 1
                        }
                    };
                    let expect = templates[ti].dm_inv_hat / s.scale;
                    if (expect - geom.dm_inv).norm() > 1e-9 * geom.dm_inv.norm() {
                        return Err(FemError::BadElement {
                            element: ei,
                            reason: format!(
                                "geometry does not match shape key {} at scale {} m",
                                s.key, s.scale
                            ),
                        });
                    }
                    template_uses[ti] += 1;
                    Some((ti, s.scale))
                }
            };
            let combo = match template {
                None => usize::MAX,
                Some((ti, _)) => *by_combo.entry((ti, e.material)).or_insert_with(|| {
                    let t = &templates[ti];
                    let (l, m) = mat.lame();
                    combos.push(t.k_lambda * l + t.k_mu * m);
                    combos.len() - 1
                }),
            };
            if let Some(s) = e.rotation_source
                && s >= desc.rotation_sources.len()
            {
                return Err(FemError::BadElement {
                    element: ei,
                    reason: format!("rotation source {s} out of range"),
                });
            }
            sources.push(Source {
                nodes: e.nodes,
                dm_inv: geom.dm_inv,
                rotation: Matrix3::identity(),
                x_last: xr,
                sigma: None,
                valid: false,
                fresh: false,
                users: 0,
                pass: 0,
            });
            let own_source = sources.len() - 1;
            let source = e.rotation_source.unwrap_or(own_source);
            sources[source].users += 1;
            let m4 = mat.density * geom.volume / 4.0;
            for &k in &e.nodes {
                mass[k] += m4;
                mass_damping[k] += mat.rayleigh_mass * m4;
            }
            elements.push(Element {
                nodes: e.nodes,
                material: e.material,
                dm_inv: geom.dm_inv,
                grads: geom.grads,
                volume: geom.volume,
                template,
                combo,
                source,
                own_source,
            });
        }
        let fixed = if desc.fixed.is_empty() {
            vec![false; n]
        } else {
            desc.fixed.clone()
        };
        tracing::debug!(
            nodes = n,
            elements = elements.len(),
            sources = sources.len(),
            templates = templates.len(),
            "built FemSystem"
        );
        Ok(Self {
            mesh: MeshData {
                rest: desc.rest.clone(),
                elements,
                materials,
                fixed,
                mass,
                mass_damping,
                templates,
                template_uses,
                combos,
            },
            rotations: RotationState {
                sources,
                num_shared: desc.rotation_sources.len(),
                pending: ExtractCount::default(),
                pass: 1,
                last_pass: ExtractCount::default(),
            },
            k_ext: Vec::new(),
            caches: Caches {
                warm_dv: vec![V3::zeros(); n],
                by_source_stale: true,
                ..Caches::default()
            },
            exec: Execution::default(),
        })
    }
}
