//! Rotation state: the rotation sources (the caller's shared ones, then one per element),
//! which element uses which, and the extraction passes with their reuse-at-rest skip.

use nalgebra::Matrix3;

use super::{FemSystem, V3, gather};
use crate::FemError;
use crate::element::edge_matrix;
use crate::polar::{ByersXu, PolarMethod, PolarResult, RotationExtractor, WarmStart};

/// The rotation sources and the bookkeeping of their extraction passes.
#[derive(Clone, Debug)]
pub(super) struct RotationState {
    /// The caller's shared sources, then one per element.
    pub(super) sources: Vec<Source>,
    /// Caller's (shared) sources are `sources[..num_shared]`.
    pub(super) num_shared: usize,
    /// Extractions of shared sources requested between steps.
    pub(super) pending: ExtractCount,
    /// Rotation passes done (1-based numbering of the current one).
    pub(super) pass: u64,
    /// Statistics of the last rotation pass.
    pub(super) last_pass: ExtractCount,
}

/// A tet whose rotation elements use: the caller's shared one or an element's own.
#[derive(Clone, Debug)]
pub(super) struct Source {
    pub(super) nodes: [usize; 4],
    pub(super) dm_inv: Matrix3<f64>,
    pub(super) rotation: Matrix3<f64>,
    pub(super) x_last: [V3; 4],
    pub(super) sigma: Option<(f64, f64)>,
    pub(super) valid: bool,
    /// Extracted at the current positions (since the last [`FemSystem::update_rotations`]).
    pub(super) fresh: bool,
    /// Elements currently using this source.
    pub(super) users: u32,
    /// Rotation pass ([`FemSystem::update_rotations`] count) of the last extraction.
    pub(super) pass: u64,
}

/// Extraction counters `(extracted, reused, polar iterations, inverted)`.
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct ExtractCount {
    pub(super) extracted: usize,
    pub(super) reused: usize,
    pub(super) iterations: usize,
    pub(super) inverted: usize,
    /// Max `‖R_new − R_old‖²_F` over sources extracted in consecutive passes.
    pub(super) max_change_sq: f64,
}

impl ExtractCount {
    pub(super) fn merge(self, o: Self) -> Self {
        Self {
            extracted: self.extracted + o.extracted,
            reused: self.reused + o.reused,
            iterations: self.iterations + o.iterations,
            inverted: self.inverted + o.inverted,
            max_change_sq: self.max_change_sq.max(o.max_change_sq),
        }
    }
}

impl FemSystem {
    /// Number of rotation sources: the caller's shared ones first, then one per element.
    pub fn num_rotation_sources(&self) -> usize {
        self.rotations.sources.len()
    }

    /// Number of the caller's (shared) rotation sources, `FemDesc::rotation_sources.len()`.
    pub fn num_shared_sources(&self) -> usize {
        self.rotations.num_shared
    }

    /// Rotation sources some element uses now (only these are extracted by a step).
    pub fn num_referenced_sources(&self) -> usize {
        self.rotations
            .sources
            .iter()
            .filter(|s| s.users > 0)
            .count()
    }

    /// The shared source element `ei` uses, or None when it uses its own rotation.
    pub fn element_source(&self, ei: usize) -> Option<usize> {
        let e = &self.mesh.elements[ei];
        (e.source != e.own_source).then_some(e.source)
    }

    /// Switch the rotation source of every element: `Some(s)` uses shared source `s`
    /// (`s < num_shared_sources()`), `None` the element's own F. Takes effect at the next
    /// force evaluation / step; only sources that some element references are extracted.
    /// Cost O(elements); an unchanged assignment changes nothing.
    pub fn set_rotation_assignment(
        &mut self,
        assignment: &[Option<usize>],
    ) -> Result<(), FemError> {
        if assignment.len() != self.mesh.elements.len() {
            return Err(FemError::Size {
                what: "rotation assignment",
                expected: self.mesh.elements.len(),
                got: assignment.len(),
            });
        }
        if let Some((ei, s)) = assignment.iter().enumerate().find_map(|(ei, a)| {
            a.filter(|s| *s >= self.rotations.num_shared)
                .map(|s| (ei, s))
        }) {
            return Err(FemError::BadElement {
                element: ei,
                reason: format!(
                    "rotation source {s} out of range ({} shared sources)",
                    self.rotations.num_shared
                ),
            });
        }
        for (e, a) in self.mesh.elements.iter_mut().zip(assignment) {
            let new = a.unwrap_or(e.own_source);
            if new != e.source {
                self.rotations.sources[e.source].users -= 1;
                self.rotations.sources[new].users += 1;
                e.source = new;
                self.caches.by_source_stale = true;
            }
        }
        Ok(())
    }

    /// Rotation of shared source `s` at positions `x`, extracted now unless it already was
    /// at these positions (since the last step) or its nodes are at rest (`rest_threshold`,
    /// m, as in [`StepParams::rest_threshold`](crate::StepParams::rest_threshold)). The extraction counts towards the next
    /// step's [`StepStats::rotations_extracted`](crate::StepStats::rotations_extracted), and the step does not extract it again.
    /// For the caller's sharing test; `s < num_shared_sources()`.
    pub fn shared_source_rotation(
        &mut self,
        s: usize,
        x: &[V3],
        polar: &PolarMethod,
        rest_threshold: f64,
    ) -> Matrix3<f64> {
        assert!(
            s < self.rotations.num_shared,
            "shared source {s} out of range"
        );
        let src = &mut self.rotations.sources[s];
        if !src.fresh {
            extract_source(
                src,
                x,
                polar,
                rest_threshold,
                self.rotations.pass,
                &mut self.rotations.pending,
            );
        }
        src.rotation
    }

    /// Current rotation of a source (valid after a step / force evaluation).
    pub fn source_rotation(&self, source: usize) -> Matrix3<f64> {
        self.rotations.sources[source].rotation
    }

    /// Current rotation used by an element.
    pub fn element_rotation(&self, element: usize) -> Matrix3<f64> {
        self.rotations.sources[self.mesh.elements[element].source].rotation
    }

    pub(super) fn element_rotation_of(
        &self,
        ei: usize,
        rotations: Option<&[Matrix3<f64>]>,
    ) -> Matrix3<f64> {
        let s = self.mesh.elements[ei].source;
        match rotations {
            Some(r) => r[s],
            None => self.rotations.sources[s].rotation,
        }
    }

    /// Extract rotations at `x` of all sources some element uses, without touching stored
    /// state (unused sources keep their stored rotation).
    pub fn compute_rotations(&self, x: &[V3], polar: &PolarMethod) -> Vec<Matrix3<f64>> {
        self.rotations
            .sources
            .iter()
            .map(|s| {
                if s.users == 0 {
                    return s.rotation;
                }
                let f = edge_matrix(&gather(x, &s.nodes)) * s.dm_inv;
                let warm = WarmStart {
                    rotation: s.valid.then_some(s.rotation),
                    sigma_bounds: None,
                };
                polar.extract(&f, Some(&warm)).rotation
            })
            .collect()
    }

    /// Update stored rotations at `x` of the sources some element uses, skipping sources
    /// whose nodes all moved less than `rest_threshold` (m) since their last extraction
    /// and those already extracted at `x` by [`FemSystem::shared_source_rotation`].
    /// Returns `(extracted, reused, polar iterations, inverted)`, including the shared
    /// extractions requested since the previous call.
    pub fn update_rotations(
        &mut self,
        x: &[V3],
        polar: &PolarMethod,
        rest_threshold: f64,
    ) -> (usize, usize, usize, usize) {
        let mut c = std::mem::take(&mut self.rotations.pending);
        let pass = self.rotations.pass;
        let visit = |s: &mut Source, c: &mut ExtractCount| {
            if s.fresh {
                s.fresh = false;
            } else if s.users > 0 {
                extract_source(s, x, polar, rest_threshold, pass, c);
                s.fresh = false;
            }
        };
        if self.exec.threads > 1 {
            use rayon::prelude::*;
            let counts = self
                .rotations
                .sources
                .par_iter_mut()
                .with_min_len(64)
                .fold(ExtractCount::default, |mut c, s| {
                    visit(s, &mut c);
                    c
                })
                .reduce(ExtractCount::default, ExtractCount::merge);
            c = c.merge(counts);
        } else if let PolarMethod::ByersXu(bx) = polar {
            extract_batched(
                &mut self.rotations.sources,
                x,
                bx,
                rest_threshold,
                pass,
                &mut c,
            );
        } else {
            for s in &mut self.rotations.sources {
                visit(s, &mut c);
            }
        }
        self.rotations.pass += 1;
        self.rotations.last_pass = c;
        (c.extracted, c.reused, c.iterations, c.inverted)
    }
}

/// The single-thread pass of [`FemSystem::update_rotations`] with Byers–Xu: the sources
/// to extract go four at a time through [`ByersXu::extract4`], which gives each the bits
/// [`extract_source`] would (so the rotations do not depend on the batching).
fn extract_batched(
    sources: &mut [Source],
    x: &[V3],
    bx: &ByersXu,
    rest_threshold: f64,
    pass: u64,
    c: &mut ExtractCount,
) {
    let mut batch: Vec<(usize, Matrix3<f64>, [V3; 4])> = Vec::with_capacity(4);
    let flush = |batch: &mut Vec<(usize, Matrix3<f64>, [V3; 4])>,
                 sources: &mut [Source],
                 c: &mut ExtractCount| {
        if batch.len() == 4 {
            let f = std::array::from_fn(|l| batch[l].1);
            let warm = std::array::from_fn(|l| sources[batch[l].0].warm());
            let out = bx.extract4(&f, &warm);
            for ((i, _, xs), r) in batch.drain(..).zip(out) {
                record(&mut sources[i], r, xs, pass, c);
            }
        } else {
            for (i, f, xs) in batch.drain(..) {
                let r = bx.extract(&f, Some(&sources[i].warm()));
                record(&mut sources[i], r, xs, pass, c);
            }
        }
    };
    for i in 0..sources.len() {
        let s = &mut sources[i];
        if s.fresh {
            s.fresh = false;
            continue;
        }
        if s.users == 0 {
            continue;
        }
        let prepared = prepare_source(s, x, rest_threshold, c);
        s.fresh = false;
        if let Some((f, xs)) = prepared {
            batch.push((i, f, xs));
            if batch.len() == 4 {
                flush(&mut batch, sources, c);
            }
        }
    }
    flush(&mut batch, sources, c);
}

impl Source {
    /// The warm start of its next extraction: its last rotation and singular value
    /// bounds, if it has been extracted.
    fn warm(&self) -> WarmStart {
        WarmStart {
            rotation: self.valid.then_some(self.rotation),
            sigma_bounds: if self.valid { self.sigma } else { None },
        }
    }
}

/// Marks the source fresh; at rest (every node within `rest_threshold` of where it was
/// extracted) counts a reuse and returns `None`, else its gradient `F` at `x` and its
/// nodes' positions.
fn prepare_source(
    s: &mut Source,
    x: &[V3],
    rest_threshold: f64,
    c: &mut ExtractCount,
) -> Option<(Matrix3<f64>, [V3; 4])> {
    let xs = gather(x, &s.nodes);
    s.fresh = true;
    let thr2 = rest_threshold * rest_threshold;
    if s.valid
        && rest_threshold > 0.0
        && xs
            .iter()
            .zip(&s.x_last)
            .all(|(a, b)| (a - b).norm_squared() < thr2)
    {
        c.reused += 1;
        return None;
    }
    Some((edge_matrix(&xs) * s.dm_inv, xs))
}

/// Extract (or, at rest, reuse) one source's rotation at `x` and mark it fresh.
pub(super) fn extract_source(
    s: &mut Source,
    x: &[V3],
    polar: &PolarMethod,
    rest_threshold: f64,
    pass: u64,
    c: &mut ExtractCount,
) {
    let Some((f, xs)) = prepare_source(s, x, rest_threshold, c) else {
        return;
    };
    let r = polar.extract(&f, Some(&s.warm()));
    record(s, r, xs, pass, c);
}

/// Stores an extraction's result in its source and counts it.
fn record(s: &mut Source, r: PolarResult, xs: [V3; 4], pass: u64, c: &mut ExtractCount) {
    // Rotation change per step; a source not extracted in the previous pass (e.g. one
    // that was shared) has no meaningful previous rotation.
    if s.valid && s.pass + 1 >= pass {
        c.max_change_sq = c
            .max_change_sq
            .max((r.rotation - s.rotation).norm_squared());
    }
    s.pass = pass;
    s.rotation = r.rotation;
    s.sigma = Some(r.sigma_bounds);
    s.x_last = xs;
    s.valid = true;
    c.extracted += 1;
    c.iterations += r.iterations as usize;
    c.inverted += r.inverted as usize;
}
