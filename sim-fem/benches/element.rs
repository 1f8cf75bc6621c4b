//! Element force kernels (template / dense / gradient) over a 1,536-tet beam (divide by
//! 1,536 for per element), and one full co-rotational step (linearised backward Euler,
//! Jacobi-PCG, 25 iterations, cold start) on 1,536 and 12,288 tets, matrix-free vs assembled.

use cosurg_sim_fem::mesh::kuhn_box;
use cosurg_sim_fem::{
    FemDesc, FemSystem, Material, Model, OperatorMode, StaticParams, StepParams, StiffnessMode,
};
use nalgebra::Vector3;

type V3 = Vector3<f64>;

fn main() {
    divan::main();
}

fn beam(cells: [usize; 3]) -> (FemSystem, Vec<V3>, Vec<V3>) {
    beam_shared(cells, false)
}

/// `shared`: the 6 tets of each cube use the rotation of the cube's first tet.
fn beam_shared(cells: [usize; 3], shared: bool) -> (FemSystem, Vec<V3>, Vec<V3>) {
    let mesh = kuhn_box(cells, [0.4, 0.1, 0.1], V3::new(0.0, -0.05, -0.05));
    let mut elements = mesh.elements(0);
    let mut sources = Vec::new();
    if shared {
        for (i, e) in elements.iter_mut().enumerate() {
            e.rotation_source = Some(i / 6);
        }
        sources = mesh
            .tets
            .chunks(6)
            .map(|c| cosurg_sim_fem::RotationSourceDesc {
                nodes: c[0],
                rest_inverse_edges: None,
            })
            .collect();
    }
    let mut sys = FemSystem::new(&FemDesc {
        rest: mesh.rest.clone(),
        elements,
        materials: vec![Material {
            rayleigh_mass: 5.0,
            ..Material::new(1e5, 0.45, 1000.0)
        }],
        fixed: mesh.nodes_with_x_at_most(1e-9),
        rotation_sources: sources,
    })
    .unwrap();
    // Deformed state: 20 steps of 10 ms under gravity (and build the dense cache).
    let mut x = mesh.rest.clone();
    let mut v = vec![V3::zeros(); x.len()];
    let zero = vec![V3::zeros(); x.len()];
    let mut x0 = x.clone();
    sys.solve_static(
        Model::Linear,
        &mut x0,
        &zero,
        &StaticParams {
            stiffness: StiffnessMode::Dense,
            ..Default::default()
        },
    )
    .unwrap();
    for _ in 0..20 {
        sys.step(&mut x, &mut v, &zero, 0.01, &StepParams::default())
            .unwrap();
    }
    (sys, x, v)
}

const MODES: [&str; 4] = ["template", "template_sparse", "dense", "gradient"];

fn mode(name: &str) -> StiffnessMode {
    match name {
        "template" => StiffnessMode::Template,
        "template_sparse" => StiffnessMode::TemplateSparse,
        "dense" => StiffnessMode::Dense,
        _ => StiffnessMode::Gradient,
    }
}

#[divan::bench(args = MODES)]
fn corotational_forces_1536(bencher: divan::Bencher, name: &str) {
    let (sys, x, _) = beam([16, 4, 4]);
    let m = mode(name);
    let mut f = vec![V3::zeros(); x.len()];
    bencher.bench_local(|| {
        sys.elastic(
            divan::black_box(&x),
            Model::Corotational,
            m,
            None,
            Some(&mut f),
        )
    });
}

#[divan::bench(args = MODES)]
fn linear_forces_1536(bencher: divan::Bencher, name: &str) {
    let (sys, x, _) = beam([16, 4, 4]);
    let m = mode(name);
    let mut f = vec![V3::zeros(); x.len()];
    bencher.bench_local(|| sys.elastic(divan::black_box(&x), Model::Linear, m, None, Some(&mut f)));
}

fn step_bench(
    bencher: divan::Bencher,
    cells: [usize; 3],
    stiffness: StiffnessMode,
    op: OperatorMode,
) {
    step_bench_shared(bencher, cells, stiffness, op, false);
}

fn step_bench_shared(
    bencher: divan::Bencher,
    cells: [usize; 3],
    stiffness: StiffnessMode,
    op: OperatorMode,
    shared: bool,
) {
    let (mut sys, x, v) = beam_shared(cells, shared);
    let zero = vec![V3::zeros(); x.len()];
    let p = StepParams {
        stiffness,
        operator: op,
        // No warm start: repeating the same step would otherwise start CG at the answer.
        solver: cosurg_sim_fem::SolverParams {
            warm_start: false,
            ..cosurg_sim_fem::SolverParams::realtime()
        },
        ..Default::default()
    };
    {
        let (mut x1, mut v1) = (x.clone(), v.clone());
        let st = sys.step(&mut x1, &mut v1, &zero, 0.01, &p).unwrap();
        eprintln!(
            "{} tets {stiffness:?}/{op:?}: {} CG iterations, rel. residual {:.1e}",
            sys.num_elements(),
            st.cg_iterations,
            st.cg_residual
        );
    }
    bencher
        .with_inputs(|| (x.clone(), v.clone()))
        .bench_local_values(|(mut x, mut v)| sys.step(&mut x, &mut v, &zero, 0.01, &p).unwrap());
}

/// Rotation sharing: one extraction per cube (256) instead of per tet (1,536).
#[divan::bench(sample_count = 30)]
fn step_1536_shared_per_cube(bencher: divan::Bencher) {
    step_bench_shared(
        bencher,
        [16, 4, 4],
        StiffnessMode::Template,
        OperatorMode::Assembled,
        true,
    );
}

#[divan::bench(args = ["template_mf", "dense_mf", "gradient_mf", "template_assembled"], sample_count = 30)]
fn step_1536(bencher: divan::Bencher, variant: &str) {
    let (k, op) = match variant {
        "template_mf" => (StiffnessMode::Template, OperatorMode::MatrixFree),
        "dense_mf" => (StiffnessMode::Dense, OperatorMode::MatrixFree),
        "gradient_mf" => (StiffnessMode::Gradient, OperatorMode::MatrixFree),
        _ => (StiffnessMode::Template, OperatorMode::Assembled),
    };
    step_bench(bencher, [16, 4, 4], k, op);
}

#[divan::bench(args = ["template_mf", "gradient_mf", "template_assembled"], sample_count = 8)]
fn step_12288(bencher: divan::Bencher, variant: &str) {
    let (k, op) = match variant {
        "template_mf" => (StiffnessMode::Template, OperatorMode::MatrixFree),
        "gradient_mf" => (StiffnessMode::Gradient, OperatorMode::MatrixFree),
        _ => (StiffnessMode::Template, OperatorMode::Assembled),
    };
    step_bench(bencher, [32, 8, 8], k, op);
}
