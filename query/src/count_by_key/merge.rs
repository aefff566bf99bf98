//! The merge: the workers' tables (or their spill files) bucket by bucket, into output batches.

use super::*;

/// What the merge needs to make output batches.
#[derive(Clone)]
pub(super) struct Output {
    pub(super) schema: SchemaRef,
    pub(super) outputs: Vec<(Counted, String)>,
    pub(super) stride: usize,
    pub(super) batch_size: usize,
    pub(super) baseline: BaselineMetrics,
    /// The memory pool's limit (`usize::MAX` when it has none).
    pub(super) limit: usize,
}

/// Merges the workers' counts bucket by bucket (ranges of buckets in parallel) and sends them
/// as batches of the output schema. When any worker spilled, every worker's tables are spilled
/// too, their reservations freed, and each bucket is read back and merged alone, charged to the
/// pool: the merge then holds one bucket's groups (1/256 of them) per task.
pub(super) async fn merge(
    counted: Vec<(Counts, Option<Spilled>, Budget)>,
    out: &Output,
    spill: &SpillTo,
    pool: &Arc<dyn MemoryPool>,
    tx: &Sender<Result<RecordBatch>>,
) -> Result<()> {
    let stride = out.stride;
    let mut null_key = vec![0u64; stride - 1];
    let mut rows = 0u64;
    let spilling = counted.iter().any(|(_, s, _)| s.is_some());
    let mut files = Vec::new();
    let mut by_bucket: Vec<Vec<Part>> = (0..BUCKETS).map(|_| Vec::new()).collect();
    let mut reservations = Vec::new();
    for (mut c, mut s, mut r) in counted {
        for (n, v) in null_key.iter_mut().zip(&c.null_key) {
            *n += v;
        }
        rows += c.rows;
        if spilling {
            if !c.is_empty_but_pending() {
                let refused = || DataFusionError::Internal("CountByKeyExec spilled with no disk manager".into());
                spill.run(&mut c, &mut s, refused)?;
            }
            r.free();
            if let Some(s) = s {
                files.push(s.finish()?);
            }
            continue;
        }
        match c.narrow {
            Some(narrow) => narrow.into_iter().enumerate().for_each(|(b, t)| by_bucket[b].push(Part::Narrow(t))),
            None => c.tables.into_iter().enumerate().for_each(|(b, t)| by_bucket[b].push(Part::Wide(t))),
        }
        reservations.push(r);
    }
    let files = Arc::new(files);
    // Narrow tables merge into a narrow table while the sum of their counts fits its low half.
    let narrow_ok = rows < LOW;
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 16);
    let per = BUCKETS.div_ceil(workers);
    let mut tasks = Vec::new();
    let mut first = 0;
    while !by_bucket.is_empty() {
        let rest = by_bucket.split_off(per.min(by_bucket.len()));
        let chunk = std::mem::replace(&mut by_bucket, rest);
        let range = first..first + chunk.len();
        first = range.end;
        let (files, tx) = (files.clone(), tx.clone());
        let reservation = MemoryConsumer::new(format!("CountByKeyExec merge[{}]", tasks.len())).register(pool);
        let reservation = Budget { reservation, share: out.limit / workers };
        let ctx = MergeTask { out: out.clone(), narrow_ok, reservation };
        tasks.push(SpawnedTask::spawn(async move { ctx.run(chunk, range, &files, &tx).await }));
    }
    for t in tasks {
        t.join().await.map_err(|e| DataFusionError::ExecutionJoin(Box::new(e)))??;
    }
    drop(reservations);
    if null_key[0] > 0 {
        let key: ArrayRef = Arc::new(UInt64Array::from(vec![None::<u64>]));
        let cols = out
            .outputs
            .iter()
            .map(|(what, _)| Arc::new(Int64Array::from(vec![null_key[what.column()] as i64])) as ArrayRef)
            .collect();
        let b = batch(&out.schema, key, cols)?;
        out.baseline.record_output(b.num_rows());
        // A closed channel: the stream was dropped, nobody wants the rest.
        let _ = tx.send(Ok(b)).await;
    }
    Ok(())
}

impl Output {
    /// The counts of `keys`, as output batches.
    pub(super) fn batches(&self, keys: &[u64], counts: &[Vec<i64>]) -> Result<Vec<RecordBatch>> {
        let mut batches = Vec::new();
        let mut start = 0;
        while start < keys.len() {
            let end = (start + self.batch_size).min(keys.len());
            let key: ArrayRef = Arc::new(UInt64Array::from(keys[start..end].to_vec()));
            let cols = self
                .outputs
                .iter()
                .map(|(what, _)| Arc::new(Int64Array::from(counts[what.column()][start..end].to_vec())) as ArrayRef)
                .collect();
            batches.push(batch(&self.schema, key, cols)?);
            start = end;
        }
        Ok(batches)
    }
}

/// One merging task: a range of buckets, from the workers' tables in memory or their spill files.
pub(super) struct MergeTask {
    pub(super) out: Output,
    pub(super) narrow_ok: bool,
    /// What the task holds while it merges a bucket read back from spill files.
    pub(super) reservation: Budget,
}

impl MergeTask {
    pub(super) async fn run(
        mut self,
        in_memory: Vec<Vec<Part>>,
        range: std::ops::Range<usize>,
        files: &[Written],
        tx: &Sender<Result<RecordBatch>>,
    ) -> Result<()> {
        let stride = self.out.stride;
        let mut readers = Vec::with_capacity(files.len());
        for s in files {
            let Some(path) = s.file.path() else {
                return Err(DataFusionError::NotImplemented(
                    "CountByKeyExec reads its spill files back by path; this disk manager's have none".into(),
                ));
            };
            readers.push(std::fs::File::open(path).map_err(|e| spill_error("opening", s.file.as_ref(), &e))?);
        }
        let narrow_runs = files.iter().all(|f| f.runs.iter().all(|r| r.narrow));
        let mut keys = Vec::new();
        let mut counts: Vec<Vec<i64>> = vec![Vec::new(); stride - 1];
        for (parts, b) in in_memory.into_iter().zip(range) {
            let timer = self.out.baseline.elapsed_compute().timer();
            let mut merged = Merged::new(self.narrow_ok && narrow_runs && parts.iter().all(Part::is_narrow));
            for p in parts {
                merged.add(p, stride);
            }
            // Room for every spilled entry of the bucket at once (they are its distinct keys when
            // no key is in two runs), where the share allows: no doubling and rehashing.
            let spilled: usize = files.iter().flat_map(|f| &f.runs).map(|r| r.entries(b) as usize).sum();
            if spilled > 0 && self.reservation.try_resize(merged.bytes() + merged.growth(spilled, stride)).is_ok() {
                merged.reserve(spilled, stride);
            }
            // Runs read back one at a time: the merged table and one run's part of the bucket.
            for (s, f) in files.iter().zip(&mut readers) {
                for run in &s.runs {
                    if let Some(p) = s.read_bucket(f, run, b, stride)? {
                        self.reservation.try_resize(merged.bytes() + p.bytes())?;
                        merged.add(p, stride);
                    }
                }
            }
            merged.list(stride, &mut keys, &mut counts);
            timer.done();
            // Buckets are gathered into batches of about the session's batch size.
            if keys.len() >= self.out.batch_size && !self.send(&mut keys, &mut counts, tx).await? {
                return Ok(());
            }
        }
        self.send(&mut keys, &mut counts, tx).await?;
        Ok(())
    }

    /// Sends the merged keys and counts as batches and empties them; false when the stream was
    /// dropped (nobody wants the rest).
    pub(super) async fn send(
        &mut self,
        keys: &mut Vec<u64>,
        counts: &mut [Vec<i64>],
        tx: &Sender<Result<RecordBatch>>,
    ) -> Result<bool> {
        let batches = self.out.batches(keys, counts)?;
        keys.clear();
        counts.iter_mut().for_each(Vec::clear);
        self.reservation.free();
        for b in batches {
            self.out.baseline.record_output(b.num_rows());
            if tx.send(Ok(b)).await.is_err() {
                return Ok(false);
            }
        }
        Ok(true)
    }
}

/// One output batch: the keys back in their type (signed keys from their bits), then the counts.
pub(super) fn batch(schema: &SchemaRef, key: ArrayRef, counts: Vec<ArrayRef>) -> Result<RecordBatch> {
    let key_type = schema.field(0).data_type();
    let key = if key_type.is_signed_integer() {
        let signed: Int64Array = key.as_primitive::<UInt64Type>().unary(|v| v as i64);
        cast(&signed, key_type)?
    } else {
        cast(&key, key_type)?
    };
    let mut columns = vec![key];
    columns.extend(counts);
    Ok(RecordBatch::try_new(schema.clone(), columns)?)
}

/// What one bucket's merge adds up.
pub(super) enum Part {
    /// A worker's table.
    Wide(Table),
    Narrow(Narrow),
    /// A run's entries read back from a spill file: `stride` words each (the key, its counts);
    /// `narrow` when they fit a [`Narrow`] table.
    Entries {
        words: Vec<u64>,
        narrow: bool,
    },
}

impl Part {
    pub(super) fn bytes(&self) -> usize {
        match self {
            Part::Wide(t) => t.bytes(),
            Part::Narrow(n) => n.bytes(),
            Part::Entries { words, .. } => words.len() * 8,
        }
    }

    pub(super) fn is_narrow(&self) -> bool {
        matches!(self, Part::Narrow(_) | Part::Entries { narrow: true, .. })
    }
}

/// One bucket's merged table, narrow while every part is.
pub(super) enum Merged {
    Narrow(Narrow),
    Wide(Table),
}

impl Merged {
    pub(super) fn new(narrow: bool) -> Self {
        if narrow { Merged::Narrow(Narrow::default()) } else { Merged::Wide(Table::default()) }
    }

    /// Adds a part's counts (a narrow table takes only narrow parts).
    pub(super) fn add(&mut self, p: Part, stride: usize) {
        match (self, p) {
            (Merged::Narrow(base), Part::Narrow(n)) if base.len == 0 => *base = n,
            (Merged::Narrow(base), Part::Narrow(n)) => {
                base.reserve(n.len);
                for w in n.words.into_iter().filter(|&w| w != 0) {
                    base.add(w >> 32, w & LOW);
                }
            }
            (Merged::Narrow(base), Part::Entries { words, .. }) => {
                for chunk in words.chunks(2048) {
                    base.reserve(chunk.len() / 2);
                    for e in chunk.chunks_exact(2) {
                        base.add(e[0], e[1]);
                    }
                }
            }
            // Never met: a table is narrow only when all its parts are (`MergeTask::run`).
            (Merged::Narrow(_), Part::Wide(_)) => debug_assert!(false, "a wide part in a narrow merge"),
            (Merged::Wide(base), Part::Wide(t)) if base.len == 0 => *base = t,
            (Merged::Wide(base), Part::Wide(t)) => {
                add_entries(base, t.words.chunks_exact(stride).filter(|s| s[1] != 0), stride);
            }
            (Merged::Wide(base), Part::Entries { words, .. }) => add_entries(base, words.chunks_exact(stride), stride),
            (Merged::Wide(base), Part::Narrow(n)) => {
                base.reserve(n.len, stride);
                for w in n.words.into_iter().filter(|&w| w != 0) {
                    let slot = base.slot_reserved(w >> 32, mix(w >> 32), stride);
                    base.words[slot + 1] += w & LOW;
                }
            }
        }
    }

    pub(super) fn bytes(&self) -> usize {
        match self {
            Merged::Narrow(n) => n.bytes(),
            Merged::Wide(t) => t.bytes(),
        }
    }

    pub(super) fn growth(&self, additional: usize, stride: usize) -> usize {
        match self {
            Merged::Narrow(n) => n.growth(additional),
            Merged::Wide(t) => t.growth(additional, stride),
        }
    }

    pub(super) fn reserve(&mut self, additional: usize, stride: usize) {
        match self {
            Merged::Narrow(n) => n.reserve(additional),
            Merged::Wide(t) => t.reserve(additional, stride),
        }
    }

    /// Appends the keys and their counts.
    pub(super) fn list(&self, stride: usize, keys: &mut Vec<u64>, counts: &mut [Vec<i64>]) {
        match self {
            Merged::Narrow(base) => {
                keys.reserve(base.len);
                for w in base.words.iter().copied().filter(|&w| w != 0) {
                    keys.push(w >> 32);
                    counts[0].push((w & LOW) as i64);
                }
            }
            Merged::Wide(base) => {
                keys.reserve(base.len);
                for s in base.words.chunks_exact(stride).filter(|s| s[1] != 0) {
                    keys.push(s[0]);
                    for (j, c) in counts.iter_mut().enumerate() {
                        c.push(s[1 + j] as i64);
                    }
                }
            }
        }
    }
}
