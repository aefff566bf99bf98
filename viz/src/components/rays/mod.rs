//! Ray trees as segments coloured by kind (the paper's colours: camera green, shadow white,
//! diffuse yellow, specular red, transmission blue), direction shown as a gradient from origin to
//! end, misses drawn to the scene bounds, filters by kind, depth, tree, pixel and sample.

use std::collections::BTreeMap;

use arrow::array::AsArray;
use arrow::datatypes::UInt64Type;
use renderers::TracerChoice;
use serde::{Deserialize, Serialize};

use crate::camera::ViewUniform;
use crate::component::{Component, ComponentId, Frame, Layer, LayerRole, Legend, RenderCtx, TraceCtx, TracedPixel};
use crate::draw::{SEGMENT_BYTES, SegmentBuffers};
use crate::sources::Sources;
use crate::splat::{DensityScale, DensityStats, Drawn, RayStyle, StyleParams};
use crate::{Error, Result};
use rtvtk_gpu::Gpu;
use store::RaySelection;

mod load;
pub use crate::lines::{SegmentBuilder, f32_columns, kind_names};
use load::{Kept, RowSampler, SUBSET_ABOVE, SUBSET_MIN_GROUPS, SUBSET_OVERSAMPLE, load_columns, pieces, read_pieces};

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
        sel = sel.only_trees_of(self.tree, self.pixel, self.sample);
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
            gpu_tracer::register();
            let t = renderers::tracer(choice, scene.clone(), bvh).map_err(|e| layer_err(&e))?;
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
}
