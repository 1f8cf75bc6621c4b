//! Point-in-mesh queries for many points: [`Containment`] answers [`TriMesh::contains`]
//! from a uniform grid over a closed mesh, evaluating the winding number only where the
//! surface may pass.
//!
//! Why: the engine gives every new tet the material of the region its centroid lies in,
//! by winding number over every triangle of the region's mesh (5,120 on the liver). When
//! the lattice refines under a grasping tool, hundreds of tets appear in one step: on the
//! 1.33 cm organ that step took 65–72 ms, and the refinements every tenth step 7–17 ms,
//! against a 4 ms budget (`cosurg run --cell 0.013333333 --script`, 2026-11-28).
//!
//! How: a cell that no triangle's bounding box touches holds no part of the surface, and
//! neither does a connected set of such cells, so the winding number of a closed mesh is
//! the same integer everywhere in it. Each such set (the inside, the outside, a cavity)
//! is labelled once by one exact winding number; a point in one of its cells gets that
//! label, a point in a cell the surface may cross gets its own exact winding number, and a
//! point outside the grid (which covers the mesh's bounding box) is outside. This holds
//! for closed, consistently oriented meshes (what scene loading accepts); for any other
//! mesh the generalised winding number varies off the surface, and every query is exact.

use nalgebra::Vector3;

use crate::mesh::TriMesh;

type V3 = Vector3<f64>;

/// Cells along the longest side of the mesh's bounding box.
const CELLS_ALONG_LONGEST: f64 = 64.0;

/// What a grid cell knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Cell {
    /// A triangle's bounding box touches it: evaluate exactly.
    Surface,
    Inside,
    Outside,
}

/// A closed mesh with a grid that answers most point-in-mesh queries without the winding
/// number (see the module documentation); [`Containment::contains`] gives the same
/// answers as [`TriMesh::contains`].
#[derive(Clone, Debug)]
pub struct Containment {
    mesh: TriMesh,
    /// `None`: no grid (the mesh is empty, not closed or not consistently oriented);
    /// every query is exact.
    grid: Option<Grid>,
}

#[derive(Clone, Debug)]
struct Grid {
    /// Lower corner of cell (0, 0, 0) (m).
    origin: V3,
    /// Cell side (m).
    cell: f64,
    dims: [usize; 3],
    cells: Vec<Cell>,
}

impl Grid {
    fn index(&self, c: [usize; 3]) -> usize {
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// The cell holding `p`, if `p` is in the grid.
    fn cell_of(&self, p: &V3) -> Option<[usize; 3]> {
        let mut c = [0; 3];
        for ax in 0..3 {
            let f = ((p[ax] - self.origin[ax]) / self.cell).floor();
            if !(f >= 0.0 && f < self.dims[ax] as f64) {
                return None; // outside, or NaN
            }
            c[ax] = f as usize;
        }
        Some(c)
    }

    fn center(&self, c: [usize; 3]) -> V3 {
        V3::from_fn(|ax, _| self.origin[ax] + (c[ax] as f64 + 0.5) * self.cell)
    }

    /// Cells (inclusive ranges per axis) that the box `[lo, hi]` touches, clamped.
    fn range(&self, lo: &V3, hi: &V3) -> [(usize, usize); 3] {
        std::array::from_fn(|ax| {
            let at = |x: f64| {
                (((x - self.origin[ax]) / self.cell).floor()).clamp(0.0, (self.dims[ax] - 1) as f64)
                    as usize
            };
            (at(lo[ax]), at(hi[ax]))
        })
    }
}

impl Containment {
    /// The grid for `mesh` (kept); for an empty, open or inconsistently oriented mesh, no
    /// grid.
    pub fn new(mesh: TriMesh) -> Self {
        let grid = (mesh.is_closed() && mesh.is_consistently_oriented())
            .then(|| mesh.bounding_box())
            .flatten()
            .map(|bb| build_grid(&mesh, bb.min, bb.max));
        Self { mesh, grid }
    }

    /// True when `p` is inside the mesh, as [`TriMesh::contains`] says.
    pub fn contains(&self, p: &V3) -> bool {
        let Some(g) = &self.grid else {
            return self.mesh.contains(p);
        };
        match g.cell_of(p).map(|c| g.cells[g.index(c)]) {
            None | Some(Cell::Outside) => false,
            Some(Cell::Inside) => true,
            Some(Cell::Surface) => self.mesh.contains(p),
        }
    }

    /// Share of the grid's cells that need the exact winding number (1 without a grid).
    #[cfg(test)]
    fn surface_fraction(&self) -> f64 {
        self.grid.as_ref().map_or(1.0, |g| {
            g.cells.iter().filter(|c| **c == Cell::Surface).count() as f64 / g.cells.len() as f64
        })
    }
}

fn build_grid(mesh: &TriMesh, min: V3, max: V3) -> Grid {
    let extent = max - min;
    let longest = extent.max();
    let cell = if longest > 0.0 {
        longest / CELLS_ALONG_LONGEST
    } else {
        1e-3
    };
    // One cell of margin on every side, so that the grid covers the bounding box with
    // room to spare (a surface on the box's faces marks the margin's cells too, which
    // may split the outside into several sets: each is labelled, only the count grows).
    let origin = min - V3::repeat(cell);
    let dims: [usize; 3] = std::array::from_fn(|ax| (extent[ax] / cell).ceil() as usize + 3);
    let mut g = Grid {
        origin,
        cell,
        dims,
        cells: vec![Cell::Outside; dims[0] * dims[1] * dims[2]],
    };
    // Triangle boxes grown by a hair, so that rounding in `cell_of` cannot put a point
    // of the surface in a cell not marked.
    let pad = V3::repeat(1e-9 * longest.max(1e-3));
    let mut labelled = vec![false; g.cells.len()];
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|v| mesh.vertices[v as usize]);
        let (lo, hi) = (a.inf(&b).inf(&c) - pad, a.sup(&b).sup(&c) + pad);
        let r = g.range(&lo, &hi);
        for z in r[2].0..=r[2].1 {
            for y in r[1].0..=r[1].1 {
                for x in r[0].0..=r[0].1 {
                    let i = g.index([x, y, z]);
                    g.cells[i] = Cell::Surface;
                    labelled[i] = true;
                }
            }
        }
    }
    // Label each connected set of surface-free cells (6-neighbours) by one exact
    // winding number at its first cell's centre.
    let mut stack = Vec::new();
    for z in 0..dims[2] {
        for y in 0..dims[1] {
            for x in 0..dims[0] {
                let start = g.index([x, y, z]);
                if labelled[start] {
                    continue;
                }
                let label = if mesh.contains(&g.center([x, y, z])) {
                    Cell::Inside
                } else {
                    Cell::Outside
                };
                labelled[start] = true;
                stack.push([x, y, z]);
                while let Some(c) = stack.pop() {
                    let i = g.index(c);
                    g.cells[i] = label;
                    for ax in 0..3 {
                        for up in [false, true] {
                            let mut n = c;
                            if up {
                                if c[ax] + 1 >= dims[ax] {
                                    continue;
                                }
                                n[ax] += 1;
                            } else {
                                if c[ax] == 0 {
                                    continue;
                                }
                                n[ax] -= 1;
                            }
                            let j = g.index(n);
                            if !labelled[j] {
                                labelled[j] = true;
                                stack.push(n);
                            }
                        }
                    }
                }
            }
        }
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn organ_mesh(name: &str) -> TriMesh {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../scenes/meshes/bodies")
            .join(name);
        TriMesh::load(&path).expect("the default scene's meshes")
    }

    /// Random points in and around the bounding box, and points just off the surface
    /// (each vertex moved a little along and against its normal): the grid's answers
    /// against the exact winding number's.
    fn agrees_with_the_winding_number(mesh: TriMesh, seed: u64) {
        let c = Containment::new(mesh.clone());
        assert!(c.grid.is_some(), "a closed mesh gets a grid");
        let bb = mesh.bounding_box().unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let size = bb.max - bb.min;
        let mut points: Vec<V3> = (0..4000)
            .map(|_| V3::from_fn(|ax, _| bb.min[ax] + size[ax] * rng.random_range(-0.1..1.1)))
            .collect();
        for (v, n) in mesh.vertices.iter().zip(mesh.vertex_normals()).step_by(3) {
            for d in [-1e-3, -1e-5, 1e-5, 1e-3] {
                points.push(v + n * d * size.max());
            }
        }
        let (mut inside, mut outside) = (0, 0);
        for p in &points {
            let want = mesh.contains(p);
            assert_eq!(c.contains(p), want, "at {p:?}");
            if want {
                inside += 1;
            } else {
                outside += 1;
            }
        }
        // The sample exercises both answers, and most cells need no winding number.
        assert!(inside > 100 && outside > 100, "{inside} in, {outside} out");
        assert!(c.surface_fraction() < 0.5, "{}", c.surface_fraction());
    }

    #[test]
    fn the_grid_answers_as_the_winding_number_on_the_organ_meshes() {
        for (i, name) in ["liver.obj", "gallbladder.obj", "cystic_duct.obj"]
            .iter()
            .enumerate()
        {
            agrees_with_the_winding_number(organ_mesh(name), i as u64);
        }
    }

    /// A box `[lo, hi]³` as 12 triangles, outward (or inward when `inward`).
    fn cube(lo: f64, hi: f64, inward: bool) -> TriMesh {
        let mut m = crate::mesh::tests::cube();
        for v in &mut m.vertices {
            *v = v.map(|c| lo + c * (hi - lo));
        }
        if inward {
            m.flip();
        }
        m
    }

    fn join(a: &TriMesh, b: &TriMesh) -> TriMesh {
        let n = a.vertices.len() as u32;
        TriMesh {
            vertices: a.vertices.iter().chain(&b.vertices).copied().collect(),
            triangles: a
                .triangles
                .iter()
                .copied()
                .chain(b.triangles.iter().map(|t| t.map(|v| v + n)))
                .collect(),
        }
    }

    /// Every point of a lattice through and around `mesh`'s box, on and between cell
    /// corners: the grid's answers against the winding number's; returns how many were
    /// inside.
    fn agrees_on_a_lattice(mesh: &TriMesh) -> usize {
        let c = Containment::new(mesh.clone());
        assert!(c.grid.is_some());
        let bb = mesh.bounding_box().unwrap();
        let mut inside = 0;
        for i in -3..=43 {
            for j in -3..=43 {
                for k in [-2, 0, 7, 20, 21, 33, 40, 42] {
                    let f = |n: i32, ax: usize| {
                        bb.min[ax] + (bb.max[ax] - bb.min[ax]) * f64::from(n) / 40.0
                    };
                    let p = V3::new(f(i, 0), f(j, 1), f(k, 2));
                    let want = mesh.contains(&p);
                    assert_eq!(c.contains(&p), want, "at {p:?}");
                    inside += usize::from(want);
                }
            }
        }
        inside
    }

    #[test]
    fn cavities_and_separate_shells_are_labelled_apart() {
        // A box with an inward-facing box inside it (a hollow shell), and two separate
        // boxes: the cavity and the gap between the boxes are outside.
        let hollow = join(&cube(0.0, 1.0, false), &cube(0.3, 0.7, true));
        let inside = agrees_on_a_lattice(&hollow);
        assert!(inside > 0);
        assert!(!Containment::new(hollow.clone()).contains(&V3::repeat(0.5)));
        assert!(Containment::new(hollow).contains(&V3::new(0.15, 0.5, 0.5)));
        let two = join(&cube(0.0, 0.4, false), &cube(0.6, 1.0, false));
        assert!(agrees_on_a_lattice(&two) > 0);
        assert!(!Containment::new(two).contains(&V3::repeat(0.5)));
    }

    #[test]
    fn a_mesh_with_a_flipped_triangle_gets_no_grid() {
        // Closed, but its winding number is no longer a whole number off the surface, so
        // one label per set of cells would be wrong: every query is exact.
        let mut m = cube(0.0, 1.0, false);
        m.triangles[0].swap(1, 2);
        assert!(m.is_closed() && !m.is_consistently_oriented());
        let c = Containment::new(m.clone());
        assert!(c.grid.is_none());
        for p in [
            V3::new(0.2, 0.8, 0.03),
            V3::repeat(0.5),
            V3::new(0.2, 0.8, -0.03),
        ] {
            assert_eq!(c.contains(&p), m.contains(&p));
        }
    }

    #[test]
    fn an_open_mesh_is_evaluated_exactly_and_far_points_are_outside() {
        let mut open = organ_mesh("gallbladder.obj");
        open.triangles.truncate(open.triangles.len() - 10);
        let c = Containment::new(open.clone());
        assert!(c.grid.is_none());
        let p = open.vertices.iter().sum::<V3>() / open.vertices.len() as f64;
        assert_eq!(c.contains(&p), open.contains(&p));
        let closed = Containment::new(organ_mesh("gallbladder.obj"));
        assert!(!closed.contains(&V3::new(10.0, 0.0, 0.0)));
        assert!(!closed.contains(&V3::new(f64::NAN, 0.0, 0.0)));
    }
}
