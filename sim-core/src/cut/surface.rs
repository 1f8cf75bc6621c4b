//! Cutting a closed embedded surface along a [`Sheet`] and capping the cut.
//!
//! Every surface edge the sheet crosses (exact decision, [`Sheet::crossing`]) gets two new
//! vertices at the crossing, one for each end's side; a triangle with two crossed edges is
//! split into its lone corner's triangle and the other side's quad (two triangles), each
//! using its side's vertices. The holes this opens are closed loops of boundary edges;
//! each loop is capped by ear-clipping it in the plane of its Newell normal, with the
//! orientation that makes the cap's edges the loop's edges reversed, so every part stays
//! closed (each edge shared by exactly two triangles) and outward oriented. A side's new
//! vertices sit a hair (1e-4 of the edge) off the sheet towards their own end, so that
//! the exact side test of the embedding puts them in their own side's element copy.
//!
//! A sheet that ends inside a triangle (a partial cut: one crossed edge) cannot be capped
//! this way; [`cut_surface`] then reports it and the caller keeps the uncut surface.

use std::collections::{BTreeMap, HashMap};

use nalgebra::{Vector2, Vector3};
use sim_scene::TriMesh;

use super::sheet::Sheet;

type V3 = Vector3<f64>;

/// Offset of a side's cut vertex from the crossing towards its own end, as a fraction of
/// the edge.
const SIDE_OFFSET: f64 = 1e-4;

/// Why a surface could not be cut.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SurfaceCutError {
    /// The sheet ends inside the surface (a triangle with one or three crossed edges).
    #[error("the cut ends inside {triangles} surface triangle(s) (a partial cut)")]
    Partial {
        /// Triangles with one or three crossed edges.
        triangles: usize,
    },
    /// A boundary loop of the cut could not be closed or triangulated.
    #[error("a cut boundary could not be capped: {0}")]
    Cap(String),
}

/// What [`cut_surface`] made.
#[derive(Clone, Debug)]
pub struct CutSurface {
    /// The cut and capped mesh (rest coordinates).
    pub mesh: TriMesh,
    /// Triangles of the caps (the last `cap_triangles` of `mesh.triangles`).
    pub cap_triangles: usize,
    /// Boundary loops capped.
    pub loops: usize,
}

/// Cuts `mesh` along `sheet` and caps the cut; `Ok` with the mesh unchanged (no loop) if
/// the sheet does not cross it.
pub fn cut_surface(mesh: &TriMesh, sheet: &Sheet) -> Result<CutSurface, SurfaceCutError> {
    let v = &mesh.vertices;
    let mut crossing: HashMap<(u32, u32), f64> = HashMap::new();
    let key = |a: u32, b: u32| (a.min(b), a.max(b));
    for t in &mesh.triangles {
        for e in 0..3 {
            let (a, b) = key(t[e], t[(e + 1) % 3]);
            if crossing.contains_key(&(a, b)) {
                continue;
            }
            if let Some(s) = sheet.crossing(&v[a as usize], &v[b as usize]) {
                crossing.insert((a, b), s);
            }
        }
    }
    if crossing.is_empty() {
        return Ok(CutSurface {
            mesh: mesh.clone(),
            cap_triangles: 0,
            loops: 0,
        });
    }
    let mut vertices = v.clone();
    // The cut vertex on edge (a, b) belonging to `end`'s side.
    let mut cut_vertex: BTreeMap<((u32, u32), u32), u32> = BTreeMap::new();
    let mut side_vertex = |a: u32, b: u32, end: u32, vertices: &mut Vec<V3>| -> u32 {
        let k = key(a, b);
        *cut_vertex.entry((k, end)).or_insert_with(|| {
            let s = crossing[&k];
            let (pa, pb) = (v[k.0 as usize], v[k.1 as usize]);
            let p = pa + s * (pb - pa);
            let toward = v[end as usize];
            vertices.push(p + SIDE_OFFSET * (toward - p));
            (vertices.len() - 1) as u32
        })
    };
    let mut triangles = Vec::with_capacity(mesh.triangles.len() + 2 * crossing.len());
    let mut partial = 0usize;
    for t in &mesh.triangles {
        let cut: Vec<usize> = (0..3)
            .filter(|&e| crossing.contains_key(&key(t[e], t[(e + 1) % 3])))
            .collect();
        match cut.len() {
            0 => triangles.push(*t),
            2 => {
                // The lone corner is the one both crossed edges share.
                let lone = (0..3)
                    .find(|&c| cut.contains(&c) && cut.contains(&((c + 2) % 3)))
                    .expect("two crossed edges share a corner");
                let (a, b, c) = (t[lone], t[(lone + 1) % 3], t[(lone + 2) % 3]);
                let ab_a = side_vertex(a, b, a, &mut vertices);
                let ac_a = side_vertex(a, c, a, &mut vertices);
                let ab_b = side_vertex(a, b, b, &mut vertices);
                let ac_c = side_vertex(a, c, c, &mut vertices);
                triangles.push([a, ab_a, ac_a]);
                triangles.push([ab_b, b, c]);
                triangles.push([ab_b, c, ac_c]);
            }
            _ => partial += 1,
        }
    }
    if partial > 0 {
        return Err(SurfaceCutError::Partial { triangles: partial });
    }
    let body = triangles.len();
    let loops = boundary_loops(&triangles).map_err(SurfaceCutError::Cap)?;
    for l in &loops {
        let reversed: Vec<u32> = l.iter().rev().copied().collect();
        triangles.extend(ear_clip(&vertices, &reversed).map_err(SurfaceCutError::Cap)?);
    }
    Ok(CutSurface {
        cap_triangles: triangles.len() - body,
        loops: loops.len(),
        mesh: TriMesh {
            vertices,
            triangles,
        },
    })
}

/// Loops of directed boundary edges (edges whose reverse no triangle has), each in edge
/// order, starting at its smallest vertex.
fn boundary_loops(triangles: &[[u32; 3]]) -> Result<Vec<Vec<u32>>, String> {
    let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
    for t in triangles {
        for e in 0..3 {
            *directed.entry((t[e], t[(e + 1) % 3])).or_default() += 1;
        }
    }
    let mut next: BTreeMap<u32, u32> = BTreeMap::new();
    for (&(a, b), &n) in &directed {
        if n > 1 {
            return Err(format!("edge {a}-{b} used {n} times in one direction"));
        }
        if !directed.contains_key(&(b, a)) && next.insert(a, b).is_some() {
            return Err(format!("vertex {a} starts two boundary edges"));
        }
    }
    let mut loops = Vec::new();
    while let Some((&start, _)) = next.iter().next() {
        let mut l = vec![start];
        let mut cur = next.remove(&start).expect("present");
        while cur != start {
            l.push(cur);
            cur = next
                .remove(&cur)
                .ok_or_else(|| format!("boundary chain through vertex {cur} does not close"))?;
        }
        loops.push(l);
    }
    Ok(loops)
}

/// Triangulates a closed 3D polygon (nearly planar) by ear clipping in the plane of its
/// Newell normal; the triangles keep the polygon's orientation.
pub(crate) fn ear_clip(vertices: &[V3], polygon: &[u32]) -> Result<Vec<[u32; 3]>, String> {
    let n = polygon.len();
    if n < 3 {
        return Err(format!("a loop of {n} vertices"));
    }
    let mut normal = V3::zeros();
    for i in 0..n {
        let (p, q) = (
            vertices[polygon[i] as usize],
            vertices[polygon[(i + 1) % n] as usize],
        );
        normal += (p - q).cross(&(p + q)) * 0.5;
        // Newell: sum over edges of (y_i - y_j)(z_i + z_j), ...: equal to the above / 2.
    }
    let normal = normal
        .try_normalize(0.0)
        .ok_or_else(|| "a loop with zero area".to_string())?;
    // In-plane axes (u, w) with u × w = normal, so the polygon is counter-clockwise.
    let helper = if normal.x.abs() < 0.9 {
        V3::x()
    } else {
        V3::y()
    };
    let u = helper.cross(&normal).normalize();
    let w = normal.cross(&u);
    let p2: Vec<Vector2<f64>> = polygon
        .iter()
        .map(|&i| {
            let p = vertices[i as usize];
            Vector2::new(p.dot(&u), p.dot(&w))
        })
        .collect();
    let cross = |a: Vector2<f64>, b: Vector2<f64>, c: Vector2<f64>| (b - a).perp(&(c - a));
    let mut idx: Vec<usize> = (0..n).collect();
    let mut out = Vec::with_capacity(n - 2);
    while idx.len() > 3 {
        let m = idx.len();
        let mut best: Option<(usize, f64)> = None;
        for k in 0..m {
            let (a, b, c) = (idx[(k + m - 1) % m], idx[k], idx[(k + 1) % m]);
            let area = cross(p2[a], p2[b], p2[c]);
            if area <= 0.0 {
                continue;
            }
            let blocked = idx.iter().any(|&o| {
                o != a
                    && o != b
                    && o != c
                    && cross(p2[a], p2[b], p2[o]) >= 0.0
                    && cross(p2[b], p2[c], p2[o]) >= 0.0
                    && cross(p2[c], p2[a], p2[o]) >= 0.0
            });
            if blocked {
                continue;
            }
            // Prefer the best-shaped ear (largest minimum angle proxy: area / longest²).
            let longest = [(a, b), (b, c), (c, a)]
                .iter()
                .map(|&(i, j)| (p2[i] - p2[j]).norm_squared())
                .fold(0.0, f64::max);
            let quality = area / longest;
            if best.is_none_or(|(_, q)| quality > q) {
                best = Some((k, quality));
            }
        }
        let (k, _) = best.ok_or_else(|| "no ear found (self-intersecting loop)".to_string())?;
        let (a, b, c) = (idx[(k + m - 1) % m], idx[k], idx[(k + 1) % m]);
        out.push([polygon[a], polygon[b], polygon[c]]);
        idx.remove(k);
    }
    out.push([polygon[idx[0]], polygon[idx[1]], polygon[idx[2]]]);
    Ok(out)
}
