//! The component trait (the paper's pipeline component, Section 3.1) and what a component is
//! given to do its work.

use serde::{Deserialize, Serialize};

use crate::camera::ViewCamera;
use crate::sources::Sources;
use crate::{Error, Result};
use rtvtk_gpu::Gpu;

/// A component's stable id within a pipeline (kept across reorders, saved with the layout).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct ComponentId(pub u64);

/// What a component's layer holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LayerRole {
    /// A picture in image space (path-traced image, heatmap): drawn without a depth test.
    Flat,
    /// Colour and depth in scene space: hidden behind the occluder below it.
    Scene,
    /// Depth only: the occluder of the scene-space layers above it (2D/3D composition).
    Occluder,
}

/// The render target of one layer.
pub struct LayerTarget {
    pub color: wgpu::Texture,
    pub color_view: wgpu::TextureView,
    pub depth: wgpu::Texture,
    pub depth_view: wgpu::TextureView,
    pub width: u32,
    pub height: u32,
}

impl LayerTarget {
    pub fn new(gpu: &Gpu, label: &str, width: u32, height: u32) -> LayerTarget {
        let color = gpu.target(label, crate::formats::COLOR_FORMAT, width, height);
        let depth = gpu.target(label, crate::formats::DEPTH_FORMAT, width, height);
        LayerTarget {
            color_view: color.create_view(&Default::default()),
            depth_view: depth.create_view(&Default::default()),
            color,
            depth,
            width,
            height,
        }
    }
}

pub use crate::camera::Frame;

/// Arguments of [`Component::render`].
pub struct RenderCtx<'a> {
    pub gpu: &'a Gpu,
    pub sources: &'a Sources,
    pub camera: &'a ViewCamera,
    pub frame: Frame,
    pub target: &'a LayerTarget,
    /// Where a long load reports how far it got, and learns it was cancelled.
    pub progress: &'a Progress,
    /// Draw at most this many items, evenly spread (a preview while the camera moves).
    pub preview: Option<u64>,
    /// The scene's depth below this layer (the nearest occluder layer under it), for layers that
    /// hide their items behind surfaces as they draw them (the alpha and density ray styles).
    pub occluder: Option<OccluderRef<'a>>,
}

/// An occluder layer's depth as another layer reads it.
#[derive(Clone, Copy)]
pub struct OccluderRef<'a> {
    /// Its Depth32Float target (bound as an unfilterable float texture).
    pub depth: &'a wgpu::TextureView,
    /// Its near and far planes.
    pub range: [f32; 2],
}

/// How far a layer's long load (millions of rays) has got, shared with another thread (the
/// viewer's status bar), which may cancel it: the layer then keeps what it loaded so far.
#[derive(Debug, Default)]
pub struct Progress {
    done: std::sync::atomic::AtomicU64,
    total: std::sync::atomic::AtomicU64,
    cancel: std::sync::atomic::AtomicBool,
    what: std::sync::Mutex<String>,
}

impl Progress {
    /// A load of `total` items begins (a cancel asked for before still holds: see `reset`).
    pub fn start(&self, what: &str, total: u64) {
        use std::sync::atomic::Ordering::SeqCst;
        if let Ok(mut w) = self.what.lock() {
            *w = what.to_string();
        }
        self.done.store(0, SeqCst);
        self.total.store(total.max(1), SeqCst);
    }
    /// `n` more items done; false once the load was cancelled.
    pub fn advance(&self, n: u64) -> bool {
        use std::sync::atomic::Ordering::SeqCst;
        self.done.fetch_add(n, SeqCst);
        !self.cancel.load(SeqCst)
    }
    /// The load ended (finished or cancelled).
    pub fn finish(&self) {
        self.total.store(0, std::sync::atomic::Ordering::SeqCst);
    }
    /// Forgets a cancel (the viewer's render thread does so when new commands arrive).
    pub fn reset(&self) {
        self.cancel.store(false, std::sync::atomic::Ordering::SeqCst);
    }
    /// Asks the running load (and any that starts before `reset`) to stop.
    pub fn cancel(&self) {
        self.cancel.store(true, std::sync::atomic::Ordering::SeqCst);
    }
    /// What is loading, items done and total, while a load runs.
    pub fn get(&self) -> Option<(String, u64, u64)> {
        use std::sync::atomic::Ordering::SeqCst;
        let total = self.total.load(SeqCst);
        (total > 0).then(|| {
            let what = self.what.lock().map(|w| w.clone()).unwrap_or_default();
            (what, self.done.load(SeqCst).min(total), total)
        })
    }
}

impl RenderCtx<'_> {
    /// The view-projection matrix of this layer's camera and size.
    pub fn view_proj(&self) -> glam::Mat4 {
        self.camera.view_proj_f32(self.frame.anchor, self.frame.radius, self.target.width, self.target.height)
    }

    /// Near and far distances of the projection (for depth composition).
    pub fn depth_range(&self) -> [f32; 2] {
        depth_range(self.camera, self.frame)
    }
}

/// Near and far planes `ViewCamera::view_proj` uses for this camera and frame.
pub fn depth_range(camera: &ViewCamera, frame: Frame) -> [f32; 2] {
    camera.planes(frame.anchor, frame.radius).map(|v| v as f32)
}

/// Arguments of [`Component::idle`].
pub struct IdleCtx<'a> {
    /// The pipeline's device (the GPU tracer traces on it).
    pub gpu: &'a Gpu,
    pub sources: &'a Sources,
    pub camera: &'a ViewCamera,
    pub width: u32,
    pub height: u32,
}

/// Arguments of [`Component::trace_ray`].
pub struct TraceCtx<'a> {
    pub gpu: &'a Gpu,
    pub sources: &'a Sources,
    pub camera: &'a ViewCamera,
    pub width: u32,
    pub height: u32,
}

/// The small target a pick draws into: ids ([`crate::formats::PICK_FORMAT`]) and depth, `size`
/// pixels square around the cursor, shared by every pickable layer so the nearest item wins.
pub struct PickTarget {
    pub ids: wgpu::Texture,
    pub ids_view: wgpu::TextureView,
    pub depth_view: wgpu::TextureView,
    pub size: u32,
}

impl PickTarget {
    pub fn new(gpu: &Gpu, size: u32) -> PickTarget {
        let ids = gpu.target("pick ids", crate::formats::PICK_FORMAT, size, size);
        let depth = gpu.target("pick depth", crate::formats::DEPTH_FORMAT, size, size);
        PickTarget {
            ids_view: ids.create_view(&Default::default()),
            depth_view: depth.create_view(&Default::default()),
            ids,
            size,
        }
    }

    /// A pass that keeps what earlier layers drew (the pipeline clears the target once).
    pub fn pass<'e>(&self, enc: &'e mut wgpu::CommandEncoder) -> wgpu::RenderPass<'e> {
        self.pass_with(enc, wgpu::LoadOp::Load, wgpu::LoadOp::Load)
    }

    pub(crate) fn pass_with<'e>(
        &self,
        enc: &'e mut wgpu::CommandEncoder,
        ids: wgpu::LoadOp<wgpu::Color>,
        depth: wgpu::LoadOp<f32>,
    ) -> wgpu::RenderPass<'e> {
        enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("pick"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &self.ids_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations { load: ids, store: wgpu::StoreOp::Store },
            })],
            depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                view: &self.depth_view,
                depth_ops: Some(wgpu::Operations { load: depth, store: wgpu::StoreOp::Store }),
                stencil_ops: None,
            }),
            timestamp_writes: None,
            occlusion_query_set: None,
            multiview_mask: None,
        })
    }
}

/// Arguments of [`Component::pick`]: draw the ids of what can be picked.
pub struct PickCtx<'a> {
    pub gpu: &'a Gpu,
    pub sources: &'a Sources,
    /// The layer's view-projection, cropped to the pick target around the cursor.
    pub view_proj: glam::Mat4,
    pub target: &'a PickTarget,
    /// The layer's slot, written with every id (`ViewUniform::params.x` of the pick draw).
    pub slot: u32,
}

impl PickCtx<'_> {
    /// The uniform block of a pick draw: the cropped projection, the target's size (so line
    /// widths stay in pixels) and the slot.
    pub fn view(&self, line_width: f32) -> crate::camera::ViewUniform {
        let mut v =
            crate::camera::ViewUniform::new(self.view_proj, self.target.size, self.target.size, line_width, 1.0, 0.0);
        v.params[0] = self.slot as f32;
        // Every segment (no preview stride).
        v.params[1] = 1.0;
        v
    }
}

/// What a layer's item is (a component's answer to [`Component::picked`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Picked {
    /// A recorded ray: its tree and index in the tree.
    Ray { tree: u64, ray: u32 },
    /// A ray traced in immediate mode: its pixel, its tree in the live trace and its index.
    Traced { pixel: [u32; 2], tree: u64, ray: u32 },
    /// A BVH node.
    Node { node: u64 },
    /// A row of a query layer's result (0-based).
    Row { row: u64 },
}

impl Picked {
    /// The item in words.
    pub fn label(&self) -> String {
        match *self {
            Picked::Ray { tree, ray } => format!("ray {ray} of tree {tree}"),
            Picked::Traced { pixel: [x, y], tree, ray } => {
                format!("traced ray {ray} of pixel {x},{y} (immediate mode, tree {tree} of the live trace)")
            }
            Picked::Node { node } => format!("BVH node {node}"),
            Picked::Row { row } => format!("row {row} of the query"),
        }
    }
}

/// What a click picked: the layer, the item's index in its pick drawing, and the item.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Pick {
    pub layer: ComponentId,
    pub index: u32,
    pub item: Picked,
}

/// What a trace of one pixel produced (immediate mode).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TracedPixel {
    pub pixel: [u32; 2],
    pub rays: usize,
}

/// An entry of a picture's legend.
#[derive(Clone, Debug, PartialEq)]
pub enum Legend {
    /// Named colours (ray kinds, materials).
    Swatches { title: String, entries: Vec<(String, [u8; 4])> },
    /// A colour map from `min` to `max` of a value (on a log scale when `log`); `min == max`
    /// is a constant, drawn as one swatch with its value.
    ColourBar { title: String, map: String, min: f64, max: f64, log: bool },
}

/// One component of the pipeline: it owns its data and draws into its own layer.
///
/// Settings are plain serializable data ([`Component::settings`] / [`Component::set_settings`]);
/// a component bumps its [`Component::generation`] whenever its output would change, so the
/// compositor re-renders only layers whose generation, camera or size changed.
pub trait Component: Send {
    fn id(&self) -> ComponentId;
    /// The registry name of the component's kind (`rays`, `geometry`, ...).
    fn kind(&self) -> &'static str;
    fn display_name(&self) -> String {
        self.kind().to_string()
    }
    fn role(&self) -> LayerRole;
    /// Whether the output depends on the camera (flat pictures of the dataset's image do not).
    fn uses_camera(&self) -> bool {
        self.role() != LayerRole::Flat
    }
    /// Whether the layer draws a cheaper preview when `RenderCtx::preview` asks for one (and so
    /// is drawn again in full once the camera stops).
    fn previews(&self) -> bool {
        false
    }
    /// Counter bumped on every change of output (settings, data, progressive refinement).
    fn generation(&self) -> u64;
    /// Whether the layer hides its items behind the occluder's depth as it draws them (the alpha
    /// and density ray styles), and so is drawn again when the occluder is.
    fn reads_occluder(&self) -> bool {
        false
    }
    fn settings(&self) -> serde_json::Value;
    /// The settings that take one of a few values, with those values (the viewer draws them as
    /// drop-downs, not text fields).
    fn choices(&self) -> Vec<(&'static str, &'static [&'static str])> {
        Vec::new()
    }
    fn set_settings(&mut self, settings: &serde_json::Value) -> Result<()>;
    /// Progressive work between frames; returns whether the output changed.
    fn idle(&mut self, _ctx: &mut IdleCtx) -> Result<bool> {
        Ok(false)
    }
    /// Draws into the layer (cleared by the pipeline before).
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()>;
    /// The layer's size changed.
    fn resize(&mut self, _width: u32, _height: u32) {}
    /// Immediate mode: trace the ray tree of a pixel and show it. `Ok(None)` when the component
    /// does not trace.
    fn trace_ray(&mut self, _ctx: &mut TraceCtx, _pixel: [u32; 2]) -> Result<Option<TracedPixel>> {
        Ok(None)
    }
    /// Picking: draws the ids of the layer's items into `ctx.target`; `Ok(false)` when the layer
    /// has nothing to pick.
    fn pick(&mut self, _ctx: &mut PickCtx) -> Result<bool> {
        Ok(false)
    }
    /// What item `index` of the last pick drawing is.
    fn picked(&self, _index: u32) -> Option<Picked> {
        None
    }
    fn legend(&self) -> Vec<Legend> {
        Vec::new()
    }
    /// Facts worth printing (segments drawn, rays skipped, what is missing).
    fn report(&self) -> Vec<String> {
        Vec::new()
    }
    /// How a progressive layer's error fell with time (empty for other layers).
    fn convergence(&self) -> Vec<ConvergencePoint> {
        Vec::new()
    }
}

/// One step of a progressive layer: time spent refining so far, samples per pixel, and the
/// image's estimated error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConvergencePoint {
    pub secs: f64,
    pub spp: u32,
    /// Estimated RMSE of the mean image (linear radiance, over pixels and channels), from the
    /// difference of the even- and odd-sample half images: needs no reference image.
    pub rmse: f64,
}

/// A component kind's settings: plain data that the pipeline, saved layouts and the viewer's
/// commands carry as JSON, decoded and encoded by these two functions only, so code that
/// changes a setting names its field (a renamed field does not compile) and a bad value names
/// the kind.
pub trait Settings: Serialize + serde::de::DeserializeOwned + Default + Clone + PartialEq {
    /// The registry name of the component kind.
    const KIND: &'static str;

    /// From JSON (null: the defaults).
    fn decode(v: &serde_json::Value) -> Result<Self> {
        if v.is_null() { Ok(Self::default()) } else { decode_settings(Self::KIND, v) }
    }

    /// To JSON.
    fn encode(&self) -> serde_json::Value {
        serde_json::to_value(self).unwrap_or_default()
    }

    /// The settings that take one of a few values, with those values (the viewer draws them as
    /// drop-downs, not text fields).
    fn choices() -> Vec<(&'static str, &'static [&'static str])> {
        Vec::new()
    }
}

/// A component written against its typed settings. [`Component`], the object-safe trait the
/// pipeline holds, is implemented once for every `Layer`: its kind is its settings' `KIND`, and
/// its settings cross as JSON through `Settings::decode` and `encode`, so a component says only
/// what is its own (the methods below mean what [`Component`]'s of the same names do).
pub trait Layer: Send {
    type Settings: Settings;
    fn id(&self) -> ComponentId;
    fn role(&self) -> LayerRole;
    fn generation(&self) -> u64;
    fn reads_occluder(&self) -> bool {
        false
    }
    /// Its settings now.
    fn current(&self) -> &Self::Settings;
    /// Checks and takes `settings` (bumping the generation when the output changes); on an error
    /// the old settings stay.
    fn apply(&mut self, settings: Self::Settings) -> Result<()>;
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()>;
    fn uses_camera(&self) -> bool {
        self.role() != LayerRole::Flat
    }
    fn previews(&self) -> bool {
        false
    }
    fn idle(&mut self, _ctx: &mut IdleCtx) -> Result<bool> {
        Ok(false)
    }
    fn resize(&mut self, _width: u32, _height: u32) {}
    fn trace_ray(&mut self, _ctx: &mut TraceCtx, _pixel: [u32; 2]) -> Result<Option<TracedPixel>> {
        Ok(None)
    }
    fn pick(&mut self, _ctx: &mut PickCtx) -> Result<bool> {
        Ok(false)
    }
    fn picked(&self, _index: u32) -> Option<Picked> {
        None
    }
    fn legend(&self) -> Vec<Legend> {
        Vec::new()
    }
    fn report(&self) -> Vec<String> {
        Vec::new()
    }
    fn convergence(&self) -> Vec<ConvergencePoint> {
        Vec::new()
    }
}

impl<L: Layer> Component for L {
    fn id(&self) -> ComponentId {
        Layer::id(self)
    }
    fn kind(&self) -> &'static str {
        L::Settings::KIND
    }
    fn role(&self) -> LayerRole {
        Layer::role(self)
    }
    fn uses_camera(&self) -> bool {
        Layer::uses_camera(self)
    }
    fn previews(&self) -> bool {
        Layer::previews(self)
    }
    fn generation(&self) -> u64 {
        Layer::generation(self)
    }
    fn reads_occluder(&self) -> bool {
        Layer::reads_occluder(self)
    }
    fn settings(&self) -> serde_json::Value {
        self.current().encode()
    }
    fn choices(&self) -> Vec<(&'static str, &'static [&'static str])> {
        L::Settings::choices()
    }
    fn set_settings(&mut self, settings: &serde_json::Value) -> Result<()> {
        self.apply(L::Settings::decode(settings)?)
    }
    fn idle(&mut self, ctx: &mut IdleCtx) -> Result<bool> {
        Layer::idle(self, ctx)
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        Layer::render(self, ctx)
    }
    fn resize(&mut self, width: u32, height: u32) {
        Layer::resize(self, width, height)
    }
    fn trace_ray(&mut self, ctx: &mut TraceCtx, pixel: [u32; 2]) -> Result<Option<TracedPixel>> {
        Layer::trace_ray(self, ctx, pixel)
    }
    fn pick(&mut self, ctx: &mut PickCtx) -> Result<bool> {
        Layer::pick(self, ctx)
    }
    fn picked(&self, index: u32) -> Option<Picked> {
        Layer::picked(self, index)
    }
    fn legend(&self) -> Vec<Legend> {
        Layer::legend(self)
    }
    fn report(&self) -> Vec<String> {
        Layer::report(self)
    }
    fn convergence(&self) -> Vec<ConvergencePoint> {
        Layer::convergence(self)
    }
}

/// Decodes a component's settings, naming the component on error.
pub fn decode_settings<T: serde::de::DeserializeOwned>(kind: &str, v: &serde_json::Value) -> Result<T> {
    serde_json::from_value(v.clone()).map_err(|e| Error::Settings(format!("{kind}: {e}")))
}

/// Replaces `current` with `new` when they differ, bumping `generation`; returns whether they did.
pub fn replace_settings<T: PartialEq>(current: &mut T, new: T, generation: &mut u64) -> bool {
    if *current == new {
        return false;
    }
    *current = new;
    *generation += 1;
    true
}

/// Checks the line width (pixels) and opacity shared by the line-drawing layers.
pub fn check_lines(kind: &str, line_width: f32, opacity: f32) -> Result<()> {
    if line_width > 0.0 && line_width <= 64.0 && (0.0..=1.0).contains(&opacity) {
        Ok(())
    } else {
        Err(Error::Settings(format!("{kind}: line_width must be in (0, 64] pixels and opacity in 0..1")))
    }
}

/// A [`renderers::TracerChoice`] as a setting: its name (`cpu` is read as `path`).
pub mod tracer_setting {
    use renderers::TracerChoice;
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(c: &TracerChoice, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(c.name())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<TracerChoice, D::Error> {
        String::deserialize(d)?.parse().map_err(serde::de::Error::custom)
    }
}
