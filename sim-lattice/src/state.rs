//! Refinement state of a region (a set of root trees) as bit sets over heap indices.
//!
//! Bit `h` of root `r` is set when tet `(r, h)` is split. The sets are stored sparsely as
//! sorted `(word index, 64-bit word)` pairs with non-zero words only, so a deep but narrow
//! refinement costs a few words, not `2^depth / 64`.

use std::collections::HashMap;

use tracing::trace;

use crate::lattice::NONE;
use crate::{Lattice, LatticeError, TetId, TopologyEvent};

/// Sparse bit sets over heap indices, one per root.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
struct SplitBits {
    roots: Vec<u32>,
    /// `words[starts[i]..starts[i + 1]]` belong to `roots[i]`; `starts.len() == roots.len() + 1`.
    starts: Vec<u32>,
    /// `(word index, word)`, word index strictly increasing per root, word non-zero.
    words: Vec<(u32, u64)>,
}

impl SplitBits {
    fn new() -> Self {
        SplitBits {
            roots: Vec::new(),
            starts: vec![0],
            words: Vec::new(),
        }
    }

    fn root_words(&self, i: usize) -> &[(u32, u64)] {
        &self.words[self.starts[i] as usize..self.starts[i + 1] as usize]
    }

    /// Appends a root whose set bits are given in increasing order.
    fn push_root(&mut self, root: u32, heaps: impl IntoIterator<Item = u32>) {
        self.roots.push(root);
        let start = self.words.len();
        for h in heaps {
            let (w, b) = (h >> 6, 1u64 << (h & 63));
            let len = self.words.len();
            match self.words.last_mut() {
                Some(last) if len > start && last.0 == w => last.1 |= b,
                _ => self.words.push((w, b)),
            }
        }
        self.starts.push(self.words.len() as u32);
    }

    fn push_root_words(&mut self, root: u32, words: impl IntoIterator<Item = (u32, u64)>) {
        self.roots.push(root);
        self.words.extend(words.into_iter().filter(|w| w.1 != 0));
        self.starts.push(self.words.len() as u32);
    }

    fn iter_bits(&self, i: usize) -> impl Iterator<Item = u32> + '_ {
        self.root_words(i).iter().flat_map(|&(w, mut bits)| {
            std::iter::from_fn(move || {
                (bits != 0).then(|| {
                    let b = bits.trailing_zeros();
                    bits &= bits - 1;
                    (w << 6) | b
                })
            })
        })
    }

    fn contains(&self, i: usize, heap: u32) -> bool {
        let words = self.root_words(i);
        words
            .binary_search_by_key(&(heap >> 6), |w| w.0)
            .is_ok_and(|j| words[j].1 & (1 << (heap & 63)) != 0)
    }

    fn count(&self) -> usize {
        self.words.iter().map(|w| w.1.count_ones() as usize).sum()
    }

    /// Per-root symmetric difference; roots missing on one side count as all-zero.
    fn xor(&self, other: &SplitBits) -> SplitBits {
        let index: HashMap<u32, usize> = other
            .roots
            .iter()
            .enumerate()
            .map(|(i, &r)| (r, i))
            .collect();
        let mut out = SplitBits::new();
        let mut used = vec![false; other.roots.len()];
        for (i, &root) in self.roots.iter().enumerate() {
            let a = self.root_words(i);
            let b = match index.get(&root) {
                Some(&j) => {
                    used[j] = true;
                    other.root_words(j)
                }
                None => &[],
            };
            out.push_root_words(root, merge_xor(a, b));
        }
        for (j, &root) in other.roots.iter().enumerate() {
            if !used[j] {
                out.push_root_words(root, other.root_words(j).iter().copied());
            }
        }
        out
    }
}

fn merge_xor(a: &[(u32, u64)], b: &[(u32, u64)]) -> Vec<(u32, u64)> {
    let mut out = Vec::with_capacity(a.len().max(b.len()));
    let (mut i, mut j) = (0, 0);
    while i < a.len() || j < b.len() {
        let take = match (a.get(i), b.get(j)) {
            (Some(x), Some(y)) if x.0 == y.0 => {
                i += 1;
                j += 1;
                (x.0, x.1 ^ y.1)
            }
            (Some(x), Some(y)) if x.0 < y.0 => {
                i += 1;
                *x
            }
            (Some(x), None) => {
                i += 1;
                *x
            }
            (_, Some(y)) => {
                j += 1;
                *y
            }
            (None, None) => unreachable!(),
        };
        if take.1 != 0 {
            out.push(take);
        }
    }
    out
}

/// Which tets of a set of root trees are split.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct RegionState(SplitBits);

/// The tets whose split state differs between two [`RegionState`]s.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct RegionDelta(SplitBits);

/// Malformed encoded region state.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum StateDecodeError {
    #[error("region state: bad magic or version")]
    BadHeader,
    #[error("region state: truncated at byte {0}")]
    Truncated(usize),
    #[error("region state: malformed varint at byte {0}")]
    BadVarint(usize),
    #[error("region state: {0}")]
    Invalid(&'static str),
    #[error("region state: {0} trailing bytes")]
    Trailing(usize),
}

const MAGIC: &[u8; 4] = b"CSRS";
const VERSION: u8 = 1;
/// Heap indices are below 2^31, so word indices are below 2^25.
const MAX_WORD: u32 = 1 << 25;

impl RegionState {
    /// The state of `roots` with nothing split.
    pub fn unrefined(roots: &[u32]) -> RegionState {
        let mut s = SplitBits::new();
        for &r in roots {
            s.push_root(r, []);
        }
        RegionState(s)
    }

    /// The state of `roots` in which exactly `tets` are split (any order, repeats
    /// allowed). Tets of roots not in `roots` and heap indices that name no tet (0, or
    /// 2^31 and above) are ignored; a root listed twice gets its tets at its first place
    /// only. As with [`RegionState::from_bytes`], consistency with a lattice (`max_depth`,
    /// ancestors split) is checked by [`Lattice::apply_state`].
    pub fn from_split_tets(roots: &[u32], tets: impl IntoIterator<Item = TetId>) -> RegionState {
        let mut per_root: HashMap<u32, Vec<u32>> = HashMap::new();
        for t in tets {
            if t.heap != 0 && t.heap >> 6 < MAX_WORD {
                per_root.entry(t.root).or_default().push(t.heap);
            }
        }
        let mut s = SplitBits::new();
        for &root in roots {
            let mut heaps = per_root.remove(&root).unwrap_or_default();
            heaps.sort_unstable();
            heaps.dedup();
            s.push_root(root, heaps);
        }
        RegionState(s)
    }

    /// Root indices of the region, in order.
    pub fn roots(&self) -> &[u32] {
        &self.0.roots
    }

    /// Split tets of the region, root by root, heap indices increasing (coarse first).
    pub fn split_tets(&self) -> impl Iterator<Item = TetId> + '_ {
        (0..self.0.roots.len()).flat_map(move |i| {
            let root = self.0.roots[i];
            self.0.iter_bits(i).map(move |heap| TetId { root, heap })
        })
    }

    /// Number of split tets.
    pub fn split_count(&self) -> usize {
        self.0.count()
    }

    pub fn is_split(&self, t: TetId) -> bool {
        self.0
            .roots
            .iter()
            .position(|&r| r == t.root)
            .is_some_and(|i| self.0.contains(i, t.heap))
    }

    /// The tets whose split state differs (roots missing on one side count as unsplit).
    pub fn xor(&self, other: &RegionState) -> RegionDelta {
        RegionDelta(self.0.xor(&other.0))
    }

    /// Compact encoding: `"CSRS"`, version byte, varint root count, then per root: varint
    /// root, varint word count, and per non-zero word a varint word-index delta (first
    /// index absolute) and the 8-byte little-endian word.
    pub fn to_bytes(&self) -> Vec<u8> {
        let s = &self.0;
        let mut out = Vec::with_capacity(8 + s.roots.len() * 4 + s.words.len() * 10);
        out.extend_from_slice(MAGIC);
        out.push(VERSION);
        put_varint(&mut out, s.roots.len() as u64);
        for (i, &root) in s.roots.iter().enumerate() {
            let words = s.root_words(i);
            put_varint(&mut out, u64::from(root));
            put_varint(&mut out, words.len() as u64);
            let mut prev = 0;
            for (n, &(w, bits)) in words.iter().enumerate() {
                put_varint(&mut out, u64::from(if n == 0 { w } else { w - prev }));
                prev = w;
                out.extend_from_slice(&bits.to_le_bytes());
            }
        }
        out
    }

    /// Decodes [`RegionState::to_bytes`]; rejects malformed input (bad header, truncation,
    /// zero words, unordered or out-of-range word indices, duplicate roots, trailing bytes)
    /// without panicking and without allocating more than the input justifies. Consistency
    /// with a lattice (`max_depth`, ancestors split) is checked by [`Lattice::apply_state`].
    pub fn from_bytes(bytes: &[u8]) -> Result<RegionState, StateDecodeError> {
        if bytes.len() < 5 || &bytes[..4] != MAGIC || bytes[4] != VERSION {
            return Err(StateDecodeError::BadHeader);
        }
        let mut rd = Reader { bytes, pos: 5 };
        let n_roots = rd.varint()?;
        // Each root takes at least two bytes.
        if n_roots > (bytes.len() as u64) / 2 {
            return Err(StateDecodeError::Invalid(
                "root count exceeds the input size",
            ));
        }
        let mut s = SplitBits::new();
        let mut seen = std::collections::HashSet::new();
        for _ in 0..n_roots {
            let root = u32::try_from(rd.varint()?)
                .map_err(|_| StateDecodeError::Invalid("root index exceeds u32"))?;
            if !seen.insert(root) {
                return Err(StateDecodeError::Invalid("duplicate root"));
            }
            let n_words = rd.varint()?;
            if n_words > (bytes.len() - rd.pos) as u64 / 9 {
                return Err(StateDecodeError::Truncated(rd.pos));
            }
            s.roots.push(root);
            let mut prev: Option<u32> = None;
            for _ in 0..n_words {
                let d = rd.varint()?;
                let w = match prev {
                    None => d,
                    Some(p) if d > 0 => u64::from(p) + d,
                    Some(_) => {
                        return Err(StateDecodeError::Invalid("word indices not increasing"));
                    }
                };
                if w >= u64::from(MAX_WORD) {
                    return Err(StateDecodeError::Invalid("word index out of range"));
                }
                let bits = u64::from_le_bytes(rd.take8()?);
                if bits == 0 {
                    return Err(StateDecodeError::Invalid("zero word"));
                }
                if w == 0 && bits & 1 != 0 {
                    return Err(StateDecodeError::Invalid("heap index 0 is not a tet"));
                }
                s.words.push((w as u32, bits));
                prev = Some(w as u32);
            }
            s.starts.push(s.words.len() as u32);
        }
        if rd.pos != bytes.len() {
            return Err(StateDecodeError::Trailing(bytes.len() - rd.pos));
        }
        Ok(RegionState(s))
    }
}

impl RegionDelta {
    /// Tets whose split state differs, root by root, coarse first.
    pub fn tets(&self) -> impl Iterator<Item = TetId> + '_ {
        (0..self.0.roots.len()).flat_map(move |i| {
            let root = self.0.roots[i];
            self.0.iter_bits(i).map(move |heap| TetId { root, heap })
        })
    }

    pub fn len(&self) -> usize {
        self.0.count()
    }

    pub fn is_empty(&self) -> bool {
        self.0.words.is_empty()
    }
}

fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    fn varint(&mut self) -> Result<u64, StateDecodeError> {
        let start = self.pos;
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let b = *self
                .bytes
                .get(self.pos)
                .ok_or(StateDecodeError::Truncated(self.pos))?;
            self.pos += 1;
            if shift == 63 && b > 1 {
                return Err(StateDecodeError::BadVarint(start));
            }
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(v);
            }
        }
        Err(StateDecodeError::BadVarint(start))
    }

    fn take8(&mut self) -> Result<[u8; 8], StateDecodeError> {
        let s = self
            .bytes
            .get(self.pos..self.pos + 8)
            .ok_or(StateDecodeError::Truncated(self.pos))?;
        self.pos += 8;
        Ok(s.try_into().expect("8 bytes"))
    }
}

/// What [`Lattice::apply_state`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ApplyStats {
    /// Tets split, including splits forced by conformity (possibly outside the region).
    pub tets_split: usize,
    /// Diamonds merged (each merges all tets around one edge).
    pub diamonds_merged: usize,
    /// Split tets named by the XOR that were to be merged but could not be, because a
    /// finer split outside the region depends on them.
    pub merges_blocked: usize,
    /// Bits where the region differs from the target afterwards (0 unless the target is
    /// inconsistent with the lattice outside the region).
    pub residual: usize,
}

impl Lattice {
    /// The split state of the trees of `roots` (out-of-range roots are skipped).
    pub fn region_state(&self, roots: &[u32]) -> RegionState {
        let mut s = SplitBits::new();
        let mut queue: Vec<u32> = Vec::new();
        for &root in roots {
            if root >= self.root_count() {
                continue;
            }
            // Breadth-first order visits heap indices in increasing order.
            queue.clear();
            queue.push(root);
            let mut head = 0;
            while head < queue.len() {
                let rec = self.tet_rec(queue[head]);
                head += 1;
                if rec.first_child != NONE {
                    queue.push(rec.first_child);
                    queue.push(rec.first_child + 1);
                }
            }
            s.push_root(
                root,
                queue.iter().filter_map(|&r| {
                    let rec = self.tet_rec(r);
                    (rec.first_child != NONE).then_some(rec.id.heap)
                }),
            );
        }
        RegionState(s)
    }

    /// Makes the region's trees match `target`: performs the splits and merges that the
    /// XOR with the current state names, merges finest-first, then splits coarsest-first.
    ///
    /// Conformity reaches outside the region: a split may force splits of coarser
    /// neighbours outside it, and a merge merges the whole diamond, whose other tets may
    /// lie in roots outside the region. A merge that a finer split outside the region
    /// blocks is skipped and counted in [`ApplyStats::merges_blocked`].
    ///
    /// # Errors
    /// [`LatticeError::InvalidState`] (nothing changed) if the target names a root out of
    /// range, a tet at or below `max_depth` as split, or a split tet whose parent is not
    /// split.
    pub fn apply_state(
        &mut self,
        target: &RegionState,
        events: &mut Vec<TopologyEvent>,
    ) -> Result<ApplyStats, LatticeError> {
        let t = &target.0;
        for (i, &root) in t.roots.iter().enumerate() {
            if root >= self.root_count() {
                return Err(LatticeError::InvalidState(format!(
                    "root {root} out of range ({} roots)",
                    self.root_count()
                )));
            }
            for heap in t.iter_bits(i) {
                let id = TetId { root, heap };
                if id.level() >= self.params().max_depth {
                    return Err(LatticeError::InvalidState(format!(
                        "{id:?} is split but at or past max_depth {}",
                        self.params().max_depth
                    )));
                }
                if heap > 1 && !t.contains(i, heap / 2) {
                    return Err(LatticeError::InvalidState(format!(
                        "{id:?} is split but its parent is not"
                    )));
                }
            }
        }
        let current = self.region_state(&t.roots);
        let mut merges: Vec<TetId> = Vec::new();
        let mut splits: Vec<TetId> = Vec::new();
        let delta = current.0.xor(t);
        for (i, &root) in delta.roots.iter().enumerate() {
            // `current` lists the same roots in the same order as `delta`.
            for heap in delta.iter_bits(i) {
                let id = TetId { root, heap };
                if current.0.contains(i, heap) {
                    merges.push(id);
                } else {
                    splits.push(id);
                }
            }
        }
        merges.sort_unstable_by_key(|id| std::cmp::Reverse(id.level()));
        splits.sort_unstable_by_key(|id| id.level());
        let mut stats = ApplyStats::default();
        for id in merges {
            // An earlier merge of the same diamond may have merged `id` already.
            if self.is_leaf(id) || !self.tet_exists(id) {
                continue;
            }
            if self.coarsen(id, events)? {
                stats.diamonds_merged += 1;
            } else {
                stats.merges_blocked += 1;
            }
        }
        for id in splits {
            if self.is_leaf(id) {
                stats.tets_split += self.refine(id, events)?;
            }
        }
        stats.residual = self.region_state(&t.roots).0.xor(t).count();
        trace!(?stats, "applied region state");
        Ok(stats)
    }
}
