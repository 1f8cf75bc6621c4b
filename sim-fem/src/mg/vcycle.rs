//! The multigrid hierarchy with its operators and the V-cycle.

use nalgebra::{Matrix3, Vector3};

use super::dense::DenseCholesky;

use super::full_rows::FullRows;
use super::galerkin::{GalerkinPlan, mask_prolongation};
use super::hybrid_rows::HybridRows;
use super::smoother::{SymRows, post_smooth, pre_smooth, symmetric_smooth};
use super::{Hierarchy, Prolongation};
use crate::FemError;
use crate::solver::BlockPattern;

type V3 = Vector3<f64>;

/// V-cycle settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MgParams {
    /// Block Gauss–Seidel sweeps on every level: forward before the coarse correction,
    /// backward after it.
    pub smoothing_steps: usize,
    /// Stop descending at the first level with at most this many nodes; it is solved
    /// directly (dense Cholesky) when it has at most [`MgParams::direct_max_nodes`].
    pub coarsest_nodes: usize,
    /// Largest coarsest level solved by dense Cholesky (3n × 3n); a larger one is only
    /// smoothed (`2 × smoothing_steps` symmetric sweeps).
    pub direct_max_nodes: usize,
}

impl Default for MgParams {
    fn default() -> Self {
        Self {
            smoothing_steps: 1,
            // 100, not the 200 it was: on the 1.33 cm organ (1,198 nodes, the liver's
            // upper half fixed) 200 stopped at a coarsest level of 143 nodes, whose dense
            // factorisation (every coarse refresh) and triangular solves (every V-cycle)
            // took 23 % of the step, and every refresh step ran past 4 ms. At 100 the
            // hierarchy goes on to 48 nodes: p50 3.55–3.63 → 2.80–3.34 ms, steps over
            // 4 ms 586–686 → 39–309 of 2,000 (the 309 a disturbed run), 13.0 → 13.2
            // iterations, two interleaved pairs (`cosurg run --cell
            // 0.013333333 --script --solver mg-pcg`, 2026-11-28). The beams' coarsest
            // levels (72 and 81 nodes) are under both floors and stay as they were.
            coarsest_nodes: 100,
            direct_max_nodes: 800,
        }
    }
}

/// One coarse level.
#[derive(Clone, Debug)]
struct Level {
    /// Prolongation from this level onto the next finer one (free nodes only).
    p: Prolongation,
    /// `Pᵀ A P` from the finer level's blocks.
    plan: GalerkinPlan,
    rows: SymRows,
    blocks: Vec<Matrix3<f64>>,
    /// The blocks by full rows in f16 (summed in f32) for the sweeps (as the finest
    /// level's; refreshed with the blocks).
    full: FullRows,
    dinv: Vec<Matrix3<f64>>,
    r: Vec<V3>,
    z: Vec<V3>,
    t: Vec<V3>,
}

/// A geometric multigrid preconditioner for the assembled system of a [`BlockPattern`].
#[derive(Clone, Debug)]
pub struct Multigrid {
    params: MgParams,
    fixed: Vec<bool>,
    fine_rows: SymRows,
    fine_dinv: Vec<Matrix3<f64>>,
    /// The finest level's rows split over threads ([`Multigrid::set_fine_parts`]).
    fine_hybrid: Option<HybridRows>,
    /// The finest level's blocks by full rows in f16 (summed in f32), for the sequential
    /// sweeps of a V-cycle with coarse levels (`full_rows.rs`; built with the first
    /// refresh).
    fine_full: Option<FullRows>,
    levels: Vec<Level>,
    coarsest: Option<DenseCholesky>,
    /// The coarsest level's right-hand side and solution, flattened.
    coarsest_rhs: Vec<f64>,
    fine_res: Vec<V3>,
}

/// `out = Pᵀ r`.
fn restrict(p: &Prolongation, r: &[V3], out: &mut [V3]) {
    out.fill(V3::zeros());
    for (i, ri) in r.iter().enumerate() {
        for (c, w) in p.row(i) {
            out[c] += ri * w;
        }
    }
}

/// `z += P zc`.
fn prolong_add(p: &Prolongation, zc: &[V3], z: &mut [V3]) {
    for (i, zi) in z.iter_mut().enumerate() {
        for (c, w) in p.row(i) {
            *zi += zc[c] * w;
        }
    }
}

impl Multigrid {
    /// The symbolic hierarchy for the system of `pattern` with the given Dirichlet mask;
    /// operators come with [`Multigrid::refresh`]. Errors if the hierarchy does not chain
    /// onto `pattern`'s nodes.
    pub fn new(
        hierarchy: &Hierarchy,
        fixed: &[bool],
        pattern: &BlockPattern,
        params: MgParams,
    ) -> Result<Self, FemError> {
        let n = pattern.num_rows();
        hierarchy.validate(n)?;
        if fixed.len() != n {
            return Err(FemError::Size {
                what: "fixed",
                expected: n,
                got: fixed.len(),
            });
        }
        let mut upper = Vec::with_capacity(pattern.num_blocks());
        for i in 0..n {
            upper.extend(
                pattern
                    .row(i)
                    .filter(|(_, j)| *j >= i)
                    .map(|(s, j)| (i, j, s)),
            );
        }
        let mut free: Vec<bool> = fixed.iter().map(|f| !f).collect();
        // Each level's nodes as indices into the unmasked hierarchy's level above.
        let mut orig_index: Vec<usize> = (0..n).collect();
        let mut levels = Vec::new();
        let mut finer_len = free.iter().filter(|f| **f).count();
        for p in &hierarchy.levels {
            if finer_len <= params.coarsest_nodes {
                break;
            }
            let (masked, kept) = mask_prolongation(p, &orig_index, &free);
            if masked.coarse_len() == 0 {
                break;
            }
            let plan = GalerkinPlan::new(&masked, &upper);
            upper = plan.coarse_upper();
            let nc = masked.coarse_len();
            finer_len = nc;
            orig_index = kept;
            free = vec![true; nc];
            let rows = SymRows::of_upper(&plan.coarse);
            levels.push(Level {
                p: masked,
                plan,
                full: FullRows::of(&rows),
                rows,
                blocks: Vec::new(),
                dinv: Vec::new(),
                r: vec![V3::zeros(); nc],
                z: vec![V3::zeros(); nc],
                t: vec![V3::zeros(); nc],
            });
        }
        tracing::debug!(
            levels = levels.len() + 1,
            sizes = ?levels.iter().map(|l| l.p.coarse_len()).collect::<Vec<_>>(),
            "multigrid hierarchy"
        );
        Ok(Self {
            params,
            fixed: fixed.to_vec(),
            fine_rows: SymRows::of_pattern(pattern),
            fine_dinv: Vec::new(),
            fine_hybrid: None,
            fine_full: None,
            levels,
            coarsest: None,
            coarsest_rhs: Vec::new(),
            fine_res: vec![V3::zeros(); n],
        })
    }

    /// Number of levels including the finest.
    pub fn num_levels(&self) -> usize {
        self.levels.len() + 1
    }

    /// Node count of each level, finest first (the finest counts every node).
    pub fn level_sizes(&self) -> Vec<usize> {
        std::iter::once(self.fixed.len())
            .chain(self.levels.iter().map(|l| l.p.coarse_len()))
            .collect()
    }

    /// Whether the coarsest level is solved by its Cholesky factor (after
    /// [`Multigrid::refresh`]): false when it is larger than
    /// [`MgParams::direct_max_nodes`] or its operator was not positive definite (then it
    /// is smoothed instead, a weaker V-cycle).
    pub fn coarsest_factored(&self) -> bool {
        self.coarsest.is_some()
    }

    /// Smallest diagonal entry of every coarse level's operator, coarsest last: positive
    /// for a positive definite fine matrix and a prolongation without empty columns (NaN
    /// for a level before the first [`Multigrid::refresh`]).
    pub fn coarse_diagonal_min(&self) -> Vec<f64> {
        self.levels
            .iter()
            .map(|l| {
                if l.blocks.is_empty() {
                    return f64::NAN; // not refreshed yet
                }
                let rows = &l.plan.coarse.row_ptr;
                rows[..rows.len() - 1]
                    .iter()
                    .map(|&s| {
                        // Each row of the upper CSR starts with its diagonal block.
                        let b = &l.blocks[s];
                        b[(0, 0)].min(b[(1, 1)]).min(b[(2, 2)])
                    })
                    .fold(f64::INFINITY, f64::min)
            })
            .collect()
    }

    /// The Dirichlet mask it was built for.
    pub fn fixed(&self) -> &[bool] {
        &self.fixed
    }

    /// Rebuilds every operator from the fine matrix (the upper blocks of the pattern it
    /// was built for): the Galerkin products, the smoothers' diagonal inverses, the
    /// coarsest factorisation.
    pub fn refresh(&mut self, fine: &[Matrix3<f64>]) {
        self.update_fine_diagonal(fine);
        for k in 0..self.levels.len() {
            let (done, rest) = self.levels.split_at_mut(k);
            let finer: &[Matrix3<f64>] = match done.last() {
                Some(l) => &l.blocks,
                None => fine,
            };
            let level = &mut rest[0];
            level.plan.apply(finer, &mut level.blocks);
            level.dinv = level.rows.diagonal_inverses(&level.blocks, &[]);
            level.full.fill(&level.rows, &level.blocks, &level.dinv);
        }
        self.coarsest = match self.levels.last() {
            Some(l) if l.p.coarse_len() <= self.params.direct_max_nodes => {
                let m = l.plan.coarse.to_dense(&l.blocks);
                let c = DenseCholesky::new(&m);
                if c.is_none() {
                    tracing::warn!("multigrid: coarsest operator not positive definite");
                }
                c
            }
            _ => None,
        };
    }

    /// Refreshes the finest level's smoother diagonal only (cheap: every solve).
    pub fn update_fine_diagonal(&mut self, fine: &[Matrix3<f64>]) {
        // Without a coarse level the V-cycle is one sequential symmetric sweep, which
        // needs the plain diagonal.
        self.fine_dinv = match &self.fine_hybrid {
            Some(h) if !self.levels.is_empty() => {
                h.diagonal_inverses(&self.fine_rows, fine, &self.fixed)
            }
            _ => self.fine_rows.diagonal_inverses(fine, &self.fixed),
        };
        // The sweeps of a V-cycle with coarse levels read full rows: one set, or one per
        // part.
        if let Some(h) = &mut self.fine_hybrid
            && !self.levels.is_empty()
        {
            h.fill(&self.fine_rows, fine, &self.fine_dinv);
            self.fine_full = None;
        } else if !self.levels.is_empty() {
            let rows = &self.fine_rows;
            self.fine_full
                .get_or_insert_with(|| FullRows::of(rows))
                .fill(rows, fine, &self.fine_dinv);
        } else {
            self.fine_full = None;
        }
    }

    /// Splits the finest level's smoothing into the contiguous row ranges `bounds` (first
    /// 0, last the row count), swept at once with ℓ1 hybrid Gauss–Seidel
    /// (`hybrid_rows.rs`; on the current rayon pool, or the solve's spinning helper,
    /// `parallel/spin.rs`); fewer than two parts: one sequential sweep. The coarse levels
    /// stay sequential (each is about an eighth of the one above). Takes effect at the
    /// next [`Multigrid::refresh`] or [`Multigrid::update_fine_diagonal`], which every
    /// solve calls first and which fill the parts' blocks (zero until then).
    /// Bounds that do not start at 0 and end at the row count split nothing.
    pub fn set_fine_parts(&mut self, bounds: &[usize]) {
        let n = self.fine_rows.num_rows();
        let valid = bounds.first() == Some(&0) && bounds.last() == Some(&n);
        let bounds = if valid { bounds } else { &[] };
        let same = match &self.fine_hybrid {
            Some(h) => h.bounds() == bounds,
            None => bounds.len() < 3,
        };
        if !same {
            self.fine_hybrid = HybridRows::new(&self.fine_rows, bounds);
        }
    }

    /// One V-cycle: `z ≈ A⁻¹ r` with `fine` the finest operator's upper blocks, those of
    /// the last [`Multigrid::refresh`] or [`Multigrid::update_fine_diagonal`] (the sweeps
    /// read their f16 copy: `full_rows.rs`, or one per part, `hybrid_rows.rs`). `r` must
    /// be zero on fixed nodes; `z` is.
    pub fn vcycle(&mut self, fine: &[Matrix3<f64>], r: &[V3], z: &mut [V3]) {
        let nu = self.params.smoothing_steps.max(1);
        let (rows, dinv) = (&self.fine_rows, &self.fine_dinv);
        if self.levels.is_empty() {
            symmetric_smooth(rows, fine, dinv, r, z, nu);
            return;
        }
        let res = &mut self.fine_res;
        match (&mut self.fine_hybrid, &mut self.fine_full) {
            (Some(h), _) => h.pre_smooth(r, z, res, nu),
            (None, Some(full)) => full.pre_smooth(r, z, res, nu),
            (None, None) => pre_smooth(rows, fine, dinv, r, z, res, nu),
        }
        let l0 = &mut self.levels[0];
        restrict(&l0.p, res, &mut l0.r);
        let last = self.levels.len() - 1;
        // Down.
        for k in 0..=last {
            let (head, tail) = self.levels.split_at_mut(k + 1);
            let l = &mut head[k];
            if k == last {
                match &self.coarsest {
                    Some(c) => {
                        let x = &mut self.coarsest_rhs;
                        x.clear();
                        x.extend(l.r.iter().flat_map(|v| v.iter().copied()));
                        c.solve_in_place(x);
                        for (zi, xi) in l.z.iter_mut().zip(x.chunks_exact(3)) {
                            *zi = V3::new(xi[0], xi[1], xi[2]);
                        }
                    }
                    None => symmetric_smooth(&l.rows, &l.blocks, &l.dinv, &l.r, &mut l.z, 2 * nu),
                }
                break;
            }
            l.full.pre_smooth(&l.r, &mut l.z, &mut l.t, nu);
            let next = &mut tail[0];
            restrict(&next.p, &l.t, &mut next.r);
        }
        // Up.
        for k in (0..last).rev() {
            let (head, tail) = self.levels.split_at_mut(k + 1);
            let l = &mut head[k];
            prolong_add(&tail[0].p, &tail[0].z, &mut l.z);
            l.full.post_smooth(&l.r, &mut l.z, nu);
        }
        prolong_add(&self.levels[0].p, &self.levels[0].z, z);
        match (&mut self.fine_hybrid, &mut self.fine_full) {
            (Some(h), _) => h.post_smooth(r, z, nu),
            (None, Some(full)) => full.post_smooth(r, z, nu),
            (None, None) => post_smooth(rows, fine, dinv, r, z, nu),
        }
    }
}
