//! Multigrid against independent references: the dense Cholesky solve of the step's own
//! matrix (nalgebra), and Jacobi-PCG's iteration count.

mod two_grid;

use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

use super::{Hierarchy, MgParams, Multigrid, Prolongation};
use crate::mesh::{BoxMesh, kuhn_box};
use crate::solver::{BlockPattern, LinearOperator, Preconditioner, SolverParams, pcg, pcg_with};
use crate::system::{FemDesc, FemSystem, Material, Model, StepParams};

type V3 = Vector3<f64>;

/// The Freudenthal (`kuhn_box`) hierarchy: the nodes of even grid index form the coarse
/// box (half the cells), and a node with odd indices on the axes `O` is the midpoint of
/// the coarse edge from `g − e_O` to `g + e_O`. Levels while every cell count is even.
fn box_hierarchy(cells: [usize; 3]) -> Hierarchy {
    let mut levels = Vec::new();
    let mut c = cells;
    while c.iter().all(|n| n % 2 == 0 && *n >= 2) {
        let fine_id = |i: usize, j: usize, k: usize| (i * (c[1] + 1) + j) * (c[2] + 1) + k;
        let cc = [c[0] / 2, c[1] / 2, c[2] / 2];
        let coarse_id = |i: usize, j: usize, k: usize| (i * (cc[1] + 1) + j) * (cc[2] + 1) + k;
        let mut rows = vec![Vec::new(); (c[0] + 1) * (c[1] + 1) * (c[2] + 1)];
        for i in 0..=c[0] {
            for j in 0..=c[1] {
                for k in 0..=c[2] {
                    let g = [i, j, k];
                    let odd = g.map(|x| x % 2);
                    let row = &mut rows[fine_id(i, j, k)];
                    if odd == [0, 0, 0] {
                        row.push((coarse_id(i / 2, j / 2, k / 2), 1.0));
                    } else {
                        let lo = [0, 1, 2].map(|a| (g[a] - odd[a]) / 2);
                        let hi = [0, 1, 2].map(|a| (g[a] + odd[a]) / 2);
                        row.push((coarse_id(lo[0], lo[1], lo[2]), 0.5));
                        row.push((coarse_id(hi[0], hi[1], hi[2]), 0.5));
                    }
                }
            }
        }
        let nc = (cc[0] + 1) * (cc[1] + 1) * (cc[2] + 1);
        levels.push(Prolongation::from_rows(nc, &rows).unwrap());
        c = cc;
    }
    Hierarchy { levels }
}

/// The step matrix of a co-rotated beam (fixed at x = 0, bent so that rotations matter),
/// stored as [`BlockPattern`] upper blocks with identity on fixed nodes.
struct Assembled {
    pattern: BlockPattern,
    blocks: Vec<Matrix3<f64>>,
    fixed: Vec<bool>,
}

impl LinearOperator for Assembled {
    fn apply(&self, p: &[V3], out: &mut [V3]) {
        self.pattern.multiply_upper(&self.blocks, p, out);
    }
    fn diagonal(&self) -> Vec<V3> {
        let d = self.pattern.diagonal_slots();
        d.iter().map(|&s| self.blocks[s].diagonal()).collect()
    }
}

/// Beam of `cells` (0.02 m cubes), E = 1e5 Pa, ν = 0.45 (ρ = 1000 kg/m³), with elements
/// whose centre lies in the rod `|y − y_c|, |z − z_c| < 1 cell` stiffer by `contrast`;
/// a penalty spring (1e4 N/m) on the free end's corner. Matrix at a bent state, dt (s).
fn beam_matrix(cells: [usize; 3], contrast: f64, dt: f64) -> (BoxMesh, Assembled) {
    beam_matrix_fixed_to(cells, contrast, dt, 1e-9, 0.45)
}

/// [`beam_matrix`] with every node at `x ≤ fixed_x` (m) fixed (cells of 2 cm) and
/// Poisson ratio `nu`.
fn beam_matrix_fixed_to(
    cells: [usize; 3],
    contrast: f64,
    dt: f64,
    fixed_x: f64,
    nu: f64,
) -> (BoxMesh, Assembled) {
    let h = 0.02;
    let size = cells.map(|c| c as f64 * h);
    let mesh = kuhn_box(cells, size, V3::zeros());
    let mut elements = mesh.elements(0);
    for (e, t) in elements.iter_mut().zip(&mesh.tets) {
        let c: V3 = t.iter().map(|&n| mesh.rest[n]).sum::<V3>() / 4.0;
        if (c.y - size[1] / 2.0).abs() < h && (c.z - size[2] / 2.0).abs() < h {
            e.material = 1;
        }
    }
    let soft = Material::new(1e5, nu, 1000.0);
    let fixed = mesh.nodes_with_x_at_most(fixed_x);
    let mut sys = FemSystem::new(&FemDesc {
        rest: mesh.rest.clone(),
        elements,
        materials: vec![soft, Material::new(1e5 * contrast, nu, 1000.0)],
        fixed: fixed.clone(),
        rotation_sources: vec![],
    })
    .unwrap();
    let corner = mesh.node(cells[0], cells[1], cells[2]);
    sys.set_external_stiffness(&[(corner, Matrix3::identity() * 1e4)]);
    // Bend about y: x' = R(θ(x)) x with θ growing along the beam (up to 1 rad).
    let len = size[0];
    let x: Vec<V3> = mesh
        .rest
        .iter()
        .map(|p| {
            let th = p.x / len;
            V3::new(
                p.x * th.cos() - p.z * th.sin(),
                p.y,
                p.x * th.sin() + p.z * th.cos(),
            )
        })
        .collect();
    let p = StepParams {
        model: Model::Corotational,
        ..Default::default()
    };
    let triplets = sys.step_matrix(&x, dt, &p).unwrap();
    let pattern = BlockPattern::new(mesh.rest.len(), &mesh.tets);
    let mut blocks = vec![Matrix3::zeros(); pattern.num_blocks()];
    for (i, &f) in fixed.iter().enumerate() {
        if f {
            blocks[pattern.diagonal_slots()[i]] = Matrix3::identity();
        }
    }
    for (i, j, b) in triplets {
        if i <= j {
            let slot = pattern.row(i).find(|(_, c)| *c == j).unwrap().0;
            blocks[slot] = b;
        }
    }
    (
        mesh,
        Assembled {
            pattern,
            blocks,
            fixed,
        },
    )
}

/// A smooth right-hand side with every free component non-zero (N·s).
fn rhs(n: usize, fixed: &[bool]) -> Vec<V3> {
    (0..n)
        .map(|i| {
            if fixed[i] {
                V3::zeros()
            } else {
                let t = i as f64;
                V3::new(
                    (0.1 * t).sin() + 0.3,
                    (0.07 * t).cos(),
                    1.0 + (0.013 * t).sin(),
                )
            }
        })
        .collect()
}

/// The whole symmetric matrix, dense.
fn dense_matrix(a: &Assembled) -> DMatrix<f64> {
    let n = a.fixed.len();
    let mut m = DMatrix::zeros(3 * n, 3 * n);
    for i in 0..n {
        for (slot, j) in a.pattern.row(i) {
            if j < i {
                continue;
            }
            let blk = a.blocks[slot];
            m.fixed_view_mut::<3, 3>(3 * i, 3 * j).copy_from(&blk);
            m.fixed_view_mut::<3, 3>(3 * j, 3 * i)
                .copy_from(&blk.transpose());
        }
    }
    m
}

/// Dense Cholesky solve on the free DOFs (the independent reference).
fn dense_solve(a: &Assembled, b: &[V3]) -> Vec<V3> {
    let n = b.len();
    let m = dense_matrix(a);
    let rhs = DVector::from_iterator(3 * n, b.iter().flat_map(|v| v.iter().copied()));
    let x = m.cholesky().expect("SPD").solve(&rhs);
    (0..n)
        .map(|i| V3::new(x[3 * i], x[3 * i + 1], x[3 * i + 2]))
        .collect()
}

fn mg_solve(
    a: &Assembled,
    h: &Hierarchy,
    b: &[V3],
    tol: f64,
    params: MgParams,
) -> (Vec<V3>, usize, usize) {
    mg_solve_split(a, h, b, tol, params, &[])
}

/// [`mg_solve`] with the finest level's smoothing split at `bounds` (hybrid sweeps).
fn mg_solve_split(
    a: &Assembled,
    h: &Hierarchy,
    b: &[V3],
    tol: f64,
    params: MgParams,
    bounds: &[usize],
) -> (Vec<V3>, usize, usize) {
    let mut mg = Multigrid::new(h, &a.fixed, &a.pattern, params).unwrap();
    mg.set_fine_parts(bounds);
    mg.refresh(&a.blocks);
    let mut x = vec![V3::zeros(); b.len()];
    let solver = SolverParams {
        max_iters: 500,
        tol,
        warm_start: false,
    };
    let mut vcycle = |r: &[V3], z: &mut [V3]| mg.vcycle(&a.blocks, r, z);
    let res = pcg_with(
        a,
        &a.fixed,
        b,
        &mut x,
        &solver,
        Preconditioner::Custom(&mut vcycle),
    );
    assert!(res.relative_residual <= tol, "{res:?}");
    (x, res.iterations, mg.num_levels())
}

fn jacobi_iterations(a: &Assembled, b: &[V3], tol: f64) -> usize {
    let mut x = vec![V3::zeros(); b.len()];
    let solver = SolverParams {
        max_iters: 20_000,
        tol,
        warm_start: false,
    };
    let res = pcg(a, &a.fixed, b, &mut x, &solver);
    assert!(res.relative_residual <= tol, "{res:?}");
    res.iterations
}

fn rel_diff(x: &[V3], y: &[V3]) -> f64 {
    let d: f64 = x.iter().zip(y).map(|(a, b)| (a - b).norm_squared()).sum();
    let n: f64 = y.iter().map(|b| b.norm_squared()).sum();
    (d / n).sqrt()
}

const SMALL_COARSEST: MgParams = MgParams {
    smoothing_steps: 2,
    coarsest_nodes: 20,
    direct_max_nodes: 800,
};

#[test]
fn mg_pcg_matches_dense_cholesky_with_fixed_nodes_and_contact() {
    let cells = [8, 4, 4];
    let (_, a) = beam_matrix(cells, 1.0, 0.01);
    let b = rhs(a.fixed.len(), &a.fixed);
    let reference = dense_solve(&a, &b);
    let (x, iters, levels) = mg_solve(&a, &box_hierarchy(cells), &b, 1e-12, SMALL_COARSEST);
    assert_eq!(levels, 3, "8×4×4 → 4×2×2 → 2×1×1");
    let d = rel_diff(&x, &reference);
    assert!(
        d < 1e-8,
        "relative difference {d:e} after {iters} iterations"
    );
    assert!(x.iter().zip(&a.fixed).all(|(v, f)| !f || *v == V3::zeros()));
}

#[test]
fn mg_pcg_matches_dense_cholesky_with_1000x_stiffness_contrast() {
    let cells = [8, 4, 4];
    let (_, a) = beam_matrix(cells, 1000.0, 0.01);
    let b = rhs(a.fixed.len(), &a.fixed);
    let reference = dense_solve(&a, &b);
    let (x, iters, _) = mg_solve(&a, &box_hierarchy(cells), &b, 1e-12, SMALL_COARSEST);
    let d = rel_diff(&x, &reference);
    assert!(
        d < 1e-8,
        "relative difference {d:e} after {iters} iterations"
    );
}

#[test]
fn mg_pcg_iterations_stay_flat_as_levels_are_added() {
    // 1e-6 relative residual at dt = 10 ms: the iteration count of MG-PCG should hardly
    // grow with the mesh (2, 3, 4 levels), Jacobi-PCG's roughly doubles per halving.
    let mut counts = Vec::new();
    for cells in [[8, 4, 4], [16, 8, 8]] {
        let (_, a) = beam_matrix(cells, 1.0, 0.01);
        let b = rhs(a.fixed.len(), &a.fixed);
        let (_, mg, levels) = mg_solve(&a, &box_hierarchy(cells), &b, 1e-6, SMALL_COARSEST);
        let jacobi = jacobi_iterations(&a, &b, 1e-6);
        counts.push((cells, levels, mg, jacobi));
    }
    eprintln!("(cells, levels, MG-PCG, Jacobi-PCG) = {counts:?}");
    let (_, _, mg_small, _) = counts[0];
    let (_, _, mg_big, jacobi_big) = counts[1];
    assert!(3 * mg_big <= jacobi_big, "{counts:?}");
    assert!(mg_big <= mg_small + 4, "{counts:?}");
}

// The sparse direct solver against the same references: the dense Cholesky and MG-PCG.

#[test]
fn direct_matches_dense_cholesky_and_mg_pcg_with_1000x_stiffness_contrast() {
    let cells = [8, 4, 4];
    let (_, a) = beam_matrix(cells, 1000.0, 0.01);
    let b = rhs(a.fixed.len(), &a.fixed);
    let direct = crate::direct::DirectSolver::new(&a.pattern, &a.fixed).unwrap();
    let free = a.fixed.iter().filter(|f| !**f).count();
    assert_eq!(direct.num_unknowns(), 3 * free);
    let mut x = vec![V3::repeat(7.0); b.len()];
    direct.solve(&a.blocks, &b, &mut x).unwrap();
    assert!(x.iter().zip(&a.fixed).all(|(v, f)| !f || *v == V3::zeros()));
    let d_dense = rel_diff(&x, &dense_solve(&a, &b));
    assert!(d_dense < 1e-10, "direct vs dense Cholesky: {d_dense:e}");
    let (mg, iters, _) = mg_solve(&a, &box_hierarchy(cells), &b, 1e-13, SMALL_COARSEST);
    let d_mg = rel_diff(&mg, &x);
    assert!(d_mg < 1e-9, "direct vs MG-PCG ({iters} its): {d_mg:e}");
}

#[test]
fn direct_refuses_a_matrix_that_is_not_positive_definite() {
    let (_, mut a) = beam_matrix([4, 2, 2], 1.0, 0.01);
    let direct = crate::direct::DirectSolver::new(&a.pattern, &a.fixed).unwrap();
    let free = a.fixed.iter().position(|f| !f).unwrap();
    a.blocks[a.pattern.diagonal_slots()[free]] = -Matrix3::identity() * 1e9;
    let b = rhs(a.fixed.len(), &a.fixed);
    let mut x = vec![V3::zeros(); b.len()];
    let err = direct.solve(&a.blocks, &b, &mut x).unwrap_err();
    assert!(err.to_string().contains("sparse Cholesky"), "{err}");
}

/// Steps a bent beam (gravity, 0.3 s at dt = 10 ms) with `solver`; CG to 1e-12.
fn stepped_beam(solver: crate::LinearSolver, fix_more_at_step: Option<usize>) -> Vec<V3> {
    let cells = [8, 2, 2];
    let mesh = kuhn_box(cells, [0.16, 0.04, 0.04], V3::zeros());
    let mut fixed = mesh.nodes_with_x_at_most(1e-9);
    let mut sys = FemSystem::new(&FemDesc {
        rest: mesh.rest.clone(),
        elements: mesh.elements(0),
        materials: vec![Material::new(1e5, 0.45, 1000.0)],
        fixed: fixed.clone(),
        rotation_sources: vec![],
    })
    .unwrap();
    let p = StepParams {
        model: Model::Corotational,
        linear_solver: solver,
        solver: SolverParams {
            max_iters: 20_000,
            tol: 1e-12,
            warm_start: false,
        },
        ..Default::default()
    };
    let (mut x, mut v) = (mesh.rest.clone(), vec![V3::zeros(); mesh.rest.len()]);
    let f_ext = vec![V3::zeros(); x.len()];
    for step in 0..30 {
        if fix_more_at_step == Some(step) {
            // A grasp pins the free end's corner: the Dirichlet mask changes mid-run.
            fixed[mesh.node(cells[0], cells[1], cells[2])] = true;
            sys.set_fixed(fixed.clone()).unwrap();
        }
        let stats = sys.step(&mut x, &mut v, &f_ext, 0.01, &p).unwrap();
        assert!(stats.cg_residual <= 1e-10, "step {step}: {stats:?}");
    }
    x
}

#[test]
fn direct_steps_agree_with_converged_jacobi_pcg_also_after_the_fixed_nodes_change() {
    for fix in [None, Some(10)] {
        let reference = stepped_beam(crate::LinearSolver::JacobiPcg, fix);
        let direct = stepped_beam(crate::LinearSolver::Direct, fix);
        let worst = direct
            .iter()
            .zip(&reference)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        // The tip sags by centimetres; both solve every step to ≤ 1e-10 relative.
        assert!(
            worst < 1e-8,
            "fix {fix:?}: max position difference {worst:e} m"
        );
    }
}

/// The V-cycle alone as a stationary iteration `x ← x + V(b − A x)` from 0: the mean
/// residual reduction per cycle over cycles 4 to 12 (past the start-up transient).
fn vcycle_contraction(
    a: &Assembled,
    h: &Hierarchy,
    params: MgParams,
    bounds: &[usize],
) -> (f64, usize) {
    let n = a.fixed.len();
    let b = rhs(n, &a.fixed);
    let mut mg = Multigrid::new(h, &a.fixed, &a.pattern, params).unwrap();
    mg.set_fine_parts(bounds);
    mg.refresh(&a.blocks);
    let norm = |v: &[V3]| v.iter().map(|x| x.norm_squared()).sum::<f64>().sqrt();
    let (mut x, mut r, mut z, mut ax) = (
        vec![V3::zeros(); n],
        b.clone(),
        vec![V3::zeros(); n],
        vec![V3::zeros(); n],
    );
    let mut norms = vec![norm(&r)];
    for _ in 0..12 {
        mg.vcycle(&a.blocks, &r, &mut z);
        for i in 0..n {
            x[i] += z[i];
        }
        a.apply(&x, &mut ax);
        for i in 0..n {
            r[i] = if a.fixed[i] {
                V3::zeros()
            } else {
                b[i] - ax[i]
            };
        }
        norms.push(norm(&r));
    }
    ((norms[12] / norms[4]).powf(1.0 / 8.0), mg.num_levels())
}

#[test]
fn vcycle_contraction_does_not_grow_with_the_level_count_also_with_a_stiff_inclusion() {
    // One forward and one backward Gauss–Seidel sweep per level, dt = 10 ms, the beam
    // bent by up to 1 rad (co-rotated blocks), a spring on the free corner; with and
    // without a rod 1000× stiffer than the rest. Multigrid's defining property: the
    // V-cycle's residual reduction per cycle is bounded away from 1 independently of the
    // number of levels (here 2, 3 and 4).
    let params = MgParams {
        smoothing_steps: 1,
        coarsest_nodes: 20,
        direct_max_nodes: 800,
    };
    for contrast in [1.0, 1000.0] {
        let mut rates = Vec::new();
        for cells in [[4, 2, 2], [8, 4, 4], [16, 8, 8]] {
            let (_, a) = beam_matrix(cells, contrast, 0.01);
            rates.push(vcycle_contraction(&a, &box_hierarchy(cells), params, &[]));
        }
        eprintln!("contrast {contrast}: (rate per V-cycle, levels) = {rates:?}");
        let levels: Vec<usize> = rates.iter().map(|r| r.1).collect();
        assert_eq!(levels, [2, 3, 4], "{rates:?}");
        for (rate, _) in &rates {
            assert!(*rate < 0.9, "contrast {contrast}: {rates:?}");
        }
        // From 3 to 4 levels the rate may not degrade by more than 0.05.
        assert!(
            rates[2].0 <= rates[1].0 + 0.05,
            "contrast {contrast}: {rates:?}"
        );
    }
}

/// Coarse levels below a level that dropped fixed nodes: the beam is fixed up to x = 2
/// cells (the nodes numbered first), so the first coarsening drops their images and
/// renumbers the rest, and the second must read the kept nodes' own prolongation rows. The
/// coarse nodes at x = 0 of the second coarsening are interpolated only from dropped
/// nodes: reading the rows by the renumbered index kept them with empty columns (a zero
/// row in the coarse operator; here the coarsest, which then could not be factored).
/// Every coarse operator must have a positive diagonal and the coarsest must be factored.
#[test]
fn coarse_levels_below_dropped_fixed_nodes_stay_positive_definite() {
    let cells = [16, 8, 8];
    let (_, a) = beam_matrix_fixed_to(cells, 1.0, 0.01, 0.04 + 1e-9, 0.45);
    let h = box_hierarchy(cells);
    let params = MgParams {
        smoothing_steps: 1,
        coarsest_nodes: 40,
        direct_max_nodes: 800,
    };
    let mut mg = Multigrid::new(&h, &a.fixed, &a.pattern, params).unwrap();
    assert!(mg.coarse_diagonal_min().iter().all(|m| m.is_nan()));
    mg.refresh(&a.blocks);
    // 17·9·9 fine nodes; 9·5·5 coarse less the 2·25 images of fixed ones; 5·3·3 less
    // the x = 0 layer (only dropped nodes interpolate from it).
    assert_eq!(mg.level_sizes(), [1377, 175, 36]);
    let mins = mg.coarse_diagonal_min();
    assert!(mins.iter().all(|m| *m > 0.0), "coarse diagonals {mins:?}");
    assert!(mg.coarsest_factored());
}

/// Splits of the rows into 2 and 3 uneven parts.
fn splits(n: usize) -> [Vec<usize>; 2] {
    [vec![0, n / 2, n], vec![0, n / 5, n / 2 + 7, n]]
}

#[test]
fn hybrid_smoothing_over_parts_matches_dense_cholesky_with_1000x_stiffness_contrast() {
    // ℓ1 hybrid Gauss–Seidel on the finest level (parts swept at once): the solve still
    // reaches the dense Cholesky solution, in at most 1.4× the iterations of sequential
    // sweeps (measured 1.13–1.29× with one or two sweeps each way, on this 225-node mesh,
    // whose parts are mostly interface;
    // a Jacobi smoother between all rows would need far more).
    let cells = [8, 4, 4];
    for contrast in [1.0, 1000.0] {
        let (_, a) = beam_matrix(cells, contrast, 0.01);
        let n = a.fixed.len();
        let b = rhs(n, &a.fixed);
        let reference = dense_solve(&a, &b);
        let h = box_hierarchy(cells);
        for nu in [1, 2] {
            let params = MgParams {
                smoothing_steps: nu,
                ..SMALL_COARSEST
            };
            let (_, sequential, _) = mg_solve(&a, &h, &b, 1e-12, params);
            for bounds in splits(n) {
                let (x, iters, _) = mg_solve_split(&a, &h, &b, 1e-12, params, &bounds);
                let case = format!("contrast {contrast}, ν = {nu}, {bounds:?}");
                eprintln!("{case}: {iters} against {sequential}");
                let d = rel_diff(&x, &reference);
                assert!(d < 1e-8, "{case}: {d:e} after {iters}");
                assert!(
                    10 * iters <= 14 * sequential,
                    "{case}: {iters} iterations against {sequential}"
                );
            }
        }
    }
}

#[test]
fn hybrid_vcycle_is_symmetric_and_contracts() {
    // CG needs a symmetric preconditioner: ⟨V a, b⟩ = ⟨a, V b⟩ for the V-cycle with the
    // backward sweeps the adjoint of the forward ones, split or not. And the V-cycle alone
    // still contracts with a stiff inclusion.
    use rand::{Rng, SeedableRng};
    let cells = [8, 4, 4];
    let (_, a) = beam_matrix(cells, 1000.0, 0.01);
    let n = a.fixed.len();
    let h = box_hierarchy(cells);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut random = || -> Vec<V3> {
        (0..n)
            .map(|i| {
                if a.fixed[i] {
                    V3::zeros()
                } else {
                    V3::new(rng.random(), rng.random(), rng.random()) - V3::repeat(0.5)
                }
            })
            .collect()
    };
    let (u, w) = (random(), random());
    let dot = |x: &[V3], y: &[V3]| x.iter().zip(y).map(|(p, q)| p.dot(q)).sum::<f64>();
    let mut all = vec![vec![]];
    all.extend(splits(n));
    // One sweep each way (the default: the split residual is then `−U z` plus the
    // coupling and ℓ1 terms, `hybrid_rows.rs`) and two (the residual in full).
    for (nu, bounds) in [1, 2]
        .into_iter()
        .flat_map(|nu| all.iter().map(move |b| (nu, b)))
    {
        let params = MgParams {
            smoothing_steps: nu,
            ..SMALL_COARSEST
        };
        let mut mg = Multigrid::new(&h, &a.fixed, &a.pattern, params).unwrap();
        mg.set_fine_parts(bounds);
        mg.refresh(&a.blocks);
        let (mut vu, mut vw) = (vec![V3::zeros(); n], vec![V3::zeros(); n]);
        mg.vcycle(&a.blocks, &u, &mut vu);
        mg.vcycle(&a.blocks, &w, &mut vw);
        let (left, right) = (dot(&vu, &w), dot(&u, &vw));
        // Every level's sweeps run in single precision on half-precision blocks
        // (`full_rows.rs`, split: `hybrid_rows.rs`): symmetric to the f32 rounding
        // (2⁻²⁴ ≈ 6e-8 relative per operation), which CG to the step's 1e-6 does not
        // notice.
        let tol = 1e-6;
        assert!(
            (left - right).abs() <= tol * left.abs().max(right.abs()),
            "ν = {nu}, {bounds:?}: ⟨Vu, w⟩ = {left:e}, ⟨u, Vw⟩ = {right:e}"
        );
        // Positive definite on these two.
        assert!(
            dot(&vu, &u) > 0.0 && dot(&vw, &w) > 0.0,
            "ν = {nu}, {bounds:?}"
        );
    }
    let params = MgParams {
        smoothing_steps: 1,
        ..SMALL_COARSEST
    };
    let (sequential, _) = vcycle_contraction(&a, &h, params, &[]);
    for bounds in splits(n) {
        let (rate, _) = vcycle_contraction(&a, &h, params, &bounds);
        assert!(
            rate < 0.9 && rate <= sequential + 0.1,
            "{bounds:?}: {rate} per V-cycle against {sequential} sequential"
        );
    }
}

#[test]
fn hybrid_l1_diagonal_matches_a_dense_computation() {
    // Each row's 3×3 diagonal block plus, on its diagonal, the sum of |a_rc| over the
    // row's scalar entries in other parts (lower blocks are stored transposed: a mix-up of
    // rows and columns there would keep the smoother symmetric and convergent, and only
    // this test would see it).
    let cells = [4, 2, 2];
    let (_, a) = beam_matrix(cells, 1000.0, 0.01);
    let n = a.fixed.len();
    let m = dense_matrix(&a);
    let rows = super::smoother::SymRows::of_pattern(&a.pattern);
    for bounds in splits(n) {
        let h = super::hybrid_rows::HybridRows::new(&rows, &bounds).unwrap();
        let dinv = h.diagonal_inverses(&rows, &a.blocks, &a.fixed);
        for i in 0..n {
            if a.fixed[i] {
                assert_eq!(dinv[i], Matrix3::zeros());
                continue;
            }
            let p = bounds.partition_point(|&b| b <= i) - 1;
            let (s, e) = (bounds[p], bounds[p + 1]);
            let mut d: Matrix3<f64> = m.fixed_view::<3, 3>(3 * i, 3 * i).into();
            for r in 0..3 {
                let off: f64 = (0..n)
                    .filter(|&j| j < s || j >= e)
                    .flat_map(|j| (0..3).map(move |c| (j, c)))
                    .map(|(j, c)| m[(3 * i + r, 3 * j + c)].abs())
                    .sum();
                d[(r, r)] += off;
            }
            let want = d.try_inverse().unwrap();
            let err = (dinv[i] - want).norm() / want.norm();
            assert!(err < 1e-12, "{bounds:?}, row {i}: relative error {err:e}");
        }
    }
}

/// The 8 × 2 × 2-cell beam with the 1000× rod and the contact spring at dt 10 ms, a
/// right-hand side zero on fixed nodes, and the finest level's full rows filled with its
/// blocks and diagonal inverses.
fn beam_full_rows() -> (Assembled, Vec<V3>, super::full_rows::FullRows) {
    let (_, a) = beam_matrix([8, 2, 2], 1000.0, 0.01);
    let r = rhs(a.fixed.len(), &a.fixed);
    let rows = super::smoother::SymRows::of_pattern(&a.pattern);
    let dinv = rows.diagonal_inverses(&a.blocks, &a.fixed);
    let mut full = super::full_rows::FullRows::of(&rows);
    full.fill(&rows, &a.blocks, &dinv);
    (a, r, full)
}

/// The sweeps' half-precision blocks are scaled by a power of two per row
/// (`full_rows.rs`), so that any scene's matrix fits in f16 (largest 65504, smallest
/// normal 6.1e-5): sweeping `2ᵏ A` from the same right-hand side gives `z / 2ᵏ` bit for
/// bit, from k = −60 to 60. Unscaled, `2⁶⁰ A` would round to infinities in f16.
#[test]
fn full_row_sweeps_are_exact_under_power_of_two_scaling() {
    let (a, r, mut full) = beam_full_rows();
    let n = a.fixed.len();
    let rows = super::smoother::SymRows::of_pattern(&a.pattern);
    let sweep = |full: &mut super::full_rows::FullRows| {
        let mut z = vec![V3::zeros(); n];
        full.forward_from_zero(&r, &mut z);
        full.backward(&r, &mut z);
        z
    };
    let z = sweep(&mut full);
    assert!(z.iter().any(|v| v.norm() > 0.0));
    for k in [-60, -20, 20, 60] {
        let f = 2f64.powi(k);
        let blocks: Vec<Matrix3<f64>> = a.blocks.iter().map(|b| b * f).collect();
        let dinv = rows.diagonal_inverses(&blocks, &a.fixed);
        let mut scaled = super::full_rows::FullRows::of(&rows);
        scaled.fill(&rows, &blocks, &dinv);
        let zk = sweep(&mut scaled);
        for (i, (u, v)) in z.iter().zip(&zk).enumerate() {
            for c in 0..3 {
                assert_eq!(
                    (u[c] / f).to_bits(),
                    v[c].to_bits(),
                    "2^{k} A, node {i}: {} against {}",
                    u[c] / f,
                    v[c]
                );
            }
        }
    }
}

/// The f32 full-row sweeps of the finest level (`full_rows.rs`) against dense block
/// substitutions in f64: a forward sweep from zero solves `(D + L) z = r`, the residual
/// after it is `−U z`, a backward sweep from `z` solves `(D + U) z' = r − L z`. Fixed
/// nodes keep `z = 0`. The off-diagonal blocks' half precision (unit roundoff 2⁻¹¹ ≈
/// 4.9e-4, on entries scaled to at most 2) bounds the difference: 1e-3 relative, with
/// the 1000× rod and the contact spring (measured 1.9e-4 for the forward sweep).
#[test]
fn full_row_sweeps_match_dense_block_substitutions() {
    let (a, r, mut full) = beam_full_rows();
    let n = a.fixed.len();
    // Dense parts: D + L and D + U (block triangles), fixed rows and columns replaced by
    // the identity's, and L, U alone.
    let m = dense_matrix(&a);
    let part = |keep: &dyn Fn(usize, usize) -> bool, diag: bool| {
        let mut p = DMatrix::zeros(3 * n, 3 * n);
        for bi in 0..n {
            for bj in 0..n {
                let on_diag = bi == bj;
                if a.fixed[bi] || a.fixed[bj] {
                    if on_diag && diag {
                        p.fixed_view_mut::<3, 3>(3 * bi, 3 * bj)
                            .copy_from(&Matrix3::identity());
                    }
                    continue;
                }
                if (on_diag && diag) || (!on_diag && keep(bi, bj)) {
                    p.fixed_view_mut::<3, 3>(3 * bi, 3 * bj)
                        .copy_from(&m.fixed_view::<3, 3>(3 * bi, 3 * bj));
                }
            }
        }
        p
    };
    let lower = |i: usize, j: usize| j < i;
    let upper = |i: usize, j: usize| j > i;
    let flat = |v: &[V3]| DVector::from_iterator(3 * n, v.iter().flat_map(|x| x.iter().copied()));
    let unflat = |x: &DVector<f64>| -> Vec<V3> {
        (0..n)
            .map(|i| V3::new(x[3 * i], x[3 * i + 1], x[3 * i + 2]))
            .collect()
    };
    // Forward from zero.
    let mut z = vec![V3::zeros(); n];
    full.forward_from_zero(&r, &mut z);
    let z_ref = unflat(&part(&lower, true).lu().solve(&flat(&r)).unwrap());
    let d = rel_diff(&z, &z_ref);
    assert!(
        d < 1e-3,
        "forward sweep from zero: relative difference {d:e}"
    );
    // Residual after it.
    let mut res = vec![V3::zeros(); n];
    full.residual_after_forward_from_zero(&z, &mut res);
    let res_ref = unflat(&(-(part(&upper, false) * flat(&z_ref))));
    let d = rel_diff(&res, &res_ref);
    assert!(
        d < 1e-3,
        "residual after the forward sweep: relative difference {d:e}"
    );
    // Backward from z.
    let rhs_back = flat(&r) - part(&lower, false) * flat(&z_ref);
    full.backward(&r, &mut z);
    let z2_ref = unflat(&part(&upper, true).lu().solve(&rhs_back).unwrap());
    let d = rel_diff(&z, &z2_ref);
    assert!(d < 1e-3, "backward sweep: relative difference {d:e}");
    assert!(
        a.fixed
            .iter()
            .zip(&z)
            .all(|(f, zi)| !f || *zi == V3::zeros())
    );
}

/// The finest sweeps' AVX path and their portable path give the same bits: forward from
/// zero, the residual after it, a backward sweep and a full residual, on the beam with
/// the 1000× rod; and so do the AVX sweeps that prefetch rows ahead (as on meshes whose
/// blocks outgrow the cache, `prefetch.rs`), which must change nothing.
#[test]
fn avx_and_portable_paired_sweeps_are_bit_identical() {
    #[cfg(target_arch = "x86_64")]
    if !std::arch::is_x86_feature_detected!("avx") || !std::arch::is_x86_feature_detected!("f16c") {
        eprintln!("no AVX and F16C on this CPU: every run takes the portable path");
    }
    let run = |portable: bool, prefetch: bool| {
        let (a, r, mut full) = beam_full_rows();
        let n = a.fixed.len();
        full.set_portable(portable);
        full.set_prefetch(prefetch);
        let mut z = vec![V3::zeros(); n];
        full.forward_from_zero(&r, &mut z);
        let mut res = vec![V3::zeros(); n];
        full.residual_after_forward_from_zero(&z, &mut res);
        full.backward(&r, &mut z);
        let mut after = vec![V3::zeros(); n];
        full.residual(&r, &mut z, &mut after);
        res.extend(after);
        (z, res)
    };
    let bits = |v: &[V3]| -> Vec<u64> {
        v.iter()
            .flat_map(|x| x.iter().map(|c| c.to_bits()))
            .collect()
    };
    let (za, ra) = run(false, false);
    let (zf, rf) = run(false, true);
    let (zp, rp) = run(true, false);
    assert!(za.iter().any(|v| v.norm() > 0.0));
    assert_eq!(bits(&za), bits(&zp));
    assert_eq!(bits(&ra), bits(&rp));
    assert_eq!(bits(&za), bits(&zf));
    assert_eq!(bits(&ra), bits(&rf));
}
