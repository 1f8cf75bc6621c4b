//! One element's 3×3 blocks of `R K Rᵀ` as assembly adds them, and a per-element cache of
//! them for steps that keep most rotations.
//!
//! Why the cache: with rotation sharing (the default scenes, θ_tol = 5°) or at rest, most
//! elements keep their rotation from one step to the next, bit for bit, yet assembly
//! rotated every element's blocks again. `callgrind` (2026-11-27) put these rotations at
//! 21 % of a step's instructions on the 5,184-tet beam at dt 1 ms (the 1 kHz row of
//! `cosurg bench cantilever`) and at 14 % of a site's step on the default organ. A cached
//! element's blocks are those the same function computed from the same rotation, volume
//! and material, so a cached assembly gives the same bits as a fresh one (sites stay
//! identical whatever their cache holds).

use nalgebra::Matrix3;

use super::V3;
use crate::element::Mat12;

/// The 10 blocks `(a, b)`, `a ≤ b`, of a symmetric 12×12 element matrix, in the order
/// of [`UPPER`]; block `(b, a)` is block `(a, b)` transposed.
pub(super) type UpperBlocks = [Matrix3<f64>; 10];

/// Index into [`UpperBlocks`] of block `(a, b)` (either order).
pub(super) const UPPER: [[usize; 4]; 4] = [[0, 1, 2, 3], [1, 4, 5, 6], [2, 5, 7, 8], [3, 6, 8, 9]];

/// Block `(a, b)` of an element matrix stored as [`UpperBlocks`] (the tests read them
/// so; assembly adds them through [`scatter_blocks`]).
#[cfg(test)]
pub(super) fn block(u: &UpperBlocks, a: usize, b: usize) -> Matrix3<f64> {
    let m = u[UPPER[a][b]];
    if a <= b { m } else { m.transpose() }
}

/// The upper blocks of `R K Rᵀ` for a symmetric 12×12 `K` (`r = None`: `K` itself).
pub(super) fn rotated_blocks(k: &Mat12, r: Option<&Matrix3<f64>>) -> UpperBlocks {
    let mut out = [Matrix3::zeros(); 10];
    for a in 0..4 {
        for b in a..4 {
            let kab: Matrix3<f64> = k.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
            out[UPPER[a][b]] = match r {
                Some(r) => r * kab * r.transpose(),
                None => kab,
            };
        }
    }
    out
}

/// The upper blocks of `R K Rᵀ` of an isotropic linear tet straight from its
/// shape-function gradients `g` (1/m) and volume `v` (m³): `K_ab = v [λ g_a g_bᵀ + μ g_b
/// g_aᵀ + μ (g_a·g_b) I]`, so with `r_a = R g_a` a rotated block is `(vλ r_a) r_bᵀ + (vμ
/// r_b) r_aᵀ + vμ (g_a·g_b) I`: four rotated vectors and two outer products per block,
/// about a third of the flops of rotating each block of `K`.
pub(super) fn rotated_iso_blocks(
    g: &[V3; 4],
    v: f64,
    lambda: f64,
    mu: f64,
    r: Option<&Matrix3<f64>>,
    out: &mut UpperBlocks,
) {
    let rg = match r {
        Some(r) => [r * g[0], r * g[1], r * g[2], r * g[3]],
        None => *g,
    };
    let (vl, vm) = (v * lambda, v * mu);
    let l = rg.map(|x| x * vl);
    let m = rg.map(|x| x * vm);
    for a in 0..4 {
        for b in a..4 {
            let (la, mb, ra, rb) = (&l[a], &m[b], &rg[a], &rg[b]);
            let mut blk = if a == b {
                // (vλ + vμ) r_a r_aᵀ: exactly symmetric, as the diagonal blocks of a
                // symmetric matrix must be (the products read them whole).
                let s = vl + vm;
                let (x, y, z) = (ra.x, ra.y, ra.z);
                let (xy, xz, yz) = (x * y * s, x * z * s, y * z * s);
                Matrix3::new(x * x * s, xy, xz, xy, y * y * s, yz, xz, yz, z * z * s)
            } else {
                // Column j: l_a (r_b)_j + m_b (r_a)_j.
                Matrix3::from_columns(&[
                    la * rb.x + mb * ra.x,
                    la * rb.y + mb * ra.y,
                    la * rb.z + mb * ra.z,
                ])
            };
            let d = vm * g[a].dot(&g[b]);
            blk[(0, 0)] += d;
            blk[(1, 1)] += d;
            blk[(2, 2)] += d;
            out[UPPER[a][b]] = blk;
        }
    }
}

/// `blocks[slots[4a + b]] += c · block(a, b)` for the blocks of one element whose bit
/// `4a + b` is set in `mask` (all 16, or those the symmetric storage keeps).
#[inline]
pub(super) fn scatter_blocks(
    blocks: &mut [Matrix3<f64>],
    slots: &[u32; 16],
    mask: u16,
    local: &UpperBlocks,
    c: f64,
) {
    for (i, (s, &(k, transposed))) in slots.iter().zip(&FULL).enumerate() {
        if mask & (1 << i) == 0 {
            continue;
        }
        let (out, m) = (&mut blocks[*s as usize], &local[k]);
        if transposed {
            // Block (a, b) = block (b, a)ᵀ, read transposed in place.
            for col in 0..3 {
                for row in 0..3 {
                    out[(row, col)] += m[(col, row)] * c;
                }
            }
        } else {
            *out += m * c;
        }
    }
}

/// Block `4a + b` of the full 4×4 as ([`UPPER`] index, whether it is transposed).
const FULL: [(usize, bool); 16] = {
    let mut t = [(0, false); 16];
    let mut i = 0;
    while i < 16 {
        let (a, b) = (i / 4, i % 4);
        t[i] = (UPPER[a][b], a > b);
        i += 1;
    }
    t
};

/// One element's rotated blocks and what they were computed from.
#[derive(Clone, Debug)]
pub(super) struct CachedBlocks {
    /// The rotation the blocks were computed with (NaN: nothing cached).
    rotation: Matrix3<f64>,
    /// The volume the blocks were scaled by (m³; the element's own, or per unit size
    /// with template stiffness; NaN: nothing cached, and no element's volume has these
    /// bits).
    volume: f64,
    blocks: UpperBlocks,
}

impl Default for CachedBlocks {
    fn default() -> Self {
        Self {
            rotation: Matrix3::from_element(f64::NAN),
            volume: f64::NAN,
            blocks: [Matrix3::zeros(); 10],
        }
    }
}

fn same_bits(a: &Matrix3<f64>, b: &Matrix3<f64>) -> bool {
    a.iter()
        .zip(b.iter())
        .all(|(x, y)| x.to_bits() == y.to_bits())
}

impl CachedBlocks {
    /// The blocks last computed ([`CachedBlocks::rotated_iso`]'s).
    #[inline]
    pub(super) fn blocks(&self) -> &UpperBlocks {
        &self.blocks
    }
    /// [`rotated_iso_blocks`] of an element with rotation `r`, from the cache when it
    /// holds them for the same rotation and volume (bit for bit), else computed and kept.
    /// An element's gradients and material never change (a topology change builds a new
    /// system).
    #[inline]
    pub(super) fn rotated_iso(
        &mut self,
        g: &[V3; 4],
        v: f64,
        lambda: f64,
        mu: f64,
        r: &Matrix3<f64>,
    ) -> &UpperBlocks {
        if !(same_bits(&self.rotation, r) && self.volume.to_bits() == v.to_bits()) {
            rotated_iso_blocks(g, v, lambda, mu, Some(r), &mut self.blocks);
            self.rotation = *r;
            self.volume = v;
        }
        &self.blocks
    }
}

/// Whether a step where `changed` of `elements` elements use a rotation extracted anew
/// should assemble through the per-element cache: when at most half of them did. A cache
/// that mostly misses costs a comparison and a copy per element for nothing (on the
/// 5,184-tet beam at dt 1 ms with rotation sharing, whose shared rotations are extracted
/// every step, it missed on nearly every element); it is allocated (800 bytes per
/// element) on the first step it pays, and kept.
pub(super) fn cache_pays(changed: usize, elements: usize) -> bool {
    2 * changed <= elements
}
