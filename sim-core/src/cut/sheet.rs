//! The union of every cut's swept triangles, in rest coordinates, with bounding boxes so
//! that an edge is only tested against the triangles near it.

use nalgebra::Vector3;

use super::predicates;

type V3 = Vector3<f64>;

/// Triangles of all applied cuts (rest coordinates, m), in canonical op order.
#[derive(Clone, Debug, Default)]
pub struct Sheet {
    tris: Vec<[V3; 3]>,
    boxes: Vec<(V3, V3)>,
    lo: V3,
    hi: V3,
}

impl Sheet {
    /// A sheet from triangles (degenerate ones must have been rejected by the caller).
    pub fn new(tris: Vec<[V3; 3]>) -> Self {
        let mut lo = V3::repeat(f64::INFINITY);
        let mut hi = V3::repeat(f64::NEG_INFINITY);
        let boxes: Vec<(V3, V3)> = tris
            .iter()
            .map(|t| {
                let l = t[0].inf(&t[1]).inf(&t[2]);
                let h = t[0].sup(&t[1]).sup(&t[2]);
                lo = lo.inf(&l);
                hi = hi.sup(&h);
                (l, h)
            })
            .collect();
        Sheet {
            tris,
            boxes,
            lo,
            hi,
        }
    }

    /// Whether there is no triangle.
    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// The triangles.
    pub fn triangles(&self) -> &[[V3; 3]] {
        &self.tris
    }

    /// Whether the box `lo..hi` overlaps the sheet's bounding box.
    pub fn overlaps_box(&self, lo: &V3, hi: &V3) -> bool {
        !self.is_empty() && (0..3).all(|k| lo[k] <= self.hi[k] && hi[k] >= self.lo[k])
    }

    /// Indices of the triangles whose boxes overlap `lo..hi`.
    fn near<'a>(&'a self, lo: &'a V3, hi: &'a V3) -> impl Iterator<Item = usize> + 'a {
        self.boxes
            .iter()
            .enumerate()
            .filter(move |(_, (l, h))| (0..3).all(|k| lo[k] <= h[k] && hi[k] >= l[k]))
            .map(|(i, _)| i)
    }

    /// The first triangle (in canonical order) that the segment `a → b` crosses, and the
    /// crossing parameter along it (exact decision, see [`predicates`]).
    pub fn crossing(&self, a: &V3, b: &V3) -> Option<f64> {
        let (lo, hi) = (a.inf(b), a.sup(b));
        if !self.overlaps_box(&lo, &hi) {
            return None;
        }
        self.near(&lo, &hi)
            .find_map(|i| predicates::segment_crossing(&self.tris[i], a, b))
    }

    /// Whether the tetrahedron with corners `p` may touch the sheet (conservative: a
    /// triangle whose box overlaps the tet's and whose plane does not have all four
    /// corners strictly on one side).
    pub fn may_touch_tet(&self, p: &[V3; 4]) -> bool {
        let lo = p[0].inf(&p[1]).inf(&p[2]).inf(&p[3]);
        let hi = p[0].sup(&p[1]).sup(&p[2]).sup(&p[3]);
        if !self.overlaps_box(&lo, &hi) {
            return false;
        }
        self.near(&lo, &hi).any(|i| {
            let t = &self.tris[i];
            let o: Vec<f64> = p
                .iter()
                .map(|q| predicates::orient3d(&t[0], &t[1], &t[2], q))
                .collect();
            !(o.iter().all(|v| *v > 0.0) || o.iter().all(|v| *v < 0.0))
        })
    }
}
