//! The radix-bucketed hash tables a worker counts into, and the keys as words.

use super::*;

/// A key's radix bucket: the top bits of a multiplicative hash (every key bit reaches them).
#[inline]
pub(super) fn bucket(key: u64) -> usize {
    (key.wrapping_mul(0x9e37_79b9_7f4a_7c15) >> (64 - BUCKET_BITS)) as usize
}

/// splitmix64's finalizer, for the slot within a bucket's table.
#[inline]
pub(super) fn mix(k: u64) -> u64 {
    let z = (k ^ (k >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// One bucket's open-addressing table (linear probing, at most half full). A slot is `stride`
/// words: the key, its row count (0 marks an empty slot: a stored key has at least one row), then
/// the non-NULL count of each counted expression.
#[derive(Default)]
pub(super) struct Table {
    pub(super) words: Vec<u64>,
    pub(super) mask: usize,
    pub(super) len: usize,
}

impl Table {
    pub(super) fn capacity(&self, stride: usize) -> usize {
        self.words.len() / stride
    }

    /// The first word of `key`'s slot, claimed (with zero counts) when the key is new.
    #[inline]
    pub(super) fn slot(&mut self, key: u64, hash: u64, stride: usize) -> usize {
        self.reserve(1, stride);
        self.slot_reserved(key, hash, stride)
    }

    /// Grows the table (if needed) so that `additional` new keys keep it at most half full.
    pub(super) fn reserve(&mut self, additional: usize, stride: usize) {
        while (self.len + additional) * 2 > self.capacity(stride) {
            self.grow(stride);
        }
    }

    /// The bytes [`Table::reserve`] would add for `additional` new keys.
    pub(super) fn growth(&self, additional: usize, stride: usize) -> usize {
        let (old, mut capacity) = (self.capacity(stride), self.capacity(stride));
        while (self.len + additional) * 2 > capacity {
            capacity = (capacity * 2).max(64);
        }
        (capacity - old) * stride * 8
    }

    /// [`Table::slot`] without the growth check: room must have been reserved.
    #[inline(always)]
    pub(super) fn slot_reserved(&mut self, key: u64, hash: u64, stride: usize) -> usize {
        let mut i = hash as usize & self.mask;
        loop {
            let w = i * stride;
            if self.words[w + 1] == 0 {
                self.words[w] = key;
                self.len += 1;
                return w;
            }
            if self.words[w] == key {
                return w;
            }
            i = (i + 1) & self.mask;
        }
    }

    pub(super) fn grow(&mut self, stride: usize) {
        let capacity = (self.capacity(stride) * 2).max(64);
        // Zeros written, not calloc's lazy zero pages: a probe reads a slot before it writes it,
        // and a write to a read-mapped zero page costs a copy-on-write fault and a TLB shootdown.
        #[expect(clippy::slow_vector_initialization, reason = "written zeros, not calloc's zero pages (see above)")]
        let words = {
            let mut words = Vec::with_capacity(capacity * stride);
            words.resize(capacity * stride, 0);
            words
        };
        let old = std::mem::replace(&mut self.words, words);
        self.mask = capacity - 1;
        self.len = 0;
        for s in old.chunks_exact(stride).filter(|s| s[1] != 0) {
            let w = self.slot(s[0], mix(s[0]), stride);
            self.words[w + 1..w + stride].copy_from_slice(&s[1..]);
        }
    }

    pub(super) fn bytes(&self) -> usize {
        self.words.len() * std::mem::size_of::<u64>()
    }
}

/// A bucket's table with one-word slots, for `count(*)` alone while every key fits in 32 bits and
/// no count can reach 2^32: the key in the high half, its count in the low half, 0 for an empty
/// slot (a stored key has a count). Half the bytes of a [`Table`] slot pair: half the cache
/// traffic per probe and half the memory.
#[derive(Default)]
pub(super) struct Narrow {
    pub(super) words: Vec<u64>,
    pub(super) mask: usize,
    pub(super) len: usize,
}

pub(super) const LOW: u64 = 0xffff_ffff;

impl Narrow {
    /// Grows the table (if needed) so that `additional` new keys keep it at most half full.
    pub(super) fn reserve(&mut self, additional: usize) {
        while (self.len + additional) * 2 > self.words.len() {
            let capacity = (self.words.len() * 2).max(64);
            // Zeros written, not calloc's lazy zero pages (see `Table::grow`).
            #[expect(clippy::slow_vector_initialization, reason = "written zeros, not calloc's zero pages")]
            let words = {
                let mut words = Vec::with_capacity(capacity);
                words.resize(capacity, 0);
                words
            };
            let old = std::mem::replace(&mut self.words, words);
            self.mask = capacity - 1;
            self.len = 0;
            for w in old.into_iter().filter(|&w| w != 0) {
                self.add(w >> 32, w & LOW);
            }
        }
    }

    /// The bytes [`Narrow::reserve`] would add for `additional` new keys.
    pub(super) fn growth(&self, additional: usize) -> usize {
        let mut capacity = self.words.len();
        while (self.len + additional) * 2 > capacity {
            capacity = (capacity * 2).max(64);
        }
        (capacity - self.words.len()) * 8
    }

    /// Adds `n` rows to `key` (below 2^32); room must have been reserved.
    #[inline(always)]
    pub(super) fn add(&mut self, key: u64, n: u64) {
        let mut i = mix(key) as usize & self.mask;
        loop {
            let w = self.words[i];
            if w == 0 {
                self.words[i] = (key << 32) | n;
                self.len += 1;
                return;
            }
            if w >> 32 == key {
                self.words[i] = w + n;
                return;
            }
            i = (i + 1) & self.mask;
        }
    }

    pub(super) fn bytes(&self) -> usize {
        self.words.len() * std::mem::size_of::<u64>()
    }
}

/// Keys a worker buffers (per radix bucket) before it adds them to its tables, bucket by bucket:
/// each bucket's table is then read into cache once per flush, not missed on every row.
pub(super) const PENDING_KEYS: usize = 4 << 20;

/// The fewest keys buffered per flush, however small the memory limit.
pub(super) const MIN_PENDING_KEYS: usize = 1 << 12;

/// Bytes a worker's single direct table may reach before the worker switches to radix buckets:
/// a table this size stays in a core's L2 cache (1 MiB of the 2 MiB here), where counting straight
/// into it is faster than buffering (with 16K distinct keys the buffered path was 3x slower than
/// DataFusion's own aggregation: `cargo bench -p rtvtk-query --bench count_by_key`).
pub(super) const DIRECT_BYTES: usize = 1 << 20;

/// One worker's counts: while few keys have been seen, one table counted into directly; then a
/// table per radix bucket, the keys not yet counted (with, when `count`s of expressions are asked,
/// a word of their validity bits after each key); and the counts of the NULL key.
pub(super) struct Counts {
    pub(super) stride: usize,
    pub(super) direct: Option<Table>,
    pub(super) tables: Vec<Table>,
    /// The buckets' tables while they can be [`Narrow`] (then `tables` stays empty).
    pub(super) narrow: Option<Vec<Narrow>>,
    /// OR of every key seen (whether they all fit in 32 bits) and rows seen, for `narrow`.
    pub(super) key_bits: u64,
    pub(super) rows: u64,
    pub(super) pending: Vec<Vec<u64>>,
    pub(super) pending_rows: usize,
    /// Rows buffered before a flush: at most [`PENDING_KEYS`], fewer under a memory limit (see
    /// [`Counts::new`]).
    pub(super) pending_limit: usize,
    pub(super) null_key: Vec<u64>,
}

impl Counts {
    /// Counts with `stride`-word slots, whose worker may hold about `share` bytes of the memory
    /// limit: the keys buffered between flushes are capped to an eighth of it (their buffers grow
    /// a batch at a time, before the pool is asked).
    pub(super) fn new(stride: usize, share: usize) -> Self {
        let per_key = if stride > 2 { 16 } else { 8 };
        let pending_limit = (share / 8 / per_key).clamp(MIN_PENDING_KEYS, PENDING_KEYS);
        Self {
            stride,
            direct: Some(Table::default()),
            tables: (0..BUCKETS).map(|_| Table::default()).collect(),
            narrow: (stride == 2).then(|| (0..BUCKETS).map(|_| Narrow::default()).collect()),
            key_bits: 0,
            rows: 0,
            pending: vec![Vec::new(); BUCKETS],
            pending_rows: 0,
            pending_limit,
            null_key: vec![0; stride - 1],
        }
    }

    /// Whether the narrow tables can no longer hold the keys or counts.
    pub(super) fn too_wide(&self) -> bool {
        self.key_bits >> 32 != 0 || self.rows >= LOW
    }

    /// Moves the narrow tables' keys into `tables` (for good).
    pub(super) fn widen(&mut self) {
        let Some(narrow) = self.narrow.take() else { return };
        for (t, n) in self.tables.iter_mut().zip(narrow) {
            t.reserve(n.len, 2);
            for w in n.words.into_iter().filter(|&w| w != 0) {
                let slot = t.slot_reserved(w >> 32, mix(w >> 32), 2);
                t.words[slot + 1] += w & LOW;
            }
        }
    }

    /// Adds the pending keys to the tables, one bucket at a time. Before a table grows, what it
    /// grows by is asked of `reservation`; when the pool refuses, its error is returned and the
    /// keys not yet added stay pending (the caller spills the tables and flushes again).
    pub(super) fn flush(&mut self, reservation: &mut Budget) -> Result<()> {
        let stride = self.stride;
        if self.too_wide() {
            self.widen();
        }
        let per = if stride > 2 { 2 } else { 1 };
        // Buffers far larger than the pending limit now needs are given back.
        let keep = (self.pending_limit / BUCKETS * per * 2).max(16);
        for b in 0..BUCKETS {
            let pending = &mut self.pending[b];
            if pending.is_empty() {
                continue;
            }
            let mut done = 0;
            let mut refused = None;
            match self.narrow.as_mut() {
                Some(narrow) => {
                    let t = &mut narrow[b];
                    if pending.len() * 64 >= t.words.len() {
                        std::hint::black_box(t.words.iter().step_by(8).fold(0u64, |a, &w| a ^ w));
                    }
                    for chunk in pending.chunks(1024) {
                        if let Err(e) = reservation.try_grow(t.growth(chunk.len())) {
                            refused = Some(e);
                            break;
                        }
                        t.reserve(chunk.len());
                        for &key in chunk {
                            t.add(key, 1);
                        }
                        done += chunk.len();
                    }
                }
                None => {
                    let t = &mut self.tables[b];
                    // Read the table into cache in order (at the prefetcher's pace) before the
                    // random probes, when they are enough to touch most of its cache lines.
                    if pending.len() * 64 >= t.words.len() {
                        std::hint::black_box(t.words.iter().step_by(8).fold(0u64, |a, &w| a ^ w));
                    }
                    // Room is reserved per chunk, not checked per key (at most a chunk's slack).
                    for chunk in pending.chunks(1024 * per) {
                        if let Err(e) = reservation.try_grow(t.growth(chunk.len() / per, stride)) {
                            refused = Some(e);
                            break;
                        }
                        t.reserve(chunk.len() / per, stride);
                        if per == 1 {
                            for &key in chunk {
                                let w = t.slot_reserved(key, mix(key), stride);
                                t.words[w + 1] += 1;
                            }
                        } else {
                            for row in chunk.chunks_exact(per) {
                                let w = t.slot_reserved(row[0], mix(row[0]), stride);
                                t.words[w + 1] += 1;
                                for j in 2..stride {
                                    t.words[w + j] += (row[1] >> (j - 2)) & 1;
                                }
                            }
                        }
                        done += chunk.len();
                    }
                }
            }
            if let Some(e) = refused {
                pending.drain(..done);
                return Err(e);
            }
            pending.clear();
            if pending.capacity() > keep {
                *pending = Vec::new();
            }
        }
        self.pending_rows = 0;
        Ok(())
    }

    /// Moves the direct table's keys into the radix buckets' tables (for good: later rows are
    /// buffered) once it has outgrown [`DIRECT_BYTES`], or always when `all`.
    pub(super) fn bucket_direct(&mut self, all: bool) {
        let stride = self.stride;
        if !all && self.direct.as_ref().is_none_or(|t| t.len * 2 * stride * 8 <= DIRECT_BYTES) {
            return;
        }
        let Some(direct) = self.direct.take() else { return };
        if self.too_wide() {
            self.widen();
        }
        if let Some(narrow) = self.narrow.as_mut() {
            for s in direct.words.chunks_exact(2).filter(|s| s[1] != 0) {
                let t = &mut narrow[bucket(s[0])];
                t.reserve(1);
                t.add(s[0], s[1]);
            }
            return;
        }
        for s in direct.words.chunks_exact(stride).filter(|s| s[1] != 0) {
            let t = &mut self.tables[bucket(s[0])];
            let w = t.slot(s[0], mix(s[0]), stride);
            for (b, v) in t.words[w + 1..w + stride].iter_mut().zip(&s[1..]) {
                *b += v;
            }
        }
    }

    /// Empties the tables once they have been written out (see [`Spilled`]), keeping their room
    /// (zeroed) so that the next run does not grow them again; keys still pending stay, to be
    /// flushed into the empty tables.
    pub(super) fn clear(&mut self) {
        self.direct = None;
        for t in &mut self.tables {
            t.words.fill(0);
            t.len = 0;
        }
        for t in self.narrow.iter_mut().flatten() {
            t.words.fill(0);
            t.len = 0;
        }
    }

    /// Resizes the reservation to what the counts hold after a spill; when the emptied tables'
    /// room and the pending keys together are over the share, the room is given back.
    pub(super) fn fit(&mut self, reservation: &mut Budget) -> Result<()> {
        if reservation.try_resize(self.bytes()).is_ok() {
            return Ok(());
        }
        self.release_room();
        reservation.try_resize(self.bytes())
    }

    /// Gives back the room of emptied tables; false when they had none.
    pub(super) fn release_room(&mut self) -> bool {
        let room = self.tables.iter().any(|t| !t.words.is_empty())
            || self.narrow.iter().flatten().any(|t| !t.words.is_empty());
        self.tables = (0..BUCKETS).map(|_| Table::default()).collect();
        if self.narrow.is_some() {
            self.narrow = Some((0..BUCKETS).map(|_| Narrow::default()).collect());
        }
        room
    }

    /// Whether the tables hold no key (the NULL key's counts are kept apart), pending keys aside.
    pub(super) fn is_empty_but_pending(&self) -> bool {
        self.direct.as_ref().is_none_or(|t| t.len == 0)
            && match &self.narrow {
                Some(n) => n.iter().all(|t| t.len == 0),
                None => self.tables.iter().all(|t| t.len == 0),
            }
    }

    /// Writes bucket `b`'s entries (`stride` words each: the key, then its counts), once the
    /// direct table and the pending keys are in the buckets; returns how many.
    pub(super) fn write_bucket(&self, b: usize, w: &mut impl Write) -> std::io::Result<u64> {
        let mut n = 0;
        match &self.narrow {
            Some(narrow) => {
                for &word in narrow[b].words.iter().filter(|&&w| w != 0) {
                    w.write_all(&(word >> 32).to_le_bytes())?;
                    w.write_all(&(word & LOW).to_le_bytes())?;
                    n += 1;
                }
            }
            None => {
                for s in self.tables[b].words.chunks_exact(self.stride).filter(|s| s[1] != 0) {
                    for v in s {
                        w.write_all(&v.to_le_bytes())?;
                    }
                    n += 1;
                }
            }
        }
        Ok(n)
    }

    pub(super) fn bytes(&self) -> usize {
        let pending: usize = self.pending.iter().map(|p| p.capacity() * std::mem::size_of::<u64>()).sum();
        let direct = self.direct.as_ref().map_or(0, Table::bytes);
        let narrow = self.narrow.iter().flatten().map(Narrow::bytes).sum::<usize>();
        direct + narrow + pending + self.tables.iter().map(Table::bytes).sum::<usize>()
    }
}

/// A key column as 64-bit words (signed keys by their two's complement bits) and its validity.
pub(super) fn key_words(a: &ArrayRef) -> Result<(Cow<'_, [u64]>, Option<NullBuffer>)> {
    let nulls = a.logical_nulls();
    let words = match a.data_type() {
        DataType::UInt64 => Cow::Borrowed(&a.as_primitive::<UInt64Type>().values()[..]),
        DataType::Int64 => Cow::Owned(a.as_primitive::<Int64Type>().values().iter().map(|&v| v as u64).collect()),
        t if t.is_signed_integer() => {
            let wide = cast(a, &DataType::Int64)?;
            Cow::Owned(wide.as_primitive::<Int64Type>().values().iter().map(|&v| v as u64).collect())
        }
        _ => {
            let wide = cast(a, &DataType::UInt64)?;
            Cow::Owned(wide.as_primitive::<UInt64Type>().values().to_vec())
        }
    };
    Ok((words, nulls))
}

/// Adds rows whose keys may be NULL, or with the validity bits of counted expressions.
pub(super) fn add_rows(
    c: &mut Counts,
    keys: &[u64],
    key_nulls: Option<&NullBuffer>,
    mask: &dyn Fn(usize) -> u64,
    args: usize,
) {
    for (i, &key) in keys.iter().enumerate() {
        if key_nulls.is_some_and(|n| n.is_null(i)) {
            c.null_key[0] += 1;
            let m = mask(i);
            for j in 0..args {
                c.null_key[1 + j] += (m >> j) & 1;
            }
            continue;
        }
        if let Some(t) = c.direct.as_mut() {
            let w = t.slot(key, mix(key), c.stride);
            t.words[w + 1] += 1;
            let m = mask(i);
            for j in 0..args {
                t.words[w + 2 + j] += (m >> j) & 1;
            }
            continue;
        }
        let pending = &mut c.pending[bucket(key)];
        pending.push(key);
        if args > 0 {
            pending.push(mask(i));
        }
    }
}

/// Adds entries (`stride` words each: a key, its counts) to a table.
pub(super) fn add_entries<'a>(base: &mut Table, entries: impl Iterator<Item = &'a [u64]>, stride: usize) {
    for s in entries {
        let w = base.slot(s[0], mix(s[0]), stride);
        for (b, v) in base.words[w + 1..w + stride].iter_mut().zip(&s[1..]) {
            *b += v;
        }
    }
}
