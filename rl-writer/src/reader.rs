//! Read mode: a cursor over the trees of a dataset (or of an immediate-mode recording), in the
//! spirit of the paper's `rlReadTree` / `rlReadRay`: the current tree, the current ray (read and
//! advance), seeking among and within trees, and statistics.

use std::path::Path;

use store::{Dataset, Ray, Stats, Tree, TreeId};

use crate::immediate::MemoryTrace;
use crate::{Error, Result};

/// Something trees can be read from by position and id.
pub trait TreeSource: Send + Sync {
    fn tree_count(&self) -> Result<usize>;
    /// The `n`-th tree (datasets: id order; immediate mode: recording order).
    fn tree_at(&self, n: usize) -> Result<Option<Tree>>;
    /// Position of a tree.
    fn position_of(&self, id: TreeId) -> Result<Option<usize>>;
    fn trees_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<Tree>>;
    fn stats(&self) -> Stats;
}

impl TreeSource for Dataset {
    fn tree_count(&self) -> Result<usize> {
        Ok(Dataset::tree_count(self) as usize)
    }

    fn tree_at(&self, n: usize) -> Result<Option<Tree>> {
        match self.tree_entry_at(n)? {
            Some(e) => Ok(Some(self.load_tree(&e)?)),
            None => Ok(None),
        }
    }

    fn position_of(&self, id: TreeId) -> Result<Option<usize>> {
        Ok(Dataset::position_of(self, id)?)
    }

    fn trees_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<Tree>> {
        Ok(Dataset::trees_at_pixel(self, x, y, sample)?)
    }

    fn stats(&self) -> Stats {
        Dataset::stats(self).clone()
    }
}

impl TreeSource for MemoryTrace {
    fn tree_count(&self) -> Result<usize> {
        Ok(MemoryTrace::tree_count(self))
    }

    fn tree_at(&self, n: usize) -> Result<Option<Tree>> {
        MemoryTrace::tree_at(self, n)
    }

    fn position_of(&self, id: TreeId) -> Result<Option<usize>> {
        Ok(self.tree_ids().iter().position(|t| *t == id))
    }

    fn trees_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<Tree>> {
        MemoryTrace::trees_at_pixel(self, x, y, sample)
    }

    fn stats(&self) -> Stats {
        MemoryTrace::stats(self)
    }
}

/// A read-mode cursor.
pub struct Reader {
    source: Box<dyn TreeSource>,
    tree_pos: usize,
    current: Option<Tree>,
    ray_pos: usize,
}

impl Reader {
    /// Opens a dataset directory for reading.
    pub fn open(dir: impl AsRef<Path>) -> Result<Reader> {
        Ok(Self::new(Box::new(Dataset::open(dir)?)))
    }

    /// A cursor over any trace source.
    pub fn new(source: Box<dyn TreeSource>) -> Reader {
        Reader { source, tree_pos: 0, current: None, ray_pos: 0 }
    }

    pub fn source(&self) -> &dyn TreeSource {
        self.source.as_ref()
    }

    /// Position of the current tree.
    pub fn position(&self) -> usize {
        self.tree_pos
    }

    /// The current tree, `None` past the last one.
    pub fn read_tree(&mut self) -> Result<Option<&Tree>> {
        if self.current.is_none() {
            self.current = self.source.tree_at(self.tree_pos)?;
        }
        Ok(self.current.as_ref())
    }

    /// The current ray of the current tree, advancing to the next ray; `None` after the last.
    pub fn read_ray(&mut self) -> Result<Option<Ray>> {
        let pos = self.ray_pos;
        let ray = self.read_tree()?.and_then(|t| t.rays.get(pos).copied());
        if ray.is_some() {
            self.ray_pos += 1;
        }
        Ok(ray)
    }

    /// Moves to the next tree; false past the last.
    pub fn next_tree(&mut self) -> Result<bool> {
        self.seek_tree(self.tree_pos + 1)
    }

    /// Moves to the tree at position `n`; false (cursor past the end) if there is none.
    pub fn seek_tree(&mut self, n: usize) -> Result<bool> {
        self.tree_pos = n;
        self.current = None;
        self.ray_pos = 0;
        Ok(self.read_tree()?.is_some())
    }

    /// Moves to the tree with id `id`.
    pub fn seek_tree_id(&mut self, id: TreeId) -> Result<()> {
        let pos = self.source.position_of(id)?.ok_or(Error::Store(store::Error::NoSuchTree(id.0)))?;
        self.seek_tree(pos)?;
        Ok(())
    }

    /// Moves within the current tree to ray `index` (the next `read_ray` returns it).
    pub fn seek_ray(&mut self, index: usize) {
        self.ray_pos = index;
    }

    /// Back to the first ray of the first tree.
    pub fn reset(&mut self) -> Result<()> {
        self.seek_tree(0).map(|_| ())
    }

    pub fn stats(&self) -> Stats {
        self.source.stats()
    }
}
