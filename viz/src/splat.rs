//! Ray styles for many rays: `lines` (opaque, depth-tested, the last drawn on top), `alpha`
//! (order-independent transparency) and `density` (rays per pixel). The two accumulating styles
//! rasterize the line layers' segments in a compute pass (`shaders/splat.wgsl`: one invocation per
//! segment walks its pixels, as Schütz et al. 2021 rasterize points) that adds into a per-pixel
//! buffer of `u32` words with atomics, then one full-screen pass turns the sums into the layer's
//! colour (`shaders/splat_resolve.wgsl`). Fixed-point atomics make the result independent of draw
//! order and need no float blending, which wgpu's GL backend lacks on many drivers; a compute pass
//! bins nothing, so a software rasterizer (lavapipe, llvmpipe) holds no memory per segment.
//!
//! These layers have no depth of their own per pixel, so the occluder (the scene's depth) hides
//! their pixels as they are accumulated, with the compositor's relative depth bias.

use serde::{Deserialize, Serialize};

use crate::camera::ViewUniform;
use crate::component::RenderCtx;
use crate::draw::{LineShape, SegmentBuffers, shader, uniform};
use crate::formats::DEPTH_FORMAT;
use crate::{Error, Result};
use rtvtk_gpu::Gpu;

/// How a line layer draws its segments.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RayStyle {
    /// Opaque lines, depth tested: the nearest segment wins.
    #[default]
    Lines,
    /// Translucent lines at the layer's opacity, blended without sorting (weighted blended
    /// order-independent transparency, McGuire & Bavoil 2013).
    Alpha,
    /// Rays per pixel, tone-mapped (log by default), the hue the mean colour of the rays there.
    Density,
}

impl RayStyle {
    pub const NAMES: &'static [&'static str] = &["lines", "alpha", "density"];

    pub fn name(self) -> &'static str {
        match self {
            RayStyle::Lines => "lines",
            RayStyle::Alpha => "alpha",
            RayStyle::Density => "density",
        }
    }
}

impl std::str::FromStr for RayStyle {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "lines" => Ok(RayStyle::Lines),
            "alpha" => Ok(RayStyle::Alpha),
            "density" => Ok(RayStyle::Density),
            _ => Err(format!("unknown ray style {s:?}: expected one of {}", RayStyle::NAMES.join(", "))),
        }
    }
}

/// How the density style maps rays per pixel to brightness.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DensityScale {
    /// log(1 + n) / log(1 + max): a single ray and the brightest pixel both show.
    #[default]
    Log,
    /// n / max.
    Linear,
}

impl DensityScale {
    pub const NAMES: &'static [&'static str] = &["log", "linear"];
}

impl std::str::FromStr for DensityScale {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "log" => Ok(DensityScale::Log),
            "linear" => Ok(DensityScale::Linear),
            _ => Err(format!("unknown density scale {s:?}: expected log or linear")),
        }
    }
}

/// A line layer's style settings, as the layer holds them.
#[derive(Clone, Debug, PartialEq)]
pub struct StyleParams {
    pub style: RayStyle,
    pub scale: DensityScale,
    /// The density style's colour map (`None`: the rays' own colours, brightness by density).
    pub map: Option<String>,
    pub opacity: f32,
    /// The alpha style chooses the rays' opacity (at most `opacity`) from how many rays cover
    /// each pixel.
    pub auto_opacity: bool,
}

/// What a styled draw found.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Drawn {
    /// The density style's statistics.
    pub density: Option<DensityStats>,
    /// The opacity the rays were drawn with (the alpha style's choice when automatic).
    pub opacity: f32,
    /// The alpha style's automatic choice: the 90th percentile of rays per covered pixel.
    pub p90: Option<u32>,
}

/// What a density accumulation found: the most rays on one pixel and the pixels any ray reached.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DensityStats {
    pub max: u32,
    pub covered: u64,
}

/// What a layer drawn in `style` reports of its last draw.
pub fn style_report(layer: &str, style: &StyleParams, drawn: &Drawn) -> Option<String> {
    match style.style {
        RayStyle::Lines => None,
        RayStyle::Alpha => Some(match drawn.p90 {
            Some(n) if drawn.opacity < style.opacity => format!(
                "{layer}: alpha style, opacity {:.4} per ray (chosen so that a pixel under {n} rays, the 90th percentile of covered pixels, is half covered)",
                drawn.opacity
            ),
            _ => format!("{layer}: alpha style, opacity {} per ray", drawn.opacity),
        }),
        RayStyle::Density => drawn.density.map(|d| {
            format!(
                "{layer}: density style, at most {} rays on one pixel, {} pixels reached, {} scale",
                d.max,
                d.covered,
                if style.scale == DensityScale::Log { "log" } else { "linear" }
            )
        }),
    }
}

/// Words of the accumulation buffer per pixel.
const WORDS: u64 = 5;

/// A dispatch of `groups` workgroups, split over two dimensions where one would exceed the
/// 65,535 a dimension allows (the shaders number the groups row by row).
fn dispatch_2d(pass: &mut wgpu::ComputePass, groups: u64) {
    let x = groups.clamp(1, 65_535);
    pass.dispatch_workgroups(x as u32, groups.div_ceil(x) as u32, 1);
}

/// Buckets of the histogram of rays per covered pixel (`splat_reduce.wgsl`; the last holds more).
const HIST: usize = 4096;

/// The 90th percentile of rays per covered pixel, from the histogram of `splat_reduce.wgsl`
/// (`hist[n]` pixels under `n` rays, the last bucket under at least that many).
fn percentile_90(hist: &[u32]) -> Option<u32> {
    let covered: u64 = hist.iter().skip(1).map(|&c| u64::from(c)).sum();
    if covered == 0 {
        return None;
    }
    let k = covered * 9 / 10;
    let mut seen = 0u64;
    for (n, &c) in hist.iter().enumerate().skip(1) {
        seen += u64::from(c);
        if seen > k {
            return Some(n as u32);
        }
    }
    None
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SplatUniform {
    ranges: [f32; 4],
    params: [f32; 4],
    size: [u32; 4],
    extra: [f32; 4],
}

/// The WGSL of [`SplatUniform`], prepended to each of the styles' shaders.
const UNIFORM_WGSL: &str = include_str!("shaders/splat_uniform.wgsl");

/// The accumulation buffers and pipelines of one line layer (made on its first styled draw).
pub struct Splat {
    layout: wgpu::BindGroupLayout,
    accumulate: wgpu::ComputePipeline,
    reduce: wgpu::ComputePipeline,
    resolve: wgpu::RenderPipeline,
    acc: Option<(wgpu::Buffer, u64)>,
    stats: wgpu::Buffer,
    lut: wgpu::Buffer,
    lut_map: Option<String>,
    /// Bound where no occluder is (never read then).
    no_occluder: wgpu::TextureView,
    /// The alpha style's automatic opacity and the 90th percentile it came from, for the items,
    /// size and opacity setting it was chosen at.
    auto: Option<(AutoKey, f32, u32)>,
}

/// What the alpha style's automatic opacity depends on: items drawn, width, height and the
/// opacity setting's bits.
type AutoKey = (u64, u32, u32, u32);

impl Splat {
    /// The pipelines of the accumulating styles for items of `shape`; an error naming what the
    /// adapter lacks when it cannot run them.
    pub fn new(gpu: &Gpu, shape: LineShape) -> Result<Splat> {
        gpu.compute_support(2)?;
        let entry = |binding, ty| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty,
            count: None,
        };
        let storage = |read_only| wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Storage { read_only },
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let uniform_ty = wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: false,
            min_binding_size: None,
        };
        let layout = gpu.device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("splat"),
            entries: &[
                entry(0, uniform_ty),
                entry(1, storage(true)),
                entry(2, storage(false)),
                // The occluder's Depth32Float as an unfilterable float texture (as the compositor
                // binds it: GLSL has no texel load of a depth texture).
                entry(
                    3,
                    wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: false },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                ),
                entry(4, uniform_ty),
            ],
        });
        let pipeline_layout = gpu.device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("splat"),
            bind_group_layouts: &[Some(&layout)],
            immediate_size: 0,
        });
        let source =
            format!("{}\n{UNIFORM_WGSL}{}", include_str!("shaders/lines.wgsl"), include_str!("shaders/splat.wgsl"));
        let module = shader(gpu, "splat", &source);
        let accumulate = gpu.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("splat accumulate"),
            layout: Some(&pipeline_layout),
            module: &module,
            entry_point: Some(shape.compute_entry()),
            compilation_options: Default::default(),
            cache: None,
        });
        let reduce_source = format!("{UNIFORM_WGSL}{}", include_str!("shaders/splat_reduce.wgsl"));
        let reduce_module = shader(gpu, "splat reduce", &reduce_source);
        let reduce = gpu.device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some("splat reduce"),
            layout: None,
            module: &reduce_module,
            entry_point: Some("reduce"),
            compilation_options: Default::default(),
            cache: None,
        });
        let resolve = crate::draw::fullscreen_pipeline(
            gpu,
            "splat resolve",
            &format!("{UNIFORM_WGSL}{}", include_str!("shaders/splat_resolve.wgsl")),
            None,
            true,
        );
        let buffer = |label, size, usage| {
            gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        use wgpu::BufferUsages as B;
        let no_occluder = gpu.target("no occluder", DEPTH_FORMAT, 1, 1).create_view(&Default::default());
        Ok(Splat {
            layout,
            accumulate,
            reduce,
            resolve,
            acc: None,
            stats: buffer("splat stats", (2 + HIST as u64) * 4, B::STORAGE | B::COPY_SRC | B::COPY_DST),
            lut: buffer("splat colour map", 256 * 4, B::STORAGE | B::COPY_DST),
            lut_map: None,
            no_occluder,
            auto: None,
        })
    }

    /// Accumulates `sets` (each with the stride its preview draws at) into the layer in `style`,
    /// resolving into the layer's colour; the density statistics when the style is density.
    pub fn draw(
        &mut self,
        ctx: &RenderCtx,
        view: &ViewUniform,
        sets: &[(&SegmentBuffers, u32)],
        style: &StyleParams,
    ) -> Result<Drawn> {
        let gpu = ctx.gpu;
        let mut p90 = None;
        let (w, h) = (ctx.target.width, ctx.target.height);
        let pixels = u64::from(w) * u64::from(h);
        let bytes = pixels * WORDS * 4;
        if bytes > gpu.max_storage_binding() {
            return Err(Error::Layer {
                layer: "rays".into(),
                message: format!(
                    "the {} style at {w}x{h} needs a {} MiB buffer, over this adapter's {} MiB storage binding limit; draw a smaller picture or use --style lines",
                    style.style.name(),
                    bytes >> 20,
                    gpu.max_storage_binding() >> 20
                ),
            });
        }
        if self.acc.as_ref().is_none_or(|(_, b)| *b != bytes) {
            let b = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("splat accumulation"),
                size: bytes,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            });
            self.acc = Some((b, bytes));
        }
        let density = style.style == RayStyle::Density;
        if let Some(map) = style.map.as_ref().filter(|_| density)
            && self.lut_map.as_ref() != Some(map)
        {
            let m = crate::legend::colour_map(map)?;
            let lut: Vec<u32> = (0..256)
                .map(|i| {
                    let c = m.eval_continuous(f64::from(i) / 255.0);
                    crate::draw::pack_rgba([c.r, c.g, c.b, 255])
                })
                .collect();
            gpu.queue.write_buffer(&self.lut, 0, bytemuck::cast_slice(&lut));
            self.lut_map = Some(map.clone());
        }
        let Some((acc, _)) = &self.acc else { return Ok(Drawn::default()) };
        let range = ctx.depth_range();
        let (occ_view, occ_range, present) = match &ctx.occluder {
            Some(o) => (o.depth, o.range, 1.0),
            None => (&self.no_occluder, [1.0, 2.0], 0.0),
        };
        let u = SplatUniform {
            ranges: [range[0], range[1], occ_range[0], occ_range[1]],
            params: [
                if density { 2.0 } else { 1.0 },
                crate::draw::DEPTH_BIAS,
                present,
                if style.scale == DensityScale::Log { 1.0 } else { 0.0 },
            ],
            size: [w, h, pixels.min(u64::from(u32::MAX)) as u32, u32::from(density && style.map.is_some())],
            extra: [style.opacity, 0.0, 0.0, 0.0],
        };
        // Clears the sums and accumulates every set into them with `u` (the style) and the rays'
        // opacity `opacity`: one dispatch per buffer of segments, one invocation per item.
        let accumulate = |u: &SplatUniform, opacity: f32| -> Result<wgpu::Buffer> {
            let ubuf = uniform(gpu, "splat", u);
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            enc.clear_buffer(acc, 0, None);
            enc.clear_buffer(&self.stats, 0, None);
            // The layer's depth cleared: these styles leave the scene's depth to the occluder.
            drop(crate::draw::pass_into(&mut enc, ctx.target, false, true));
            for (set, stride) in sets {
                let mut v = *view;
                v.params[1] = (*stride).max(1) as f32;
                v.viewport[3] = opacity;
                let vbuf = uniform(gpu, "view", &v);
                for (chunk, n) in set.chunks(gpu) {
                    let g = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("splat"),
                        layout: &self.layout,
                        entries: &[
                            wgpu::BindGroupEntry { binding: 0, resource: vbuf.as_entire_binding() },
                            wgpu::BindGroupEntry { binding: 1, resource: chunk.as_entire_binding() },
                            wgpu::BindGroupEntry { binding: 2, resource: acc.as_entire_binding() },
                            wgpu::BindGroupEntry { binding: 3, resource: wgpu::BindingResource::TextureView(occ_view) },
                            wgpu::BindGroupEntry { binding: 4, resource: ubuf.as_entire_binding() },
                        ],
                    });
                    let mut pass = enc.begin_compute_pass(&Default::default());
                    pass.set_pipeline(&self.accumulate);
                    pass.set_bind_group(0, &g, &[]);
                    dispatch_2d(&mut pass, u64::from(n.div_ceil((*stride).max(1))).div_ceil(64));
                }
            }
            gpu.queue.submit([enc.finish()]);
            Ok(ubuf)
        };
        // The density statistics and the histogram of rays per covered pixel (`stats`, cleared
        // by `accumulate`) of what `accumulate` left.
        let reduce = |enc: &mut wgpu::CommandEncoder, ubuf: &wgpu::Buffer| {
            let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("splat reduce"),
                layout: &self.reduce.get_bind_group_layout(0),
                entries: &[
                    wgpu::BindGroupEntry { binding: 0, resource: acc.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 1, resource: self.stats.as_entire_binding() },
                    wgpu::BindGroupEntry { binding: 2, resource: ubuf.as_entire_binding() },
                ],
            });
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.reduce);
            pass.set_bind_group(0, &group, &[]);
            dispatch_2d(&mut pass, pixels.div_ceil(256));
        };
        let mut opacity = style.opacity;
        let items: u64 = sets.iter().map(|(s, stride)| s.count.div_ceil(u64::from((*stride).max(1)))).sum();
        let auto_key = (items, w, h, style.opacity.to_bits());
        if style.style == RayStyle::Alpha
            && style.auto_opacity
            && let Some((key, o, n)) = self.auto
            && key == auto_key
        {
            // Chosen already for these rays at this size (not again at every camera move).
            opacity = o;
            p90 = Some(n);
        } else if style.style == RayStyle::Alpha && style.auto_opacity {
            // Count the rays per pixel first: the rays' opacity leaves nine in ten covered pixels
            // at most half covered, so what lies under them shows.
            let counting = SplatUniform { params: [2.0, u.params[1], u.params[2], u.params[3]], ..u };
            let ubuf = accumulate(&counting, 1.0)?;
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            reduce(&mut enc, &ubuf);
            gpu.queue.submit([enc.finish()]);
            let stats: Vec<u32> = gpu.read_values(&self.stats, (2 + HIST as u64) * 4)?;
            if let Some(n) = percentile_90(stats.get(2..).unwrap_or_default()) {
                opacity = opacity.min(1.0 - 0.5f32.powf(1.0 / n.max(1) as f32));
                p90 = Some(n);
                self.auto = Some((auto_key, opacity, n));
            }
        }
        let ubuf = accumulate(&u, opacity)?;
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        if density {
            reduce(&mut enc, &ubuf);
        }
        let group = gpu.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("splat resolve"),
            layout: &self.resolve.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: acc.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 1, resource: self.stats.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 2, resource: ubuf.as_entire_binding() },
                wgpu::BindGroupEntry { binding: 3, resource: self.lut.as_entire_binding() },
            ],
        });
        {
            let mut pass = crate::draw::pass_into(&mut enc, ctx.target, true, false);
            pass.set_pipeline(&self.resolve);
            pass.set_bind_group(0, &group, &[]);
            pass.draw(0..3, 0..1);
        }
        gpu.queue.submit([enc.finish()]);
        if !density {
            return Ok(Drawn { density: None, opacity, p90 });
        }
        let s: Vec<u32> = gpu.read_values(&self.stats, 8)?;
        let stats =
            DensityStats { max: s.first().copied().unwrap_or(0), covered: s.get(1).copied().map_or(0, u64::from) };
        Ok(Drawn { density: Some(stats), opacity, p90 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The alpha style's 90th percentile from the histogram is the sorted counts' element at nine
    /// tenths, as it was when the counts were read back and sorted.
    #[test]
    fn percentile_of_the_histogram_is_that_of_the_sorted_counts() {
        let counts: Vec<u32> = (0..1000u32).map(|i| (i * 7919) % 97 + 1).chain([5000, 9000]).collect();
        let mut hist = vec![0u32; HIST];
        for &n in &counts {
            hist[(n as usize).min(HIST - 1)] += 1;
        }
        let mut sorted = counts.clone();
        sorted.sort_unstable();
        assert_eq!(percentile_90(&hist), Some(sorted[sorted.len() * 9 / 10]));
        assert_eq!(percentile_90(&vec![0; HIST]), None);
        let mut one = vec![0u32; HIST];
        one[HIST - 1] = 3;
        assert_eq!(percentile_90(&one), Some(HIST as u32 - 1), "the last bucket holds the densest");
    }
}
