//! A shared rotation source's elements as one: their co-rotational forces and their
//! assembled blocks.
//!
//! All elements of a source turn with one rotation `R`, so their forces are
//! `f = −R K_s (Rᵀ(x − x_0) − (X − X_0))` and their blocks of the step matrix `c R K_s Rᵀ`,
//! with `K_s = Σ_e K_e` the source's stiffness in the rest frame, summed once over the
//! source's nodes (`x_0`, `X_0`: its first node; `K_s` annihilates translations, as each
//! `K_e` does, so the forces are the sum of the per-element ones; `c` the elements'
//! common coefficient, `dt β + dt²`). A step then rotates each node twice and each node
//! pair's block once, instead of every element's: a block of 8 lattice cubes holds 48 tets
//! but 27 nodes and 98 node pairs, against 48 × 10 element blocks to rotate and scatter.
//!
//! Why: on the 5,184-tet beam at dt 1 ms (the 1 kHz row of `cosurg bench cantilever`,
//! about 50 elements per shared source) the per-element forces were about a sixth of a
//! step and the element blocks with their scatter a fifth (`perf`, 2026-11-28). With
//! both summed per source (`step_cost 1e5 0.016666667 0.001 300 1 1 50`, three
//! interleaved runs) the step went from 1.11–1.12 to 0.83–0.84 ms, and the tip ended
//! within 3e-15 m of where it did. `K_s` is kept while the source holds the same elements
//! (sharing reassigns sources rarely once a motion settles); it sums the same element
//! matrices the per-element loops apply, so forces and blocks differ from theirs by
//! rounding only (tests `source_forces_match_the_per_element_loop`,
//! `source_assembly_matches_the_per_element_assembly`). The loops by source run on one
//! thread; a step on several threads uses them too when most elements are in summed
//! sources ([`FemSystem::sums_most_sources`]), and splits only its products and sweeps
//! (its element loops split by node ranges were slower: 0.968 against 0.891 ms on two
//! threads for the 5,184-tet beam at dt 1 ms).

use std::collections::HashMap;

use nalgebra::Matrix3;

use super::{FemSystem, StiffnessMode, V3};

/// Sources with fewer elements keep the per-element loop (a lone cube's six tets share
/// most of their nodes with no other element of the source, and gain little).
pub(super) const MIN_ELEMENTS: usize = 12;

/// Blocks ahead whose operator slot [`SourceStiffness::add_blocks`] prefetches.
const SCATTER_AHEAD_BLOCKS: usize = 8;

/// One source's stiffness in its rest frame.
#[derive(Clone, Debug)]
pub(super) struct SourceStiffness {
    /// The stiffness mode the element matrices came from.
    mode: StiffnessMode,
    /// The elements summed, in [`super::caches::Caches::by_source`] order.
    elements: Vec<u32>,
    /// Global index of each local node; local 0 is the reference node.
    nodes: Vec<u32>,
    /// `X_a − X_0` per local node (m).
    rest: Vec<V3>,
    /// `Σ_e K_e[a, a]` per local node (N/m).
    diag: Vec<Matrix3<f64>>,
    /// Local node pairs `(a, b)`, `a < b`, and `Σ_e K_e[a, b]` of each (N/m).
    pairs: Vec<[u32; 2]>,
    off: Vec<Matrix3<f64>>,
    /// The assembled operator's upper-storage slot of each local node's diagonal block,
    /// and of each pair's block (transposed: the pair's global nodes are in decreasing
    /// order, and the storage keeps block `(b, a)`).
    diag_slots: Vec<u32>,
    pair_slots: Vec<(u32, bool)>,
    /// Whether the elements share one stiffness damping `β` (bit for bit), hence one
    /// assembly coefficient `dt β + dt²`: then the source assembles as one. Their
    /// materials may differ otherwise: `K_s` sums each element's own matrix, so a source
    /// that mixes fill-weighted boundary tets (E and ρ scaled, `β` kept) with whole ones
    /// assembles as one too. (Until 2026-11-29 one material was required, and the
    /// fill-weighted organ assembled most of its surface element by element: the 1.33 cm
    /// organ's step went from 23.3 to 21.9 M instructions, docs/RESULTS.md.)
    one_coefficient: bool,
}

impl SourceStiffness {
    /// `K_s` of `elements` (all of one source).
    fn build(sys: &FemSystem, elements: &[u32], mode: StiffnessMode) -> Self {
        let mut index = LocalIndex::default();
        let locals: Vec<[u32; 4]> = elements
            .iter()
            .map(|&ei| {
                sys.mesh.elements[ei as usize]
                    .nodes
                    .map(|n| index.of(n as u32))
            })
            .collect();
        let nodes = index.nodes;
        let x0 = sys.mesh.rest[nodes[0] as usize];
        let rest = nodes
            .iter()
            .map(|&n| sys.mesh.rest[n as usize] - x0)
            .collect();
        let mut diag = vec![Matrix3::zeros(); nodes.len()];
        let mut diag_slots = vec![0u32; nodes.len()];
        // Per local node `a`, its pairs `(a, b)`, `a < b`, as `(b, pair index)`.
        let mut pairs_of: Vec<Vec<(u32, u32)>> = vec![Vec::new(); nodes.len()];
        let (mut pairs, mut off, mut pair_slots) = (Vec::new(), Vec::new(), Vec::new());
        let pattern = sys.caches.pattern.as_ref().expect("pattern built");
        let beta = |ei: u32| sys.mesh.materials[sys.mesh.elements[ei as usize].material].beta;
        let beta0 = beta(elements[0]).to_bits();
        let mut one_coefficient = true;
        for (&ei, l) in elements.iter().zip(&locals) {
            let e = &sys.mesh.elements[ei as usize];
            one_coefficient &= beta(ei).to_bits() == beta0;
            let k = sys.k0_matrix(ei as usize, mode);
            let slots = pattern.element_slots(ei as usize);
            for a in 0..4 {
                diag[l[a] as usize] += k.fixed_view::<3, 3>(3 * a, 3 * a);
                diag_slots[l[a] as usize] = slots[4 * a + a];
                for b in 0..4 {
                    // The element matrix is symmetric: the pair (a, b) with the lower
                    // local index first, its mirror read transposed.
                    if l[a] >= l[b] {
                        continue;
                    }
                    let list = &mut pairs_of[l[a] as usize];
                    let p = match list.iter().find(|(other, _)| *other == l[b]) {
                        Some(&(_, p)) => p as usize,
                        None => {
                            pairs.push([l[a], l[b]]);
                            off.push(Matrix3::zeros());
                            pair_slots.push(if e.nodes[a] <= e.nodes[b] {
                                (slots[4 * a + b], false)
                            } else {
                                (slots[4 * b + a], true)
                            });
                            list.push((l[b], (pairs.len() - 1) as u32));
                            pairs.len() - 1
                        }
                    };
                    off[p] += k.fixed_view::<3, 3>(3 * a, 3 * b);
                }
            }
        }
        Self {
            mode,
            elements: elements.to_vec(),
            nodes,
            rest,
            diag,
            pairs,
            off,
            diag_slots,
            pair_slots,
            one_coefficient,
        }
    }

    /// Whether this is `K_s` of `elements` in `mode`.
    fn is_for(&self, elements: &[u32], mode: StiffnessMode) -> bool {
        self.mode == mode && self.elements == elements
    }

    /// Adds the source's elastic forces at `x` with rotation `r` into `out` (N) and
    /// returns its elastic energy (J). `u`, `y`: scratch of at least the source's node
    /// count.
    fn add_forces(
        &self,
        x: &[V3],
        r: &Matrix3<f64>,
        out: &mut [V3],
        u: &mut Vec<V3>,
        y: &mut Vec<V3>,
    ) -> f64 {
        let rt = r.transpose();
        let x0 = x[self.nodes[0] as usize];
        u.clear();
        u.extend(
            self.nodes
                .iter()
                .zip(&self.rest)
                .map(|(&n, xr)| rt * (x[n as usize] - x0) - xr),
        );
        y.clear();
        y.extend(self.diag.iter().zip(u.iter()).map(|(d, ua)| d * ua));
        for (&[a, b], k) in self.pairs.iter().zip(&self.off) {
            let (a, b) = (a as usize, b as usize);
            y[a] += k * u[b];
            y[b] += k.tr_mul(&u[a]);
        }
        let mut energy = 0.0;
        for ((&n, ua), ya) in self.nodes.iter().zip(u.iter()).zip(y.iter()) {
            energy += 0.5 * ua.dot(ya);
            out[n as usize] -= r * ya;
        }
        energy
    }
}

/// Local indices of a source's nodes, in order of first appearance.
#[derive(Default)]
struct LocalIndex {
    nodes: Vec<u32>,
    /// Global → local, once the source has more than [`LocalIndex::LINEAR`] nodes.
    map: Option<HashMap<u32, u32>>,
}

impl LocalIndex {
    /// Most sources span a few dozen nodes, where a linear search beats hashing (a
    /// source is rebuilt whenever sharing reassigns it); a source of the whole stiff beam
    /// spans thousands.
    const LINEAR: usize = 64;

    fn of(&mut self, n: u32) -> u32 {
        if let Some(map) = &mut self.map {
            let next = self.nodes.len() as u32;
            let i = *map.entry(n).or_insert(next);
            if i == next {
                self.nodes.push(n);
            }
            return i;
        }
        if let Some(i) = self.nodes.iter().position(|&m| m == n) {
            return i as u32;
        }
        self.nodes.push(n);
        if self.nodes.len() > Self::LINEAR {
            let map = self
                .nodes
                .iter()
                .enumerate()
                .map(|(i, &m)| (m, i as u32))
                .collect();
            self.map = Some(map);
        }
        (self.nodes.len() - 1) as u32
    }
}

impl SourceStiffness {
    /// Whether its elements assemble as one: they share one assembly coefficient.
    pub(super) fn assembles_as_one(&self) -> bool {
        self.one_coefficient
    }

    /// `blocks += c R K_s Rᵀ` into the assembled operator's upper storage (`c`: the
    /// elements' common assembly coefficient, s²). Diagonal blocks are made exactly
    /// symmetric, as the products that read them whole need.
    pub(super) fn add_blocks(&self, r: &Matrix3<f64>, c: f64, blocks: &mut [Matrix3<f64>]) {
        let rt = r.transpose() * c;
        let prefetch = crate::prefetch::outgrows_cache(blocks);
        for (d, &slot) in self.diag.iter().zip(&self.diag_slots) {
            let b = r * d * rt;
            blocks[slot as usize] += (b + b.transpose()) * 0.5;
        }
        for (i, (k, &(slot, transposed))) in self.off.iter().zip(&self.pair_slots).enumerate() {
            // The blocks a few ahead are scattered over the whole operator.
            if prefetch && let Some(&(ahead, _)) = self.pair_slots.get(i + SCATTER_AHEAD_BLOCKS) {
                crate::prefetch::prefetch(blocks, ahead as usize);
            }
            let b = r * k * rt;
            blocks[slot as usize] += if transposed { b.transpose() } else { b };
        }
    }
}

impl FemSystem {
    /// The assembly order's runs of elements with one source, as `(source, elements)`.
    pub(super) fn source_runs(&self) -> impl Iterator<Item = (usize, &[u32])> + '_ {
        let elements = &self.mesh.elements;
        self.caches
            .by_source
            .chunk_by(|&a, &b| elements[a as usize].source == elements[b as usize].source)
            .map(|run| (elements[run[0] as usize].source, run))
    }

    /// The kept stiffness of source `s` if it is for exactly `elements` in `mode`.
    pub(super) fn source_stiffness_for(
        &self,
        s: usize,
        elements: &[u32],
        mode: StiffnessMode,
    ) -> Option<&SourceStiffness> {
        self.caches
            .source_stiffness
            .get(s)
            .and_then(Option::as_ref)
            .filter(|k| k.is_for(elements, mode))
    }

    /// Brings the per-source stiffness up to date with the current assignment
    /// (co-rotational steps): built for each source of at least [`MIN_ELEMENTS`]
    /// elements that holds the same elements as at the previous refresh, dropped for the
    /// others.
    ///
    /// Why not at once: while a motion starts, sharing reassigns many sources from one
    /// step to the next, and a sum built for one step only costs more than it saves
    /// (the 98,304-tet beam's first 20 steps were slower with every new assignment
    /// summed at once).
    pub(super) fn refresh_source_stiffness(&mut self, mode: StiffnessMode) {
        self.refresh_order();
        let mut kept = std::mem::take(&mut self.caches.source_stiffness);
        kept.resize(self.rotations.sources.len(), None);
        kept.truncate(self.rotations.sources.len());
        let mut seen = std::mem::take(&mut self.caches.source_seen);
        seen.resize(self.rotations.sources.len(), Vec::new());
        seen.truncate(self.rotations.sources.len());
        let mut summed = 0;
        for (s, elements) in self.source_runs() {
            let (slot, seen) = (&mut kept[s], &mut seen[s]);
            if elements.len() < MIN_ELEMENTS {
                *slot = None;
                seen.clear();
            } else if slot.as_ref().is_some_and(|k| k.is_for(elements, mode)) {
                summed += elements.len();
            } else if seen.as_slice() == elements {
                // The same elements two refreshes running: worth summing.
                *slot = Some(SourceStiffness::build(self, elements, mode));
                seen.clear();
                summed += elements.len();
            } else {
                *slot = None;
                seen.clear();
                seen.extend_from_slice(elements);
            }
        }
        self.caches.source_stiffness = kept;
        self.caches.source_seen = seen;
        self.caches.source_summed = summed;
    }

    /// Whether most elements are in summed sources, so that a step on several threads
    /// is faster with its element loops on one, source by source, than split by node
    /// ranges element by element (its products and sweeps stay split).
    pub(super) fn sums_most_sources(&self) -> bool {
        !self.caches.by_source_stale && 2 * self.caches.source_summed >= self.mesh.elements.len()
    }

    /// Co-rotational energy (J) and forces added into `out` (N) source by source
    /// ([`SourceStiffness`]) where one is kept for the source's current elements and
    /// mode, element by element otherwise; `None` when the assembly order is stale (the
    /// caller's per-element loop then runs).
    pub(super) fn elastic_by_source(
        &self,
        x: &[V3],
        mode: StiffnessMode,
        rotations: Option<&[Matrix3<f64>]>,
        out: &mut [V3],
    ) -> Option<f64> {
        if self.caches.by_source_stale
            || self.caches.source_stiffness.is_empty()
            || self.caches.by_source.len() != self.mesh.elements.len()
        {
            return None;
        }
        let (mut u, mut y) = (Vec::new(), Vec::new());
        let mut energy = 0.0;
        for (s, elements) in self.source_runs() {
            match self.source_stiffness_for(s, elements, mode) {
                Some(k) => {
                    let r = self.element_rotation_of(elements[0] as usize, rotations);
                    energy += k.add_forces(x, &r, out, &mut u, &mut y);
                }
                _ => {
                    for &ei in elements {
                        let (e, fe) = self.element_force(
                            ei as usize,
                            x,
                            crate::Model::Corotational,
                            mode,
                            rotations,
                        );
                        for (&n, f) in self.mesh.elements[ei as usize].nodes.iter().zip(&fe) {
                            out[n] += f;
                        }
                        energy += e;
                    }
                }
            }
        }
        Some(energy)
    }
}

#[cfg(test)]
mod tests {
    use super::LocalIndex;

    /// Local indices in order of first appearance, before and after the switch from
    /// linear search to hashing.
    #[test]
    fn local_indices_follow_first_appearance_across_the_switch_to_hashing() {
        let mut index = LocalIndex::default();
        let mut want: Vec<u32> = Vec::new();
        for k in 0..1000u32 {
            let n = (k * 7919) % 150;
            let i = index.of(n);
            let expect = match want.iter().position(|&m| m == n) {
                Some(i) => i,
                None => {
                    want.push(n);
                    want.len() - 1
                }
            };
            assert_eq!(i as usize, expect, "node {n}");
        }
        assert_eq!(index.nodes, want);
        assert!(index.map.is_some());
    }
}
