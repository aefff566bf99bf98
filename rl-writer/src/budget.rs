//! A byte budget shared by the recording threads and the workers: backpressure instead of
//! unbounded memory.

use std::sync::{Condvar, Mutex};

pub(crate) struct Budget {
    limit: usize,
    /// Chunks that may wait at once, whatever their bytes.
    max_chunks: usize,
    /// Bytes and chunks held.
    used: Mutex<(usize, usize)>,
    peak: std::sync::atomic::AtomicUsize,
    freed: Condvar,
}

impl Budget {
    pub(crate) fn new(limit: usize, max_chunks: usize) -> Self {
        Self {
            limit: limit.max(1),
            max_chunks: max_chunks.max(1),
            used: Mutex::new((0, 0)),
            peak: std::sync::atomic::AtomicUsize::new(0),
            freed: Condvar::new(),
        }
    }

    /// Takes `n` bytes for one chunk, waiting while that would exceed the byte limit or the
    /// chunk limit (one chunk may always proceed when nothing else is held, so a chunk larger
    /// than the budget cannot deadlock).
    pub(crate) fn acquire(&self, n: usize) {
        let mut used = self.used.lock().unwrap_or_else(|p| p.into_inner());
        while used.1 > 0 && (used.0 + n > self.limit || used.1 >= self.max_chunks) {
            used = self.freed.wait(used).unwrap_or_else(|p| p.into_inner());
        }
        used.0 += n;
        used.1 += 1;
        self.peak.fetch_max(used.0, std::sync::atomic::Ordering::Relaxed);
    }

    /// Gives back the `n` bytes of one chunk.
    pub(crate) fn release(&self, n: usize) {
        let mut used = self.used.lock().unwrap_or_else(|p| p.into_inner());
        used.0 = used.0.saturating_sub(n);
        used.1 = used.1.saturating_sub(1);
        self.freed.notify_all();
    }

    /// The most bytes held at once.
    pub(crate) fn peak(&self) -> usize {
        self.peak.load(std::sync::atomic::Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::time::Duration;

    #[test]
    fn the_chunk_limit_blocks_like_the_byte_limit() {
        let b = Arc::new(Budget::new(1 << 30, 2));
        b.acquire(10);
        b.acquire(10);
        let passed = Arc::new(AtomicBool::new(false));
        let t = {
            let (b, passed) = (b.clone(), passed.clone());
            std::thread::spawn(move || {
                b.acquire(10);
                passed.store(true, Ordering::SeqCst);
            })
        };
        std::thread::sleep(Duration::from_millis(100));
        assert!(!passed.load(Ordering::SeqCst), "a third chunk waits while two are held");
        b.release(10);
        t.join().unwrap();
        assert!(passed.load(Ordering::SeqCst));
        assert_eq!(b.peak(), 20);
        // A chunk larger than the byte budget still goes when nothing is held.
        let small = Budget::new(5, 4);
        small.acquire(50);
        small.release(50);
        small.acquire(50);
    }
}
