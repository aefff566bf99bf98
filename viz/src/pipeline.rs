//! The pipeline: components in the user's order, each drawing into its own layer, and the
//! compositor that lays the layers over each other. A layer is re-rendered only when its
//! component's generation, its camera, its size or the scene frame changed (lazy evaluation);
//! hidden layers do no work.

use crate::camera::ViewCamera;
use crate::component::{
    Component, ComponentId, Frame, IdleCtx, LayerRole, LayerTarget, Legend, OccluderRef, Pick, PickCtx, PickTarget,
    RenderCtx, depth_range,
};
use crate::formats::COLOR_FORMAT;
use crate::legend::{Canvas, draw_legends};
use crate::sources::Sources;
use crate::{Error, Result};
use rtvtk_gpu::Gpu;

#[derive(Clone, Copy, Debug, PartialEq)]
struct RenderKey {
    generation: u64,
    camera: Option<ViewCamera>,
    size: [u32; 2],
    frame: Frame,
    /// The preview budget the layer was drawn with (only for layers that preview).
    preview: Option<u64>,
    /// The occluder under the layer and how often it was rendered (its depth hides the layer's
    /// items as they are drawn in the alpha and density styles).
    occluder: Option<(ComponentId, u64)>,
}

/// One layer: a component, whether it is shown, its own camera (when it does not follow the
/// pipeline's), its target and how often it was rendered.
pub struct Layer {
    pub component: Box<dyn Component>,
    pub enabled: bool,
    /// A camera of this layer only (`None`: the pipeline's camera).
    pub camera: Option<ViewCamera>,
    target: Option<LayerTarget>,
    key: Option<RenderKey>,
    range: [f32; 2],
    /// Times the component's `render` ran.
    pub renders: u64,
    /// Why the last render of this layer failed (a table it reads is broken): the layer is left
    /// empty and the others draw.
    failed: Option<String>,
}

impl Layer {
    /// Why this layer drew nothing at its last render, if it failed (a broken table, a refused
    /// query); `Pipeline::report` and the viewer's layer list say it.
    pub fn failed(&self) -> Option<&str> {
        self.failed.as_deref()
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct CompUniform {
    ranges: [f32; 4],
    params: [f32; 4],
}

struct Compositor {
    pipeline: wgpu::RenderPipeline,
    layout: wgpu::BindGroupLayout,
}

impl Compositor {
    fn new(gpu: &Gpu) -> Compositor {
        // Colour and both depths as unfilterable float textures (a Depth32Float texture may be
        // bound so): the shader loads texels, and GLSL has no texel load of a depth texture.
        let texture = |binding| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::FRAGMENT,
            ty: wgpu::BindingType::Texture {
                sample_type: wgpu::TextureSampleType::Float { filterable: false },
                view_dimension: wgpu::TextureViewDimension::D2,
                multisampled: false,
            },
            count: None,
        };
        let layout = gpu.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("composite"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                texture(1),
                texture(2),
                texture(3),
            ],
        });
        let pipeline_layout = gpu.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("composite"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let source = include_str!("shaders/composite.wgsl");
        let pipeline = crate::draw::fullscreen_pipeline(gpu, "composite", source, Some(&pipeline_layout), false);
        Compositor { pipeline, layout }
    }
}

/// The clip-space transform that maps the `size`-pixel square around `pixel` of a `view`-sized
/// image onto a whole target (rows top to bottom).
pub fn crop_matrix([x, y]: [u32; 2], [w, h]: [u32; 2], size: u32) -> glam::Mat4 {
    let cx = 2.0 * (x as f32 + 0.5) / w as f32 - 1.0;
    let cy = 1.0 - 2.0 * (y as f32 + 0.5) / h as f32;
    let (sx, sy) = (w as f32 / size as f32, h as f32 / size as f32);
    glam::Mat4::from_cols(
        glam::Vec4::new(sx, 0.0, 0.0, 0.0),
        glam::Vec4::new(0.0, sy, 0.0, 0.0),
        glam::Vec4::Z,
        glam::Vec4::new(-sx * cx, -sy * cy, 0.0, 1.0),
    )
}

/// A pipeline's work finishes before it goes: nothing it submitted still runs on the device
/// when its buffers are freed or the process exits (lavapipe's exit handlers tear down LLVM
/// while a queue thread may still be compiling a draw's shader variant).
impl Drop for Pipeline {
    fn drop(&mut self) {
        let _ = self.gpu.wait();
    }
}

/// The layered visualizer, headless: `render` composites into an offscreen texture, `snapshot`
/// reads it back with legends.
pub struct Pipeline {
    pub gpu: Gpu,
    pub sources: Sources,
    layers: Vec<Layer>,
    camera: ViewCamera,
    width: u32,
    height: u32,
    frame: Frame,
    output: wgpu::Texture,
    far: LayerTarget,
    compositor: Compositor,
    next_id: u64,
    /// Background colour (display values, opaque).
    pub background: [f64; 3],
    /// How far the running load has got; another thread may read it and cancel the load.
    pub progress: std::sync::Arc<crate::component::Progress>,
    /// While the camera moves (the viewer sets it): at most this many items per layer are drawn,
    /// spread evenly over the layer; `None` draws everything.
    pub preview: Option<u64>,
}

impl Pipeline {
    /// A pipeline with no layers, at the dataset's camera and image size.
    pub fn new(gpu: Gpu, sources: Sources) -> Pipeline {
        let [width, height] = sources.image_size;
        let camera = sources.initial_camera();
        let frame = sources.frame();
        let output = gpu.target("output", COLOR_FORMAT, width, height);
        let far = LayerTarget::new(&gpu, "far", width, height);
        crate::draw::clear_layer(&gpu, &far);
        let compositor = Compositor::new(&gpu);
        Pipeline {
            progress: Default::default(),
            preview: None,
            gpu,
            sources,
            layers: Vec::new(),
            camera,
            width,
            height,
            frame,
            output,
            far,
            compositor,
            next_id: 1,
            background: [0.02, 0.02, 0.025],
        }
    }

    /// Adds a component of a registered kind on top; returns its id.
    pub fn add(&mut self, kind: &str, settings: &serde_json::Value) -> Result<ComponentId> {
        let id = ComponentId(self.next_id);
        let c = crate::registry::make(kind, id, &self.sources, settings)?;
        self.next_id += 1;
        self.push(c);
        Ok(id)
    }

    /// Adds a component made elsewhere on top.
    pub fn push(&mut self, component: Box<dyn Component>) {
        self.next_id = self.next_id.max(component.id().0 + 1);
        self.layers.push(Layer {
            component,
            enabled: true,
            camera: None,
            target: None,
            key: None,
            range: [1.0, 2.0],
            renders: 0,
            failed: None,
        });
    }

    pub fn layers(&self) -> &[Layer] {
        &self.layers
    }

    pub fn layer_mut(&mut self, id: ComponentId) -> Result<&mut Layer> {
        self.layers
            .iter_mut()
            .find(|l| l.component.id() == id)
            .ok_or_else(|| Error::Settings(format!("no component with id {}", id.0)))
    }

    /// Removes a component.
    pub fn remove(&mut self, id: ComponentId) -> Result<Box<dyn Component>> {
        let i = self.index(id)?;
        Ok(self.layers.remove(i).component)
    }

    /// Moves a component to position `to` (0 = bottom).
    pub fn reorder(&mut self, id: ComponentId, to: usize) -> Result<()> {
        let i = self.index(id)?;
        let l = self.layers.remove(i);
        self.layers.insert(to.min(self.layers.len()), l);
        Ok(())
    }

    fn index(&self, id: ComponentId) -> Result<usize> {
        self.layers
            .iter()
            .position(|l| l.component.id() == id)
            .ok_or_else(|| Error::Settings(format!("no component with id {}", id.0)))
    }

    pub fn camera(&self) -> ViewCamera {
        self.camera
    }

    pub fn set_camera(&mut self, c: ViewCamera) -> Result<()> {
        c.validate().map_err(Error::Settings)?;
        self.camera = c;
        Ok(())
    }

    pub fn size(&self) -> [u32; 2] {
        [self.width, self.height]
    }

    /// Resizes every layer and the output.
    pub fn resize(&mut self, width: u32, height: u32) -> Result<()> {
        let max = self.gpu.device.limits().max_texture_dimension_2d;
        if width == 0 || height == 0 || width > max || height > max {
            return Err(Error::Settings(format!("size {width}x{height} must be between 1x1 and {max}x{max}")));
        }
        if [width, height] != [self.width, self.height] {
            self.width = width;
            self.height = height;
            self.output = self.gpu.target("output", COLOR_FORMAT, width, height);
            self.far = LayerTarget::new(&self.gpu, "far", width, height);
            crate::draw::clear_layer(&self.gpu, &self.far);
            for l in &mut self.layers {
                l.component.resize(width, height);
            }
        }
        Ok(())
    }

    /// Progressive work of every shown component; returns whether any output changed.
    pub fn idle(&mut self) -> Result<bool> {
        let mut changed = false;
        for l in self.layers.iter_mut().filter(|l| l.enabled) {
            let camera = l.camera.unwrap_or(self.camera);
            let mut ctx = IdleCtx {
                gpu: &self.gpu,
                sources: &self.sources,
                camera: &camera,
                width: self.width,
                height: self.height,
            };
            changed |= l.component.idle(&mut ctx)?;
        }
        Ok(changed)
    }

    /// Immediate mode: the component `id` traces the ray tree of `pixel` (of the pipeline's
    /// view) at its camera; `Ok(None)` when that component does not trace.
    pub fn trace_ray(&mut self, id: ComponentId, pixel: [u32; 2]) -> Result<Option<crate::component::TracedPixel>> {
        let (camera, width, height) = (self.camera, self.width, self.height);
        let i = self.index(id)?;
        let l = &mut self.layers[i];
        let camera = l.camera.unwrap_or(camera);
        let mut ctx =
            crate::component::TraceCtx { gpu: &self.gpu, sources: &self.sources, camera: &camera, width, height };
        l.component.trace_ray(&mut ctx, pixel)
    }

    /// Renders the layers that changed and composites all shown layers into the output: an
    /// `Rgba8Unorm` texture of display values (gamma space, as egui-wgpu's own textures are, so
    /// the viewer's window samples it as it is), the same texture until the size changes.
    pub fn render(&mut self) -> Result<&wgpu::Texture> {
        let size = [self.width, self.height];
        for i in 0..self.layers.len() {
            let (below, rest) = self.layers.split_at_mut(i);
            let Some(l) = rest.first_mut().filter(|l| l.enabled) else { continue };
            // The nearest occluder under a layer that reads it: its depth hides what the layer draws.
            let occluder = match l.component.reads_occluder() {
                true => below
                    .iter()
                    .rev()
                    .filter(|o| o.enabled)
                    .find(|o| o.component.role() == LayerRole::Occluder)
                    .and_then(|o| o.target.as_ref().map(|t| (o, t))),
                false => None,
            };
            let camera = l.camera.unwrap_or(self.camera);
            let key = RenderKey {
                generation: l.component.generation(),
                camera: l.component.uses_camera().then_some(camera),
                size,
                frame: self.frame,
                preview: self.preview.filter(|_| l.component.previews()),
                occluder: occluder.map(|(o, _)| (o.component.id(), o.renders)),
            };
            if l.key == Some(key) {
                continue;
            }
            if l.target.as_ref().is_none_or(|t| [t.width, t.height] != size) {
                l.target = Some(LayerTarget::new(&self.gpu, l.component.kind(), size[0], size[1]));
            }
            let Some(target) = &l.target else { continue };
            crate::draw::clear_layer(&self.gpu, target);
            let mut ctx = RenderCtx {
                gpu: &self.gpu,
                sources: &self.sources,
                camera: &camera,
                frame: self.frame,
                target,
                progress: &self.progress,
                preview: key.preview,
                occluder: occluder.map(|(o, t)| OccluderRef { depth: &t.depth_view, range: o.range }),
            };
            // A layer whose table is broken is left empty, saying why; the others draw. Any
            // other error (a device's, a query whose columns cannot be drawn) stops the frame.
            match l.component.render(&mut ctx) {
                Ok(()) => l.failed = None,
                Err(e) if store::says_unavailable(&e.to_string()) => {
                    crate::draw::clear_layer(&self.gpu, target);
                    l.failed = Some(e.to_string());
                }
                Err(e) => return Err(e),
            }
            self.gpu.check().map_err(|e| Error::Layer { layer: l.component.kind().into(), message: e.to_string() })?;
            l.range = depth_range(&camera, self.frame);
            l.renders += 1;
            l.key = Some(key);
        }
        self.composite();
        self.gpu.check()?;
        Ok(&self.output)
    }

    fn composite(&self) {
        let gpu = &self.gpu;
        let out_view = self.output.create_view(&Default::default());
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        let [r, g, b] = self.background;
        drop(enc.begin_render_pass(&wgpu::RenderPassDescriptor {
            label: Some("background"),
            color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                view: &out_view,
                depth_slice: None,
                resolve_target: None,
                ops: wgpu::Operations {
                    load: wgpu::LoadOp::Clear(wgpu::Color { r, g, b, a: 1.0 }),
                    store: wgpu::StoreOp::Store,
                },
            })],
            ..Default::default()
        }));
        let mut occluder: Option<(&LayerTarget, [f32; 2])> = None;
        let mut groups = Vec::new();
        for l in self.layers.iter().filter(|l| l.enabled) {
            let Some(t) = &l.target else { continue };
            let role = l.component.role();
            if role == LayerRole::Occluder {
                occluder = Some((t, l.range));
                continue;
            }
            let (occ, orange, test) = match (role, occluder) {
                (LayerRole::Scene, Some((o, r))) => (o, r, 1.0),
                _ => (&self.far, [1.0, 2.0], 0.0),
            };
            let u = CompUniform {
                ranges: [l.range[0], l.range[1], orange[0], orange[1]],
                params: [test, crate::draw::DEPTH_BIAS, 0.0, 0.0],
            };
            let ubuf = crate::draw::uniform(gpu, "composite", &u);
            let occ_view = occ.depth.create_view(&Default::default());
            groups.push(gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &self.compositor.layout,
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: ubuf.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::TextureView(&t.color_view) },
                    wgpu::BindGroupEntry { binding: 2, resource: wgpu::BindingResource::TextureView(&t.depth_view) },
                    wgpu::BindGroupEntry { binding: 3, resource: wgpu::BindingResource::TextureView(&occ_view) },
                ],
            }));
        }
        {
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("composite"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &out_view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations { load: wgpu::LoadOp::Load, store: wgpu::StoreOp::Store },
                })],
                ..Default::default()
            });
            pass.set_pipeline(&self.compositor.pipeline);
            for g in &groups {
                pass.set_bind_group(0, g, &[]);
                pass.draw(0..3, 0..1);
            }
        }
        gpu.queue.submit([enc.finish()]);
    }

    /// Picking: the nearest pickable item (ray segment, BVH box, query row) within `radius`
    /// pixels of `pixel` of the view. The shown layers draw their items' ids into a small
    /// target around the cursor (the projection cropped to it, depth tested), which is read back:
    /// no CPU search over the segments.
    pub fn pick(&mut self, [x, y]: [u32; 2], radius: u32) -> Result<Option<Pick>> {
        let (w, h) = (self.width, self.height);
        if x >= w || y >= h {
            return Err(Error::Settings(format!("pixel {x},{y} is outside the {w}x{h} view")));
        }
        let size = 2 * radius.min(64) + 1;
        let target = PickTarget::new(&self.gpu, size);
        let mut enc = self.gpu.device.create_command_encoder(&Default::default());
        drop(target.pass_with(&mut enc, wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT), wgpu::LoadOp::Clear(1.0)));
        self.gpu.queue.submit([enc.finish()]);
        let crop = crop_matrix([x, y], [w, h], size);
        for (slot, l) in self.layers.iter_mut().enumerate() {
            if !l.enabled || l.key.is_none() {
                continue;
            }
            let camera = l.camera.unwrap_or(self.camera);
            let view_proj = crop * camera.view_proj_f32(self.frame.anchor, self.frame.radius, w, h);
            let mut ctx =
                PickCtx { gpu: &self.gpu, sources: &self.sources, view_proj, target: &target, slot: slot as u32 + 1 };
            l.component.pick(&mut ctx)?;
        }
        self.gpu.check()?;
        let texels = self.gpu.read_texels(&target.ids, 8)?;
        let word = |k: usize| u32::from_le_bytes([texels[k], texels[k + 1], texels[k + 2], texels[k + 3]]);
        let r = (size / 2) as i64;
        let mut best: Option<(i64, u32, u32)> = None;
        for j in 0..size as usize {
            for i in 0..size as usize {
                let k = (j * size as usize + i) * 8;
                let (slot, id) = (word(k), word(k + 4));
                let d = (i as i64 - r).pow(2) + (j as i64 - r).pow(2);
                if id != 0 && slot != 0 && best.is_none_or(|b| d < b.0) {
                    best = Some((d, slot, id - 1));
                }
            }
        }
        let Some((_, slot, index)) = best else { return Ok(None) };
        let Some(l) = self.layers.get(slot as usize - 1) else { return Ok(None) };
        Ok(l.component.picked(index).map(|item| Pick { layer: l.component.id(), index, item }))
    }

    /// The legends of the shown layers, bottom to top.
    pub fn legends(&self) -> Vec<Legend> {
        self.layers.iter().filter(|l| l.enabled && l.failed.is_none()).flat_map(|l| l.component.legend()).collect()
    }

    /// What the shown layers report, and what the sources lack.
    pub fn report(&self) -> Vec<String> {
        let mut r: Vec<String> = self
            .layers
            .iter()
            .filter(|l| l.enabled)
            .flat_map(|l| match &l.failed {
                // What a failed layer would report of its last load is not what is shown.
                Some(why) => vec![format!("warning: the {} layer is not drawn: {why}", l.component.kind())],
                None => l.component.report(),
            })
            .collect();
        r.extend(self.sources.missing.iter().map(|m| format!("note: {m}")));
        r
    }

    /// Renders and reads the picture back (RGBA8, rows top to bottom), with legends when asked.
    pub fn snapshot(&mut self, legends: bool) -> Result<image::RgbaImage> {
        self.render()?;
        let mut px = self.gpu.read_rgba(&self.output)?;
        if legends {
            let l = self.legends();
            draw_legends(&mut Canvas { rgba: &mut px, width: self.width, height: self.height }, &l);
        }
        image::RgbaImage::from_raw(self.width, self.height, px)
            .ok_or_else(|| Error::Gpu(rtvtk_gpu::Error::Gpu("read back a picture of the wrong size".into())))
    }
}
