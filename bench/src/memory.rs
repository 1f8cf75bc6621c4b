//! Heap memory of a measured scope, for the benches' memory columns: a global allocator
//! ([`CountingAlloc`], installed by the `cosurg` binary) that counts the bytes in use
//! while a [`HeapScope`] is open.
//!
//! Why an allocator and not the process's resident size: the rows of `bench scale` run
//! one after the other in one process, and freed pages stay resident (glibc keeps them),
//! so the resident size after a 100k-tet row hides every smaller row after it. Bytes
//! requested from the allocator are what the row's structures hold.
//!
//! Closed, the allocator costs one relaxed load per allocation and nothing else (the
//! sites' real-time loops run in the same binary).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicIsize, Ordering::Relaxed};

/// The system allocator, counting while a [`HeapScope`] is open.
pub struct CountingAlloc;

static COUNTING: AtomicBool = AtomicBool::new(false);
/// Bytes allocated minus bytes freed since the scope opened (negative when the scope
/// frees what was allocated before it).
static CURRENT: AtomicIsize = AtomicIsize::new(0);
static PEAK: AtomicIsize = AtomicIsize::new(0);
/// One scope at a time (the counters are global).
static SCOPE: Mutex<()> = Mutex::new(());

#[inline]
fn note(delta: isize) {
    if COUNTING.load(Relaxed) {
        let now = CURRENT.fetch_add(delta, Relaxed) + delta;
        if delta > 0 {
            PEAK.fetch_max(now, Relaxed);
        }
    }
}

// SAFETY: every call is forwarded to `System` unchanged; the counters only observe sizes.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract for `alloc` is passed on.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            note(layout.size() as isize);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: as `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            note(layout.size() as isize);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from this allocator (hence from `System`) with `layout`.
        unsafe { System.dealloc(ptr, layout) };
        note(-(layout.size() as isize));
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as `dealloc`, and `new_size` is the caller's.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            note(new_size as isize - layout.size() as isize);
        }
        p
    }
}

/// An open measurement: the peak of the heap bytes in use above what was in use when it
/// opened, over every thread.
pub struct HeapScope {
    _one_at_a_time: std::sync::MutexGuard<'static, ()>,
}

impl HeapScope {
    /// Opens a scope, or `None` when this binary does not count (its global allocator is
    /// not [`CountingAlloc`], as in tests) or another scope is open (the counters are
    /// global; waiting for it could deadlock a thread that holds it).
    pub fn open() -> Option<HeapScope> {
        let guard = match SCOPE.try_lock() {
            Ok(g) => g,
            Err(std::sync::TryLockError::Poisoned(e)) => e.into_inner(),
            Err(std::sync::TryLockError::WouldBlock) => return None,
        };
        CURRENT.store(0, Relaxed);
        PEAK.store(0, Relaxed);
        COUNTING.store(true, Relaxed);
        // A probe allocation shows whether the counting allocator is installed.
        let probe = std::hint::black_box(vec![0u8; 64]);
        let installed = CURRENT.load(Relaxed) >= 64;
        drop(probe);
        if !installed {
            COUNTING.store(false, Relaxed);
            return None;
        }
        PEAK.store(CURRENT.load(Relaxed).max(0), Relaxed);
        Some(HeapScope {
            _one_at_a_time: guard,
        })
    }

    /// The peak so far (bytes).
    pub fn peak_bytes(&self) -> usize {
        PEAK.load(Relaxed).max(0) as usize
    }
}

impl Drop for HeapScope {
    fn drop(&mut self) {
        COUNTING.store(false, Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // The test binary's allocator is the system's: no scope opens.
    #[test]
    fn without_the_counting_allocator_no_scope_opens() {
        assert!(HeapScope::open().is_none());
    }
}
