//! CG's sparse product on the cantilever beams' Kuhn lattices (5,184 and 12,288 tets): the
//! symmetric upper-stored product (in place, scalar; and copied into contiguous rows,
//! vectorised: `solver/upper_product.rs`) against the full-row one (`solver/full_product.rs`,
//! vectorised with AVX where the CPU has it), and the per-step copy into full rows that the
//! full-row product needs. A step makes one copy and one product per CG iteration.

use cosurg_sim_fem::mesh::kuhn_box;
use cosurg_sim_fem::solver::{BlockPattern, RowBlock};
use divan::Bencher;
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

type V3 = Vector3<f64>;

fn main() {
    divan::main();
}

/// Cells of the 0.4 × 0.1 × 0.1 m beam: 5,184, 12,288 and 98,304 tets.
const CELLS: [[usize; 3]; 3] = [[24, 6, 6], [32, 8, 8], [64, 16, 16]];

/// The beam's pattern, random upper blocks (diagonally dominant) and a random vector.
fn setup(cells: [usize; 3]) -> (BlockPattern, Vec<Matrix3<f64>>, Vec<V3>) {
    let mesh = kuhn_box(cells, [0.4, 0.1, 0.1], V3::zeros());
    let n = mesh.rest.len();
    let pat = BlockPattern::new(n, &mesh.tets);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut upper = vec![Matrix3::zeros(); pat.num_blocks()];
    for i in 0..n {
        for (s, j) in pat.row(i) {
            if j >= i {
                upper[s] = Matrix3::from_fn(|_, _| rng.random_range(-1.0..1.0));
                if j == i {
                    upper[s] = upper[s] + upper[s].transpose() + Matrix3::identity() * 40.0;
                }
            }
        }
    }
    let p = (0..n)
        .map(|_| V3::from_fn(|_, _| rng.random_range(-1.0..1.0)))
        .collect();
    (pat, upper, p)
}

#[divan::bench(args = CELLS)]
fn upper_product(bencher: Bencher, cells: [usize; 3]) {
    let (pat, upper, p) = setup(cells);
    let mut out = vec![V3::zeros(); p.len()];
    bencher.bench_local(|| pat.multiply_upper(&upper, &p, &mut out));
}

#[divan::bench(args = CELLS)]
fn upper_rows_product(bencher: Bencher, cells: [usize; 3]) {
    let (pat, upper, p) = setup(cells);
    let mut rows = cosurg_sim_fem::solver::UpperRows::default();
    rows.copy_from(&pat, &upper);
    let mut out = vec![V3::zeros(); p.len()];
    bencher.bench_local(|| rows.multiply(&pat, &p, &mut out));
}

#[divan::bench(args = CELLS)]
fn copy_into_upper_rows(bencher: Bencher, cells: [usize; 3]) {
    let (pat, upper, _) = setup(cells);
    let mut rows = cosurg_sim_fem::solver::UpperRows::default();
    rows.copy_from(&pat, &upper);
    bencher.bench_local(|| rows.copy_from(&pat, &upper));
}

#[divan::bench(args = CELLS)]
fn full_row_product(bencher: Bencher, cells: [usize; 3]) {
    let (pat, upper, p) = setup(cells);
    let full = pat.full_rows(&upper);
    let mut out = vec![V3::zeros(); p.len()];
    bencher.bench_local(|| pat.multiply_full(&full, &p, &mut out));
}

#[divan::bench(args = CELLS)]
fn copy_into_full_rows(bencher: Bencher, cells: [usize; 3]) {
    let (pat, upper, _) = setup(cells);
    let mut full: Vec<RowBlock> = pat.full_rows(&upper);
    bencher.bench_local(|| pat.full_rows_into(&upper, &mut full));
}
