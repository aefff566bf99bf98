//! A worker's counting: input partitions into its tables, held to its share of the memory limit,
//! written to a spill file when the pool refuses them more.

use super::*;

/// Counts input partitions, one after the other, into one set of tables; when the memory pool
/// refuses them more, writes them to a spill file and starts again with empty ones.
pub(super) async fn count_partitions(
    streams: Vec<SendableRecordBatchStream>,
    key: Arc<dyn PhysicalExpr>,
    args: Vec<Arc<dyn PhysicalExpr>>,
    stride: usize,
    mut reservation: Budget,
    spill: SpillTo,
) -> Result<(Counts, Option<Spilled>, Budget)> {
    let mut c = Counts::new(stride, reservation.share);
    let mut spilled = None;
    let mut batches = futures::stream::iter(streams).flatten();
    while let Some(batch) = batches.next().await {
        let batch = batch?;
        let rows = batch.num_rows();
        let k = key.evaluate(&batch)?.into_array(rows)?;
        let (keys, key_nulls) = key_words(&k)?;
        if c.narrow.is_some() {
            c.key_bits |= keys.iter().fold(0, |a, &k| a | k);
        }
        c.rows += rows as u64;
        let valid: Vec<Option<NullBuffer>> =
            args.iter().map(|a| Ok(a.evaluate(&batch)?.into_array(rows)?.logical_nulls())).collect::<Result<_>>()?;
        let mask = |i: usize| -> u64 {
            valid.iter().enumerate().map(|(j, v)| u64::from(v.as_ref().is_none_or(|n| n.is_valid(i))) << j).sum()
        };
        if key_nulls.is_none()
            && args.is_empty()
            && let Some(t) = c.direct.as_mut()
        {
            for chunk in keys.chunks(1024) {
                t.reserve(chunk.len(), stride);
                for &key in chunk {
                    let w = t.slot_reserved(key, mix(key), stride);
                    t.words[w + 1] += 1;
                }
            }
        } else if key_nulls.is_none() && args.is_empty() {
            for &key in keys.iter() {
                c.pending[bucket(key)].push(key);
            }
        } else {
            add_rows(&mut c, &keys, key_nulls.as_ref(), &mask, args.len());
        }
        if c.direct.is_some() {
            c.bucket_direct(false);
        } else {
            c.pending_rows += rows;
        }
        if c.pending_rows >= c.pending_limit {
            flush_or_spill(&mut c, &mut reservation, &spill, &mut spilled)?;
        }
        let now = c.bytes();
        if now != reservation.size()
            && let Err(refused) = reservation.try_resize(now)
        {
            // Over the limit: the pending keys go into the tables (spilled as they fill) and
            // their buffers are given back; then, if that is still too much, the tables are spilled.
            if c.pending_rows > 0 {
                flush_or_spill(&mut c, &mut reservation, &spill, &mut spilled)?;
                c.pending.iter_mut().for_each(|p| *p = Vec::new());
            }
            if reservation.try_resize(c.bytes()).is_err() {
                if !c.is_empty_but_pending() {
                    spill.run(&mut c, &mut spilled, || refused)?;
                } else if !c.release_room() {
                    return Err(refused);
                }
                c.fit(&mut reservation)?;
            }
        }
    }
    c.bucket_direct(true);
    flush_or_spill(&mut c, &mut reservation, &spill, &mut spilled)?;
    Ok((c, spilled, reservation))
}

/// Flushes the pending keys into the tables; each time the pool refuses a table's growth, spills
/// the tables and goes on with empty ones. An error when even empty tables are refused.
pub(super) fn flush_or_spill(
    c: &mut Counts,
    reservation: &mut Budget,
    spill: &SpillTo,
    spilled: &mut Option<Spilled>,
) -> Result<()> {
    loop {
        let Err(refused) = c.flush(reservation) else { return Ok(()) };
        if c.is_empty_but_pending() {
            // Emptied tables kept their room for the next run: given back, the room may do.
            if !c.release_room() {
                return Err(refused);
            }
            reservation.try_resize(c.bytes())?;
            continue;
        }
        spill.run(c, spilled, || refused)?;
        c.fit(reservation)?;
    }
}

/// A worker's (or a merging task's) reservation, held to its share of the memory limit even
/// where the pool would give it more: a greedy pool lets the first task to grow take it all, and
/// the others then could not hold even one table.
pub(super) struct Budget {
    pub(super) reservation: MemoryReservation,
    pub(super) share: usize,
}

impl Budget {
    pub(super) fn size(&self) -> usize {
        self.reservation.size()
    }

    pub(super) fn free(&mut self) {
        self.reservation.free();
    }

    pub(super) fn over(&self, bytes: usize) -> DataFusionError {
        DataFusionError::ResourcesExhausted(format!(
            "{} would hold {bytes} bytes, over its share of the memory limit ({} bytes)",
            self.reservation.consumer().name(),
            self.share
        ))
    }

    pub(super) fn try_grow(&mut self, more: usize) -> Result<()> {
        let want = self.size().saturating_add(more);
        if more > 0 && want > self.share {
            return Err(self.over(want));
        }
        self.reservation.try_grow(more)
    }

    pub(super) fn try_resize(&mut self, bytes: usize) -> Result<()> {
        if bytes > self.size() && bytes > self.share {
            return Err(self.over(bytes));
        }
        self.reservation.try_resize(bytes)
    }
}

/// Where a worker writes its tables when the memory pool refuses them more: the session's disk
/// manager (its temporary directory and its limit on spilled bytes), and the operator's spill
/// metrics (`EXPLAIN ANALYZE` shows `spill_count` and `spilled_bytes`).
#[derive(Clone)]
pub(super) struct SpillTo {
    pub(super) disk: Arc<DiskManager>,
    pub(super) runs: Count,
    pub(super) bytes: Count,
}

impl SpillTo {
    /// Writes `c`'s tables out as a new run of `spilled` (the worker's spill file, created on its
    /// first run) and empties them. Without a temporary directory (a disk manager disabled),
    /// `refused` is the error: the memory pool's, naming the limit.
    pub(super) fn run(
        &self,
        c: &mut Counts,
        spilled: &mut Option<Spilled>,
        refused: impl FnOnce() -> DataFusionError,
    ) -> Result<()> {
        let s = match spilled {
            Some(s) => s,
            None => {
                if !self.disk.tmp_files_enabled() {
                    return Err(refused());
                }
                let file = self.disk.create_tmp_file("CountByKeyExec")?;
                let writer = BufWriter::with_capacity(1 << 20, file.open_writer()?);
                spilled.insert(Spilled { file, writer: Some(writer), len: 0, runs: Vec::new() })
            }
        };
        c.bucket_direct(true);
        let before = s.len;
        s.write_run(c)?;
        self.runs.add(1);
        self.bytes.add((s.len - before) as usize);
        c.clear();
        Ok(())
    }
}

/// A worker's spill file: runs of its tables, each written bucket by bucket, `stride`
/// little-endian words an entry (the key, then its counts). A key may be in several runs; the
/// merge adds them up.
pub(super) struct Spilled {
    pub(super) file: Arc<dyn SpillFile>,
    pub(super) writer: Option<BufWriter<Box<dyn SpillWriter>>>,
    /// Bytes written.
    pub(super) len: u64,
    pub(super) runs: Vec<Run>,
}

/// One run of a spill file: where it starts, where each bucket starts in it (in entries, with the
/// run's end last), and whether its keys and counts fit the narrow tables' 32 bits.
pub(super) struct Run {
    pub(super) start: u64,
    pub(super) offsets: Vec<u64>,
    pub(super) narrow: bool,
}

impl Run {
    pub(super) fn entries(&self, b: usize) -> u64 {
        self.offsets[b + 1] - self.offsets[b]
    }

    /// Bucket `b`'s byte offset in the file and entry count.
    pub(super) fn bucket(&self, b: usize, stride: usize) -> (u64, u64) {
        (self.start + self.offsets[b] * stride as u64 * 8, self.entries(b))
    }
}

impl Spilled {
    pub(super) fn write_run(&mut self, c: &Counts) -> Result<()> {
        let Some(w) = self.writer.as_mut() else {
            return Err(DataFusionError::Internal("CountByKeyExec wrote to a spill file it had finished".into()));
        };
        let mut offsets = Vec::with_capacity(BUCKETS + 1);
        offsets.push(0);
        for b in 0..BUCKETS {
            let n = c.write_bucket(b, w).map_err(|e| spill_error("writing", self.file.as_ref(), &e))?;
            offsets.push(offsets[b] + n);
        }
        let start = self.len;
        self.len += offsets[BUCKETS] * c.stride as u64 * 8;
        self.runs.push(Run { start, offsets, narrow: c.narrow.is_some() });
        Ok(())
    }

    /// Flushes the writer: the file is then only read.
    pub(super) fn finish(mut self) -> Result<Written> {
        if let Some(mut w) = self.writer.take() {
            w.flush().map_err(|e| spill_error("writing", self.file.as_ref(), &e))?;
            w.into_inner().map_err(|e| spill_error("writing", self.file.as_ref(), e.error()))?.finish()?;
        }
        Ok(Written { file: self.file, runs: self.runs })
    }
}

/// A spill file once written: read back bucket by bucket by the merge.
pub(super) struct Written {
    pub(super) file: Arc<dyn SpillFile>,
    pub(super) runs: Vec<Run>,
}

impl Written {
    /// Bucket `b`'s entries in `run` (none when it has none).
    pub(super) fn read_bucket(
        &self,
        f: &mut std::fs::File,
        run: &Run,
        b: usize,
        stride: usize,
    ) -> Result<Option<Part>> {
        let (at, n) = run.bucket(b, stride);
        if n == 0 {
            return Ok(None);
        }
        let mut bytes = vec![0u8; (n as usize) * stride * 8];
        f.seek(SeekFrom::Start(at))
            .and_then(|_| f.read_exact(&mut bytes))
            .map_err(|e| spill_error("reading", self.file.as_ref(), &e))?;
        let words = bytes.chunks_exact(8).map(|w| u64::from_le_bytes(w.try_into().unwrap_or_default())).collect();
        Ok(Some(Part::Entries { words, narrow: run.narrow }))
    }
}

pub(super) fn spill_error(doing: &str, file: &dyn SpillFile, e: &std::io::Error) -> DataFusionError {
    let path = file.path().map_or_else(|| "(no path)".to_string(), |p| p.display().to_string());
    DataFusionError::Execution(format!("CountByKeyExec: {doing} its spill file {path}: {e}"))
}
