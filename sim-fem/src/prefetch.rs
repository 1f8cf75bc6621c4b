//! Software prefetch: asking for a cache line before a loop needs it.
//!
//! Why: at 98,304 tets the step's matrices (tens of MB) no longer fit the level-3 cache,
//! and loops whose next element waits on the one before (a Gauss–Seidel sweep: row `i`
//! needs row `i − 1`'s result) or whose addresses come from an index array (gathers and
//! scatters by slot) cannot run far enough ahead for the hardware to fetch their data in
//! time. Prefetching a fixed distance ahead made the 98,304-tet MG-PCG step 11 % faster
//! (docs/RESULTS.md). A prefetch never changes memory or results; on other CPUs it is
//! nothing.

/// Whether loops over `blocks` (the step's block storage: one 3×3 f64 block per slot of
/// the operator's pattern) should prefetch: only once it passes 8 MiB, a quarter of this
/// machine's 32 MB level-3 cache. Below that the step's matrices stay in cache and the
/// prefetches cost without saving: the 12,288-tet MG-PCG step (3 MB of blocks) was 3–5 %
/// slower with them, the 98,304-tet one (20 MB) about 10 % faster (docs/RESULTS.md;
/// sizes between were not measured).
pub(crate) fn worth_it<T>(blocks: &[T]) -> bool {
    std::mem::size_of_val(blocks) >= 8 << 20
}

/// Asks for the cache line holding `slice[i]` (nothing if `i` is out of bounds).
#[inline(always)]
pub(crate) fn prefetch<T>(slice: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(x) = slice.get(i) {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: a prefetch reads and writes nothing; the address is that of `slice[i]`.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(x).cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (slice, i);
}

/// Asks for every cache line of `slice[range]`.
#[inline(always)]
pub(crate) fn prefetch_range<T>(slice: &[T], range: std::ops::Range<usize>) {
    let step = (64 / std::mem::size_of::<T>().max(1)).max(1);
    let mut i = range.start;
    while i < range.end {
        prefetch(slice, i);
        i += step;
    }
    // The last element's line, when the stride stepped over it.
    if range.end > range.start {
        prefetch(slice, range.end - 1);
    }
}
