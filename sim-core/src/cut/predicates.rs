//! Exact geometric predicates for the decisions every site must repeat identically.
//!
//! Every topological decision of a cut (which lattice edge a sheet crosses, which side of
//! a sheet a point lies on, which surface edge is split) goes through [`orient3d`], the
//! adaptive-precision orientation test of the `robust` crate (Shewchuk's predicates): its
//! sign is exact for the given `f64` inputs, so it does not depend on evaluation order,
//! FMA contraction or the machine. A point exactly on a sheet's plane counts as lying on
//! its positive side (where `orient3d` > 0: below a triangle that is counter-clockwise
//! seen from above) (a fixed tie-break, so a lattice node on a sheet belongs to one side
//! and no edge is cut "twice"). Only intersection *points* (where the sheet crosses an
//! edge) are computed in floating point, after the exact decision.

use nalgebra::Vector3;
use robust::Coord3D;

type V3 = Vector3<f64>;

fn c(p: &V3) -> Coord3D<f64> {
    Coord3D {
        x: p.x,
        y: p.y,
        z: p.z,
    }
}

/// Exact sign (and adaptive magnitude) of the orientation of `d` relative to the plane
/// through `a, b, c`: positive when `d` lies below the plane of `a, b, c` seen
/// counter-clockwise from above; proportional to the signed volume of the tetrahedron.
pub fn orient3d(a: &V3, b: &V3, c3: &V3, d: &V3) -> f64 {
    robust::orient3d(c(a), c(b), c(c3), c(d))
}

/// Which side of the plane of `tri` `p` lies on (`true`: positive or on the plane).
pub fn side(tri: &[V3; 3], p: &V3) -> bool {
    orient3d(&tri[0], &tri[1], &tri[2], p) >= 0.0
}

/// Whether triangle `tri` has a non-zero area (decided exactly: some coordinate-plane
/// projection has a non-zero exact 2D orientation).
pub fn non_degenerate(tri: &[V3; 3]) -> bool {
    let proj = |k: usize, l: usize| {
        let p = |v: &V3| robust::Coord { x: v[k], y: v[l] };
        robust::orient2d(p(&tri[0]), p(&tri[1]), p(&tri[2])) != 0.0
    };
    proj(0, 1) || proj(1, 2) || proj(2, 0)
}

/// If the segment `a → b` crosses the (closed) triangle `tri` with its ends on strictly
/// different sides (ties as in [`side`]), the crossing parameter `t ∈ [0, 1]` along
/// `a → b` (floating point; the decision itself is exact).
pub fn segment_crossing(tri: &[V3; 3], a: &V3, b: &V3) -> Option<f64> {
    let oa = orient3d(&tri[0], &tri[1], &tri[2], a);
    let ob = orient3d(&tri[0], &tri[1], &tri[2], b);
    if (oa >= 0.0) == (ob >= 0.0) {
        return None;
    }
    // The line a-b passes through the closed triangle iff the three orientations of the
    // triangle's edges seen along the line agree in sign.
    let s0 = orient3d(a, b, &tri[0], &tri[1]);
    let s1 = orient3d(a, b, &tri[1], &tri[2]);
    let s2 = orient3d(a, b, &tri[2], &tri[0]);
    let all_nonneg = s0 >= 0.0 && s1 >= 0.0 && s2 >= 0.0;
    let all_nonpos = s0 <= 0.0 && s1 <= 0.0 && s2 <= 0.0;
    if !(all_nonneg || all_nonpos) {
        return None;
    }
    Some((oa / (oa - ob)).clamp(0.0, 1.0))
}
