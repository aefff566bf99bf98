//! BVH node boxes for a range of levels (Figure 7), optionally only the nodes the rays of a tree
//! (or all rays) visited, from `ray_nodes`, coloured by level or by visit count.

use arrow::array::AsArray;
use arrow::datatypes::{DataType, Float64Type};
use serde::{Deserialize, Serialize};

use crate::camera::ViewUniform;
use crate::component::{Component, ComponentId, Frame, Layer, LayerRole, Legend, RenderCtx};
use crate::draw::{GpuSegment, SegmentBuffers, pack_rgba};
use crate::legend::colour_map;
use crate::lines::f32_columns;
use crate::sources::Sources;
use crate::{Error, Result};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BoxColour {
    Level,
    Visits,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BvhSettings {
    /// Levels `[min, max]` (root = 0).
    pub levels: [u32; 2],
    /// Only nodes visited by rays (needs `ray_nodes`).
    pub only_visited: bool,
    /// With `only_visited`: only the visits of this tree.
    pub tree: Option<u64>,
    /// With `only_visited`: only the visits of the trees of this pixel (and `sample`).
    pub pixel: Option<[u32; 2]>,
    pub sample: Option<u32>,
    pub colour: BoxColour,
    pub map: String,
    pub line_width: f32,
    pub opacity: f32,
}

impl crate::component::Settings for BvhSettings {
    const KIND: &'static str = "bvh";
}

impl Default for BvhSettings {
    fn default() -> Self {
        BvhSettings {
            levels: [0, 4],
            only_visited: false,
            tree: None,
            pixel: None,
            sample: None,
            colour: BoxColour::Level,
            map: "turbo".into(),
            line_width: 1.0,
            opacity: 0.9,
        }
    }
}

/// The BVH layer.
pub struct BvhBoxes {
    id: ComponentId,
    settings: BvhSettings,
    generation: u64,
    loaded: Option<(Frame, BvhSettings)>,
    boxes: Option<SegmentBuffers>,
    /// Node id of every box, in buffer order (picking).
    nodes: Vec<u64>,
    /// The line pipelines it draws and picks with.
    lines: crate::lines::Lines,
    range: Option<(f64, f64)>,
}

impl BvhBoxes {
    pub fn new(id: ComponentId, sources: &Sources, settings: &serde_json::Value) -> Result<BvhBoxes> {
        if !sources.has_bvh_nodes {
            return Err(Error::Layer { layer: "bvh".into(), message: "the dataset has no bvh_nodes table".into() });
        }
        let mut b = BvhBoxes {
            id,
            settings: BvhSettings::default(),
            generation: 0,
            loaded: None,
            boxes: None,
            nodes: Vec::new(),
            lines: crate::lines::Lines::new(crate::draw::LineShape::Boxes),
            range: None,
        };
        if !settings.is_null() {
            b.set_settings(settings)?;
        }
        if b.settings.only_visited && !sources.has_ray_nodes {
            return Err(Error::Layer {
                layer: "bvh".into(),
                message: "only_visited needs the ray_nodes table (record with --record-visits)".into(),
            });
        }
        Ok(b)
    }

    fn sql(&self, sources: &Sources) -> String {
        let (bvh_nodes, ray_nodes) = (sources.table("bvh_nodes"), sources.table("ray_nodes"));
        let s = &self.settings;
        let [a, b] = s.levels;
        if s.only_visited || s.colour == BoxColour::Visits {
            // The trees whose visits count, said as a ray selection: `ray_nodes` holds tree ids
            // only, so a pixel or sample goes through the tree table.
            use store::scene::col;
            let sel = store::RaySelection::all().only_trees_of(s.tree, s.pixel, s.sample);
            let tree = if sel.is_all() {
                String::new()
            } else if sel.constrained().all(|(c, _)| c == col::TREE_ID) {
                format!(" WHERE {}", sel.to_sql())
            } else {
                format!(" WHERE tree_id IN (SELECT tree_id FROM {} WHERE {})", sources.table("trees"), sel.to_sql())
            };
            let join = if s.only_visited { "JOIN" } else { "LEFT JOIN" };
            format!(
                "SELECT n.level, n.min_x, n.min_y, n.min_z, n.max_x, n.max_y, n.max_z, coalesce(v.visits, 0) AS visits, n.node_id \
                 FROM {bvh_nodes} n {join} (SELECT node_id, count(*) AS visits FROM {ray_nodes}{tree} GROUP BY node_id) v \
                 ON n.node_id = v.node_id WHERE n.level BETWEEN {a} AND {b}"
            )
        } else {
            format!(
                "SELECT level, min_x, min_y, min_z, max_x, max_y, max_z, 0 AS visits, node_id FROM {bvh_nodes} WHERE level BETWEEN {a} AND {b}"
            )
        }
    }

    fn load(&mut self, ctx: &RenderCtx) -> Result<()> {
        let gpu = ctx.gpu;
        let mut rows: Vec<([f64; 3], [f64; 3], f64, u64)> = Vec::new();
        let by_visits = self.settings.colour == BoxColour::Visits;
        ctx.sources.query_batches(&self.sql(ctx.sources), |b| {
            let [x0, y0, z0, x1, y1, z1] = f32_columns(b, ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"])?;
            let level = arrow::compute::cast(b.column(0), &DataType::Float64)?;
            let visits = arrow::compute::cast(b.column(7), &DataType::Float64)?;
            let (level, visits) = (level.as_primitive::<Float64Type>(), visits.as_primitive::<Float64Type>());
            let node = arrow::compute::cast(b.column(8), &DataType::UInt64)?;
            let node = node.as_primitive::<arrow::datatypes::UInt64Type>();
            for r in 0..b.num_rows() {
                let lo = [x0.value(r), y0.value(r), z0.value(r)].map(f64::from);
                let hi = [x1.value(r), y1.value(r), z1.value(r)].map(f64::from);
                if lo.iter().chain(hi.iter()).all(|v| v.is_finite()) {
                    let v = if by_visits { (1.0 + visits.value(r)).log10() } else { level.value(r) };
                    rows.push((lo, hi, v, node.value(r)));
                }
            }
            Ok(())
        })?;
        let (lo, hi) = rows.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| (a.min(r.2), b.max(r.2)));
        self.range = (lo <= hi).then_some((lo, hi));
        let map = colour_map(&self.settings.map)?;
        let mut bufs = SegmentBuffers::new(gpu);
        self.nodes = rows.iter().map(|r| r.3).collect();
        for (a, b, v, _) in rows {
            let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.5 };
            let c = map.eval_continuous(t);
            bufs.push(
                gpu,
                GpuSegment {
                    a: ctx.frame.local(a),
                    color: pack_rgba([c.r, c.g, c.b, 255]),
                    b: ctx.frame.local(b),
                    flags: 0,
                },
            );
        }
        bufs.finish(gpu);
        self.boxes = Some(bufs);
        self.loaded = Some((ctx.frame, self.settings.clone()));
        Ok(())
    }
}

impl Layer for BvhBoxes {
    type Settings = BvhSettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Scene
    }
    fn generation(&self) -> u64 {
        self.generation
    }
    fn current(&self) -> &BvhSettings {
        &self.settings
    }
    fn apply(&mut self, s: BvhSettings) -> Result<()> {
        colour_map(&s.map)?;
        if s.levels[0] > s.levels[1] {
            return Err(Error::Settings(format!("bvh: level range {}..{} is empty", s.levels[0], s.levels[1])));
        }
        crate::component::check_lines("bvh", s.line_width, s.opacity)?;
        crate::component::replace_settings(&mut self.settings, s, &mut self.generation);
        Ok(())
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        if self.loaded.as_ref() != Some(&(ctx.frame, self.settings.clone())) {
            self.load(ctx)?;
        }
        let s = &self.settings;
        let view = ViewUniform::new(ctx.view_proj(), ctx.target.width, ctx.target.height, s.line_width, s.opacity, 0.0);
        self.lines.draw(ctx, &view, &[self.boxes.as_ref()], false);
        Ok(())
    }
    fn pick(&mut self, ctx: &mut crate::component::PickCtx) -> Result<bool> {
        Ok(self.lines.pick(ctx, self.settings.line_width, &[self.boxes.as_ref()]))
    }
    fn picked(&self, index: u32) -> Option<crate::component::Picked> {
        let node = *self.nodes.get(index as usize)?;
        Some(crate::component::Picked::Node { node })
    }
    fn legend(&self) -> Vec<Legend> {
        let Some((min, max)) = self.range else { return Vec::new() };
        let title = match self.settings.colour {
            BoxColour::Level => "BVH level".to_string(),
            BoxColour::Visits => "log10(1 + visits)".to_string(),
        };
        vec![Legend::ColourBar { title, map: self.settings.map.clone(), min, max, log: false }]
    }
    fn report(&self) -> Vec<String> {
        vec![format!("bvh: {} boxes", self.boxes.as_ref().map_or(0, |b| b.count))]
    }
}
