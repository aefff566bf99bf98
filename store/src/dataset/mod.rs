//! Reading a dataset: opening and validating it (the manifest, the files' schemas), its
//! accessors and segment metadata; the tree index (`index`), random access and projected reads
//! (`read`) and the sequential scan (`scan`) live in the child modules. `check` sits on top.

mod index;
mod plan;
mod pooled;
mod read;
mod scan;

use index::TreeIndex;
pub use index::{TreeEntry, TreeFilter};
pub use plan::{AccessPlan, SegmentAccess};
pub use read::READ_BATCH_ROWS;
pub(crate) use read::cores;
use read::select_rows;
pub use scan::TreeIter;

use std::collections::{BTreeSet, HashMap};
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use arrow::array::RecordBatch;
use arrow::compute::concat_batches;
use arrow::datatypes::{SchemaRef, UInt16Type, UInt32Type, UInt64Type};
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection, RowSelector,
};
use parquet::file::metadata::PageIndexPolicy;

use crate::codec::{Decoder, ENC_T, Encoding, file_schema};
use crate::error::{arrow_err, io_err, pq_err};
use crate::manifest::{MANIFEST_FILE, Manifest, SegmentEntry};
use crate::path_payload::CHROMAS_KEY;
use crate::planes::{PLANES_KEY, Planes};
use crate::schema::{KindTable, PayloadSchema, ray_schema, tree_schema};
use crate::stats::Stats;
use crate::tree::{Tree, TreeId, TreeInfo, rays_from_batch, tree_ids_of, validate_tree};
use crate::{Error, Kind, Result};

struct SegmentMeta {
    meta: ArrowReaderMetadata,
    /// First row of each row group.
    row_group_starts: Vec<u64>,
    /// The planes hit distances are predicted from (format version 3; empty before).
    planes: Arc<Planes>,
    /// The throughput colours (format version 4 with the path payload; empty otherwise).
    chromas: Arc<crate::path_payload::Chromas>,
    /// The root column at which a read of a few trees splits the file's columns in two for two
    /// threads: the halves hold about the same bytes, compressed and decompressed together.
    split_root: usize,
}

/// A trace dataset opened for reading.
pub struct Dataset {
    dir: PathBuf,
    manifest: Manifest,
    payload: PayloadSchema,
    kinds: KindTable,
    kinds_by_name: HashMap<String, Kind>,
    schema: SchemaRef,
    /// Schema of the ray files (differs from `schema` when origins and directions are encoded).
    file_schema: SchemaRef,
    metas: Vec<OnceLock<Arc<SegmentMeta>>>,
    index: OnceLock<Arc<TreeIndex>>,
    /// Each segment's tree-file footer with its page index, loaded on the first lookup in it.
    tree_metas: Vec<OnceLock<ArrowReaderMetadata>>,
    /// Why a segment's tree file cannot be read (missing, or not the size the manifest records),
    /// found at open: that segment's trees are unavailable, its rays and every other segment
    /// stay readable.
    tree_faults: Vec<Option<String>>,
    /// Each segment's tree file checked whole (size, CRC32, schema), once, by
    /// [`Dataset::verify_trees`].
    tree_checks: Vec<OnceLock<std::result::Result<(), String>>>,
    /// Each whole-dataset table of the manifest checked whole (size, CRC32, schema), once, by
    /// [`Dataset::verify_table`].
    table_checks: std::collections::BTreeMap<String, OnceLock<std::result::Result<(), String>>>,
}

/// Datasets opened by this process so far (see [`Dataset::opened`]).
static OPENED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

impl Dataset {
    /// How many times this process has called [`Dataset::open`]: a process shares one open
    /// dataset (and its tree index) among its readers, and its tests check it with this.
    pub fn opened() -> u64 {
        OPENED.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Opens the dataset at `dir`: reads the manifest and checks every listed file is there
    /// with the size the manifest records.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        OPENED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = dir.as_ref().to_path_buf();
        let manifest = Manifest::load(&dir)?;
        let payload = manifest.payload_schema(&dir.join(MANIFEST_FILE))?;
        // A ray file that is missing or of another size refuses the dataset; a tree file only
        // makes its segment's trees unavailable (`tree_faults`).
        let mut tree_faults = Vec::with_capacity(manifest.segments.len());
        for seg in &manifest.segments {
            let path = dir.join(&seg.rays.path);
            let len = match fs::metadata(&path) {
                Ok(m) => m.len(),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    return Err(Error::MissingFile { segment: seg.id, path });
                }
                Err(e) => return Err(Error::Io { action: "reading segment file metadata", path, source: e }),
            };
            if len != seg.rays.bytes {
                return Err(Error::SizeMismatch { segment: seg.id, path, expected: seg.rays.bytes, found: len });
            }
            tree_faults.push(file_fault(&dir.join(&seg.trees.path), seg.trees.bytes));
        }
        // Whole-dataset tables are checked when read (`table`, `table_schema`): a broken one is
        // unavailable alone, the rays stay readable.
        let kinds = manifest.kind_table();
        let kinds_by_name = manifest.kinds.iter().map(|(n, c)| (n.clone(), Kind(*c))).collect();
        let metas = manifest.segments.iter().map(|_| OnceLock::new()).collect();
        let tree_metas = manifest.segments.iter().map(|_| OnceLock::new()).collect();
        let table_checks = manifest.tables.keys().map(|t| (t.clone(), OnceLock::new())).collect();
        let schema = ray_schema(&payload);
        Ok(Self {
            file_schema: file_schema(&schema, manifest.encoding, manifest.format_version),
            schema,
            dir,
            manifest,
            payload,
            kinds,
            kinds_by_name,
            metas,
            index: OnceLock::new(),
            tree_metas,
            tree_checks: tree_faults.iter().map(|_| OnceLock::new()).collect(),
            tree_faults,
            table_checks,
        })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    pub fn stats(&self) -> &Stats {
        &self.manifest.stats
    }

    pub fn payload_schema(&self) -> &PayloadSchema {
        &self.payload
    }

    /// The Arrow schema of the ray table.
    pub fn ray_schema(&self) -> SchemaRef {
        self.schema.clone()
    }

    pub fn kinds(&self) -> &KindTable {
        &self.kinds
    }

    /// Paths of the ray files, in segment order (for engines that read the Parquet directly).
    pub fn ray_files(&self) -> Vec<PathBuf> {
        self.manifest.segments.iter().map(|s| self.dir.join(&s.rays.path)).collect()
    }

    /// Paths of the tree files, in segment order.
    pub fn tree_files(&self) -> Vec<PathBuf> {
        self.manifest.segments.iter().map(|s| self.dir.join(&s.trees.path)).collect()
    }

    /// The names of the whole-dataset tables the recording wrote (`triangles`, `lights`, ...),
    /// sorted.
    pub fn table_names(&self) -> Vec<String> {
        self.manifest.tables.keys().cloned().collect()
    }

    /// The schema of a whole-dataset table as its file holds it, read from the Parquet footer
    /// and checked against the table's known schema (`store::scene::check_table`: a known
    /// table missing a column or with a column of another type is an `Error::Table` naming it);
    /// `None` when the recording wrote no such table.
    pub fn table_schema(&self, name: &str) -> Result<Option<SchemaRef>> {
        Ok(self.table_reader(name)?.map(|(_, reader)| reader.schema().clone()))
    }

    /// An optional whole-dataset table (`bvh_nodes`, `lights`, ...), if the recording wrote it,
    /// verified whole first ([`Dataset::verify_table`]).
    pub fn table(&self, name: &str) -> Result<Option<RecordBatch>> {
        if !self.verify_table(name)? {
            return Ok(None);
        }
        let Some((path, reader)) = self.table_reader(name)? else { return Ok(None) };
        let schema = reader.schema().clone();
        let mut batches = Vec::new();
        for b in Guarded::new(reader.build().map_err(pq_err(&path))?, &path) {
            batches.push(b?);
        }
        concat_batches(&schema, &batches).map(Some).map_err(arrow_err(path.display().to_string()))
    }

    /// The reader of a whole-dataset table's file, its schema checked against the table's
    /// known one (`Error::Table` naming the table and column when it does not match).
    fn table_reader(&self, name: &str) -> Result<Option<(PathBuf, ParquetRecordBatchReaderBuilder<File>)>> {
        let Some(path) = self.table_file(name)? else { return Ok(None) };
        let f = File::open(&path).map_err(io_err("opening a table file", &path))?;
        let builder =
            guard(&path, || ParquetRecordBatchReaderBuilder::try_new(f).map_err(pq_err(&path))).map_err(|e| {
                Error::Table { name: name.into(), path: path.clone(), message: crate::error::unreadable(e) }
            })?;
        if let Err(message) = crate::scene::check_table(name, builder.schema()) {
            return Err(Error::Table { name: name.into(), path, message });
        }
        // The columns the manifest records it was written with (any table, known or not).
        if let Some(expected) = self.manifest.tables.get(name).and_then(|f| f.columns.as_ref()) {
            let found = crate::manifest::table_columns(builder.schema());
            if &found != expected {
                let message = format!(
                    "its file has the columns [{}]: expected [{}] as the manifest records",
                    found.join(", "),
                    expected.join(", ")
                );
                return Err(Error::Table { name: name.into(), path, message });
            }
        }
        Ok(Some((path, builder)))
    }

    /// The file of a whole-dataset table, if the recording wrote it, checked to have the size
    /// the manifest records (`Error::Table` naming the table when truncated, changed or gone).
    fn table_file(&self, name: &str) -> Result<Option<PathBuf>> {
        let Some(file) = self.manifest.tables.get(name) else { return Ok(None) };
        let path = self.dir.join(&file.path);
        match file_fault(&path, file.bytes) {
            None => Ok(Some(path)),
            Some(message) => Err(Error::Table { name: name.into(), path, message }),
        }
    }

    /// Checks that the whole-dataset table `name` can be read: its file is there with the size
    /// and CRC32 the manifest records, and its columns match the table's known schema (an
    /// `Error::Table` naming the table and what is wrong otherwise). `Ok(false)` when the
    /// recording wrote no such table. The file is read whole once per process for its checksum
    /// (a broken table is unavailable alone: the rays and the other tables stay readable); later
    /// calls answer from memory.
    pub fn verify_table(&self, name: &str) -> Result<bool> {
        let (Some(file), Some(cell)) = (self.manifest.tables.get(name), self.table_checks.get(name)) else {
            return Ok(false);
        };
        let path = self.dir.join(&file.path);
        let outcome = cell.get_or_init(|| match verify_file(&path, file.bytes, file.crc32) {
            Some(m) => Err(m),
            None => self.table_reader(name).map(|_| ()).map_err(crate::error::unreadable),
        });
        outcome.clone().map(|()| true).map_err(|message| Error::Table { name: name.into(), path, message })
    }

    /// Why segment `i`'s tree file cannot be read, as found at open (missing, or not the size
    /// the manifest records): an `Error::TreeTable` naming the segment, or nothing.
    pub(crate) fn tree_fault(&self, i: usize) -> Result<()> {
        match self.tree_faults.get(i).and_then(|f| f.as_ref()) {
            None => Ok(()),
            Some(message) => Err(Error::TreeTable {
                segment: self.segment(i).id,
                path: self.dir.join(&self.segment(i).trees.path),
                message: message.clone(),
            }),
        }
    }

    /// Checks segment `i`'s tree file whole: there, with the size and CRC32 the manifest
    /// records, and the tree table's columns (an `Error::TreeTable` naming the segment
    /// otherwise). Read once per process (what SQL's `trees` table does before its first scan);
    /// lookups of a few trees check only the size and the footer.
    pub fn verify_trees(&self, i: usize) -> Result<()> {
        self.tree_fault(i)?;
        let Some(cell) = self.tree_checks.get(i) else { return Ok(()) };
        let seg = self.segment(i);
        let path = self.dir.join(&seg.trees.path);
        let outcome = cell.get_or_init(|| match verify_file(&path, seg.trees.bytes, seg.trees.crc32) {
            Some(m) => Err(m),
            None => self.tree_file(i).map(|_| ()).map_err(crate::error::unreadable),
        });
        outcome.clone().map_err(|message| Error::TreeTable { segment: seg.id, path, message })
    }

    /// Path of an optional table's Parquet file, if the recording wrote it.
    pub fn table_path(&self, name: &str) -> Option<PathBuf> {
        self.manifest.tables.get(name).map(|f| self.dir.join(&f.path))
    }

    fn segment(&self, i: usize) -> &SegmentEntry {
        &self.manifest.segments[i]
    }

    fn segment_meta(&self, i: usize) -> Result<Arc<SegmentMeta>> {
        if let Some(m) = self.metas[i].get() {
            return Ok(m.clone());
        }
        let path = self.dir.join(&self.segment(i).rays.path);
        let file = File::open(&path).map_err(io_err("opening a ray file", &path))?;
        // The offset index (where each page starts) is what reads of a few trees need; the column
        // index (per-page statistics) is never consulted on ray files and was most of the
        // footer's memory, which the dataset keeps per segment.
        let options = ArrowReaderOptions::new()
            .with_offset_index_policy(PageIndexPolicy::Required)
            .with_column_index_policy(PageIndexPolicy::Skip);
        let meta = guard(&path, || ArrowReaderMetadata::load(&file, options).map_err(pq_err(&path)))?;
        check_schema(meta.schema(), &self.file_schema, &path)?;
        let starts = row_group_starts(&meta);
        let row: u64 =
            meta.metadata().row_groups().iter().fold(0u64, |a, g| a.saturating_add(g.num_rows().max(0) as u64));
        if row != self.segment(i).rays.rows {
            return Err(Error::Corrupt {
                path,
                what: "ray file".into(),
                message: format!("manifest lists {} rows, file holds {row}", self.segment(i).rays.rows),
            });
        }
        // What the writer learned of the segment, in the file's key-value metadata.
        let learned = |key: &str| {
            meta.metadata()
                .file_metadata()
                .key_value_metadata()
                .and_then(|kv| kv.iter().find(|e| e.key == key).and_then(|e| e.value.clone()))
        };
        let bad_metadata =
            |message: String| Error::Corrupt { path: path.clone(), what: "ray file metadata".into(), message };
        let planes = match learned(PLANES_KEY) {
            Some(v) => Planes::from_metadata(&v).map_err(bad_metadata)?,
            None => Planes::default(),
        };
        let chromas = match learned(CHROMAS_KEY) {
            Some(v) => crate::path_payload::Chromas::from_metadata(&v).map_err(bad_metadata)?,
            None => Default::default(),
        };
        let split_root = balanced_split(&meta);
        let m = Arc::new(SegmentMeta {
            meta,
            row_group_starts: starts,
            planes: Arc::new(planes),
            chromas: Arc::new(chromas),
            split_root,
        });
        let _ = self.metas[i].set(m.clone());
        Ok(m)
    }

    /// How the ray files store origins and directions.
    pub fn encoding(&self) -> Encoding {
        self.manifest.encoding
    }

    /// The schema of the ray files as stored (the ray table schema for `plain` datasets).
    pub fn file_schema(&self) -> SchemaRef {
        self.file_schema.clone()
    }

    /// A decoder from segment `i`'s ray-file batches (starting at a tree) to ray-table batches.
    pub fn decoder(&self, i: usize) -> Result<Decoder> {
        let (planes, chromas) = if self.manifest.encoding == Encoding::Plain {
            (Arc::default(), Arc::default())
        } else {
            let m = self.segment_meta(i)?;
            (m.planes.clone(), m.chromas.clone())
        };
        Ok(Decoder::new(self.manifest.encoding, self.schema.clone(), self.kinds.clone())
            .with_planes(planes)
            .with_chromas(chromas))
    }

    pub(crate) fn segment_entries(&self, i: usize) -> Result<Vec<TreeEntry>> {
        self.read_tree_table(i)
    }

    pub(crate) fn segment_meta_checked(&self, i: usize) -> Result<()> {
        self.segment_meta(i).map(|_| ())
    }

    /// The rows of each row group of segment `i`'s ray file, in order. Row groups of encoded
    /// files start at trees, so each decodes on its own.
    pub fn segment_row_groups(&self, i: usize) -> Result<Vec<std::ops::Range<u64>>> {
        let starts = self.row_group_starts(i)?;
        let rows = self.segment(i).rays.rows;
        Ok(starts.iter().enumerate().map(|(k, &a)| a..starts.get(k + 1).copied().unwrap_or(rows)).collect())
    }

    /// First row of each row group of segment `i`'s ray file.
    pub(crate) fn row_group_starts(&self, i: usize) -> Result<Vec<u64>> {
        Ok(self.segment_meta(i)?.row_group_starts.clone())
    }
}

/// The root column splitting a file's columns into two runs whose column chunks hold about the
/// same compressed plus decompressed bytes (what decoding them costs); at least one root on
/// each side where there are two.
fn balanced_split(meta: &ArrowReaderMetadata) -> usize {
    let schema = meta.metadata().file_metadata().schema_descr();
    let roots = schema.root_schema().get_fields().len();
    let mut cost = vec![0u64; roots];
    for rg in meta.metadata().row_groups() {
        for (leaf, c) in rg.columns().iter().enumerate().take(schema.num_columns()) {
            let root = schema.get_column_root_idx(leaf);
            if let Some(slot) = cost.get_mut(root) {
                let bytes = c.compressed_size().max(0) as u64 + c.uncompressed_size().max(0) as u64;
                *slot = slot.saturating_add(bytes);
            }
        }
    }
    let total: u64 = cost.iter().sum();
    let mut acc = 0u64;
    let mut split = roots / 2;
    for (r, c) in cost.iter().enumerate() {
        if acc.saturating_add(c / 2) >= total / 2 {
            split = r;
            break;
        }
        acc += c;
    }
    if roots < 2 { split } else { split.clamp(1, roots - 1) }
}

/// A Parquet batch reader whose errors and panics name the file, and which ends after its first
/// error. arrow-rs asserts on some corrupt pages (found by the fuzz harness: a fixed-size binary
/// page whose length disagrees with its values' count, and a definition-level bitmap of the wrong
/// length, panic in `parquet` 59.3); such a panic becomes an error naming the file. After a
/// decode error arrow-rs's reader can return the same error forever (a consumer collecting
/// errors never ended: the harness ran out of memory).
pub(crate) struct Guarded {
    inner: parquet::arrow::arrow_reader::ParquetRecordBatchReader,
    path: PathBuf,
    done: bool,
}

impl Guarded {
    pub(crate) fn new(inner: parquet::arrow::arrow_reader::ParquetRecordBatchReader, path: &Path) -> Self {
        Self { inner, path: path.to_path_buf(), done: false }
    }

    pub(crate) fn schema(&self) -> SchemaRef {
        arrow::record_batch::RecordBatchReader::schema(&self.inner)
    }
}

impl Iterator for Guarded {
    type Item = Result<RecordBatch>;

    fn next(&mut self) -> Option<Result<RecordBatch>> {
        if self.done {
            return None;
        }
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.inner.next())) {
            Ok(None) => None,
            Ok(Some(Ok(b))) => Some(Ok(b)),
            Ok(Some(Err(e))) => {
                // arrow-rs's reader may repeat an error forever: the first one ends it.
                self.done = true;
                Some(Err(Error::Parquet { path: self.path.clone(), source: e.into() }))
            }
            Err(panic) => {
                self.done = true;
                Some(Err(rejected(&self.path, "Parquet page", panic.as_ref())))
            }
        }
    }
}

/// The error for a panic of arrow-rs on corrupt input, naming the file.
fn rejected(path: &Path, what: &str, panic: &(dyn std::any::Any + Send)) -> Error {
    let text = panic
        .downcast_ref::<String>()
        .map(String::as_str)
        .or_else(|| panic.downcast_ref::<&str>().copied())
        .unwrap_or("no message");
    Error::Corrupt {
        path: path.to_path_buf(),
        what: what.into(),
        message: format!("the Parquet decoder rejected corrupt data ({text})"),
    }
}

/// Runs arrow-rs's reading of a file's footer, its panics on corrupt input (an embedded Arrow
/// schema with a 28704-bit integer panics in `arrow-ipc` 59.3, found by the fuzz harness) made
/// errors naming the file.
pub(crate) fn guard<T>(path: &Path, f: impl FnOnce() -> Result<T>) -> Result<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
        .unwrap_or_else(|panic| Err(rejected(path, "Parquet footer", panic.as_ref())))
}

fn check_schema(found: &SchemaRef, expected: &SchemaRef, path: &Path) -> Result<()> {
    for f in expected.fields() {
        match found.field_with_name(f.name()) {
            Ok(g) if g.data_type() == f.data_type() => {}
            Ok(g) => {
                return Err(Error::Schema {
                    path: path.to_path_buf(),
                    field: f.name().clone(),
                    expected: f.data_type().to_string(),
                    found: g.data_type().to_string(),
                });
            }
            Err(_) => {
                return Err(Error::Schema {
                    path: path.to_path_buf(),
                    field: f.name().clone(),
                    expected: f.data_type().to_string(),
                    found: "no such column".into(),
                });
            }
        }
    }
    if found.fields().len() != expected.fields().len() {
        let extra: Vec<_> = found
            .fields()
            .iter()
            .filter(|f| expected.field_with_name(f.name()).is_err())
            .map(|f| f.name().clone())
            .collect();
        return Err(Error::Schema {
            path: path.to_path_buf(),
            field: extra.join(", "),
            expected: "only the columns the manifest declares".into(),
            found: "undeclared columns".into(),
        });
    }
    Ok(())
}

/// The first row of each row group of a file.
fn row_group_starts(meta: &ArrowReaderMetadata) -> Vec<u64> {
    meta.metadata()
        .row_groups()
        .iter()
        .scan(0u64, |row, g| {
            let start = *row;
            *row += g.num_rows() as u64;
            Some(start)
        })
        .collect()
}

/// Why the file at `path` cannot be the one a manifest lists with `bytes` bytes: missing,
/// unreadable, or of another size (truncated or changed); `None` when it can.
fn file_fault(path: &Path, bytes: u64) -> Option<String> {
    match fs::metadata(path) {
        Ok(m) if m.len() == bytes => None,
        Ok(m) => {
            Some(format!("expected {bytes} bytes as the manifest records, found {}: truncated or changed", m.len()))
        }
        Err(e) => Some(format!("listed in the manifest but cannot be read: {e}")),
    }
}

/// [`file_fault`], then the file's CRC32 against the manifest's `crc32` (the file read whole).
fn verify_file(path: &Path, bytes: u64, crc32: u32) -> Option<String> {
    if let Some(m) = file_fault(path, bytes) {
        return Some(m);
    }
    match crc_of(path) {
        Ok((crc, _)) if crc != crc32 => Some(format!(
            "expected CRC32 {crc32:08x} as the manifest records, computed {crc:08x}: the file is corrupted"
        )),
        Ok(_) => None,
        Err(e) => Some(format!("cannot be read: {e}")),
    }
}

/// The CRC32 and length of the file at `path`, read through once.
pub(crate) fn crc_of(path: &Path) -> std::io::Result<(u32, u64)> {
    use std::io::Read;
    let mut f = File::open(path)?;
    let mut h = crc32fast::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf)?;
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        n += k as u64;
    }
    Ok((h.finalize(), n))
}
