//! Shared test helpers: Kuhn-split beams and cubes.
#![allow(dead_code)]

use cosurg_sim_fem::mesh::{BoxMesh, kuhn_box};
use cosurg_sim_fem::{FemDesc, FemSystem, Material};
use nalgebra::Vector3;

pub type V3 = Vector3<f64>;

/// Beam 0.4 × 0.1 × 0.1 m along x, centred on y = z = 0, clamped at x = 0.
pub fn beam(cells: [usize; 3], mat: Material, clamp: bool) -> (BoxMesh, FemSystem) {
    let mesh = kuhn_box(cells, [0.4, 0.1, 0.1], V3::new(0.0, -0.05, -0.05));
    let fixed = if clamp {
        mesh.nodes_with_x_at_most(1e-9)
    } else {
        vec![false; mesh.rest.len()]
    };
    let desc = FemDesc {
        rest: mesh.rest.clone(),
        elements: mesh.elements(0),
        materials: vec![mat],
        fixed,
        rotation_sources: vec![],
    };
    let sys = FemSystem::new(&desc).expect("valid beam");
    (mesh, sys)
}

pub fn norm(f: &[V3]) -> f64 {
    f.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt()
}

/// Nodes on the tip face x = 0.4 m.
pub fn tip_nodes(mesh: &BoxMesh) -> Vec<usize> {
    (0..mesh.rest.len())
        .filter(|&i| (mesh.rest[i].x - 0.4).abs() < 1e-9)
        .collect()
}

/// Total force `p` (N) spread over the tip face with bilinear area weights.
pub fn tip_load(mesh: &BoxMesh, p: V3) -> Vec<V3> {
    let [nx, ny, nz] = mesh.cells;
    let mut f = vec![V3::zeros(); mesh.rest.len()];
    let w = 1.0 / (4.0 * (ny * nz) as f64);
    for j in 0..ny {
        for k in 0..nz {
            for (dj, dk) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                f[mesh.node(nx, j + dj, k + dk)] += p * w;
            }
        }
    }
    f
}

/// Mean displacement of the tip face.
pub fn tip_displacement(mesh: &BoxMesh, x: &[V3]) -> V3 {
    let t = tip_nodes(mesh);
    t.iter().map(|&i| x[i] - mesh.rest[i]).sum::<V3>() / t.len() as f64
}
