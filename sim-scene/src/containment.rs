//! Point-in-mesh queries for many points: [`Containment`] answers [`TriMesh::contains`]
//! from a uniform grid over a closed mesh, evaluating the winding number only where the
//! surface may pass, and there from the few triangles near the point.
//!
//! Why: the engine gives every new tet the material of the region its centroid lies in,
//! by winding number over every triangle of the region's mesh (5,120 on the liver). When
//! the lattice refines under a grasping tool, hundreds of tets appear in one step: on the
//! 1.33 cm organ that step took 65–72 ms, and the refinements every tenth step 7–17 ms,
//! against a 4 ms budget (`cosurg run --cell 0.013333333 --script`, 2026-11-28). Fill
//! weighting asks 20 points of every new tet, many of them near a surface: the default
//! scene's rebuilds took up to 30–38 ms with exact winding numbers in the cells the
//! surface crosses, and take up to 7 ms with the crossings below (one site, the scripted
//! 20 s, three interleaved runs each, 2026-11-29: docs/RESULTS.md).
//!
//! How: a cell that no triangle's bounding box touches holds no part of the surface, and
//! neither does a connected set of such cells, so the winding number of a closed mesh is
//! the same integer everywhere in it. Each such set (the inside, the outside, a cavity)
//! is labelled once by one exact winding number, and a point outside the grid (which
//! covers the mesh's bounding box) is outside. A cell the surface may cross keeps the
//! triangles whose boxes touch it and the winding number at its centre, carried from a
//! neighbour's centre by the signed crossings of the segment between the two centres (the
//! segment lies in the two cells, so only their triangles can cross it). A point in such
//! a cell gets its centre's number plus the signed crossings of the segment from the
//! centre to the point. A segment that passes within rounding of a triangle's edge,
//! corner or plane where it meets it decides nothing: the point (or the cell's centre)
//! then takes the exact winding number over the whole mesh. This holds for closed,
//! consistently oriented meshes (what scene loading accepts); for any other mesh the
//! generalised winding number varies off the surface, and every query is exact.

use nalgebra::Vector3;

use crate::mesh::TriMesh;

type V3 = Vector3<f64>;

/// Cells along the longest side of the mesh's bounding box.
const CELLS_ALONG_LONGEST: f64 = 64.0;

/// A crossing test whose scalar triple products come within this share of the cube of
/// the lengths involved decides nothing (the exact winding number does): about 10⁶ times
/// the rounding of a triple product of f64 differences.
const DEGENERATE: f64 = 1e-10;

/// What a grid cell knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Cell {
    /// A triangle's bounding box touches it: its index in [`Grid::surface`].
    Surface(u32),
    /// No triangle's box touches it: the winding number everywhere in it.
    Free(i32),
}

/// A cell the surface may cross.
#[derive(Clone, Debug)]
struct SurfaceCell {
    /// Its triangles: `Grid::triangles[first..end]`.
    first: u32,
    end: u32,
    /// The winding number at its centre; `None` when no crossing test decided it and the
    /// exact one is not a whole number (the centre lies on the surface): its points are
    /// evaluated exactly.
    centre_winding: Option<i32>,
}

/// A closed mesh with a grid that answers point-in-mesh queries from the few triangles
/// near the point (see the module documentation); [`Containment::contains`] gives the
/// same answers as [`TriMesh::contains`].
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
    surface: Vec<SurfaceCell>,
    /// Triangle indices of the surface cells, cell after cell.
    triangles: Vec<u32>,
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

    /// The triangles of surface cell `k`.
    fn triangles_of(&self, k: u32) -> &[u32] {
        let s = &self.surface[k as usize];
        &self.triangles[s.first as usize..s.end as usize]
    }

    /// Every cell, x fastest.
    fn all_cells(&self) -> impl Iterator<Item = [usize; 3]> + use<> {
        let [nx, ny, nz] = self.dims;
        (0..nz).flat_map(move |z| (0..ny).flat_map(move |y| (0..nx).map(move |x| [x, y, z])))
    }

    /// The 6-neighbours of cell `c`.
    fn neighbours(&self, c: [usize; 3]) -> impl Iterator<Item = [usize; 3]> + '_ {
        (0..3).flat_map(move |ax| {
            [false, true].into_iter().filter_map(move |up| {
                let mut n = c;
                if up {
                    (c[ax] + 1 < self.dims[ax]).then(|| {
                        n[ax] += 1;
                        n
                    })
                } else {
                    (c[ax] > 0).then(|| {
                        n[ax] -= 1;
                        n
                    })
                }
            })
        })
    }
}

/// How the segment `q0 → q1` meets triangle `[a, b, c]` of an outward-oriented mesh:
/// `Some(-1)` when it leaves through it (against its normal: the winding number drops by
/// one), `Some(1)` when it enters, `Some(0)` when it misses, and `None` when it passes
/// within rounding of the triangle's edges, corners or plane where it meets it.
fn signed_crossing(q0: &V3, q1: &V3, [a, b, c]: [V3; 3]) -> Option<i32> {
    let d = q1 - q0;
    let (a0, b0, c0) = (a - q0, b - q0, c - q0);
    let scale = a0.norm().max(b0.norm()).max(c0.norm()).max(d.norm());
    let eps = DEGENERATE * scale * scale * scale;
    // Which side of the triangle's plane each end lies on.
    let n = (b - a).cross(&(c - a));
    let (s0, s1) = (-n.dot(&a0), n.dot(&(q1 - a)));
    if (s0 > eps && s1 > eps) || (s0 < -eps && s1 < -eps) {
        return Some(0);
    }
    // Whether the segment's line passes through the triangle: the three edges seen
    // from the line turn the same way.
    let e = [
        d.dot(&a0.cross(&b0)),
        d.dot(&b0.cross(&c0)),
        d.dot(&c0.cross(&a0)),
    ];
    if e.iter().any(|x| *x > eps) && e.iter().any(|x| *x < -eps) {
        return Some(0); // the line misses the triangle
    }
    if e.iter().any(|x| x.abs() <= eps) || s0.abs() <= eps || s1.abs() <= eps {
        return None; // through an edge or a corner, or an end on the surface
    }
    Some(if s0 < 0.0 { -1 } else { 1 })
}

/// The sum of [`signed_crossing`] over `triangles` of `mesh`; `None` if one is undecided.
fn crossings(mesh: &TriMesh, triangles: &[u32], q0: &V3, q1: &V3) -> Option<i32> {
    triangles.iter().try_fold(0, |sum, &t| {
        let [a, b, c] = mesh.triangles[t as usize].map(|v| mesh.vertices[v as usize]);
        Some(sum + signed_crossing(q0, q1, [a, b, c])?)
    })
}

impl Containment {
    /// The grid for `mesh` (kept); for an empty, open or inconsistently oriented mesh, or
    /// one with a non-finite vertex (no crossing test decides against NaN), no grid.
    pub fn new(mesh: TriMesh) -> Self {
        let finite = mesh
            .vertices
            .iter()
            .all(|v| v.iter().all(|c| c.is_finite()));
        let grid = (finite && mesh.is_closed() && mesh.is_consistently_oriented())
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
        let Some(c) = g.cell_of(p) else {
            return false;
        };
        match g.cells[g.index(c)] {
            Cell::Free(w) => w >= 1,
            Cell::Surface(k) => self
                .near_surface(g, c, k, p)
                .unwrap_or_else(|| self.mesh.contains(p)),
        }
    }

    /// Whether `p`, in surface cell `c` (index `k`), is inside, from its centre's winding
    /// number and the crossings on the way to `p`; `None` when they decide nothing.
    fn near_surface(&self, g: &Grid, c: [usize; 3], k: u32, p: &V3) -> Option<bool> {
        let w = g.surface[k as usize].centre_winding?;
        let across = crossings(&self.mesh, g.triangles_of(k), &g.center(c), p)?;
        Some(w + across >= 1)
    }

    /// Share of the grid's cells the surface may cross (1 without a grid).
    #[cfg(test)]
    fn surface_fraction(&self) -> f64 {
        self.grid
            .as_ref()
            .map_or(1.0, |g| g.surface.len() as f64 / g.cells.len() as f64)
    }

    /// Share of the surface cells whose centre no crossing test decided (1 without a grid).
    #[cfg(test)]
    fn undecided_fraction(&self) -> f64 {
        self.grid.as_ref().map_or(1.0, |g| {
            let undecided = g.surface.iter().filter(|s| s.centre_winding.is_none());
            undecided.count() as f64 / g.surface.len().max(1) as f64
        })
    }
}

/// The winding number of a closed mesh at `p`, when `p` is off the surface (a whole
/// number within rounding).
fn whole_winding(mesh: &TriMesh, p: &V3) -> Option<i32> {
    let w = mesh.winding_number(p);
    ((w - w.round()).abs() < 1e-6).then_some(w.round() as i32)
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
        cells: vec![Cell::Free(0); dims[0] * dims[1] * dims[2]],
        surface: Vec::new(),
        triangles: Vec::new(),
    };
    // Triangle boxes grown by a hair, so that rounding in `cell_of` cannot put a point
    // of the surface in a cell not marked. Each cell a box touches lists the triangle.
    let pad = V3::repeat(1e-9 * longest.max(1e-3));
    let mut lists: Vec<Vec<u32>> = Vec::new();
    for (ti, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = t.map(|v| mesh.vertices[v as usize]);
        let (lo, hi) = (a.inf(&b).inf(&c) - pad, a.sup(&b).sup(&c) + pad);
        let r = g.range(&lo, &hi);
        for z in r[2].0..=r[2].1 {
            for y in r[1].0..=r[1].1 {
                for x in r[0].0..=r[0].1 {
                    let i = g.index([x, y, z]);
                    let k = match g.cells[i] {
                        Cell::Surface(k) => k as usize,
                        Cell::Free(_) => {
                            g.cells[i] = Cell::Surface(lists.len() as u32);
                            lists.push(Vec::new());
                            lists.len() - 1
                        }
                    };
                    lists[k].push(ti as u32);
                }
            }
        }
    }
    for list in &lists {
        let first = g.triangles.len() as u32;
        g.triangles.extend_from_slice(list);
        g.surface.push(SurfaceCell {
            first,
            end: g.triangles.len() as u32,
            centre_winding: None,
        });
    }
    // Label each connected set of surface-free cells (6-neighbours) by one exact
    // winding number at its first cell's centre.
    let mut labelled: Vec<bool> = g
        .cells
        .iter()
        .map(|c| matches!(c, Cell::Surface(_)))
        .collect();
    let mut stack = Vec::new();
    for start in g.all_cells() {
        if labelled[g.index(start)] {
            continue;
        }
        // No triangle's box touches the cell: its centre is off the surface.
        let w = mesh.winding_number(&g.center(start)).round() as i32;
        labelled[g.index(start)] = true;
        stack.push(start);
        while let Some(c) = stack.pop() {
            let i = g.index(c);
            g.cells[i] = Cell::Free(w);
            for n in g.neighbours(c).collect::<Vec<_>>() {
                let j = g.index(n);
                if !labelled[j] {
                    labelled[j] = true;
                    stack.push(n);
                }
            }
        }
    }
    label_surface_centres(mesh, &mut g);
    g
}

/// The winding number at every surface cell's centre, carried from cell to cell by the
/// signed crossings between neighbouring centres, breadth first from the labelled free
/// cells; a centre no crossing test reaches takes the exact winding number.
fn label_surface_centres(mesh: &TriMesh, g: &mut Grid) {
    // Centres known so far: (cell, winding number there), to carry on from.
    let mut frontier: std::collections::VecDeque<([usize; 3], i32)> = g
        .all_cells()
        .filter_map(|c| match g.cells[g.index(c)] {
            Cell::Free(w) => Some((c, w)),
            Cell::Surface(_) => None,
        })
        .filter(|(c, _)| {
            g.neighbours(*c)
                .any(|n| matches!(g.cells[g.index(n)], Cell::Surface(_)))
        })
        .collect();
    let no_triangles: &[u32] = &[];
    while let Some((c, w)) = frontier.pop_front() {
        let from = g.center(c);
        for n in g.neighbours(c).collect::<Vec<_>>() {
            let Cell::Surface(k) = g.cells[g.index(n)] else {
                continue;
            };
            if g.surface[k as usize].centre_winding.is_some() {
                continue;
            }
            // The segment between the centres lies in the two cells.
            let own = match g.cells[g.index(c)] {
                Cell::Surface(j) => g.triangles_of(j),
                Cell::Free(_) => no_triangles,
            };
            // The two cells' triangles, one listed by both counted once.
            let theirs = g.triangles_of(k);
            let both: Vec<u32> = own
                .iter()
                .chain(theirs.iter().filter(|t| !own.contains(t)))
                .copied()
                .collect();
            if let Some(x) = crossings(mesh, &both, &from, &g.center(n)) {
                g.surface[k as usize].centre_winding = Some(w + x);
                frontier.push_back((n, w + x));
            }
        }
    }
    for c in g.all_cells() {
        if let Cell::Surface(k) = g.cells[g.index(c)]
            && g.surface[k as usize].centre_winding.is_none()
        {
            g.surface[k as usize].centre_winding = whole_winding(mesh, &g.center(c));
        }
    }
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
        // Points at surface cells' centres: the segment from the centre has no length.
        let g = c.grid.as_ref().unwrap();
        let surface_centres = (0..g.cells.len())
            .filter(|i| matches!(g.cells[*i], Cell::Surface(_)))
            .step_by(7)
            .map(|i| {
                let (x, yz) = (i % g.dims[0], i / g.dims[0]);
                g.center([x, yz % g.dims[1], yz / g.dims[1]])
            });
        points.extend(surface_centres.collect::<Vec<_>>());
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
        // Near the surface the crossings answer, not the exact winding number: every
        // surface cell's centre is labelled, and nearly every point there is decided
        // (and agrees, above).
        assert_eq!(c.undecided_fraction(), 0.0);
        let g = c.grid.as_ref().unwrap();
        let (mut near, mut decided) = (0, 0);
        for p in &points {
            if let Some(cell) = g.cell_of(p)
                && let Cell::Surface(k) = g.cells[g.index(cell)]
            {
                near += 1;
                if let Some(answer) = c.near_surface(g, cell, k, p) {
                    assert_eq!(answer, mesh.contains(p), "by crossings at {p:?}");
                    decided += 1;
                }
            }
        }
        assert!(near > 500, "{near} points near the surface");
        assert!(
            decided as f64 >= 0.99 * near as f64,
            "{decided} of {near} decided by crossings"
        );
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
