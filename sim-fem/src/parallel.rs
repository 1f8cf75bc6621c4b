//! Multi-threaded step: a split of the mesh into parts that threads can work on without
//! sharing writes, and the block sparse product on it.
//!
//! Nodes are cut into `parts` contiguous index ranges of about equal sparse-matrix work.
//! An element whose four nodes lie in one part only writes that part's force entries and
//! matrix rows, so the parts' elements are processed in parallel (one part per task) and
//! the remaining *interface* elements after them, on one thread. With the lattice's
//! spatially ordered node numbering the interface is a thin layer of elements.
//!
//! Results equal the sequential ones up to the order of floating-point sums.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::solver::BlockPattern;

type V3 = Vector3<f64>;

/// Nodes and elements split for `parts` threads.
#[derive(Clone, Debug)]
pub(crate) struct Partition {
    /// The thread count it was built for (parts are fewer when nodes are fewer).
    pub threads: usize,
    /// Node index where each part starts, then the node count (`parts + 1` entries).
    pub node_start: Vec<usize>,
    /// Per part, its elements (in the order they were given).
    pub elements: Vec<Vec<u32>>,
    /// Elements with nodes in more than one part.
    pub interface: Vec<u32>,
    /// Per part, one past the largest column its rows reach (its spill range in
    /// [`multiply_upper_parts`] ends there); set by [`Partition::set_spill_ends`].
    pub spill_end: Vec<usize>,
}

impl Partition {
    /// Splits the nodes so that each part holds about the same number of `row_work` (the
    /// stored blocks of each node's matrix row), then the elements, visited in `order`.
    pub fn new(
        parts: usize,
        row_work: &[usize],
        order: &[u32],
        nodes_of: impl Fn(usize) -> [usize; 4],
    ) -> Self {
        let n = row_work.len();
        let threads = parts;
        let parts = parts.clamp(1, n.max(1));
        let total: usize = row_work.iter().sum();
        let mut node_start = vec![0];
        let mut acc = 0;
        for (i, w) in row_work.iter().enumerate() {
            // Cut before node i once the work so far reaches the next part's share.
            if node_start.len() < parts && acc * parts >= total * node_start.len() {
                node_start.push(i);
            }
            acc += w;
        }
        while node_start.len() < parts {
            node_start.push(n);
        }
        node_start.push(n);
        let part_of = |node: usize| node_start.partition_point(|&s| s <= node) - 1;
        let mut elements = vec![Vec::new(); parts];
        let mut interface = Vec::new();
        for &e in order {
            let nodes = nodes_of(e as usize);
            let p = part_of(nodes[0]);
            if nodes[1..].iter().all(|&k| part_of(k) == p) {
                elements[p].push(e);
            } else {
                interface.push(e);
            }
        }
        let spill_end = node_start[1..].to_vec();
        Partition {
            threads,
            node_start,
            elements,
            interface,
            spill_end,
        }
    }

    /// Records how far each part's rows reach to the right in `pat` (with the lattice's
    /// node order, a thin band past the part's end).
    pub fn set_spill_ends(&mut self, pat: &BlockPattern) {
        for (t, w) in self.node_start.windows(2).enumerate() {
            let reach = (w[0]..w[1])
                .filter_map(|i| pat.row(i).last().map(|(_, c)| c + 1))
                .max()
                .unwrap_or(w[1]);
            self.spill_end[t] = reach.max(w[1]);
        }
    }
}

/// Splits `data` at the given ascending offsets (`bounds[0]` = 0, last = `data.len()`)
/// into one mutable slice per range.
pub(crate) fn split_ranges<'a, T>(mut data: &'a mut [T], bounds: &[usize]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(bounds.len().saturating_sub(1));
    for w in bounds.windows(2) {
        let (head, tail) = data.split_at_mut(w[1] - w[0]);
        out.push(head);
        data = tail;
    }
    out
}

/// `out = A p` for a symmetric `A` stored as its upper blocks (as
/// [`BlockPattern::multiply_upper`]), rows split by `node_start` over the current rayon
/// pool. A part owns its rows of `out`; the transposed products it makes for rows of later
/// parts go to its own spill buffer, added in afterwards.
pub(crate) fn multiply_upper_parts(
    pat: &BlockPattern,
    blocks: &[Matrix3<f64>],
    p: &[V3],
    out: &mut [V3],
    part: &Partition,
) {
    let node_start = &part.node_start;
    let parts = node_start.len() - 1;
    let mut spills: Vec<Vec<V3>> = (0..parts)
        .map(|t| vec![V3::zeros(); part.spill_end[t] - node_start[t + 1]])
        .collect();
    split_ranges(out, node_start)
        .into_par_iter()
        .zip(spills.par_iter_mut())
        .enumerate()
        .for_each(|(t, (rows, spill))| {
            let (start, end) = (node_start[t], node_start[t + 1]);
            pat.multiply_upper_rows(blocks, p, start, end, rows, spill);
        });
    for (t, spill) in spills.iter().enumerate() {
        for (o, s) in out[node_start[t + 1]..].iter_mut().zip(spill) {
            *o += s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_cover_nodes_and_elements_once() {
        // A strip of 10 tets sharing nodes along a line: node i..i+3.
        let tets: Vec<[usize; 4]> = (0..10).map(|i| [i, i + 1, i + 2, i + 3]).collect();
        let order: Vec<u32> = (0..10).collect();
        let p = Partition::new(2, &[1; 13], &order, |e| tets[e]);
        assert_eq!(p.node_start.first(), Some(&0));
        assert_eq!(p.node_start.last(), Some(&13));
        assert_eq!(p.elements.len(), 2);
        let mut all: Vec<u32> = p.elements.concat();
        all.extend(&p.interface);
        all.sort_unstable();
        assert_eq!(all, order);
        // Every non-interface element lies inside its part.
        for (t, els) in p.elements.iter().enumerate() {
            for &e in els {
                for &k in &tets[e as usize] {
                    assert!(p.node_start[t] <= k && k < p.node_start[t + 1]);
                }
            }
        }
        assert!(!p.interface.is_empty());
    }

    #[test]
    fn split_ranges_matches_bounds() {
        let mut v: Vec<u32> = (0..10).collect();
        let parts = split_ranges(&mut v, &[0, 3, 3, 10]);
        assert_eq!(parts.len(), 3);
        assert_eq!(parts[0], &[0, 1, 2]);
        assert!(parts[1].is_empty());
        assert_eq!(parts[2].len(), 7);
    }
}

#[cfg(test)]
mod product_tests {
    use super::*;

    /// A symmetric block matrix on the pattern of a small tet strip, with distinct entries:
    /// all its blocks, and only those on and above the diagonal (the rest zero).
    type Strip = (BlockPattern, Vec<Matrix3<f64>>, Vec<Matrix3<f64>>, Vec<V3>);
    fn strip() -> Strip {
        let tets: Vec<[usize; 4]> = (0..30).map(|i| [i, i + 1, i + 2, i + 3]).collect();
        let n = 33;
        let pat = BlockPattern::new(n, &tets);
        let mut full = vec![Matrix3::zeros(); pat.num_blocks()];
        let mut upper = full.clone();
        for (e, t) in tets.iter().enumerate() {
            let slots = pat.element_slots(e);
            let mask = pat.element_upper(e);
            for a in 0..4 {
                for b in 0..4 {
                    // Block (a, b) = f(min, max) so that (b, a) is its transpose.
                    let (lo, hi) = (t[a].min(t[b]), t[a].max(t[b]));
                    let m =
                        Matrix3::from_fn(|i, j| ((lo * 7 + hi * 3 + i * 5 + j * 11) % 13) as f64);
                    let blk = if t[a] <= t[b] { m } else { m.transpose() };
                    let blk = if a == b {
                        (blk + blk.transpose()) * 0.5
                    } else {
                        blk
                    };
                    let s = slots[4 * a + b] as usize;
                    full[s] += blk;
                    if mask & (1 << (4 * a + b)) != 0 {
                        upper[s] += blk;
                    }
                }
            }
        }
        let p = (0..n)
            .map(|i| V3::new(i as f64, 1.0 - i as f64 * 0.3, (i % 5) as f64))
            .collect();
        (pat, full, upper, p)
    }

    #[test]
    fn upper_storage_and_split_products_equal_the_full_product() {
        let (pat, full, upper, p) = strip();
        let n = p.len();
        let mut reference = vec![V3::zeros(); n];
        pat.multiply(&full, &p, &mut reference);
        let mut upper_only = vec![V3::zeros(); n];
        pat.multiply_upper(&upper, &p, &mut upper_only);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        let mut split = vec![V3::zeros(); n];
        let mut part = Partition {
            threads: 3,
            node_start: vec![0, 10, 21, n],
            elements: vec![Vec::new(); 3],
            interface: Vec::new(),
            spill_end: vec![10, 21, n],
        };
        part.set_spill_ends(&pat);
        // The strip's rows reach 3 nodes ahead: the spills are that thin.
        assert_eq!(part.spill_end, vec![13, 24, n]);
        pool.install(|| multiply_upper_parts(&pat, &upper, &p, &mut split, &part));
        for i in 0..n {
            assert!(
                (upper_only[i] - reference[i]).norm() < 1e-9,
                "row {i} upper"
            );
            assert!((split[i] - reference[i]).norm() < 1e-9, "row {i} split");
        }
    }
}
