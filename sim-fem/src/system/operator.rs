//! The system matrix as CG sees it, `A = diag(mass_coef) + Σ_e (element matrix) +
//! ext_coef K_c`: element-by-element products (matrix-free) or the assembled 3×3-block CSR
//! (built in the assembly order of `caches.rs`, which keeps rotation sharing cheap).

use std::sync::{Mutex, OnceLock};

use nalgebra::Matrix3;

use super::element_blocks::{
    CachedBlocks, UpperBlocks, cache_pays, rotated_blocks, rotated_iso_blocks, scatter_blocks,
};
use super::{FemSystem, V3, gather};
use crate::element::{Mat12, apply_dense};
use crate::parallel::{multiply_full_parts, split_ranges};
use crate::solver::{LinearOperator, RowBlock, UpperRows};
use crate::system::{OperatorMode, StiffnessMode};

/// Element matrices entering a linear operator.
pub(super) enum ElemMats {
    /// `coef_e · R_e K_e R_eᵀ` (R = I if `rotated` is false).
    Rotated { coef: Vec<f64>, rotated: bool },
    /// Explicit per-element 12×12 matrices.
    Dense(Vec<Mat12>),
}

impl FemSystem {
    /// The operator of one linear solve; assembled now when `operator` says so (reusing the
    /// block storage of the previous solve, to be handed back with
    /// [`SysOp::into_buffers`]).
    pub(super) fn build_operator<'a>(
        &'a mut self,
        mass_coef: Vec<f64>,
        elem: ElemMats,
        ext_coef: f64,
        mode: StiffnessMode,
        operator: OperatorMode,
    ) -> SysOp<'a> {
        if operator == OperatorMode::Assembled || self.exec.threads > 1 {
            self.refresh_order();
        }
        let buf = std::mem::take(&mut self.caches.block_buf);
        let full_spare = Mutex::new(std::mem::take(&mut self.caches.full_buf));
        let upper_spare = Mutex::new(std::mem::take(&mut self.caches.upper_rows_buf));
        let elements = self.mesh.elements.len();
        // Only a one-thread assembly of rotated blocks reads the cache.
        let reads_cache = operator == OperatorMode::Assembled
            && self.active_partition().is_none()
            && mode != StiffnessMode::Dense
            && matches!(elem, ElemMats::Rotated { rotated: true, .. });
        // Elements whose source the last rotation pass extracted (sources carry the
        // number of the pass that extracted them; `pass` counts on after it).
        let changed = || {
            let last = self.rotations.pass.wrapping_sub(1);
            let sources = &self.rotations.sources;
            (self.mesh.elements.iter())
                .filter(|e| sources[e.source].pass == last)
                .count()
        };
        let element_blocks = if reads_cache && cache_pays(changed(), elements) {
            let mut c = std::mem::take(&mut self.caches.element_blocks);
            c.resize_with(elements, CachedBlocks::default);
            c
        } else {
            // Kept (its entries say what they were computed from) for later steps.
            Vec::new()
        };
        let this: &'a FemSystem = self;
        let mut op = SysOp {
            sys: this,
            mass_coef,
            elem,
            ext_coef,
            mode,
            assembled: None,
            full: OnceLock::new(),
            full_spare,
            upper_rows: OnceLock::new(),
            upper_spare,
            element_blocks,
        };
        if operator == OperatorMode::Assembled {
            op.assemble(buf);
        }
        op
    }
}

/// Templates `R C Rᵀ` kept per rotation group by [`SysOp::add_rotated`].
const TEMPLATE_CACHE: usize = 8;

/// [`SysOp::add_rotated`]'s working storage, made once per assembly (per part on several
/// threads) and passed to each of its calls: a step of the soft 12,288-tet beam makes
/// hundreds of calls, one per run of elements by rotation source, and zeroing these 6 KB
/// in each was 2 % of the step (`perf`, 2026-11-28).
pub(super) struct RotatedScratch {
    /// Per group (rotation source, or all when unrotated): the combos seen and
    /// `R C Rᵀ` of each (C = template stiffness at unit size: the element's own blocks
    /// over its size h). Few per group. A group's entries stay valid in a later call:
    /// they depend only on the group's rotation and the combo.
    combo: [usize; TEMPLATE_CACHE],
    blocks: [UpperBlocks; TEMPLATE_CACHE],
    /// Per entry, the element whose per-element cache holds its blocks (`None`: `blocks`
    /// does): read there, not copied into `blocks` (see `element_iso_blocks`). An
    /// element's cached blocks do not change during an assembly, since each element is
    /// assembled once, with its source's rotation; every call that shares a scratch
    /// passes the same per-element cache (or none).
    kept_at: [Option<u32>; TEMPLATE_CACHE],
    cached: usize,
    group: usize,
    /// One element's blocks.
    local: UpperBlocks,
}

impl Default for RotatedScratch {
    fn default() -> Self {
        Self {
            combo: [usize::MAX; TEMPLATE_CACHE],
            blocks: [[Matrix3::zeros(); 10]; TEMPLATE_CACHE],
            kept_at: [None; TEMPLATE_CACHE],
            cached: 0,
            group: usize::MAX,
            local: [Matrix3::zeros(); 10],
        }
    }
}

/// The storage an operator hands back for the next one ([`SysOp::into_buffers`]).
pub(super) struct OperatorBuffers {
    pub(super) blocks: Vec<Matrix3<f64>>,
    pub(super) full: Vec<RowBlock>,
    pub(super) upper_rows: UpperRows,
    pub(super) element_blocks: Vec<CachedBlocks>,
}

/// The operator `A p = diag(mass_coef) p + Σ_e (element matrix) p_e + ext_coef K_c p`.
pub(super) struct SysOp<'a> {
    pub(super) sys: &'a FemSystem,
    mass_coef: Vec<f64>,
    elem: ElemMats,
    ext_coef: f64,
    mode: StiffnessMode,
    pub(super) assembled: Option<Vec<Matrix3<f64>>>,
    /// The assembled blocks by full rows for the product, on one thread or split by rows
    /// ([`crate::solver::BlockPattern::full_rows_into`]), made at the first product in the
    /// storage of `full_spare` (the previous step's). `assembled` must not change after
    /// that product (only [`SysOp::assemble`], in `build_operator`, writes it).
    pub(super) full: OnceLock<Vec<RowBlock>>,
    full_spare: Mutex<Vec<RowBlock>>,
    /// The assembled blocks by contiguous upper rows, for the product of a matrix that
    /// outgrows the cache (on one thread or split), made at its first product in the storage of
    /// `upper_spare` (as `full`).
    pub(super) upper_rows: OnceLock<UpperRows>,
    upper_spare: Mutex<UpperRows>,
    /// Per-element rotated blocks kept from earlier assemblies (one per element, or empty:
    /// not used this step; see `element_blocks.rs`).
    element_blocks: Vec<CachedBlocks>,
}

/// Smallest mesh (nodes) whose sparse products are split over threads: on 2 cores the
/// coarse cantilever beam (425 nodes, about 4 µs per product) stepped 25 % slower with
/// a split product at dt = 10 ms (50 CG iterations), the 12,288-tet one (2,673 nodes)
/// 1.5× faster (`examples/step_cost.rs`).
const PARALLEL_PRODUCT_MIN_NODES: usize = 1000;

impl SysOp<'_> {
    /// `out = A p` for a product made once, such as the step's right-hand side: where
    /// [`LinearOperator::apply`] would copy the blocks into full rows for a product on one
    /// thread, the symmetric upper product instead (a direct solve makes no other). Split
    /// over threads, or beyond the cache, the copy that CG's products read (full or upper
    /// rows) is made, and reused by them.
    pub(super) fn apply_once(&self, p: &[V3], out: &mut [V3]) {
        if let (Some(blocks), ElemMats::Rotated { .. }) = (&self.assembled, &self.elem)
            && self.product_partition(out.len()).is_none()
        {
            if crate::prefetch::outgrows_cache(blocks) {
                self.multiply_upper_rows(blocks, p, out, None);
            } else {
                let pat = self.sys.caches.pattern.as_ref().expect("pattern");
                pat.multiply_upper(blocks, p, out);
            }
            return;
        }
        self.apply(p, out);
    }

    /// `out = A p` from the assembled blocks copied into contiguous upper rows, for a
    /// matrix that outgrows the cache, on one thread or split by `part`'s rows
    /// (`solver/upper_product.rs`: half the bytes of the full rows per product, and a
    /// cheaper copy).
    fn multiply_upper_rows(
        &self,
        blocks: &[Matrix3<f64>],
        p: &[V3],
        out: &mut [V3],
        part: Option<&crate::parallel::Partition>,
    ) {
        let pat = self.sys.caches.pattern.as_ref().expect("pattern");
        let rows = self.upper_rows.get_or_init(|| {
            let mut rows =
                std::mem::take(&mut *self.upper_spare.lock().unwrap_or_else(|e| e.into_inner()));
            rows.copy_from(pat, blocks);
            rows
        });
        match part {
            Some(part) => rows.multiply_parts(pat, p, out, &part.node_start),
            None => rows.multiply(pat, p, out),
        }
    }

    /// The partition an assembled product of `n` nodes is split over, if any: below
    /// [`PARALLEL_PRODUCT_MIN_NODES`] a product is a few µs of work, less than forking and
    /// joining costs, and one thread does it.
    fn product_partition(&self, n: usize) -> Option<&crate::parallel::Partition> {
        self.sys
            .active_partition()
            .filter(|_| n >= PARALLEL_PRODUCT_MIN_NODES)
    }

    /// Hands back the assembled block storage and its full-row or upper-row copy (for
    /// reuse by the next step: [`super::caches::Caches::recycle`]).
    pub(super) fn into_buffers(self) -> OperatorBuffers {
        OperatorBuffers {
            blocks: self.assembled.unwrap_or_default(),
            full: match self.full.into_inner() {
                Some(full) => full,
                None => self.full_spare.into_inner().unwrap_or_default(),
            },
            upper_rows: match self.upper_rows.into_inner() {
                Some(rows) => rows,
                None => self.upper_spare.into_inner().unwrap_or_default(),
            },
            element_blocks: self.element_blocks,
        }
    }

    /// Adds `coef_e · R_e K_e R_eᵀ` (upper blocks) of `elements` (grouped by rotation
    /// source) into `blocks`, which holds the pattern's blocks from index `offset` on.
    /// With template stiffness `R C Rᵀ` is formed once per (source, template-material
    /// combination) and shared by every element of the group, scaled by its size `h`: with
    /// rotation sharing most elements then cost a scaled scatter only (the point of
    /// combining sharing with templates). Every call of one assembly that shares
    /// `scratch` must pass the same `kept` (its entries may point into it).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn add_rotated(
        &self,
        elements: &[u32],
        blocks: &mut [Matrix3<f64>],
        offset: usize,
        coef: &[f64],
        rotated: bool,
        mut kept: Option<&mut [CachedBlocks]>,
        scratch: &mut RotatedScratch,
    ) {
        let sys = self.sys;
        let pat = sys.caches.pattern.as_ref().expect("pattern built");
        let templated = matches!(
            self.mode,
            StiffnessMode::Template | StiffnessMode::TemplateSparse
        );
        let RotatedScratch {
            combo: cache_combo,
            blocks: cache,
            kept_at,
            cached,
            group,
            local,
        } = scratch;
        let mut slots = [0u32; 16];
        for &element in elements {
            let ei = element as usize;
            let e = &sys.mesh.elements[ei];
            // One thread assembles the whole matrix (offset 0): the pattern's own slots.
            let slots = if offset == 0 {
                pat.element_slots(ei)
            } else {
                for (s, abs) in slots.iter_mut().zip(pat.element_slots(ei)) {
                    *s = abs - offset as u32;
                }
                &slots
            };
            // `R K Rᵀ` is symmetric: store the upper triangle only.
            let upper = pat.element_upper(ei);
            match (templated, e.template, self.mode) {
                (true, Some((_, h)), _) => {
                    // Unrotated: one group for all elements.
                    let key = if rotated { e.source } else { 0 };
                    if key != *group {
                        *cached = 0;
                        *group = key;
                    }
                    let hit = cache_combo[..*cached].iter().position(|c| *c == e.combo);
                    let i = match hit {
                        Some(i) => i,
                        None => {
                            // A full cache (rare) recycles its last entry.
                            let i = (*cached).min(TEMPLATE_CACHE - 1);
                            *cached = (*cached + 1).min(TEMPLATE_CACHE);
                            cache_combo[i] = e.combo;
                            // The blocks come from the element's own cache when it has
                            // one and is rotated (see `element_iso_blocks`).
                            kept_at[i] = (rotated && kept.is_some()).then_some(element);
                            element_iso_blocks(
                                sys,
                                rotated,
                                kept.as_deref_mut(),
                                ei,
                                e.volume / h,
                                &mut cache[i],
                            );
                            i
                        }
                    };
                    let entry = match kept_at[i] {
                        None => &cache[i],
                        Some(at) => kept
                            .as_deref()
                            .expect("an entry names an element's cache only when there is one")
                            [at as usize]
                            .blocks(),
                    };
                    scatter_blocks(blocks, slots, upper, entry, coef[ei] * h);
                }
                (_, _, StiffnessMode::Dense) => {
                    let k0 = sys.k0_matrix(ei, self.mode);
                    let r = rotated.then(|| &sys.rotations.sources[e.source].rotation);
                    let k = rotated_blocks(&k0, r);
                    scatter_blocks(blocks, slots, upper, &k, coef[ei]);
                }
                _ => {
                    let k =
                        element_iso_blocks(sys, rotated, kept.as_deref_mut(), ei, e.volume, local);
                    scatter_blocks(blocks, slots, upper, k, coef[ei]);
                }
            }
        }
    }

    /// Assembles `A` into `blocks` (reused storage): element blocks (on the parts of a
    /// multi-threaded step in parallel, then the interface), mass and external stiffness.
    pub(super) fn assemble(&mut self, mut blocks: Vec<Matrix3<f64>>) {
        let sys = self.sys;
        let pat = sys.caches.pattern.as_ref().expect("pattern built");
        blocks.clear();
        blocks.resize(pat.num_blocks(), Matrix3::zeros());
        match &self.elem {
            ElemMats::Dense(m) => {
                // Newton tangents (possibly unsymmetric): every block as given.
                for (ei, k) in m.iter().enumerate() {
                    let slots = pat.element_slots(ei);
                    for a in 0..4 {
                        for b in 0..4 {
                            blocks[slots[4 * a + b] as usize] += k.fixed_view::<3, 3>(3 * a, 3 * b);
                        }
                    }
                }
            }
            // Split over threads, unless most elements are in summed sources (their loop
            // is faster on one thread, `source_stiffness.rs`).
            ElemMats::Rotated { coef, rotated } => {
                match sys.active_partition().filter(|_| !sys.sums_most_sources()) {
                    Some(part) => {
                        use rayon::prelude::*;
                        // A part's elements only touch its nodes' rows: a contiguous block range.
                        let bounds: Vec<usize> = part
                            .node_start
                            .iter()
                            .map(|&s| pat.row_block_range(s, s).0)
                            .collect();
                        split_ranges(&mut blocks, &bounds)
                            .into_par_iter()
                            .zip(part.elements.par_iter())
                            .zip(bounds.par_iter())
                            .for_each(|((b, els), &offset)| {
                                let scratch = &mut RotatedScratch::default();
                                self.add_rotated(els, b, offset, coef, *rotated, None, scratch)
                            });
                        let scratch = &mut RotatedScratch::default();
                        let interface = &part.interface;
                        self.add_rotated(interface, &mut blocks, 0, coef, *rotated, None, scratch);
                    }
                    _ => {
                        // One thread: a source whose stiffness is kept (`source_stiffness.rs`) as
                        // one, the others through the per-element cache, if this step keeps
                        // one.
                        let mut kept = std::mem::take(&mut self.element_blocks);
                        let mut k = (!kept.is_empty()).then_some(kept.as_mut_slice());
                        let scratch = &mut RotatedScratch::default();
                        for (s, elements) in sys.source_runs() {
                            match sys.source_stiffness_for(s, elements, self.mode) {
                                Some(ks) if *rotated && ks.assembles_as_one() => {
                                    let r = &sys.rotations.sources[s].rotation;
                                    let c = coef[elements[0] as usize];
                                    // One β gives one coefficient only if the caller's
                                    // coefficients are `dt β + dt²` (`linearised.rs`).
                                    debug_assert!(
                                        elements.iter().all(|&e| coef[e as usize] == c),
                                        "a summed source's elements take one coefficient"
                                    );
                                    ks.add_blocks(r, c, &mut blocks);
                                }
                                _ => {
                                    let k = k.as_deref_mut();
                                    self.add_rotated(
                                        elements,
                                        &mut blocks,
                                        0,
                                        coef,
                                        *rotated,
                                        k,
                                        scratch,
                                    );
                                }
                            }
                        }
                        self.element_blocks = kept;
                    }
                }
            }
        }
        for (i, d) in pat.diagonal_slots().iter().enumerate() {
            blocks[*d] += Matrix3::identity() * self.mass_coef[i];
        }
        for (k, blk) in &self.sys.k_ext {
            blocks[pat.diagonal_slots()[*k]] += blk * self.ext_coef;
        }
        self.assembled = Some(blocks);
    }
}

impl LinearOperator for SysOp<'_> {
    fn apply(&self, p: &[V3], out: &mut [V3]) {
        if let Some(blocks) = &self.assembled {
            let pat = self.sys.caches.pattern.as_ref().expect("pattern");
            match (&self.elem, self.product_partition(out.len())) {
                (ElemMats::Rotated { .. }, part) if crate::prefetch::outgrows_cache(blocks) => {
                    self.multiply_upper_rows(blocks, p, out, part);
                }
                (ElemMats::Rotated { .. }, part) => {
                    let full = self.full.get_or_init(|| {
                        let mut full = std::mem::take(
                            &mut *self.full_spare.lock().unwrap_or_else(|e| e.into_inner()),
                        );
                        match part {
                            Some(part) => {
                                pat.full_rows_into_parts(blocks, &mut full, &part.node_start)
                            }
                            None => pat.full_rows_into(blocks, &mut full),
                        }
                        full
                    });
                    match part {
                        Some(part) => multiply_full_parts(pat, full, p, out, &part.node_start),
                        None => pat.multiply_full(full, p, out),
                    }
                }
                (ElemMats::Dense(_), _) => pat.multiply(blocks, p, out),
            }
            return;
        }
        for (i, o) in out.iter_mut().enumerate() {
            *o = p[i] * self.mass_coef[i];
        }
        match &self.elem {
            ElemMats::Dense(m) => {
                for (ei, e) in self.sys.mesh.elements.iter().enumerate() {
                    let y = apply_dense(&m[ei], &gather(p, &e.nodes));
                    for a in 0..4 {
                        out[e.nodes[a]] += y[a];
                    }
                }
            }
            ElemMats::Rotated { coef, rotated } => {
                for (ei, e) in self.sys.mesh.elements.iter().enumerate() {
                    let pe = gather(p, &e.nodes);
                    if *rotated {
                        let r = self.sys.rotations.sources[e.source].rotation;
                        let rt = r.transpose();
                        let u = [rt * pe[0], rt * pe[1], rt * pe[2], rt * pe[3]];
                        let y = self.sys.apply_k0(ei, &u, self.mode);
                        let c = coef[ei];
                        for a in 0..4 {
                            out[e.nodes[a]] += r * y[a] * c;
                        }
                    } else {
                        let y = self.sys.apply_k0(ei, &pe, self.mode);
                        for a in 0..4 {
                            out[e.nodes[a]] += y[a] * coef[ei];
                        }
                    }
                }
            }
        }
        for (k, blk) in &self.sys.k_ext {
            out[*k] += blk * p[*k] * self.ext_coef;
        }
    }

    fn diagonal(&self) -> Vec<V3> {
        if let Some(blocks) = &self.assembled {
            let pat = self.sys.caches.pattern.as_ref().expect("pattern");
            return pat
                .diagonal_slots()
                .iter()
                .map(|&d| blocks[d].diagonal())
                .collect();
        }
        let mut d: Vec<V3> = self.mass_coef.iter().map(|m| V3::repeat(*m)).collect();
        for ei in 0..self.sys.mesh.elements.len() {
            let e = &self.sys.mesh.elements[ei];
            match &self.elem {
                ElemMats::Dense(m) => {
                    for a in 0..4 {
                        for c in 0..3 {
                            d[e.nodes[a]][c] += m[ei][(3 * a + c, 3 * a + c)];
                        }
                    }
                }
                ElemMats::Rotated { coef, rotated } => {
                    // diag(R K_aa Rᵀ) from the 3×3 diagonal blocks of K (cheap: from the
                    // gradients, K_aa = V[λ g gᵀ + μ(|g|² I + g gᵀ)]).
                    let m = &self.sys.mesh.materials[e.material];
                    let r = if *rotated {
                        self.sys.rotations.sources[e.source].rotation
                    } else {
                        Matrix3::identity()
                    };
                    for a in 0..4 {
                        let g = e.grads[a];
                        let kaa = (g * g.transpose() * (m.lambda + m.mu)
                            + Matrix3::identity() * (m.mu * g.norm_squared()))
                            * e.volume;
                        let rk = r * kaa * r.transpose();
                        d[e.nodes[a]] += rk.diagonal() * coef[ei];
                    }
                }
            }
        }
        for (k, blk) in &self.sys.k_ext {
            d[*k] += blk.diagonal() * self.ext_coef;
        }
        d
    }
}

/// Element `ei`'s upper blocks `R K Rᵀ` at volume `v`: from the per-element cache when
/// there is one and the element is rotated, read in place (copying its 720 bytes out was
/// 6–9 % of a step on the 1.33 cm organ, `perf`, 2026-11-28), else computed into `out`.
fn element_iso_blocks<'a>(
    sys: &FemSystem,
    rotated: bool,
    kept: Option<&'a mut [CachedBlocks]>,
    ei: usize,
    v: f64,
    out: &'a mut UpperBlocks,
) -> &'a UpperBlocks {
    let e = &sys.mesh.elements[ei];
    let m = &sys.mesh.materials[e.material];
    let r = rotated.then(|| &sys.rotations.sources[e.source].rotation);
    match (r, kept) {
        (Some(r), Some(kept)) => kept[ei].rotated_iso(&e.grads, v, m.lambda, m.mu, r),
        _ => {
            rotated_iso_blocks(&e.grads, v, m.lambda, m.mu, r, out);
            out
        }
    }
}
