//! Immediate mode: trees recorded into memory, readable from other threads while recording
//! goes on (the viewer's ctrl-click tracing).

use std::collections::{HashMap, VecDeque};
use std::path::Path;
use std::sync::{Arc, RwLock};

use arrow::array::RecordBatch;
use store::{Kind, KindTable, PayloadSchema, RayRows, RowLayout, Stats, Tree, TreeId, TreeInfo, TreeRow};

use crate::sink::{Sink, Summary};
use crate::{Error, Result};

struct MemChunk {
    seq: u64,
    batch: RecordBatch,
    trees: Vec<TreeRow>,
    kinds: HashMap<String, Kind>,
    bytes: usize,
}

#[derive(Default)]
struct MemState {
    chunks: VecDeque<Arc<MemChunk>>,
    next_seq: u64,
    /// Tree id to (chunk sequence number, position in that chunk's trees).
    by_id: HashMap<u64, (u64, u32)>,
    /// Pixel to tree ids, in recording order.
    by_pixel: HashMap<(u32, u32), Vec<u64>>,
    bytes: usize,
    evicted_trees: u64,
    stats: Stats,
    error: Option<String>,
    tables: HashMap<String, RecordBatch>,
    attributes: HashMap<String, String>,
}

struct MemShared {
    payload: PayloadSchema,
    budget: usize,
    state: RwLock<MemState>,
}

/// The immediate-mode sink.
pub(crate) struct ImmediateSink {
    shared: Arc<MemShared>,
    layout: RowLayout,
}

/// A read handle on an immediate-mode recording; clone it into any thread.
#[derive(Clone)]
pub struct MemoryTrace {
    shared: Arc<MemShared>,
}

impl ImmediateSink {
    pub(crate) fn new(payload: PayloadSchema, budget: usize) -> (Self, MemoryTrace) {
        let layout = RowLayout::new(&payload);
        let shared = Arc::new(MemShared { payload, budget, state: RwLock::new(MemState::default()) });
        (Self { shared: shared.clone(), layout }, MemoryTrace { shared })
    }
}

impl Sink for ImmediateSink {
    fn write_table(&self, name: &str, batch: RecordBatch) -> Result<()> {
        let mut st = self.shared.state.write().unwrap_or_else(|p| p.into_inner());
        st.tables.insert(name.to_string(), batch);
        Ok(())
    }

    fn set_attributes(&self, attributes: Vec<(String, String)>) -> Result<()> {
        let mut st = self.shared.state.write().unwrap_or_else(|p| p.into_inner());
        st.attributes.extend(attributes);
        Ok(())
    }

    fn submit(&self, chunk: RayRows, kinds: &Arc<KindTable>) {
        let chunk = match chunk.into_columns(&self.layout) {
            Ok(c) => c,
            Err(e) => {
                let mut st = self.shared.state.write().unwrap_or_else(|p| p.into_inner());
                st.error.get_or_insert_with(|| e.to_string());
                return;
            }
        };
        let stats = Stats::of_columns(&chunk, kinds);
        let trees = chunk.trees.clone();
        let bytes = chunk.heap_bytes();
        let batch = match chunk.into_ray_batch(&self.shared.payload, kinds) {
            Ok(b) => b,
            Err(e) => {
                let mut st = self.shared.state.write().unwrap_or_else(|p| p.into_inner());
                st.error.get_or_insert_with(|| e.to_string());
                return;
            }
        };
        let mut st = self.shared.state.write().unwrap_or_else(|p| p.into_inner());
        let seq = st.next_seq;
        st.next_seq += 1;
        for (i, t) in trees.iter().enumerate() {
            st.by_id.insert(t.tree_id, (seq, i as u32));
            st.by_pixel.entry((t.pixel_x, t.pixel_y)).or_default().push(t.tree_id);
        }
        st.stats.merge(&stats);
        st.bytes += bytes;
        st.chunks.push_back(Arc::new(MemChunk { seq, batch, trees, kinds: kinds.by_name(), bytes }));
        // Evict the oldest trees to stay within the budget (always keep the newest chunk).
        while st.bytes > self.shared.budget && st.chunks.len() > 1 {
            let Some(old) = st.chunks.pop_front() else { break };
            st.bytes -= old.bytes;
            st.evicted_trees += old.trees.len() as u64;
            for t in &old.trees {
                st.by_id.remove(&t.tree_id);
                if let Some(v) = st.by_pixel.get_mut(&(t.pixel_x, t.pixel_y)) {
                    v.retain(|id| *id != t.tree_id);
                    if v.is_empty() {
                        st.by_pixel.remove(&(t.pixel_x, t.pixel_y));
                    }
                }
            }
        }
    }

    fn flush(&self, _kinds: &Arc<KindTable>) -> Result<()> {
        let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
        match &st.error {
            Some(e) => Err(Error::InvalidArgument(format!("immediate-mode recording failed: {e}"))),
            None => Ok(()),
        }
    }

    fn finish(&self, kinds: &Arc<KindTable>) -> Result<Summary> {
        self.flush(kinds)?;
        let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
        Ok(Summary {
            trees: st.stats.trees,
            rays: st.stats.rays,
            segments: 0,
            bytes: st.bytes as u64,
            evicted_trees: st.evicted_trees,
            peak_buffered_bytes: 0,
        })
    }
}

impl MemoryTrace {
    /// Number of trees held now.
    pub fn tree_count(&self) -> usize {
        self.shared.state.read().unwrap_or_else(|p| p.into_inner()).by_id.len()
    }

    /// Statistics of everything recorded so far (evicted trees included).
    pub fn stats(&self) -> Stats {
        self.shared.state.read().unwrap_or_else(|p| p.into_inner()).stats.clone()
    }

    /// An optional whole-recording table (`bvh_nodes`, `lights`, ...), if one was written.
    pub fn table(&self, name: &str) -> Option<RecordBatch> {
        self.shared.state.read().unwrap_or_else(|p| p.into_inner()).tables.get(name).cloned()
    }

    /// A recording attribute (scene, tracer, seed, ...).
    pub fn attribute(&self, key: &str) -> Option<String> {
        self.shared.state.read().unwrap_or_else(|p| p.into_inner()).attributes.get(key).cloned()
    }

    /// Trees evicted to stay within the memory budget.
    pub fn evicted_trees(&self) -> u64 {
        self.shared.state.read().unwrap_or_else(|p| p.into_inner()).evicted_trees
    }

    /// Ids of the trees held, in recording order.
    pub fn tree_ids(&self) -> Vec<TreeId> {
        let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
        st.chunks.iter().flat_map(|c| c.trees.iter().map(|t| TreeId(t.tree_id))).collect()
    }

    fn extract(chunk: &MemChunk, pos: usize) -> Result<Tree> {
        let t = chunk.trees[pos];
        let batch = chunk.batch.slice(t.first_row as usize, t.ray_count as usize);
        let rays = store::rays_from_batch(&batch, &chunk.kinds, Path::new("(immediate-mode memory)"))?;
        Ok(Tree {
            info: TreeInfo {
                id: TreeId(t.tree_id),
                pixel: [t.pixel_x, t.pixel_y],
                sample: t.sample,
                ray_count: t.ray_count,
                max_depth: t.max_depth,
            },
            rays,
            batch,
        })
    }

    fn find(st: &MemState, id: u64) -> Option<(Arc<MemChunk>, usize)> {
        let (seq, pos) = *st.by_id.get(&id)?;
        let front = st.chunks.front()?.seq;
        let chunk = st.chunks.get((seq - front) as usize)?.clone();
        Some((chunk, pos as usize))
    }

    /// One tree by id, if it is held.
    pub fn tree(&self, id: TreeId) -> Result<Option<Tree>> {
        let found = {
            let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
            Self::find(&st, id.0)
        };
        found.map(|(c, p)| Self::extract(&c, p)).transpose()
    }

    /// The `n`-th tree held, in recording order.
    pub fn tree_at(&self, n: usize) -> Result<Option<Tree>> {
        let found = {
            let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
            let mut n = n;
            let mut hit = None;
            for c in &st.chunks {
                if n < c.trees.len() {
                    hit = Some((c.clone(), n));
                    break;
                }
                n -= c.trees.len();
            }
            hit
        };
        found.map(|(c, p)| Self::extract(&c, p)).transpose()
    }

    /// The payload columns the recording declared.
    pub fn payload_schema(&self) -> &PayloadSchema {
        &self.shared.payload
    }

    /// The rays held now, one batch per recorded chunk, as SQL's `rays` table shows them
    /// (`store::ray_table_schema`: with each ray's tree's pixel and sample): what SQL over an
    /// immediate-mode recording reads at each query.
    pub fn ray_batches(&self) -> store::Result<Vec<RecordBatch>> {
        let chunks: Vec<Arc<MemChunk>> =
            self.shared.state.read().unwrap_or_else(|p| p.into_inner()).chunks.iter().cloned().collect();
        let mut out = Vec::with_capacity(chunks.len());
        for c in chunks {
            let n = c.batch.num_rows();
            let mut cols: [Vec<u32>; 3] = [vec![0; n], vec![0; n], vec![0; n]];
            for t in &c.trees {
                let rows = t.first_row as usize..(t.first_row as usize + t.ray_count as usize).min(n);
                cols[0][rows.clone()].fill(t.pixel_x);
                cols[1][rows.clone()].fill(t.pixel_y);
                cols[2][rows].fill(t.sample);
            }
            let schema = store::ray_table_schema(&c.batch.schema());
            let mut arrays = c.batch.columns().to_vec();
            arrays.extend(cols.map(|v| Arc::new(arrow::array::UInt32Array::from(v)) as arrow::array::ArrayRef));
            let b = RecordBatch::try_new(schema, arrays).map_err(|e| store::Error::Arrow {
                context: "the rays of an immediate-mode recording".into(),
                source: e,
            })?;
            out.push(b);
        }
        Ok(out)
    }

    /// The trees held now, in the `trees` table's schema (`store::tree_schema`; `segment` is
    /// the chunk's number and `first_row` the tree's first row in it).
    pub fn tree_batches(&self) -> store::Result<Vec<RecordBatch>> {
        let chunks: Vec<Arc<MemChunk>> =
            self.shared.state.read().unwrap_or_else(|p| p.into_inner()).chunks.iter().cloned().collect();
        let mut out = Vec::with_capacity(chunks.len());
        for c in chunks {
            let segment = u32::try_from(c.seq).unwrap_or(u32::MAX);
            for b in store::RayColumns::merged_tree_batches(std::slice::from_ref(&c.trees), segment, c.trees.len()) {
                out.push(b?);
            }
        }
        Ok(out)
    }

    /// The names of the whole-recording tables written so far (`triangles`, `lights`, ...).
    pub fn table_names(&self) -> Vec<String> {
        let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
        let mut names: Vec<String> = st.tables.keys().cloned().collect();
        names.sort();
        names
    }

    /// Every recording attribute, sorted by key.
    pub fn attributes(&self) -> Vec<(String, String)> {
        let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
        let mut a: Vec<(String, String)> = st.attributes.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        a.sort();
        a
    }

    /// The trees of a pixel (one sample or all), in recording order.
    pub fn trees_at_pixel(&self, x: u32, y: u32, sample: Option<u32>) -> Result<Vec<Tree>> {
        let found: Vec<_> = {
            let st = self.shared.state.read().unwrap_or_else(|p| p.into_inner());
            st.by_pixel
                .get(&(x, y))
                .map(|ids| ids.iter().filter_map(|id| Self::find(&st, *id)).collect())
                .unwrap_or_default()
        };
        let mut out = Vec::new();
        for (c, p) in found {
            if sample.is_none_or(|s| c.trees[p].sample == s) {
                out.push(Self::extract(&c, p)?);
            }
        }
        Ok(out)
    }
}
