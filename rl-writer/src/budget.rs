//! A byte budget shared by the recording threads and the workers: backpressure instead of
//! unbounded memory.

use std::sync::{Condvar, Mutex};

pub(crate) struct Budget {
    limit: usize,
    used: Mutex<usize>,
    peak: std::sync::atomic::AtomicUsize,
    freed: Condvar,
}

impl Budget {
    pub(crate) fn new(limit: usize) -> Self {
        Self {
            limit: limit.max(1),
            used: Mutex::new(0),
            peak: std::sync::atomic::AtomicUsize::new(0),
            freed: Condvar::new(),
        }
    }

    /// Takes `n` bytes, waiting while that would exceed the limit (one chunk may always proceed
    /// when nothing else is held, so a chunk larger than the budget cannot deadlock).
    pub(crate) fn acquire(&self, n: usize) {
        let mut used = self.used.lock().unwrap_or_else(|p| p.into_inner());
        while *used > 0 && *used + n > self.limit {
            used = self.freed.wait(used).unwrap_or_else(|p| p.into_inner());
        }
        *used += n;
        self.peak.fetch_max(*used, std::sync::atomic::Ordering::Relaxed);
    }

    pub(crate) fn release(&self, n: usize) {
        let mut used = self.used.lock().unwrap_or_else(|p| p.into_inner());
        *used = used.saturating_sub(n);
        self.freed.notify_all();
    }

    /// The most bytes held at once.
    pub(crate) fn peak(&self) -> usize {
        self.peak.load(std::sync::atomic::Ordering::Relaxed)
    }
}
