//! What every line layer (rays, query, bvh) draws and picks with: [`Lines`], over the segment
//! buffers of `draw.rs`, in a ray style of `splat.rs` (lines opaque, or accumulated as alpha or
//! density), and the rows they draw made into segments ([`SegmentBuilder`], [`f32_columns`]).

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::Float32Type;

use crate::camera::ViewUniform;
use crate::component::{Frame, RenderCtx};
use crate::draw::{Blend, GpuSegment, LineShape, SegmentBuffers, pack_rgba, pick_pipeline, scene_pipeline, shader};
use crate::{Error, Result};

/// What every line layer (rays, query, bvh) draws and picks with: its colour and pick pipelines,
/// made on first use, over sets of [`SegmentBuffers`].
pub struct Lines {
    shape: LineShape,
    pipeline: Option<wgpu::RenderPipeline>,
    pick: Option<wgpu::RenderPipeline>,
    /// The alpha and density styles' buffers and pipelines (`splat.rs`), made on first use.
    splat: Option<crate::splat::Splat>,
}

impl Lines {
    pub fn new(shape: LineShape) -> Lines {
        Lines { shape, pipeline: None, pick: None, splat: None }
    }

    /// [`Lines::draw`] in a ray style: `lines` draws as `draw` does; `alpha` and `density`
    /// accumulate every set (the first thinned to the preview budget when `preview`) and
    /// resolve into the layer. Returns what the styled draw found.
    pub fn draw_styled(
        &mut self,
        ctx: &RenderCtx,
        view: &ViewUniform,
        sets: &[Option<&SegmentBuffers>],
        preview: bool,
        style: &crate::splat::StyleParams,
    ) -> crate::Result<crate::splat::Drawn> {
        if style.style == crate::splat::RayStyle::Lines {
            self.draw(ctx, view, sets, preview);
            return Ok(crate::splat::Drawn { opacity: style.opacity, ..Default::default() });
        }
        let splat = match &mut self.splat {
            Some(s) => s,
            None => self.splat.insert(crate::splat::Splat::new(ctx.gpu, self.shape)?),
        };
        // Density counts rays per pixel: lines one pixel wide, whatever the layer's width.
        let mut view = *view;
        if style.style == crate::splat::RayStyle::Density {
            view.viewport[2] = 1.0;
        }
        let strided: Vec<(&SegmentBuffers, u32)> = sets
            .iter()
            .enumerate()
            .filter_map(|(i, s)| s.map(|s| (s, if preview && i == 0 { s.stride_for(ctx.preview) } else { 1 })))
            .collect();
        splat.draw(ctx, &view, &strided, style)
    }

    /// Draws `sets` into the layer (the first clears it; with `preview`, the first is thinned to
    /// the layer's preview budget): lines `view.params`' width and opacity, as `view` says.
    pub fn draw(&mut self, ctx: &RenderCtx, view: &ViewUniform, sets: &[Option<&SegmentBuffers>], preview: bool) {
        let shape = self.shape;
        let p = self.pipeline.get_or_insert_with(|| {
            let m = shader(ctx.gpu, "lines", include_str!("shaders/lines.wgsl"));
            scene_pipeline(ctx.gpu, &m, shape.vertex_entry(), "fs_line", Blend::Opaque)
        });
        for (i, set) in sets.iter().enumerate() {
            let Some(set) = set else { continue };
            let stride = if preview && i == 0 { set.stride_for(ctx.preview) } else { 1 };
            set.draw_strided(ctx.gpu, ctx, p, view, shape.per_item(), i == 0, stride);
        }
    }

    /// Picking: the ids of `sets`' items, numbered across the sets in order; false when there is
    /// nothing to pick.
    pub fn pick(&mut self, ctx: &crate::component::PickCtx, line_width: f32, sets: &[Option<&SegmentBuffers>]) -> bool {
        let shape = self.shape;
        pick_sets(&mut self.pick, ctx, shape.vertex_entry(), shape.per_item(), line_width, sets)
    }
}

/// Picking for layers of line segments or boxes (`vs`: `vs_seg` or `vs_box`, `per` vertices
/// each): the pick pipeline is made on first use in `slot`, then the ids of every set are drawn,
/// numbered on from one set to the next, lines at least 3 pixels wide so thin ones are easy to hit.
/// Returns whether anything was drawn.
fn pick_sets(
    slot: &mut Option<wgpu::RenderPipeline>,
    ctx: &crate::component::PickCtx,
    vs: &str,
    per: u32,
    line_width: f32,
    sets: &[Option<&SegmentBuffers>],
) -> bool {
    let p = slot.get_or_insert_with(|| {
        let m = shader(ctx.gpu, "lines", include_str!("shaders/lines.wgsl"));
        pick_pipeline(ctx.gpu, &m, vs)
    });
    let view = ctx.view(line_width.max(3.0));
    let mut base = 0u32;
    let mut any = false;
    for set in sets.iter().flatten() {
        set.draw_ids(ctx.gpu, ctx.target, p, &view, per, base);
        base = base.saturating_add(set.count as u32);
        any = true;
    }
    any
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
