//! An experiment, not a test (ignored; run it with `cargo test --release -p
//! cosurg-sim-fem --lib two_grid -- --ignored --nocapture`): where MG-PCG's iterations on
//! the beam come from. A dense two-grid preconditioner (block Gauss–Seidel sweeps, the
//! coarse level `PᵀAP` solved exactly) with the plain hierarchy's prolongation and with it
//! smoothed by one damped block-Jacobi step of the operator (`P = (I − ω D⁻¹A) P₀`, the
//! prolongation smoothing of smoothed aggregation), at ν = 0.3 and 0.45, with and without
//! the 1000× rod; and with the point sweeps replaced by vertex-star Schwarz sweeps, by
//! block sweeps over disjoint clusters of grid nodes, or by Chebyshev smoothing.
//! Results in docs/RESULTS.md ("What limits the two-grid").

use nalgebra::{DMatrix, DVector};

use super::{Assembled, BoxMesh, Hierarchy, beam_matrix_fixed_to, box_hierarchy, dense_matrix};

/// How the two-grid cycle smooths.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Smoother {
    /// Nodal 3×3-block Gauss–Seidel in node order (what `Multigrid` does).
    Point,
    /// Multiplicative Schwarz over vertex stars: each free node with its free neighbours
    /// solved together (exactly), in node order forward, reversed backward.
    Star,
    /// Block Gauss–Seidel over disjoint clusters of `c × c × c` grid nodes (each cluster
    /// solved exactly), forward, then reversed.
    Cluster(usize),
    /// A Chebyshev polynomial of this degree in `D⁻¹A` (`D` the 3×3-block diagonal) on
    /// `[λmax / 30, 1.1 λmax]`, the same before and after the coarse correction: each
    /// degree costs one product, like one point sweep.
    Chebyshev(usize),
}

/// Dense two-grid PCG: `sweeps` forward smoothing sweeps, exact coarse `PᵀAP`, `sweeps`
/// backward ones.
fn dense_two_grid_iterations(
    mesh: &BoxMesh,
    a: &Assembled,
    p: &DMatrix<f64>,
    sweeps: usize,
    smoother: Smoother,
) -> usize {
    let n = a.fixed.len();
    let free: Vec<usize> = (0..3 * n).filter(|k| !a.fixed[k / 3]).collect();
    let full = dense_matrix(a);
    let m = DMatrix::from_fn(free.len(), free.len(), |i, j| full[(free[i], free[j])]);
    let pf = DMatrix::from_fn(free.len(), p.ncols(), |i, j| p[(free[i], j)]);
    // Drop coarse columns that are zero.
    let keep: Vec<usize> = (0..pf.ncols())
        .filter(|&j| pf.column(j).norm() > 0.0)
        .collect();
    let pf = DMatrix::from_fn(pf.nrows(), keep.len(), |i, j| pf[(i, keep[j])]);
    let ac = pf.transpose() * &m * &pf;
    let chol = ac.cholesky().expect("coarse SPD");
    let nf = free.len();
    // The patches (single nodes, stars or clusters) in free-DOF numbering, with their
    // blocks' Cholesky factors; a sweep solves each exactly in turn (multiplicative
    // Schwarz; with single nodes, block Gauss–Seidel).
    let dof_of: Vec<Option<usize>> = {
        let mut v = vec![None; 3 * n];
        for (k, &d) in free.iter().enumerate() {
            v[d] = Some(k);
        }
        v
    };
    let node_sets: Vec<Vec<usize>> = match smoother {
        Smoother::Point | Smoother::Chebyshev(_) => {
            (0..n).filter(|&i| !a.fixed[i]).map(|i| vec![i]).collect()
        }
        Smoother::Star => (0..n)
            .filter(|&i| !a.fixed[i])
            .map(|i| {
                let mut nodes: Vec<usize> = a
                    .pattern
                    .row(i)
                    .map(|(_, j)| j)
                    .filter(|&j| !a.fixed[j])
                    .collect();
                nodes.push(i);
                nodes.sort_unstable();
                nodes.dedup();
                nodes
            })
            .collect(),
        Smoother::Cluster(c) => {
            let mut by_key: std::collections::BTreeMap<[i64; 3], Vec<usize>> = Default::default();
            for i in (0..n).filter(|&i| !a.fixed[i]) {
                let g = [0, 1, 2].map(|k| (mesh.rest[i][k] / mesh.spacing[k]).round() as i64);
                by_key.entry(g.map(|x| x / c as i64)).or_default().push(i);
            }
            by_key.into_values().collect()
        }
    };
    let patches: Vec<(Vec<usize>, nalgebra::Cholesky<f64, nalgebra::Dyn>)> = node_sets
        .iter()
        .map(|nodes| {
            let dofs: Vec<usize> = nodes
                .iter()
                .flat_map(|&j| (0..3).filter_map(|c| dof_of[3 * j + c]).collect::<Vec<_>>())
                .collect();
            let local = DMatrix::from_fn(dofs.len(), dofs.len(), |x, y| m[(dofs[x], dofs[y])]);
            (dofs, local.cholesky().expect("star block SPD"))
        })
        .collect();
    let sweep = |r: &DVector<f64>, z: &mut DVector<f64>, forward: bool| {
        let mut res = r - &m * &*z;
        let order: Box<dyn Iterator<Item = &(Vec<usize>, _)>> = if forward {
            Box::new(patches.iter())
        } else {
            Box::new(patches.iter().rev())
        };
        for (dofs, chol) in order {
            let local = DVector::from_iterator(dofs.len(), dofs.iter().map(|&d| res[d]));
            let dz = chol.solve(&local);
            for (x, &d) in dofs.iter().enumerate() {
                z[d] += dz[x];
            }
            for (x, &d) in dofs.iter().enumerate() {
                res.axpy(-dz[x], &m.column(d), 1.0);
            }
        }
    };
    // `D⁻¹` from the single-node patches' factors, and λmax(D⁻¹A) by power iteration.
    let dinv = |v: &DVector<f64>| -> DVector<f64> {
        let mut out = DVector::zeros(nf);
        for (dofs, c) in &patches {
            let local = DVector::from_iterator(dofs.len(), dofs.iter().map(|&d| v[d]));
            let sol = c.solve(&local);
            for (k, &d) in dofs.iter().enumerate() {
                out[d] = sol[k];
            }
        }
        out
    };
    let lambda_max = if matches!(smoother, Smoother::Chebyshev(_)) {
        let mut v = DVector::from_fn(nf, |i, _| 1.0 + (i as f64 * 0.37).sin());
        let mut lam = 0.0;
        for _ in 0..50 {
            let w = dinv(&(&m * &v));
            lam = w.norm() / v.norm();
            v = w;
        }
        lam
    } else {
        0.0
    };
    // Chebyshev smoothing of `A x = f` from `x` (Adams, Brezina, Hu and Tuminaro 2003).
    let chebyshev = |f: &DVector<f64>, x: &mut DVector<f64>, degree: usize| {
        let (hi, lo) = (1.1 * lambda_max, 1.1 * lambda_max / 30.0);
        let (theta, delta) = (0.5 * (hi + lo), 0.5 * (hi - lo));
        let sigma = theta / delta;
        let mut rho = 1.0 / sigma;
        let mut res = f - &m * &*x;
        let mut d = dinv(&res) / theta;
        for _ in 1..degree {
            *x += &d;
            res -= &m * &d;
            let rho_next = 1.0 / (2.0 * sigma - rho);
            d = &d * (rho_next * rho) + dinv(&res) * (2.0 * rho_next / delta);
            rho = rho_next;
        }
        *x += &d;
    };
    let prec = |r: &DVector<f64>| -> DVector<f64> {
        let mut z = DVector::zeros(nf);
        match smoother {
            Smoother::Chebyshev(k) => chebyshev(r, &mut z, k),
            _ => (0..sweeps).for_each(|_| sweep(r, &mut z, true)),
        }
        let res = r - &m * &z;
        z += &pf * chol.solve(&(pf.transpose() * res));
        match smoother {
            Smoother::Chebyshev(k) => chebyshev(r, &mut z, k),
            _ => (0..sweeps).for_each(|_| sweep(r, &mut z, false)),
        }
        z
    };
    let b = DVector::from_fn(nf, |i, _| ((i as f64) * 0.1).sin() + 0.3);
    let mut x = DVector::zeros(nf);
    let mut r = b.clone();
    let mut z = prec(&r);
    let mut d = z.clone();
    let mut rz = r.dot(&z);
    for it in 1..500 {
        let ad = &m * &d;
        let alpha = rz / d.dot(&ad);
        x += alpha * &d;
        r -= alpha * &ad;
        if r.norm() <= 1e-6 * b.norm() {
            return it;
        }
        z = prec(&r);
        let rz2 = r.dot(&z);
        d = &z + (rz2 / rz) * &d;
        rz = rz2;
    }
    500
}

/// The first prolongation, expanded to 3 components, dense; smoothed by
/// `(I − ω D⁻¹ A)` with the 3×3-block diagonal `D` when `omega > 0` (ω scaled by
/// `4 / (3 λ_max(D⁻¹A))`).
fn dense_prolongation(a: &Assembled, h: &Hierarchy, omega: f64) -> DMatrix<f64> {
    let n = a.fixed.len();
    let p0 = &h.levels[0];
    let mut p = DMatrix::zeros(3 * n, 3 * p0.coarse_len());
    for i in 0..n {
        if a.fixed[i] {
            continue;
        }
        for (c, w) in p0.row(i) {
            for k in 0..3 {
                p[(3 * i + k, 3 * c + k)] = w;
            }
        }
    }
    if omega == 0.0 {
        return p;
    }
    let mut m = dense_matrix(a);
    for i in 0..3 * n {
        for j in 0..3 * n {
            if a.fixed[i / 3] || a.fixed[j / 3] {
                m[(i, j)] = if i == j { 1.0 } else { 0.0 };
            }
        }
    }
    let mut dinv = DMatrix::zeros(3 * n, 3 * n);
    for i in 0..n {
        let blk = m.fixed_view::<3, 3>(3 * i, 3 * i).into_owned();
        dinv.fixed_view_mut::<3, 3>(3 * i, 3 * i)
            .copy_from(&blk.try_inverse().unwrap());
    }
    let da = &dinv * &m;
    let mut v = DVector::from_fn(3 * n, |i, _| 1.0 + (i as f64 * 0.37).sin());
    let mut lam = 0.0;
    for _ in 0..50 {
        let w = &da * &v;
        lam = w.norm() / v.norm();
        v = w;
    }
    let w = omega * 4.0 / (3.0 * lam);
    let mut sp = &p - w * (&da * &p);
    for i in 0..n {
        if a.fixed[i] {
            for k in 0..3 {
                sp.row_mut(3 * i + k).fill(0.0);
            }
        }
    }
    sp
}

#[test]
#[ignore = "experiment: prints iteration counts"]
fn experiment_two_grid_smoother_against_coarse_space() {
    for nu in [0.3, 0.45] {
        for (cells, contrast) in [([16, 4, 4], 1.0), ([16, 4, 4], 1000.0)] {
            let (mesh, a) = beam_matrix_fixed_to(cells, contrast, 0.01, 1e-9, nu);
            let h = box_hierarchy(cells);
            let mut out = Vec::new();
            for omega in [0.0, 1.0] {
                let p = dense_prolongation(&a, &h, omega);
                for sweeps in [1, 2, 4] {
                    out.push(format!(
                        "ω {omega}, {sweeps}+{sweeps} sweeps: {}",
                        dense_two_grid_iterations(&mesh, &a, &p, sweeps, Smoother::Point)
                    ));
                }
            }
            let p = dense_prolongation(&a, &h, 0.0);
            for (name, smoother) in [
                ("stars 1+1", Smoother::Star),
                ("2×2×2 clusters 1+1", Smoother::Cluster(2)),
                ("3×3×3 clusters 1+1", Smoother::Cluster(3)),
                ("Chebyshev 1+1", Smoother::Chebyshev(1)),
                ("Chebyshev 2+2", Smoother::Chebyshev(2)),
                ("Chebyshev 4+4", Smoother::Chebyshev(4)),
            ] {
                out.push(format!(
                    "{name}: {}",
                    dense_two_grid_iterations(&mesh, &a, &p, 1, smoother)
                ));
            }
            eprintln!("ν {nu} {cells:?} contrast {contrast}: {}", out.join("; "));
        }
    }
}
