//! Software prefetch: asking for a cache line before a loop needs it.
//!
//! Why: at 98,304 tets the step's matrices (tens of MB) no longer fit the level-3 cache,
//! and loops whose next element waits on the one before (a Gauss–Seidel sweep: row `i`
//! needs row `i − 1`'s result) or whose addresses come from an index array (gathers and
//! scatters by slot) cannot run far enough ahead for the hardware to fetch their data in
//! time. Prefetching a fixed distance ahead made the 98,304-tet MG-PCG step 9–17 %
//! faster (docs/RESULTS.md, "Prefetching once the matrices leave the cache"). A prefetch
//! never changes memory or results; on architectures other than x86-64 it is nothing.

/// Size of a step's block storage from which loops over it prefetch: a quarter of the
/// 32 MiB level-3 cache of the machines this was measured on (2-core AMD EPYC VMs).
const BEYOND_CACHE_BYTES: usize = 8 << 20;

/// Whether `blocks` (a step's block storage: one 3×3 f64 block per slot of the operator's
/// pattern, or a coarse level's) outgrows the cache, so that loops over it should
/// prefetch. Below [`BEYOND_CACHE_BYTES`] the matrices stay in cache and the prefetches
/// cost without saving: the 12,288-tet MG-PCG step (3 MB of blocks) was 3–5 % slower with
/// them, the 98,304-tet one (20 MB) 9–17 % faster (docs/RESULTS.md; sizes between were
/// not measured). The coarse levels, far smaller, never prefetch.
pub(crate) fn outgrows_cache<T>(blocks: &[T]) -> bool {
    std::mem::size_of_val(blocks) >= BEYOND_CACHE_BYTES
}

/// Asks for the cache line at `p` (nothing on other architectures).
#[inline(always)]
fn prefetch_address(p: *const u8) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: `_mm_prefetch` needs SSE, which every x86-64 CPU has; it reads and
        // writes nothing and cannot fault, whatever the address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(p.cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Asks for the cache line holding the start of `slice[i]` (nothing if `i` is out of
/// bounds).
#[inline(always)]
pub(crate) fn prefetch<T>(slice: &[T], i: usize) {
    if let Some(x) = slice.get(i) {
        prefetch_address(std::ptr::from_ref(x).cast::<u8>());
    }
}

/// Asks for every cache line that `slice[range]` touches (the part of it in bounds).
#[inline(always)]
pub(crate) fn prefetch_range<T>(slice: &[T], range: std::ops::Range<usize>) {
    let end = range.end.min(slice.len());
    if range.start >= end {
        return;
    }
    let bytes = (end - range.start) * std::mem::size_of::<T>();
    if bytes == 0 {
        return;
    }
    // Addresses only (never dereferenced), all within `slice`'s memory.
    let first = slice.as_ptr().wrapping_add(range.start).cast::<u8>();
    // Every 64 bytes from the first, then the last byte's line, which the stride can
    // step over.
    let mut offset = 0;
    while offset < bytes {
        prefetch_address(first.wrapping_add(offset));
        offset += 64;
    }
    prefetch_address(first.wrapping_add(bytes - 1));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prefetching_out_of_bounds_empty_or_reversed_ranges_is_nothing() {
        let v = vec![[0u8; 48]; 10];
        prefetch(&v, 10);
        prefetch(&v, usize::MAX);
        prefetch_range(&v, 4..4);
        prefetch_range(&v, 8..12);
        #[allow(clippy::reversed_empty_ranges)]
        prefetch_range(&v, 7..3);
        prefetch_range(&v, 0..10);
        prefetch_range::<u8>(&[], 0..1);
        assert!(!outgrows_cache(&v));
        assert!(outgrows_cache(&vec![0u8; BEYOND_CACHE_BYTES]));
    }
}
