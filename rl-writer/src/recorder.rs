//! The recorder: trees are built by the tracing threads, sealed into shared chunks, and handed
//! to a sink (write mode: background workers writing segments; immediate mode: memory).

use std::cell::Cell;
use std::path::Path;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use store::{KindTable, PayloadMismatch, PayloadSchema, RayFields, RayRows, RowLayout, TreeId, TreeRow, Value};

use crate::immediate::{ImmediateSink, MemoryTrace};
use crate::sink::Sink;
pub use crate::sink::{RecorderOptions, Summary};
use crate::write::WriteSink;
use crate::{Error, Result};

/// Index of a ray within its tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct RayId(pub u32);

/// The payload handed with one ray: typed values (in declared column order) and opaque bytes.
#[derive(Clone, Copy, Debug, Default)]
pub struct Payload<'a> {
    pub values: &'a [Value<'a>],
    pub bytes: Option<&'a [u8]>,
}

impl<'a> Payload<'a> {
    /// No payload.
    pub const NONE: Payload<'static> = Payload { values: &[], bytes: None };

    /// Typed values only.
    pub fn values(values: &'a [Value<'a>]) -> Self {
        Self { values, bytes: None }
    }

    /// Opaque bytes only.
    pub fn bytes(bytes: &'a [u8]) -> Self {
        Self { values: &[], bytes: Some(bytes) }
    }
}

#[derive(Default)]
struct Mistakes {
    count: u64,
    first: Vec<String>,
}

/// Where ended trees gather before they go to the sink: one per tracing thread (by a thread-local
/// index), so its lock is normally taken by that thread alone. It also pools the buffers of ended
/// trees for `begin_tree` and counts the trees begun minus those ended on this shard.
struct Shard {
    cols: RayRows,
    pool: Vec<RayRows>,
    open: i64,
}

/// A value alone on its cache lines: the tree-id counter every `begin_tree` bumps would otherwise
/// evict the read-mostly fields the tracing threads read for every ray from the other cores.
#[repr(align(128))]
struct Padded<T>(T);

pub(crate) struct Inner {
    payload: PayloadSchema,
    layout: RowLayout,
    kinds: RwLock<Arc<KindTable>>,
    next_tree: Padded<AtomicU64>,
    shards: Vec<Padded<Mutex<Shard>>>,
    chunk_rays: usize,
    sink: Box<dyn Sink>,
    mistakes: Mutex<Mistakes>,
    mode: Mode,
    /// With `RecorderOptions::sites`: the sites seen, and the `site` column's slot.
    sites: Option<Sites>,
}

/// The recording sites seen so far, interned: a caller's `Location` (Rust) by its address, a
/// site given as text (C, Python) by its value.
struct Sites {
    /// This table's number in the process (never 0, never reused), for the per-thread cache.
    serial: u64,
    slot: usize,
    by_location: RwLock<std::collections::HashMap<usize, u32>>,
    by_site: Mutex<std::collections::HashMap<store::scene::Site, u32>>,
    all: Mutex<Vec<store::scene::Site>>,
    /// Sites written to the `sites` table so far (it is written again when more appear).
    written: AtomicUsize,
}

impl Sites {
    fn id_of(&self, site: store::scene::Site) -> u32 {
        let mut by = self.by_site.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(id) = by.get(&site) {
            return *id;
        }
        let mut all = self.all.lock().unwrap_or_else(|p| p.into_inner());
        let id = all.len() as u32;
        all.push(site.clone());
        by.insert(site, id);
        id
    }

    fn id_of_location(&self, loc: &'static std::panic::Location<'static>) -> u32 {
        thread_local! {
            /// The last (sites table, location, id) this thread looked up: a tracer adds runs of
            /// rays from one place, so most rays take no lock.
            static LAST: Cell<(u64, usize, u32)> = const { Cell::new((0, 0, 0)) };
        }
        let key = loc as *const _ as usize;
        let me = self.serial;
        let (t, l, id) = LAST.with(Cell::get);
        if t == me && l == key {
            return id;
        }
        let found = self.by_location.read().unwrap_or_else(|p| p.into_inner()).get(&key).copied();
        if let Some(id) = found {
            LAST.with(|c| c.set((me, key, id)));
            return id;
        }
        let id = self.id_of(store::scene::Site {
            file: loc.file().to_string(),
            line: loc.line(),
            column: loc.column(),
            function: None,
        });
        self.by_location.write().unwrap_or_else(|p| p.into_inner()).insert(key, id);
        LAST.with(|c| c.set((me, key, id)));
        id
    }
}

/// Where a ray was added, for the `site` column.
#[derive(Clone, Copy, Debug)]
pub enum SiteRef<'a> {
    /// A place in Rust source (`#[track_caller]`'s `Location::caller()`).
    Location(&'static std::panic::Location<'static>),
    /// A place named by the caller (C's `__FILE__`/`__LINE__`, a Python frame).
    Named { file: &'a str, line: u32, function: Option<&'a str> },
}

impl Inner {
    fn mistake(&self, msg: String) {
        let mut m = self.mistakes.lock().unwrap_or_else(|p| p.into_inner());
        m.count += 1;
        if m.first.len() < 8 {
            m.first.push(msg);
        }
    }

    fn kinds(&self) -> Arc<KindTable> {
        self.kinds.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    fn shard(&self) -> std::sync::MutexGuard<'_, Shard> {
        let i = SHARD.with(|s| s.get()) % self.shards.len();
        self.shards[i].0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands an ended tree to its thread's shard (or straight to the sink when it is big, and in
    /// immediate mode); a full shard goes to the sink as one chunk. The tree's buffers are pooled.
    fn seal(&self, cols: RayRows) {
        let inner = self;
        if cols.len() >= inner.chunk_rays {
            // Big trees (and immediate mode) go straight to the sink.
            inner.shard().open -= 1;
            inner.sink.submit(cols, &inner.kinds());
            return;
        }
        let full = {
            let mut s = inner.shard();
            s.open -= 1;
            s.cols.append(&cols);
            let full = if s.cols.len() >= inner.chunk_rays {
                let next = inner.sink.spare().unwrap_or_else(|| {
                    let cap = inner.chunk_rays + inner.chunk_rays / 8;
                    RayRows::with_capacity(&inner.payload, &inner.layout, cap)
                });
                Some(std::mem::replace(&mut s.cols, next))
            } else {
                None
            };
            if s.pool.len() < 32 {
                let mut cols = cols;
                cols.clear();
                s.pool.push(cols);
            }
            full
        };
        if let Some(chunk) = full {
            inner.sink.submit(chunk, &inner.kinds());
        }
    }
}

/// Where a recorder's trees go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Into a dataset directory, by background workers (`Recorder::create`).
    Write,
    /// Into memory, readable while recording (`Recorder::immediate`).
    Immediate,
}

impl Mode {
    pub fn name(self) -> &'static str {
        match self {
            Mode::Write => "write",
            Mode::Immediate => "immediate",
        }
    }
}

/// Records ray trees from any number of threads. Cheap to clone (shared handle).
#[derive(Clone)]
pub struct Recorder {
    inner: Arc<Inner>,
}

static NEXT_SHARD: AtomicUsize = AtomicUsize::new(0);
/// Numbers the recorders' site tables (from 1).
static SITE_TABLES: AtomicU64 = AtomicU64::new(1);
thread_local! {
    static SHARD: Cell<usize> = Cell::new(NEXT_SHARD.fetch_add(1, Ordering::Relaxed));
}

impl Recorder {
    /// Write mode: records into a new dataset directory `dir` (which must not exist or be empty).
    pub fn create(dir: impl AsRef<Path>, options: RecorderOptions) -> Result<Recorder> {
        let options = with_site_column(options)?;
        let kinds = registry(&options.kinds)?;
        let sink = WriteSink::start(dir.as_ref(), &options)?;
        Ok(Self::with_sink(Box::new(sink), options, kinds, Mode::Write))
    }

    /// Immediate mode: records into memory; the returned [`MemoryTrace`] reads it from any thread
    /// while recording goes on. Trees become visible as soon as they end. When the memory budget
    /// is exceeded, the oldest trees are evicted.
    pub fn immediate(options: RecorderOptions) -> Result<(Recorder, MemoryTrace)> {
        let mut options = with_site_column(options)?;
        let kinds = registry(&options.kinds)?;
        let (sink, trace) = ImmediateSink::new(options.payload.clone(), options.memory_budget);
        options.chunk_rays = 0;
        Ok((Self::with_sink(Box::new(sink), options, kinds, Mode::Immediate), trace))
    }

    /// A recorder over any sink.
    fn with_sink(sink: Box<dyn Sink>, options: RecorderOptions, kinds: KindTable, mode: Mode) -> Recorder {
        let shards = (0..8)
            .map(|_| Padded(Mutex::new(Shard { cols: RayRows::new(&options.payload), pool: Vec::new(), open: 0 })))
            .collect();
        let site_slot = options.payload.fields.len().saturating_sub(1);
        Recorder {
            inner: Arc::new(Inner {
                layout: RowLayout::new(&options.payload),
                payload: options.payload,
                kinds: RwLock::new(Arc::new(kinds)),
                next_tree: Padded(AtomicU64::new(0)),
                shards,
                chunk_rays: options.chunk_rays,
                sink,
                mistakes: Mutex::new(Mistakes::default()),
                mode,
                sites: options.sites.then(|| Sites {
                    serial: SITE_TABLES.fetch_add(1, Ordering::Relaxed),
                    slot: site_slot,
                    by_location: RwLock::default(),
                    by_site: Mutex::default(),
                    all: Mutex::default(),
                    written: AtomicUsize::new(0),
                }),
            }),
        }
    }

    /// Where this recorder's trees go.
    pub fn mode(&self) -> Mode {
        self.inner.mode
    }

    pub fn payload_schema(&self) -> &PayloadSchema {
        &self.inner.payload
    }

    /// Stores an optional whole-recording table, e.g. the BVH's nodes (`bvh_nodes`).
    pub fn write_table(&self, name: &str, batch: arrow::array::RecordBatch) -> Result<()> {
        // A table the store knows (`triangles`, `lights`, ...) must match its schema: refused here,
        // at once, rather than when the background write reaches it.
        store::scene::check_table(name, &batch.schema())
            .map_err(|m| crate::Error::InvalidArgument(format!("table `{name}`: {m}")))?;
        self.inner.sink.write_table(name, batch)
    }

    /// Records free-form facts about the recording (scene, tracer, seed, image size, ...).
    pub fn set_attributes<K: Into<String>, V: Into<String>>(
        &self,
        attributes: impl IntoIterator<Item = (K, V)>,
    ) -> Result<()> {
        self.inner.sink.set_attributes(attributes.into_iter().map(|(k, v)| (k.into(), v.into())).collect())
    }

    /// Registers a ray kind by name (or returns the kind already registered under it).
    pub fn register_kind(&self, name: &str) -> Result<store::Kind> {
        let mut k = self.inner.kinds.write().unwrap_or_else(|p| p.into_inner());
        if let Some(kind) = k.lookup(name) {
            return Ok(kind);
        }
        let mut next = (**k).clone();
        let kind = next.register(name)?;
        *k = Arc::new(next);
        Ok(kind)
    }

    /// Starts a tree for `(x, y)` and sample `sample`. Any number may be open at once, on any threads.
    pub fn begin_tree(&self, x: u32, y: u32, sample: u32) -> TreeBuilder {
        let id = self.inner.next_tree.0.fetch_add(1, Ordering::Relaxed);
        let pooled = {
            let mut s = self.inner.shard();
            s.open += 1;
            s.pool.pop()
        };
        let cols = pooled.unwrap_or_else(|| RayRows::new(&self.inner.payload));
        TreeBuilder {
            rec: self.inner.clone(),
            id,
            pixel: [x, y],
            sample,
            cols,
            stack: Vec::new(),
            last: None,
            max_depth: 0,
            mismatches: Vec::new(),
        }
    }

    /// Hands every ended tree to the sink and waits until they are sealed (write mode: durable
    /// on disk and listed in the manifest; immediate mode: visible).
    pub fn flush(&self) -> Result<()> {
        self.drain_shards();
        self.write_sites()?;
        self.inner.sink.flush(&self.inner.kinds())
    }

    /// Whether rays carry their recording site (`RecorderOptions::sites`).
    pub fn records_sites(&self) -> bool {
        self.inner.sites.is_some()
    }

    /// Writes the `sites` table when sites appeared since it was last written.
    fn write_sites(&self) -> Result<()> {
        let Some(sites) = &self.inner.sites else { return Ok(()) };
        let all = sites.all.lock().unwrap_or_else(|p| p.into_inner()).clone();
        if all.len() == sites.written.load(Ordering::Relaxed) {
            return Ok(());
        }
        let batch =
            store::scene::sites_batch(&all).map_err(|e| Error::InvalidArgument(format!("the sites table: {e}")))?;
        self.write_table(store::scene::SITES_TABLE, batch)?;
        sites.written.store(all.len(), Ordering::Relaxed);
        Ok(())
    }

    fn drain_shards(&self) {
        let kinds = self.inner.kinds();
        for shard in &self.inner.shards {
            let chunk = {
                let mut s = shard.0.lock().unwrap_or_else(|p| p.into_inner());
                if s.cols.trees.is_empty() {
                    continue;
                }
                std::mem::replace(&mut s.cols, RayRows::new(&self.inner.payload))
            };
            self.inner.sink.submit(chunk, &kinds);
        }
    }

    /// Seals everything and stops the workers. Reports write failures (trees sealed before them
    /// stay intact) and recording mistakes (nesting, payload types, trees never ended).
    pub fn finish(self) -> Result<Summary> {
        self.drain_shards();
        let sites = self.write_sites();
        let summary = self.inner.sink.finish(&self.inner.kinds())?;
        let open: i64 = self.inner.shards.iter().map(|s| s.0.lock().unwrap_or_else(|p| p.into_inner()).open).sum();
        if open > 0 {
            self.inner.mistake(format!("{open} trees were begun and never ended (they are not in the trace)"));
        }
        let m = self.inner.mistakes.lock().unwrap_or_else(|p| p.into_inner());
        if m.count > 0 {
            return Err(Error::Misuse { count: m.count, first: m.first.clone() });
        }
        sites?;
        Ok(summary)
    }
}

/// `options` with the `site` payload column appended when sites are recorded (refused when the
/// renderer declared a column of that name itself).
fn with_site_column(mut options: RecorderOptions) -> Result<RecorderOptions> {
    if options.sites {
        let name = store::scene::SITE_COLUMN;
        if options.payload.fields.iter().any(|f| f.name == name) {
            return Err(Error::InvalidArgument(format!(
                "payload column `{name}` is the recording site's when sites are recorded: rename yours"
            )));
        }
        let mut fields = options.payload.fields.clone();
        fields.push(store::PayloadField {
            name: name.into(),
            element: arrow::datatypes::DataType::UInt32,
            list_len: None,
        });
        options.payload = PayloadSchema::new(fields, options.payload.bytes)?;
    }
    Ok(options)
}

fn registry(names: &[String]) -> Result<KindTable> {
    let mut k = KindTable::default();
    for n in names {
        k.register(n)?;
    }
    Ok(k)
}

/// One tree being recorded. Depth-first renderers use [`TreeBuilder::descend`] /
/// [`TreeBuilder::ascend`]; breadth-first and wavefront renderers name parents with
/// [`TreeBuilder::add_ray_under`].
pub struct TreeBuilder {
    rec: Arc<Inner>,
    id: u64,
    pixel: [u32; 2],
    sample: u32,
    cols: RayRows,
    stack: Vec<u32>,
    last: Option<u32>,
    max_depth: u16,
    mismatches: Vec<PayloadMismatch>,
}

impl TreeBuilder {
    pub fn id(&self) -> TreeId {
        TreeId(self.id)
    }

    /// The ray added last, if any.
    pub fn last_ray(&self) -> Option<RayId> {
        self.last.map(RayId)
    }

    /// Rays added so far.
    pub fn ray_count(&self) -> u32 {
        self.cols.len() as u32
    }

    /// Adds a ray under the current parent (the ray last descended into; none at the top).
    #[inline]
    #[track_caller]
    pub fn add_ray(&mut self, ray: &RayFields, payload: Payload<'_>) -> RayId {
        let site = SiteRef::Location(std::panic::Location::caller());
        self.add_ray_at(site, ray, payload)
    }

    /// [`TreeBuilder::add_ray`] with its recording site given (a renderer that records rays
    /// after tracing them keeps each ray's `Location` from where it was traced; C and Python
    /// name the file and line).
    pub fn add_ray_at(&mut self, site: SiteRef<'_>, ray: &RayFields, payload: Payload<'_>) -> RayId {
        let parent = self.stack.last().copied();
        self.push(parent, ray, payload, site)
    }

    /// Adds a ray under an explicit parent ray of this tree (breadth-first recording).
    #[track_caller]
    pub fn add_ray_under(&mut self, parent: RayId, ray: &RayFields, payload: Payload<'_>) -> RayId {
        self.add_ray_under_at(SiteRef::Location(std::panic::Location::caller()), parent, ray, payload)
    }

    /// [`TreeBuilder::add_ray_under`] with its recording site given.
    pub fn add_ray_under_at(
        &mut self,
        site: SiteRef<'_>,
        parent: RayId,
        ray: &RayFields,
        payload: Payload<'_>,
    ) -> RayId {
        if parent.0 as usize >= self.cols.len() {
            self.rec.mistake(format!(
                "tree {}: parent ray {} does not exist yet (tree has {} rays); recorded as a root",
                self.id,
                parent.0,
                self.cols.len()
            ));
            return self.push(None, ray, payload, site);
        }
        self.push(Some(parent.0), ray, payload, site)
    }

    #[inline]
    fn push(&mut self, parent: Option<u32>, ray: &RayFields, payload: Payload<'_>, site: SiteRef<'_>) -> RayId {
        let index = self.cols.len() as u32;
        let depth = parent.map_or(0, |p| self.cols.core.get(p as usize).map_or(0, |r| r.depth + 1));
        self.max_depth = self.max_depth.max(depth);
        self.cols.push_core(parent.unwrap_or(store::NONE_U32), depth, ray);
        if !self.rec.payload.fields.is_empty()
            || self.rec.payload.bytes.is_some()
            || payload.bytes.is_some()
            || !payload.values.is_empty()
        {
            self.cols.push_payload(
                &self.rec.payload,
                &self.rec.layout,
                payload.values,
                payload.bytes,
                &mut self.mismatches,
            );
        }
        if let Some(sites) = &self.rec.sites {
            let id = match site {
                SiteRef::Location(loc) => sites.id_of_location(loc),
                SiteRef::Named { file, line, function } => sites.id_of(store::scene::Site {
                    file: file.to_string(),
                    line,
                    column: 0,
                    function: function.map(str::to_string),
                }),
            };
            self.cols.set_last_value(&self.rec.layout, sites.slot, store::Value::U32(id));
        }
        self.last = Some(index);
        RayId(index)
    }

    /// Makes the last added ray the parent of the rays added next (recursion into it).
    pub fn descend(&mut self) {
        match self.last {
            Some(l) if self.stack.last() != Some(&l) => self.stack.push(l),
            _ => self.rec.mistake(format!("tree {}: descend without a new ray to descend into; ignored", self.id)),
        }
    }

    /// Returns to the parent level (the end of a recursion).
    pub fn ascend(&mut self) {
        match self.stack.pop() {
            Some(p) => self.last = Some(p),
            None => self.rec.mistake(format!("tree {}: ascend above the root; ignored", self.id)),
        }
    }

    /// Ends the tree and hands it to the recorder. Returns its id.
    /// A tree dropped without `end` is not recorded; `finish` reports it as a mistake.
    pub fn end(mut self) -> TreeId {
        if !self.stack.is_empty() {
            self.rec.mistake(format!(
                "tree {}: ended {} levels below the root (missing ascend)",
                self.id,
                self.stack.len()
            ));
        }
        for m in self.mismatches.drain(..).take(1) {
            self.rec.mistake(format!(
                "tree {}: payload column `{}` expected {}, got {}; stored as null",
                self.id, m.column, m.expected, m.found
            ));
        }
        let mut cols = std::mem::take(&mut self.cols);
        cols.trees.push(TreeRow {
            tree_id: self.id,
            pixel_x: self.pixel[0],
            pixel_y: self.pixel[1],
            sample: self.sample,
            ray_count: cols.len() as u32,
            max_depth: self.max_depth,
            first_row: 0,
        });
        self.rec.seal(cols);
        TreeId(self.id)
    }
}
