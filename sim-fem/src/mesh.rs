//! Structured test meshes: a box of cubes, each split into 6 Kuhn tetrahedra around the
//! cube's main diagonal (same numbering as the peer script `../shared/peers/beam.py`,
//! relative to the project). Used by tests, benchmarks and as an example of the arrays
//! sim-core passes in.

use nalgebra::Vector3;

use crate::system::{ElementDesc, ShapeRef};

/// A Kuhn-split box mesh.
#[derive(Clone, Debug)]
pub struct BoxMesh {
    /// Cells per axis.
    pub cells: [usize; 3],
    /// Cell size per axis (m).
    pub spacing: [f64; 3],
    /// Rest node positions (m).
    pub rest: Vec<Vector3<f64>>,
    /// Positively oriented tets.
    pub tets: Vec<[usize; 4]>,
    /// Shape key per tet (permutation index × 2 + orientation swap).
    pub shape_keys: Vec<u64>,
}

impl BoxMesh {
    /// Node index of grid point (i, j, k), x slowest.
    pub fn node(&self, i: usize, j: usize, k: usize) -> usize {
        let [_, ny, nz] = self.cells;
        (i * (ny + 1) + j) * (nz + 1) + k
    }

    /// Element descriptions with one material; shape keys only when cells are cubes.
    pub fn elements(&self, material: usize) -> Vec<ElementDesc> {
        let [hx, hy, hz] = self.spacing;
        let cubic = (hx - hy).abs() <= 1e-12 * hx && (hx - hz).abs() <= 1e-12 * hx;
        self.tets
            .iter()
            .zip(&self.shape_keys)
            .map(|(t, &key)| ElementDesc {
                nodes: *t,
                material,
                shape: cubic.then_some(ShapeRef { key, scale: hx }),
                rotation_source: None,
            })
            .collect()
    }

    /// Nodes with x ≤ `x_max` (e.g. a clamped end).
    pub fn nodes_with_x_at_most(&self, x_max: f64) -> Vec<bool> {
        self.rest.iter().map(|p| p.x <= x_max).collect()
    }
}

const PERMS: [[usize; 3]; 6] = [
    [0, 1, 2],
    [0, 2, 1],
    [1, 0, 2],
    [1, 2, 0],
    [2, 0, 1],
    [2, 1, 0],
];

/// Box `[origin, origin + size]` of `cells` cubes (or boxes), each split into 6 tets that
/// share the main diagonal (0,0,0)–(1,1,1) of the cell.
pub fn kuhn_box(cells: [usize; 3], size: [f64; 3], origin: Vector3<f64>) -> BoxMesh {
    let [nx, ny, nz] = cells;
    let spacing = [
        size[0] / nx as f64,
        size[1] / ny as f64,
        size[2] / nz as f64,
    ];
    let mut rest = Vec::with_capacity((nx + 1) * (ny + 1) * (nz + 1));
    for i in 0..=nx {
        for j in 0..=ny {
            for k in 0..=nz {
                rest.push(
                    origin
                        + Vector3::new(
                            i as f64 * spacing[0],
                            j as f64 * spacing[1],
                            k as f64 * spacing[2],
                        ),
                );
            }
        }
    }
    let mut mesh = BoxMesh {
        cells,
        spacing,
        rest,
        tets: Vec::with_capacity(6 * nx * ny * nz),
        shape_keys: Vec::with_capacity(6 * nx * ny * nz),
    };
    for i in 0..nx {
        for j in 0..ny {
            for k in 0..nz {
                for (pi, p) in PERMS.iter().enumerate() {
                    let mut c = [0usize; 3];
                    let mut t = [0usize; 4];
                    t[0] = mesh.node(i, j, k);
                    for (s, &ax) in p.iter().enumerate() {
                        c[ax] += 1;
                        t[s + 1] = mesh.node(i + c[0], j + c[1], k + c[2]);
                    }
                    let x = |n: usize| mesh.rest[n];
                    let vol = (x(t[1]) - x(t[0]))
                        .cross(&(x(t[2]) - x(t[0])))
                        .dot(&(x(t[3]) - x(t[0])));
                    let mut key = 2 * pi as u64;
                    if vol < 0.0 {
                        t.swap(2, 3);
                        key += 1;
                    }
                    mesh.tets.push(t);
                    mesh.shape_keys.push(key);
                }
            }
        }
    }
    mesh
}
