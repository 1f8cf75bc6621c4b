//! What steps keep for the next one: per-element dense stiffness, the CG warm start, the
//! block pattern of the assembled operator, the assembly order and its block storage.

use nalgebra::Matrix3;

use super::{FemSystem, V3};
use crate::element::Mat12;
use crate::parallel::Partition;
use crate::solver::BlockPattern;
use crate::system::StiffnessMode;

/// What a [`FemSystem`] keeps between steps. Only the warm start (when
/// [`crate::SolverParams::warm_start`] is on) changes results; the rest changes their cost.
#[derive(Clone, Debug, Default)]
pub(super) struct Caches {
    /// Per-element dense `K_e` ([`StiffnessMode::Dense`]), built on first use.
    pub(super) dense: Option<Vec<Mat12>>,
    /// Δv of the previous linearised step (CG warm start).
    pub(super) warm_dv: Vec<V3>,
    /// Block pattern of the assembled operator, built on first use.
    pub(super) pattern: Option<BlockPattern>,
    /// Element indices grouped by their current rotation source (assembly order), and
    /// whether the assignment changed since it was built.
    pub(super) by_source: Vec<u32>,
    /// Every element, by template-material combination (stable: element order within
    /// one); the order [`FemSystem::group_by_source`] sorts from.
    pub(super) by_combo: Vec<u32>,
    pub(super) by_source_stale: bool,
    /// Block storage of the assembled operator, kept between steps to avoid reallocating.
    pub(super) block_buf: Vec<Matrix3<f64>>,
    /// The same by full rows for the one-thread product, kept likewise (a new 1.7 MB
    /// buffer per step at 5,184 tets cost as much in page faults as the copy itself).
    pub(super) full_buf: Vec<crate::solver::RowBlock>,
    /// The same by contiguous upper rows, for the product beyond the cache, kept likewise.
    pub(super) upper_rows_buf: crate::solver::UpperRows,
    /// Per-element rotated blocks of earlier assemblies (`element_blocks.rs`), kept while
    /// most rotations stay as they were.
    pub(super) element_blocks: Vec<super::element_blocks::CachedBlocks>,
    /// Per rotation source, its elements' stiffness in the rest frame for the one-thread
    /// co-rotational forces (`source_stiffness.rs`), where the source is large enough.
    pub(super) source_stiffness: Vec<Option<super::source_stiffness::SourceStiffness>>,
    /// Per rotation source not summed, the elements it held at the last refresh.
    pub(super) source_seen: Vec<Vec<u32>>,
    /// Elements in summed sources at the last refresh.
    pub(super) source_summed: usize,
    /// Multigrid hierarchy given by the caller, and the preconditioner built on it.
    pub(super) mg_hierarchy: Option<crate::mg::Hierarchy>,
    pub(super) mg: Option<super::multigrid::MgCache>,
    /// [`crate::LinearSolver::Auto`]'s choice: `None` before its first solve, then
    /// whether it chose MG-PCG.
    pub(super) auto_multigrid: Option<bool>,
    /// Symbolic factorisation of [`crate::LinearSolver::Direct`], for the current pattern
    /// and Dirichlet mask.
    pub(super) direct: Option<crate::direct::DirectSolver>,
}

impl FemSystem {
    /// Builds the per-element dense stiffness matrices of [`StiffnessMode::Dense`] once.
    pub(super) fn ensure_dense(&mut self) {
        if self.caches.dense.is_none() {
            let d = (0..self.mesh.elements.len())
                .map(|ei| self.k0_matrix(ei, StiffnessMode::Gradient))
                .collect();
            self.caches.dense = Some(d);
        }
    }

    /// Brings the block pattern, the assembly order and (on multi-threaded steps) the
    /// partition up to date.
    pub(super) fn refresh_order(&mut self) {
        if self.caches.pattern.is_none() {
            let conn: Vec<[usize; 4]> = self.mesh.elements.iter().map(|e| e.nodes).collect();
            self.caches.pattern = Some(BlockPattern::new(self.mesh.rest.len(), &conn));
        }
        if self.caches.by_source_stale {
            self.group_by_source();
        }
    }

    /// Counting sort of the elements by their current rotation source (O(elements +
    /// sources)), the order in which assembly visits them; on multi-threaded steps also
    /// the partition (its element lists follow that order). Within a source the elements
    /// come by template-material combination, so that assembly's per-source cache of
    /// `R C Rᵀ` (`SysOp::add_rotated`) computes each combination once per source.
    ///
    /// Why: in element order a shared source's elements cycle through all the lattice's
    /// combinations (48 on the cantilever beams: more than the cache holds), and the
    /// cache missed on nearly every element: 4,988 block rotations per step for 5,184
    /// tets at dt 1 ms with sharing (`examples/step_cost.rs`, 2026-11-28), 3,843 in this
    /// order. It pays where sources are large: the stiff 12,288-tet beam at dt 10 ms
    /// (four shared rotations per step) went from 5.29 to 5.01 ms per MG-PCG step, the
    /// soft one from 5.51 to 5.26 ms (medians of five interleaved runs).
    pub(super) fn group_by_source(&mut self) {
        if self.caches.by_combo.len() != self.mesh.elements.len() {
            self.caches.by_combo = (0..self.mesh.elements.len() as u32).collect();
            let elements = &self.mesh.elements;
            self.caches
                .by_combo
                .sort_by_key(|&ei| elements[ei as usize].combo);
        }
        let mut start = vec![0u32; self.rotations.sources.len() + 1];
        for e in &self.mesh.elements {
            start[e.source + 1] += 1;
        }
        for s in 0..self.rotations.sources.len() {
            start[s + 1] += start[s];
        }
        self.caches.by_source.clear();
        self.caches.by_source.resize(self.mesh.elements.len(), 0);
        for &ei in &self.caches.by_combo {
            let slot = &mut start[self.mesh.elements[ei as usize].source];
            self.caches.by_source[*slot as usize] = ei;
            *slot += 1;
        }
        self.caches.by_source_stale = false;
        // A partition's element lists follow this order: rebuild it, or drop it when the
        // step is single-threaded (the next multi-threaded step rebuilds it).
        self.exec.partition = None;
        if self.exec.threads > 1
            && let Some(pat) = &self.caches.pattern
        {
            let elements = &self.mesh.elements;
            let part = Partition::new(
                self.exec.threads,
                &pat.upper_row_work(),
                &self.caches.by_source,
                |e| elements[e].nodes,
            );
            self.exec.partition = Some(part);
        }
    }
}

impl Caches {
    /// Keeps an operator's storage for the next one.
    pub(super) fn recycle(&mut self, buffers: super::operator::OperatorBuffers) {
        self.block_buf = buffers.blocks;
        self.full_buf = buffers.full;
        self.upper_rows_buf = buffers.upper_rows;
        // An operator that did not use the per-element cache left it here.
        if !buffers.element_blocks.is_empty() {
            self.element_blocks = buffers.element_blocks;
        }
    }
}
