//! Exact integer predicates on the dyadic grid.

/// A point or vector in integer grid units.
pub(crate) type Grid = [i64; 3];

#[inline]
pub(crate) fn sub(a: Grid, b: Grid) -> Grid {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn add(a: Grid, b: Grid) -> Grid {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
pub(crate) fn scale(a: Grid, s: i64) -> Grid {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// `det[a; b; c]` (rows), exact.
#[inline]
pub(crate) fn det3(a: Grid, b: Grid, c: Grid) -> i128 {
    let [a0, a1, a2] = a.map(i128::from);
    let [b0, b1, b2] = b.map(i128::from);
    let [c0, c1, c2] = c.map(i128::from);
    a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
}

/// Six times the signed volume of `(a, b, c, d)`; positive when `d − a` lies on the side of
/// `(b − a) × (c − a)`.
#[inline]
pub(crate) fn orient(a: Grid, b: Grid, c: Grid, d: Grid) -> i128 {
    det3(sub(b, a), sub(c, a), sub(d, a))
}

/// Sign of [`orient`] for the symbolically perturbed point `p + ε d₀ + ε² d₁ + …`:
/// the first non-zero of `orient(a, b, c, p)` and the plane normal's products with the
/// perturbation directions.
#[inline]
pub(crate) fn orient_perturbed(a: Grid, b: Grid, c: Grid, p: Grid, dirs: &[Grid]) -> i32 {
    let u = sub(b, a);
    let v = sub(c, a);
    let s = det3(u, v, sub(p, a));
    if s != 0 {
        return s.signum() as i32;
    }
    for &d in dirs {
        let s = det3(u, v, d);
        if s != 0 {
            return s.signum() as i32;
        }
    }
    0
}

/// Midpoint of two grid points whose coordinate sums are even (guaranteed by the choice
/// of grid units per cell).
#[inline]
pub(crate) fn midpoint(a: Grid, b: Grid) -> Grid {
    debug_assert!(
        (0..3).all(|i| (a[i] + b[i]) % 2 == 0),
        "midpoint off the grid"
    );
    [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2, (a[2] + b[2]) / 2]
}

/// The three axis unit vectors; a final tie-breaker for perturbed predicates.
pub(crate) const AXES: [Grid; 3] = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
