//! Symmetric 3×3-block CSR (upper triangle stored) for the coarse levels, the masking
//! of a prolongation by the fixed nodes, and the Galerkin product `Pᵀ A P` split into a
//! symbolic plan (built once per hierarchy) and a numeric pass (every refresh).

use nalgebra::Matrix3;

use super::Prolongation;

/// Structure of a symmetric block matrix storing the blocks on and above the diagonal;
/// each row starts with its diagonal block.
#[derive(Clone, Debug, Default)]
pub(super) struct UpperCsr {
    pub row_ptr: Vec<usize>,
    pub cols: Vec<u32>,
}

impl UpperCsr {
    pub fn num_rows(&self) -> usize {
        self.row_ptr.len() - 1
    }

    /// The dense symmetric matrix (3n × 3n), for the coarsest direct solve.
    pub fn to_dense(&self, blocks: &[Matrix3<f64>]) -> nalgebra::DMatrix<f64> {
        let n = self.num_rows();
        let mut m = nalgebra::DMatrix::zeros(3 * n, 3 * n);
        for i in 0..n {
            let (a, b) = (self.row_ptr[i], self.row_ptr[i + 1]);
            for (blk, &j) in blocks[a..b].iter().zip(&self.cols[a..b]) {
                let j = j as usize;
                m.fixed_view_mut::<3, 3>(3 * i, 3 * j).copy_from(blk);
                if j != i {
                    m.fixed_view_mut::<3, 3>(3 * j, 3 * i)
                        .copy_from(&blk.transpose());
                }
            }
        }
        m
    }
}

/// A prolongation restricted to the free nodes: rows of fixed fine nodes emptied, and the
/// coarse nodes renumbered to those kept (not the weight-1 image of a fixed fine node, and
/// interpolated from by at least one free fine node). The fine level may itself have been
/// renumbered by the masking above it: its node `i` is `p`'s row `orig_index[i]`, and
/// `fine_free[i]` says whether it is free. Returns the masked prolongation and the kept
/// coarse nodes' indices in `p`'s coarse numbering (the next level's `orig_index`).
pub(super) fn mask_prolongation(
    p: &Prolongation,
    orig_index: &[usize],
    fine_free: &[bool],
) -> (Prolongation, Vec<usize>) {
    debug_assert_eq!(orig_index.len(), fine_free.len());
    let nc = p.coarse_len();
    let mut image_of_fixed = vec![false; nc];
    let mut used = vec![false; nc];
    // Reading `p`'s rows by this level's own index `i` instead kept coarse nodes that no
    // kept node interpolates from (zero rows, a singular coarsest matrix).
    for (&orig, &free) in orig_index.iter().zip(fine_free) {
        let mut row = p.row(orig);
        match (row.next(), row.next()) {
            (Some((c, w)), None) if !free && w == 1.0 => image_of_fixed[c] = true,
            _ => {}
        }
        if free {
            for (c, _) in p.row(orig) {
                used[c] = true;
            }
        }
    }
    let keep: Vec<bool> = (0..nc).map(|c| used[c] && !image_of_fixed[c]).collect();
    let mut new_index = vec![usize::MAX; nc];
    let mut kept = Vec::new();
    for c in 0..nc {
        if keep[c] {
            new_index[c] = kept.len();
            kept.push(c);
        }
    }
    // Rows: the fine level's own rows (`orig_index` maps its numbering to `p`'s).
    let rows: Vec<Vec<(usize, f64)>> = orig_index
        .iter()
        .enumerate()
        .map(|(i, &orig)| {
            if !fine_free[i] {
                return Vec::new();
            }
            p.row(orig)
                .filter(|(c, _)| keep[*c])
                .map(|(c, w)| (new_index[c], w))
                .collect()
        })
        .collect();
    let masked = Prolongation::from_rows(kept.len(), &rows).expect("columns renumbered in range");
    (masked, kept)
}

/// One term of the Galerkin product: `coarse[dst] += w · fine[src]` (transposed if `t`).
#[derive(Clone, Copy, Debug)]
struct Term {
    src: u32,
    dst: u32,
    w: f64,
    t: bool,
}

/// `Pᵀ A P` for a fixed `P` and fixed upper structure of `A`: the coarse structure and the
/// list of terms.
#[derive(Clone, Debug, Default)]
pub(super) struct GalerkinPlan {
    pub coarse: UpperCsr,
    terms: Vec<Term>,
}

impl GalerkinPlan {
    /// `upper` lists the fine matrix's stored blocks as `(row, column, slot)` with
    /// `row ≤ column`.
    pub fn new(p: &Prolongation, upper: &[(usize, usize, usize)]) -> Self {
        let nc = p.coarse_len();
        let mut rows: Vec<Vec<u32>> = (0..nc).map(|a| vec![a as u32]).collect();
        let visit = |f: &mut dyn FnMut(usize, usize, usize, f64, bool)| {
            for &(i, j, slot) in upper {
                for (a, wa) in p.row(i) {
                    for (b, wb) in p.row(j) {
                        let w = wa * wb;
                        if i == j {
                            // A symmetric diagonal block: (a, b) and (b, a) are one
                            // stored block.
                            if a <= b {
                                f(a, b, slot, w, false);
                            }
                        } else if a == b {
                            // (i, j) and its mirror (j, i) both land on (a, a).
                            f(a, a, slot, w, false);
                            f(a, a, slot, w, true);
                        } else if a < b {
                            f(a, b, slot, w, false);
                        } else {
                            f(b, a, slot, w, true);
                        }
                    }
                }
            }
        };
        visit(&mut |a, b, _, _, _| rows[a].push(b as u32));
        let mut coarse = UpperCsr {
            row_ptr: vec![0],
            cols: Vec::new(),
        };
        for r in &mut rows {
            // The diagonal (pushed first) is the smallest column: it stays first.
            r.sort_unstable();
            r.dedup();
            coarse.cols.extend_from_slice(r);
            coarse.row_ptr.push(coarse.cols.len());
        }
        let mut terms = Vec::new();
        visit(&mut |a, b, slot, w, t| {
            let s = &coarse.cols[coarse.row_ptr[a]..coarse.row_ptr[a + 1]];
            let k = coarse.row_ptr[a] + s.binary_search(&(b as u32)).expect("in pattern");
            terms.push(Term {
                src: slot as u32,
                dst: k as u32,
                w,
                t,
            });
        });
        terms.sort_unstable_by_key(|t| (t.dst, t.src));
        Self { coarse, terms }
    }

    /// `out = Pᵀ A P` (coarse blocks) from the fine blocks.
    pub fn apply(&self, fine: &[Matrix3<f64>], out: &mut Vec<Matrix3<f64>>) {
        out.clear();
        out.resize(self.coarse.cols.len(), Matrix3::zeros());
        for t in &self.terms {
            let b = &fine[t.src as usize];
            let o = &mut out[t.dst as usize];
            if t.t {
                *o += b.transpose() * t.w;
            } else {
                *o += b * t.w;
            }
        }
    }

    /// The coarse matrix's stored blocks as `(row, column, slot)`.
    pub fn coarse_upper(&self) -> Vec<(usize, usize, usize)> {
        upper_entries(&self.coarse)
    }
}

/// The stored blocks of an upper structure as `(row, column, slot)`.
pub(super) fn upper_entries(s: &UpperCsr) -> Vec<(usize, usize, usize)> {
    let mut out = Vec::with_capacity(s.cols.len());
    for i in 0..s.num_rows() {
        for k in s.row_ptr[i]..s.row_ptr[i + 1] {
            out.push((i, s.cols[k] as usize, k));
        }
    }
    out
}
