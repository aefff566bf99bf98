//! The tree index: every tree's pixel, sample, size and place, from the tree tables (loaded
//! whole when a caller asks for every tree, otherwise only the pages of the ids or pixels asked
//! for), and the lookups on it.

use super::*;

impl Dataset {
    /// A reader of segment `i`'s tree file (its schema checked), with its path.
    pub(super) fn tree_file(&self, i: usize) -> Result<(PathBuf, ParquetRecordBatchReaderBuilder<File>)> {
        self.tree_fault(i)?;
        let path = self.dir.join(&self.segment(i).trees.path);
        let file = File::open(&path).map_err(io_err("opening a tree file", &path))?;
        let builder = guard(&path, || ParquetRecordBatchReaderBuilder::try_new(file).map_err(pq_err(&path)))
            .map_err(|e| self.tree_error(i, e))?;
        check_schema(builder.schema(), &tree_schema(), &path).map_err(|e| self.tree_error(i, e))?;
        Ok((path, builder))
    }

    /// `e`, a failure to open segment `i`'s tree file (its footer or its columns), as the
    /// segment's tree table being unavailable, naming the segment.
    fn tree_error(&self, i: usize, e: Error) -> Error {
        let path = self.dir.join(&self.segment(i).trees.path);
        Error::TreeTable { segment: self.segment(i).id, path, message: crate::error::unreadable(e) }
    }

    /// Reads the tree table of segment `i`, sorted by id.
    pub(super) fn read_tree_table(&self, i: usize) -> Result<Vec<TreeEntry>> {
        let seg = self.segment(i);
        let (path, builder) = self.tree_file(i)?;
        let reader = Guarded::new(builder.with_batch_size(64 * 1024).build().map_err(pq_err(&path))?, &path);
        let mut out = Vec::with_capacity((seg.trees.rows as usize).min(1 << 22));
        for batch in reader {
            let b = batch.map_err(|e| self.tree_error(i, e))?;
            push_tree_entries(&b, i, &mut out, &path, None).map_err(|e| self.tree_error(i, e))?;
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

    /// The `tree_id` column of segment `i`'s tree table, in file order (sorted by id in a sound
    /// file), a batch at a time: memory is one batch and the column chunk being read.
    pub(crate) fn segment_tree_ids(&self, i: usize) -> Result<impl Iterator<Item = Result<Vec<u64>>> + use<>> {
        use crate::schema::col;
        let (path, builder) = self.tree_file(i)?;
        let at = builder.schema().index_of(col::TREE_ID).map_err(|_| Error::Corrupt {
            path: path.clone(),
            what: "tree file".into(),
            message: "no tree_id column".into(),
        })?;
        let mask = parquet::arrow::ProjectionMask::roots(builder.parquet_schema(), [at]);
        let reader = builder.with_projection(mask).with_batch_size(8 * 1024).build().map_err(pq_err(&path))?;
        Ok(Guarded::new(reader, &path).map(move |b| {
            let b = b?;
            Ok(crate::tree::primitive::<UInt64Type>(&b, col::TREE_ID, &path)?.values().to_vec())
        }))
    }

    /// The trees of segment `i` that `filter` keeps, sorted by id. Reads only the tree-table
    /// pages whose statistics (the file's page index: min/max of `tree_id`, `pixel_x`, `pixel_y`,
    /// `sample` per page) can hold a kept tree; the footer and page index are read once per
    /// segment and kept (about 50 bytes per column per page of 2048 trees: a few percent of the
    /// table decoded), so later lookups in the segment read one or two pages.
    pub fn segment_tree_entries_where(&self, i: usize, filter: &TreeFilter) -> Result<Vec<TreeEntry>> {
        self.tree_fault(i)?;
        let path = self.dir.join(&self.segment(i).trees.path);
        let file = File::open(&path).map_err(io_err("opening a tree file", &path))?;
        let meta = match self.tree_metas.get(i).and_then(|c| c.get()) {
            Some(m) => m.clone(),
            None => {
                let options = ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Optional);
                let meta = guard(&path, || ArrowReaderMetadata::load(&file, options).map_err(pq_err(&path)))
                    .map_err(|e| self.tree_error(i, e))?;
                check_schema(meta.schema(), &tree_schema(), &path).map_err(|e| self.tree_error(i, e))?;
                if let Some(cell) = self.tree_metas.get(i) {
                    let _ = cell.set(meta.clone());
                }
                meta
            }
        };
        let Some(rows) = filter_pages(&meta, filter) else {
            // No page index (not written by this store): the whole table.
            return Ok(self.segment_tree_entries(i)?.iter().filter(|e| filter.keeps(&e.info)).copied().collect());
        };
        let mut out = Vec::new();
        if rows.is_empty() {
            return Ok(out);
        }
        let (groups, selection) = select_rows(&row_group_starts(&meta), &meta, &rows);
        let reader = super::pooled::reader(file, &meta, None, Some(groups), Some(selection), 64 * 1024)
            .map_err(pq_err(&path))?;
        for batch in Guarded::new(reader, &path) {
            let b = batch.map_err(|e| self.tree_error(i, e))?;
            push_tree_entries(&b, i, &mut out, &path, Some(filter)).map_err(|e| self.tree_error(i, e))?;
        }
        out.sort_unstable_by_key(|e| e.info.id);
        Ok(out)
    }

    pub(super) fn index(&self) -> Result<Arc<TreeIndex>> {
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

    /// Where tree `id` is: from the whole index when it is loaded, otherwise from only the
    /// segments whose id range holds `id`, and in them only the tree-table page whose id
    /// statistics hold it, so a lookup on a large trace reads a page, not every tree table.
    pub fn entry_of(&self, id: TreeId) -> Result<TreeEntry> {
        if let Some(ix) = self.index.get() {
            let pos = ix.by_id.binary_search_by_key(&id, |e| e.info.id).map_err(|_| Error::NoSuchTree(id.0))?;
            return Ok(ix.by_id[pos]);
        }
        let filter = TreeFilter { tree_id: Some(vec![(id.0, id.0)]), ..Default::default() };
        for (i, seg) in self.manifest.segments.iter().enumerate() {
            if id.0 < seg.tree_id_min || id.0 > seg.tree_id_max {
                continue;
            }
            if let Some(e) = self.segment_tree_entries_where(i, &filter)?.first() {
                return Ok(*e);
            }
        }
        Err(Error::NoSuchTree(id.0))
    }

    /// The trees of segment `i`, sorted by id: its whole tree table, read on each call and not
    /// kept by the dataset (a scan holds it while it reads the segment), so memory does not grow
    /// with the trees a process has touched.
    pub fn segment_tree_entries(&self, i: usize) -> Result<Arc<Vec<TreeEntry>>> {
        Ok(Arc::new(self.read_tree_table(i)?))
    }

    /// Every tree of a pixel (of one sample, or of all samples), ordered by sample then id.
    pub fn trees_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<Tree>> {
        self.tree_entries_at_pixel(x, y, sample)?.iter().map(|e| self.load_tree(e)).collect()
    }

    /// The trees `filter` keeps, segment by segment (each sorted by id): segments whose id range
    /// or pixel bounds (manifest) rule the filter out are not opened, and in the others only the
    /// tree-table pages whose statistics can hold a kept tree are read.
    pub fn tree_entries_where(&self, filter: &TreeFilter) -> Result<Vec<TreeEntry>> {
        let overlaps = |r: &Option<Vec<(u64, u64)>>, lo: u64, hi: u64| {
            r.as_ref().is_none_or(|r| r.iter().any(|&(a, b)| a <= hi && lo <= b))
        };
        let mut out = Vec::new();
        for (i, seg) in self.manifest.segments.iter().enumerate() {
            let pb = &seg.stats.pixel_bounds;
            let pixels = pb.is_empty()
                || (overlaps(&filter.pixel_x, u64::from(pb.min[0]), u64::from(pb.max[0]))
                    && overlaps(&filter.pixel_y, u64::from(pb.min[1]), u64::from(pb.max[1])));
            if pixels && overlaps(&filter.tree_id, seg.tree_id_min, seg.tree_id_max) {
                out.extend(self.segment_tree_entries_where(i, filter)?);
            }
        }
        Ok(out)
    }

    /// Where the trees of a pixel are (of one sample, or of all), ordered by sample then id;
    /// reads no rays. With the whole index loaded it is a lookup in it; otherwise only the
    /// segments whose pixel bounds (manifest) hold the pixel are opened, and in them only the
    /// tree-table pages whose pixel and sample statistics can hold it, so the first lookup on a
    /// large trace reads a few pages instead of every tree table.
    pub fn tree_entries_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<TreeEntry>> {
        let Some(ix) = self.index.get() else {
            let one = |v: u32| Some(vec![(u64::from(v), u64::from(v))]);
            let filter =
                TreeFilter { pixel_x: one(x), pixel_y: one(y), sample: sample.and_then(one), ..Default::default() };
            let mut out = self.tree_entries_where(&filter)?;
            out.sort_unstable_by_key(|e| (e.info.sample, e.info.id));
            return Ok(out);
        };
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
}

/// Which trees a lookup wants: inclusive ranges of each tree-table column (`None`: any value).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TreeFilter {
    pub tree_id: Option<Vec<(u64, u64)>>,
    pub pixel_x: Option<Vec<(u64, u64)>>,
    pub pixel_y: Option<Vec<(u64, u64)>>,
    pub sample: Option<Vec<(u64, u64)>>,
}

impl TreeFilter {
    /// Whether a tree with this metadata is wanted.
    pub fn keeps(&self, i: &TreeInfo) -> bool {
        let inside = |r: &Option<Vec<(u64, u64)>>, v: u64| {
            r.as_ref().is_none_or(|r| r.iter().any(|&(lo, hi)| lo <= v && v <= hi))
        };
        inside(&self.tree_id, i.id.0)
            && inside(&self.pixel_x, u64::from(i.pixel[0]))
            && inside(&self.pixel_y, u64::from(i.pixel[1]))
            && inside(&self.sample, u64::from(i.sample))
    }

    /// The constrained columns and their ranges.
    fn columns(&self) -> impl Iterator<Item = (&'static str, &[(u64, u64)])> {
        use crate::schema::col;
        [
            (col::TREE_ID, &self.tree_id),
            (col::PIXEL_X, &self.pixel_x),
            (col::PIXEL_Y, &self.pixel_y),
            (col::SAMPLE, &self.sample),
        ]
        .into_iter()
        .filter_map(|(name, r)| r.as_deref().map(|r| (name, r)))
    }
}

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
pub(super) struct TreeIndex {
    pub(super) by_id: Vec<TreeEntry>,
    /// Positions in `by_id`, sorted by (pixel y, pixel x, sample, id).
    pub(super) by_pixel: Vec<u32>,
}

/// Appends the tree entries of one tree-table batch (those `filter` keeps, when given: a lookup
/// by id reads a page of 2048 trees to keep one), its columns found by name (a file whose table
/// lacks one, or holds it with another type, is corrupt: named in the error).
pub(super) fn push_tree_entries(
    b: &RecordBatch,
    segment: usize,
    out: &mut Vec<TreeEntry>,
    path: &Path,
    filter: Option<&TreeFilter>,
) -> Result<()> {
    use crate::schema::col;
    use crate::tree::primitive as get;
    let id = get::<UInt64Type>(b, col::TREE_ID, path)?;
    let (px, py) = (get::<UInt32Type>(b, col::PIXEL_X, path)?, get::<UInt32Type>(b, col::PIXEL_Y, path)?);
    let s = get::<UInt32Type>(b, col::SAMPLE, path)?;
    let n = get::<UInt32Type>(b, col::RAY_COUNT, path)?;
    let d = get::<UInt16Type>(b, col::MAX_DEPTH, path)?;
    let first = get::<UInt64Type>(b, col::FIRST_ROW, path)?;
    for r in 0..b.num_rows() {
        let info = TreeInfo {
            id: TreeId(id.value(r)),
            pixel: [px.value(r), py.value(r)],
            sample: s.value(r),
            ray_count: n.value(r),
            max_depth: d.value(r),
        };
        if filter.is_none_or(|f| f.keeps(&info)) {
            out.push(TreeEntry { info, segment: segment as u32, first_row: first.value(r) });
        }
    }
    Ok(())
}

/// The rows (file-wide, sorted, merged) of the tree-table pages that can hold a tree `filter`
/// keeps: for each constrained column, the pages whose min/max overlaps its ranges, intersected
/// over the columns (their pages need not line up). None when the file lacks a page index for a
/// constrained column.
pub(super) fn filter_pages(meta: &ArrowReaderMetadata, filter: &TreeFilter) -> Option<Vec<std::ops::Range<u64>>> {
    let total: u64 =
        meta.metadata().row_groups().iter().fold(0u64, |a, g| a.saturating_add(g.num_rows().max(0) as u64));
    let mut rows: Vec<std::ops::Range<u64>> = std::iter::once(0..total).collect();
    for (name, ranges) in filter.columns() {
        let kept = column_pages(meta, name, ranges)?;
        rows = intersect(&rows, &kept);
        if rows.is_empty() {
            break;
        }
    }
    Some(rows)
}

/// The intersection of two sorted lists of disjoint row ranges.
fn intersect(a: &[std::ops::Range<u64>], b: &[std::ops::Range<u64>]) -> Vec<std::ops::Range<u64>> {
    let (mut i, mut j, mut out) = (0, 0, Vec::new());
    while i < a.len() && j < b.len() {
        let (lo, hi) = (a[i].start.max(b[j].start), a[i].end.min(b[j].end));
        if lo < hi {
            out.push(lo..hi);
        }
        if a[i].end < b[j].end {
            i += 1;
        } else {
            j += 1;
        }
    }
    out
}

/// The rows of the pages of column `name` whose min/max overlaps `ranges` (sorted, merged).
fn column_pages(meta: &ArrowReaderMetadata, name: &str, ranges: &[(u64, u64)]) -> Option<Vec<std::ops::Range<u64>>> {
    use parquet::file::page_index::column_index::ColumnIndexMetaData;
    let md = meta.metadata();
    let (columns, offsets) = (md.column_index()?, md.offset_index()?);
    let c = md.file_metadata().schema_descr().columns().iter().position(|c| c.path().parts() == [name])?;
    let mut rows: Vec<std::ops::Range<u64>> = Vec::new();
    let mut group_start = 0u64;
    for (g, rg) in md.row_groups().iter().enumerate() {
        let group_rows = rg.num_rows() as u64;
        let pages = offsets.get(g)?.get(c)?.page_locations();
        // Unsigned values are stored as signed bit patterns: below 2^31 (2^63) the orders agree,
        // outside it the page is kept (no pruning rather than a wrong one).
        let bounds = |p: usize| -> (u64, u64) {
            let got = match columns.get(g).and_then(|c2| c2.get(c)) {
                Some(ColumnIndexMetaData::INT64(ix)) => match (ix.min_value(p), ix.max_value(p)) {
                    (Some(&lo), Some(&hi)) if lo >= 0 && hi >= lo => Some((lo as u64, hi as u64)),
                    _ => None,
                },
                Some(ColumnIndexMetaData::INT32(ix)) => match (ix.min_value(p), ix.max_value(p)) {
                    (Some(&lo), Some(&hi)) if lo >= 0 && hi >= lo => Some((lo as u64, hi as u64)),
                    _ => None,
                },
                _ => None,
            };
            got.unwrap_or((0, u64::MAX))
        };
        for (p, loc) in pages.iter().enumerate() {
            let first = loc.first_row_index as u64;
            let end = pages.get(p + 1).map_or(group_rows, |n| n.first_row_index as u64);
            let (lo, hi) = bounds(p);
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
