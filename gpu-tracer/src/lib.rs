#![doc = include_str!("../README.md")]

use bytemuck::{Pod, Zeroable};
use renderers::{Bvh, Scene};
use wgpu::util::DeviceExt;

/// What the GPU tracer can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(
        "no GPU adapter found ({0}); install a Vulkan driver, e.g. Mesa's software rasterizer lavapipe: \
         `apt-get install mesa-vulkan-drivers libvulkan1` (Debian/Ubuntu)"
    )]
    NoAdapter(String),
    #[error("cannot open the GPU device: {0}")]
    Device(String),
    #[error("GPU error: {0}")]
    Gpu(String),
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

/// The closest hit of one pixel's primary ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PrimaryHit {
    /// The scene triangle hit, `None` for a miss.
    pub prim: Option<u32>,
    /// Hit distance (`f32::INFINITY` for a miss).
    pub t: f32,
}

/// A scene and its BVH on the GPU, with the compute pipelines that trace them.
pub struct GpuTracer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    adapter: String,
    nodes: wgpu::Buffer,
    tris: wgpu::Buffer,
    primary: wgpu::ComputePipeline,
    camera: renderers::Camera,
}

impl GpuTracer {
    /// Uploads `scene` (its triangles in `bvh`'s leaf order) and its BVH to a headless device.
    pub fn new(scene: &Scene, bvh: &Bvh) -> Result<GpuTracer> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let options = wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::from_env().unwrap_or(wgpu::PowerPreference::HighPerformance),
            force_fallback_adapter: false,
            compatible_surface: None,
            apply_limit_buckets: false,
        };
        let adapter =
            pollster::block_on(instance.request_adapter(&options)).map_err(|e| Error::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let have = adapter.limits();
        let desc = wgpu::DeviceDescriptor {
            label: Some("rtvtk gpu tracer"),
            required_features: wgpu::Features::empty(),
            required_limits: wgpu::Limits {
                max_storage_buffer_binding_size: have.max_storage_buffer_binding_size,
                max_buffer_size: have.max_buffer_size,
                ..Default::default()
            },
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        };
        let (device, queue) =
            pollster::block_on(adapter.request_device(&desc)).map_err(|e| Error::Device(e.to_string()))?;
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
        let nodes = storage("bvh nodes", bytemuck::cast_slice(&nodes));
        let tris = storage("leaf triangles", bytemuck::cast_slice(&tris));
        let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("trace"),
            source: wgpu::ShaderSource::Wgsl(include_str!("trace.wgsl").into()),
        });
        let primary = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("primary"),
            layout: None,
            module: &module,
            entry_point: Some("primary"),
            compilation_options: Default::default(),
            cache: None,
        });
        Ok(GpuTracer {
            device,
            queue,
            adapter: format!("{} ({:?})", info.name, info.backend),
            nodes,
            tris,
            primary,
            camera: scene.camera,
        })
    }

    /// The adapter in words (`llvmpipe (Vulkan)`).
    pub fn adapter(&self) -> &str {
        &self.adapter
    }

    /// The closest hit of the primary ray through the centre of every pixel of a `w` × `h`
    /// image at the scene's camera (rows top to bottom), the camera model of
    /// `renderers::Camera::direction`.
    pub fn primary_hits(&self, w: u32, h: u32) -> Result<Vec<PrimaryHit>> {
        if w == 0 || h == 0 || w > 16384 || h > 16384 {
            return Err(Error::Input(format!("image size {w}x{h}: expected 1..=16384 on each side")));
        }
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
        let ubuf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("camera"),
            contents: bytemuck::bytes_of(&cam),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let bytes = u64::from(w) * u64::from(h) * 8;
        let out = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("hits"),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let read = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("hits read back"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &self.primary.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: ubuf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: self.nodes.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: self.tris.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: out.as_entire_binding() },
            ],
        });
        let mut enc = self.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.primary);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(w.div_ceil(8), h.div_ceil(8), 1);
        }
        enc.copy_buffer_to_buffer(&out, 0, &read, 0, bytes);
        self.queue.submit([enc.finish()]);
        let slice = read.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device.poll(wgpu::PollType::wait_indefinitely()).map(|_| ()).map_err(|e| Error::Gpu(e.to_string()))?;
        rx.recv().map_err(|e| Error::Gpu(e.to_string()))?.map_err(|e| Error::Gpu(e.to_string()))?;
        let data = slice.get_mapped_range().map_err(|e| Error::Gpu(e.to_string()))?;
        let words: &[u32] = bytemuck::cast_slice(&data);
        let hits = words
            .chunks_exact(2)
            .map(|p| match p[0] {
                u32::MAX => PrimaryHit { prim: None, t: f32::INFINITY },
                prim => PrimaryHit { prim: Some(prim), t: f32::from_bits(p[1]) },
            })
            .collect();
        drop(data);
        read.unmap();
        Ok(hits)
    }
}
