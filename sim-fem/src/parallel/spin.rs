//! A second thread kept awake for the length of a solve, for its many short parallel
//! regions (two per V-cycle and one per CG product).
//!
//! Why: on a two-thread rayon pool every region of a 12,288-tet MG-PCG solve (tens of
//! µs each, a few hundred per step) found the other worker asleep, and waking it cost
//! about as much as the region saved: `perf` put 15 % of the second worker's samples in
//! the scheduler and its split of the work at 1 : 3 (2026-11-28). Here the helper spins
//! on one atomic between regions, so handing it half of a region costs a cache-line
//! transfer.
//!
//! Deadlock-free by construction: [`with_helper`] starts the helper as the second half
//! of a `rayon::join`, and a region never waits for a helper that has not taken its
//! half: the caller takes it back (an atomic compare-and-swap decides who runs it) and
//! runs it itself. With no free worker the solve runs on one thread, as before.

use std::cell::Cell;
use std::sync::atomic::{AtomicPtr, AtomicU8, Ordering};

/// No job posted.
const IDLE: u8 = 0;
/// A job is posted and not taken.
const POSTED: u8 = 1;
/// The helper runs the job.
const RUNNING: u8 = 2;
/// The helper finished the job.
const DONE: u8 = 3;
/// The helper finished the job, which panicked.
const PANICKED: u8 = 4;
/// The helper is to return.
const STOP: u8 = 5;

/// The job slot shared by the caller and the helper.
pub(crate) struct SpinHelper {
    state: AtomicU8,
    /// The posted job: a `&mut dyn FnMut()` on the caller's stack, valid while the state
    /// is `POSTED` or `RUNNING` (the caller does not return before it leaves them).
    job: AtomicPtr<&'static mut (dyn FnMut() + Send)>,
}

thread_local! {
    /// The helper of the solve running on this thread, if any.
    static CURRENT: Cell<*const SpinHelper> = const { Cell::new(std::ptr::null()) };
}

impl SpinHelper {
    fn new() -> Self {
        Self {
            state: AtomicU8::new(IDLE),
            job: AtomicPtr::new(std::ptr::null_mut()),
        }
    }

    /// The helper's side: runs posted jobs until told to stop, spinning in between
    /// (yielding the core now and then, so that an oversubscribed machine still
    /// progresses).
    fn serve(&self) {
        let mut idle_spins = 0u32;
        loop {
            match self.state.load(Ordering::Acquire) {
                STOP => return,
                POSTED
                    if self
                        .state
                        .compare_exchange(POSTED, RUNNING, Ordering::Acquire, Ordering::Relaxed)
                        .is_ok() =>
                {
                    // SAFETY: the job pointer was stored before the state became POSTED
                    // (release/acquire), and the caller keeps the job alive until the
                    // state leaves RUNNING, which only this thread changes now.
                    let job = unsafe { &mut **self.job.load(Ordering::Acquire) };
                    let ok = std::panic::catch_unwind(std::panic::AssertUnwindSafe(job)).is_ok();
                    self.state
                        .store(if ok { DONE } else { PANICKED }, Ordering::Release);
                    idle_spins = 0;
                }
                _ => {
                    idle_spins = idle_spins.saturating_add(1);
                    if idle_spins.is_multiple_of(4096) {
                        std::thread::yield_now();
                    } else {
                        std::hint::spin_loop();
                    }
                }
            }
        }
    }

    /// Runs `mine` on this thread and `theirs` on the helper (or here, if the helper has
    /// not taken it by the time `mine` is done), and returns when both are done.
    fn run_pair(&self, mine: impl FnOnce(), theirs: impl FnOnce() + Send) {
        let mut theirs = Some(theirs);
        let mut job = || {
            if let Some(f) = theirs.take() {
                f()
            }
        };
        let mut job_ref: &mut (dyn FnMut() + Send) = &mut job;
        // SAFETY (lifetime): the helper only reads the job while the state is POSTED or
        // RUNNING, and this function does not return before the state is IDLE again.
        let ptr = (&mut job_ref as *mut &mut (dyn FnMut() + Send))
            .cast::<&'static mut (dyn FnMut() + Send)>();
        self.job.store(ptr, Ordering::Release);
        self.state.store(POSTED, Ordering::Release);
        mine();
        if self
            .state
            .compare_exchange(POSTED, IDLE, Ordering::Acquire, Ordering::Relaxed)
            .is_ok()
        {
            job_ref();
            return;
        }
        let panicked = loop {
            match self.state.load(Ordering::Acquire) {
                DONE => break false,
                PANICKED => break true,
                _ => std::hint::spin_loop(),
            }
        };
        self.state.store(IDLE, Ordering::Release);
        assert!(
            !panicked,
            "a part of a parallel region panicked on the helper thread"
        );
    }
}

/// Runs `f` on this thread with a helper spinning on another worker of the current
/// rayon pool for its length; [`run_parts`] inside `f` hands one of two parts to it.
pub(crate) fn with_helper<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    let helper = SpinHelper::new();
    let (out, ()) = rayon::join(
        || {
            let previous = CURRENT.with(|c| c.replace(&helper));
            // Stops the helper even if `f` panics (the join then waits for it).
            struct Stop<'a>(&'a SpinHelper, *const SpinHelper);
            impl Drop for Stop<'_> {
                fn drop(&mut self) {
                    CURRENT.with(|c| c.set(self.1));
                    self.0.state.store(STOP, Ordering::Release);
                }
            }
            let _stop = Stop(&helper, previous);
            f()
        },
        || helper.serve(),
    );
    out
}

/// Runs `f(k, item)` for every item, in parallel: two items on this thread and the
/// helper of [`with_helper`] when one is running here, otherwise on the current rayon
/// pool.
pub(crate) fn run_parts<T: Send>(items: Vec<T>, f: impl Fn(usize, T) + Sync) {
    let helper = CURRENT.with(Cell::get);
    if items.len() == 2 && !helper.is_null() {
        // SAFETY: CURRENT points at the helper of the `with_helper` call running on this
        // thread (it is reset before that helper is dropped).
        let helper = unsafe { &*helper };
        let mut it = items.into_iter();
        let (a, b) = (it.next().expect("two items"), it.next().expect("two items"));
        let f = &f;
        helper.run_pair(|| f(0, a), move || f(1, b));
        return;
    }
    use rayon::prelude::*;
    items
        .into_par_iter()
        .enumerate()
        .for_each(|(k, item)| f(k, item));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parts_run_once_each_with_and_without_a_helper() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        for helped in [false, true] {
            let mut data = vec![0u64; 1000];
            let run = |data: &mut Vec<u64>| {
                for round in 0..500u64 {
                    let (a, b) = data.split_at_mut(400);
                    run_parts(vec![a, b], |k, part| {
                        for x in part.iter_mut() {
                            *x += round * (k as u64 + 1);
                        }
                    });
                }
            };
            pool.install(|| {
                if helped {
                    with_helper(|| run(&mut data))
                } else {
                    run(&mut data)
                }
            });
            let sum: u64 = (0..500).sum();
            assert!(data[..400].iter().all(|&x| x == sum), "{helped}");
            assert!(data[400..].iter().all(|&x| x == 2 * sum), "{helped}");
        }
    }

    #[test]
    fn a_one_thread_pool_runs_both_parts_on_the_caller() {
        // No second worker ever takes the helper's half: nothing waits for it.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let mut data = [0u32; 2];
        pool.install(|| {
            with_helper(|| {
                for _ in 0..100 {
                    let (a, b) = data.split_at_mut(1);
                    run_parts(vec![a, b], |_, part| part[0] += 1);
                }
            })
        });
        assert_eq!(data, [100, 100]);
    }
}
