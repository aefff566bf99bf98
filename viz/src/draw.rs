//! GPU plumbing shared by the components: shader modules, pipelines over storage buffers, and
//! the chunked segment buffers the ray, box and query layers draw from.

use wgpu::util::DeviceExt;

use crate::camera::ViewUniform;
use crate::component::{LayerTarget, RenderCtx};
use crate::formats::{COLOR_FORMAT, DEPTH_FORMAT};
use rtvtk_gpu::Gpu;

const COMMON: &str = include_str!("shaders/common.wgsl");

/// A shader module of `common.wgsl` plus `src`.
pub fn shader(gpu: &Gpu, label: &str, src: &str) -> wgpu::ShaderModule {
    let code = format!("{COMMON}\n{src}");
    gpu.device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(code.into()),
    })
}

/// How a scene-space pipeline treats depth and colour.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Blend {
    /// Colour written with premultiplied alpha blending, depth tested and written.
    Opaque,
    /// Colour blended, depth tested but not written (alpha-blended surfaces).
    Transparent,
    /// No colour target: depth only.
    DepthOnly,
}

/// A pipeline that draws one full-screen triangle (`vs` and `fs` of the WGSL `source`) with
/// premultiplied alpha into a colour target: into a layer (`layer`: with the layer's depth
/// attachment, neither tested nor written) or into the output (no depth). `layout`: the bind
/// group layouts when the shader's own deduction is not wanted (the compositor's depth textures).
pub fn fullscreen_pipeline(
    gpu: &Gpu,
    label: &str,
    source: &str,
    layout: Option<&wgpu::PipelineLayout>,
    layer: bool,
) -> wgpu::RenderPipeline {
    let depth = layer.then_some((false, wgpu::CompareFunction::Always));
    colour_pipeline(gpu, label, &shader(gpu, label, source), "vs", Some("fs"), layout, depth)
}

/// Draws the full-screen triangle of `pipeline` (a [`fullscreen_pipeline`] made for a layer)
/// with bind group 0 `group` over the layer `target`, and submits it.
pub fn fullscreen_into_layer(
    gpu: &Gpu,
    target: &LayerTarget,
    pipeline: &wgpu::RenderPipeline,
    group: &wgpu::BindGroup,
) {
    let mut enc = gpu.device.create_command_encoder(&Default::default());
    {
        let mut pass = layer_pass(&mut enc, target, true);
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        pass.draw(0..3, 0..1);
    }
    gpu.queue.submit([enc.finish()]);
}

/// A triangle-list pipeline with the layout deduced from the shader (bind group 0).
pub fn scene_pipeline(
    gpu: &Gpu,
    module: &wgpu::ShaderModule,
    vs: &str,
    fs: &str,
    blend: Blend,
) -> wgpu::RenderPipeline {
    let fs = (blend != Blend::DepthOnly).then_some(fs);
    let depth = Some((blend != Blend::Transparent, wgpu::CompareFunction::LessEqual));
    colour_pipeline(gpu, vs, module, vs, fs, None, depth)
}

/// A triangle-list pipeline drawing premultiplied-alpha colour into [`COLOR_FORMAT`] (`fs`; none:
/// depth only) and, with `depth` = (written, compare), against a [`DEPTH_FORMAT`] attachment.
fn colour_pipeline(
    gpu: &Gpu,
    label: &str,
    module: &wgpu::ShaderModule,
    vs: &str,
    fs: Option<&str>,
    layout: Option<&wgpu::PipelineLayout>,
    depth: Option<(bool, wgpu::CompareFunction)>,
) -> wgpu::RenderPipeline {
    let targets = [Some(wgpu::ColorTargetState {
        format: COLOR_FORMAT,
        blend: Some(wgpu::BlendState::PREMULTIPLIED_ALPHA_BLENDING),
        write_mask: wgpu::ColorWrites::ALL,
    })];
    gpu.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some(label),
        layout,
        vertex: wgpu::VertexState {
            module,
            entry_point: Some(vs),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState { cull_mode: None, ..Default::default() },
        depth_stencil: depth.map(|(write, compare)| wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(write),
            depth_compare: Some(compare),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        multisample: Default::default(),
        fragment: fs.map(|fs| wgpu::FragmentState {
            module,
            entry_point: Some(fs),
            compilation_options: Default::default(),
            targets: &targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// Format of the picking target: (layer slot, item index + 1) per pixel.
pub use crate::formats::PICK_FORMAT;

/// A picking pipeline: the ids of `vs`'s items into a [`PICK_FORMAT`] target, depth tested, so
/// the nearest item wins (`fs_pick` of `lines.wgsl`).
pub fn pick_pipeline(gpu: &Gpu, module: &wgpu::ShaderModule, vs: &str) -> wgpu::RenderPipeline {
    pick_pipeline_with(gpu, module, vs, "fs_pick", wgpu::ColorWrites::ALL)
}

/// A pick pipeline that writes depth only (`fs` outputs a `vec2<u32>` that is not written): the
/// scene's triangles, so ids of the layers above the composition hide behind geometry.
pub fn pick_depth_pipeline(gpu: &Gpu, module: &wgpu::ShaderModule, vs: &str, fs: &str) -> wgpu::RenderPipeline {
    pick_pipeline_with(gpu, module, vs, fs, wgpu::ColorWrites::empty())
}

fn pick_pipeline_with(
    gpu: &Gpu,
    module: &wgpu::ShaderModule,
    vs: &str,
    fs: &str,
    write_mask: wgpu::ColorWrites,
) -> wgpu::RenderPipeline {
    let targets = [Some(wgpu::ColorTargetState { format: PICK_FORMAT, blend: None, write_mask })];
    gpu.device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
        label: Some("pick"),
        layout: None,
        vertex: wgpu::VertexState {
            module,
            entry_point: Some(vs),
            compilation_options: Default::default(),
            buffers: &[],
        },
        primitive: wgpu::PrimitiveState { cull_mode: None, ..Default::default() },
        depth_stencil: Some(wgpu::DepthStencilState {
            format: DEPTH_FORMAT,
            depth_write_enabled: Some(true),
            depth_compare: Some(wgpu::CompareFunction::LessEqual),
            stencil: Default::default(),
            bias: Default::default(),
        }),
        multisample: Default::default(),
        fragment: Some(wgpu::FragmentState {
            module,
            entry_point: Some(fs),
            compilation_options: Default::default(),
            targets: &targets,
        }),
        multiview_mask: None,
        cache: None,
    })
}

/// The shape a line layer draws: segments (rays, query rows; 6 vertices each) or box edges (BVH
/// nodes; 72 vertices each), from the same 32-byte items and `lines.wgsl`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LineShape {
    Segments,
    Boxes,
}

impl LineShape {
    /// The vertex shader entry of `lines.wgsl` that expands an item.
    pub fn vertex_entry(self) -> &'static str {
        match self {
            LineShape::Segments => "vs_seg",
            LineShape::Boxes => "vs_box",
        }
    }

    /// The compute entry of `splat.wgsl` that rasterizes an item in the accumulating styles.
    pub fn compute_entry(self) -> &'static str {
        match self {
            LineShape::Segments => "cs_seg",
            LineShape::Boxes => "cs_box",
        }
    }

    /// Vertices per item (a segment's quad, a box's twelve edges).
    pub fn per_item(self) -> u32 {
        match self {
            LineShape::Segments => 6,
            LineShape::Boxes => 72,
        }
    }
}

/// A uniform buffer holding `v`.
pub fn uniform<T: bytemuck::Pod>(gpu: &Gpu, label: &str, v: &T) -> wgpu::Buffer {
    gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::bytes_of(v),
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    })
}

/// Bind group 0 of `pipeline` with a uniform at 0 and a storage buffer at 1.
pub fn bind_view_storage(
    gpu: &Gpu,
    pipeline: &wgpu::RenderPipeline,
    view: &wgpu::Buffer,
    storage: &wgpu::Buffer,
) -> wgpu::BindGroup {
    gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: None,
        layout: &pipeline.get_bind_group_layout(0),
        entries: &[
            wgpu::BindGroupEntry { binding: 0, resource: view.as_entire_binding() },
            wgpu::BindGroupEntry { binding: 1, resource: storage.as_entire_binding() },
        ],
    })
}

/// Begins a pass into a layer; `clear` clears colour to transparent and depth to far.
pub fn layer_pass<'e>(enc: &'e mut wgpu::CommandEncoder, target: &LayerTarget, color: bool) -> wgpu::RenderPass<'e> {
    pass_into(enc, target, color, true)
}

/// A pass into a layer that keeps (`clear` false) or clears what the layer holds.
pub fn pass_into<'e>(
    enc: &'e mut wgpu::CommandEncoder,
    target: &LayerTarget,
    color: bool,
    clear: bool,
) -> wgpu::RenderPass<'e> {
    let (cload, dload) = if clear {
        (wgpu::LoadOp::Clear(wgpu::Color::TRANSPARENT), wgpu::LoadOp::Clear(1.0))
    } else {
        (wgpu::LoadOp::Load, wgpu::LoadOp::Load)
    };
    let color_att = [Some(wgpu::RenderPassColorAttachment {
        view: &target.color_view,
        depth_slice: None,
        resolve_target: None,
        ops: wgpu::Operations { load: cload, store: wgpu::StoreOp::Store },
    })];
    enc.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("layer"),
        color_attachments: if color { &color_att } else { &[] },
        depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
            view: &target.depth_view,
            depth_ops: Some(wgpu::Operations { load: dload, store: wgpu::StoreOp::Store }),
            stencil_ops: None,
        }),
        timestamp_writes: None,
        occlusion_query_set: None,
        multiview_mask: None,
    })
}

/// Clears a layer (colour transparent, depth far) and draws nothing.
pub fn clear_layer(gpu: &Gpu, target: &LayerTarget) {
    let mut enc = gpu.device.create_command_encoder(&Default::default());
    drop(layer_pass(&mut enc, target, true));
    gpu.queue.submit([enc.finish()]);
}

/// One segment (or box, with `a` = min and `b` = max) as the line shader reads it: 32 bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub struct GpuSegment {
    pub a: [f32; 3],
    pub color: u32,
    pub b: [f32; 3],
    pub flags: u32,
}

/// Relative depth bias of the composition (and of the styles' occluder test): a segment ending
/// on a surface stays visible.
pub(crate) const DEPTH_BIAS: f32 = 2e-3;

/// Items (segments, boxes) per submission of a line draw: a software rasterizer (lavapipe,
/// llvmpipe) bins a whole submission's triangles before drawing them (on lavapipe, drawing 1M
/// segments grew the process by 230 MB in batches of 2^18, 43 MB in batches of 2^15 and 18 MB in
/// batches of 2^12, no slower), so it gets small batches; a GPU gets large ones.
fn draw_batch(gpu: &Gpu) -> u32 {
    if gpu.adapter.device_type == wgpu::DeviceType::Cpu { 1 << 12 } else { 1 << 18 }
}

/// Bytes of segments written to the GPU at once (see [`SegmentBuffers::flush`]).
const WRITE_PIECE: usize = 1 << 20;

/// Bytes of GPU memory per segment.
pub const SEGMENT_BYTES: u64 = std::mem::size_of::<GpuSegment>() as u64;

/// Packs RGBA8 the way WGSL's `unpack4x8unorm` reads it.
pub fn pack_rgba(c: [u8; 4]) -> u32 {
    u32::from_le_bytes(c)
}

/// Segments on the GPU in buffers of at most `chunk` segments each (one binding per buffer,
/// within the device's storage binding limit), filled as rows stream in: at most one chunk
/// (2^18 segments, 8 MiB) is staged on the CPU, and each buffer is exactly the size of its
/// segments, so GPU memory is 32 bytes per segment.
pub struct SegmentBuffers {
    chunk: usize,
    buffers: Vec<(wgpu::Buffer, u64)>,
    staged: Vec<GpuSegment>,
    pub count: u64,
}

impl SegmentBuffers {
    pub fn new(gpu: &Gpu) -> SegmentBuffers {
        // Buffers of at most 2^18 segments (8 MiB): the staging copy on the CPU is one buffer's.
        let chunk = (gpu.max_storage_binding() / SEGMENT_BYTES).clamp(1024, 1 << 18) as usize;
        SegmentBuffers { chunk, buffers: Vec::new(), staged: Vec::new(), count: 0 }
    }

    /// Queues a segment; a full chunk goes to the GPU.
    pub fn push(&mut self, gpu: &Gpu, s: GpuSegment) {
        if self.staged.capacity() == 0 {
            self.staged.reserve_exact(self.chunk);
        }
        self.staged.push(s);
        if self.staged.len() >= self.chunk {
            self.flush(gpu);
        }
    }

    /// Writes the staged segments into a new GPU buffer of their size, and waits for the copy:
    /// a buffer made mapped would be filled through a staging buffer of its size that wgpu's
    /// allocator keeps once freed (on lavapipe it doubled the layer's memory); the queue's
    /// staging is one piece of [`WRITE_PIECE`] bytes at a time.
    pub fn flush(&mut self, gpu: &Gpu) {
        if self.staged.is_empty() {
            return;
        }
        let bytes: &[u8] = bytemuck::cast_slice(&self.staged);
        let buf = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("segments"),
            size: bytes.len() as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        // In pieces of 1 MiB, each waited for: the queue's staging memory (which the driver or
        // the allocator keeps once freed) stays one piece, not one buffer.
        for (i, piece) in bytes.chunks(WRITE_PIECE).enumerate() {
            gpu.queue.write_buffer(&buf, (i * WRITE_PIECE) as u64, piece);
            gpu.queue.submit([]);
            // A failed wait shows at the next draw, which checks the device.
            let _ = gpu.wait();
        }
        let n = self.staged.len() as u64;
        self.buffers.push((buf, n));
        self.count += n;
        self.staged.clear();
    }

    /// Writes the staged segments and frees the staging memory (the load is done).
    pub fn finish(&mut self, gpu: &Gpu) {
        self.flush(gpu);
        self.staged = Vec::new();
        give_back_freed_memory();
    }

    /// Segments made elsewhere, uploaded at the first draw.
    pub fn from_segments(segments: Vec<GpuSegment>) -> SegmentBuffers {
        let count = segments.len() as u64;
        SegmentBuffers { chunk: usize::MAX, buffers: Vec::new(), staged: segments, count }
    }

    /// GPU bytes allocated.
    pub fn gpu_bytes(&self) -> u64 {
        self.buffers.iter().map(|(b, _)| b.size()).sum()
    }

    /// Every non-empty buffer with its segment count, the staged segments uploaded into one more.
    pub fn chunks(&self, gpu: &Gpu) -> Vec<(wgpu::Buffer, u32)> {
        let staged = (!self.staged.is_empty()).then(|| {
            use wgpu::util::DeviceExt;
            let b = gpu.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("segments"),
                contents: bytemuck::cast_slice(&self.staged),
                usage: wgpu::BufferUsages::STORAGE,
            });
            (b, self.staged.len() as u64)
        });
        self.buffers.iter().filter(|(_, n)| *n > 0).cloned().chain(staged).map(|(b, n)| (b, n as u32)).collect()
    }

    /// Bind groups (view uniform + storage) of every chunk, each with its segment count and the
    /// index of its first segment (from `base`).
    fn bind_groups(
        &self,
        gpu: &Gpu,
        pipeline: &wgpu::RenderPipeline,
        ubuf: &wgpu::Buffer,
        base: u32,
    ) -> Vec<(wgpu::BindGroup, u32, u32)> {
        let mut first = base;
        let mut groups = Vec::new();
        for (b, n) in self.chunks(gpu) {
            groups.push((bind_view_storage(gpu, pipeline, ubuf, &b), n, first));
            first = first.saturating_add(n);
        }
        groups
    }

    /// Draws the ids of every segment (index in push order) into a picking target with a
    /// [`pick_pipeline`]; `base` is added to every index (a second buffer set drawn after this one).
    pub fn draw_ids(
        &self,
        gpu: &Gpu,
        target: &crate::component::PickTarget,
        pipeline: &wgpu::RenderPipeline,
        view: &ViewUniform,
        per: u32,
        base: u32,
    ) {
        let ubuf = uniform(gpu, "pick view", view);
        let groups = self.bind_groups(gpu, pipeline, &ubuf, base);
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        {
            let mut pass = target.pass(&mut enc);
            pass.set_pipeline(pipeline);
            for (g, n, first) in &groups {
                pass.set_bind_group(0, g, &[]);
                pass.draw(0..n * per, *first..*first + 1);
            }
        }
        gpu.queue.submit([enc.finish()]);
    }

    /// Draws every buffer with `pipeline` (`per` vertices per segment).
    /// `clear`: clear the layer first (the first draw into it), else draw over what is there.
    pub fn draw(
        &self,
        gpu: &Gpu,
        ctx: &RenderCtx,
        pipeline: &wgpu::RenderPipeline,
        view: &ViewUniform,
        per: u32,
        clear: bool,
    ) {
        self.draw_strided(gpu, ctx, pipeline, view, per, clear, 1);
    }

    /// The stride that keeps a draw within `budget` segments (1: every segment).
    pub fn stride_for(&self, budget: Option<u64>) -> u32 {
        budget.map_or(1, |b| self.count.div_ceil(b.max(1)).clamp(1, u64::from(u32::MAX)) as u32)
    }

    /// [`SegmentBuffers::draw`] of every `stride`-th segment only (the shader reads the stride
    /// from `view.params.y`, which this sets): a preview of millions of segments while the
    /// camera moves, spread over the whole layer.
    #[allow(clippy::too_many_arguments)]
    pub fn draw_strided(
        &self,
        gpu: &Gpu,
        ctx: &RenderCtx,
        pipeline: &wgpu::RenderPipeline,
        view: &ViewUniform,
        per: u32,
        clear: bool,
        stride: u32,
    ) {
        let stride = stride.max(1);
        let mut view = *view;
        view.params[1] = stride as f32;
        let ubuf = uniform(gpu, "view", &view);
        let groups = self.bind_groups(gpu, pipeline, &ubuf, 0);
        // Submissions of at most `draw_batch` items, each waited for before the next: a software
        // rasterizer (lavapipe, llvmpipe) bins a whole submission's triangles before drawing
        // them, so millions of segments in one would hold gigabytes of bins.
        let batch = draw_batch(gpu);
        let mut first = true;
        let batches: Vec<(&wgpu::BindGroup, u32, u32)> = groups
            .iter()
            .flat_map(|(g, n, _)| {
                let items = n.div_ceil(stride);
                (0..items.div_ceil(batch)).map(move |b| (g, b * batch, ((b + 1) * batch).min(items)))
            })
            .collect();
        for (g, a, b) in &batches {
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            {
                let mut pass = pass_into(&mut enc, ctx.target, true, clear && first);
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, *g, &[]);
                pass.draw(a * per..b * per, 0..1);
            }
            first = false;
            gpu.queue.submit([enc.finish()]);
            if batches.len() > 1 {
                let _ = gpu.wait();
            }
        }
        if batches.is_empty() && clear {
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            drop(pass_into(&mut enc, ctx.target, true, true));
            gpu.queue.submit([enc.finish()]);
        }
    }
}

/// Returns the memory a load freed to the operating system. A load decodes its columns in batches
/// and writes its segments through the device's staging memory in chunks of megabytes; glibc
/// raises its mmap threshold past the first such freed block and keeps the later ones in its
/// heaps, so a million-segment load left ~30 MB resident beyond its 31 MB of segments (`bench
/// viz`: growth 2.4x the segment buffer; 1.6x after this). Trimming once per load costs
/// milliseconds and leaves the allocator's settings alone.
fn give_back_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages of the allocator's heaps; thread-safe.
    unsafe {
        libc::malloc_trim(0);
    }
}
