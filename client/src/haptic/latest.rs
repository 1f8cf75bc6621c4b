//! `Latest<T>`: a single-value, newest-wins cell shared between threads, implemented as a
//! sequence lock over `AtomicU64` words (no `unsafe`, no allocation after construction).
//!
//! Writers serialise among themselves through the sequence word (compare-and-swap from an
//! even to an odd value); readers never block a writer and never write: a reader copies the
//! words and accepts them if the sequence was even and unchanged around the copy, which is
//! the fence pattern of Boehm, "Can seqlocks get along with programming language memory
//! models?" (2012).

use std::sync::atomic::{AtomicU64, Ordering, fence};

/// A value that can be stored as a fixed number of 64-bit words.
pub trait Words: Sized {
    /// Number of words.
    const WORDS: usize;
    /// Writes the value into `out` (`out.len() == WORDS`).
    fn to_words(&self, out: &mut [u64]);
    /// Reads a value back from `words` (`words.len() == WORDS`).
    fn from_words(words: &[u64]) -> Self;
}

/// Newest-wins cell. `version()` is 0 until the first `store`.
pub struct Latest<T: Words> {
    seq: AtomicU64,
    data: Box<[AtomicU64]>,
    _t: std::marker::PhantomData<fn() -> T>,
}

impl<T: Words> Default for Latest<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T: Words> std::fmt::Debug for Latest<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Latest")
            .field("version", &self.version())
            .finish()
    }
}

impl<T: Words> Latest<T> {
    /// An empty cell.
    pub fn new() -> Self {
        Latest {
            seq: AtomicU64::new(0),
            data: (0..T::WORDS).map(|_| AtomicU64::new(0)).collect(),
            _t: std::marker::PhantomData,
        }
    }

    /// Number of completed stores.
    pub fn version(&self) -> u64 {
        self.seq.load(Ordering::Acquire) / 2
    }

    /// Stores a value (newest wins). Concurrent writers wait for each other; readers never
    /// delay a writer.
    pub fn store(&self, value: &T) {
        let mut words = [0u64; 64];
        let buf: &mut [u64] = if T::WORDS <= 64 {
            &mut words[..T::WORDS]
        } else {
            // Large values are not used by this module; keep it correct anyway.
            return self.store_slow(value);
        };
        value.to_words(buf);
        self.store_words(buf);
    }

    fn store_slow(&self, value: &T) {
        let mut v = vec![0u64; T::WORDS];
        value.to_words(&mut v);
        self.store_words(&v);
    }

    fn store_words(&self, words: &[u64]) {
        // Take the writer side: even → odd.
        let mut s = self.seq.load(Ordering::Relaxed);
        loop {
            if s & 1 == 1 {
                std::hint::spin_loop();
                s = self.seq.load(Ordering::Relaxed);
                continue;
            }
            match self
                .seq
                .compare_exchange_weak(s, s + 1, Ordering::Acquire, Ordering::Relaxed)
            {
                Ok(_) => break,
                Err(now) => s = now,
            }
        }
        // Orders the odd sequence before the data stores for any reader that sees data.
        fence(Ordering::Release);
        for (d, w) in self.data.iter().zip(words) {
            d.store(*w, Ordering::Relaxed);
        }
        self.seq.store(s + 2, Ordering::Release);
    }

    /// Tries to read a consistent value: `None` if nothing was stored yet or if `tries`
    /// attempts all overlapped a write (then keep the previous value). Returns the value
    /// and its version.
    pub fn try_load(&self, tries: u32) -> Option<(u64, T)> {
        let mut words = [0u64; 64];
        let mut heap;
        let buf: &mut [u64] = if T::WORDS <= 64 {
            &mut words[..T::WORDS]
        } else {
            heap = vec![0u64; T::WORDS];
            &mut heap
        };
        for _ in 0..tries.max(1) {
            let s1 = self.seq.load(Ordering::Acquire);
            if s1 == 0 {
                return None;
            }
            if s1 & 1 == 1 {
                std::hint::spin_loop();
                continue;
            }
            for (b, d) in buf.iter_mut().zip(self.data.iter()) {
                *b = d.load(Ordering::Relaxed);
            }
            fence(Ordering::Acquire);
            let s2 = self.seq.load(Ordering::Relaxed);
            if s1 == s2 {
                return Some((s1 / 2, T::from_words(buf)));
            }
            std::hint::spin_loop();
        }
        None
    }

    /// Reads a consistent value, retrying until one is obtained (`None` only when nothing
    /// was stored yet). For threads that may wait briefly (not the haptic thread).
    pub fn load(&self) -> Option<(u64, T)> {
        loop {
            if self.seq.load(Ordering::Acquire) == 0 {
                return None;
            }
            if let Some(v) = self.try_load(64) {
                return Some(v);
            }
            std::thread::yield_now();
        }
    }
}

pub(crate) fn f(x: f64) -> u64 {
    x.to_bits()
}

pub(crate) fn g(w: u64) -> f64 {
    f64::from_bits(w)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// Three words that must always be equal in a consistent snapshot.
    #[derive(Debug, Clone, Copy, PartialEq)]
    struct Triple(u64);

    impl Words for Triple {
        const WORDS: usize = 3;
        fn to_words(&self, out: &mut [u64]) {
            out.fill(self.0);
        }
        fn from_words(w: &[u64]) -> Self {
            assert!(w[0] == w[1] && w[1] == w[2], "torn read {w:?}");
            Triple(w[0])
        }
    }

    #[test]
    fn empty_then_newest_wins() {
        let c = Latest::<Triple>::new();
        assert!(c.try_load(3).is_none());
        assert!(c.load().is_none());
        c.store(&Triple(5));
        c.store(&Triple(7));
        assert_eq!(c.try_load(1), Some((2, Triple(7))));
        assert_eq!(c.version(), 2);
    }

    #[test]
    fn no_torn_reads_under_contention() {
        let c = Arc::new(Latest::<Triple>::new());
        let writers: Vec<_> = (0..2)
            .map(|k| {
                let c = c.clone();
                std::thread::spawn(move || {
                    for i in 0..50_000u64 {
                        c.store(&Triple(i * 2 + k));
                    }
                })
            })
            .collect();
        let mut ok = 0u64;
        let mut last_version = 0;
        while ok < 50_000 {
            if let Some((v, _t)) = c.try_load(4) {
                assert!(v >= last_version, "versions never go back");
                last_version = v;
                ok += 1;
            }
        }
        for w in writers {
            w.join().unwrap();
        }
        assert_eq!(c.version(), 100_000);
    }
}
