//! Reading a dataset: the manifest, the tree index, one tree by id or pixel, every tree in order,
//! and `check`.

use std::collections::{BTreeSet, HashMap};
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use arrow::array::{AsArray, RecordBatch};
use arrow::compute::concat_batches;
use arrow::datatypes::{SchemaRef, UInt16Type, UInt32Type, UInt64Type};
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection, RowSelector,
};
use parquet::file::metadata::PageIndexPolicy;

use crate::codec::{Decoder, ENC_T, Encoding, file_schema};
use crate::error::{arrow_err, io_err, pq_err};
use crate::manifest::{MANIFEST_FILE, Manifest, SegmentEntry};
use crate::planes::{PLANES_KEY, Planes};
use crate::schema::{KindTable, PayloadSchema, ray_schema, tree_schema};
use crate::stats::Stats;
use crate::tree::{Tree, TreeId, TreeInfo, rays_from_batch, tree_ids_of, validate_tree};
use crate::{Error, Kind, Result};

/// Where one tree's rays are.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TreeEntry {
    pub info: TreeInfo,
    /// Index of the segment in the manifest's list.
    pub segment: u32,
    /// Row of the first ray in that segment's ray file.
    pub first_row: u64,
}

/// The in-memory tree index: every tree, sorted by id, plus a pixel order.
struct TreeIndex {
    by_id: Vec<TreeEntry>,
    /// Positions in `by_id`, sorted by (pixel y, pixel x, sample, id).
    by_pixel: Vec<u32>,
}

struct SegmentMeta {
    meta: ArrowReaderMetadata,
    /// First row of each row group.
    row_group_starts: Vec<u64>,
    /// The planes hit distances are predicted from (format version 3; empty before).
    planes: Arc<Planes>,
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
    /// Each segment's tree table (sorted by id), loaded on the first lookup by id that needs it.
    segment_trees: Vec<OnceLock<Arc<Vec<TreeEntry>>>>,
}

impl Dataset {
    /// Opens the dataset at `dir`: reads the manifest and checks every listed file is there
    /// with the size the manifest records.
    pub fn open(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref().to_path_buf();
        let manifest = Manifest::load(&dir)?;
        let payload = manifest.payload_schema(&dir.join(MANIFEST_FILE))?;
        for seg in &manifest.segments {
            for file in [&seg.rays, &seg.trees] {
                let path = dir.join(&file.path);
                let len = match fs::metadata(&path) {
                    Ok(m) => m.len(),
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                        return Err(Error::MissingFile { segment: seg.id, path });
                    }
                    Err(e) => {
                        return Err(Error::Io { action: "reading segment file metadata", path, source: e });
                    }
                };
                if len != file.bytes {
                    return Err(Error::SizeMismatch { segment: seg.id, path, expected: file.bytes, found: len });
                }
            }
        }
        for (name, file) in &manifest.tables {
            let path = dir.join(&file.path);
            let message = match fs::metadata(&path) {
                Ok(m) if m.len() == file.bytes => continue,
                Ok(m) => format!(
                    "expected {} bytes as the manifest records, found {}: truncated or changed",
                    file.bytes,
                    m.len()
                ),
                Err(e) => format!("listed in the manifest but cannot be read: {e}"),
            };
            return Err(Error::Table { name: name.clone(), path, message });
        }
        let kinds = manifest.kind_table();
        let kinds_by_name = manifest.kinds.iter().map(|(n, c)| (n.clone(), Kind(*c))).collect();
        let metas = manifest.segments.iter().map(|_| OnceLock::new()).collect();
        let segment_trees = manifest.segments.iter().map(|_| OnceLock::new()).collect();
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
            segment_trees,
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

    /// An optional whole-dataset table (`bvh_nodes`, `lights`, ...), if the recording wrote it.
    pub fn table(&self, name: &str) -> Result<Option<RecordBatch>> {
        let Some(file) = self.manifest.tables.get(name) else { return Ok(None) };
        let path = self.dir.join(&file.path);
        let f = File::open(&path).map_err(io_err("opening a table file", &path))?;
        let builder = ParquetRecordBatchReaderBuilder::try_new(f).map_err(pq_err(&path))?;
        let schema = builder.schema().clone();
        crate::scene::check_table(name, &schema).map_err(|message| Error::Table {
            name: name.into(),
            path: path.clone(),
            message,
        })?;
        let reader = builder.build().map_err(pq_err(&path))?;
        let mut batches = Vec::new();
        for b in reader {
            batches.push(b.map_err(|e| Error::Parquet { path: path.clone(), source: e.into() })?);
        }
        concat_batches(&schema, &batches).map(Some).map_err(arrow_err(path.display().to_string()))
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
        let meta = ArrowReaderMetadata::load(
            &file,
            ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Required),
        )
        .map_err(pq_err(&path))?;
        check_schema(meta.schema(), &self.file_schema, &path)?;
        let starts = row_group_starts(&meta);
        let row: u64 = meta.metadata().row_groups().iter().map(|g| g.num_rows() as u64).sum();
        if row != self.segment(i).rays.rows {
            return Err(Error::Corrupt {
                path,
                what: "ray file".into(),
                message: format!("manifest lists {} rows, file holds {row}", self.segment(i).rays.rows),
            });
        }
        let planes = match meta
            .metadata()
            .file_metadata()
            .key_value_metadata()
            .and_then(|kv| kv.iter().find(|e| e.key == PLANES_KEY).and_then(|e| e.value.as_deref()))
        {
            Some(v) => Planes::from_metadata(v).map_err(|message| Error::Corrupt {
                path: path.clone(),
                what: "ray file metadata".into(),
                message,
            })?,
            None => Planes::default(),
        };
        let m = Arc::new(SegmentMeta { meta, row_group_starts: starts, planes: Arc::new(planes) });
        let _ = self.metas[i].set(m.clone());
        Ok(m)
    }

    /// Reads the tree table of segment `i`, sorted by id.
    fn read_tree_table(&self, i: usize) -> Result<Vec<TreeEntry>> {
        let seg = self.segment(i);
        let path = self.dir.join(&seg.trees.path);
        let file = File::open(&path).map_err(io_err("opening a tree file", &path))?;
        let builder = ParquetRecordBatchReaderBuilder::try_new(file).map_err(pq_err(&path))?;
        check_schema(builder.schema(), &tree_schema(), &path)?;
        let reader = builder.with_batch_size(64 * 1024).build().map_err(pq_err(&path))?;
        let mut out = Vec::with_capacity(seg.trees.rows as usize);
        for batch in reader {
            let b = batch.map_err(|e| Error::Parquet { path: path.clone(), source: e.into() })?;
            push_tree_entries(&b, i, &mut out);
        }
        if out.len() as u64 != seg.trees.rows {
            return Err(Error::Corrupt {
                path,
                what: "tree file".into(),
                message: format!("manifest lists {} trees, file holds {}", seg.trees.rows, out.len()),
            });
        }
        if !out.is_sorted_by_key(|e| e.info.id) {
            out.sort_unstable_by_key(|e| e.info.id);
        }
        Ok(out)
    }

    /// The trees of segment `i` whose ids fall in `ranges` (inclusive bounds), sorted by id. Reads
    /// only the tree-table pages whose id range (the file's page index) overlaps `ranges`, so a
    /// lookup of a few trees does not decode the whole table; uses the table when already loaded.
    pub fn segment_tree_entries_in(&self, i: usize, ranges: &[(u64, u64)]) -> Result<Vec<TreeEntry>> {
        let wanted = |id: u64| ranges.iter().any(|&(lo, hi)| lo <= id && id <= hi);
        if let Some(all) = self.segment_trees.get(i).and_then(|c| c.get()) {
            return Ok(all.iter().filter(|e| wanted(e.info.id.0)).copied().collect());
        }
        let path = self.dir.join(&self.segment(i).trees.path);
        let file = File::open(&path).map_err(io_err("opening a tree file", &path))?;
        let options = ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Optional);
        let meta = ArrowReaderMetadata::load(&file, options).map_err(pq_err(&path))?;
        check_schema(meta.schema(), &tree_schema(), &path)?;
        let Some(rows) = tree_id_pages(&meta, ranges) else {
            // No page index (not written by this store): the whole table.
            return Ok(self.segment_tree_entries(i)?.iter().filter(|e| wanted(e.info.id.0)).copied().collect());
        };
        let mut out = Vec::new();
        if rows.is_empty() {
            return Ok(out);
        }
        let (groups, selection) = select_rows(&row_group_starts(&meta), &meta, &rows);
        let reader = ParquetRecordBatchReaderBuilder::new_with_metadata(file, meta)
            .with_row_groups(groups)
            .with_row_selection(selection)
            .with_batch_size(64 * 1024)
            .build()
            .map_err(pq_err(&path))?;
        for batch in reader {
            let b = batch.map_err(|e| Error::Parquet { path: path.clone(), source: e.into() })?;
            push_tree_entries(&b, i, &mut out);
        }
        out.retain(|e| wanted(e.info.id.0));
        out.sort_unstable_by_key(|e| e.info.id);
        Ok(out)
    }

    fn index(&self) -> Result<Arc<TreeIndex>> {
        if let Some(ix) = self.index.get() {
            return Ok(ix.clone());
        }
        // Tree tables are read on up to 4 threads; each is sorted by id already (sorted here if
        // not), and the runs are merged (a sort of the whole index took ~1 s at 24M trees).
        let n = self.manifest.segments.len();
        let threads = cores().clamp(1, 4).min(n.max(1));
        let parts: Vec<Result<Vec<Vec<TreeEntry>>>> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..threads)
                .map(|t| s.spawn(move || (t..n).step_by(threads).map(|i| self.read_tree_table(i)).collect()))
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|_| Err(Error::Encoding("index thread panicked".into()))))
                .collect()
        });
        let runs: Vec<Vec<TreeEntry>> = parts.into_iter().collect::<Result<Vec<_>>>()?.into_iter().flatten().collect();
        let mut by_id = Vec::with_capacity(runs.iter().map(Vec::len).sum());
        by_id.extend(crate::columns::RunMerge::new(&runs, |e: &TreeEntry| e.info.id.0).copied());
        drop(runs);
        // Pixel order: (y, x, sample) packed into one key when they fit (a stable sort keeps id
        // order among equal keys); the general comparison otherwise.
        let fits =
            by_id.iter().all(|e| e.info.pixel[0] < 1 << 20 && e.info.pixel[1] < 1 << 20 && e.info.sample < 1 << 24);
        let by_pixel: Vec<u32> = if fits {
            let mut keyed: Vec<(u64, u32)> = by_id
                .iter()
                .enumerate()
                .map(|(k, e)| {
                    let i = &e.info;
                    ((u64::from(i.pixel[1]) << 44) | (u64::from(i.pixel[0]) << 24) | u64::from(i.sample), k as u32)
                })
                .collect();
            // Trees are traced pass after pass over the image: in id order the keys are a few
            // long sorted runs, which the run-adaptive stable sort merges.
            keyed.sort();
            keyed.into_iter().map(|(_, k)| k).collect()
        } else {
            let mut v: Vec<u32> = (0..by_id.len() as u32).collect();
            v.sort_unstable_by_key(|&k| {
                let i = &by_id[k as usize].info;
                (i.pixel[1], i.pixel[0], i.sample, i.id)
            });
            v
        };
        let ix = Arc::new(TreeIndex { by_id, by_pixel });
        let _ = self.index.set(ix.clone());
        Ok(ix)
    }

    /// Number of trees.
    pub fn tree_count(&self) -> u64 {
        self.manifest.stats.trees
    }

    /// Number of rays.
    pub fn ray_count(&self) -> u64 {
        self.manifest.stats.rays
    }

    /// Every tree's metadata and location, sorted by id (loads the index on first use).
    pub fn tree_entries(&self) -> Result<Vec<TreeEntry>> {
        Ok(self.index()?.by_id.clone())
    }

    /// The `n`-th tree in id order.
    pub fn tree_entry_at(&self, n: usize) -> Result<Option<TreeEntry>> {
        Ok(self.index()?.by_id.get(n).copied())
    }

    /// Position of a tree in id order.
    pub fn position_of(&self, id: TreeId) -> Result<Option<usize>> {
        Ok(self.index()?.by_id.binary_search_by_key(&id, |e| e.info.id).ok())
    }

    /// Metadata of one tree.
    pub fn tree_info(&self, id: TreeId) -> Result<TreeInfo> {
        Ok(self.entry_of(id)?.info)
    }

    /// One whole tree by id; reads only the pages that hold its rays.
    pub fn tree(&self, id: TreeId) -> Result<Tree> {
        self.load_tree(&self.entry_of(id)?)
    }

    /// Where tree `id` is: from the whole index when it is loaded, otherwise from the tree tables
    /// of only the segments whose id range holds `id` (each loaded once), so a first lookup on a
    /// large trace does not read every tree table.
    pub fn entry_of(&self, id: TreeId) -> Result<TreeEntry> {
        if let Some(ix) = self.index.get() {
            let pos = ix.by_id.binary_search_by_key(&id, |e| e.info.id).map_err(|_| Error::NoSuchTree(id.0))?;
            return Ok(ix.by_id[pos]);
        }
        for (i, seg) in self.manifest.segments.iter().enumerate() {
            if id.0 < seg.tree_id_min || id.0 > seg.tree_id_max {
                continue;
            }
            let entries = self.segment_tree_entries(i)?;
            if let Ok(pos) = entries.binary_search_by_key(&id, |e| e.info.id) {
                return Ok(entries[pos]);
            }
        }
        Err(Error::NoSuchTree(id.0))
    }

    /// The trees of segment `i`, sorted by id (its tree table, loaded once and kept).
    pub fn segment_tree_entries(&self, i: usize) -> Result<Arc<Vec<TreeEntry>>> {
        if let Some(e) = self.segment_trees.get(i).and_then(|c| c.get()) {
            return Ok(e.clone());
        }
        let e = Arc::new(self.read_tree_table(i)?);
        if let Some(cell) = self.segment_trees.get(i) {
            let _ = cell.set(e.clone());
        }
        Ok(e)
    }

    /// Every tree of a pixel (of one sample, or of all samples), ordered by sample then id.
    pub fn trees_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<Tree>> {
        self.tree_entries_at_pixel(x, y, sample)?.iter().map(|e| self.load_tree(e)).collect()
    }

    /// Where the trees of a pixel are (of one sample, or of all), ordered by sample then id;
    /// reads no rays.
    pub fn tree_entries_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<TreeEntry>> {
        let ix = self.index()?;
        let key = |k: &u32| {
            let i = &ix.by_id[*k as usize].info;
            (i.pixel[1], i.pixel[0])
        };
        let start = ix.by_pixel.partition_point(|k| key(k) < (y, x));
        let mut out = Vec::new();
        for k in &ix.by_pixel[start..] {
            if key(k) != (y, x) {
                break;
            }
            let e = &ix.by_id[*k as usize];
            if sample.is_none_or(|s| s == e.info.sample) {
                out.push(*e);
            }
        }
        Ok(out)
    }

    /// Loads the tree an index entry points at.
    pub fn load_tree(&self, e: &TreeEntry) -> Result<Tree> {
        let batch = self.read_rows(e.segment as usize, e.first_row, u64::from(e.info.ray_count))?;
        self.tree_from_rows(e.info, e.segment as usize, batch)
    }

    fn tree_from_rows(&self, info: TreeInfo, segment: usize, batch: RecordBatch) -> Result<Tree> {
        let path = self.dir.join(&self.segment(segment).rays.path);
        let rays = rays_from_batch(&batch, &self.kinds_by_name, &path)?;
        let ids = tree_ids_of(&batch, &path)?;
        validate_tree(&info, &ids, &rays).map_err(|message| Error::Corrupt {
            path,
            what: "ray file".into(),
            message,
        })?;
        Ok(Tree { info, rays, batch })
    }

    /// A reader of segment `i`'s ray file: the `roots` columns (all when None), only the row
    /// groups and pages of `rows` (sorted, disjoint; every row when None), in batches of
    /// `batch_size`. Returns the file's path with it, for errors.
    fn ray_reader(
        &self,
        i: usize,
        roots: Option<Vec<usize>>,
        rows: Option<&[std::ops::Range<u64>]>,
        batch_size: usize,
    ) -> Result<(PathBuf, parquet::arrow::arrow_reader::ParquetRecordBatchReader)> {
        let meta = self.segment_meta(i)?;
        let path = self.dir.join(&self.segment(i).rays.path);
        let file = File::open(&path).map_err(io_err("opening a ray file", &path))?;
        let mut builder =
            ParquetRecordBatchReaderBuilder::new_with_metadata(file, meta.meta.clone()).with_batch_size(batch_size);
        if let Some(roots) = roots {
            let schema = meta.meta.metadata().file_metadata().schema_descr();
            builder = builder.with_projection(parquet::arrow::ProjectionMask::roots(schema, roots));
        }
        if let Some(rows) = rows {
            let (groups, selection) = select_rows(&meta.row_group_starts, &meta.meta, rows);
            builder = builder.with_row_groups(groups).with_row_selection(selection);
        }
        let reader = builder.build().map_err(pq_err(&path))?;
        Ok((path, reader))
    }

    /// Reads `count` rows from `first` of segment `i`'s ray file, touching only the pages needed.
    pub fn read_rows(&self, i: usize, first: u64, count: u64) -> Result<RecordBatch> {
        if count == 0 {
            return Ok(RecordBatch::new_empty(self.schema.clone()));
        }
        let one = [std::ops::Range { start: first, end: first + count }];
        let roots = self.file_schema.fields().len();
        let path = self.dir.join(&self.segment(i).rays.path);
        // A few trees' rows cost one page of each column, mostly zstd decompression (and two
        // codec contexts per column, made anew by the parquet reader): two threads decode the
        // two halves of the columns at once where there is a second core.
        let split = roots >= 4 && count <= PARALLEL_READ_ROWS && cores() > 1;
        let batch = if split {
            let half = roots / 2;
            let second = || self.read_rows_of(i, Some((half..roots).collect()), &one, count);
            let (a, b) = std::thread::scope(|s| {
                let other = std::thread::Builder::new().name("rtvtk-fetch".into()).spawn_scoped(s, second);
                let a = self.read_rows_of(i, Some((0..half).collect()), &one, count);
                let b = match other {
                    Ok(h) => h.join().unwrap_or_else(|_| {
                        Err(Error::Corrupt {
                            path: path.clone(),
                            what: "ray file".into(),
                            message: "the thread decoding half of the columns panicked".into(),
                        })
                    }),
                    // No thread to be had: decode the other half here.
                    Err(_) => second(),
                };
                (a, b)
            });
            let (a, b) = (a?, b?);
            let columns = a.columns().iter().chain(b.columns()).cloned().collect();
            RecordBatch::try_new(self.file_schema.clone(), columns).map_err(arrow_err(path.display().to_string()))?
        } else {
            self.read_rows_of(i, None, &one, count)?
        };
        if batch.num_rows() as u64 != count {
            return Err(Error::Corrupt {
                path,
                what: "ray file".into(),
                message: format!("expected {count} rows from row {first}, read {}", batch.num_rows()),
            });
        }
        self.decoder(i)?.decode(batch, &path)
    }

    /// Rows `rows` of segment `i`'s ray file, the `roots` columns (all when None), undecoded,
    /// as one batch.
    fn read_rows_of(
        &self,
        i: usize,
        roots: Option<Vec<usize>>,
        rows: &[std::ops::Range<u64>],
        count: u64,
    ) -> Result<RecordBatch> {
        let (path, reader) = self.ray_reader(i, roots, Some(rows), count.max(1) as usize)?;
        let schema = arrow::record_batch::RecordBatchReader::schema(&reader);
        let mut batches = Vec::new();
        for b in reader {
            batches.push(b.map_err(|e| Error::Parquet { path: path.clone(), source: e.into() })?);
        }
        if batches.len() == 1 {
            Ok(batches.pop().unwrap_or_else(|| RecordBatch::new_empty(schema)))
        } else {
            concat_batches(&schema, &batches).map_err(arrow_err(path.display().to_string()))
        }
    }

    /// Every ray batch of segment `i`, in file order.
    pub fn segment_batches(&self, i: usize) -> Result<impl Iterator<Item = Result<RecordBatch>> + use<>> {
        self.segment_batches_in(i, None)
    }

    /// The ray batches of segment `i` holding the rows `rows` (sorted, disjoint ranges of whole
    /// trees; every row when None), in file order. Reads only the row groups and pages they touch.
    pub fn segment_batches_in(
        &self,
        i: usize,
        rows: Option<&[std::ops::Range<u64>]>,
    ) -> Result<impl Iterator<Item = Result<RecordBatch>> + use<>> {
        let (path, reader) = self.ray_reader(i, None, rows, 64 * 1024)?;
        let mut decoder = self.decoder(i)?;
        Ok(reader.map(move |b| {
            let b = b.map_err(|e| Error::Parquet { path: path.clone(), source: e.into() })?;
            decoder.decode(b, &path)
        }))
    }

    /// The columns `names` of the ray table (in that order) for every ray of segment `i`, in file
    /// order. Reads only the file columns they need: origins and directions are decoded only when
    /// asked for (decoding needs the tree structure columns too), and `kind` comes from the kind
    /// codes without touching the encoded columns.
    pub fn segment_columns(
        &self,
        i: usize,
        names: &[String],
    ) -> Result<Box<dyn Iterator<Item = Result<RecordBatch>> + Send>> {
        self.segment_columns_in(i, names, None)
    }

    /// [`Dataset::segment_columns`] of only the rows `rows` (sorted, disjoint ranges of whole
    /// trees, as the tree table gives them; every row when None): row groups and pages outside
    /// them are not read.
    pub fn segment_columns_in(
        &self,
        i: usize,
        names: &[String],
        rows: Option<&[std::ops::Range<u64>]>,
    ) -> Result<Box<dyn Iterator<Item = Result<RecordBatch>> + Send>> {
        let mut fields = Vec::with_capacity(names.len());
        for n in names {
            let f = self.schema.field_with_name(n).map_err(|_| Error::Schema {
                path: self.dir.join(&self.segment(i).rays.path),
                field: n.clone(),
                expected: "a column of the ray table".into(),
                found: "no such column".into(),
            })?;
            fields.push(f.clone());
        }
        let out_schema = Arc::new(arrow::datatypes::Schema::new(fields));
        let path = self.dir.join(&self.segment(i).rays.path);
        let project = {
            let path = path.clone();
            move |b: RecordBatch| -> Result<RecordBatch> {
                let cols = out_schema
                    .fields()
                    .iter()
                    .map(|f| {
                        b.column_by_name(f.name()).cloned().ok_or_else(|| Error::Corrupt {
                            path: path.clone(),
                            what: "ray file".into(),
                            message: format!("no column {} after reading", f.name()),
                        })
                    })
                    .collect::<Result<Vec<_>>>()?;
                let options = arrow::array::RecordBatchOptions::new().with_row_count(Some(b.num_rows()));
                RecordBatch::try_new_with_options(out_schema.clone(), cols, &options)
                    .map_err(arrow_err("projected ray batch"))
            }
        };
        let encoded = self.encoding() != Encoding::Plain;
        // From format version 3 `t` is encoded too, predicted from the decoded origin and direction.
        let t_encoded = self.file_schema.index_of(ENC_T).is_ok();
        let is_origin = |n: &str| n.starts_with("origin_") || (t_encoded && n == "t");
        let is_dir = |n: &str| n.starts_with("dir_");
        let want_origin = encoded && names.iter().any(|n| is_origin(n));
        let want_geometry = want_origin || (encoded && names.iter().any(|n| is_dir(n)));
        // The file columns: what is asked for as stored (kind from its codes in encoded files),
        // plus what decoding needs: the direction columns, and for origins the tree structure.
        let mut file_names: Vec<&str> = names
            .iter()
            .map(|n| n.as_str())
            .filter(|n| !encoded || !(is_origin(n) || is_dir(n)))
            .map(|n| if encoded && n == "kind" { crate::codec::KIND_CODE } else { n })
            .collect();
        if want_geometry {
            file_names.extend(&crate::codec::ENCODED_COLUMNS[3..]);
        }
        if want_origin {
            file_names.extend(&crate::codec::ENCODED_COLUMNS[..3]);
            file_names.extend(["tree_id", "ray", "parent"]);
            if t_encoded {
                file_names.extend([ENC_T, "prim"]);
            } else {
                file_names.push("t");
            }
        }
        let roots: BTreeSet<usize> = file_names.iter().filter_map(|n| self.file_schema.index_of(n).ok()).collect();
        let (path, reader) = self.ray_reader(i, Some(roots.into_iter().collect()), rows, 64 * 1024)?;
        let kinds = self.kinds.clone();
        let mut decoder = self.decoder(i)?;
        Ok(Box::new(reader.map(move |b| {
            let b = b.map_err(|e| Error::Parquet { path: path.clone(), source: e.into() })?;
            let mut fields: Vec<arrow::datatypes::FieldRef> = b.schema().fields().iter().cloned().collect();
            let mut cols = b.columns().to_vec();
            if want_geometry {
                let g = decoder.decode_geometry(&b, &path, want_origin)?;
                for (name, col) in g.columns() {
                    fields.push(Arc::new(arrow::datatypes::Field::new(
                        name,
                        arrow::datatypes::DataType::Float32,
                        true,
                    )));
                    cols.push(col);
                }
            }
            if let Ok(k) = b.schema().index_of(crate::codec::KIND_CODE) {
                // The kind codes as the kind column, under its name.
                cols[k] = crate::codec::kinds_of_codes(&cols[k], &kinds, &path)?;
                fields[k] = Arc::new(arrow::datatypes::Field::new("kind", crate::schema::kind_data_type(), false));
            }
            let options = arrow::array::RecordBatchOptions::new().with_row_count(Some(b.num_rows()));
            let b = RecordBatch::try_new_with_options(Arc::new(arrow::datatypes::Schema::new(fields)), cols, &options)
                .map_err(arrow_err("decoded columns"))?;
            project(b)
        })))
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
        let planes = if self.manifest.encoding == Encoding::Plain {
            Arc::default()
        } else {
            self.segment_meta(i)?.planes.clone()
        };
        Ok(Decoder::new(self.manifest.encoding, self.schema.clone(), self.kinds.clone()).with_planes(planes))
    }

    /// Every tree, segment by segment in file order: a sequential scan that reads each page once.
    pub fn trees(&self) -> TreeIter<'_> {
        TreeIter {
            ds: self,
            segment: 0,
            last_segment: self.manifest.segments.len(),
            preloaded: None,
            entries: Vec::new(),
            next_entry: 0,
            batches: None,
            pending: None,
            pending_start: 0,
            failed: false,
        }
    }

    /// Every tree of segment `i` in file order, given its tree table.
    pub(crate) fn trees_of_segment(&self, i: usize, entries: Vec<TreeEntry>) -> TreeIter<'_> {
        TreeIter {
            ds: self,
            segment: i,
            last_segment: i + 1,
            preloaded: Some(entries),
            entries: Vec::new(),
            next_entry: 0,
            batches: None,
            pending: None,
            pending_start: 0,
            failed: false,
        }
    }

    /// Every tree of segment `i` in file order: a sequential scan of that segment alone.
    pub fn segment_trees(&self, i: usize) -> Result<TreeIter<'_>> {
        let mut entries = self.read_tree_table(i)?;
        entries.sort_unstable_by_key(|e| e.first_row);
        Ok(self.trees_of_segment(i, entries))
    }

    pub(crate) fn segment_entries(&self, i: usize) -> Result<Vec<TreeEntry>> {
        self.read_tree_table(i)
    }

    pub(crate) fn segment_meta_checked(&self, i: usize) -> Result<()> {
        self.segment_meta(i).map(|_| ())
    }

    /// First row of each row group of segment `i`'s ray file.
    pub(crate) fn row_group_starts(&self, i: usize) -> Result<Vec<u64>> {
        Ok(self.segment_meta(i)?.row_group_starts.clone())
    }
}

/// Sequential iterator over every tree of a dataset.
pub struct TreeIter<'a> {
    ds: &'a Dataset,
    segment: usize,
    last_segment: usize,
    preloaded: Option<Vec<TreeEntry>>,
    entries: Vec<TreeEntry>,
    next_entry: usize,
    batches: Option<Box<dyn Iterator<Item = Result<RecordBatch>> + 'a>>,
    pending: Option<RecordBatch>,
    pending_start: u64,
    failed: bool,
}

impl TreeIter<'_> {
    fn next_tree(&mut self) -> std::result::Result<Option<Tree>, ScanError> {
        loop {
            if self.batches.is_none() {
                if self.segment >= self.last_segment {
                    return Ok(None);
                }
                let mut entries = match self.preloaded.take() {
                    Some(e) => e,
                    None => self.ds.read_tree_table(self.segment)?,
                };
                entries.sort_unstable_by_key(|e| e.first_row);
                self.entries = entries;
                self.next_entry = 0;
                self.batches = Some(Box::new(self.ds.segment_batches(self.segment)?));
                self.pending = None;
                self.pending_start = 0;
            }
            let Some(e) = self.entries.get(self.next_entry).copied() else {
                self.batches = None;
                self.segment += 1;
                continue;
            };
            if e.info.ray_count == 0 {
                self.next_entry += 1;
                let empty = RecordBatch::new_empty(self.ds.schema.clone());
                return Ok(Some(self.ds.tree_from_rows(e.info, self.segment, empty).map_err(TreeError)?));
            }
            let need_end = e.first_row + u64::from(e.info.ray_count);
            // Gather batches until the pending rows cover this tree.
            loop {
                let have_end = self.pending_start + self.pending.as_ref().map_or(0, |b| b.num_rows() as u64);
                if have_end >= need_end {
                    break;
                }
                let Some(next) = self.batches.as_mut().and_then(|b| b.next()) else {
                    let path = self.ds.dir.join(&self.ds.segment(self.segment).rays.path);
                    return Err(Error::Corrupt {
                        path,
                        what: "ray file".into(),
                        message: format!("tree {} needs rows up to {need_end}, file ends at {have_end}", e.info.id),
                    }
                    .into());
                };
                let next = next?;
                self.pending = Some(match self.pending.take() {
                    None => next,
                    Some(p) => {
                        // Keep only rows not yet consumed.
                        let skip = (e.first_row - self.pending_start) as usize;
                        let p = p.slice(skip, p.num_rows() - skip);
                        self.pending_start += skip as u64;
                        concat_batches(&self.ds.schema, &[p, next]).map_err(arrow_err("tree scan"))?
                    }
                });
            }
            let pending = self.pending.as_ref().ok_or_else(|| Error::Corrupt {
                path: self.ds.dir.clone(),
                what: "tree scan".into(),
                message: "no rows buffered".into(),
            })?;
            let off = (e.first_row - self.pending_start) as usize;
            let rows = pending.slice(off, e.info.ray_count as usize);
            self.next_entry += 1;
            // A malformed tree is reported, and the scan can go on with the next one.
            return Ok(Some(self.ds.tree_from_rows(e.info, self.segment, rows).map_err(TreeError)?));
        }
    }

    /// True after an error the scan cannot continue past.
    pub fn is_broken(&self) -> bool {
        self.failed
    }
}

/// Marks an error confined to one tree.
struct TreeError(Error);

enum ScanError {
    Tree(Error),
    Fatal(Error),
}

impl From<TreeError> for ScanError {
    fn from(e: TreeError) -> Self {
        ScanError::Tree(e.0)
    }
}

impl From<Error> for ScanError {
    fn from(e: Error) -> Self {
        ScanError::Fatal(e)
    }
}

impl Iterator for TreeIter<'_> {
    type Item = Result<Tree>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        match self.next_tree() {
            Ok(t) => t.map(Ok),
            Err(ScanError::Tree(e)) => Some(Err(e)),
            Err(ScanError::Fatal(e)) => {
                self.failed = true;
                Some(Err(e))
            }
        }
    }
}

/// Rows up to which [`Dataset::read_rows`] decodes two halves of the columns on two threads.
const PARALLEL_READ_ROWS: u64 = 64 * 1024;

/// Cores this process may use (asked once).
fn cores() -> usize {
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
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

/// Appends the tree entries of one tree-table batch (columns in `tree_schema` order).
fn push_tree_entries(b: &RecordBatch, segment: usize, out: &mut Vec<TreeEntry>) {
    let c = |j: usize| b.column(j);
    let (id, px, py, s) = (
        c(0).as_primitive::<UInt64Type>(),
        c(1).as_primitive::<UInt32Type>(),
        c(2).as_primitive::<UInt32Type>(),
        c(3).as_primitive::<UInt32Type>(),
    );
    let (n, d, first) =
        (c(4).as_primitive::<UInt32Type>(), c(5).as_primitive::<UInt16Type>(), c(7).as_primitive::<UInt64Type>());
    for r in 0..b.num_rows() {
        out.push(TreeEntry {
            info: TreeInfo {
                id: TreeId(id.value(r)),
                pixel: [px.value(r), py.value(r)],
                sample: s.value(r),
                ray_count: n.value(r),
                max_depth: d.value(r),
            },
            segment: segment as u32,
            first_row: first.value(r),
        });
    }
}

/// The rows (file-wide, sorted, merged) of the tree-table pages whose `tree_id` min/max overlaps
/// `ranges`; None when the file has no page index for the column.
fn tree_id_pages(meta: &ArrowReaderMetadata, ranges: &[(u64, u64)]) -> Option<Vec<std::ops::Range<u64>>> {
    use parquet::file::page_index::column_index::ColumnIndexMetaData;
    let md = meta.metadata();
    let (columns, offsets) = (md.column_index()?, md.offset_index()?);
    let mut rows: Vec<std::ops::Range<u64>> = Vec::new();
    let mut group_start = 0u64;
    for (g, rg) in md.row_groups().iter().enumerate() {
        let group_rows = rg.num_rows() as u64;
        let ColumnIndexMetaData::INT64(index) = columns.get(g)?.first()? else { return None };
        let pages = offsets.get(g)?.first()?.page_locations();
        for (p, loc) in pages.iter().enumerate() {
            let first = loc.first_row_index as u64;
            let end = pages.get(p + 1).map_or(group_rows, |n| n.first_row_index as u64);
            // Ids are stored as INT64 bit patterns of u64; below 2^63 the orders agree, above it
            // the page is kept (no pruning rather than a wrong one).
            let (lo, hi) = match (index.min_value(p), index.max_value(p)) {
                (Some(&lo), Some(&hi)) if lo >= 0 && hi >= lo => (lo as u64, hi as u64),
                _ => (0, u64::MAX),
            };
            if ranges.iter().any(|&(a, b)| a <= hi && lo <= b) {
                let r = group_start + first..group_start + end;
                match rows.last_mut() {
                    Some(last) if last.end == r.start => last.end = r.end,
                    _ => rows.push(r),
                }
            }
        }
        group_start += group_rows;
    }
    Some(rows)
}

/// The row groups that `rows` (sorted, disjoint ranges) touch and the selection of those rows
/// within them.
fn select_rows(
    starts: &[u64],
    meta: &ArrowReaderMetadata,
    rows: &[std::ops::Range<u64>],
) -> (Vec<usize>, RowSelection) {
    let mut groups = Vec::new();
    let mut selectors: Vec<RowSelector> = Vec::new();
    let mut next = 0usize;
    for (g, rg) in meta.metadata().row_groups().iter().enumerate() {
        let start = starts[g];
        let end = start + rg.num_rows() as u64;
        while next < rows.len() && rows[next].end <= start {
            next += 1;
        }
        let mut pos = start;
        let mut touched = false;
        let mut k = next;
        while k < rows.len() && rows[k].start < end {
            let (lo, hi) = (rows[k].start.max(start), rows[k].end.min(end));
            if lo < hi {
                if !touched {
                    groups.push(g);
                    touched = true;
                }
                if lo > pos {
                    selectors.push(RowSelector::skip((lo - pos) as usize));
                }
                selectors.push(RowSelector::select((hi - lo) as usize));
                pos = hi;
            }
            if rows[k].end > end {
                break;
            }
            k += 1;
        }
        if touched && pos < end {
            selectors.push(RowSelector::skip((end - pos) as usize));
        }
    }
    (groups, RowSelection::from(selectors))
}
