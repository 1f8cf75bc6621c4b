//! The cholecystectomy with separate bodies (`scenes/cholecystectomy-bodies.toml`): the
//! gallbladder held by the bed's attachment layer; released, it hangs from its duct and
//! artery only.

use std::path::PathBuf;

use cosurg_sim_core::cut::{OpId, ReleaseOp, TopologyOp};
use cosurg_sim_core::sim_scene::Scene;
use cosurg_sim_core::{SimOptions, Simulation};
use nalgebra::Vector3;

type V3 = Vector3<f64>;

fn bodies_scene() -> Simulation {
    let path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../scenes/cholecystectomy-bodies.toml");
    let scene = Scene::load(&path).expect("scenes/cholecystectomy-bodies.toml loads");
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options).expect("simulation")
}

fn centroid(sim: &Simulation, body: usize) -> V3 {
    let s = &sim.surfaces()[body];
    s.deformed.iter().sum::<V3>() / s.deformed.len() as f64
}

#[test]
fn explore() {
    let mut sim = bodies_scene();
    let l = &sim.attachments().layers[0];
    eprintln!(
        "springs {} leaves {} nodes {}",
        l.springs.len(),
        sim.lattice().leaf_count(),
        sim.lattice().node_count()
    );
    let lens: Vec<f64> = l.springs.iter().map(|s| s.rest_length).collect();
    eprintln!(
        "len min {:?} max {:?}",
        lens.iter().cloned().fold(1.0, f64::min),
        lens.iter().cloned().fold(0.0, f64::max)
    );
    let mass: f64 = sim.fem().unwrap().lumped_mass().iter().sum();
    eprintln!("mass {mass}");
    let mut free = bodies_scene();
    let n = free.attachments().layers[0].springs.len() as u32;
    free.apply_topology_op(TopologyOp::Release(ReleaseOp {
        id: OpId { site: 0, seq: 0 },
        layer: 0,
        springs: (0..n).collect(),
    }))
    .unwrap();
    let c0 = centroid(&sim, 1);
    let t = std::time::Instant::now();
    for i in 0..1000 {
        sim.step().unwrap();
        free.step().unwrap();
        if i % 100 == 99 {
            eprintln!(
                "t {:.2} tied drop {:.4} free drop {:.4} free duct {:.4}",
                sim.time(),
                c0.z - centroid(&sim, 1).z,
                c0.z - centroid(&free, 1).z,
                centroid(&free, 2).z
            );
        }
    }
    eprintln!("{:?}", t.elapsed());
}

#[test]
fn explore_script() {
    use cosurg_sim_core::Interaction;
    let mut sim = bodies_scene();
    let mut inter = Interaction::new(&sim);
    let c0 = centroid(&sim, 1);
    let t = std::time::Instant::now();
    let mut released = 0;
    let mut cuts = 0;
    for i in 0..6000 {
        let inputs = inter.scripted_inputs(&sim, sim.time());
        let r = inter.before_step(&mut sim, &inputs).unwrap();
        released += r.released;
        cuts += r.cuts;
        sim.step().unwrap();
        if i % 250 == 249 {
            eprintln!(
                "t {:.2} drop {:.4} released {} cuts {} grasped {} holding {} epoch {} leaves {}",
                sim.time(),
                c0.z - centroid(&sim, 1).z,
                released,
                cuts,
                r.grasped,
                sim.attachments().layers[0].holding(),
                sim.topology().epoch(),
                sim.lattice().leaf_count()
            );
        }
    }
    eprintln!("{:?}", t.elapsed());
}
