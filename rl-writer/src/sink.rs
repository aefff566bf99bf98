//! What the recorder and its sinks share: the options, the summary, and the sink interface
//! (a leaf: it imports neither the recorder nor a sink). `Sink` is crate-private: the modes are
//! chosen by constructor (`Recorder::create`, `Recorder::immediate`), not by handing the
//! recorder a sink of one's own.

use std::sync::Arc;
use std::time::Duration;

use store::{KindTable, PayloadSchema, RayRows, WriteOptions};

use crate::Result;

/// How a recorder records.
#[derive(Clone, Debug)]
pub struct RecorderOptions {
    /// Typed payload columns and the optional bytes column.
    pub payload: PayloadSchema,
    /// Kinds registered by name up front (more may be registered while recording).
    pub kinds: Vec<String>,
    /// Bytes of sealed rays that may wait for the workers before `end_tree` blocks.
    pub memory_budget: usize,
    /// Rays gathered from the tracing threads before a chunk goes to a worker.
    pub chunk_rays: usize,
    /// Rays per segment file before it is sealed.
    pub segment_rays: u64,
    /// A segment holding rays is sealed at least this often, bounding what a crash can lose.
    pub seal_interval: Duration,
    /// Background threads that encode and write segments.
    pub workers: usize,
    /// Parquet settings of the segments.
    pub write: WriteOptions,
    /// Record where in the renderer's source each ray was added (its site): a `site` payload
    /// column and the `sites` table (see `Recorder`'s text).
    pub sites: bool,
}

impl Default for RecorderOptions {
    fn default() -> Self {
        Self {
            payload: PayloadSchema::default(),
            kinds: Vec::new(),
            memory_budget: 256 << 20,
            chunk_rays: 16 * 1024,
            segment_rays: 4 << 20,
            seal_interval: Duration::from_secs(2),
            workers: 1,
            write: WriteOptions::default(),
            sites: false,
        }
    }
}

/// What a sink did, reported by `finish`.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Summary {
    pub trees: u64,
    pub rays: u64,
    /// Segments sealed (write mode).
    pub segments: u64,
    /// Bytes of the sealed segment files (write mode).
    pub bytes: u64,
    /// Trees evicted from memory to stay under the budget (immediate mode).
    pub evicted_trees: u64,
    /// The most bytes of sealed rays waiting for the workers at once (write mode).
    pub peak_buffered_bytes: u64,
}

/// Where sealed chunks of whole trees go: the one interface behind write and immediate mode.
pub(crate) trait Sink: Send + Sync {
    /// Takes a chunk of whole trees (as the tracing threads recorded them: rows); may block to
    /// stay within the memory budget.
    fn submit(&self, chunk: RayRows, kinds: &Arc<KindTable>);
    /// Makes every submitted tree durable (write mode) or visible (immediate mode).
    fn flush(&self, kinds: &Arc<KindTable>) -> Result<()>;
    /// Flushes, stops background work and reports what was recorded.
    fn finish(&self, kinds: &Arc<KindTable>) -> Result<Summary>;
    /// Stores an optional whole-recording table (`bvh_nodes`, `lights`, ...).
    fn write_table(&self, name: &str, batch: arrow::array::RecordBatch) -> Result<()>;
    /// Records free-form facts about the recording (scene, tracer, seed, ...).
    fn set_attributes(&self, attributes: Vec<(String, String)>) -> Result<()>;
    /// An emptied chunk buffer handed back by the sink once it was done with it, for the next
    /// chunk (so that the tracing threads refill memory already faulted in instead of fresh pages).
    fn spare(&self) -> Option<RayRows> {
        None
    }
}
