//! Attachments: connective layers that tie two bodies (the scene's `[[attachment]]`,
//! e.g. the gallbladder bed), and their release by dissection.
//!
//! A layer is a set of springs between embedded points of two bodies: every surface vertex
//! of the attached body inside the layer's box is tied to the nearest surface vertex of the
//! host body within `reach`. Each end is hosted by its own body's lattice (barycentric
//! weights of a leaf), so the spring's force is spread over the eight nodes of the two host
//! tets. The spring pairs are a pure function of the scene (same on every site), so a
//! spring is named by `(layer, index)` and a release is a [`crate::cut::ReleaseOp`] listing
//! indices: releases are topology operations, shared, ordered and digested with the cuts
//! ([`crate::cut::TopologyLog`]). What is released stays released.
//!
//! Forces are explicit (computed at the start of the step) with their stiffness on the
//! diagonal node blocks (`w_i² K`, `K` the spring's tangent stiffness) added to the implicit
//! step, the same treatment as contact forces: stable for the layer's stiffness, without
//! coupling blocks between the two bodies in the FEM matrix.
//!
//! The two bodies must not share lattice nodes (all bodies share one lattice; bodies whose
//! cells touch are one elastic body). [`Attachments::build`] checks this.

pub mod hook;
#[cfg(test)]
mod tests;

use nalgebra::{Matrix3, Vector3};
use sim_lattice::{Embedding, Lattice, NodeId, TetId};
use sim_scene::{Scene, TriMesh};

use crate::cut::ReleaseOp;
use crate::error::SimError;

type V3 = Vector3<f64>;

/// One attachment spring, in rest coordinates (m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spring {
    /// The end on the attached body (one of its surface vertices).
    pub attached: V3,
    /// The end on the host body (its surface vertex nearest to `attached`).
    pub host: V3,
    /// Rest length (m): the ends' rest distance.
    pub rest_length: f64,
}

/// The current state of a spring.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpringState {
    /// Midpoint of the two ends (m, world).
    pub midpoint: V3,
    /// Tension (N; negative when compressed).
    pub tension: f64,
}

/// One connective layer between two bodies.
#[derive(Clone, Debug)]
pub struct Layer {
    /// The scene's name of the layer.
    pub name: String,
    /// Body index of the host (`bodies[0]`).
    pub host_body: usize,
    /// Body index of the attached body (`bodies[1]`).
    pub attached_body: usize,
    /// Stiffness of every spring (N/m): the layer's stiffness over the spring count.
    pub spring_stiffness: f64,
    /// Springs a hook releases per second.
    pub release_rate: f64,
    /// Least tension (N) at which a spring releases.
    pub release_force: f64,
    /// Reach of a hook's tip (m).
    pub release_radius: f64,
    /// The springs, in the attached body's surface vertex order.
    pub springs: Vec<Spring>,
    /// Whether each spring is released.
    released: Vec<bool>,
    /// Embedded ends: `2 i` the attached end of spring `i`, `2 i + 1` its host end.
    ends: Embedding,
    /// Once a cut has separated elements: the degrees of freedom each end follows (the
    /// copy of its host leaf on its side of the cut), in the order of `ends`. `None`: the
    /// host leaf's lattice nodes.
    end_dofs: Option<Vec<[usize; 4]>>,
}

impl Layer {
    /// Whether spring `i` is released.
    pub fn is_released(&self, i: usize) -> bool {
        self.released.get(i).copied().unwrap_or(true)
    }
    /// Springs still holding.
    pub fn holding(&self) -> usize {
        self.released.iter().filter(|r| !**r).count()
    }
    /// Indices of the released springs, ascending.
    pub fn released_indices(&self) -> Vec<u32> {
        (0..self.released.len())
            .filter(|&i| self.released[i])
            .map(|i| i as u32)
            .collect()
    }

    /// End `k`'s position (m), the degrees of freedom it follows and their weights.
    fn end(&self, x: &[V3], k: usize) -> (V3, [usize; 4], [f64; 4]) {
        let (_, w, _) = self.ends.host(k);
        let dofs = self.end_dofs(k);
        let p = (0..4).map(|j| w[j] * x[dofs[j]]).sum();
        (p, dofs, w)
    }

    /// The degrees of freedom end `k` follows (`2 i`: spring `i`'s attached end, `2 i + 1`
    /// its host end): its host leaf's nodes, or after a cut the copy on its side.
    pub fn end_dofs(&self, k: usize) -> [usize; 4] {
        match &self.end_dofs {
            Some(d) => d[k],
            None => self.ends.host(k).2.map(|n| n.0 as usize),
        }
    }

    /// Rest position (m) of end `k`.
    fn end_rest(&self, k: usize) -> &V3 {
        let s = &self.springs[k / 2];
        if k.is_multiple_of(2) {
            &s.attached
        } else {
            &s.host
        }
    }

    /// Current midpoint and tension of spring `i` at node positions `x` (m).
    pub fn state(&self, x: &[V3], i: usize) -> SpringState {
        let (p, _, _) = self.end(x, 2 * i);
        let (q, _, _) = self.end(x, 2 * i + 1);
        SpringState {
            midpoint: 0.5 * (p + q),
            tension: self.spring_stiffness * ((p - q).norm() - self.springs[i].rest_length),
        }
    }
}

/// Every connective layer of a simulation.
#[derive(Clone, Debug, Default)]
pub struct Attachments {
    /// Layers in scene order.
    pub layers: Vec<Layer>,
}

impl Attachments {
    /// Springs of every `[[attachment]]` of `scene`. `surfaces[b]` is body `b`'s rest
    /// surface; `file` labels errors. Fails when a layer has no spring or ties two bodies
    /// that share lattice nodes.
    pub fn build(
        scene: &Scene,
        file: &str,
        lattice: &Lattice,
        surfaces: &[&TriMesh],
    ) -> Result<Self, SimError> {
        let mut layers = Vec::new();
        let component = if scene.attachments.is_empty() {
            Vec::new()
        } else {
            node_components(lattice)
        };
        for (li, a) in scene.attachments.iter().enumerate() {
            let err = |problem: String| {
                SimError::Scene(sim_scene::SceneError::Invalid {
                    file: file.to_string(),
                    key: format!("attachment[{li}]"),
                    problem: format!("({}) {problem}", a.name),
                })
            };
            let body = |name: &str| {
                scene
                    .bodies
                    .iter()
                    .position(|b| b.name == name)
                    .ok_or_else(|| err(format!("undefined body {name:?}")))
            };
            let (host_body, attached_body) = (body(&a.bodies[0])?, body(&a.bodies[1])?);
            let (host, attached) = (surfaces[host_body], surfaces[attached_body]);
            let mut springs = Vec::new();
            for v in attached.vertices.iter().filter(|v| a.region.contains(v)) {
                // Nearest host vertex; ties go to the lower index (same on every site).
                let nearest = host.vertices.iter().map(|h| ((h - v).norm(), *h)).fold(
                    None,
                    |best: Option<(f64, V3)>, c| match best {
                        Some(b) if b.0 <= c.0 => Some(b),
                        _ => Some(c),
                    },
                );
                if let Some((d, h)) = nearest
                    && d <= a.reach
                {
                    springs.push(Spring {
                        attached: *v,
                        host: h,
                        rest_length: d,
                    });
                }
            }
            if springs.is_empty() {
                return Err(err(format!(
                    "no surface vertex of {:?} inside the box has a surface vertex of {:?} \
                     within reach ({} m)",
                    a.bodies[1], a.bodies[0], a.reach
                )));
            }
            let points: Vec<V3> = springs.iter().flat_map(|s| [s.attached, s.host]).collect();
            let ends = Embedding::new(lattice, &points)?;
            for i in 0..springs.len() {
                let (_, _, na) = ends.host(2 * i);
                let (_, _, nh) = ends.host(2 * i + 1);
                if component[na[0].0 as usize] == component[nh[0].0 as usize] {
                    return Err(err(format!(
                        "bodies {:?} and {:?} share lattice nodes (their lattice cells touch): \
                         leave at least one empty cell ({} m) between them",
                        a.bodies[0],
                        a.bodies[1],
                        lattice.params().cell
                    )));
                }
            }
            let n = springs.len();
            tracing::info!(
                layer = %a.name,
                springs = n,
                stiffness_n_per_m = a.stiffness,
                "attachment layer built"
            );
            layers.push(Layer {
                name: a.name.clone(),
                host_body,
                attached_body,
                spring_stiffness: a.stiffness / n as f64,
                release_rate: a.release_rate,
                release_force: a.release_force,
                release_radius: a.release_radius,
                springs,
                released: vec![false; n],
                ends,
                end_dofs: None,
            });
        }
        Ok(Attachments { layers })
    }

    /// Re-hosts the ends after a lattice topology change.
    pub(crate) fn update(&mut self, lattice: &Lattice) {
        for l in &mut self.layers {
            l.ends.update(lattice);
        }
    }

    /// After a cut: every end follows `dofs(host leaf, its nodes, end's rest position)`,
    /// the degrees of freedom of the leaf's copy on the end's side.
    pub(crate) fn follow_cut(&mut self, dofs: impl Fn(TetId, [NodeId; 4], &V3) -> [usize; 4]) {
        for l in &mut self.layers {
            let follow = (0..l.ends.len())
                .map(|k| {
                    let (t, _, nodes) = l.ends.host(k);
                    dofs(t, nodes, l.end_rest(k))
                })
                .collect();
            l.end_dofs = Some(follow);
        }
    }

    /// Checks a release against the layers (the layer and every index exist).
    pub fn validate(&self, op: &ReleaseOp) -> Result<(), String> {
        let layer = self.layers.get(op.layer as usize).ok_or_else(|| {
            format!(
                "release {:?}: no attachment layer {} (the scene has {})",
                op.id,
                op.layer,
                self.layers.len()
            )
        })?;
        if op.springs.is_empty() {
            return Err(format!("release {:?} lists no spring", op.id));
        }
        if let Some(s) = op
            .springs
            .iter()
            .find(|&&s| s as usize >= layer.springs.len())
        {
            return Err(format!(
                "release {:?}: layer {} has {} springs, no spring {s}",
                op.id,
                layer.name,
                layer.springs.len()
            ));
        }
        Ok(())
    }

    /// Marks the op's springs released (after [`Attachments::validate`]); returns how many
    /// were holding.
    pub(crate) fn release(&mut self, op: &ReleaseOp) -> usize {
        let Some(layer) = self.layers.get_mut(op.layer as usize) else {
            return 0;
        };
        let mut n = 0;
        for &s in &op.springs {
            if let Some(r) = layer.released.get_mut(s as usize)
                && !*r
            {
                *r = true;
                n += 1;
            }
        }
        n
    }

    /// Every layer's released springs (for the topology digest).
    pub(crate) fn released_sets(&self) -> Vec<Vec<u32>> {
        self.layers.iter().map(Layer::released_indices).collect()
    }

    /// Adds the holding springs' forces (N) to `f` and their stiffness blocks (N/m) to
    /// `k`, at positions `x` (both indexed by node slot).
    pub(crate) fn add_forces(&self, x: &[V3], f: &mut [V3], k: &mut Vec<(usize, Matrix3<f64>)>) {
        for l in &self.layers {
            for (i, s) in l.springs.iter().enumerate() {
                if l.released[i] {
                    continue;
                }
                let (p, na, wa) = l.end(x, 2 * i);
                let (q, nh, wh) = l.end(x, 2 * i + 1);
                let d = p - q;
                let len = d.norm();
                let ks = l.spring_stiffness;
                let (force, stiffness) = if len > 1e-12 {
                    let dir = d / len;
                    let along = dir * dir.transpose();
                    let lateral = (1.0 - s.rest_length / len).max(0.0);
                    (
                        -ks * (len - s.rest_length) * dir,
                        ks * (along + lateral * (Matrix3::identity() - along)),
                    )
                } else {
                    (V3::zeros(), ks * Matrix3::identity())
                };
                for j in 0..4 {
                    let (a, h) = (na[j], nh[j]);
                    if let Some(fa) = f.get_mut(a) {
                        *fa += wa[j] * force;
                    }
                    if let Some(fh) = f.get_mut(h) {
                        *fh -= wh[j] * force;
                    }
                    k.push((a, wa[j] * wa[j] * stiffness));
                    k.push((h, wh[j] * wh[j] * stiffness));
                }
            }
        }
    }

    /// Elastic energy of the holding springs (J).
    pub fn energy(&self, x: &[V3]) -> f64 {
        self.layers
            .iter()
            .map(|l| {
                (0..l.springs.len())
                    .filter(|&i| !l.released[i])
                    .map(|i| {
                        let st = l.state(x, i);
                        0.5 * st.tension * st.tension / l.spring_stiffness
                    })
                    .sum::<f64>()
            })
            .sum()
    }
}

/// Connected component of every node slot (through shared leaves), by union–find.
fn node_components(lattice: &Lattice) -> Vec<u32> {
    let cap = lattice.node_capacity();
    let mut parent: Vec<u32> = (0..cap as u32).collect();
    fn find(p: &mut [u32], mut i: u32) -> u32 {
        while p[i as usize] != i {
            p[i as usize] = p[p[i as usize] as usize];
            i = p[i as usize];
        }
        i
    }
    for &t in lattice.leaves() {
        let n = lattice.tet_nodes(t);
        let r0 = find(&mut parent, n[0].0);
        for m in &n[1..] {
            let r = find(&mut parent, m.0);
            parent[r as usize] = r0;
        }
    }
    (0..cap as u32).map(|i| find(&mut parent, i)).collect()
}
