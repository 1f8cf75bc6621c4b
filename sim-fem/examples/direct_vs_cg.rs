//! Direct (sparse Cholesky, faer) against PCG on the co-rotational step's own system, to
//! decide the linear solver by measurement (a sparse direct factorisation "may win on
//! small meshes — measure"):
//!
//! `cargo run --release -p cosurg-sim-fem --example direct_vs_cg`
//!
//! The beam of the cantilever benchmark (0.4 × 0.1 × 0.1 m, E = 1e5 Pa, ν = 0.45, clamped
//! at x = 0) is bent by 0.5 s of gravity at dt = 10 ms, then the matrix of the next step
//! is taken at dt = 1 and 10 ms. For each: faer's symbolic factorisation (once per
//! topology), numeric factorisation (every step: the rotations change the matrix), the
//! triangular solves, and Jacobi-PCG from zero to a relative residual of 1e-6 and with
//! the real-time budget of 50 iterations (the residual it reaches). One thread
//! (`Par::Seq`); medians of repeated runs.

use std::time::Instant;

use cosurg_sim_fem::mesh::kuhn_box;
use cosurg_sim_fem::solver::{LinearOperator, SolverParams, pcg};
use cosurg_sim_fem::{FemDesc, FemSystem, Material, StepParams};
use faer::linalg::solvers::SolveCore;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::{SparseColMat, Triplet};
use faer::{Conj, Mat, Par, Side};
use nalgebra::{Matrix3, Vector3};

type V3 = Vector3<f64>;

/// The step matrix as a block-row operator for `pcg`.
struct Blocks {
    rows: Vec<Vec<(usize, Matrix3<f64>)>>,
}

impl LinearOperator for Blocks {
    fn apply(&self, p: &[V3], out: &mut [V3]) {
        for (o, row) in out.iter_mut().zip(&self.rows) {
            *o = row.iter().map(|(j, b)| b * p[*j]).sum();
        }
    }
    fn diagonal(&self) -> Vec<V3> {
        self.rows
            .iter()
            .enumerate()
            .map(|(i, row)| {
                row.iter()
                    .find(|(j, _)| *j == i)
                    .map_or(V3::repeat(1.0), |(_, b)| b.diagonal())
            })
            .collect()
    }
}

fn median_ms(mut f: impl FnMut(), reps: usize) -> f64 {
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    faer::set_global_parallelism(Par::Seq);
    println!(
        "{:>6} {:>5} {:>8} {:>9} {:>9} {:>8} {:>11} {:>6} {:>10} {:>10}",
        "tets",
        "dt ms",
        "unknowns",
        "symb. ms",
        "numer. ms",
        "solve ms",
        "PCG 1e-6 ms",
        "its",
        "PCG-50 ms",
        "PCG-50 res"
    );
    for cells in [[16, 4, 4], [32, 8, 8]] {
        let mesh = kuhn_box(cells, [0.4, 0.1, 0.1], V3::zeros());
        let desc = FemDesc {
            rest: mesh.rest.clone(),
            elements: mesh.elements(0),
            materials: vec![Material::new(1e5, 0.45, 1000.0)],
            fixed: mesh.nodes_with_x_at_most(1e-9),
            rotation_sources: vec![],
        };
        let mut sys = FemSystem::new(&desc)?;
        let (mut x, mut v) = (mesh.rest.clone(), vec![V3::zeros(); mesh.rest.len()]);
        let zero = vec![V3::zeros(); x.len()];
        let p = StepParams::default();
        for _ in 0..50 {
            sys.step(&mut x, &mut v, &zero, 0.01, &p)?;
        }
        let n = x.len();
        let fixed = sys.fixed().to_vec();
        for dt in [0.001, 0.01] {
            let blocks = sys.step_matrix(&x, dt, &p)?;
            let mut rows = vec![Vec::new(); n];
            let mut triplets = Vec::with_capacity(blocks.len() * 9);
            for (i, j, b) in &blocks {
                rows[*i].push((*j, *b));
                for r in 0..3 {
                    for c in 0..3 {
                        triplets.push(Triplet::new(3 * i + r, 3 * j + c, b[(r, c)]));
                    }
                }
            }
            // Fixed nodes: identity rows keep the matrix square and positive definite.
            for (i, f) in fixed.iter().enumerate() {
                if *f {
                    rows[i].push((i, Matrix3::identity()));
                    for r in 0..3 {
                        triplets.push(Triplet::new(3 * i + r, 3 * i + r, 1.0));
                    }
                }
            }
            let a = SparseColMat::<usize, f64>::try_new_from_triplets(3 * n, 3 * n, &triplets)?;
            let symbolic = SymbolicLlt::try_new(a.symbolic(), Side::Lower)?;
            let t_symbolic = median_ms(|| drop(SymbolicLlt::try_new(a.symbolic(), Side::Lower)), 5);
            let mut llt = None;
            let t_numeric = median_ms(
                || {
                    llt = Some(Llt::try_new_with_symbolic(
                        symbolic.clone(),
                        a.as_ref(),
                        Side::Lower,
                    ))
                },
                11,
            );
            let llt = llt.expect("ran").map_err(|e| format!("{e:?}"))?;
            // Right-hand side A·u for a known smooth field u.
            let exact: Vec<V3> = (0..n)
                .map(|i| {
                    if fixed[i] {
                        V3::zeros()
                    } else {
                        V3::new(1.0, -0.5, 0.25) * (i as f64 / n as f64)
                    }
                })
                .collect();
            let op = Blocks { rows };
            let mut b = vec![V3::zeros(); n];
            op.apply(&exact, &mut b);
            let mut rhs = Mat::<f64>::zeros(3 * n, 1);
            let t_solve = median_ms(
                || {
                    for i in 0..3 * n {
                        rhs[(i, 0)] = b[i / 3][i % 3];
                    }
                    llt.solve_in_place_with_conj(Conj::No, rhs.as_mut());
                },
                11,
            );
            let direct_err = (0..n)
                .map(|i| {
                    (V3::new(rhs[(3 * i, 0)], rhs[(3 * i + 1, 0)], rhs[(3 * i + 2, 0)]) - exact[i])
                        .norm()
                })
                .fold(0.0, f64::max);
            let cg = |max_iters: usize| {
                let mut xs = vec![V3::zeros(); n];
                pcg(
                    &op,
                    &fixed,
                    &b,
                    &mut xs,
                    &SolverParams {
                        max_iters,
                        tol: 1e-6,
                        warm_start: false,
                    },
                )
            };
            let full = cg(100_000);
            let t_full = median_ms(
                || {
                    let _ = cg(100_000);
                },
                5,
            );
            let budget = cg(50);
            let t_budget = median_ms(
                || {
                    let _ = cg(50);
                },
                11,
            );
            println!(
                "{:>6} {:>5} {:>8} {:>9.2} {:>9.2} {:>8.2} {:>11.2} {:>6} {:>10.2} {:>10.1e}   direct max error {direct_err:.1e}",
                sys.num_elements(),
                dt * 1e3,
                3 * n,
                t_symbolic,
                t_numeric,
                t_solve,
                t_full,
                full.iterations,
                t_budget,
                budget.relative_residual,
            );
        }
    }
    println!(
        "PCG here runs on a generic block-row operator; the engine's symmetric block product is faster"
    );
    Ok(())
}
