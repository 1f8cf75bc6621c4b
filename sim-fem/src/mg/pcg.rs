//! Conjugate gradients with a caller-given symmetric positive-definite preconditioner
//! (the V-cycle); same stopping rule and Dirichlet projection as [`crate::solver::pcg`].

use nalgebra::Vector3;

use crate::solver::{CgResult, LinearOperator, SolverParams};

type V3 = Vector3<f64>;

fn dot(a: &[V3], b: &[V3]) -> f64 {
    a.iter().zip(b).map(|(p, q)| p.dot(q)).sum()
}

fn project(v: &mut [V3], fixed: &[bool]) {
    for (vi, f) in v.iter_mut().zip(fixed) {
        if *f {
            *vi = V3::zeros();
        }
    }
}

/// Solve `A x = b` on the free nodes (`fixed[i]` ⇒ `x_i = 0`) by CG preconditioned with
/// `precond(r, z)` (`z ≈ A⁻¹ r`, zero on fixed nodes), from the initial guess in `x`
/// (kept only if it lowers `½xᵀAx − bᵀx` below 0, as in [`crate::solver::pcg`]). Stops
/// when `‖b − A x‖₂ ≤ tol ‖b‖₂` (recursive residual, free DOFs).
pub fn pcg_preconditioned(
    op: &impl LinearOperator,
    fixed: &[bool],
    b: &[V3],
    x: &mut [V3],
    params: &SolverParams,
    precond: &mut dyn FnMut(&[V3], &mut [V3]),
) -> CgResult {
    let n = b.len();
    project(x, fixed);
    let mut bb = b.to_vec();
    project(&mut bb, fixed);
    let bnorm = dot(&bb, &bb).sqrt();
    if bnorm == 0.0 {
        x.iter_mut().for_each(|v| *v = V3::zeros());
        return CgResult::default();
    }
    let mut r = vec![V3::zeros(); n];
    op.apply(x, &mut r);
    for i in 0..n {
        r[i] = bb[i] - r[i];
    }
    project(&mut r, fixed);
    let phi0: f64 = -0.5
        * x.iter()
            .zip(bb.iter().zip(&r))
            .map(|(xi, (bi, ri))| xi.dot(&(bi + ri)))
            .sum::<f64>();
    if phi0 >= 0.0 && x.iter().any(|v| *v != V3::zeros()) {
        x.iter_mut().for_each(|v| *v = V3::zeros());
        r.copy_from_slice(&bb);
    }
    let mut res = CgResult {
        relative_residual: dot(&r, &r).sqrt() / bnorm,
        ..Default::default()
    };
    if res.relative_residual <= params.tol {
        return res;
    }
    let mut z = vec![V3::zeros(); n];
    precond(&r, &mut z);
    project(&mut z, fixed);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut ap = vec![V3::zeros(); n];
    for k in 0..params.max_iters {
        op.apply(&p, &mut ap);
        project(&mut ap, fixed);
        let pap = dot(&p, &ap);
        if pap <= 0.0 || !pap.is_finite() {
            res.negative_curvature = true;
            if k == 0 {
                x.copy_from_slice(&z);
            }
            tracing::trace!(k, "MG-PCG: non-positive curvature");
            return res;
        }
        let alpha = rz / pap;
        let mut rr = 0.0;
        for i in 0..n {
            x[i] += p[i] * alpha;
            r[i] -= ap[i] * alpha;
            rr += r[i].norm_squared();
        }
        res.iterations = k + 1;
        res.relative_residual = rr.sqrt() / bnorm;
        if res.relative_residual <= params.tol {
            break;
        }
        precond(&r, &mut z);
        project(&mut z, fixed);
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        for i in 0..n {
            p[i] = z[i] + p[i] * beta;
        }
    }
    res
}
