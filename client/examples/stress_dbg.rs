use cosurg::bench::stress::inclusion_beam;
use nalgebra::Vector3;
use sim_core::{SimOptions, Simulation, sim_fem::Model};
fn main() {
    let dt: f64 = std::env::args().nth(1).unwrap().parse().unwrap();
    let share: f64 = std::env::args().nth(2).unwrap().parse().unwrap();
    let scene = inclusion_beam(0.05).unwrap();
    let mut o = SimOptions::from_scene(&scene.scene);
    o.model = Model::Corotational;
    if let Ok(n) = std::env::var("CG") {
        o.solver.max_iters = n.parse().unwrap();
    }
    if let Ok(a) = std::env::var("FB") {
        o.fallback_angle_deg = a.parse().unwrap();
    }
    o.dt = dt;
    o.sharing_angle_deg = (share > 0.0).then_some(share);
    let mut sim = Simulation::new(scene, o).unwrap();
    let nodes: Vec<_> = sim.lattice().nodes().collect();
    let tip: Vec<_> = nodes
        .iter()
        .copied()
        .filter(|n| sim.lattice().node_rest(*n).x > 0.4 - 1e-9)
        .collect();
    let inj = (1.5 / dt).round() as usize;
    for k in 0..(inj + 3000) {
        if k < inj {
            let s = ((k + 1) as f64 * dt / 1.0).min(1.0);
            for &n in &tip {
                let r = sim.lattice().node_rest(n);
                sim.prescribe(n, Vector3::new(r.x + s * (-0.2 - r.x), r.y, r.z));
            }
        }
        let rep = sim.step().unwrap();
        let vmax = sim
            .velocities()
            .iter()
            .map(|v| v.norm())
            .fold(0.0, f64::max);
        let e = sim.energy().unwrap();
        if k % 100 == 0 || (k >= inj && k < inj + 10) {
            println!(
                "{k} vmax {vmax:.4e} E {e:.4e} inv {} cg {} res {:.2e} shared {}",
                rep.fem.inverted, rep.fem.cg_iterations, rep.fem.cg_residual, rep.shared_rotations
            );
        }
    }
}
