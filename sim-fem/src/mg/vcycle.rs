//! The multigrid hierarchy with its operators and the V-cycle.

use nalgebra::{Cholesky, DVector, Dyn, Matrix3, Vector3};

use super::galerkin::{GalerkinPlan, mask_prolongation};
use super::{Hierarchy, Prolongation};
use crate::FemError;
use crate::solver::BlockPattern;

type V3 = Vector3<f64>;

/// V-cycle settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MgParams {
    /// Damped block-Jacobi sweeps before and after the coarse correction on every level.
    pub smoothing_steps: usize,
    /// Stop descending at the first level with at most this many nodes; it is solved
    /// directly (dense Cholesky) when it has at most [`MgParams::direct_max_nodes`].
    pub coarsest_nodes: usize,
    /// Largest coarsest level solved by dense Cholesky (3n × 3n); a larger one is only
    /// smoothed (`4 × smoothing_steps` sweeps).
    pub direct_max_nodes: usize,
}

impl Default for MgParams {
    fn default() -> Self {
        Self {
            smoothing_steps: 2,
            coarsest_nodes: 200,
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
    blocks: Vec<Matrix3<f64>>,
    dinv: Vec<Matrix3<f64>>,
    omega: f64,
    r: Vec<V3>,
    z: Vec<V3>,
    t: Vec<V3>,
}

/// A geometric multigrid preconditioner for the assembled system of a [`BlockPattern`].
#[derive(Clone, Debug)]
pub struct Multigrid {
    params: MgParams,
    fixed: Vec<bool>,
    fine_dinv: Vec<Matrix3<f64>>,
    fine_omega: f64,
    levels: Vec<Level>,
    coarsest: Option<Cholesky<f64, Dyn>>,
    fine_t: Vec<V3>,
    fine_res: Vec<V3>,
}

/// Inverse of each diagonal block (zero for `skip` nodes and singular blocks).
fn block_inverses(diag: impl Iterator<Item = Matrix3<f64>>, skip: &[bool]) -> Vec<Matrix3<f64>> {
    diag.enumerate()
        .map(|(i, d)| {
            if skip.get(i).copied().unwrap_or(false) {
                Matrix3::zeros()
            } else {
                d.try_inverse().unwrap_or_else(Matrix3::zeros)
            }
        })
        .collect()
}

/// Damping of the Jacobi smoother, `1.2 / λ_max(D⁻¹A)` with λ_max from 15 power
/// iterations (raised 5 %: power iteration approaches it from below). Jacobi smooths for
/// `ω < 2 / λ_max`.
fn jacobi_damping(apply: &mut dyn FnMut(&[V3], &mut [V3]), dinv: &[Matrix3<f64>]) -> f64 {
    let n = dinv.len();
    // A deterministic start with every component non-zero on free nodes.
    let mut v: Vec<V3> = (0..n)
        .map(|i| {
            let h = (i as f64 * 0.618_033_988_75).fract();
            dinv[i] * V3::new(1.0 + h, 1.5 - h, 0.7 + 0.5 * h)
        })
        .collect();
    let mut av = vec![V3::zeros(); n];
    let mut lambda = 1.0;
    for _ in 0..15 {
        let norm = v.iter().map(|x| x.norm_squared()).sum::<f64>().sqrt();
        if norm == 0.0 || !norm.is_finite() {
            return 1.0;
        }
        v.iter_mut().for_each(|x| *x /= norm);
        apply(&v, &mut av);
        for i in 0..n {
            v[i] = dinv[i] * av[i];
        }
        lambda = v.iter().map(|x| x.norm_squared()).sum::<f64>().sqrt();
    }
    if lambda > 0.0 && lambda.is_finite() {
        1.2 / (1.05 * lambda)
    } else {
        1.0
    }
}

/// Smoothing sweeps `z += ω D⁻¹ (r − A z)` (`jacobi` = (D⁻¹ blocks, ω)); with
/// `zero_start` the first is `z = ω D⁻¹ r`.
fn smooth(
    apply: &mut dyn FnMut(&[V3], &mut [V3]),
    (dinv, omega): (&[Matrix3<f64>], f64),
    r: &[V3],
    z: &mut [V3],
    t: &mut [V3],
    steps: usize,
    zero_start: bool,
) {
    let mut steps = steps;
    if zero_start {
        for i in 0..z.len() {
            z[i] = dinv[i] * r[i] * omega;
        }
        steps = steps.saturating_sub(1);
    }
    for _ in 0..steps {
        apply(z, t);
        for i in 0..z.len() {
            z[i] += dinv[i] * (r[i] - t[i]) * omega;
        }
    }
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
        let mut rows: Vec<usize> = (0..n).collect();
        let mut levels = Vec::new();
        let mut finer_len = free.iter().filter(|f| **f).count();
        for p in &hierarchy.levels {
            if finer_len <= params.coarsest_nodes {
                break;
            }
            let (masked, _keep, kept) = mask_prolongation(p, &rows, &free);
            if masked.coarse_len() == 0 {
                break;
            }
            let plan = GalerkinPlan::new(&masked, &upper);
            upper = plan.coarse_upper();
            let nc = masked.coarse_len();
            finer_len = nc;
            rows = kept;
            free = vec![true; nc];
            levels.push(Level {
                p: masked,
                plan,
                blocks: Vec::new(),
                dinv: Vec::new(),
                omega: 1.0,
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
            fine_dinv: Vec::new(),
            fine_omega: 1.0,
            levels,
            coarsest: None,
            fine_t: vec![V3::zeros(); n],
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

    /// The Dirichlet mask it was built for.
    pub fn fixed(&self) -> &[bool] {
        &self.fixed
    }

    /// Rebuilds every operator from the fine matrix (`pattern`'s upper blocks): the
    /// Galerkin products, smoother diagonals and damping, the coarsest factorisation.
    pub fn refresh(&mut self, pattern: &BlockPattern, fine: &[Matrix3<f64>]) {
        self.update_fine_diagonal(pattern, fine);
        let fixed = &self.fixed;
        let mut apply_fine = |p: &[V3], out: &mut [V3]| {
            pattern.multiply_upper(fine, p, out);
            for (o, f) in out.iter_mut().zip(fixed) {
                if *f {
                    *o = V3::zeros();
                }
            }
        };
        self.fine_omega = jacobi_damping(&mut apply_fine, &self.fine_dinv);
        for k in 0..self.levels.len() {
            let (done, rest) = self.levels.split_at_mut(k);
            let finer: &[Matrix3<f64>] = match done.last() {
                Some(l) => &l.blocks,
                None => fine,
            };
            let level = &mut rest[0];
            let mut blocks = std::mem::take(&mut level.blocks);
            level.plan.apply(finer, &mut blocks);
            let s = &level.plan.coarse;
            level.dinv = block_inverses((0..s.num_rows()).map(|i| blocks[s.diag(i)]), &[]);
            let mut apply = |p: &[V3], out: &mut [V3]| s.multiply(&blocks, p, out);
            level.omega = jacobi_damping(&mut apply, &level.dinv);
            level.blocks = blocks;
        }
        self.coarsest = match self.levels.last() {
            Some(l) if l.p.coarse_len() <= self.params.direct_max_nodes => {
                let m = l.plan.coarse.to_dense(&l.blocks);
                let c = Cholesky::new(m);
                if c.is_none() {
                    tracing::warn!("multigrid: coarsest operator not positive definite");
                }
                c
            }
            _ => None,
        };
    }

    /// Refreshes the finest level's smoother diagonal only (cheap: every solve).
    pub fn update_fine_diagonal(&mut self, pattern: &BlockPattern, fine: &[Matrix3<f64>]) {
        self.fine_dinv = block_inverses(
            pattern.diagonal_slots().iter().map(|&d| fine[d]),
            &self.fixed,
        );
    }

    /// One V-cycle: `z ≈ A⁻¹ r` with `fine_apply` the finest operator (`out = A p`). `r`
    /// must be zero on fixed nodes; `z` is.
    pub fn vcycle(&mut self, fine_apply: &mut dyn FnMut(&[V3], &mut [V3]), r: &[V3], z: &mut [V3]) {
        let nu = self.params.smoothing_steps.max(1);
        let (dinv, omega) = (&self.fine_dinv, self.fine_omega);
        let (t, res) = (&mut self.fine_t, &mut self.fine_res);
        smooth(fine_apply, (dinv, omega), r, z, t, nu, true);
        if self.levels.is_empty() {
            smooth(fine_apply, (dinv, omega), r, z, t, nu, false);
            return;
        }
        fine_apply(z, t);
        for i in 0..r.len() {
            res[i] = r[i] - t[i];
        }
        let l0 = &mut self.levels[0];
        restrict(&l0.p, res, &mut l0.r);
        let last = self.levels.len() - 1;
        // Down.
        for k in 0..=last {
            let (head, tail) = self.levels.split_at_mut(k + 1);
            let l = &mut head[k];
            let s = &l.plan.coarse;
            let blocks = &l.blocks;
            let mut apply = |p: &[V3], out: &mut [V3]| s.multiply(blocks, p, out);
            if k == last {
                match &self.coarsest {
                    Some(c) => {
                        let b = DVector::from_iterator(
                            3 * l.r.len(),
                            l.r.iter().flat_map(|v| v.iter().copied()),
                        );
                        let x = c.solve(&b);
                        for (i, zi) in l.z.iter_mut().enumerate() {
                            *zi = V3::new(x[3 * i], x[3 * i + 1], x[3 * i + 2]);
                        }
                    }
                    None => smooth(
                        &mut apply,
                        (&l.dinv, l.omega),
                        &l.r,
                        &mut l.z,
                        &mut l.t,
                        4 * nu,
                        true,
                    ),
                }
                break;
            }
            smooth(
                &mut apply,
                (&l.dinv, l.omega),
                &l.r,
                &mut l.z,
                &mut l.t,
                nu,
                true,
            );
            apply(&l.z, &mut l.t);
            for i in 0..l.r.len() {
                l.t[i] = l.r[i] - l.t[i];
            }
            let next = &mut tail[0];
            restrict(&next.p, &l.t, &mut next.r);
        }
        // Up.
        for k in (0..last).rev() {
            let (head, tail) = self.levels.split_at_mut(k + 1);
            let l = &mut head[k];
            prolong_add(&tail[0].p, &tail[0].z, &mut l.z);
            let s = &l.plan.coarse;
            let blocks = &l.blocks;
            let mut apply = |p: &[V3], out: &mut [V3]| s.multiply(blocks, p, out);
            smooth(
                &mut apply,
                (&l.dinv, l.omega),
                &l.r,
                &mut l.z,
                &mut l.t,
                nu,
                false,
            );
        }
        prolong_add(&self.levels[0].p, &self.levels[0].z, z);
        smooth(fine_apply, (dinv, omega), r, z, t, nu, false);
        for (zi, f) in z.iter_mut().zip(&self.fixed) {
            if *f {
                *zi = V3::zeros();
            }
        }
    }
}
