#![doc = include_str!("../README.md")]

use bytemuck::{Pod, Zeroable};
use renderers::{Bvh, Scene};
use wgpu::util::DeviceExt;

mod choice;
mod record;

pub use choice::register;

/// What the GPU tracer can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No adapter, an adapter that cannot run the tracer, a device error (`rtvtk_gpu`).
    #[error(transparent)]
    Gpu(#[from] rtvtk_gpu::Error),
    #[error("invalid input: {0}")]
    Input(String),
}

/// Result alias of the GPU tracer.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A BVH node as the shader reads it (32 bytes): an inner node (count 0) has its children at
/// `first` and `first + 1`, a leaf its `count` triangles at slots `first..`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuNode {
    min: [f32; 3],
    first: u32,
    max: [f32; 3],
    count: u32,
}

/// A leaf slot's triangle (48 bytes): the vertices, the scene triangle's index in `v0[3]`'s bits.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuTri {
    v0: [f32; 4],
    v1: [f32; 4],
    v2: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuCamera {
    position: [f32; 4],
    forward: [f32; 4],
    right: [f32; 4],
    up: [f32; 4],
    /// tan(fov_y / 2), aspect, width, height
    params: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuMaterial {
    kind: u32,
    exponent: f32,
    ior: f32,
    pad: f32,
    diffuse: [f32; 4],
    specular: [f32; 4],
    emission: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuLight {
    v0: [f32; 4],
    v1: [f32; 4],
    v2: [f32; 4],
    normal: [f32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuFrame {
    /// sample index, seed, max depth, light count
    counts: [u32; 4],
    /// total emitter area
    area: [f32; 4],
    /// the pixels of the dispatch: x0, y0, width, height
    window: [u32; 4],
    /// recording (0/1), ray slots per path, the sample's index in its batch, injected bug (0/1)
    rec: [u32; 4],
}

/// One recorded ray as the shader writes it (80 bytes; `RayRec` in `trace.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
struct GpuRay {
    o: [f32; 3],
    t: f32,
    d: [f32; 3],
    prim: u32,
    beta: [f32; 3],
    parent: u32,
    rad: [f32; 3],
    kind: u32,
    nodes: u32,
    boxes: u32,
    tris: u32,
    material: u32,
}

const NONE: u32 = u32::MAX;
/// Bytes of one recorded ray.
const RAY_BYTES: u64 = std::mem::size_of::<GpuRay>() as u64;
/// The deepest path the GPU records (`2 * (63 + 1)` ray slots per path).
pub const MAX_RECORDED_DEPTH: u32 = 63;

/// A progressive image on the GPU: the sum of the samples traced so far, per pixel.
pub struct Accumulation {
    width: u32,
    height: u32,
    accum: wgpu::Buffer,
    /// Rays packed (\[0\]) and traced per kind (\[1 + kind\]) by the last dispatches.
    totals: wgpu::Buffer,
    /// Samples per pixel added so far.
    pub spp: u32,
    pub seed: u32,
    pub max_depth: u32,
    /// Rays traced so far by kind (camera, shadow, diffuse, specular, transmission).
    pub rays_by_kind: [u64; 5],
}

impl Accumulation {
    /// The accumulated radiance: per pixel (rows top to bottom) four f32, the sum of the
    /// samples' RGB and the number of samples. Bound read-only, it is tone-mapped on the GPU
    /// (`viz`'s image layer) with no read-back.
    pub fn accumulation(&self) -> &wgpu::Buffer {
        &self.accum
    }

    /// The image's size in pixels.
    pub fn size(&self) -> [u32; 2] {
        [self.width, self.height]
    }

    /// The next `samples` sample indices, each at index 0 of its batch (one dispatch each).
    fn next_samples(&self, samples: u32) -> Vec<(u32, u32)> {
        (self.spp..self.spp.saturating_add(samples)).map(|s| (s, 0)).collect()
    }
}

/// The buffers a recording dispatch writes its rays to.
struct RecordBuffers {
    scratch: wgpu::Buffer,
    packed: wgpu::Buffer,
    spans: wgpu::Buffer,
    slots: u32,
}

/// The closest hit of one pixel's primary ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PrimaryHit {
    /// The scene triangle hit, `None` for a miss.
    pub prim: Option<u32>,
    /// Hit distance (`f32::INFINITY` for a miss).
    pub t: f32,
}

/// Image sizes the tracer accepts: 1..=16384 pixels on each side.
fn check_size(w: u32, h: u32) -> Result<()> {
    if w == 0 || h == 0 || w > 16384 || h > 16384 {
        return Err(Error::Input(format!("image size {w}x{h}: expected 1..=16384 on each side")));
    }
    Ok(())
}

/// A scene and its BVH on the GPU, with the compute pipelines that trace them.
pub struct GpuTracer {
    /// The device it traces on (its queue, limits and read-back).
    gpu: rtvtk_gpu::Gpu,
    nodes: wgpu::Buffer,
    tris: wgpu::Buffer,
    primary: wgpu::ComputePipeline,
    path: wgpu::ComputePipeline,
    normals: wgpu::Buffer,
    materials: wgpu::Buffer,
    lights: wgpu::Buffer,
    light_cdf: wgpu::Buffer,
    light_count: u32,
    light_area: f32,
    camera: renderers::Camera,
    /// Stand-ins for the recording buffers when not recording (bindings may not be missing).
    no_record: RecordBuffers,
    module: wgpu::ShaderModule,
}

/// The primary-ray and path-tracing pipelines of `module`, with the nearer child visited first
/// or not.
fn pipelines(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    nearer_first: bool,
) -> (wgpu::ComputePipeline, wgpu::ComputePipeline) {
    let constants = [("NEARER_FIRST", if nearer_first { 1.0 } else { 0.0 })];
    let make = |entry: &str| {
        device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: None,
            module,
            entry_point: Some(entry),
            compilation_options: wgpu::PipelineCompilationOptions { constants: &constants, ..Default::default() },
            cache: None,
        })
    };
    (make("primary"), make("path"))
}

/// Storage buffers the path tracer binds in its compute stage.
pub const STORAGE_BUFFERS: u32 = 12;

impl GpuTracer {
    /// Uploads `scene` (its triangles in `bvh`'s leaf order) and its BVH to the process's GPU
    /// (`rtvtk_gpu::Gpu::shared`, the device the visualizer draws with).
    pub fn new(scene: &Scene, bvh: &Bvh) -> Result<GpuTracer> {
        Self::with_gpu(&rtvtk_gpu::Gpu::shared()?, scene, bvh)
    }

    /// The same on a given device. Refuses (`rtvtk_gpu::Error::Unsupported`) an adapter with no
    /// compute shaders or fewer than [`STORAGE_BUFFERS`] storage buffers per stage (an old GL
    /// driver): the caller traces on the CPU instead.
    pub fn with_gpu(gpu: &rtvtk_gpu::Gpu, scene: &Scene, bvh: &Bvh) -> Result<GpuTracer> {
        gpu.compute_support(STORAGE_BUFFERS)?;
        let device = &gpu.device;
        let mut nodes: Vec<GpuNode> =
            bvh.binary_nodes().into_iter().map(|(min, max, first, count)| GpuNode { min, first, max, count }).collect();
        let mut tris: Vec<GpuTri> = bvh
            .leaf_slots()
            .map(|(prim, [a, b, c])| GpuTri {
                v0: [a.x, a.y, a.z, f32::from_bits(prim)],
                v1: [b.x, b.y, b.z, 0.0],
                v2: [c.x, c.y, c.z, 0.0],
            })
            .collect();
        if nodes.is_empty() {
            // No triangles: one empty leaf whose box no ray enters.
            nodes.push(GpuNode { min: [f32::INFINITY; 3], first: 0, max: [f32::NEG_INFINITY; 3], count: 0 });
            nodes[0].count = u32::MAX;
        }
        if tris.is_empty() {
            tris.push(GpuTri::zeroed());
        }
        let storage = |label: &str, bytes: &[u8]| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        let v4 = |v: glam::Vec3A, w: f32| [v.x, v.y, v.z, w];
        let mut normals: Vec<[f32; 4]> =
            scene.normals.iter().zip(&scene.tri_material).map(|(n, &m)| v4(*n, f32::from_bits(m))).collect();
        let mut materials: Vec<GpuMaterial> = scene
            .materials
            .iter()
            .map(|m| GpuMaterial {
                kind: match m.kind {
                    renderers::MaterialKind::Diffuse => 0,
                    renderers::MaterialKind::Glossy => 1,
                    renderers::MaterialKind::Mirror => 2,
                    renderers::MaterialKind::Dielectric => 3,
                },
                exponent: m.exponent,
                ior: m.ior,
                pad: 0.0,
                diffuse: v4(m.diffuse, 0.0),
                specular: v4(m.specular, 0.0),
                emission: v4(m.emission, 0.0),
            })
            .collect();
        let mut lights = Vec::with_capacity(scene.lights.len());
        for &p in &scene.lights {
            let (Some([a, b, c]), Some(n)) = (scene.tris.get(p as usize), scene.normals.get(p as usize)) else {
                return Err(Error::Input(format!(
                    "emitter triangle {p} is not among the scene's {} triangles",
                    scene.tris.len()
                )));
            };
            lights.push(GpuLight {
                v0: v4(*a, 0.0),
                v1: v4(*b, 0.0),
                v2: v4(*c, 0.0),
                normal: v4(*n, f32::from_bits(p)),
            });
        }
        if scene.normals.len() != scene.tris.len() || scene.tri_material.len() != scene.tris.len() {
            return Err(Error::Input(format!(
                "the scene has {} triangles but {} normals and {} material indices",
                scene.tris.len(),
                scene.normals.len(),
                scene.tri_material.len()
            )));
        }
        if let Some(m) = scene.tri_material.iter().find(|&&m| m as usize >= scene.materials.len()) {
            return Err(Error::Input(format!("material index {m}: the scene has {} materials", scene.materials.len())));
        }
        let mut light_cdf = scene.light_cdf.clone();
        let (light_count, light_area) = (lights.len() as u32, scene.light_area);
        // Storage buffers may not be empty.
        if normals.is_empty() {
            normals.push([0.0; 4]);
        }
        if materials.is_empty() {
            materials.push(GpuMaterial::zeroed());
        }
        if lights.is_empty() {
            lights.push(GpuLight::zeroed());
        }
        if light_cdf.is_empty() {
            light_cdf.push(0.0);
        }
        let nodes = storage("bvh nodes", bytemuck::cast_slice(&nodes));
        let normals = storage("normals", bytemuck::cast_slice(&normals));
        let materials = storage("materials", bytemuck::cast_slice(&materials));
        let lights = storage("lights", bytemuck::cast_slice(&lights));
        let light_cdf = storage("light cdf", bytemuck::cast_slice(&light_cdf));
        let tris = storage("leaf triangles", bytemuck::cast_slice(&tris));
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("trace"),
            source: wgpu::ShaderSource::Wgsl(include_str!("trace.wgsl").into()),
        });
        let (primary, path) = gpu.capture("the tracing shaders", || pipelines(device, &module, true))?;
        let small = |label: &str, size: u64| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        };
        let no_record = RecordBuffers {
            scratch: small("no scratch", RAY_BYTES),
            packed: small("no packed rays", RAY_BYTES),
            spans: small("no spans", 8),
            slots: 0,
        };
        Ok(GpuTracer {
            gpu: gpu.clone(),
            nodes,
            tris,
            primary,
            path,
            normals,
            materials,
            lights,
            light_cdf,
            light_count,
            light_area,
            camera: scene.camera,
            no_record,
            module,
        })
    }

    /// The camera as the shader reads it, for a `w` × `h` image.
    fn camera_uniform(&self, w: u32, h: u32) -> wgpu::Buffer {
        let c = &self.camera;
        let forward = (c.target - c.position).normalize();
        let right = forward.cross(c.up).normalize();
        let up = right.cross(forward);
        let v4 = |v: glam::Vec3A| [v.x, v.y, v.z, 0.0];
        let cam = GpuCamera {
            position: v4(c.position),
            forward: v4(forward),
            right: v4(right),
            up: v4(up),
            params: [(c.fov_y.to_radians() * 0.5).tan(), w as f32 / h as f32, w as f32, h as f32],
        };
        self.gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("camera"),
            contents: bytemuck::bytes_of(&cam),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    }

    /// An empty progressive image of `w` × `h` pixels (`max_depth` bounces at most, as
    /// `renderers::RenderOptions::max_depth`).
    pub fn progressive(&self, w: u32, h: u32, seed: u32, max_depth: u32) -> Result<Accumulation> {
        check_size(w, h)?;
        // wgpu zero-fills new buffers: no samples yet.
        let accum = self.gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("accumulated radiance"),
            size: u64::from(w) * u64::from(h) * 16,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let totals = self.gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("ray totals"),
            size: 32,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(Accumulation { width: w, height: h, accum, totals, spp: 0, seed, max_depth, rays_by_kind: [0; 5] })
    }

    /// Adds `samples` path-traced samples per pixel to `p` (one dispatch each) and waits for
    /// them, counting the rays traced by kind (`Accumulation::rays_by_kind`).
    pub fn trace(&self, p: &mut Accumulation, samples: u32) -> Result<()> {
        self.dispatch(p, [0, 0, p.width, p.height], &p.next_samples(samples), None, false)?;
        p.spp = p.spp.saturating_add(samples);
        Ok(())
    }

    /// Adds `samples` samples per pixel to `p` without waiting: nothing is read back and the
    /// rays are not counted (the visualizer's progressive image, tone-mapped on the GPU from
    /// [`Accumulation::accumulation`]).
    pub fn accumulate(&self, p: &mut Accumulation, samples: u32) {
        self.submit(p, [0, 0, p.width, p.height], &p.next_samples(samples), None, false);
        p.spp = p.spp.saturating_add(samples);
    }

    /// Traces one sample per `(sample index, index in the batch)` over the window
    /// `[x0, y0, width, height]` of `p`, one dispatch each, recording into `rec` when given;
    /// returns how many rays were recorded.
    fn dispatch(
        &self,
        p: &mut Accumulation,
        window: [u32; 4],
        samples: &[(u32, u32)],
        rec: Option<&RecordBuffers>,
        bug: bool,
    ) -> Result<u32> {
        let mut clear = self.gpu.device.create_command_encoder(&Default::default());
        clear.clear_buffer(&p.totals, 0, None);
        self.gpu.queue.submit([clear.finish()]);
        self.submit(p, window, samples, rec, bug);
        let totals: Vec<u32> = self.read_back(&p.totals, 32)?;
        for (k, n) in p.rays_by_kind.iter_mut().zip(&totals[1..6]) {
            *k += u64::from(*n);
        }
        Ok(totals[0])
    }

    /// Submits the dispatches of [`GpuTracer::dispatch`] without waiting for them.
    fn submit(
        &self,
        p: &Accumulation,
        window: [u32; 4],
        samples: &[(u32, u32)],
        rec: Option<&RecordBuffers>,
        bug: bool,
    ) {
        let cam = self.camera_uniform(p.width, p.height);
        let frame = self.gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("frame"),
            size: std::mem::size_of::<GpuFrame>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let r = rec.unwrap_or(&self.no_record);
        let group = self.gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.path.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: cam.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: self.nodes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: self.tris.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 4, resource: frame.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 5, resource: self.normals.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 6, resource: self.materials.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 7, resource: self.lights.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 8, resource: self.light_cdf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 9, resource: p.accum.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 10, resource: r.scratch.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 11, resource: r.packed.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 12, resource: r.spans.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 13, resource: p.totals.as_entire_binding() },
            ],
        });
        for &(s, batch_index) in samples {
            let f = GpuFrame {
                counts: [s, p.seed, p.max_depth, self.light_count],
                area: [self.light_area, 0.0, 0.0, 0.0],
                window,
                rec: [u32::from(rec.is_some()), r.slots, batch_index, u32::from(bug)],
            };
            self.gpu.queue.write_buffer(&frame, 0, bytemuck::bytes_of(&f));
            let mut enc = self.gpu.device.create_command_encoder(&Default::default());
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                pass.set_pipeline(&self.path);
                pass.set_bind_group(0, &group, &[]);
                pass.dispatch_workgroups(window[2].div_ceil(8), window[3].div_ceil(8), 1);
            }
            self.gpu.queue.submit([enc.finish()]);
        }
    }

    /// The mean of the samples so far, as the CPU tracer's film.
    pub fn film(&self, p: &Accumulation) -> Result<renderers::Film> {
        let sums: Vec<[f32; 4]> = self.read_back(&p.accum, p.accum.size())?;
        let pixels = sums
            .iter()
            .map(|s| if s[3] > 0.0 { glam::Vec3A::new(s[0], s[1], s[2]) / s[3] } else { glam::Vec3A::ZERO })
            .collect();
        Ok(renderers::Film { width: p.width, height: p.height, pixels })
    }

    /// A path-traced image of `spp` samples per pixel.
    pub fn render(&self, w: u32, h: u32, spp: u32, seed: u32, max_depth: u32) -> Result<renderers::Film> {
        let mut p = self.progressive(w, h, seed, max_depth)?;
        self.trace(&mut p, spp)?;
        self.film(&p)
    }

    /// The first `bytes` of a storage buffer (made with `COPY_SRC`).
    fn read_back<T: Pod>(&self, buf: &wgpu::Buffer, bytes: u64) -> Result<Vec<T>> {
        Ok(self.gpu.read_values(buf, bytes)?)
    }

    /// Visits the nearer of two hit BVH children first (the default) or always the first one
    /// (the traversal-order measurement of `rtvtk bench gpu`).
    pub fn set_nearer_child_first(&mut self, on: bool) {
        (self.primary, self.path) = pipelines(&self.gpu.device, &self.module, on);
    }

    /// Traces from `camera` from now on (the scene's camera at first).
    pub fn set_camera(&mut self, camera: renderers::Camera) {
        self.camera = camera;
    }

    /// The adapter in words (`llvmpipe (Vulkan)`).
    pub fn adapter(&self) -> String {
        self.gpu.describe()
    }

    /// The device the tracer runs on.
    pub fn gpu(&self) -> &rtvtk_gpu::Gpu {
        &self.gpu
    }

    /// The closest hit of the primary ray through the centre of every pixel of a `w` × `h`
    /// image at the scene's camera (rows top to bottom), the camera model of
    /// `renderers::Camera::direction`.
    pub fn primary_hits(&self, w: u32, h: u32) -> Result<Vec<PrimaryHit>> {
        check_size(w, h)?;
        let ubuf = self.camera_uniform(w, h);
        let bytes = u64::from(w) * u64::from(h) * 8;
        let out = self.gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("hits"),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let group = self.gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.primary.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: ubuf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: self.nodes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: self.tris.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: out.as_entire_binding() },
            ],
        });
        let mut enc = self.gpu.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.primary);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(w.div_ceil(8), h.div_ceil(8), 1);
        }
        self.gpu.queue.submit([enc.finish()]);
        let hits = self
            .read_back::<[u32; 2]>(&out, bytes)?
            .into_iter()
            .map(|[prim, t]| match prim {
                u32::MAX => PrimaryHit { prim: None, t: f32::INFINITY },
                prim => PrimaryHit { prim: Some(prim), t: f32::from_bits(t) },
            })
            .collect();
        Ok(hits)
    }
}
