//! Flat layers: the path-traced image of the dataset (or one refined progressively by the CPU
//! path tracer in `idle`), and a per-pixel heatmap of any `GROUP BY pixel_x, pixel_y` query.

use std::sync::Arc;

use arrow::array::{Array, AsArray};
use arrow::datatypes::{DataType, Float64Type, UInt32Type};
use renderers::TracerChoice;
use serde::{Deserialize, Serialize};

use crate::component::{Component, ComponentId, IdleCtx, Layer, LayerRole, Legend, RenderCtx};
use crate::legend::colour_map;
use crate::sources::{Picture, Sources};
use crate::{Error, Result};
use rtvtk_gpu::Gpu;

/// Draws an RGBA8 picture over the whole layer, with `opacity`.
pub struct Blitter {
    pipeline: wgpu::RenderPipeline,
    sampler: wgpu::Sampler,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct BlitUniform {
    params: [f32; 4],
}

impl Blitter {
    pub fn new(gpu: &Gpu) -> Blitter {
        let pipeline = crate::draw::fullscreen_pipeline(gpu, "blit", include_str!("../shaders/blit.wgsl"), None, true);
        let sampler = gpu.device.create_sampler(&wgpu::SamplerDescriptor {
            mag_filter: wgpu::FilterMode::Nearest,
            min_filter: wgpu::FilterMode::Linear,
            ..Default::default()
        });
        Blitter { pipeline, sampler }
    }

    pub fn draw(&self, ctx: &RenderCtx, texture: &wgpu::Texture, opacity: f32) {
        let gpu = ctx.gpu;
        let ubuf = crate::draw::uniform(gpu, "blit", &BlitUniform { params: [opacity, 0.0, 0.0, 0.0] });
        let view = texture.create_view(&Default::default());
        let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: ubuf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::TextureView(&view) },
                wgpu::BindGroupEntry { binding: 2, resource: wgpu::BindingResource::Sampler(&self.sampler) },
            ],
        });
        crate::draw::fullscreen_into_layer(gpu, ctx.target, &self.pipeline, &group);
    }
}

/// Where the image layer's picture comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum ImageSource {
    /// The picture recorded with the dataset while the view is at the recorded camera; anywhere
    /// else (and with no recorded picture) path-traced from the view, on the GPU where the
    /// adapter can run the GPU tracer, on the CPU otherwise. Never the recorded picture under
    /// rays seen from elsewhere.
    Auto,
    /// The PNG recorded with the dataset, whatever the view (registered only at the recorded
    /// camera).
    Dataset,
    /// Traced from the view by this tracer: a CPU tracer one sample per pixel per idle call
    /// (`path`, also read as `cpu` or `trace`; `whitted`), or the GPU path tracer on the
    /// pipeline's device, as many samples per idle call as fit in about 50 ms, tone-mapped on the
    /// GPU (the CPU path tracer where the adapter cannot run it).
    Traced(TracerChoice),
}

impl ImageSource {
    /// The values of the `source` setting, as the viewer's drop-down offers them.
    pub const NAMES: &'static [&'static str] = &["auto", "dataset", "path", "whitted", "gpu"];

    /// The CPU tracer that traces the image (the fallback of the GPU's).
    fn cpu_tracer(self) -> TracerChoice {
        match self {
            ImageSource::Traced(TracerChoice::Whitted) => TracerChoice::Whitted,
            _ => TracerChoice::Path,
        }
    }
}

impl TryFrom<String> for ImageSource {
    type Error = String;

    fn try_from(s: String) -> std::result::Result<ImageSource, String> {
        match s.as_str() {
            "auto" => Ok(ImageSource::Auto),
            "dataset" => Ok(ImageSource::Dataset),
            "trace" => Ok(ImageSource::Traced(TracerChoice::Path)),
            other => other
                .parse()
                .map(ImageSource::Traced)
                .map_err(|_| format!("source {other:?}: expected one of {}", ImageSource::NAMES.join(", "))),
        }
    }
}

impl From<ImageSource> for String {
    fn from(s: ImageSource) -> String {
        match s {
            ImageSource::Auto => "auto".into(),
            ImageSource::Dataset => "dataset".into(),
            ImageSource::Traced(t) => t.name().into(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImageSettings {
    pub source: ImageSource,
    pub opacity: f32,
    pub exposure: f32,
    /// Stop refining after this many samples per pixel.
    pub max_spp: u32,
}

impl crate::component::Settings for ImageSettings {
    fn choices() -> Vec<(&'static str, &'static [&'static str])> {
        vec![("source", ImageSource::NAMES)]
    }
    const KIND: &'static str = "image";
}

impl Default for ImageSettings {
    fn default() -> Self {
        ImageSettings { source: ImageSource::Auto, opacity: 1.0, exposure: 1.0, max_spp: 1024 }
    }
}

/// The GPU tracer of the image layer and its two accumulating images.
struct GpuImage {
    tracer: gpu_tracer::GpuTracer,
    /// Samples per half per idle call (adapted to about 50 ms).
    batch: u32,
    /// The even and odd batches' sums, for the current camera and size.
    halves: Option<[gpu_tracer::Accumulation; 2]>,
    /// The next sample count at which the halves are read back for the convergence curve
    /// (doubling: a read-back per octave of samples, never one per frame).
    next_curve: u32,
}

/// The image layer's progressive tracing of the current view (camera and size): its CPU or GPU
/// tracer, the sums so far and the convergence curve.
struct ViewTrace {
    bvh: Arc<renderers::Bvh>,
    /// The CPU tracer's sum of the samples per pixel (empty until its first sample; the GPU
    /// tracer keeps its sums on the GPU).
    sum: Vec<glam::Vec3A>,
    /// The sum of the even-numbered samples only (the odd ones are `sum - even`).
    even: Vec<glam::Vec3A>,
    spp: u32,
    secs: f64,
    curve: Vec<crate::component::ConvergencePoint>,
    key: Option<(crate::camera::ViewCamera, u32, u32)>,
    /// The GPU tracer (sources `gpu` and `auto`), when the adapter runs it.
    gpu: Option<GpuImage>,
    /// Why the GPU tracer does not run here (then the CPU traces; said once, in the report).
    gpu_failed: Option<String>,
    /// The CPU tracer (source `path` or `whitted`, or the GPU's fallback), made on first use.
    cpu: Option<Box<dyn renderers::Tracer>>,
}

/// Draws a [`GpuImage`]'s accumulation into a layer, tone-mapped on the GPU (`film.wgsl`).
struct FilmDrawer {
    pipeline: wgpu::RenderPipeline,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct FilmUniform {
    params: [f32; 4],
    dest: [f32; 4],
}

impl FilmDrawer {
    fn new(gpu: &Gpu) -> FilmDrawer {
        let pipeline = crate::draw::fullscreen_pipeline(gpu, "film", include_str!("../shaders/film.wgsl"), None, true);
        FilmDrawer { pipeline }
    }

    fn draw(&self, ctx: &RenderCtx, [even, odd]: &[gpu_tracer::Accumulation; 2], exposure: f32, opacity: f32) {
        let gpu = ctx.gpu;
        let [w, h] = even.size();
        let (tw, th) = (ctx.target.width, ctx.target.height);
        let u = FilmUniform { params: [w as f32, h as f32, exposure, opacity], dest: [tw as f32, th as f32, 0.0, 0.0] };
        let ubuf = crate::draw::uniform(gpu, "film", &u);
        let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("film"),
            layout: &self.pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: ubuf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: even.accumulation().as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: odd.accumulation().as_entire_binding() },
            ],
        });
        crate::draw::fullscreen_into_layer(gpu, ctx.target, &self.pipeline, &group);
    }
}

/// The image layer.
pub struct Image {
    id: ComponentId,
    settings: ImageSettings,
    generation: u64,
    /// The picture recorded with the dataset.
    recorded: Option<Picture>,
    /// The CPU tracer's latest picture.
    traced: Option<Picture>,
    /// The texture of the picture shown last: which one (traced or not) and its generation.
    texture: Option<(bool, u64, wgpu::Texture)>,
    blitter: Option<Blitter>,
    film: Option<FilmDrawer>,
    progressive: Option<ViewTrace>,
    size: [u32; 2],
    /// Whether the last render showed a traced picture (else the recorded one).
    shown_traced: bool,
}

/// Whether `camera` is the camera the dataset's picture was rendered from (to a millionth of the
/// camera's distance to its target, and of a degree).
fn at_recorded(sources: &Sources, camera: &crate::camera::ViewCamera) -> bool {
    let Some(r) = &sources.camera else { return false };
    let d = |a: [f64; 3], b: [f64; 3]| (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt();
    let scale = d(r.position, r.target).max(f64::MIN_POSITIVE);
    d(r.position, camera.position) <= 1e-6 * scale
        && d(r.target, camera.target) <= 1e-6 * scale
        && d(r.up, camera.up) <= 1e-6 * d(r.up, [0.0; 3])
        && (r.fov_y - camera.fov_y).abs() <= 1e-6
}

impl Image {
    pub fn new(id: ComponentId, sources: &Sources, settings: &serde_json::Value) -> Result<Image> {
        let mut im = Image {
            id,
            settings: ImageSettings::default(),
            generation: 0,
            recorded: sources.picture.clone(),
            traced: None,
            texture: None,
            blitter: None,
            film: None,
            progressive: None,
            size: sources.image_size,
            shown_traced: false,
        };
        if !settings.is_null() {
            im.set_settings(settings)?;
        }
        im.check(sources)?;
        Ok(im)
    }

    fn check(&self, sources: &Sources) -> Result<()> {
        let no_scene = sources.scene.is_none();
        let message = match self.settings.source {
            ImageSource::Dataset if self.recorded.is_none() => {
                "the dataset has no rendered image; use source \"auto\", \"cpu\" or \"gpu\" to path-trace one"
            }
            ImageSource::Traced(_) if no_scene => "there is no scene (triangles table) to trace from",
            ImageSource::Auto if no_scene && self.recorded.is_none() => {
                "there is no image and no scene (triangles table) to trace one from"
            }
            _ => return Ok(()),
        };
        Err(Error::Layer { layer: "image".into(), message: message.into() })
    }

    /// Whether the layer shows a traced picture at `camera` (else the recorded one).
    fn traces_at(&self, sources: &Sources, camera: &crate::camera::ViewCamera) -> bool {
        match self.settings.source {
            ImageSource::Dataset => false,
            ImageSource::Traced(_) => true,
            ImageSource::Auto => sources.scene.is_some() && !(self.recorded.is_some() && at_recorded(sources, camera)),
        }
    }

    /// Samples per pixel accumulated by the progressive tracer.
    pub fn spp(&self) -> u32 {
        self.progressive.as_ref().map_or(0, |p| p.spp)
    }

    /// The GPU tracer of `p` for `scene`, made on first use; `None` (and the reason kept in
    /// `p.gpu_failed`) where the adapter cannot run it.
    fn gpu_tracer<'p>(p: &'p mut ViewTrace, gpu: &Gpu, scene: &renderers::Scene) -> Option<&'p mut GpuImage> {
        if p.gpu.is_none() && p.gpu_failed.is_none() {
            match gpu_tracer::GpuTracer::with_gpu(gpu, scene, &p.bvh) {
                Ok(tracer) => p.gpu = Some(GpuImage { tracer, batch: 1, halves: None, next_curve: 2 }),
                Err(e) => p.gpu_failed = Some(e.to_string()),
            }
        }
        p.gpu.as_mut()
    }
}

/// Whether `source` traces on the GPU where the adapter allows.
fn on_gpu_source(source: ImageSource) -> bool {
    matches!(source, ImageSource::Traced(TracerChoice::Gpu) | ImageSource::Auto)
}

/// The estimated RMSE of the mean of `n` samples, from the sums of all samples and of the even
/// ones: the two half means differ by noise of variance σ²(1/ne + 1/no) per value, the whole
/// mean has σ²/n. `None` before there are two samples. Non-finite values (fireflies gone wrong)
/// are left out.
pub fn half_difference_rmse(sum: &[glam::Vec3A], even: &[glam::Vec3A], n: u32) -> Option<f64> {
    if n < 2 {
        return None;
    }
    let ne = f64::from(n.div_ceil(2));
    let no = f64::from(n / 2);
    let (mut se, mut count) = (0.0f64, 0u64);
    for (s, e) in sum.iter().zip(even) {
        for c in 0..3 {
            let (s, e) = (f64::from(s[c]), f64::from(e[c]));
            let d = e / ne - (s - e) / no;
            if d.is_finite() {
                se += d * d;
                count += 1;
            }
        }
    }
    if count == 0 {
        return None;
    }
    let diff_ms = se / count as f64;
    Some((diff_ms / f64::from(n) / (1.0 / ne + 1.0 / no)).sqrt())
}

/// One idle step of the GPU tracer: two equal batches of k samples (one counted as the even
/// samples, one as the odd) over the view; the samples then taken in all, the step's seconds,
/// and a point of the convergence curve when the halves were read back (once per doubling).
/// `None` when the halves could not be made.
fn gpu_samples(
    g: &mut GpuImage,
    ctx: &IdleCtx,
    camera: renderers::Camera,
    spp: u32,
    max_spp: u32,
    t0: std::time::Instant,
) -> Result<Option<(u32, f64, Option<f64>)>> {
    let gpu_err = |e: gpu_tracer::Error| Error::Layer { layer: "image".into(), message: e.to_string() };
    // Two equal batches of k samples: one counts as the even samples, one as the odd.
    g.tracer.set_camera(camera);
    let k = g.batch.min((max_spp - spp).div_ceil(2)).max(1);
    if g.halves.is_none() {
        let depth = renderers::RenderOptions::default().max_depth;
        let half = |seed| g.tracer.progressive(ctx.width, ctx.height, seed, depth).map_err(gpu_err);
        g.halves = Some([half(0)?, half(1)?]);
    }
    let Some(halves) = g.halves.as_mut() else { return Ok(None) };
    for h in halves.iter_mut() {
        g.tracer.accumulate(h, k);
    }
    let n = spp + 2 * k;
    // The convergence curve: the halves read back once per doubling of the samples.
    let mut point = None;
    if n >= g.next_curve || n >= max_spp {
        // Each half's per-pixel sums (RGB and the sample count), as accumulated.
        let sums = |h: &gpu_tracer::Accumulation| {
            let buf = h.accumulation();
            g.tracer.gpu().read_values::<[f32; 4]>(buf, buf.size())
        };
        let rgb = |s: &[f32; 4]| glam::Vec3A::new(s[0], s[1], s[2]);
        let (even, odd) = (sums(&halves[0])?, sums(&halves[1])?);
        let ev: Vec<glam::Vec3A> = even.iter().map(rgb).collect();
        let sum: Vec<glam::Vec3A> = ev.iter().zip(&odd).map(|(e, o)| *e + rgb(o)).collect();
        point = half_difference_rmse(&sum, &ev, n);
        while g.next_curve <= n {
            g.next_curve *= 2;
        }
    } else {
        // Nothing read back: wait for the work so the batch size follows its time.
        ctx.gpu.wait()?;
    }
    // Aim at about 50 ms per idle call.
    let took = t0.elapsed().as_secs_f64();
    g.batch = if took < 0.025 {
        (k * 2).min(256)
    } else if took > 0.1 {
        (k / 2).max(1)
    } else {
        k
    };
    Ok(Some((n, took, point)))
}

/// One idle step of a CPU tracer: one more sample of every pixel added to the sums (and to the
/// even samples' sums), a point of the convergence curve, and the average so far as a picture.
fn cpu_sample(
    p: &mut ViewTrace,
    ctx: &IdleCtx,
    scene: &Arc<renderers::Scene>,
    camera: renderers::Camera,
    settings: &ImageSettings,
    t0: std::time::Instant,
) -> Result<Picture> {
    let opts = renderers::RenderOptions {
        width: ctx.width,
        height: ctx.height,
        spp: 1,
        seed: u64::from(p.spp),
        ..Default::default()
    };
    let choice = settings.source.cpu_tracer();
    if p.cpu.as_ref().is_none_or(|t| t.choice() != choice) {
        p.cpu = Some(
            renderers::tracer(choice, scene.clone(), p.bvh.clone())
                .map_err(|e| Error::Layer { layer: "image".into(), message: format!("tracer \"{choice}\": {e}") })?,
        );
    }
    let Some(tracer) = p.cpu.as_mut() else {
        return Err(Error::Layer { layer: "image".into(), message: "no CPU tracer".into() });
    };
    tracer.set_camera(camera);
    let (film, _) = tracer.render(&opts, None, &|_| {})?;
    if p.sum.is_empty() {
        p.sum = vec![glam::Vec3A::ZERO; film.pixels.len()];
        p.even = p.sum.clone();
    }
    for (a, b) in p.sum.iter_mut().zip(&film.pixels) {
        *a += *b;
    }
    if p.spp.is_multiple_of(2) {
        for (a, b) in p.even.iter_mut().zip(&film.pixels) {
            *a += *b;
        }
    }
    p.spp += 1;
    p.secs += t0.elapsed().as_secs_f64();
    if let Some(rmse) = half_difference_rmse(&p.sum, &p.even, p.spp) {
        p.curve.push(crate::component::ConvergencePoint { secs: p.secs, spp: p.spp, rmse });
    }
    let n = p.spp as f32;
    let avg = renderers::Film { width: ctx.width, height: ctx.height, pixels: p.sum.iter().map(|v| *v / n).collect() };
    Ok(Picture { width: ctx.width, height: ctx.height, rgba: avg.to_srgb8(settings.exposure, 4) })
}

impl Layer for Image {
    type Settings = ImageSettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Flat
    }
    fn uses_camera(&self) -> bool {
        self.settings.source != ImageSource::Dataset
    }
    fn generation(&self) -> u64 {
        self.generation
    }
    fn current(&self) -> &ImageSettings {
        &self.settings
    }
    fn apply(&mut self, s: ImageSettings) -> Result<()> {
        if !((0.0..=1.0).contains(&s.opacity) && s.exposure.is_finite() && s.exposure > 0.0) {
            return Err(Error::Settings("image: opacity must be in 0..1 and exposure positive".into()));
        }
        if s != self.settings {
            if s.source != self.settings.source || s.exposure != self.settings.exposure {
                self.texture = None;
            }
            if s.source != self.settings.source {
                // Another tracer: a new image.
                self.progressive = None;
                self.traced = None;
            }
            self.settings = s;
            self.generation += 1;
        }
        Ok(())
    }
    fn idle(&mut self, ctx: &mut IdleCtx) -> Result<bool> {
        self.shown_traced = self.traces_at(ctx.sources, ctx.camera);
        if !self.shown_traced {
            return Ok(false);
        }
        let Some(scene) = &ctx.sources.scene else { return Ok(false) };
        let key = (*ctx.camera, ctx.width, ctx.height);
        let p = self.progressive.get_or_insert_with(|| ViewTrace {
            bvh: Arc::new(renderers::Bvh::build(&scene.tris)),
            sum: Vec::new(),
            even: Vec::new(),
            spp: 0,
            secs: 0.0,
            curve: Vec::new(),
            key: None,
            gpu: None,
            gpu_failed: None,
            cpu: None,
        });
        if p.key != Some(key) {
            p.key = Some(key);
            p.sum.clear();
            p.even.clear();
            p.spp = 0;
            p.secs = 0.0;
            p.curve.clear();
            if let Some(g) = p.gpu.as_mut() {
                g.halves = None;
                g.next_curve = 2;
            }
            self.traced = None;
        }
        if p.spp >= self.settings.max_spp {
            return Ok(false);
        }
        let camera = renderers::Camera::from(ctx.camera);
        let t0 = std::time::Instant::now();
        let on_gpu = on_gpu_source(self.settings.source);
        let max_spp = self.settings.max_spp;
        let (spp, secs) = (p.spp, p.secs);
        if let Some(g) = on_gpu.then(|| Self::gpu_tracer(p, ctx.gpu, scene)).flatten() {
            let Some((n, took, point)) = gpu_samples(g, ctx, camera, spp, max_spp, t0)? else { return Ok(false) };
            p.spp = n;
            p.secs = secs + took;
            if let Some(rmse) = point {
                p.curve.push(crate::component::ConvergencePoint { secs: p.secs, spp: p.spp, rmse });
            }
        } else {
            self.traced = Some(cpu_sample(p, ctx, scene, camera, &self.settings, t0)?);
        }
        self.generation += 1;
        Ok(true)
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        let traced = self.traces_at(ctx.sources, ctx.camera);
        self.shown_traced = traced;
        if traced
            && let Some(p) = &self.progressive
            && p.key == Some((*ctx.camera, ctx.target.width, ctx.target.height))
            && let Some(halves) = p.gpu.as_ref().and_then(|g| g.halves.as_ref())
        {
            let f = self.film.get_or_insert_with(|| FilmDrawer::new(ctx.gpu));
            f.draw(ctx, halves, self.settings.exposure, self.settings.opacity);
            return Ok(());
        }
        // A traced picture only for the view it was traced from: never one misregistered.
        let pic = if traced {
            self.traced
                .as_ref()
                .filter(|t| self.progressive.as_ref().is_some_and(|p| p.key == Some((*ctx.camera, t.width, t.height))))
        } else {
            self.recorded.as_ref()
        };
        let Some(pic) = pic else {
            crate::draw::clear_layer(ctx.gpu, ctx.target);
            return Ok(());
        };
        if self.texture.as_ref().is_none_or(|(t, g, _)| *t != traced || *g != self.generation) {
            self.texture =
                Some((traced, self.generation, ctx.gpu.rgba_texture("image", pic.width, pic.height, &pic.rgba)));
        }
        let b = self.blitter.get_or_insert_with(|| Blitter::new(ctx.gpu));
        if let Some((_, _, t)) = &self.texture {
            b.draw(ctx, t, self.settings.opacity);
        }
        Ok(())
    }
    fn resize(&mut self, width: u32, height: u32) {
        self.size = [width, height];
    }
    fn convergence(&self) -> Vec<crate::component::ConvergencePoint> {
        self.progressive.as_ref().map_or_else(Vec::new, |p| p.curve.clone())
    }
    fn report(&self) -> Vec<String> {
        let Some(p) = &self.progressive else { return Vec::new() };
        let mut r = Vec::new();
        if let Some(why) = &p.gpu_failed
            && on_gpu_source(self.settings.source)
        {
            r.push(format!("image: the GPU tracer cannot run here ({why}); tracing on the CPU"));
        }
        if self.shown_traced && p.spp > 0 {
            let on = if p.gpu.is_some() { " on the GPU" } else { "" };
            r.push(format!("image: path traced{on}, {} samples per pixel", p.spp));
        }
        r
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HeatmapSettings {
    /// A query with columns `pixel_x`, `pixel_y` and one numeric value column (the third).
    pub sql: String,
    /// Title of the colour bar.
    pub title: String,
    /// Colour map name (viridis, magma, inferno, plasma, turbo, cividis).
    pub map: String,
    pub opacity: f32,
}

impl crate::component::Settings for HeatmapSettings {
    const KIND: &'static str = "heatmap";
}

impl Default for HeatmapSettings {
    fn default() -> Self {
        HeatmapSettings {
            sql: "SELECT pixel_x, pixel_y, count(*) AS rays FROM rays GROUP BY pixel_x, pixel_y".into(),
            title: "rays per pixel".into(),
            map: "viridis".into(),
            opacity: 0.85,
        }
    }
}

/// The heatmap layer.
pub struct Heatmap {
    id: ComponentId,
    settings: HeatmapSettings,
    generation: u64,
    size: [u32; 2],
    image: Option<(u64, wgpu::Texture)>,
    range: Option<(f64, f64)>,
    blitter: Option<Blitter>,
}

impl Heatmap {
    pub fn new(id: ComponentId, sources: &Sources, settings: &serde_json::Value) -> Result<Heatmap> {
        if !sources.has_rays() {
            return Err(Error::Layer { layer: "heatmap".into(), message: "no dataset is loaded".into() });
        }
        let mut h = Heatmap {
            id,
            settings: HeatmapSettings::default(),
            generation: 0,
            size: sources.image_size,
            image: None,
            range: None,
            blitter: None,
        };
        if !settings.is_null() {
            h.set_settings(settings)?;
        }
        Ok(h)
    }

    fn compute(&mut self, sources: &Sources) -> Result<Vec<u8>> {
        let [w, h] = self.size;
        let mut grid = vec![f64::NAN; w as usize * h as usize];
        let batches = sources.query(&self.settings.sql)?;
        for b in &batches {
            let s = b.schema();
            let need = |n: &str| {
                s.index_of(n).map_err(|_| {
                    Error::Columns(format!(
                        "the heatmap query must return pixel_x, pixel_y and a value column; `{n}` is missing (columns: {})",
                        s.fields().iter().map(|f| f.name().as_str()).collect::<Vec<_>>().join(", ")
                    ))
                })
            };
            let (ix, iy) = (need("pixel_x")?, need("pixel_y")?);
            let iv = (0..b.num_columns()).find(|&i| i != ix && i != iy).ok_or_else(|| {
                Error::Columns("the heatmap query has no value column besides pixel_x, pixel_y".into())
            })?;
            let cast = |i: usize, t: &DataType| arrow::compute::cast(b.column(i), t);
            let (x, y) = (cast(ix, &DataType::UInt32)?, cast(iy, &DataType::UInt32)?);
            let v = cast(iv, &DataType::Float64)
                .map_err(|e| Error::Columns(format!("value column `{}` is not numeric: {e}", s.field(iv).name())))?;
            let (x, y, v) =
                (x.as_primitive::<UInt32Type>(), y.as_primitive::<UInt32Type>(), v.as_primitive::<Float64Type>());
            for r in 0..b.num_rows() {
                if x.is_null(r) || y.is_null(r) || v.is_null(r) {
                    continue;
                }
                let (px, py) = (x.value(r), y.value(r));
                if px < w && py < h && v.value(r).is_finite() {
                    grid[(py * w + px) as usize] = v.value(r);
                }
            }
        }
        let (lo, hi) = grid
            .iter()
            .filter(|v| v.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
        self.range = (lo <= hi).then_some((lo, hi));
        let map = colour_map(&self.settings.map)?;
        let mut rgba = vec![0u8; grid.len() * 4];
        for (i, v) in grid.iter().enumerate() {
            if v.is_finite() {
                let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.5 };
                let c = map.eval_continuous(t.clamp(0.0, 1.0));
                rgba[i * 4..i * 4 + 4].copy_from_slice(&[c.r, c.g, c.b, 255]);
            }
        }
        Ok(rgba)
    }
}

impl Layer for Heatmap {
    type Settings = HeatmapSettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Flat
    }
    fn generation(&self) -> u64 {
        self.generation
    }
    fn current(&self) -> &HeatmapSettings {
        &self.settings
    }
    fn apply(&mut self, s: HeatmapSettings) -> Result<()> {
        colour_map(&s.map)?;
        if !(0.0..=1.0).contains(&s.opacity) {
            return Err(Error::Settings("heatmap: opacity must be in 0..1".into()));
        }
        if crate::component::replace_settings(&mut self.settings, s, &mut self.generation) {
            self.image = None;
        }
        Ok(())
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        if self.image.as_ref().is_none_or(|(g, _)| *g != self.generation) {
            let rgba = self.compute(ctx.sources)?;
            let [w, h] = self.size;
            self.image = Some((self.generation, ctx.gpu.rgba_texture("heatmap", w, h, &rgba)));
        }
        let b = self.blitter.get_or_insert_with(|| Blitter::new(ctx.gpu));
        if let Some((_, t)) = &self.image {
            b.draw(ctx, t, self.settings.opacity);
        }
        Ok(())
    }
    fn legend(&self) -> Vec<Legend> {
        match self.range {
            Some((min, max)) => {
                vec![Legend::ColourBar {
                    title: self.settings.title.clone(),
                    map: self.settings.map.clone(),
                    min,
                    max,
                    log: false,
                }]
            }
            None => Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::half_difference_rmse;

    #[test]
    fn the_half_difference_estimates_the_error_of_the_mean() {
        // Values 0.5 ± 0.2 uniform noise (σ = 0.2/√3) per sample: the mean of n samples has an
        // error of σ/√n, which the estimate must find within 10 % over 20k values.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f32 / (1u64 << 53) as f32
        };
        let sigma = 0.2 / 3f64.sqrt(); // uniform on [-0.2, 0.2)
        for n in [2u32, 3, 8, 33] {
            let px = 7000;
            let mut sum = vec![glam::Vec3A::ZERO; px];
            let mut even = vec![glam::Vec3A::ZERO; px];
            for k in 0..n {
                for i in 0..px {
                    let v = glam::Vec3A::new(rnd(), rnd(), rnd()) * 0.4 + glam::Vec3A::splat(0.3);
                    sum[i] += v;
                    if k % 2 == 0 {
                        even[i] += v;
                    }
                }
            }
            let want = sigma / f64::from(n).sqrt();
            let got = half_difference_rmse(&sum, &even, n).unwrap();
            assert!((got / want - 1.0).abs() < 0.1, "n = {n}: estimated {got}, true {want}");
        }
        assert_eq!(half_difference_rmse(&[glam::Vec3A::ONE], &[glam::Vec3A::ONE], 1), None);
        // Non-finite values are left out, not spread over the estimate.
        let sum = [glam::Vec3A::new(f32::NAN, 1.0, 1.0), glam::Vec3A::ONE];
        let even = [glam::Vec3A::new(f32::INFINITY, 0.5, 0.5), glam::Vec3A::splat(0.5)];
        assert_eq!(half_difference_rmse(&sum, &even, 2), Some(0.0));
    }
}
