//! Which cube cells a closed triangle surface needs.
//!
//! A cell is kept when
//! * it contains a surface vertex (so every vertex lies in a kept tet), or
//! * a triangle overlaps the closed cube (separating-axis test), or
//! * a point near its centre is inside the surface.
//!
//! A cube that overlaps the interior either has its centre inside or is crossed by the
//! surface, so the kept cubes cover the enclosed volume. Inside/outside is decided by ray
//! parity along +x, majority of three rays jittered off the cell centre so that rays
//! almost surely miss triangle edges and vertices; rows of cells share a ray, so the cost
//! is O(rows · triangles per row) rather than O(cells · triangles).

use std::collections::HashSet;

use nalgebra::{Vector2, Vector3};

use crate::{LatticeError, LatticeParams};

/// Offsets (in cells) of the three rays of a row from the row's centre line.
const RAY_JITTER: [(f64, f64); 3] = [
    (0.012_345_7, 0.009_876_5),
    (-0.021_357_9, 0.017_171_3),
    (0.007_713_1, -0.018_932_7),
];

pub(crate) fn cells_covering(
    params: &LatticeParams,
    vertices: &[Vector3<f64>],
    triangles: &[[u32; 3]],
) -> Result<Vec<[i32; 3]>, LatticeError> {
    if !(params.cell.is_finite() && params.cell > 0.0) {
        return Err(LatticeError::InvalidParams(format!(
            "cell size must be positive and finite, got {}",
            params.cell
        )));
    }
    if vertices.is_empty() || triangles.is_empty() {
        return Err(LatticeError::InvalidSurface(
            "no vertices or no triangles".into(),
        ));
    }
    if let Some(i) = vertices
        .iter()
        .position(|v| !v.iter().all(|c| c.is_finite()))
    {
        return Err(LatticeError::InvalidSurface(format!(
            "vertex {i} is not finite"
        )));
    }
    if let Some(i) = triangles
        .iter()
        .position(|t| t.iter().any(|&v| v as usize >= vertices.len()))
    {
        return Err(LatticeError::InvalidSurface(format!(
            "triangle {i} references a vertex out of range ({} vertices)",
            vertices.len()
        )));
    }
    // Work in cell units: cell [i, j, k] is the unit cube at (i, j, k).
    let g: Vec<Vector3<f64>> = vertices
        .iter()
        .map(|v| (v - params.origin) / params.cell)
        .collect();
    let mut lo = g[0];
    let mut hi = g[0];
    for p in &g {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    let span = hi - lo;
    if span.iter().any(|&s| s > f64::from(1u32 << 20)) {
        return Err(LatticeError::InvalidSurface(format!(
            "surface spans {span:?} cells; choose a larger cell"
        )));
    }
    let cell_of = |p: &Vector3<f64>| [p.x.floor() as i32, p.y.floor() as i32, p.z.floor() as i32];
    let lo_c = cell_of(&lo);
    let hi_c = cell_of(&hi);

    let mut keep: HashSet<[i32; 3]> = g.iter().map(cell_of).collect();

    // Cubes crossed by a triangle.
    for t in triangles {
        let [a, b, c] = t.map(|i| g[i as usize]);
        let tlo = cell_of(&a.inf(&b).inf(&c));
        let thi = cell_of(&a.sup(&b).sup(&c));
        for k in tlo[2]..=thi[2] {
            for j in tlo[1]..=thi[1] {
                for i in tlo[0]..=thi[0] {
                    let centre =
                        Vector3::new(f64::from(i), f64::from(j), f64::from(k)).add_scalar(0.5);
                    if triangle_overlaps_box(&(a - centre), &(b - centre), &(c - centre), 0.5) {
                        keep.insert([i, j, k]);
                    }
                }
            }
        }
    }

    // Cubes with an inside point near the centre: one ray (three, jittered) per row.
    let ny = (hi_c[1] - lo_c[1] + 1) as usize;
    let nz = (hi_c[2] - lo_c[2] + 1) as usize;
    let mut rows: Vec<Vec<u32>> = vec![Vec::new(); ny * nz];
    for (ti, t) in triangles.iter().enumerate() {
        let [a, b, c] = t.map(|i| g[i as usize]);
        let tlo = cell_of(&a.inf(&b).inf(&c));
        let thi = cell_of(&a.sup(&b).sup(&c));
        for k in tlo[2]..=thi[2] {
            for j in tlo[1]..=thi[1] {
                rows[(k - lo_c[2]) as usize * ny + (j - lo_c[1]) as usize].push(ti as u32);
            }
        }
    }
    let mut crossings: [Vec<f64>; 3] = Default::default();
    for k in lo_c[2]..=hi_c[2] {
        for j in lo_c[1]..=hi_c[1] {
            let row = &rows[(k - lo_c[2]) as usize * ny + (j - lo_c[1]) as usize];
            if row.is_empty() {
                continue;
            }
            for (xs, (dy, dz)) in crossings.iter_mut().zip(RAY_JITTER) {
                xs.clear();
                let p = Vector2::new(f64::from(j) + 0.5 + dy, f64::from(k) + 0.5 + dz);
                for &ti in row {
                    let [a, b, c] = triangles[ti as usize].map(|i| g[i as usize]);
                    if let Some(x) = ray_x_crossing(&p, &a, &b, &c) {
                        xs.push(x);
                    }
                }
                xs.sort_unstable_by(f64::total_cmp);
            }
            for i in lo_c[0]..=hi_c[0] {
                let x = f64::from(i) + 0.5;
                let votes = crossings
                    .iter()
                    .filter(|xs| xs.partition_point(|&c| c < x) % 2 == 1)
                    .count();
                if votes >= 2 {
                    keep.insert([i, j, k]);
                }
            }
        }
    }
    let mut cells: Vec<[i32; 3]> = keep.into_iter().collect();
    // Deterministic root order (z-major, then y, then x).
    cells.sort_unstable_by_key(|c| [c[2], c[1], c[0]]);
    tracing::debug!(
        cells = cells.len(),
        triangles = triangles.len(),
        "cells covering surface"
    );
    Ok(cells)
}

/// x where the line `{(x, p.x, p.y)}` (p given in (y, z)) crosses triangle `abc`, if it
/// passes strictly inside the triangle's yz projection.
fn ray_x_crossing(
    p: &Vector2<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    c: &Vector3<f64>,
) -> Option<f64> {
    let yz = |v: &Vector3<f64>| Vector2::new(v.y, v.z);
    let (a2, b2, c2) = (yz(a), yz(b), yz(c));
    let cross = |u: Vector2<f64>, v: Vector2<f64>| u.x * v.y - u.y * v.x;
    let wa = cross(c2 - b2, p - b2);
    let wb = cross(a2 - c2, p - c2);
    let wc = cross(b2 - a2, p - a2);
    let inside = (wa > 0.0 && wb > 0.0 && wc > 0.0) || (wa < 0.0 && wb < 0.0 && wc < 0.0);
    if !inside {
        return None;
    }
    let area = wa + wb + wc;
    Some((wa * a.x + wb * b.x + wc * c.x) / area)
}

/// Separating-axis test of a triangle (relative to the box centre) against the cube of
/// half-size `h` (Akenine-Möller 2001), with a tiny margin so touching counts as overlap.
fn triangle_overlaps_box(a: &Vector3<f64>, b: &Vector3<f64>, c: &Vector3<f64>, h: f64) -> bool {
    let h = h * (1.0 + 1e-9);
    let separated = |axis: &Vector3<f64>| {
        let (pa, pb, pc) = (axis.dot(a), axis.dot(b), axis.dot(c));
        let r = h * (axis.x.abs() + axis.y.abs() + axis.z.abs());
        pa.min(pb).min(pc) > r || pa.max(pb).max(pc) < -r
    };
    let edges = [b - a, c - b, a - c];
    for e in &edges {
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            let ax = e.cross(&axis);
            if ax.norm_squared() > 0.0 && separated(&ax) {
                return false;
            }
        }
    }
    for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
        if separated(&axis) {
            return false;
        }
    }
    !separated(&edges[0].cross(&edges[1]))
}
