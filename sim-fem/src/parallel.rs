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

use nalgebra::Vector3;

use crate::solver::{BlockPattern, RowBlock};

mod spin;

pub(crate) use spin::{run_parts, with_helper};

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
        Partition {
            threads,
            node_start,
            elements,
            interface,
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

/// `out = A p` by the full rows of [`BlockPattern::full_rows`], the rows split at
/// `node_start` (first 0, last the row count) over the current threads ([`run_parts`]): each part
/// computes its own rows, with the same bits as [`BlockPattern::multiply_full`].
///
/// (Until 2026-11-28 the parts multiplied the upper storage, each adding its transposed
/// products for later parts' rows from a spill buffer; with the full rows every part
/// reads only its own rows, and the product vectorises as on one thread.)
pub(crate) fn multiply_full_parts(
    pat: &BlockPattern,
    full: &[RowBlock],
    p: &[V3],
    out: &mut [V3],
    node_start: &[usize],
) {
    run_parts(split_ranges(out, node_start), |k, rows| {
        pat.multiply_full_rows(full, p, node_start[k], rows)
    });
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
    use nalgebra::Matrix3;

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
    fn upper_full_row_and_split_products_equal_the_plain_product() {
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
        let rows = pat.full_rows(&upper);
        let mut split_rows = Vec::new();
        pool.install(|| pat.full_rows_into_parts(&upper, &mut split_rows, &[0, 10, 21, n]));
        assert_eq!(split_rows, rows, "full rows copied in parts");
        let mut whole = vec![V3::zeros(); n];
        pat.multiply_full(&rows, &p, &mut whole);
        let mut split = vec![V3::zeros(); n];
        pool.install(|| multiply_full_parts(&pat, &rows, &p, &mut split, &[0, 10, 21, n]));
        for i in 0..n {
            assert!(
                (upper_only[i] - reference[i]).norm() < 1e-9,
                "row {i} upper"
            );
            assert!((whole[i] - reference[i]).norm() < 1e-9, "row {i} full rows");
            // Each row is computed the same way whichever part holds it.
            assert_eq!(split[i], whole[i], "row {i} split");
        }
    }
}
