//! The beam and its regions shared by the sync tests (`sync.rs`, `hybrid.rs`).
// Each test crate uses a part of this module.
#![allow(dead_code)]

use cosurg_sim_core::sync::{RegionId, RegionMap};
use cosurg_sim_core::{NodeId, SimOptions, Simulation};
use nalgebra::Vector3;

pub type V3 = Vector3<f64>;

/// The cantilever (0.4 × 0.1 × 0.1 m, clamped at x = 0) with 5 cm cells: 8 × 2 × 2 cells;
/// with 2-cell blocks 4 regions along x, the tip region is 3. Stiffer than the shipped
/// beam and mass-damped so that it settles within a second.
pub fn beam() -> Simulation {
    let mut scene = sim_scene::builtin::cantilever();
    scene
        .modify(|sc| {
            for m in sc.materials.values_mut() {
                m.young = 5e5;
                m.rayleigh_mass = 10.0;
            }
            for b in &mut sc.bodies {
                b.cell = 0.05;
            }
        })
        .unwrap();
    let opts = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, opts).unwrap()
}

pub const TIP: RegionId = 3;

pub fn beam_map(sim: &Simulation) -> RegionMap {
    let map = RegionMap::new(sim.lattice(), 2);
    assert_eq!(map.len(), 4);
    assert_eq!(map.block_of(TIP), Some([3, 0, 0]));
    map
}

/// Live nodes of the tip region with rest x above `x`.
pub fn tip_nodes(sim: &Simulation, map: &RegionMap, x: f64) -> Vec<NodeId> {
    map.canonical_nodes(sim.lattice(), TIP)
        .into_iter()
        .filter(|&n| sim.lattice().node_rest(n).x > x)
        .collect()
}
