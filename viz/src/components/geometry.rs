//! The scene's triangles: wireframe, alpha-blended or opaque surfaces coloured by material
//! (Figure 5), and the depth-only rasterization that hides scene-space layers behind geometry
//! over a ray-traced image (the 2D/3D composition).

use serde::{Deserialize, Serialize};

use crate::camera::ViewUniform;
use crate::component::{Component, ComponentId, Frame, Layer, LayerRole, Legend, RenderCtx};
use crate::draw::{Blend, bind_view_storage, layer_pass, scene_pipeline, shader, uniform};
use crate::sources::Sources;
use crate::{Error, Result};
use rtvtk_gpu::Gpu;

/// How the geometry layer draws surfaces.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SurfaceStyle {
    Wireframe,
    Transparent,
    Opaque,
}

impl SurfaceStyle {
    /// The values of the `style` setting (the viewer's drop-down).
    pub const NAMES: &'static [&'static str] = &["wireframe", "transparent", "opaque"];
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GeometrySettings {
    pub style: SurfaceStyle,
    /// Opacity of transparent surfaces and of wireframe lines.
    pub opacity: f32,
    /// Wireframe line width in pixels.
    pub line_width: f32,
}

impl crate::component::Settings for GeometrySettings {
    fn choices() -> Vec<(&'static str, &'static [&'static str])> {
        vec![("style", SurfaceStyle::NAMES)]
    }
    const KIND: &'static str = "geometry";
}

impl Default for GeometrySettings {
    fn default() -> Self {
        GeometrySettings { style: SurfaceStyle::Wireframe, opacity: 0.8, line_width: 1.2 }
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct GpuTri {
    a: [f32; 4],
    b: [f32; 4],
    c: [f32; 4],
    color: [f32; 4],
}

/// The scene's triangles on the GPU.
struct Mesh {
    buffer: wgpu::Buffer,
    count: u32,
    frame: Frame,
}

fn upload(gpu: &Gpu, sources: &Sources, frame: Frame) -> Result<Mesh> {
    let scene = sources
        .scene
        .as_ref()
        .ok_or_else(|| Error::Layer { layer: "geometry".into(), message: sources.why_no_scene() })?;
    let mut tris = Vec::with_capacity(scene.tris.len());
    for (i, t) in scene.tris.iter().enumerate() {
        let m = scene.material_of(i as u32);
        let p = |v: glam::Vec3A| {
            let l = frame.local(v.to_array().map(f64::from));
            [l[0], l[1], l[2], 1.0]
        };
        let color = if m.is_emissive() {
            let e = m.emission / m.emission.max_element().max(1e-9);
            [e.x, e.y, e.z, 2.0]
        } else {
            let c = (m.diffuse + m.specular).min(glam::Vec3A::ONE);
            let c = if c.max_element() < 0.05 { glam::Vec3A::splat(0.7) } else { c };
            [c.x, c.y, c.z, 1.0]
        };
        tris.push(GpuTri { a: p(t[0]), b: p(t[1]), c: p(t[2]), color });
    }
    use wgpu::util::DeviceExt;
    let buffer = gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some("triangles"),
        contents: bytemuck::cast_slice(&tris),
        usage: wgpu::BufferUsages::STORAGE,
    });
    Ok(Mesh { buffer, count: tris.len() as u32, frame })
}

struct Gpus {
    mesh: Mesh,
    opaque: wgpu::RenderPipeline,
    transparent: wgpu::RenderPipeline,
    depth_only: wgpu::RenderPipeline,
}

fn gpus(gpu: &Gpu, sources: &Sources, frame: Frame) -> Result<Gpus> {
    let module = shader(gpu, "surface", include_str!("../shaders/surface.wgsl"));
    Ok(Gpus {
        mesh: upload(gpu, sources, frame)?,
        opaque: scene_pipeline(gpu, &module, "vs", "fs", Blend::Opaque),
        transparent: scene_pipeline(gpu, &module, "vs", "fs", Blend::Transparent),
        depth_only: scene_pipeline(gpu, &module, "vs", "fs", Blend::DepthOnly),
    })
}

fn draw(gpu: &Gpu, ctx: &RenderCtx, g: &Gpus, pipeline: &wgpu::RenderPipeline, view: ViewUniform, color: bool) {
    let ubuf = uniform(gpu, "view", &view);
    let group = bind_view_storage(gpu, pipeline, &ubuf, &g.mesh.buffer);
    let mut enc = gpu.device.create_command_encoder(&Default::default());
    {
        let mut pass = layer_pass(&mut enc, ctx.target, color);
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.draw(0..g.mesh.count * 3, 0..1);
    }
    gpu.queue.submit([enc.finish()]);
}

/// The geometry layer.
pub struct Geometry {
    id: ComponentId,
    settings: GeometrySettings,
    generation: u64,
    gpu: Option<Gpus>,
    materials: Vec<(String, [u8; 4])>,
}

impl Geometry {
    pub fn new(id: ComponentId, sources: &Sources, settings: &serde_json::Value) -> Result<Geometry> {
        let scene = sources
            .scene
            .as_ref()
            .ok_or_else(|| Error::Layer { layer: "geometry".into(), message: sources.why_no_scene() })?;
        let to8 = |c: glam::Vec3A| [0, 1, 2].map(|k| (c[k].clamp(0.0, 1.0) * 255.0).round() as u8);
        let materials = scene
            .materials
            .iter()
            .enumerate()
            .filter(|(i, _)| scene.tri_material.contains(&(*i as u32)))
            .map(|(_, m)| {
                let c = if m.is_emissive() {
                    m.emission / m.emission.max_element()
                } else {
                    (m.diffuse + m.specular).min(glam::Vec3A::ONE)
                };
                let [r, g, b] = to8(c);
                (m.name.clone(), [r, g, b, 255])
            })
            .collect();
        let mut g = Geometry { id, settings: GeometrySettings::default(), generation: 0, gpu: None, materials };
        if !settings.is_null() {
            g.set_settings(settings)?;
        }
        Ok(g)
    }
}

impl Layer for Geometry {
    type Settings = GeometrySettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Scene
    }
    fn generation(&self) -> u64 {
        self.generation
    }
    fn current(&self) -> &GeometrySettings {
        &self.settings
    }
    fn apply(&mut self, s: GeometrySettings) -> Result<()> {
        if !((0.0..=1.0).contains(&s.opacity) && s.line_width > 0.0 && s.line_width <= 64.0) {
            return Err(Error::Settings("geometry: opacity must be in 0..1 and line_width in (0, 64] pixels".into()));
        }
        crate::component::replace_settings(&mut self.settings, s, &mut self.generation);
        Ok(())
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        let gpu = ctx.gpu;
        if self.gpu.as_ref().is_none_or(|g| g.mesh.frame != ctx.frame) {
            self.gpu = Some(gpus(gpu, ctx.sources, ctx.frame)?);
        }
        let Some(g) = &self.gpu else { return Ok(()) };
        let s = &self.settings;
        let (pipeline, opacity, mode) = match s.style {
            SurfaceStyle::Opaque => (&g.opaque, 1.0, 0.0),
            SurfaceStyle::Transparent => (&g.transparent, s.opacity, 1.0),
            SurfaceStyle::Wireframe => (&g.opaque, s.opacity, 2.0),
        };
        let view = ViewUniform::new(ctx.view_proj(), ctx.target.width, ctx.target.height, s.line_width, opacity, mode);
        draw(gpu, ctx, g, pipeline, view, true);
        Ok(())
    }
    fn legend(&self) -> Vec<Legend> {
        if self.settings.style == SurfaceStyle::Wireframe && self.settings.opacity < 0.05 {
            return Vec::new();
        }
        vec![Legend::Swatches { title: "materials".into(), entries: self.materials.clone() }]
    }
}

/// The composition layer has no settings (`{}`; any field is refused, naming it).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CompositionSettings {}

impl crate::component::Settings for CompositionSettings {
    const KIND: &'static str = "composition";
}

/// The 2D/3D composition layer: the scene's depth, no colour.
pub struct Composition {
    id: ComponentId,
    gpu: Option<Gpus>,
    pick_pipeline: Option<wgpu::RenderPipeline>,
}

impl Composition {
    pub fn new(id: ComponentId, sources: &Sources) -> Result<Composition> {
        if sources.scene.is_none() {
            return Err(Error::Layer {
                layer: "composition".into(),
                message: format!("{}: there is no scene depth to compose with", sources.why_no_scene()),
            });
        }
        Ok(Composition { id, gpu: None, pick_pipeline: None })
    }
}

impl Layer for Composition {
    type Settings = CompositionSettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Occluder
    }
    fn generation(&self) -> u64 {
        0
    }
    fn current(&self) -> &CompositionSettings {
        &CompositionSettings {}
    }
    fn apply(&mut self, _settings: CompositionSettings) -> Result<()> {
        Ok(())
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        if self.gpu.as_ref().is_none_or(|g| g.mesh.frame != ctx.frame) {
            self.gpu = Some(gpus(ctx.gpu, ctx.sources, ctx.frame)?);
        }
        let Some(g) = &self.gpu else { return Ok(()) };
        let view = ViewUniform::new(ctx.view_proj(), ctx.target.width, ctx.target.height, 1.0, 1.0, 0.0);
        draw(ctx.gpu, ctx, g, &g.depth_only, view, false);
        Ok(())
    }
    /// The scene's depth into the pick target: segments and boxes of the layers above are then
    /// picked only where they are seen, not through the tall box.
    fn pick(&mut self, ctx: &mut crate::component::PickCtx) -> Result<bool> {
        let Some(g) = &self.gpu else { return Ok(false) };
        let gpu = ctx.gpu;
        let p = self.pick_pipeline.get_or_insert_with(|| {
            let m = shader(gpu, "surface", include_str!("../shaders/surface.wgsl"));
            crate::draw::pick_depth_pipeline(gpu, &m, "vs", "fs_pick_depth")
        });
        let ubuf = uniform(gpu, "pick view", &ctx.view(1.0));
        let group = bind_view_storage(gpu, p, &ubuf, &g.mesh.buffer);
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        {
            let mut pass = ctx.target.pass(&mut enc);
            pass.set_pipeline(p);
            pass.set_bind_group(0, &group, &[]);
            pass.draw(0..g.mesh.count * 3, 0..1);
        }
        gpu.queue.submit([enc.finish()]);
        Ok(false)
    }
}
