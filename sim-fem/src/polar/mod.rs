//! Rotation extraction from a deformation gradient `F = D_s D_m⁻¹` (dimensionless).
//!
//! # Which rotation
//! Every extractor returns the same rotation, the *closest proper rotation*
//! `R = argmax_{R ∈ SO(3)} tr(Rᵀ F)`. With the SVD `F = U Σ Vᵀ` this is
//! `R = U diag(1, 1, d) Vᵀ`, `d = sign det(U Vᵀ)`, the ±1 sitting at the *smallest*
//! singular value. For `det F > 0` it is the orthogonal polar factor; for an inverted
//! element (`det F < 0`) it is the rule of Irving, Teran & Fedkiw (2004, "Invertible finite
//! elements"): the direction of least stretch is the one that is flipped, so an element
//! pulled through itself gets a rotation that pushes it back out. `det R = +1` always.
//!
//! Iterative methods (Newton) converge to the orthogonal factor `Q = U Vᵀ`, with
//! `det Q = sign det F`; when it is −1 we post-multiply by the Householder reflection
//! `I − 2 v vᵀ` where `v` is the eigenvector of the smallest eigenvalue of `S = Qᵀ F`
//! (= `V`'s column at `σ_min`): `Q (I − 2 v vᵀ) = U diag(1,1,−1) Vᵀ`.
//!
//! Degenerate gradients (`|det F| ≤ 1e-14 ‖F‖_F³`, zero or non-finite) fall back to the
//! SVD rule above (nalgebra's SVD completes `U`, `V` to orthogonal matrices); non-finite
//! input returns the warm-start rotation or the identity and logs a warning.

use nalgebra::{Matrix3, SymmetricEigen, Unit, UnitQuaternion, Vector3};

mod byers_xu;
pub use byers_xu::ByersXu;

/// Relative determinant below which `F` counts as degenerate (rank < 3 numerically).
pub const DEGENERATE_DET: f64 = 1e-14;

/// Output of a rotation extraction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolarResult {
    /// Proper rotation, `det = +1` (to rounding).
    pub rotation: Matrix3<f64>,
    /// Iterations used (0 for closed-form / SVD methods).
    pub iterations: u32,
    /// `det F ≤ 0` (inverted or degenerate element).
    pub inverted: bool,
    /// Bounds `(a, b)` with `a ≤ σ_min(F)`, `b ≥ σ_max(F)` used or found by the method;
    /// pass them back as warm start (Byers–Xu scaling) for the next extraction.
    pub sigma_bounds: (f64, f64),
}

/// Optional warm start for an extraction.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct WarmStart {
    /// A rotation close to the answer (previous step, parent tet).
    pub rotation: Option<Matrix3<f64>>,
    /// Estimates `(a, b)` of `(σ_min, σ_max)` (previous step, parent tet). They need not be
    /// strict bounds: the scaled Newton iteration converges for any positive scaling.
    pub sigma_bounds: Option<(f64, f64)>,
}

/// A method that extracts the closest proper rotation from a 3×3 deformation gradient.
pub trait RotationExtractor {
    /// Rotation of `f` (see module docs for the inversion rule).
    fn extract(&self, f: &Matrix3<f64>, warm: Option<&WarmStart>) -> PolarResult;
    /// Short name for logs and benchmarks.
    fn name(&self) -> &'static str;
}

/// Closest proper rotation by SVD (the reference rule of the module docs).
pub fn svd_rotation(f: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = f.svd_unordered(true, true);
    let (Some(mut u), Some(vt)) = (svd.u, svd.v_t) else {
        return Matrix3::identity();
    };
    if u.determinant() * vt.determinant() < 0.0 {
        let s = svd.singular_values;
        let k = if s[0] <= s[1] && s[0] <= s[2] {
            0
        } else if s[1] <= s[2] {
            1
        } else {
            2
        };
        u.column_mut(k).neg_mut();
    }
    u * vt
}

/// Turn an orthogonal `q` with `det q = −1` into the closest proper rotation of `f`
/// (Irving et al.): flip the direction of least stretch of `S = qᵀ f`.
fn flip_least_stretch(q: &Matrix3<f64>, f: &Matrix3<f64>) -> Matrix3<f64> {
    let s = q.transpose() * f;
    let s = (s + s.transpose()) * 0.5;
    let eig = SymmetricEigen::new(s);
    let k = eig.eigenvalues.imin();
    let v = eig.eigenvectors.column(k).into_owned();
    q * (Matrix3::identity() - 2.0 * v * v.transpose())
}

fn degenerate(f: &Matrix3<f64>, det: f64) -> bool {
    let n = f.norm();
    n == 0.0 || det.abs() <= DEGENERATE_DET * n * n * n
}

fn non_finite(warm: Option<&WarmStart>) -> PolarResult {
    tracing::warn!("non-finite deformation gradient; returning warm/identity rotation");
    PolarResult {
        rotation: warm
            .and_then(|w| w.rotation)
            .unwrap_or_else(Matrix3::identity),
        iterations: 0,
        inverted: false,
        sigma_bounds: (1.0, 1.0),
    }
}

fn svd_fallback(f: &Matrix3<f64>, det: f64) -> PolarResult {
    PolarResult {
        rotation: svd_rotation(f),
        iterations: 0,
        inverted: det <= 0.0,
        sigma_bounds: (0.0, f.norm()),
    }
}

/// Reference: nalgebra SVD, then the inversion rule of the module docs.
#[derive(Clone, Copy, Debug, Default)]
pub struct SvdPolar;

impl RotationExtractor for SvdPolar {
    fn extract(&self, f: &Matrix3<f64>, warm: Option<&WarmStart>) -> PolarResult {
        if !f.iter().all(|v| v.is_finite()) {
            return non_finite(warm);
        }
        let det = f.determinant();
        let svd = f.svd_unordered(false, false);
        let s = svd.singular_values;
        PolarResult {
            rotation: svd_rotation(f),
            iterations: 0,
            inverted: det <= 0.0,
            sigma_bounds: (s.min(), s.max()),
        }
    }
    fn name(&self) -> &'static str {
        "svd"
    }
}

/// Müller, Bender, Chentanez & Macklin (2016), "A robust method to extract the rotational
/// part of deformations": quaternion fixed-point iteration
/// `ω = Σᵢ rᵢ × fᵢ / (|Σᵢ rᵢ·fᵢ| + ε)`, `q ← exp(ω) q` (rᵢ, fᵢ columns of R, F).
/// It ascends `tr(Rᵀ F)` over SO(3), hence converges to the closest proper rotation,
/// inverted or not. Warm start: `WarmStart::rotation`; cold start: Gram–Schmidt frame of
/// `F`'s first two columns (always proper). Stops when `|ω| < tol` (radians).
#[derive(Clone, Copy, Debug)]
pub struct MullerIterative {
    /// Stopping threshold on the update angle |ω| (rad).
    pub tol: f64,
    /// Iteration cap.
    pub max_iters: u32,
}

impl Default for MullerIterative {
    fn default() -> Self {
        Self {
            tol: 1e-10,
            max_iters: 100,
        }
    }
}

fn gram_schmidt(f: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let c0 = f.column(0).into_owned();
    let c1 = f.column(1).into_owned();
    let e0 = c0.try_normalize(1e-300)?;
    let e1 = (c1 - e0 * e0.dot(&c1)).try_normalize(1e-300)?;
    let e2 = e0.cross(&e1);
    Some(Matrix3::from_columns(&[e0, e1, e2]))
}

impl RotationExtractor for MullerIterative {
    fn extract(&self, f: &Matrix3<f64>, warm: Option<&WarmStart>) -> PolarResult {
        if !f.iter().all(|v| v.is_finite()) {
            return non_finite(warm);
        }
        let start = warm
            .and_then(|w| w.rotation)
            .or_else(|| gram_schmidt(f))
            .unwrap_or_else(Matrix3::identity);
        let mut q = UnitQuaternion::from_matrix_eps(&start, 1e-12, 20, UnitQuaternion::identity());
        let scale = f.norm().max(1e-300);
        let mut iterations = 0;
        for k in 0..self.max_iters {
            let r = q.to_rotation_matrix().into_inner();
            let mut num = Vector3::zeros();
            let mut den = 0.0;
            for i in 0..3 {
                num += r.column(i).cross(&f.column(i));
                den += r.column(i).dot(&f.column(i));
            }
            let omega = num / (den.abs() + 1e-9 * scale);
            let w = omega.norm();
            iterations = k + 1;
            if w < self.tol {
                break;
            }
            q = UnitQuaternion::from_axis_angle(&Unit::new_unchecked(omega / w), w) * q;
            q.renormalize();
        }
        let det = f.determinant();
        PolarResult {
            rotation: q.to_rotation_matrix().into_inner(),
            iterations,
            inverted: det <= 0.0,
            sigma_bounds: (0.0, f.norm()),
        }
    }
    fn name(&self) -> &'static str {
        "muller2016"
    }
}

/// Müller et al. (2005) shape matching: `Q = A (AᵀA)^{-1/2}` via the symmetric eigen
/// decomposition `AᵀA = V Λ Vᵀ`. Evaluated column-wise as `Q vᵢ = A vᵢ / √λᵢ` for the two
/// largest eigenvalues, the third column completed by a cross product with `V` made
/// right-handed: this is `A (AᵀA)^{-1/2}` when `det A > 0`, and it yields the inversion
/// rule (least-stretch direction flipped) and a proper rotation for inverted and
/// rank-2 `A` without dividing by the smallest eigenvalue (whose relative accuracy is only
/// `ε·cond(A)²`).
#[derive(Clone, Copy, Debug, Default)]
pub struct ShapeMatching;

impl RotationExtractor for ShapeMatching {
    fn extract(&self, f: &Matrix3<f64>, warm: Option<&WarmStart>) -> PolarResult {
        if !f.iter().all(|v| v.is_finite()) {
            return non_finite(warm);
        }
        let det = f.determinant();
        let eig = SymmetricEigen::new(f.transpose() * f);
        let mut idx = [0usize, 1, 2];
        idx.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let l1 = eig.eigenvalues[idx[0]];
        let l2 = eig.eigenvalues[idx[1]];
        if l2 <= 1e-24 * l1 || l1 <= 0.0 {
            return svd_fallback(f, det);
        }
        let v1 = eig.eigenvectors.column(idx[0]).into_owned();
        let v2 = eig.eigenvectors.column(idx[1]).into_owned();
        let v3 = v1.cross(&v2);
        let u1 = (f * v1) / l1.sqrt();
        let u2 = (f * v2) / l2.sqrt();
        // re-orthogonalise (u1, u2 are orthonormal up to rounding)
        let u1 = u1.normalize();
        let u2 = (u2 - u1 * u1.dot(&u2)).normalize();
        let u3 = u1.cross(&u2);
        let rotation =
            Matrix3::from_columns(&[u1, u2, u3]) * Matrix3::from_columns(&[v1, v2, v3]).transpose();
        let l3 = eig.eigenvalues[idx[2]].max(0.0);
        PolarResult {
            rotation,
            iterations: 1,
            inverted: det <= 0.0,
            sigma_bounds: (l3.sqrt(), l1.sqrt()),
        }
    }
    fn name(&self) -> &'static str {
        "shape_matching"
    }
}

/// The polar methods as a value (for parameter structs).
#[derive(Clone, Copy, Debug)]
pub enum PolarMethod {
    /// [`ByersXu`].
    ByersXu(ByersXu),
    /// [`SvdPolar`].
    Svd,
    /// [`MullerIterative`].
    Muller(MullerIterative),
    /// [`ShapeMatching`].
    ShapeMatching,
}

impl Default for PolarMethod {
    fn default() -> Self {
        PolarMethod::ByersXu(ByersXu::default())
    }
}

impl RotationExtractor for PolarMethod {
    fn extract(&self, f: &Matrix3<f64>, warm: Option<&WarmStart>) -> PolarResult {
        match self {
            PolarMethod::ByersXu(m) => m.extract(f, warm),
            PolarMethod::Svd => SvdPolar.extract(f, warm),
            PolarMethod::Muller(m) => m.extract(f, warm),
            PolarMethod::ShapeMatching => ShapeMatching.extract(f, warm),
        }
    }
    fn name(&self) -> &'static str {
        match self {
            PolarMethod::ByersXu(m) => m.name(),
            PolarMethod::Svd => SvdPolar.name(),
            PolarMethod::Muller(m) => m.name(),
            PolarMethod::ShapeMatching => ShapeMatching.name(),
        }
    }
}

/// Squared Frobenius threshold equivalent to a rotation-angle tolerance:
/// `‖R_m − R_n‖²_F = 4(1 − cos θ)` for rotations differing by angle θ (rad).
#[inline]
pub fn rotation_threshold_sq(theta_tol: f64) -> f64 {
    4.0 * (1.0 - theta_tol.cos())
}

/// `true` if rotations `rm`, `rn` differ by less than `theta_tol` (rad), tested without
/// quaternions or trigonometry: `‖R_m − R_n‖²_F < 4(1 − cos θ_tol)`.
#[inline]
pub fn rotations_within(rm: &Matrix3<f64>, rn: &Matrix3<f64>, theta_tol: f64) -> bool {
    (rm - rn).norm_squared() < rotation_threshold_sq(theta_tol)
}
