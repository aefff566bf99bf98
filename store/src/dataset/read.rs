//! Random access and projected reads of the ray files: one tree's rows (its pages only, two
//! threads decoding half the columns each), whole segments, and chosen columns (origins and
//! directions decoded only when asked for).

use super::*;
use crate::path_payload::{ENC_CHROMA, ENC_RADIANCE, ENC_THROUGHPUT};

impl Dataset {
    /// Loads the tree an index entry points at.
    pub fn load_tree(&self, e: &TreeEntry) -> Result<Tree> {
        let batch = self.read_rows(e.segment as usize, e.first_row, u64::from(e.info.ray_count))?;
        self.tree_from_rows(e.info, e.segment as usize, batch)
    }

    pub(super) fn tree_from_rows(&self, info: TreeInfo, segment: usize, batch: RecordBatch) -> Result<Tree> {
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
    pub(super) fn ray_reader(
        &self,
        i: usize,
        roots: Option<Vec<usize>>,
        rows: Option<&[std::ops::Range<u64>]>,
        batch_size: usize,
    ) -> Result<(PathBuf, Guarded)> {
        let meta = self.segment_meta(i)?;
        let path = self.dir.join(&self.segment(i).rays.path);
        let file = File::open(&path).map_err(io_err("opening a ray file", &path))?;
        let projection = roots.map(|roots| {
            let schema = meta.meta.metadata().file_metadata().schema_descr();
            parquet::arrow::ProjectionMask::roots(schema, roots)
        });
        let (mut groups, mut selection) = (None, None);
        if let Some(rows) = rows {
            let (g, s) = select_rows(&meta.row_group_starts, &meta.meta, rows);
            groups = Some(g);
            // Whole row groups need no selection (the viewer's loads read row group by row
            // group): arrow-rs then reads their pages straight through.
            if s.iter().any(|s| s.skip) {
                selection = Some(s);
            }
        }
        let reader = super::pooled::reader(file, &meta.meta, projection, groups, selection, batch_size);
        let reader = Guarded::new(reader.map_err(pq_err(&path))?, &path);
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
        // codec contexts per column, made anew by the parquet reader): this thread decodes the
        // first half of the columns while the fetch helper decodes the second.
        let split = roots >= 4 && count <= PARALLEL_READ_ROWS;
        let helper = if split { FetchHelper::take() } else { None };
        let batch = if let Some(helper) = helper {
            let half = self.segment_meta(i)?.split_root;
            let second = || self.read_rows_of(i, Some((half..roots).collect()), &one, count);
            let mut b = None;
            let a = helper.0.pool.in_place_scope(|s| {
                s.spawn(|_| b = Some(std::panic::catch_unwind(std::panic::AssertUnwindSafe(second))));
                self.read_rows_of(i, Some((0..half).collect()), &one, count)
            });
            drop(helper);
            let b = match b {
                Some(Ok(b)) => b,
                _ => Err(Error::Corrupt {
                    path: path.clone(),
                    what: "ray file".into(),
                    message: "the thread decoding half of the columns panicked".into(),
                }),
            };
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
    pub(super) fn read_rows_of(
        &self,
        i: usize,
        roots: Option<Vec<usize>>,
        rows: &[std::ops::Range<u64>],
        count: u64,
    ) -> Result<RecordBatch> {
        let (path, reader) = self.ray_reader(i, roots, Some(rows), count.max(1) as usize)?;
        let schema = reader.schema();
        let mut batches = Vec::new();
        for b in reader {
            batches.push(b?);
        }
        if batches.len() == 1 {
            Ok(batches.pop().unwrap_or_else(|| RecordBatch::new_empty(schema)))
        } else {
            concat_batches(&schema, &batches).map_err(arrow_err(path.display().to_string()))
        }
    }

    /// `reader`'s batches cut to end at tree ends where radiance is decoded (`wanted`) from a
    /// file that predicts it from whole trees; as they come otherwise.
    fn tree_aligned_if_needed(
        &self,
        reader: Guarded,
        path: &Path,
        wanted: bool,
    ) -> Box<dyn Iterator<Item = Result<RecordBatch>> + Send> {
        let tree = reader.schema().index_of(crate::schema::col::TREE_ID).ok();
        match tree {
            Some(tree) if wanted && crate::path_payload::predicted_in(&self.file_schema) => {
                Box::new(crate::path_payload::tree_aligned(reader, tree, path))
            }
            _ => Box::new(reader),
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
        let batches = self.tree_aligned_if_needed(reader, &path, true);
        Ok(batches.map(move |b| {
            let b = b?;
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
        self.segment_columns_in(i, names, None, READ_BATCH_ROWS)
    }

    /// [`Dataset::segment_columns`] of only the rows `rows` (sorted, disjoint ranges of whole
    /// trees, as the tree table gives them; every row when None), in batches of `batch_rows`
    /// ([`READ_BATCH_ROWS`] where nothing else is asked): row groups and pages outside them are
    /// not read.
    pub fn segment_columns_in(
        &self,
        i: usize,
        names: &[String],
        rows: Option<&[std::ops::Range<u64>]>,
        batch_rows: usize,
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
            file_names.extend([crate::schema::col::TREE_ID, crate::schema::col::RAY, crate::schema::col::PARENT]);
            if t_encoded {
                file_names.extend([ENC_T, "prim"]);
            } else {
                file_names.push("t");
            }
        }
        // The path payload: throughput predicted by colour, radiance from whole trees'
        // throughput and kinds.
        let predicted = crate::path_payload::predicted_in(&self.file_schema);
        let want_radiance = predicted && names.iter().any(|n| n == crate::path_payload::RADIANCE);
        let want_throughput =
            predicted && (want_radiance || names.iter().any(|n| n == crate::path_payload::THROUGHPUT));
        if want_throughput {
            file_names.extend(ENC_THROUGHPUT);
            file_names.push(ENC_CHROMA);
        }
        if want_radiance {
            file_names.extend(ENC_RADIANCE);
            file_names.extend([crate::schema::col::TREE_ID, crate::codec::KIND_CODE]);
        }
        let roots: BTreeSet<usize> = file_names.iter().filter_map(|n| self.file_schema.index_of(n).ok()).collect();
        let (path, reader) = self.ray_reader(i, Some(roots.into_iter().collect()), rows, batch_rows.max(1))?;
        let kinds = self.kinds.clone();
        let mut decoder = self.decoder(i)?;
        let batches = self.tree_aligned_if_needed(reader, &path, want_radiance);
        Ok(Box::new(batches.map(move |b| {
            let b = b?;
            let mut fields: Vec<arrow::datatypes::FieldRef> = b.schema().fields().iter().cloned().collect();
            let mut cols = b.columns().to_vec();
            // Decoded columns, under their ray-table names.
            let mut decoded: Vec<(&str, arrow::array::ArrayRef)> = Vec::new();
            if want_throughput {
                let throughput = decoder.decode_throughput(&b, &path)?;
                if want_radiance {
                    decoded.push((crate::path_payload::RADIANCE, decoder.decode_radiance(&b, &throughput, &path)?));
                }
                decoded.push((crate::path_payload::THROUGHPUT, throughput));
            }
            if want_geometry {
                decoded.extend(decoder.decode_geometry(&b, &path, want_origin)?.columns());
            }
            for (name, col) in decoded {
                fields.push(Arc::new(arrow::datatypes::Field::new(name, col.data_type().clone(), true)));
                cols.push(col);
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
}

/// Rows up to which [`Dataset::read_rows`] decodes two halves of the columns on two threads.
pub(super) const PARALLEL_READ_ROWS: u64 = 64 * 1024;

/// Rows per batch of [`Dataset::segment_columns`] (and of `segment_columns_in` where its caller
/// has no other need): the viewer's ray loads and `check`. SQL scans ask for 8K rows (`query`'s
/// scan: 42% less memory for a two-column scan), but with 8K rows the viewer's loads of 1M rays
/// took 13-19% longer.
pub const READ_BATCH_ROWS: usize = 64 * 1024;

/// The one long-lived thread that decodes the second half of a fetch's columns while the
/// fetching thread decodes the first. A thread made for each fetch (as before) cost its stack's
/// page faults, and its exit a TLB shootdown on every core: about a tenth of a fetch's time.
/// Taken by one fetch at a time; a fetch that finds it taken (or no second core) decodes all
/// columns itself rather than queue behind another's. A process forked from the one that
/// started it (Python's `multiprocessing`) has no such thread and decodes alone too, rather
/// than wait for a job no thread will run.
struct FetchHelper {
    pool: rayon_core::ThreadPool,
    busy: std::sync::atomic::AtomicBool,
    /// The process that started the thread.
    pid: u32,
}

/// The helper, held by one fetch until dropped.
struct HeldHelper(&'static FetchHelper);

impl Drop for HeldHelper {
    fn drop(&mut self) {
        self.0.busy.store(false, std::sync::atomic::Ordering::Release);
    }
}

impl FetchHelper {
    /// The helper if this process has a second core, the thread could be started (by this
    /// process, not one it was forked from) and no other fetch holds it.
    fn take() -> Option<HeldHelper> {
        static HELPER: std::sync::OnceLock<Option<FetchHelper>> = std::sync::OnceLock::new();
        let helper = HELPER
            .get_or_init(|| {
                if cores() < 2 {
                    return None;
                }
                let pool =
                    rayon_core::ThreadPoolBuilder::new().num_threads(1).thread_name(|_| "rtvtk-fetch".into()).build();
                pool.ok().map(|pool| FetchHelper { pool, busy: false.into(), pid: std::process::id() })
            })
            .as_ref()
            .filter(|h| h.pid == std::process::id())?;
        use std::sync::atomic::Ordering;
        helper.busy.compare_exchange(false, true, Ordering::Acquire, Ordering::Relaxed).ok()?;
        Some(HeldHelper(helper))
    }
}

/// Cores this process may use (asked once).
pub(crate) fn cores() -> usize {
    static CORES: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *CORES.get_or_init(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// The row groups that `rows` (sorted, disjoint ranges) touch and the selection of those rows
/// within them.
pub(super) fn select_rows(
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
