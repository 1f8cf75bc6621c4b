//! Jacobi-preconditioned conjugate gradients on 3-vector fields with Dirichlet projection,
//! and a 3×3-block CSR pattern for the assembled operator.

use nalgebra::{Matrix3, Vector3};

mod cg_vectors;
mod full_product;
mod upper_product;
pub use full_product::RowBlock;
pub use upper_product::UpperRows;

use cg_vectors::{flat, flat_mut};

type V3 = Vector3<f64>;

/// CG control.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolverParams {
    /// Iteration budget.
    pub max_iters: usize,
    /// Stop when `‖b − A x‖₂ ≤ tol ‖b‖₂` (unpreconditioned residual, free DOFs).
    pub tol: f64,
    /// Start from the previous step's solution (dynamic steps only), when that solve
    /// converged (reached `tol`): a truncated solve's Δv is not kept.
    pub warm_start: bool,
}

impl SolverParams {
    /// Real-time budget: 25 iterations, 1e-3 relative, cold start (SOFA-like budget).
    ///
    /// Warm-starting Δv with the previous step's Δv and truncating CG pumped energy into a
    /// stiff beam (E = 1e6 Pa, dt = 33 ms: +890 J in 1 s); `pcg` therefore only keeps an
    /// initial guess that lowers `½xᵀAx − bᵀx` below its value at 0, and warm start is
    /// off by default.
    pub fn realtime() -> Self {
        Self {
            max_iters: 25,
            tol: 1e-3,
            warm_start: false,
        }
    }
    /// Reference accuracy: 1e-10 relative, up to 20 000 iterations.
    pub fn accurate() -> Self {
        Self {
            max_iters: 20_000,
            tol: 1e-10,
            warm_start: false,
        }
    }
}

/// Outcome of a CG solve.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CgResult {
    /// Iterations done.
    pub iterations: usize,
    /// `‖b − A x‖/‖b‖` at exit (recursive residual).
    pub relative_residual: f64,
    /// Stopped on `pᵀ A p ≤ 0` (indefinite operator); `x` is the last iterate (or the
    /// preconditioned residual if that happened at the first iteration).
    pub negative_curvature: bool,
}

/// A symmetric operator on 3-vector fields.
pub trait LinearOperator {
    /// `out = A p`.
    fn apply(&self, p: &[V3], out: &mut [V3]);
    /// Diagonal of A (for Jacobi).
    fn diagonal(&self) -> Vec<V3>;
}

fn dot(a: &[V3], b: &[V3]) -> f64 {
    cg_vectors::dot(flat(a), flat(b))
}

/// A preconditioner's application `(r, z) ↦ z ≈ A⁻¹ r`.
type CustomPrecond<'a> = dyn FnMut(&[V3], &mut [V3]) + 'a;

/// The preconditioner of [`pcg_with`]: `z ≈ A⁻¹ r`.
pub enum Preconditioner<'a> {
    /// Jacobi: `z = diag(A)⁻¹ r` (3-vector diagonal; non-positive entries act as 1). Its
    /// application is fused into the iteration's vector updates, which cost as much as
    /// the sparse product on small meshes.
    Jacobi(Vec<V3>),
    /// Any symmetric positive-definite `apply(r, z)` (e.g. a multigrid V-cycle); `z` is
    /// projected onto the free nodes after each application.
    Custom(&'a mut dyn FnMut(&[V3], &mut [V3])),
}

impl Preconditioner<'_> {
    /// Jacobi from the operator's diagonal.
    pub fn jacobi(op: &impl LinearOperator) -> Self {
        Preconditioner::Jacobi(
            op.diagonal()
                .iter()
                .map(|d| d.map(|c| if c > 0.0 { 1.0 / c } else { 1.0 }))
                .collect(),
        )
    }
}

fn project(v: &mut [V3], fixed: &[bool]) {
    for (vi, f) in v.iter_mut().zip(fixed) {
        if *f {
            *vi = V3::zeros();
        }
    }
}

/// Solve `A x = b` on the free nodes (`fixed[i]` ⇒ `x_i = 0`) with Jacobi-PCG from the
/// initial guess in `x` (see [`pcg_with`]).
pub fn pcg(
    op: &impl LinearOperator,
    fixed: &[bool],
    b: &[V3],
    x: &mut [V3],
    params: &SolverParams,
) -> CgResult {
    pcg_with(op, fixed, b, x, params, Preconditioner::jacobi(op))
}

/// Solve `A x = b` on the free nodes (`fixed[i]` ⇒ `x_i = 0`) by preconditioned CG from
/// the initial guess in `x`. The guess is kept only if it lowers `½xᵀAx − bᵀx` below its
/// value at 0. Stops when `‖b − A x‖₂ ≤ tol ‖b‖₂` (recursive residual, free DOFs), after
/// `max_iters` iterations, or on non-positive curvature.
pub fn pcg_with(
    op: &impl LinearOperator,
    fixed: &[bool],
    b: &[V3],
    x: &mut [V3],
    params: &SolverParams,
    mut precond: Preconditioner<'_>,
) -> CgResult {
    let n = b.len();
    assert!(
        fixed.len() == n && x.len() == n,
        "CG on {n} nodes: {} fixed flags, {} unknowns",
        fixed.len(),
        x.len()
    );
    project(x, fixed);
    let mut bb = b.to_vec();
    project(&mut bb, fixed);
    let bnorm = dot(&bb, &bb).sqrt();
    if bnorm == 0.0 {
        x.iter_mut().for_each(|v| *v = V3::zeros());
        return CgResult::default();
    }
    // From zero (a cold start) the residual is `b` itself: no product.
    let mut r = bb.clone();
    if x.iter().any(|v| *v != V3::zeros()) {
        op.apply(x, &mut r);
        for i in 0..n {
            r[i] = bb[i] - r[i];
        }
        project(&mut r, fixed);
    }
    // Guard the initial guess: keep it only if it lowers φ(x) = ½xᵀAx − bᵀx below
    // φ(0) = 0, i.e. −½ xᵀ(b + r) < 0.
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
    // The Jacobi diagonal as components (fused into the updates below), or the custom
    // preconditioner (applied between them).
    let (inv_diag, mut custom): (Option<&[f64]>, Option<&mut CustomPrecond<'_>>) =
        match &mut precond {
            Preconditioner::Jacobi(d) => (Some(flat(d)), None),
            Preconditioner::Custom(f) => (None, Some(&mut **f)),
        };
    match (inv_diag, custom.as_deref_mut()) {
        (Some(d), _) => {
            for ((zi, ri), di) in flat_mut(&mut z).iter_mut().zip(flat(&r)).zip(d) {
                *zi = ri * di;
            }
        }
        (None, Some(f)) => {
            f(&r, &mut z);
            project(&mut z, fixed);
        }
        (None, None) => unreachable!("a preconditioner is Jacobi or custom"),
    }
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut ap = vec![V3::zeros(); n];
    let fixed_nodes: Vec<usize> = (0..n).filter(|&i| fixed[i]).collect();
    // The vector updates of an iteration are fused into two passes over the unknowns (three
    // with a custom preconditioner), over their components (`cg_vectors.rs`).
    for k in 0..params.max_iters {
        op.apply(&p, &mut ap);
        for &i in &fixed_nodes {
            ap[i] = V3::zeros();
        }
        let pap = dot(&p, &ap);
        if pap <= 0.0 || !pap.is_finite() {
            res.negative_curvature = true;
            if k == 0 {
                x.copy_from_slice(&z);
            }
            tracing::trace!(k, "CG: non-positive curvature");
            return res;
        }
        let alpha = rz / pap;
        let (xf, rf, pf, apf) = (flat_mut(x), flat_mut(&mut r), flat(&p), flat(&ap));
        let (rr, mut rz_new) = match inv_diag {
            Some(d) => cg_vectors::update_jacobi(xf, rf, flat_mut(&mut z), pf, apf, d, alpha),
            None => (cg_vectors::update(xf, rf, pf, apf, alpha), 0.0),
        };
        res.iterations = k + 1;
        res.relative_residual = rr.sqrt() / bnorm;
        if res.relative_residual <= params.tol {
            break;
        }
        if let Some(f) = custom.as_deref_mut() {
            f(&r, &mut z);
            project(&mut z, fixed);
            rz_new = dot(&r, &z);
        }
        let beta = rz_new / rz;
        rz = rz_new;
        cg_vectors::next_direction(flat_mut(&mut p), flat(&z), beta);
    }
    res
}

/// Sparsity of a 3×3-block matrix on a tet mesh (node adjacency incl. the diagonal).
#[derive(Clone, Debug)]
pub struct BlockPattern {
    row_ptr: Vec<usize>,
    cols: Vec<usize>,
    diag: Vec<usize>,
    /// Per slot, the slot of its mirror block (row and column swapped).
    mirror: Vec<usize>,
    /// Per element, the slot of each of its 16 blocks (u32: half the bytes that assembly
    /// streams per element; a pattern has far fewer than 2³² blocks).
    elem_slots: Vec<[u32; 16]>,
    /// Per element, bit `4a + b` set when block `(a, b)` lies on or above the diagonal
    /// (row node ≤ column node): the blocks a symmetric assembly stores.
    elem_upper: Vec<u16>,
    /// The index of [`UpperRows`]: row `i`'s blocks on and above the diagonal are
    /// `upper_ptr[i]..upper_ptr[i + 1]` there, in the columns `upper_cols` (u32: the
    /// product streams them with the blocks).
    upper_ptr: Vec<u32>,
    upper_cols: Vec<u32>,
}

impl BlockPattern {
    /// Pattern for `n` nodes and the given tets.
    pub fn new(n: usize, tets: &[[usize; 4]]) -> Self {
        let mut adj: Vec<Vec<usize>> = (0..n).map(|i| vec![i]).collect();
        for t in tets {
            for &a in t {
                for &b in t {
                    adj[a].push(b);
                }
            }
        }
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut cols = Vec::new();
        row_ptr.push(0);
        for a in &mut adj {
            a.sort_unstable();
            a.dedup();
            cols.extend_from_slice(a);
            row_ptr.push(cols.len());
        }
        let find = |r: usize, c: usize| -> usize {
            let s = &cols[row_ptr[r]..row_ptr[r + 1]];
            row_ptr[r] + s.binary_search(&c).expect("in pattern")
        };
        let diag: Vec<usize> = (0..n).map(|i| find(i, i)).collect();
        let mirror = (0..n)
            .flat_map(|i| (row_ptr[i]..row_ptr[i + 1]).map(move |s| (i, s)))
            .map(|(i, s)| find(cols[s], i))
            .collect();
        let elem_slots = tets
            .iter()
            .map(|t| {
                let mut s = [0u32; 16];
                for a in 0..4 {
                    for b in 0..4 {
                        s[4 * a + b] =
                            u32::try_from(find(t[a], t[b])).expect("fewer than 2³² blocks");
                    }
                }
                s
            })
            .collect();
        let elem_upper = tets
            .iter()
            .map(|t| {
                let mut m = 0u16;
                for a in 0..4 {
                    for b in 0..4 {
                        if t[a] <= t[b] {
                            m |= 1 << (4 * a + b);
                        }
                    }
                }
                m
            })
            .collect();
        let (mut upper_ptr, mut upper_cols) = (vec![0u32], Vec::new());
        for (i, &d) in diag.iter().enumerate() {
            upper_cols.extend(
                cols[d..row_ptr[i + 1]]
                    .iter()
                    .map(|&j| u32::try_from(j).expect("fewer than 2³² nodes")),
            );
            upper_ptr.push(u32::try_from(upper_cols.len()).expect("fewer than 2³² blocks"));
        }
        Self {
            row_ptr,
            cols,
            diag,
            mirror,
            elem_slots,
            elem_upper,
            upper_ptr,
            upper_cols,
        }
    }
    /// Blocks of element `e` on or above the diagonal (bit `4a + b`).
    pub fn element_upper(&self, e: usize) -> u16 {
        self.elem_upper[e]
    }
    /// Number of block rows (nodes).
    pub fn num_rows(&self) -> usize {
        self.diag.len()
    }
    /// `(slot, column)` of every block of row `i`, columns ascending.
    pub fn row(&self, i: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        (self.row_ptr[i]..self.row_ptr[i + 1]).map(move |k| (k, self.cols[k]))
    }
    /// Number of 3×3 blocks.
    pub fn num_blocks(&self) -> usize {
        self.cols.len()
    }
    /// Block slots of element `e`, index `4a + b`.
    pub fn element_slots(&self, e: usize) -> &[u32; 16] {
        &self.elem_slots[e]
    }
    /// Slot of each diagonal block.
    pub fn diagonal_slots(&self) -> &[usize] {
        &self.diag
    }
    /// `out = A p`.
    pub fn multiply(&self, blocks: &[Matrix3<f64>], p: &[V3], out: &mut [V3]) {
        for (i, o) in out.iter_mut().enumerate() {
            let mut acc = V3::zeros();
            for k in self.row_ptr[i]..self.row_ptr[i + 1] {
                acc += blocks[k] * p[self.cols[k]];
            }
            *o = acc;
        }
    }
    /// `out = A p` for a symmetric `A` of which only the blocks on and above the diagonal
    /// are stored (the others are ignored): each stored off-diagonal block is used twice,
    /// as `A_ij p_j` and `A_ijᵀ p_i`, so half the matrix is read.
    pub fn multiply_upper(&self, blocks: &[Matrix3<f64>], p: &[V3], out: &mut [V3]) {
        self.multiply_upper_rows(blocks, p, 0, out.len(), out, &mut []);
    }

    /// Rows `start..end` of [`BlockPattern::multiply_upper`]: `rows` (length `end − start`)
    /// receives those rows' products, `spill` (length `n − end`) the transposed products
    /// that fall on later rows; both are overwritten.
    pub fn multiply_upper_rows(
        &self,
        blocks: &[Matrix3<f64>],
        p: &[V3],
        start: usize,
        end: usize,
        rows: &mut [V3],
        spill: &mut [V3],
    ) {
        rows.fill(V3::zeros());
        spill.fill(V3::zeros());
        for i in start..end {
            let d = self.diag[i];
            let pi = p[i];
            let row_end = self.row_ptr[i + 1];
            let mut acc = blocks[d] * pi;
            for (b, &j) in blocks[d + 1..row_end]
                .iter()
                .zip(&self.cols[d + 1..row_end])
            {
                acc += b * p[j];
                let t = b.tr_mul(&pi);
                if j < end {
                    rows[j - start] += t;
                } else {
                    spill[j - end] += t;
                }
            }
            rows[i - start] += acc;
        }
    }

    /// Stored blocks of each row under upper (symmetric) storage: the work of its row in
    /// [`BlockPattern::multiply_upper`].
    pub fn upper_row_work(&self) -> Vec<usize> {
        (0..self.diag.len())
            .map(|i| self.row_ptr[i + 1] - self.diag[i])
            .collect()
    }

    /// Block range `[first, last)` holding the rows of nodes `start..end`.
    pub fn row_block_range(&self, start: usize, end: usize) -> (usize, usize) {
        (self.row_ptr[start], self.row_ptr[end])
    }
}
