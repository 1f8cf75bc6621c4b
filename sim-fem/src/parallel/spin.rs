//! A second thread kept awake for the length of a solve, for its many short parallel
//! regions (with one sweep each way, two per V-cycle and one per CG product, and a few
//! per step for the smoother's refresh).
//!
//! Why: on a two-thread rayon pool the regions of a 12,288-tet MG-PCG solve (tens of µs
//! each, a few hundred per step) often found the other worker asleep, and waking it cost
//! about as much as the region saved: `perf` found the second worker in the scheduler in
//! 15 % of all the step's samples, and the sweeps split 3 : 1 between the workers
//! (2026-11-28). Here the helper spins
//! on one atomic between regions, so handing it half of a region costs a cache-line
//! transfer.
//!
//! No deadlock: [`with_helper`] starts the helper as the second half of a `rayon::join`,
//! and a region never waits for a helper that has not taken its half: the caller takes
//! it back (an atomic compare-and-swap decides who runs it) and runs it itself. With no
//! free worker the solve runs on one thread, as before. A region inside a region (or a
//! `with_helper` inside another) runs on the calling thread alone, and a panic in either
//! half is passed on to the caller only once the helper has let go of the job.

use std::any::Any;
use std::cell::Cell;
use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};
use std::sync::Mutex;
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
    /// is `POSTED` or `RUNNING` (the caller neither returns nor unwinds before it leaves
    /// them).
    job: AtomicPtr<&'static mut (dyn FnMut() + Send)>,
    /// The payload of a job that panicked on the helper.
    panic: Mutex<Option<Box<dyn Any + Send>>>,
}

/// Spins of a waiting thread between two yields of its core (so that a preempted peer
/// gets to run on an oversubscribed machine).
const SPINS_PER_YIELD: u32 = 4096;

/// One step of a spin-wait: a spin hint, and every [`SPINS_PER_YIELD`] spins a yield.
fn spin_wait(spins: &mut u32) {
    *spins = spins.wrapping_add(1);
    if spins.is_multiple_of(SPINS_PER_YIELD) {
        std::thread::yield_now();
    } else {
        std::hint::spin_loop();
    }
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
            panic: Mutex::new(None),
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
                    let state = match catch_unwind(AssertUnwindSafe(job)) {
                        Ok(()) => DONE,
                        Err(payload) => {
                            *self.panic.lock().unwrap_or_else(|e| e.into_inner()) = Some(payload);
                            PANICKED
                        }
                    };
                    self.state.store(state, Ordering::Release);
                    idle_spins = 0;
                }
                _ => spin_wait(&mut idle_spins),
            }
        }
    }

    /// Runs `mine` on this thread and `theirs` on the helper (or here, if the helper has
    /// not taken it by the time `mine` is done), and returns when both are done. Called
    /// while a job is already out (a region inside `mine`), it runs both here.
    fn run_pair(&self, mine: impl FnOnce(), theirs: impl FnOnce() + Send) {
        // Only this thread posts jobs and resets the state to IDLE: anything else means a
        // job of an enclosing region is still out.
        if self.state.load(Ordering::Acquire) != IDLE {
            mine();
            theirs();
            return;
        }
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
        // A panic here must not unwind past the job while the helper may run it.
        let mine = catch_unwind(AssertUnwindSafe(mine));
        if self
            .state
            .compare_exchange(POSTED, IDLE, Ordering::Acquire, Ordering::Relaxed)
            .is_ok()
        {
            if let Err(payload) = mine {
                resume_unwind(payload);
            }
            job_ref();
            return;
        }
        let mut spins = 0;
        let panicked = loop {
            match self.state.load(Ordering::Acquire) {
                DONE => break false,
                PANICKED => break true,
                _ => spin_wait(&mut spins),
            }
        };
        self.state.store(IDLE, Ordering::Release);
        if let Err(payload) = mine {
            resume_unwind(payload);
        }
        if panicked {
            let payload = self.panic.lock().unwrap_or_else(|e| e.into_inner()).take();
            resume_unwind(payload.unwrap_or_else(|| Box::new("a part panicked on the helper")));
        }
    }
}

/// Runs `f` on this thread with a helper spinning on another worker of the current
/// rayon pool for its length; [`run_parts`] inside `f` hands one of two parts to it.
/// Inside another `with_helper` on this thread, just runs `f`.
pub(crate) fn with_helper<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    if !CURRENT.with(Cell::get).is_null() {
        return f();
    }
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
    fn regions_inside_regions_run_every_part() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let mut data = vec![0u32; 8];
        pool.install(|| {
            with_helper(|| {
                for _ in 0..200 {
                    let (a, b) = data.split_at_mut(4);
                    run_parts(vec![a, b], |_, half| {
                        let (c, d) = half.split_at_mut(2);
                        // On the caller this nests in a posted region; on the helper
                        // there is no helper: both run all their parts.
                        run_parts(vec![c, d], |_, q| q.iter_mut().for_each(|x| *x += 1));
                        with_helper(|| half[0] += 1);
                    });
                }
            })
        });
        assert_eq!(data, [400, 200, 200, 200, 400, 200, 200, 200]);
    }

    #[test]
    fn a_panic_in_either_half_reaches_the_caller_with_its_message() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        for bad in [0usize, 1] {
            let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                pool.install(|| {
                    with_helper(|| {
                        for round in 0..100 {
                            run_parts(vec![0usize, 1], |k, _| {
                                if k == bad && round == 50 {
                                    panic!("part {k} failed");
                                }
                            });
                        }
                    })
                })
            }));
            let payload = caught.expect_err("the panic is passed on");
            let message = payload
                .downcast_ref::<String>()
                .cloned()
                .unwrap_or_default();
            assert_eq!(message, format!("part {bad} failed"));
        }
        // The pool is still usable: no thread is left spinning on a dead job.
        let mut data = [0u32; 2];
        pool.install(|| {
            with_helper(|| {
                let (a, b) = data.split_at_mut(1);
                run_parts(vec![a, b], |_, part| part[0] += 1);
            })
        });
        assert_eq!(data, [1, 1]);
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
