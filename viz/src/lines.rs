//! What every line layer (rays, query, bvh) draws and picks with: [`Lines`], over the segment
//! buffers of `draw.rs`, in a ray style of `splat.rs` (lines opaque, or accumulated as alpha or
//! density).

use crate::camera::ViewUniform;
use crate::component::RenderCtx;
use crate::draw::{Blend, LineShape, SegmentBuffers, pick_pipeline, scene_pipeline, shader};

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
