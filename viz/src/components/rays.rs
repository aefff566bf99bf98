//! Ray trees as segments coloured by kind (the paper's colours: camera green, shadow white,
//! diffuse yellow, specular red, transmission blue), direction shown as a gradient from origin to
//! end, misses drawn to the scene bounds, filters by kind, depth, tree, pixel and sample.

use std::collections::BTreeMap;

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::{Float32Type, UInt64Type};
use renderers::TracerChoice;
use serde::{Deserialize, Serialize};

use crate::camera::ViewUniform;
use crate::component::{Component, ComponentId, Frame, Layer, LayerRole, Legend, RenderCtx, TraceCtx, TracedPixel};
use crate::draw::{GpuSegment, SEGMENT_BYTES, SegmentBuffers, pack_rgba};
use crate::sources::Sources;
use crate::splat::{DensityScale, DensityStats, Drawn, RayStyle, StyleParams};
use crate::{Error, Result};
use rtvtk_gpu::Gpu;
use store::RaySelection;

/// The colour of a ray kind (Figure 6 of the paper).
pub fn kind_color(kind: &str) -> [u8; 4] {
    match kind {
        "camera" => [40, 220, 40, 255],
        "shadow" => [245, 245, 245, 255],
        "diffuse" => [250, 220, 30, 255],
        "specular" => [235, 40, 40, 255],
        "transmission" => [60, 110, 255, 255],
        _ => [220, 80, 220, 255],
    }
}

/// The most rays a refining layer loads (640 MiB of segments).
pub const REFINE_LIMIT: u64 = 20_000_000;

/// The kinds in legend order.
pub const KIND_ORDER: [&str; 5] = ["camera", "shadow", "diffuse", "specular", "transmission"];

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RaysSettings {
    /// Only these kinds (all when `None`).
    pub kinds: Option<Vec<String>>,
    /// Only depths in `[min, max]`.
    pub depth: Option<[u32; 2]>,
    /// Only this tree.
    pub tree: Option<u64>,
    /// Only the trees of this pixel.
    pub pixel: Option<[u32; 2]>,
    /// Only this sample (with or without `pixel`).
    pub sample: Option<u32>,
    /// Only rays whose index in their tree is at most this (stepping through a tree ray by ray).
    pub ray_upto: Option<u32>,
    /// At most this many rays (`None`: all that match). When more match, a sample stratified
    /// by kind and depth, spread over the pixels, is drawn (never the first rows), and the
    /// legend says how many of how many.
    pub max_rays: Option<u64>,
    /// After drawing a sample, draw larger ones while idle (four times as many each time), up to
    /// every matching ray or [`REFINE_LIMIT`] (the viewer refines; a headless render does not).
    pub refine: bool,
    pub line_width: f32,
    pub opacity: f32,
    /// How the rays are drawn: `lines` (opaque), `alpha` (translucent at `opacity`, in no
    /// particular order) or `density` (rays per pixel).
    pub style: RayStyle,
    /// The density style's scale: `log` or `linear`.
    pub density_scale: DensityScale,
    /// The alpha style lowers `opacity` so that nine in ten covered pixels stay at most half
    /// covered (what lies under the rays shows however many there are); false: `opacity` as is.
    pub auto_opacity: bool,
    /// The density style's colour map (`None`: the kinds' colours, brightness by density).
    pub density_map: Option<String>,
    /// Direction as a gradient (dim at the origin, full colour at the end).
    pub gradient: bool,
    /// Highlight this tree (drawn wider).
    pub selected_tree: Option<u64>,
    /// The tracer of immediate mode (Ctrl-click): `path` (`cpu`), `whitted` or `gpu` (the GPU
    /// path tracer, recording the pixel's rays on the GPU).
    #[serde(with = "crate::component::tracer_setting")]
    pub tracer: TracerChoice,
}

impl crate::component::Settings for RaysSettings {
    fn choices() -> Vec<(&'static str, &'static [&'static str])> {
        vec![("tracer", TracerChoice::NAMES), ("style", RayStyle::NAMES), ("density_scale", DensityScale::NAMES)]
    }
    const KIND: &'static str = "rays";
}

impl Default for RaysSettings {
    fn default() -> Self {
        RaysSettings {
            kinds: None,
            depth: None,
            tree: None,
            pixel: None,
            sample: None,
            ray_upto: None,
            max_rays: Some(10_000_000),
            refine: false,
            line_width: 1.5,
            opacity: 1.0,
            style: RayStyle::Lines,
            density_scale: DensityScale::Log,
            density_map: None,
            auto_opacity: true,
            gradient: true,
            selected_tree: None,
            tracer: TracerChoice::Path,
        }
    }
}

/// What decides which rays are loaded (and highlighted).
type DataKey = (
    Option<Vec<String>>,
    Option<[u32; 2]>,
    Option<u64>,
    Option<[u32; 2]>,
    Option<u32>,
    Option<u64>,
    Option<u64>,
    Option<u32>,
);

impl RaysSettings {
    /// The rays the filters select (kinds, depth range, tree, pixel, sample, `ray_upto`).
    pub fn selection(&self) -> Result<RaySelection> {
        use store::scene::col;
        let mut sel = RaySelection::all();
        if let Some(k) = &self.kinds {
            for name in k {
                if !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') || name.is_empty() {
                    return Err(Error::Settings(format!("rays: kind {name:?} is not a kind name")));
                }
            }
            sel = sel.only_kinds(k.iter().cloned());
        }
        if let Some([a, b]) = self.depth {
            if a > b {
                return Err(Error::Settings(format!("rays: depth range {a}..{b} is empty")));
            }
            sel = sel.only(col::DEPTH, [(u64::from(a), u64::from(b))]);
        }
        if let Some(t) = self.tree {
            sel = sel.only(col::TREE_ID, [(t, t)]);
        }
        if let Some([x, y]) = self.pixel {
            sel = sel
                .only(col::PIXEL_X, [(u64::from(x), u64::from(x))])
                .only(col::PIXEL_Y, [(u64::from(y), u64::from(y))]);
        }
        if let Some(v) = self.sample {
            sel = sel.only(col::SAMPLE, [(u64::from(v), u64::from(v))]);
        }
        if let Some(n) = self.ray_upto {
            sel = sel.only(col::RAY, [(0, u64::from(n))]);
        }
        Ok(sel)
    }

    /// The filters as a SQL predicate over the `rays` table (what a served dataset is asked).
    pub fn predicate(&self) -> Result<String> {
        Ok(self.selection()?.to_sql())
    }

    /// The style settings as the line drawing takes them.
    pub fn style_params(&self) -> StyleParams {
        StyleParams {
            style: self.style,
            scale: self.density_scale,
            map: self.density_map.clone(),
            opacity: self.opacity,
            auto_opacity: self.auto_opacity,
        }
    }

    fn data_key(&self) -> DataKey {
        (
            self.kinds.clone(),
            self.depth,
            self.tree,
            self.pixel,
            self.sample,
            self.max_rays,
            self.selected_tree,
            self.ray_upto,
        )
    }
}

/// Turns ray rows (origin, direction, t) into segments, clipping misses to a box.
pub struct SegmentBuilder {
    lo: [f64; 3],
    hi: [f64; 3],
    frame: Frame,
    /// Rows skipped for NaN or infinite origins or directions (or NaN t).
    pub skipped: u64,
    pub misses: u64,
}

impl SegmentBuilder {
    pub fn new(bounds: Option<([f64; 3], [f64; 3])>, frame: Frame) -> SegmentBuilder {
        let (lo, hi) = bounds.unwrap_or(([-1.0; 3], [1.0; 3]));
        // A little beyond the scene so misses visibly leave it.
        let pad = (0..3).map(|k| hi[k] - lo[k]).fold(0.0f64, f64::max) * 0.05;
        SegmentBuilder { lo: lo.map(|v| v - pad), hi: hi.map(|v| v + pad), frame, skipped: 0, misses: 0 }
    }

    /// The end point of a ray, or `None` (counted) when it cannot be drawn.
    pub fn end(&mut self, o: [f32; 3], d: [f32; 3], t: f32) -> Option<([f64; 3], [f64; 3])> {
        if o.iter().chain(d.iter()).any(|v| !v.is_finite()) || t.is_nan() || d == [0.0; 3] {
            self.skipped += 1;
            return None;
        }
        let o = o.map(f64::from);
        let d = d.map(f64::from);
        let t = if t.is_finite() {
            f64::from(t)
        } else {
            self.misses += 1;
            // Exit of the bounding box (slab test), from the origin on.
            let mut t1 = f64::INFINITY;
            for k in 0..3 {
                if d[k] != 0.0 {
                    let a = (self.lo[k] - o[k]) / d[k];
                    let b = (self.hi[k] - o[k]) / d[k];
                    t1 = t1.min(a.max(b));
                }
            }
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if t1.is_finite() && t1 > 0.0 { t1 } else { self.frame.radius * 0.25 / len }
        };
        Some((o, [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t]))
    }

    pub fn segment(&self, a: [f64; 3], b: [f64; 3], color: [u8; 4], flags: u32) -> GpuSegment {
        GpuSegment { a: self.frame.local(a), color: pack_rgba(color), b: self.frame.local(b), flags }
    }
}

/// The columns `names` of a batch as Float32 (cast from other numeric types), or an error naming
/// the one that is missing or not numeric.
pub fn f32_columns<const N: usize>(batch: &RecordBatch, names: [&str; N]) -> Result<[arrow::array::Float32Array; N]> {
    let mut out = Vec::with_capacity(N);
    for n in names {
        let c = batch.column_by_name(n).ok_or_else(|| Error::Columns(format!("column `{n}` is missing")))?;
        let c = match c.as_primitive_opt::<Float32Type>() {
            Some(f) => f.clone(),
            None if c.data_type().is_numeric() => {
                arrow::compute::cast(c, &arrow::datatypes::DataType::Float32)?.as_primitive::<Float32Type>().clone()
            }
            None => return Err(Error::Columns(format!("column `{n}` is {}, expected a number", c.data_type()))),
        };
        out.push(c);
    }
    out.try_into().map_err(|_| Error::Columns("column count".into()))
}

/// Names of a kind column (plain or dictionary-encoded strings), per row.
pub fn kind_names(col: &dyn Array) -> Result<Vec<Option<String>>> {
    let strings = arrow::compute::cast(col, &arrow::datatypes::DataType::Utf8)?;
    let s = strings.as_string::<i32>();
    Ok((0..s.len()).map(|i| (!s.is_null(i)).then(|| s.value(i).to_string())).collect())
}

/// The ray layer.
pub struct Rays {
    id: ComponentId,
    settings: RaysSettings,
    generation: u64,
    loaded: Option<(Frame, DataKey)>,
    segments: Option<SegmentBuffers>,
    /// The line pipelines it draws and picks with.
    lines: crate::lines::Lines,
    kinds: BTreeMap<String, u64>,
    skipped: u64,
    misses: u64,
    /// Seconds the last load took.
    pub load_secs: f64,
    /// Trees traced in immediate mode (`trace_ray`), drawn highlighted over the loaded rays.
    traced: Option<SegmentBuffers>,
    traced_kinds: BTreeMap<String, u64>,
    /// Tree and ray index of every loaded segment, in buffer order (picking).
    picks: PickIds,
    /// Pixel, tree and ray index of every traced segment.
    traced_ids: Vec<([u32; 2], u64, u32)>,
    bvh: Option<std::sync::Arc<renderers::Bvh>>,
    /// The tracer of immediate mode (setting `tracer`), made on first use.
    tracer: Option<Box<dyn renderers::Tracer>>,
    /// The last load was cancelled after this many segments (kept, drawn).
    cancelled_after: Option<u64>,
    /// What the last styled draw found (the density colour bar's range, the alpha opacity).
    drawn: Drawn,
    /// Rays that matched the filters at the last load, and how many of them were drawn when
    /// that was a sample.
    matched: u64,
    sampled: Option<u64>,
    /// When the sample was drawn from some row groups only (a large trace): (read, of all).
    groups_read: Option<(usize, usize)>,
    /// The budget of a refining layer's next load (`None`: `max_rays`).
    budget: Option<u64>,
}

impl Rays {
    pub fn new(id: ComponentId, sources: &Sources, settings: &serde_json::Value) -> Result<Rays> {
        if !sources.has_rays() && sources.scene.is_none() {
            return Err(Error::Layer { layer: "rays".into(), message: "no dataset and no scene to trace".into() });
        }
        let mut r = Rays {
            id,
            settings: RaysSettings::default(),
            generation: 0,
            loaded: None,
            segments: None,
            lines: crate::lines::Lines::new(crate::draw::LineShape::Segments),
            kinds: BTreeMap::new(),
            skipped: 0,
            misses: 0,
            load_secs: 0.0,
            traced: None,
            traced_kinds: BTreeMap::new(),
            picks: PickIds::default(),
            traced_ids: Vec::new(),
            bvh: None,
            tracer: None,
            cancelled_after: None,
            drawn: Drawn::default(),
            matched: 0,
            sampled: None,
            groups_read: None,
            budget: None,
        };
        if !settings.is_null() {
            r.set_settings(settings)?;
        }
        Ok(r)
    }

    /// Number of segments on the GPU.
    pub fn segment_count(&self) -> u64 {
        self.segments.as_ref().map_or(0, |s| s.count)
    }

    /// GPU bytes of the segment buffers.
    pub fn gpu_bytes(&self) -> u64 {
        self.segments.as_ref().map_or(0, |s| s.gpu_bytes())
    }

    /// Streams the rays that pass the filters from the dataset onto the GPU, straight from the
    /// store (no SQL engine): the tree, pixel and sample filters pick whole trees from the tree
    /// index, so only the pages holding their rows are read; kinds, depths and `ray_upto` are
    /// applied to the decoded columns batch by batch, and no copy of the whole trace is kept.
    pub fn load(&mut self, gpu: &Gpu, sources: &Sources, frame: Frame) -> Result<()> {
        self.load_with(gpu, sources, frame, &crate::component::Progress::default())
    }

    /// [`Rays::load`], reporting the rows read to `progress`; when it is cancelled the layer keeps
    /// the rays loaded so far (and says so in its report) until its filters change.
    pub fn load_with(
        &mut self,
        gpu: &Gpu,
        sources: &Sources,
        frame: Frame,
        progress: &crate::component::Progress,
    ) -> Result<()> {
        let t0 = std::time::Instant::now();
        self.cancelled_after = None;
        let s = self.settings.clone();
        let sel = s.selection()?;
        let mut bufs = SegmentBuffers::new(gpu);
        // Rows that could not be drawn, and misses clipped to the scene, over every piece.
        let (mut skipped, mut misses) = (0u64, 0u64);
        let mut kinds: BTreeMap<String, u64> = BTreeMap::new();
        let mut picks = PickIds::default();
        if !sources.has_rays() {
            // Immediate mode only: nothing recorded to load.
            self.segments = Some(bufs);
            self.loaded = Some((frame, self.settings.data_key()));
            return Ok(());
        }
        // Ends the progress however the load ends (an error, a cancel, done).
        struct Finish<'a>(&'a crate::component::Progress);
        impl Drop for Finish<'_> {
            fn drop(&mut self) {
                self.0.finish();
            }
        }
        let _finish = Finish(progress);
        use store::scene::col;
        let names = load_columns();
        let budget = self.budget.or(s.max_rays);
        let mut left = budget.unwrap_or(u64::MAX);
        // Where more rays match than the budget allows, each (kind, depth) stratum keeps share
        // `p` of its rays (see `RowSampler`); `p` is set once the matching rows are known.
        let mut p = 1.0f64;
        let mut matched = 0u64;
        let mut known: Option<u64> = None;
        // The rows of one batch made into segments (on a decoding thread), appended in trace
        // order; false once no more are wanted (cancelled, or `max_rays` reached).
        let mut consume = |mut k: Kept| -> Result<bool> {
            if !progress.advance(k.rows) {
                self.cancelled_after = Some(picks.len() as u64);
                return Ok(false);
            }
            matched += k.matched;
            skipped += k.skipped;
            misses += k.misses;
            let more = (k.segments.len() as u64) < left;
            if !more {
                k.truncate(left as usize);
            }
            left -= k.segments.len() as u64;
            for (name, n) in k.kinds() {
                *kinds.entry(name.to_string()).or_default() += n;
            }
            for (seg, (tree, ray)) in k.segments.into_iter().zip(k.picks) {
                bufs.push(gpu, seg);
                picks.push(tree, ray);
            }
            Ok(more && left > 0)
        };
        let sampler = |seed: u64, p: f64| {
            RowSampler::new(&sel, s.selected_tree, p, SegmentBuilder::new(sources.bounds, frame), seed)
        };
        match &sources.dataset {
            Some(ds) => {
                // The store plans the rows (whole trees) that can hold a selected ray; the
                // sampler keeps the selected ones.
                let mut plan = ds.plan(&sel)?;
                let mut total = plan.rays();
                self.groups_read = None;
                if let Some(b) = budget.filter(|b| total > *b) {
                    let m = ds.count_planned(&sel, &plan)?;
                    known = Some(m);
                    p = (b as f64 / m.max(1) as f64).min(1.0);
                    // A large trace: read only some of its row groups (each starts at a tree),
                    // spread evenly over the trace (which lies in pixel order), and sample those.
                    if total > SUBSET_ABOVE
                        && let Some((subset, read, groups)) =
                            ds.spread_row_groups(&plan, p, SUBSET_OVERSAMPLE, SUBSET_MIN_GROUPS)?
                    {
                        let read_rows = subset.rays();
                        p = (p * total as f64 / read_rows.max(1) as f64).min(1.0);
                        plan = subset;
                        total = read_rows;
                        self.groups_read = Some((read, groups));
                    }
                }
                progress.start("loading rays", total);
                read_pieces(ds, &names, pieces(ds, &plan)?, &|piece| sampler(piece as u64, p), &mut consume)?;
            }
            None => {
                // A service's dataset: the same rows through SQL, in tree order, sampled as above
                // once a count says how many match.
                let (table, pred) = (sources.table("rays"), sel.to_sql());
                if let Some(b) = budget {
                    let counted = sources.query(&format!("SELECT count(*) AS n FROM {table} WHERE {pred}"))?;
                    let m = counted
                        .first()
                        .and_then(|c| arrow::compute::cast(c.column(0), &arrow::datatypes::DataType::UInt64).ok())
                        .map_or(0, |c| c.as_primitive::<UInt64Type>().value(0));
                    known = Some(m);
                    p = (b as f64 / m.max(1) as f64).min(1.0);
                }
                let sql = format!(
                    "SELECT {} FROM {table} WHERE {pred} ORDER BY {}, {}",
                    names.join(", "),
                    col::TREE_ID,
                    col::RAY
                );
                progress.start("loading rays", budget.unwrap_or(0));
                let mut done = false;
                let mut one = sampler(0, p);
                sources.query_batches(&sql, |b| {
                    if !done && !consume(one.batch(b)?)? {
                        done = true;
                    }
                    Ok(())
                })?;
            }
        }
        bufs.finish(gpu);
        self.matched = known.unwrap_or(matched);
        self.sampled = (p < 1.0).then_some(picks.len() as u64);
        self.skipped = skipped;
        self.misses = misses;
        self.kinds = kinds;
        self.segments = Some(bufs);
        picks.shrink();
        self.picks = picks;
        let mut key = self.settings.data_key();
        key.5 = budget;
        self.loaded = Some((frame, key));
        self.load_secs = t0.elapsed().as_secs_f64();
        Ok(())
    }
}

/// The tree and ray index of each loaded segment, in buffer order: a tree's segments arrive
/// together, so tree ids are kept once per run of segments (about 6 bytes a segment instead of
/// 12; the segment buffer is 32).
#[derive(Debug, Default)]
struct PickIds {
    /// (first segment, tree id) of each run of segments of one tree.
    runs: Vec<(u32, u64)>,
    rays: Vec<u32>,
}

impl PickIds {
    fn push(&mut self, tree: u64, ray: u32) {
        if self.runs.last().is_none_or(|&(_, t)| t != tree) {
            self.runs.push((self.rays.len() as u32, tree));
        }
        self.rays.push(ray);
    }

    fn len(&self) -> usize {
        self.rays.len()
    }

    fn get(&self, i: usize) -> Option<(u64, u32)> {
        let ray = *self.rays.get(i)?;
        let run = self.runs.partition_point(|&(first, _)| first as usize <= i).checked_sub(1)?;
        Some((self.runs[run].1, ray))
    }

    fn shrink(&mut self) {
        self.runs.shrink_to_fit();
        self.rays.shrink_to_fit();
    }
}

/// Part of a load decoded on one thread: rows of one segment (whole row groups, or the tree
/// ranges a filter kept within one row group).
struct Piece {
    segment: usize,
    rows: Option<Vec<std::ops::Range<u64>>>,
}

/// The pieces that read `plan`'s rows, in trace order: row group by row group where row groups
/// start at trees (format version 2 on, or plain columns), so each decodes alone; otherwise a
/// segment at a time.
fn pieces(ds: &store::Dataset, plan: &store::AccessPlan) -> Result<Vec<Piece>> {
    let m = ds.manifest();
    let split = m.format_version >= 2 || m.encoding == store::Encoding::Plain;
    let mut out = Vec::new();
    for part in &plan.segments {
        let (i, ranges) = (part.segment, part.rows.as_deref().map(Vec::as_slice));
        if !split {
            out.push(Piece { segment: i, rows: ranges.map(<[_]>::to_vec) });
            continue;
        }
        for g in ds.segment_row_groups(i)? {
            let Some(ranges) = ranges else {
                out.push(Piece { segment: i, rows: Some(vec![g]) });
                continue;
            };
            let within: Vec<std::ops::Range<u64>> =
                ranges.iter().map(|r| r.start.max(g.start)..r.end.min(g.end)).filter(|r| !r.is_empty()).collect();
            if !within.is_empty() {
                out.push(Piece { segment: i, rows: Some(within) });
            }
        }
    }
    Ok(out)
}

/// The columns a load reads, in [`RowSampler::batch`]'s order.
fn load_columns() -> Vec<String> {
    use store::scene::col;
    let [ox, oy, oz] = col::ORIGIN;
    let [dx, dy, dz] = col::DIR;
    [col::TREE_ID, col::RAY, col::DEPTH, col::KIND, ox, oy, oz, dx, dy, dz, col::T].map(String::from).to_vec()
}

/// What one batch of rows became: the segments of the rows kept (in row order) with their tree
/// and ray ids and kinds, and what was counted on the way.
#[derive(Debug, Default)]
struct Kept {
    /// Rows read.
    rows: u64,
    /// Rows the filters kept (before sampling).
    matched: u64,
    skipped: u64,
    misses: u64,
    segments: Vec<GpuSegment>,
    picks: Vec<(u64, u32)>,
    /// Per kept segment, its kind's index in `kind_names`.
    kind_of: Vec<u16>,
    kind_names: Vec<String>,
}

impl Kept {
    /// Only the first `n` segments (the end of the budget).
    fn truncate(&mut self, n: usize) {
        self.segments.truncate(n);
        self.picks.truncate(n);
        self.kind_of.truncate(n);
    }

    /// Segments kept per kind name.
    fn kinds(&self) -> Vec<(&str, u64)> {
        let mut n = vec![0u64; self.kind_names.len()];
        for &k in &self.kind_of {
            n[usize::from(k)] += 1;
        }
        self.kind_names.iter().map(String::as_str).zip(n).filter(|(_, n)| *n > 0).collect()
    }
}

/// Turns rows (columns in the load's order: tree, ray, depth, kind, origin, direction, t) into
/// segments: the rows the selection keeps, then, where `p` < 1, a sample keeping share `p` of each
/// (kind, depth) stratum. Within a stratum the sample is systematic (every 1/p-th ray: rows
/// arrive tree by tree in pixel order, so the kept rays spread over the image too), from a
/// start drawn from `seed` and the stratum: each piece of a load samples alone, and a fixed
/// start would keep nothing of a stratum with fewer than 1/p rays per piece.
struct RowSampler<'a> {
    sel: &'a RaySelection,
    /// The tree drawn highlighted.
    selected_tree: Option<u64>,
    p: f64,
    builder: SegmentBuilder,
    seed: u64,
    /// Each stratum's accumulator, by kind id and then depth (a lookup per row: no hashing).
    strata: Vec<Vec<f64>>,
    kind_ids: Vec<String>,
}

impl<'a> RowSampler<'a> {
    fn new(sel: &'a RaySelection, selected_tree: Option<u64>, p: f64, builder: SegmentBuilder, seed: u64) -> Self {
        RowSampler { sel, selected_tree, p, builder, seed, strata: Vec::new(), kind_ids: Vec::new() }
    }

    /// The start of a stratum's systematic sample in [0, 1): a hash of the seed, kind and depth.
    fn start(&self, kind: &str, depth: usize) -> f64 {
        let mut h = self.seed ^ 0x9E37_79B9_7F4A_7C15;
        for b in kind.bytes().chain((depth as u64).to_le_bytes()) {
            h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01B3);
        }
        // splitmix64's finalizer, then the top 53 bits as a fraction.
        h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        h ^= h >> 31;
        (h >> 11) as f64 / (1u64 << 53) as f64
    }

    fn batch(&mut self, b: &RecordBatch) -> Result<Kept> {
        use store::scene::col;
        let [ox, oy, oz] = col::ORIGIN;
        let [dx, dy, dz] = col::DIR;
        let sel = self.sel;
        let mut out = Kept { rows: b.num_rows() as u64, ..Kept::default() };
        let [ox, oy, oz, dx, dy, dz, t] = f32_columns(b, [ox, oy, oz, dx, dy, dz, col::T])?;
        let tree = arrow::compute::cast(b.column(0), &arrow::datatypes::DataType::UInt64)?;
        let tree = tree.as_primitive::<UInt64Type>();
        let ray = arrow::compute::cast(b.column(1), &arrow::datatypes::DataType::UInt32)?;
        let ray = ray.as_primitive::<arrow::datatypes::UInt32Type>();
        let depth = arrow::compute::cast(b.column(2), &arrow::datatypes::DataType::UInt32)?;
        let depth = depth.as_primitive::<arrow::datatypes::UInt32Type>();
        let (names_of, codes) = store::selection::kind_codes(b.column(3).as_ref())?;
        // Per kind value: its colour, whether the kind filter keeps it, and its stratum id.
        let per_kind: Vec<([u8; 4], bool, usize)> = names_of
            .iter()
            .map(|n| {
                let n = n.as_deref().unwrap_or("?");
                let id = match self.kind_ids.iter().position(|k| k == n) {
                    Some(i) => i,
                    None => {
                        self.kind_ids.push(n.to_string());
                        self.kind_ids.len() - 1
                    }
                };
                (kind_color(n), sel.keeps_kind(n), id)
            })
            .collect();
        out.kind_names = names_of.iter().map(|n| n.clone().unwrap_or_default()).collect();
        let keep_share = self.p;
        for (r, &k) in codes.iter().enumerate() {
            let (colour, keep, stratum) = per_kind[k];
            if !keep || !sel.keeps_depth_and_ray(u64::from(depth.value(r)), u64::from(ray.value(r))) {
                continue;
            }
            out.matched += 1;
            if keep_share < 1.0 {
                let d = depth.value(r) as usize;
                if self.strata.len() <= stratum {
                    self.strata.resize_with(stratum + 1, Vec::new);
                }
                if self.strata[stratum].len() <= d {
                    let starts: Vec<f64> = (self.strata[stratum].len()..=d)
                        .map(|depth| self.start(&self.kind_ids[stratum], depth))
                        .collect();
                    self.strata[stratum].extend(starts);
                }
                let acc = &mut self.strata[stratum][d];
                *acc += keep_share;
                if *acc < 1.0 {
                    continue;
                }
                *acc -= 1.0;
            }
            // A miss has a null t.
            let tv = if t.is_null(r) { f32::INFINITY } else { t.value(r) };
            let Some((a, e)) =
                self.builder.end([ox.value(r), oy.value(r), oz.value(r)], [dx.value(r), dy.value(r), dz.value(r)], tv)
            else {
                continue;
            };
            let flags = u32::from(self.selected_tree == Some(tree.value(r)));
            out.segments.push(self.builder.segment(a, e, colour, flags));
            out.picks.push((tree.value(r), ray.value(r)));
            out.kind_of.push(k as u16);
        }
        out.skipped = std::mem::take(&mut self.builder.skipped);
        out.misses = std::mem::take(&mut self.builder.misses);
        Ok(out)
    }
}

/// Pieces decoded ahead of the one being consumed, at most: the decoders keep working while
/// this thread waits for the device to take a chunk of segments (what a piece keeps is at most
/// a row group's segments, ~128K of 46 bytes).
const PIECES_AHEAD: usize = 8;

/// Decodes `pieces` of `ds` (the columns `names`) and samples them into segments on all cores,
/// each piece with its own `sampler(index)`, at most [`PIECES_AHEAD`] ahead, and hands what they
/// kept to `consume` in trace order on this thread. When `consume` returns false the decoders
/// stop after their batch in progress. Decoding on one thread and building segments on another
/// made a 50M-ray load 1.5x a SQL scan of the same columns (which decodes on every core).
fn read_pieces<'s>(
    ds: &store::Dataset,
    names: &[String],
    pieces: Vec<Piece>,
    sampler: &(dyn Fn(usize) -> RowSampler<'s> + Sync),
    consume: &mut dyn FnMut(Kept) -> Result<bool>,
) -> Result<()> {
    use std::sync::mpsc;
    type Out = mpsc::SyncSender<Result<Kept>>;
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 8).min(pieces.len().max(1));
    let (work, jobs) = mpsc::channel::<(usize, Piece, Out)>();
    let jobs = std::sync::Mutex::new(jobs);
    std::thread::scope(|sc| -> Result<()> {
        // Owned here: returning drops it, which closes the queue and ends the decoders.
        let work = work;
        for t in 0..threads {
            let jobs = &jobs;
            let spawned =
                std::thread::Builder::new().name(format!("rtvtk-rays-read-{t}")).spawn_scoped(sc, move || {
                    loop {
                        // The lock is held only to take a job: a closed queue ends the thread.
                        let job = jobs.lock().map_err(|_| ()).and_then(|q| q.recv().map_err(|_| ()));
                        let Ok((index, piece, out)) = job else { return };
                        let batches = match ds.segment_columns_in(
                            piece.segment,
                            names,
                            piece.rows.as_deref(),
                            store::READ_BATCH_ROWS,
                        ) {
                            Ok(it) => it,
                            Err(e) => {
                                let _ = out.send(Err(e.into()));
                                continue;
                            }
                        };
                        let mut smp = sampler(index);
                        for b in batches {
                            let kept = b.map_err(Error::from).and_then(|b| smp.batch(&b));
                            let failed = kept.is_err();
                            if out.send(kept).is_err() || failed {
                                break;
                            }
                        }
                    }
                });
            if let Err(e) = spawned {
                return Err(Error::from(store::Error::Io {
                    action: "starting a thread that reads rays",
                    path: ds.dir().to_path_buf(),
                    source: e,
                }));
            }
        }
        // Pieces handed out and not yet consumed, oldest first.
        let mut ahead: std::collections::VecDeque<mpsc::Receiver<Result<Kept>>> = Default::default();
        let mut pieces = pieces.into_iter().enumerate();
        loop {
            while ahead.len() < PIECES_AHEAD {
                let Some((index, piece)) = pieces.next() else { break };
                // Room for a whole row group's batches (64K rows each): its decoder never
                // waits; a whole segment (older files) waits after four.
                let (tx, rx) = mpsc::sync_channel(4);
                if work.send((index, piece, tx)).is_err() {
                    break;
                }
                ahead.push_back(rx);
            }
            let Some(rx) = ahead.pop_front() else { return Ok(()) };
            // Ends when its decoder is done with the piece (the sender dropped).
            for kept in rx {
                if !consume(kept?)? {
                    // Dropping the queue and the receivers stops the decoders.
                    return Ok(());
                }
            }
        }
    })
}

/// Traces of more rays than this load a sample from some of their row groups only (see
/// [`store::Dataset::spread_row_groups`]); smaller ones are read whole and sampled ray by ray.
const SUBSET_ABOVE: u64 = 32_000_000;
/// A subset reads this many times the rays a sample keeps ...
const SUBSET_OVERSAMPLE: f64 = 16.0;
/// ... and at least this many row groups (about 4M rays: patches spread over the image).
const SUBSET_MIN_GROUPS: usize = 32;

/// The colour bar of a density draw: rays per pixel from 1 to the most on one pixel, in the
/// style's scale and map (a brightness ramp when the rays keep their own colours).
pub fn density_legend(style: &StyleParams, stats: Option<DensityStats>) -> Option<Legend> {
    let s = stats.filter(|_| style.style == RayStyle::Density)?;
    let log = style.scale == DensityScale::Log;
    Some(Legend::ColourBar {
        title: format!("rays per pixel{}", if log { " (log)" } else { "" }),
        map: style.map.clone().unwrap_or_else(|| "greys".into()),
        min: if log { 1.0 } else { 0.0 },
        max: f64::from(s.max.max(1)),
        log,
    })
}

/// A count in a few characters: 950, 12.3K, 5.56M, 1.2B.
pub fn short_count(n: u64) -> String {
    let f = n as f64;
    let (v, unit) = match n {
        0..1_000 => return n.to_string(),
        1_000..1_000_000 => (f / 1e3, "K"),
        1_000_000..1_000_000_000 => (f / 1e6, "M"),
        _ => (f / 1e9, "B"),
    };
    format!("{}{unit}", crate::legend::label(v))
}

impl Layer for Rays {
    type Settings = RaysSettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Scene
    }
    fn reads_occluder(&self) -> bool {
        self.settings.style != RayStyle::Lines
    }
    fn previews(&self) -> bool {
        true
    }
    fn generation(&self) -> u64 {
        self.generation
    }
    fn current(&self) -> &RaysSettings {
        &self.settings
    }
    fn apply(&mut self, s: RaysSettings) -> Result<()> {
        s.selection()?;
        crate::component::check_lines("rays", s.line_width, s.opacity)?;
        if let Some(m) = &s.density_map {
            crate::legend::colour_map(m)?;
        }
        if s.data_key() != self.settings.data_key() {
            self.budget = None;
        }
        crate::component::replace_settings(&mut self.settings, s, &mut self.generation);
        Ok(())
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        let mut key = (ctx.frame, self.settings.data_key());
        key.1.5 = self.budget.or(key.1.5);
        if self.loaded.as_ref() != Some(&key) {
            self.load_with(ctx.gpu, ctx.sources, ctx.frame, ctx.progress)?;
        }
        let s = &self.settings;
        let gradient = if s.gradient { 1.0 } else { 0.0 };
        let view =
            ViewUniform::new(ctx.view_proj(), ctx.target.width, ctx.target.height, s.line_width, s.opacity, gradient);
        // The loaded rays (thinned while the camera moves), then the traced tree over them.
        self.drawn = self.lines.draw_styled(
            ctx,
            &view,
            &[self.segments.as_ref(), self.traced.as_ref()],
            true,
            &self.settings.style_params(),
        )?;
        Ok(())
    }
    fn idle(&mut self, _ctx: &mut crate::component::IdleCtx) -> Result<bool> {
        // A refining layer that drew a sample loads four times as many next (until all match
        // or the limit), once the last load is on screen.
        let Some(drawn) = self.sampled.filter(|_| self.settings.refine && self.loaded.is_some()) else {
            return Ok(false);
        };
        let current = self.budget.or(self.settings.max_rays).unwrap_or(u64::MAX);
        if self.loaded.as_ref().is_none_or(|(_, k)| k.5 != Some(current)) {
            // The last refinement is not loaded yet.
            return Ok(false);
        }
        let next = current.saturating_mul(4).min(REFINE_LIMIT.max(current));
        if next <= current || drawn >= self.matched || self.cancelled_after.is_some() {
            return Ok(false);
        }
        self.budget = Some(next);
        self.generation += 1;
        Ok(true)
    }
    fn trace_ray(&mut self, ctx: &mut TraceCtx, [x, y]: [u32; 2]) -> Result<Option<TracedPixel>> {
        let Some(scene) = &ctx.sources.scene else { return Ok(None) };
        if x >= ctx.width || y >= ctx.height {
            return Err(Error::Settings(format!("pixel {x},{y} is outside the {}x{} view", ctx.width, ctx.height)));
        }
        let bvh = self.bvh.get_or_insert_with(|| std::sync::Arc::new(renderers::Bvh::build(&scene.tris))).clone();
        // The pixel's ray tree through `rl` immediate mode, as a renderer records it.
        let options = rl::RecorderOptions { payload: renderers::payload_schema(), ..Default::default() };
        let (rec, trace) = rl::Recorder::immediate(options)?;
        let opts = renderers::RenderOptions {
            width: ctx.width,
            height: ctx.height,
            spp: 1,
            seed: u64::from(x) << 32 | u64::from(y),
            window: Some([x, y, x + 1, y + 1]),
            threads: 1,
            ..Default::default()
        };
        let choice = self.settings.tracer;
        let layer_err = |e: &dyn std::fmt::Display| Error::Layer {
            layer: "rays".into(),
            message: format!("tracer \"{choice}\": {e}"),
        };
        if self.tracer.as_ref().is_none_or(|t| t.choice() != choice) {
            let t = gpu_tracer::tracer(choice, scene.clone(), bvh, Some(ctx.gpu)).map_err(|e| layer_err(&e))?;
            self.tracer = Some(t);
        }
        if let Some(t) = self.tracer.as_mut() {
            t.set_camera(ctx.camera.into());
            t.render(&opts, Some(&rec), &|_| {}).map_err(|e| layer_err(&e))?;
        }
        rec.finish()?;
        let kinds = store::KindTable::default();
        let mut builder = SegmentBuilder::new(ctx.sources.bounds, ctx.sources.frame());
        let mut segs = Vec::new();
        self.traced_kinds.clear();
        self.traced_ids.clear();
        for tree in trace.trees_at_pixel(x, y, None)? {
            for r in &tree.rays {
                let name = kinds.name(r.kind).unwrap_or("?").to_string();
                let Some((a, e)) = builder.end(r.origin, r.direction, r.t.unwrap_or(f32::INFINITY)) else { continue };
                segs.push(builder.segment(a, e, kind_color(&name), 1));
                self.traced_ids.push(([x, y], tree.info.id.0, r.index));
                *self.traced_kinds.entry(name).or_default() += 1;
            }
        }
        let n = segs.len();
        self.traced = Some(SegmentBuffers::from_segments(segs));
        self.generation += 1;
        Ok(Some(TracedPixel { pixel: [x, y], rays: n }))
    }
    fn pick(&mut self, ctx: &mut crate::component::PickCtx) -> Result<bool> {
        Ok(self.lines.pick(ctx, self.settings.line_width, &[self.segments.as_ref(), self.traced.as_ref()]))
    }
    fn picked(&self, index: u32) -> Option<crate::component::Picked> {
        let i = index as usize;
        if let Some((tree, ray)) = self.picks.get(i) {
            return Some(crate::component::Picked::Ray { tree, ray });
        }
        let j = i.checked_sub(self.picks.len())?;
        let (pixel, tree, ray) = *self.traced_ids.get(j)?;
        Some(crate::component::Picked::Traced { pixel, tree, ray })
    }
    fn legend(&self) -> Vec<Legend> {
        let mut all = self.kinds.clone();
        for (k, n) in &self.traced_kinds {
            *all.entry(k.clone()).or_default() += n;
        }
        let mut entries: Vec<(String, [u8; 4])> = KIND_ORDER
            .iter()
            .filter(|k| all.contains_key(**k))
            .map(|k| (format!("{k} ({})", all[*k]), kind_color(k)))
            .collect();
        for (k, n) in &all {
            if !KIND_ORDER.contains(&k.as_str()) {
                entries.push((format!("{k} ({n})"), kind_color(k)));
            }
        }
        if entries.is_empty() {
            return Vec::new();
        }
        let mut out = Vec::new();
        if self.settings.density_map.is_none() || self.settings.style != RayStyle::Density {
            let title = match self.sampled {
                Some(n) => format!("ray kinds ({} of {} rays drawn)", short_count(n), short_count(self.matched)),
                None => "ray kinds".into(),
            };
            out.push(Legend::Swatches { title, entries });
        }
        out.extend(density_legend(&self.settings.style_params(), self.drawn.density));
        out
    }
    fn report(&self) -> Vec<String> {
        let mut r = vec![format!(
            "rays: {} segments ({} MiB of GPU memory, {} B each), {} misses clipped to the scene bounds, loaded in {:.3} s",
            self.segment_count(),
            self.gpu_bytes() >> 20,
            SEGMENT_BYTES,
            self.misses,
            self.load_secs
        )];
        if let Some(n) = self.sampled {
            r.push(format!(
                "rays: {n} of the {} matching rays drawn ({:.2}%), a sample stratified by kind and depth, spread over the pixels{}{}",
                self.matched,
                100.0 * n as f64 / self.matched.max(1) as f64,
                match self.groups_read {
                    Some((read, all)) => format!(" of {read} of the trace's {all} row groups (evenly spaced)"),
                    None => String::new(),
                },
                if self.settings.refine { "; refining while idle" } else { "" }
            ));
        }
        r.extend(crate::splat::style_report("rays", &self.settings.style_params(), &self.drawn));
        if self.skipped > 0 {
            r.push(format!("rays: skipped {} rays with NaN or infinite origin/direction", self.skipped));
        }
        if let Some(n) = self.cancelled_after {
            r.push(format!("rays: loading was cancelled after {n} segments; change a filter to load again"));
        }
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use store::{DatasetWriter, KindTable, PayloadSchema, RayColumns, RayFields, TreeRow, WriteOptions};

    /// A lossless dataset of 3 segments with row groups of ~64 rays (trees of 1..=5 rays).
    fn dataset(dir: &std::path::Path) -> store::Dataset {
        let schema = PayloadSchema::default();
        let options = WriteOptions { row_group_rows: 64, page_rows: 16, ..WriteOptions::default() };
        let w = DatasetWriter::create(dir, schema.clone(), options).unwrap();
        let kinds = KindTable::default();
        let mut id = 0u64;
        for _ in 0..3 {
            let mut seg = w.open_segment().unwrap();
            let mut cols = RayColumns::new(&schema);
            for _ in 0..1500 {
                let first = cols.len() as u64;
                let n = (id % 5 + 1) as u32;
                for r in 0..n {
                    let f = RayFields {
                        origin: [r as f32, id as f32, 0.5],
                        direction: [0.0, 0.0, -1.0],
                        t: Some(1.0),
                        kind: if r == 0 { store::Kind::CAMERA } else { store::Kind::DIFFUSE },
                        prim: Some(1),
                    };
                    cols.push_core(id, r, if r == 0 { store::NONE_U32 } else { r - 1 }, r as u16, &f);
                }
                cols.trees.push(TreeRow {
                    tree_id: id,
                    pixel_x: (id % 64) as u32,
                    pixel_y: (id / 64) as u32,
                    sample: 0,
                    ray_count: n,
                    max_depth: n as u16 - 1,
                    first_row: first,
                });
                id += 1;
            }
            seg.write(cols, &schema, &kinds).unwrap();
            seg.seal(&w, &kinds).unwrap();
        }
        w.mark_complete().unwrap();
        store::Dataset::open(dir).unwrap()
    }

    /// Picked segments name their tree and ray through runs of tree ids, the same answer as one
    /// id per segment, including a tree seen again after another and the ends.
    #[test]
    fn pick_ids_give_each_segments_tree_and_ray() {
        let rows: Vec<(u64, u32)> = vec![(7, 0), (7, 1), (7, 4), (3, 0), (9, 2), (9, 3), (7, 9), (u64::MAX, u32::MAX)];
        let mut p = PickIds::default();
        for &(t, r) in &rows {
            p.push(t, r);
        }
        p.shrink();
        assert_eq!(p.len(), rows.len());
        assert_eq!(p.runs.len(), 5);
        for (i, want) in rows.iter().enumerate() {
            assert_eq!(p.get(i), Some(*want), "segment {i}");
        }
        assert_eq!(p.get(rows.len()), None);
        assert_eq!(PickIds::default().get(0), None);
    }

    /// The subset of a large trace's row groups is as many as asked (at least the minimum),
    /// spread evenly from the first segment to the last, made of whole row groups that start at
    /// trees; asking for most of the trace reads it whole.
    #[test]
    fn row_group_subsets_are_evenly_spread_whole_row_groups() {
        let dir = tempfile::tempdir().unwrap();
        let ds = dataset(&dir.path().join("ds"));
        let groups: Vec<(usize, std::ops::Range<u64>)> =
            (0..3).flat_map(|i| ds.segment_row_groups(i).unwrap().into_iter().map(move |r| (i, r))).collect();
        let all = groups.len();
        assert!(all > 4 * SUBSET_MIN_GROUPS, "{all} row groups");
        for p in [0.0001, 0.01] {
            let whole = ds.plan(&RaySelection::all()).unwrap();
            let (plan, read, total) =
                ds.spread_row_groups(&whole, p, SUBSET_OVERSAMPLE, SUBSET_MIN_GROUPS).unwrap().unwrap();
            let rows: BTreeMap<usize, Vec<std::ops::Range<u64>>> =
                plan.segments.iter().map(|s| (s.segment, s.rows.as_deref().unwrap().clone())).collect();
            let want = ((p * SUBSET_OVERSAMPLE * all as f64).ceil() as usize).max(SUBSET_MIN_GROUPS);
            assert_eq!((read, total), (want, all));
            let chosen: Vec<(usize, std::ops::Range<u64>)> = groups
                .iter()
                .filter(|(i, g)| rows.get(i).is_some_and(|v| v.iter().any(|r| r.start <= g.start && g.end <= r.end)))
                .cloned()
                .collect();
            assert_eq!(chosen.len(), want, "p = {p}");
            assert_eq!(rows.keys().copied().collect::<Vec<_>>(), vec![0, 1, 2], "every segment is sampled");
            // Each range starts at a tree.
            for (i, v) in &rows {
                let starts: std::collections::HashSet<u64> =
                    ds.segment_tree_entries(*i).unwrap().iter().map(|e| e.first_row).collect();
                assert!(v.iter().all(|r| starts.contains(&r.start)), "segment {i}: {v:?}");
            }
            // Gaps between chosen groups differ by at most one group.
            let pos: Vec<usize> = chosen.iter().map(|c| groups.iter().position(|g| g == c).unwrap()).collect();
            let gaps: Vec<usize> = pos.windows(2).map(|w| w[1] - w[0]).collect();
            assert!(gaps.iter().max().unwrap() - gaps.iter().min().unwrap() <= 1, "{gaps:?}");
        }
        let whole = ds.plan(&RaySelection::all()).unwrap();
        assert!(
            ds.spread_row_groups(&whole, 0.5, SUBSET_OVERSAMPLE, SUBSET_MIN_GROUPS).unwrap().is_none(),
            "most of the trace: read whole"
        );
    }

    /// The load's pieces, decoded on several threads, hand over every row asked for exactly once
    /// and in trace order, each piece within one row group; with tree ranges that cross row
    /// groups too; and a consumer that stops early ends the read.
    #[test]
    fn pieces_read_on_all_cores_come_back_in_trace_order() {
        let dir = tempfile::tempdir().unwrap();
        let ds = dataset(&dir.path().join("ds"));
        let names = load_columns();
        let sel = RaySelection::all();
        let frame = Frame { anchor: [0.0; 3], radius: 10.0 };
        let whole = ds.plan(&sel).unwrap();
        let read = |plan: &store::AccessPlan, stop_after: usize| {
            let mut got: Vec<(u64, u32, f32)> = Vec::new();
            let sampler = |_: usize| RowSampler::new(&sel, None, 1.0, SegmentBuilder::new(None, frame), 0);
            read_pieces(&ds, &names, pieces(&ds, plan).unwrap(), &sampler, &mut |k| {
                for (seg, &(tree, ray)) in k.segments.iter().zip(&k.picks) {
                    got.push((tree, ray, seg.a[1]));
                }
                Ok(got.len() < stop_after)
            })
            .unwrap();
            got
        };
        // Every row: the trees in id order (as written), rays 0..n each, origins decoded.
        let all = read(&whole, usize::MAX);
        assert_eq!(all.len() as u64, ds.ray_count());
        let mut want = Vec::new();
        for id in 0..4500u64 {
            for r in 0..(id % 5 + 1) as u32 {
                want.push((id, r, id as f32));
            }
        }
        assert_eq!(all, want);
        let groups = ds.segment_row_groups(1).unwrap();
        let total: usize = (0..3).map(|i| ds.segment_row_groups(i).unwrap().len()).sum();
        assert_eq!(pieces(&ds, &whole).unwrap().len(), total, "a piece per row group");
        // Tree ranges crossing row groups: split at the groups, rows the same.
        let (a, b) = (groups[1].start, groups[3].end);
        let entries = ds.segment_tree_entries(1).unwrap();
        let (a, b) = (
            entries.iter().map(|e| e.first_row).filter(|&r| r >= a + 3).min().unwrap(),
            entries.iter().map(|e| e.first_row).filter(|&r| r <= b - 3).max().unwrap(),
        );
        let rows = store::AccessPlan {
            segments: vec![store::SegmentAccess {
                segment: 1,
                rows: Some(std::sync::Arc::new(std::iter::once(a..b).collect())),
                trees: 0,
                rays: b - a,
                entries: None,
            }],
        };
        let ps = pieces(&ds, &rows).unwrap();
        assert_eq!(ps.len(), 3, "three row groups touched");
        for p in &ps {
            let r = &p.rows.as_ref().unwrap()[0];
            assert!(groups.iter().any(|g| g.start <= r.start && r.end <= g.end), "{r:?} within one row group");
        }
        let part = read(&rows, usize::MAX);
        assert_eq!(part.len() as u64, b - a);
        let first = want.iter().position(|w| w.0 == part[0].0 && w.1 == 0).unwrap();
        assert_eq!(part[..], want[first..first + part.len()]);
        // Stopping early returns promptly with what was consumed.
        let some = read(&whole, 10);
        assert!(some.len() >= 10 && some.len() < all.len() && some[..] == want[..some.len()]);
    }

    /// Pieces sampled apart keep share p of every (kind, depth) stratum, rare ones included: a
    /// stratum of less than 1/p rays per piece is still sampled (a fixed start of the systematic
    /// sample would keep none of it).
    #[test]
    fn pieces_sampled_apart_keep_their_share_of_every_stratum() {
        let dir = tempfile::tempdir().unwrap();
        let ds = dataset(&dir.path().join("ds"));
        let sel = RaySelection::all();
        let frame = Frame { anchor: [0.0; 3], radius: 10.0 };
        let p = 0.02;
        let sampler = |piece: usize| RowSampler::new(&sel, None, p, SegmentBuilder::new(None, frame), piece as u64);
        let ps = pieces(&ds, &ds.plan(&sel).unwrap()).unwrap();
        let n_pieces = ps.len();
        let mut kept: BTreeMap<(String, u32), u64> = BTreeMap::new();
        let mut matched = 0;
        read_pieces(&ds, &load_columns(), ps, &sampler, &mut |k| {
            matched += k.matched;
            for (i, &(_, ray)) in k.picks.iter().enumerate() {
                // In this trace a ray's depth is its index.
                *kept.entry((k.kind_names[usize::from(k.kind_of[i])].clone(), ray)).or_default() += 1;
            }
            Ok(true)
        })
        .unwrap();
        assert_eq!(matched, ds.ray_count());
        // Rays per stratum: trees 0..4500 of id % 5 + 1 rays; ray r at depth r (camera at 0).
        for depth in 0..5u32 {
            let n = (0..4500u64).filter(|id| id % 5 + 1 > u64::from(depth)).count() as f64;
            let kind = if depth == 0 { "camera" } else { "diffuse" };
            let got = kept.get(&(kind.to_string(), depth)).copied().unwrap_or(0) as f64;
            assert!(n * p / n_pieces as f64 <= 0.5, "a stratum rarer than 1/p per piece");
            // Within four standard deviations of a sum of one Bernoulli draw per piece.
            let tolerance = 4.0 * (n * p).sqrt() + 1.0;
            assert!(
                got >= 1.0 && (got - n * p).abs() <= tolerance,
                "{kind} depth {depth}: kept {got} of {n}, expected {}",
                n * p
            );
        }
    }
}
