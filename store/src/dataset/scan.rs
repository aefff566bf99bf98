//! The sequential scan: every tree, segment by segment in file order, each page read once.

use super::*;

impl Dataset {
    /// Every tree, segment by segment in file order: a sequential scan that reads each page once.
    pub fn trees(&self) -> TreeIter<'_> {
        self.scan(0, self.manifest.segments.len(), None)
    }

    /// Every tree of segment `i` in file order, given its tree table.
    pub(crate) fn trees_of_segment(&self, i: usize, entries: Vec<TreeEntry>) -> TreeIter<'_> {
        self.scan(i, i + 1, Some(entries))
    }

    /// A scan of segments `first..last` (the first one's tree table given when known).
    fn scan(&self, first: usize, last: usize, preloaded: Option<Vec<TreeEntry>>) -> TreeIter<'_> {
        TreeIter {
            ds: self,
            segment: first,
            last_segment: last,
            preloaded,
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
        entries.sort_unstable_by_key(|e| (e.first_row, e.info.ray_count));
        Ok(self.trees_of_segment(i, entries))
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
    pub(super) fn next_tree(&mut self) -> std::result::Result<Option<Tree>, ScanError> {
        loop {
            if self.batches.is_none() {
                if self.segment >= self.last_segment {
                    return Ok(None);
                }
                let mut entries = match self.preloaded.take() {
                    Some(e) => e,
                    None => self.ds.read_tree_table(self.segment)?,
                };
                entries.sort_unstable_by_key(|e| (e.first_row, e.info.ray_count));
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
pub(super) struct TreeError(Error);

pub(super) enum ScanError {
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
