//! The coarsest level's direct solve: a dense Cholesky factor `A = L Lᵀ` kept twice, as
//! `L` and as `Lᵀ`, both column-major, so that the factorisation and both triangular
//! solves are column updates (`y[i..] −= c · col[i..]`) on contiguous slices.
//!
//! Why not nalgebra's `Cholesky`: its factorisation and solves go through strided matrix
//! views; on the 12,288-tet beam (coarsest level 81 nodes, 243 unknowns) they were 5 % of
//! an MG-PCG step at dt 10 ms (`perf`, 2026-11-28), for a system solved twice per CG
//! iteration. The column updates here have no reductions, so the compiler vectorises them
//! without reordering a sum: the bits do not depend on the CPU.

use nalgebra::DMatrix;

/// `A = L Lᵀ` of a symmetric positive definite matrix.
#[derive(Clone, Debug)]
pub(super) struct DenseCholesky {
    n: usize,
    /// `L`, column-major (entries above the diagonal unused).
    l: Vec<f64>,
    /// `Lᵀ`, column-major: column `j` is row `j` of `L` (entries below the diagonal
    /// unused).
    lt: Vec<f64>,
    /// `1 / L_jj`.
    inv_diag: Vec<f64>,
}

impl DenseCholesky {
    /// The factor of `a` (its lower triangle is read), or `None` if a pivot is not
    /// positive (not positive definite, or NaN).
    pub fn new(a: &DMatrix<f64>) -> Option<Self> {
        assert_eq!(a.ncols(), a.nrows(), "square matrix");
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            /// # Safety
            /// The CPU must support AVX.
            #[target_feature(enable = "avx")]
            unsafe fn avx(a: &DMatrix<f64>) -> Option<DenseCholesky> {
                DenseCholesky::factor(a)
            }
            // SAFETY: the CPU has AVX (checked just above).
            return unsafe { avx(a) };
        }
        Self::factor(a)
    }

    /// [`DenseCholesky::new`]'s column updates (elementwise, as the solves').
    #[inline(always)]
    fn factor(a: &DMatrix<f64>) -> Option<Self> {
        let n = a.nrows();
        let mut l = a.as_slice().to_vec();
        let mut inv_diag = vec![0.0; n];
        for k in 0..n {
            let (done, rest) = l.split_at_mut((k + 1) * n);
            let col_k = &mut done[k * n..];
            let d = col_k[k];
            if d.is_nan() || d <= 0.0 {
                return None;
            }
            let lkk = d.sqrt();
            col_k[k] = lkk;
            let inv = 1.0 / lkk;
            inv_diag[k] = inv;
            for v in &mut col_k[k + 1..] {
                *v *= inv;
            }
            let col_k = &done[k * n..];
            // Right-looking update of the columns to the right, below their diagonals.
            for (jj, col_j) in rest.chunks_exact_mut(n).enumerate() {
                let j = k + 1 + jj;
                let ljk = col_k[j];
                for (a_ij, l_ik) in col_j[j..].iter_mut().zip(&col_k[j..]) {
                    *a_ij -= l_ik * ljk;
                }
            }
        }
        let mut lt = vec![0.0; n * n];
        for j in 0..n {
            for i in j..n {
                lt[i * n + j] = l[j * n + i];
            }
        }
        Some(Self { n, l, lt, inv_diag })
    }

    /// `x ← A⁻¹ x`.
    pub fn solve_in_place(&self, x: &mut [f64]) {
        assert_eq!(x.len(), self.n, "right-hand side of the factor's size");
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx") {
            /// # Safety
            /// The CPU must support AVX.
            #[target_feature(enable = "avx")]
            unsafe fn avx(c: &DenseCholesky, x: &mut [f64]) {
                c.solve(x);
            }
            // SAFETY: the CPU has AVX (checked just above).
            unsafe { avx(self, x) };
            return;
        }
        self.solve(x);
    }

    /// [`DenseCholesky::solve_in_place`]'s column updates (elementwise: the same bits
    /// whatever the vector width they are compiled for).
    #[inline(always)]
    fn solve(&self, x: &mut [f64]) {
        let n = self.n;
        // L y = b, column by column.
        for j in 0..n {
            let yj = x[j] * self.inv_diag[j];
            x[j] = yj;
            for (xi, lij) in x[j + 1..]
                .iter_mut()
                .zip(&self.l[j * n + j + 1..(j + 1) * n])
            {
                *xi -= lij * yj;
            }
        }
        // Lᵀ x = y, column by column from the last.
        for j in (0..n).rev() {
            let xj = x[j] * self.inv_diag[j];
            x[j] = xj;
            for (xi, uij) in x[..j].iter_mut().zip(&self.lt[j * n..j * n + j]) {
                *xi -= uij * xj;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn solves_like_nalgebra_cholesky_and_refuses_indefinite_matrices() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        for n in [1, 2, 7, 30, 81] {
            let b = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
            let a = &b * b.transpose() + DMatrix::identity(n, n) * 0.1;
            let rhs: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut x = rhs.clone();
            DenseCholesky::new(&a)
                .expect("positive definite")
                .solve_in_place(&mut x);
            // Independent reference: nalgebra's factorisation.
            let want = nalgebra::Cholesky::new(a.clone())
                .expect("positive definite")
                .solve(&nalgebra::DVector::from_vec(rhs.clone()));
            for (g, w) in x.iter().zip(want.iter()) {
                assert!(
                    (g - w).abs() <= 1e-9 * (1.0 + w.abs()),
                    "n {n}: {g} against {w}"
                );
            }
            // And the residual itself.
            let ax = &a * nalgebra::DVector::from_vec(x.clone());
            for (r, b) in ax.iter().zip(&rhs) {
                assert!((r - b).abs() <= 1e-9, "n {n}: residual {}", r - b);
            }
        }
        let mut indefinite = DMatrix::identity(3, 3);
        indefinite[(2, 2)] = -1.0;
        assert!(DenseCholesky::new(&indefinite).is_none());
        assert!(DenseCholesky::new(&DMatrix::from_element(2, 2, f64::NAN)).is_none());
    }
}
