//! Write mode: background workers encode chunks into Parquet segments and seal them.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Sender};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use store::{DatasetWriter, KindTable, RayRows, RowLayout, SegmentWriter};

use crate::budget::Budget;
use crate::sink::{RecorderOptions, Sink, Summary};
use crate::{Error, Result};

/// Chunks that may wait for each writer thread before `end_tree` blocks (besides the byte budget).
const QUEUED_CHUNKS_PER_WRITER: usize = 4;

/// Emptied chunk buffers kept for the tracing threads, per writer thread.
const SPARE_CHUNKS_PER_WRITER: usize = 2 * QUEUED_CHUNKS_PER_WRITER;

/// A chunk waiting for a writer: its rows, the kinds as of its submission, its bytes in the budget.
type Queued = (Box<RayRows>, Arc<KindTable>, usize);

/// What a writer thread does next.
enum Job {
    Chunk(Queued),
    Flush(Arc<KindTable>, Sender<()>),
    /// The open segment is older than `seal_interval`.
    SealDue,
    /// The recording is over (or every writer is gone): seal and stop.
    Closed,
}

/// A flush asked of one writer: it seals once every chunk submitted before the flush is taken.
struct Flush {
    upto: u64,
    kinds: Arc<KindTable>,
    ack: Sender<()>,
}

/// Chunks waiting for the writers, one queue for all of them: a writer free takes the next chunk,
/// so one writer busy sealing (or preempted) does not leave the other idle while its own queue
/// is full (as with a channel per writer served round robin).
#[derive(Default)]
struct QueueState {
    chunks: VecDeque<Queued>,
    submitted: u64,
    taken: u64,
    /// Per writer: the flush it owes, and whether it still runs.
    flushes: Vec<Option<Flush>>,
    alive: Vec<bool>,
    closed: bool,
}

#[derive(Default)]
struct Queue {
    state: Mutex<QueueState>,
    ready: Condvar,
}

impl Queue {
    fn lock(&self) -> MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The next job of writer `me`: its flush once the chunks before it are taken, else the next
    /// chunk, else waiting (at most until `seal_at`).
    fn next(&self, me: usize, seal_at: Option<Instant>) -> Job {
        let mut st = self.lock();
        loop {
            let due = st.flushes.get(me).and_then(Option::as_ref).is_some_and(|f| st.taken >= f.upto);
            if due && let Some(f) = st.flushes.get_mut(me).and_then(Option::take) {
                return Job::Flush(f.kinds, f.ack);
            }
            if let Some(queued) = st.chunks.pop_front() {
                st.taken += 1;
                return Job::Chunk(queued);
            }
            if st.closed {
                return Job::Closed;
            }
            st = match seal_at {
                Some(at) => {
                    let now = Instant::now();
                    if now >= at {
                        return Job::SealDue;
                    }
                    self.ready.wait_timeout(st, at - now).unwrap_or_else(|p| p.into_inner()).0
                }
                None => self.ready.wait(st).unwrap_or_else(|p| p.into_inner()),
            };
        }
    }
}

/// Marks its writer gone when the thread ends, even by a panic: the last one out closes the
/// queue and drops what is left in it (releasing its budget, counting its trees as lost), so no
/// tracing thread waits on a budget nobody frees and no flush waits on a writer that is gone.
struct Leaving {
    me: usize,
    queue: Arc<Queue>,
    budget: Arc<Budget>,
    shared: Arc<Shared>,
}

impl Drop for Leaving {
    fn drop(&mut self) {
        let mut st = self.queue.lock();
        if let Some(a) = st.alive.get_mut(self.me) {
            *a = false;
        }
        if let Some(f) = st.flushes.get_mut(self.me) {
            f.take();
        }
        if st.alive.iter().any(|&a| a) {
            return;
        }
        st.closed = true;
        for (chunk, _, bytes) in st.chunks.drain(..) {
            self.shared.lost_trees.fetch_add(chunk.trees.len() as u64, Ordering::Relaxed);
            self.budget.release(bytes);
        }
        drop(st);
        self.queue.ready.notify_all();
    }
}

#[derive(Default)]
struct Shared {
    first_error: Mutex<Option<store::Error>>,
    lost_trees: AtomicU64,
    trees: AtomicU64,
    rays: AtomicU64,
    segments: AtomicU64,
    bytes: AtomicU64,
    /// Chunk buffers the writers are done with, emptied, for the tracing threads to fill again:
    /// a buffer allocated by a tracing thread and freed by a writer went back to the allocator,
    /// and the next chunk faulted fresh pages in (half the replay thread's time in `bench store`).
    spare: Mutex<Vec<RayRows>>,
    /// The most spare buffers kept, and the largest (in rays) worth keeping.
    spare_count: usize,
    spare_rays: usize,
}

impl Shared {
    fn fail(&self, e: store::Error, lost_trees: u64) {
        self.lost_trees.fetch_add(lost_trees, Ordering::Relaxed);
        let mut f = self.first_error.lock().unwrap_or_else(|p| p.into_inner());
        if f.is_none() {
            *f = Some(e);
        }
    }

    fn failed(&self) -> bool {
        self.first_error.lock().unwrap_or_else(|p| p.into_inner()).is_some()
    }
}

/// The write-mode sink.
pub(crate) struct WriteSink {
    ds: Arc<DatasetWriter>,
    /// Optional tables being written in the background (`write_table` returns at once: the
    /// renderer's BVH table would otherwise hold up its first traced ray).
    tables: Mutex<Vec<JoinHandle<store::Result<()>>>>,
    workers: Mutex<Vec<JoinHandle<()>>>,
    queue: Arc<Queue>,
    budget: Arc<Budget>,
    shared: Arc<Shared>,
}

impl WriteSink {
    pub(crate) fn start(dir: &Path, options: &RecorderOptions) -> Result<Self> {
        let ds = Arc::new(DatasetWriter::create(dir, options.payload.clone(), options.write.clone())?);
        // A few chunks queued per writer keep it busy; more would only be memory the tracing
        // threads fault in fresh while they run ahead of the writers (in `bench store`, whose
        // replay outruns them, a full 256 MB queue cost ~0.25 s of page zeroing per 10M rays).
        let workers_n = options.workers.max(1);
        let budget = Arc::new(Budget::new(options.memory_budget, QUEUED_CHUNKS_PER_WRITER * workers_n));
        let shared = Arc::new(Shared {
            spare_count: SPARE_CHUNKS_PER_WRITER * workers_n,
            spare_rays: 2 * options.chunk_rays.max(1),
            ..Default::default()
        });
        let queue = Arc::new(Queue::default());
        {
            let mut st = queue.lock();
            st.flushes = (0..workers_n).map(|_| None).collect();
            st.alive = vec![true; workers_n];
        }
        let mut workers = Vec::new();
        for i in 0..workers_n {
            let leaving = Leaving { me: i, queue: queue.clone(), budget: budget.clone(), shared: shared.clone() };
            let ctx = WorkerCtx {
                ds: ds.clone(),
                layout: RowLayout::new(&options.payload),
                budget: budget.clone(),
                shared: shared.clone(),
                segment_rays: options.segment_rays.max(1),
                seal_interval: options.seal_interval,
                segment: None,
                kinds: Arc::new(KindTable::default()),
            };
            let spawned = std::thread::Builder::new().name(format!("rl-writer-{i}")).spawn(move || ctx.run(leaving));
            match spawned {
                Ok(join) => workers.push(join),
                Err(e) => {
                    // The writers started so far stop (the queue closes once they are all gone).
                    queue.lock().closed = true;
                    queue.ready.notify_all();
                    for j in workers {
                        let _ = j.join();
                    }
                    return Err(Error::Store(store::Error::Io {
                        action: "starting a writer thread",
                        path: dir.to_path_buf(),
                        source: e,
                    }));
                }
            }
        }
        Ok(Self { ds, tables: Mutex::new(Vec::new()), workers: Mutex::new(workers), queue, budget, shared })
    }

    /// Asks every running writer to seal once the chunks submitted so far are taken.
    fn send_all(&self, kinds: &Arc<KindTable>) -> Vec<mpsc::Receiver<()>> {
        let mut acks = Vec::new();
        let mut st = self.queue.lock();
        let upto = st.submitted;
        for i in 0..st.flushes.len() {
            if st.alive.get(i).copied().unwrap_or(false) {
                let (ack, rx) = mpsc::channel();
                st.flushes[i] = Some(Flush { upto, kinds: kinds.clone(), ack });
                acks.push(rx);
            }
        }
        drop(st);
        self.queue.ready.notify_all();
        acks
    }

    /// Closes the queue and waits for the writers; whether one panicked.
    fn stop_workers(&self) -> bool {
        self.queue.lock().closed = true;
        self.queue.ready.notify_all();
        let joins = std::mem::take(&mut *self.workers.lock().unwrap_or_else(|p| p.into_inner()));
        let mut panicked = false;
        for j in joins {
            panicked |= j.join().is_err();
        }
        panicked
    }

    /// Waits for the tables being written; the first failure comes back.
    fn join_tables(&self) -> Result<()> {
        let joins = std::mem::take(&mut *self.tables.lock().unwrap_or_else(|p| p.into_inner()));
        let mut first = Ok(());
        for j in joins {
            let r = match j.join() {
                Ok(r) => r.map_err(Error::Store),
                Err(_) => Err(Error::WorkerPanicked),
            };
            if first.is_ok() {
                first = r;
            }
        }
        first
    }

    fn error(&self) -> Result<()> {
        let mut f = self.shared.first_error.lock().unwrap_or_else(|p| p.into_inner());
        match f.take() {
            None => Ok(()),
            Some(source) => {
                let lost = self.shared.lost_trees.load(Ordering::Relaxed);
                // Keep reporting on later calls too.
                *f = Some(store::Error::Corrupt {
                    path: self.ds.dir().to_path_buf(),
                    what: "recording".into(),
                    message: format!("an earlier write failed: {source}"),
                });
                Err(Error::Write { source, lost_trees: lost })
            }
        }
    }
}

impl Sink for WriteSink {
    fn write_table(&self, name: &str, batch: arrow::array::RecordBatch) -> Result<()> {
        DatasetWriter::check_table_name(name)?;
        let (ds, name) = (self.ds.clone(), name.to_string());
        let join = std::thread::Builder::new()
            .name("rl-table".into())
            .spawn(move || ds.write_table(&name, &batch))
            .map_err(|e| {
                Error::Store(store::Error::Io {
                    action: "starting a table writer thread",
                    path: self.ds.dir().to_path_buf(),
                    source: e,
                })
            })?;
        self.tables.lock().unwrap_or_else(|p| p.into_inner()).push(join);
        Ok(())
    }

    fn set_attributes(&self, attributes: Vec<(String, String)>) -> Result<()> {
        Ok(self.ds.set_attributes(attributes)?)
    }

    fn spare(&self) -> Option<RayRows> {
        self.shared.spare.lock().unwrap_or_else(|p| p.into_inner()).pop()
    }

    fn submit(&self, chunk: RayRows, kinds: &Arc<KindTable>) {
        let bytes = chunk.heap_bytes();
        self.budget.acquire(bytes);
        let mut st = self.queue.lock();
        if st.closed {
            drop(st);
            self.budget.release(bytes);
            self.shared.lost_trees.fetch_add(chunk.trees.len() as u64, Ordering::Relaxed);
            return;
        }
        st.chunks.push_back((Box::new(chunk), kinds.clone(), bytes));
        st.submitted += 1;
        drop(st);
        self.queue.ready.notify_one();
    }

    fn flush(&self, kinds: &Arc<KindTable>) -> Result<()> {
        for ack in self.send_all(kinds) {
            let _ = ack.recv();
        }
        self.join_tables()?;
        self.error()
    }

    fn finish(&self, kinds: &Arc<KindTable>) -> Result<Summary> {
        self.flush(kinds)?;
        if self.stop_workers() {
            return Err(Error::WorkerPanicked);
        }
        self.error()?;
        self.ds.mark_complete()?;
        Ok(Summary {
            trees: self.shared.trees.load(Ordering::Relaxed),
            rays: self.shared.rays.load(Ordering::Relaxed),
            segments: self.shared.segments.load(Ordering::Relaxed),
            bytes: self.shared.bytes.load(Ordering::Relaxed),
            evicted_trees: 0,
            peak_buffered_bytes: self.budget.peak() as u64,
        })
    }
}

impl Drop for WriteSink {
    fn drop(&mut self) {
        // A recorder dropped without `finish` still seals what it has.
        let _ = self.join_tables();
        self.stop_workers();
    }
}

struct WorkerCtx {
    ds: Arc<DatasetWriter>,
    layout: RowLayout,
    budget: Arc<Budget>,
    shared: Arc<Shared>,
    segment_rays: u64,
    seal_interval: Duration,
    segment: Option<(SegmentWriter, Instant, u64)>,
    kinds: Arc<KindTable>,
}

impl WorkerCtx {
    fn run(mut self, leaving: Leaving) {
        let (me, queue) = (leaving.me, leaving.queue.clone());
        loop {
            let seal_at = self.segment.as_ref().map(|(_, opened, _)| *opened + self.seal_interval);
            match queue.next(me, seal_at) {
                Job::Chunk((chunk, kinds, bytes)) => {
                    self.kinds = kinds;
                    self.write(*chunk);
                    self.budget.release(bytes);
                    if self.segment.as_ref().is_some_and(|(s, _, _)| s.rows() >= self.segment_rays) {
                        self.seal();
                    }
                }
                Job::Flush(kinds, ack) => {
                    self.kinds = kinds;
                    self.seal();
                    let _ = ack.send(());
                }
                Job::SealDue => self.seal(),
                Job::Closed => {
                    self.seal();
                    return;
                }
            }
        }
    }

    /// Writes a chunk, then hands its emptied buffers back for the tracing threads.
    fn write(&mut self, mut rows: RayRows) {
        self.write_rows(&rows);
        if rows.core.capacity() <= self.shared.spare_rays {
            rows.clear();
            let mut spare = self.shared.spare.lock().unwrap_or_else(|p| p.into_inner());
            if spare.len() < self.shared.spare_count {
                spare.push(rows);
            }
        }
    }

    fn write_rows(&mut self, rows: &RayRows) {
        let trees = rows.trees.len() as u64;
        if self.shared.failed() {
            self.shared.lost_trees.fetch_add(trees, Ordering::Relaxed);
            return;
        }
        let chunk = match rows.to_columns(&self.layout) {
            Ok(c) => c,
            Err(e) => {
                self.shared.fail(e, trees);
                return;
            }
        };
        if self.segment.is_none() {
            match self.ds.open_segment() {
                Ok(s) => self.segment = Some((s, Instant::now(), 0)),
                Err(e) => {
                    self.shared.fail(e, trees);
                    return;
                }
            }
        }
        if let Some((seg, _, seg_trees)) = &mut self.segment {
            match seg.write(chunk, self.ds.payload(), &self.kinds) {
                Ok(()) => *seg_trees += trees,
                Err(e) => {
                    let lost = *seg_trees + trees;
                    if let Some((s, _, _)) = self.segment.take() {
                        s.abandon();
                    }
                    self.shared.fail(e, lost);
                }
            }
        }
    }

    fn seal(&mut self) {
        let Some((seg, _, seg_trees)) = self.segment.take() else {
            return;
        };
        match seg.seal(&self.ds, &self.kinds) {
            Ok(Some(entry)) => {
                self.shared.trees.fetch_add(entry.trees.rows, Ordering::Relaxed);
                self.shared.rays.fetch_add(entry.rays.rows, Ordering::Relaxed);
                self.shared.segments.fetch_add(1, Ordering::Relaxed);
                self.shared.bytes.fetch_add(entry.rays.bytes + entry.trees.bytes, Ordering::Relaxed);
            }
            Ok(None) => {}
            Err(e) => self.shared.fail(e, seg_trees),
        }
    }
}
