//! Linear (constant-strain) tetrahedron: geometry, Lamé parameters, stiffness.
//!
//! Nodal shape-function gradients `g_a` (1/m): `g_1..g_3` are the rows of `D_m⁻¹`
//! (`D_m = [X₁−X₀, X₂−X₀, X₃−X₀]`, m), `g_0 = −(g_1+g_2+g_3)`, so `F = Σ_a x_a ⊗ g_a`.
//! Small-strain stiffness (N/m), 3×3 block of nodes a, b:
//! `K_ab = V [ λ g_a g_bᵀ + μ ((g_a·g_b) I + g_b g_aᵀ) ] = λ K_λ,ab + μ K_μ,ab`.
//! Under uniform scaling by h, `g ∝ 1/h` and `V ∝ h³`, hence `K = h (λ K̂_λ + μ K̂_μ)`
//! for the unit-scale shape — the template table of [`Template`].

use nalgebra::{Matrix3, SMatrix, Vector3};

use crate::FemError;

/// 12×12 element matrix (node-major: rows `3a..3a+3` belong to node a).
pub type Mat12 = SMatrix<f64, 12, 12>;

/// Lamé parameters `(λ, μ)` in Pa from Young's modulus `young` (Pa) and Poisson ratio `nu`.
pub fn lame(young: f64, nu: f64) -> (f64, f64) {
    let mu = young / (2.0 * (1.0 + nu));
    let lambda = young * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    (lambda, mu)
}

/// Rest geometry of a tetrahedron.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TetGeometry {
    /// `D_m⁻¹` (1/m).
    pub dm_inv: Matrix3<f64>,
    /// Shape-function gradients (1/m).
    pub grads: [Vector3<f64>; 4],
    /// Rest volume (m³), positive.
    pub volume: f64,
}

/// Edge matrix `[x₁−x₀, x₂−x₀, x₃−x₀]`.
#[inline]
pub fn edge_matrix(x: &[Vector3<f64>; 4]) -> Matrix3<f64> {
    Matrix3::from_columns(&[x[1] - x[0], x[2] - x[0], x[3] - x[0]])
}

/// Gradients from `D_m⁻¹`.
#[inline]
pub fn grads_from_dm_inv(dm_inv: &Matrix3<f64>) -> [Vector3<f64>; 4] {
    let g1 = dm_inv.row(0).transpose();
    let g2 = dm_inv.row(1).transpose();
    let g3 = dm_inv.row(2).transpose();
    [-(g1 + g2 + g3), g1, g2, g3]
}

impl TetGeometry {
    /// Geometry of a positively oriented tet; error if its volume is not positive.
    pub fn new(x: &[Vector3<f64>; 4]) -> Result<Self, FemError> {
        let dm = edge_matrix(x);
        let det = dm.determinant();
        let scale = dm.norm().powi(3);
        if det <= 1e-12 * scale || !det.is_finite() {
            return Err(FemError::BadElement {
                element: usize::MAX,
                reason: format!("non-positive rest volume det(D_m) = {det:e} m³"),
            });
        }
        let dm_inv = dm.try_inverse().ok_or_else(|| FemError::BadElement {
            element: usize::MAX,
            reason: "singular rest edge matrix".into(),
        })?;
        Ok(Self {
            dm_inv,
            grads: grads_from_dm_inv(&dm_inv),
            volume: det / 6.0,
        })
    }
}

/// `(K_λ, K_μ)` of a tet (m, i.e. N/m per Pa).
pub fn k_lambda_mu(grads: &[Vector3<f64>; 4], volume: f64) -> (Mat12, Mat12) {
    let mut kl = Mat12::zeros();
    let mut km = Mat12::zeros();
    for a in 0..4 {
        for b in 0..4 {
            let ga = grads[a];
            let gb = grads[b];
            let bl = ga * gb.transpose() * volume;
            let bm = (Matrix3::identity() * ga.dot(&gb) + gb * ga.transpose()) * volume;
            kl.fixed_view_mut::<3, 3>(3 * a, 3 * b).copy_from(&bl);
            km.fixed_view_mut::<3, 3>(3 * a, 3 * b).copy_from(&bm);
        }
    }
    (kl, km)
}

/// Dense small-strain stiffness `λ K_λ + μ K_μ` (N/m).
pub fn stiffness_dense(geom: &TetGeometry, lambda: f64, mu: f64) -> Mat12 {
    let (kl, km) = k_lambda_mu(&geom.grads, geom.volume);
    kl * lambda + km * mu
}

/// `y_a = V σ(∇u) g_a` with `σ = 2μ ε + λ tr(ε) I`, `ε = sym ∇u`, `∇u = Σ u_b ⊗ g_b`:
/// the product `K u` without forming `K` (≈ 90 flops).
#[inline]
pub fn apply_k_gradient(
    grads: &[Vector3<f64>; 4],
    volume: f64,
    lambda: f64,
    mu: f64,
    u: &[Vector3<f64>; 4],
) -> [Vector3<f64>; 4] {
    let mut du = Matrix3::zeros();
    for b in 0..4 {
        du += u[b] * grads[b].transpose();
    }
    let tr = du.trace();
    let sigma =
        (du + du.transpose()) * (mu * volume) + Matrix3::identity() * (lambda * tr * volume);
    [
        sigma * grads[0],
        sigma * grads[1],
        sigma * grads[2],
        sigma * grads[3],
    ]
}

/// `y = K u` for a dense element matrix.
#[inline]
pub fn apply_dense(k: &Mat12, u: &[Vector3<f64>; 4]) -> [Vector3<f64>; 4] {
    let mut uu = SMatrix::<f64, 12, 1>::zeros();
    for (a, ua) in u.iter().enumerate() {
        uu.fixed_view_mut::<3, 1>(3 * a, 0).copy_from(ua);
    }
    let y = k * uu;
    [
        y.fixed_view::<3, 1>(0, 0).into_owned(),
        y.fixed_view::<3, 1>(3, 0).into_owned(),
        y.fixed_view::<3, 1>(6, 0).into_owned(),
        y.fixed_view::<3, 1>(9, 0).into_owned(),
    ]
}

/// One non-zero entry of a template: `K_e[row, col] = h (λ kl + μ km)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TemplateEntry {
    /// Row 0..12.
    pub row: u8,
    /// Column 0..12.
    pub col: u8,
    /// `K̂_λ` entry (m at h = 1 m).
    pub kl: f64,
    /// `K̂_μ` entry.
    pub km: f64,
}

/// Stiffness template of one shape (unit scale h = 1 m): canonical rest coordinates are
/// the first element's `(X_a − X_0)/h`. Only entries that are non-zero in `K̂_λ` or `K̂_μ`
/// (|k| > 1e-12 max|k|) are stored.
#[derive(Clone, Debug)]
pub struct Template {
    /// Caller's shape key.
    pub key: u64,
    /// `D̂_m⁻¹` at unit scale (element: `D̂_m⁻¹ / h`).
    pub dm_inv_hat: Matrix3<f64>,
    /// Unit-scale gradients.
    pub grads_hat: [Vector3<f64>; 4],
    /// Unit-scale volume (m³ at h = 1 m).
    pub volume_hat: f64,
    /// `K̂_λ` dense (kept for assembly).
    pub k_lambda: Mat12,
    /// `K̂_μ` dense.
    pub k_mu: Mat12,
    /// Non-zero entries, row-major.
    pub entries: Vec<TemplateEntry>,
    /// Fraction of the 144 entries that are zero in both `K̂_λ` and `K̂_μ`.
    pub zero_fraction: f64,
    /// Fraction of the 16 3×3 blocks that are entirely zero.
    pub zero_block_fraction: f64,
}

impl Template {
    /// Template from one element's rest positions and its scale `h` (m).
    pub fn new(key: u64, x: &[Vector3<f64>; 4], h: f64) -> Result<Self, FemError> {
        let xs = [
            Vector3::zeros(),
            (x[1] - x[0]) / h,
            (x[2] - x[0]) / h,
            (x[3] - x[0]) / h,
        ];
        let g = TetGeometry::new(&xs)?;
        let (kl, km) = k_lambda_mu(&g.grads, g.volume);
        let maxabs = kl.amax().max(km.amax());
        let thr = 1e-12 * maxabs;
        let mut entries = Vec::new();
        for r in 0..12 {
            for c in 0..12 {
                let (a, b) = (kl[(r, c)], km[(r, c)]);
                if a.abs() > thr || b.abs() > thr {
                    entries.push(TemplateEntry {
                        row: r as u8,
                        col: c as u8,
                        kl: if a.abs() > thr { a } else { 0.0 },
                        km: if b.abs() > thr { b } else { 0.0 },
                    });
                }
            }
        }
        let mut zero_blocks = 0;
        for a in 0..4 {
            for b in 0..4 {
                if !entries
                    .iter()
                    .any(|e| e.row as usize / 3 == a && e.col as usize / 3 == b)
                {
                    zero_blocks += 1;
                }
            }
        }
        Ok(Self {
            key,
            dm_inv_hat: g.dm_inv,
            grads_hat: g.grads,
            volume_hat: g.volume,
            k_lambda: kl,
            k_mu: km,
            zero_fraction: 1.0 - entries.len() as f64 / 144.0,
            zero_block_fraction: zero_blocks as f64 / 16.0,
            entries,
        })
    }

    /// `y = h (λ K̂_λ + μ K̂_μ) u`, skipping zero entries.
    #[inline]
    pub fn apply(&self, h: f64, lambda: f64, mu: f64, u: &[Vector3<f64>; 4]) -> [Vector3<f64>; 4] {
        let mut uf = [0.0; 12];
        for a in 0..4 {
            uf[3 * a] = u[a].x;
            uf[3 * a + 1] = u[a].y;
            uf[3 * a + 2] = u[a].z;
        }
        let (cl, cm) = (h * lambda, h * mu);
        let mut y = [0.0; 12];
        for e in &self.entries {
            y[e.row as usize] += (cl * e.kl + cm * e.km) * uf[e.col as usize];
        }
        [
            Vector3::new(y[0], y[1], y[2]),
            Vector3::new(y[3], y[4], y[5]),
            Vector3::new(y[6], y[7], y[8]),
            Vector3::new(y[9], y[10], y[11]),
        ]
    }
}
