//! Writing a dataset: segments sealed atomically, the manifest replaced atomically after each.
//!
//! A segment is written to `segments/NNNNNN.{rays,trees}.parquet.tmp`, synced, renamed into place,
//! and only then listed in the manifest. A process killed at any moment therefore leaves a dataset
//! whose manifest lists only whole segments; leftover `.tmp` files are ignored by readers and
//! reported by `check`.

use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use arrow::datatypes::DataType;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, Encoding as Encoding_, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::{EnabledStatistics, WriterProperties};
use parquet::schema::types::ColumnPath;

use crate::codec::{ENC_T, ENCODED_COLUMNS, Encoding, KIND_CODE, encode, file_schema};
use crate::columns::{RayColumns, TreeRow};
use crate::error::{io_err, pq_err};
use crate::manifest::{FileEntry, Manifest, SegmentEntry, segment_file, sync_dir};
use crate::pages::{Plan, RayFileWriter};
use crate::path_payload::{
    CHROMAS_KEY, ChromaLearner, ENC_CHROMA, ENC_THROUGHPUT, RADIANCE, THROUGHPUT, encoded_columns,
};
use crate::planes::{PLANES_KEY, PlaneLearner};
use crate::schema::{KindTable, PayloadSchema, ray_schema, tree_schema};
use crate::stats::Stats;
use crate::{Error, FORMAT_VERSION, Result};

/// How a dataset is written.
#[derive(Clone, Debug)]
pub struct WriteOptions {
    /// Rows per Parquet row group in a ray file.
    pub row_group_rows: usize,
    /// Rows per data page: the unit a one-tree fetch reads and decompresses. 8K rows (16K until
    /// 2026-12-05): on a 25M-ray path-tracer trace with its payload a fetch by id takes 0.67
    /// instead of 0.95 ms at p50 for 0.6% more bytes, and a scan of the directions ~10% longer;
    /// 4K-row pages add 2.1% bytes and cost the writers more CPU (zstd's per-page table
    /// building, arrow-rs's per-page work) for little more (`rtvtk record --page-rows N`, then
    /// `rtvtk bench fetch`).
    pub page_rows: usize,
    /// zstd level of every column.
    pub zstd_level: i32,
    /// fsync files and directories when sealing (needed for power-loss safety; a SIGKILL is
    /// survived either way).
    pub sync: bool,
    /// How origins and directions are stored (lossless residuals by default).
    pub encoding: Encoding,
    /// Lossy payload: float32 and float64 payload values (scalars and list elements) rounded to
    /// this many mantissa bits (1..=22; round half to even, never to infinity; NaN, infinities
    /// and zeros kept) before they are written. None (the default): payload bit-exact. Recorded
    /// in the manifest (`payload_mantissa_bits`). 10 bits is half precision's mantissa: a
    /// relative error of at most 2^-11. The path payload of encoded layouts (`throughput` and
    /// `radiance`, both float32[3]) is predicted instead and stays exact (rounded, it cost more
    /// than exact values predicted).
    pub payload_mantissa_bits: Option<u8>,
}

impl Default for WriteOptions {
    fn default() -> Self {
        Self {
            row_group_rows: 128 * 1024,
            page_rows: 8 * 1024,
            zstd_level: 1,
            sync: true,
            encoding: Encoding::default(),
            payload_mantissa_bits: None,
        }
    }
}

/// Writes `Write` through while computing the CRC32 and length of what passed.
pub struct CrcWriter<W: Write> {
    inner: W,
    hasher: crc32fast::Hasher,
    bytes: u64,
}

impl<W: Write> CrcWriter<W> {
    pub fn new(inner: W) -> Self {
        Self { inner, hasher: crc32fast::Hasher::new(), bytes: 0 }
    }

    pub fn finish(self) -> (W, u32, u64) {
        (self.inner, self.hasher.finalize(), self.bytes)
    }
}

impl<W: Write> Write for CrcWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

type FileSink = CrcWriter<BufWriter<File>>;

/// A dataset being written. Shared by the workers that write its segments.
pub struct DatasetWriter {
    dir: PathBuf,
    payload: PayloadSchema,
    options: WriteOptions,
    manifest: Mutex<Manifest>,
    next_segment: AtomicU32,
    /// Emptied blocks of tree rows from sealed segments, for the segments opened next.
    tree_blocks: TreeBlocks,
}

/// Tree rows per block of a segment's tree rows.
const TREE_BLOCK_ROWS: usize = 16 * 1024;
/// Spare blocks kept for later segments (~40 MB).
const SPARE_TREE_BLOCKS: usize = 64;

/// A pool of emptied tree-row blocks shared by a dataset's segment writers: a segment holds its
/// tree rows until it is sealed (the tree file is sorted by id), ~24 MB for 4M path-tracer rays,
/// and allocating them anew for every segment faulted fresh pages in on the writer threads.
type TreeBlocks = Arc<Mutex<Vec<Vec<TreeRow>>>>;

impl DatasetWriter {
    /// Creates a new dataset at `dir` (which must not exist or be empty) with an empty manifest.
    pub fn create(dir: &Path, payload: PayloadSchema, options: WriteOptions) -> Result<Self> {
        ensure_empty(dir)?;
        let segments = dir.join("segments");
        fs::create_dir_all(&segments).map_err(io_err("creating the dataset directory", &segments))?;
        if let Some(bits) = options.payload_mantissa_bits
            && !(1..=22).contains(&bits)
        {
            return Err(Error::Encoding(format!(
                "payload mantissa bits {bits}: expected 1 to 22 (None keeps every bit)"
            )));
        }
        let mut manifest = Manifest::new(&payload, options.encoding);
        manifest.payload_mantissa_bits = options.payload_mantissa_bits;
        manifest.store(dir, options.sync)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            payload,
            options,
            manifest: Mutex::new(manifest),
            next_segment: AtomicU32::new(1),
            tree_blocks: TreeBlocks::default(),
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn payload(&self) -> &PayloadSchema {
        &self.payload
    }

    /// A copy of the manifest as last committed.
    pub fn manifest(&self) -> Manifest {
        self.manifest.lock().map(|m| m.clone()).unwrap_or_else(|p| p.into_inner().clone())
    }

    /// Opens a new segment for one worker to fill.
    pub fn open_segment(&self) -> Result<SegmentWriter> {
        let id = self.next_segment.fetch_add(1, Ordering::Relaxed);
        let rel = segment_file(id, "rays");
        let tmp = self.dir.join(format!("{rel}.tmp"));
        let file = File::create(&tmp).map_err(io_err("creating a segment file", &tmp))?;
        let sink = CrcWriter::new(BufWriter::with_capacity(1 << 20, file));
        let schema = file_schema(&ray_schema(&self.payload), self.options.encoding, FORMAT_VERSION);
        let plans: Vec<Plan> = schema.fields().iter().map(|f| column_plan(f, self.options.encoding)).collect();
        let writer = RayFileWriter::try_new(
            sink,
            schema.clone(),
            ray_properties(&self.options, &self.dir)?,
            &plans,
            self.options.zstd_level,
            self.options.page_rows,
        )
        .map_err(pq_err(&tmp))?;
        Ok(SegmentWriter {
            id,
            tmp,
            writer: Some(writer),
            trees: Vec::new(),
            tree_blocks: self.tree_blocks.clone(),
            rows: 0,
            stats: Stats::default(),
            encoding: self.options.encoding,
            payload_mantissa_bits: self.options.payload_mantissa_bits,
            schema,
            row_group_rows: self.options.row_group_rows.max(1),
            planes: PlaneLearner::default(),
            chromas: ChromaLearner::default(),
        })
    }

    /// Marks the recording as finished cleanly.
    pub fn mark_complete(&self) -> Result<()> {
        let mut m = self.manifest.lock().unwrap_or_else(|p| p.into_inner());
        m.complete = true;
        m.store(&self.dir, self.options.sync)
    }

    /// Sets free-form attributes of the recording (scene, tracer, seed, ...), committed at once.
    pub fn set_attributes(&self, attributes: impl IntoIterator<Item = (String, String)>) -> Result<()> {
        let mut m = self.manifest.lock().unwrap_or_else(|p| p.into_inner());
        let mut next = m.clone();
        next.attributes.extend(attributes);
        next.store(&self.dir, self.options.sync)?;
        *m = next;
        Ok(())
    }

    /// Writes an optional whole-dataset table (`tables/NAME.parquet`) atomically and lists it in
    /// the manifest. Replaces an earlier table of that name.
    pub fn write_table(&self, name: &str, batch: &arrow::array::RecordBatch) -> Result<()> {
        Self::check_table_name(name)?;
        let rel = format!("tables/{name}.parquet");
        crate::scene::check_table(name, &batch.schema()).map_err(|message| Error::Table {
            name: name.into(),
            path: self.dir.join(&rel),
            message,
        })?;
        let dir = self.dir.join("tables");
        fs::create_dir_all(&dir).map_err(io_err("creating the tables directory", &dir))?;
        let tmp = self.dir.join(format!("{rel}.tmp"));
        let (crc, bytes) = write_small_table(&tmp, name, &batch.schema(), [Ok(batch.clone())], self.options.sync)?;
        let path = self.dir.join(&rel);
        fs::rename(&tmp, &path).map_err(io_err("moving a table into place", &path))?;
        if self.options.sync {
            sync_dir(&dir)?;
        }
        let mut m = self.manifest.lock().unwrap_or_else(|p| p.into_inner());
        let mut next = m.clone();
        let columns = Some(crate::manifest::table_columns(&batch.schema()));
        next.tables.insert(
            name.to_string(),
            FileEntry { path: rel, bytes, crc32: crc, rows: batch.num_rows() as u64, columns },
        );
        next.store(&self.dir, self.options.sync)?;
        *m = next;
        Ok(())
    }

    /// Whether `name` may name an optional table (ASCII letters, digits or '_').
    pub fn check_table_name(name: &str) -> Result<()> {
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            return Err(Error::PayloadDecl(format!("table name must be ASCII letters, digits or '_', got {name:?}")));
        }
        Ok(())
    }

    fn commit(&self, seg: SegmentEntry, kinds: &KindTable) -> Result<()> {
        let mut m = self.manifest.lock().unwrap_or_else(|p| p.into_inner());
        let mut next = m.clone();
        next.add_segment(seg, kinds);
        next.store(&self.dir, self.options.sync)?;
        *m = next;
        Ok(())
    }
}

/// Trees per batch handed to the tree file's writer at seal.
const TREE_BATCH_ROWS: usize = 64 * 1024;

/// One segment being filled by one worker.
pub struct SegmentWriter {
    id: u32,
    tmp: PathBuf,
    writer: Option<RayFileWriter<FileSink>>,
    /// The tree rows written, rows made file-relative, in blocks of [`TREE_BLOCK_ROWS`] (sorted
    /// and merged by id at seal) rather than one vector: growing one vector of ~24 MB copied it
    /// and faulted fresh pages in each time; blocks come from and go back to `tree_blocks`.
    trees: Vec<Vec<TreeRow>>,
    tree_blocks: TreeBlocks,
    rows: u64,
    stats: Stats,
    encoding: Encoding,
    /// [`WriteOptions::payload_mantissa_bits`].
    payload_mantissa_bits: Option<u8>,
    /// Schema of the ray file (the ray table's, or the encoded layout).
    schema: arrow::datatypes::SchemaRef,
    row_group_rows: usize,
    /// Planes of the primitives hit so far, for predicting hit distances (saved at seal).
    planes: PlaneLearner,
    /// Throughput colours seen so far, for predicting throughput (saved at seal).
    chromas: ChromaLearner,
}

impl SegmentWriter {
    pub fn id(&self) -> u32 {
        self.id
    }

    /// Rays written so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Appends whole trees to the segment.
    pub fn write(&mut self, mut cols: RayColumns, payload: &PayloadSchema, kinds: &KindTable) -> Result<()> {
        let n = cols.len() as u64;
        if n == 0 && cols.trees.is_empty() {
            return Ok(());
        }
        // Where trees end in this chunk: row groups are only ever cut there.
        let mut ends: Vec<usize> = cols.trees.iter().map(|t| (t.first_row + u64::from(t.ray_count)) as usize).collect();
        ends.sort_unstable();
        let plain = self.encoding == Encoding::Plain;
        let mut stats = Stats::of_columns_with(&cols, kinds, plain);
        let encoded = if self.encoding == Encoding::Plain {
            None
        } else {
            Some((
                encode(&cols, self.encoding, &mut stats, &mut self.planes)?,
                arrow::array::UInt8Array::from(cols.kind.clone()),
            ))
        };
        self.stats.merge(&stats);
        // Whether the file predicts the path payload (throughput and radiance).
        let predicted = crate::path_payload::predicted_in(&self.schema);
        if let Some(bits) = self.payload_mantissa_bits {
            // The predicted path payload stays exact: rounded, it would no longer match its
            // predictions (10 bits made a Cornell trace 22.36 instead of 16.67 B/ray).
            for (field, buf) in payload.fields.iter().zip(cols.payload.iter_mut()) {
                if predicted && (field.name == THROUGHPUT || field.name == RADIANCE) {
                    continue;
                }
                crate::columns::round_mantissas(&field.element, &mut buf.bytes, bits);
            }
        }
        let trees = std::mem::take(&mut cols.trees);
        let mut batch = cols.into_ray_batch(payload, kinds)?;
        if let Some((enc, kind_codes)) = encoded {
            let t_nulls = batch.column_by_name("t").and_then(|t| t.nulls().cloned());
            let mut arrays = enc.into_arrays(t_nulls).into_iter();
            // The path payload's columns, in `encoded_columns` order.
            let path_payload = if predicted {
                encode_path_payload(&batch, kind_codes.values(), &mut self.chromas)?
            } else {
                Vec::new()
            };
            let kind_codes: arrow::array::ArrayRef = std::sync::Arc::new(kind_codes);
            let mut columns = Vec::with_capacity(self.schema.fields().len());
            for f in self.schema.fields() {
                let c = match batch.column_by_name(f.name()) {
                    Some(c) => c.clone(),
                    None if f.name() == KIND_CODE => kind_codes.clone(),
                    None => match encoded_columns().position(|n| n == f.name()) {
                        Some(k) => path_payload.get(k).cloned(),
                        None => arrays.next(),
                    }
                    .ok_or_else(|| Error::Encoding(format!("no encoded column {}", f.name())))?,
                };
                columns.push(c);
            }
            batch = arrow::array::RecordBatch::try_new(self.schema.clone(), columns)
                .map_err(crate::error::arrow_err("encoded ray batch"))?;
        }
        let writer = self.writer.as_mut().ok_or_else(|| Error::Corrupt {
            path: self.tmp.clone(),
            what: "segment writer".into(),
            message: "write after seal".into(),
        })?;
        // A row group closes at the first tree end that brings it to `row_group_rows`, so every row
        // group starts with a whole tree and decodes on its own.
        let mut start = 0usize;
        for &end in &ends {
            if end > start && writer.in_progress_rows() + (end - start) >= self.row_group_rows {
                writer.write(&batch.slice(start, end - start)).map_err(pq_err(&self.tmp))?;
                writer.flush().map_err(pq_err(&self.tmp))?;
                start = end;
            }
        }
        if start < batch.num_rows() {
            writer.write(&batch.slice(start, batch.num_rows() - start)).map_err(pq_err(&self.tmp))?;
        }
        self.keep_trees(&trees);
        self.rows += n;
        Ok(())
    }

    /// Copies a chunk's tree rows into the segment's blocks, rows made file-relative.
    fn keep_trees(&mut self, trees: &[TreeRow]) {
        let base = self.rows;
        let mut rest = trees;
        while !rest.is_empty() {
            let room = self.trees.last().map_or(0, |b| b.capacity() - b.len());
            if room == 0 {
                let spare = self.tree_blocks.lock().unwrap_or_else(|p| p.into_inner()).pop();
                self.trees.push(spare.unwrap_or_else(|| Vec::with_capacity(TREE_BLOCK_ROWS)));
                continue;
            }
            let (now, later) = rest.split_at(room.min(rest.len()));
            if let Some(block) = self.trees.last_mut() {
                block.extend(now.iter().map(|t| TreeRow { first_row: t.first_row + base, ..*t }));
            }
            rest = later;
        }
    }

    /// Hands the emptied tree blocks back to the pool (as many as it keeps).
    fn return_tree_blocks(&mut self) {
        let mut pool = self.tree_blocks.lock().unwrap_or_else(|p| p.into_inner());
        for mut block in self.trees.drain(..) {
            if pool.len() >= SPARE_TREE_BLOCKS {
                break;
            }
            block.clear();
            pool.push(block);
        }
    }

    /// Finishes the files, moves them into place and lists the segment in the manifest.
    /// An empty segment is discarded instead. Returns the segment entry when one was committed.
    pub fn seal(mut self, ds: &DatasetWriter, kinds: &KindTable) -> Result<Option<SegmentEntry>> {
        let Some(mut writer) = self.writer.take() else {
            return Ok(None);
        };
        if self.trees.is_empty() {
            drop(writer);
            let _ = fs::remove_file(&self.tmp);
            return Ok(None);
        }
        let planes = self.planes.planes();
        if !planes.is_empty() {
            writer.append_key_value_metadata(KeyValue::new(PLANES_KEY.into(), planes.to_metadata()));
        }
        let chromas = self.chromas.chromas();
        if !chromas.is_empty() {
            writer.append_key_value_metadata(KeyValue::new(CHROMAS_KEY.into(), chromas.to_metadata()));
        }
        let sink = writer.into_inner().map_err(pq_err(&self.tmp))?;
        let rays = finish_file(sink, &self.tmp, ds.options.sync)?;

        let rays_rel = segment_file(self.id, "rays");
        let trees_rel = segment_file(self.id, "trees");
        let trees_tmp = ds.dir.join(format!("{trees_rel}.tmp"));
        for block in &mut self.trees {
            block.sort_unstable_by_key(|t| t.tree_id);
        }
        let tree_count: usize = self.trees.iter().map(Vec::len).sum();
        let id_min = self.trees.iter().filter_map(|c| c.first()).map(|t| t.tree_id).min().unwrap_or(0);
        let id_max = self.trees.iter().filter_map(|c| c.last()).map(|t| t.tree_id).max().unwrap_or(0);
        let trees = write_small_table(
            &trees_tmp,
            "trees",
            &tree_schema(),
            RayColumns::merged_tree_batches(&self.trees, self.id, TREE_BATCH_ROWS),
            ds.options.sync,
        )?;

        let rays_path = ds.dir.join(&rays_rel);
        let trees_path = ds.dir.join(&trees_rel);
        fs::rename(&self.tmp, &rays_path).map_err(io_err("moving a sealed segment into place", &rays_path))?;
        fs::rename(&trees_tmp, &trees_path).map_err(io_err("moving a sealed segment into place", &trees_path))?;
        if ds.options.sync {
            sync_dir(&ds.dir.join("segments"))?;
        }
        let entry = SegmentEntry {
            id: self.id,
            rays: FileEntry { path: rays_rel, bytes: rays.1, crc32: rays.0, rows: self.rows, columns: None },
            trees: FileEntry {
                path: trees_rel,
                bytes: trees.1,
                crc32: trees.0,
                rows: tree_count as u64,
                columns: None,
            },
            tree_id_min: id_min,
            tree_id_max: id_max,
            stats: std::mem::take(&mut self.stats),
        };
        self.return_tree_blocks();
        ds.commit(entry.clone(), kinds)?;
        Ok(Some(entry))
    }

    /// Drops the segment without sealing it (its temporary file is removed).
    pub fn abandon(mut self) {
        self.writer.take();
        let _ = fs::remove_file(&self.tmp);
    }
}

/// The predicted path payload of a ray batch of whole trees (`kind` its kind codes), its
/// columns in file order.
fn encode_path_payload(
    batch: &arrow::array::RecordBatch,
    kind: &[u8],
    chromas: &mut ChromaLearner,
) -> Result<Vec<arrow::array::ArrayRef>> {
    use arrow::array::AsArray;
    let col = |name: &str| batch.column_by_name(name).ok_or_else(|| Error::Encoding(format!("no column {name}")));
    let tree = col(crate::schema::col::TREE_ID)?
        .as_primitive_opt::<arrow::datatypes::UInt64Type>()
        .ok_or_else(|| Error::Encoding("tree_id is not UInt64".into()))?;
    crate::path_payload::encode_path(tree.values(), kind, col(THROUGHPUT)?, col(RADIANCE)?, chromas)
}

/// Refuses a directory that exists and holds anything: a new dataset never overwrites a trace.
fn ensure_empty(dir: &Path) -> Result<()> {
    if dir.exists() {
        let mut entries = fs::read_dir(dir).map_err(io_err("listing the dataset directory", dir))?;
        if entries.next().is_some() {
            return Err(Error::NotEmpty { path: dir.to_path_buf() });
        }
    }
    Ok(())
}

/// How a column of a ray file is written. Plain layouts, and payload columns of other types than
/// u8/u16/u32/f32 and fixed-size lists of them (`RayFileWriter` checks the types), go through
/// arrow-rs with [`ray_properties`]. In encoded layouts the rest is paged by `RayFileWriter`:
/// float payloads PLAIN (byte-splitting them hid their repeated triples from zstd: +8% bytes on
/// a path-tracer trace); tree ids (runs of +0/+1) delta-packed; the integer columns byte-split, because the high bytes of small integers and residuals and
/// the sign/exponent bytes of raw float bits are nearly constant and compress to almost nothing
/// apart from the low bytes (0.3-0.5 B/value less than plain on a Cornell-box trace; for
/// `kind_code` a dictionary costs a hash per row and saves ~0.02 B/ray). Residuals have no
/// useful min/max: the encoded columns carry no statistics.
fn column_plan(field: &arrow::datatypes::Field, encoding: Encoding) -> Plan {
    if encoding == Encoding::Plain {
        return Plan::Arrow;
    }
    let float = match field.data_type() {
        DataType::FixedSizeList(item, _) => item.data_type() == &DataType::Float32,
        t => t == &DataType::Float32,
    };
    match field.name().as_str() {
        crate::schema::col::TREE_ID => Plan::Delta,
        n if n == ENC_T || ENCODED_COLUMNS.contains(&n) => Plan::Split { stats: false },
        // The path payload: the colour and the throughput's residual channels byte-split (their
        // high bytes are nearly constant); the first channel's raw bits and the radiance
        // residuals (zeros, and the bits of repeated emitter values) plain: 17.0 instead of 17.8
        // B/ray with all six byte-split on a Cornell trace.
        n if n == ENC_CHROMA || ENC_THROUGHPUT[1..].contains(&n) => Plan::Split { stats: false },
        n if encoded_columns().any(|e| e == n) => Plan::Plain { stats: false },
        _ if float => Plan::Plain { stats: true },
        _ => Plan::Split { stats: true },
    }
}

/// Parquet properties of the ray files (for what arrow-rs writes of them: plain layouts and
/// payload columns [`column_plan`] leaves to it).
fn ray_properties(options: &WriteOptions, dir: &Path) -> Result<WriterProperties> {
    let level = ZstdLevel::try_new(options.zstd_level).map_err(pq_err(dir))?;
    let b = WriterProperties::builder()
        .set_compression(Compression::ZSTD(level))
        .set_dictionary_enabled(false)
        .set_column_dictionary_enabled(ColumnPath::from("kind"), true)
        .set_statistics_enabled(EnabledStatistics::Page);
    Ok(b.set_max_row_group_row_count(Some(options.row_group_rows.max(1)))
        .set_data_page_row_count_limit(options.page_rows.max(1))
        .set_key_value_metadata(Some(vec![
            KeyValue::new("rtvtk.format_version".into(), FORMAT_VERSION.to_string()),
            KeyValue::new("rtvtk.table".into(), "rays".to_string()),
        ]))
        .build())
}

/// Rows per data page of a tree table.
const TREE_PAGE_ROWS: usize = 2048;

/// Writes one small Parquet file (a segment's tree table, an optional table) to `tmp` in one go:
/// zstd, page statistics, rtvtk key-value metadata. Returns its CRC32 and size; the caller renames it.
fn write_small_table(
    tmp: &Path,
    table: &str,
    schema: &arrow::datatypes::SchemaRef,
    batches: impl IntoIterator<Item = Result<arrow::array::RecordBatch>>,
    sync: bool,
) -> Result<(u32, u64)> {
    let file = File::create(tmp).map_err(io_err("creating a table file", tmp))?;
    // Dictionaries only for text and byte columns: for numbers (node bounds, ids, counts) they
    // cost a hash per value and are dropped again once the dictionary page overflows (writing a
    // 267K-node `bvh_nodes` table spent most of its time hashing).
    let mut props = WriterProperties::builder().set_dictionary_enabled(false);
    for f in schema.fields() {
        if matches!(
            f.data_type(),
            DataType::Utf8 | DataType::LargeUtf8 | DataType::Utf8View | DataType::Binary | DataType::LargeBinary
        ) {
            props = props.set_column_dictionary_enabled(ColumnPath::from(f.name().as_str()), true);
        }
    }
    if table == "trees" {
        // Sorted ids and rows: deltas of +1 and of the tree sizes; pixels, samples and the
        // segment: runs and steps of +1. Tree sizes and depths: small values, one byte plane.
        use crate::schema::col;
        for name in [col::TREE_ID, col::FIRST_ROW, col::PIXEL_X, col::PIXEL_Y, col::SAMPLE, col::SEGMENT] {
            props = props.set_column_encoding(ColumnPath::from(name), Encoding_::DELTA_BINARY_PACKED);
        }
        for name in [col::RAY_COUNT, col::MAX_DEPTH] {
            props = props.set_column_encoding(ColumnPath::from(name), Encoding_::BYTE_STREAM_SPLIT);
        }
        // Small pages: a lookup by id or pixel decodes one page of each column (at arrow-rs's
        // default of 20K rows that was 1.5 ms of a 2.5 ms fetch); the file grows by a few percent.
        props = props.set_data_page_row_count_limit(TREE_PAGE_ROWS).set_write_batch_size(TREE_PAGE_ROWS);
    }
    let props = props
        .set_compression(Compression::ZSTD(ZstdLevel::default()))
        .set_statistics_enabled(EnabledStatistics::Page)
        .set_key_value_metadata(Some(vec![
            KeyValue::new("rtvtk.format_version".into(), FORMAT_VERSION.to_string()),
            KeyValue::new("rtvtk.table".into(), table.to_string()),
        ]))
        .build();
    let mut w =
        ArrowWriter::try_new(CrcWriter::new(BufWriter::new(file)), schema.clone(), Some(props)).map_err(pq_err(tmp))?;
    for batch in batches {
        w.write(&batch?).map_err(pq_err(tmp))?;
    }
    let sink = w.into_inner().map_err(pq_err(tmp))?;
    finish_file(sink, tmp, sync)
}

fn finish_file(sink: FileSink, path: &Path, sync: bool) -> Result<(u32, u64)> {
    let (buf, crc, bytes) = sink.finish();
    let file = buf.into_inner().map_err(|e| Error::Io {
        action: "flushing a segment file",
        path: path.to_path_buf(),
        source: e.into_error(),
    })?;
    if sync {
        file.sync_all().map_err(io_err("syncing a segment file", path))?;
    }
    Ok((crc, bytes))
}

/// Writes a copy of `ds` at `out` (which must not exist or be empty) whose ray files hold plain
/// float origins and directions (`"encoding": "plain"`), for tools that read the Parquet files
/// directly. Segments, tree files and optional tables keep their names; the manifest is written
/// last, so an interrupted export is not a dataset.
pub fn export_plain(ds: &crate::Dataset, out: &Path) -> Result<Manifest> {
    ensure_empty(out)?;
    let options = WriteOptions { encoding: Encoding::Plain, ..WriteOptions::default() };
    fs::create_dir_all(out.join("segments")).map_err(io_err("creating the export directory", out))?;
    let mut manifest = ds.manifest().clone();
    manifest.encoding = Encoding::Plain;
    manifest.format_version = FORMAT_VERSION;
    let schema = ray_schema(ds.payload_schema());
    for (i, seg) in manifest.segments.iter_mut().enumerate() {
        let path = out.join(&seg.rays.path);
        let tmp = out.join(format!("{}.tmp", seg.rays.path));
        let file = File::create(&tmp).map_err(io_err("creating a segment file", &tmp))?;
        let sink = CrcWriter::new(BufWriter::with_capacity(1 << 20, file));
        let mut w =
            ArrowWriter::try_new(sink, schema.clone(), Some(ray_properties(&options, out)?)).map_err(pq_err(&tmp))?;
        for batch in ds.segment_batches(i)? {
            w.write(&batch?).map_err(pq_err(&tmp))?;
        }
        let sink = w.into_inner().map_err(pq_err(&tmp))?;
        let (crc, bytes) = finish_file(sink, &tmp, true)?;
        fs::rename(&tmp, &path).map_err(io_err("moving a segment into place", &path))?;
        seg.rays.crc32 = crc;
        seg.rays.bytes = bytes;
        let from = ds.dir().join(&seg.trees.path);
        fs::copy(&from, out.join(&seg.trees.path)).map_err(io_err("copying a tree file", &from))?;
    }
    if !manifest.tables.is_empty() {
        fs::create_dir_all(out.join("tables")).map_err(io_err("creating the tables directory", out))?;
    }
    for file in manifest.tables.values() {
        let from = ds.dir().join(&file.path);
        fs::copy(&from, out.join(&file.path)).map_err(io_err("copying a table", &from))?;
    }
    sync_dir(&out.join("segments"))?;
    manifest.store(out, true)?;
    Ok(manifest)
}
