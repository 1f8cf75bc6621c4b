//! The counting allocator, installed as this test binary's global allocator as the
//! `cosurg` binary installs it: a scope's peak is the most its allocations held above what
//! was in use when it opened, over every thread.

use cosurg_bench::memory::{CountingAlloc, HeapScope};

#[global_allocator]
static ALLOC: CountingAlloc = CountingAlloc;

const MB: usize = 1 << 20;
/// Room for the test harness's own small allocations meanwhile.
const SLACK: usize = 64 * 1024;

// One test: the counters see every thread of the process, so a second test running
// beside it would count in its scope.
#[test]
fn a_scope_peaks_at_what_it_held_over_threads_and_freeing_makes_room() {
    let scope = HeapScope::open().expect("the counting allocator is installed");
    let a = vec![1u8; 3 * MB];
    let b = std::thread::spawn(|| vec![2u8; 5 * MB]).join().unwrap();
    let peak = scope.peak_bytes();
    assert!((8 * MB..8 * MB + SLACK).contains(&peak), "peak {peak} B");
    drop((a, b));
    let c = vec![3u8; MB];
    assert_eq!(
        scope.peak_bytes(),
        peak,
        "a later, smaller allocation moves no peak"
    );
    drop(c);
    drop(scope);

    // Memory freed in a scope makes room for its own allocations.
    let before = vec![1u8; 8 * MB];
    let scope = HeapScope::open().unwrap();
    drop(before);
    let a = vec![1u8; 3 * MB];
    assert!(scope.peak_bytes() < SLACK, "{}", scope.peak_bytes());
    drop(a);
}
