//! The rows of any SQL query drawn in scene space: rows with origin/direction (and `t`) as
//! segments, rows with a position (`x, y, z`) as points, coloured by a chosen column through a
//! colour map (numbers) or a palette (names), with a legend.

use std::collections::BTreeMap;

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float64Type};
use serde::{Deserialize, Serialize};

use crate::camera::ViewUniform;
use crate::component::{Component, ComponentId, Frame, Layer, LayerRole, Legend, RenderCtx};
use crate::draw::SegmentBuffers;
use crate::legend::colour_map;
use crate::lines::{SegmentBuilder, f32_columns, kind_names};
use crate::splat::{DensityScale, Drawn, RayStyle, StyleParams};
use crate::{Error, Result};

const SEGMENT_COLUMNS: [&str; 6] = ["origin_x", "origin_y", "origin_z", "dir_x", "dir_y", "dir_z"];
const POINT_COLUMNS: [&str; 3] = ["x", "y", "z"];

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct QuerySettings {
    pub sql: String,
    /// Column that colours the rows (`None`: one colour).
    pub colour_by: Option<String>,
    pub map: String,
    pub line_width: f32,
    pub opacity: f32,
    /// How the rows are drawn: `lines`, `alpha` or `density` (as the rays layer's).
    pub style: RayStyle,
    /// The density style's scale: `log` or `linear`.
    pub density_scale: DensityScale,
    /// The alpha style lowers `opacity` so that nine in ten covered pixels stay at most half
    /// covered (what lies under the rays shows however many there are); false: `opacity` as is.
    pub auto_opacity: bool,
    /// The density style's colour map (`None`: the rows' colours, brightness by density).
    pub density_map: Option<String>,
}

impl crate::component::Settings for QuerySettings {
    const KIND: &'static str = "query";
    fn choices() -> Vec<(&'static str, &'static [&'static str])> {
        vec![("map", &crate::legend::COLOUR_MAPS), ("style", RayStyle::NAMES), ("density_scale", DensityScale::NAMES)]
    }
}

impl Default for QuerySettings {
    fn default() -> Self {
        QuerySettings {
            sql: String::new(),
            colour_by: None,
            map: "plasma".into(),
            line_width: 2.0,
            opacity: 1.0,
            style: RayStyle::Lines,
            density_scale: DensityScale::Log,
            density_map: None,
            auto_opacity: true,
        }
    }
}

impl QuerySettings {
    fn style_params(&self) -> StyleParams {
        StyleParams {
            style: self.style,
            scale: self.density_scale,
            map: self.density_map.clone(),
            opacity: self.opacity,
            auto_opacity: self.auto_opacity,
        }
    }
}

/// At most this many distinct integer values are told apart by a categorical legend (more get a
/// colour bar).
const MAX_CATEGORIES: usize = 12;

enum Values {
    None,
    Numbers(Vec<f64>),
    Names(Vec<Option<String>>),
}

/// The query layer.
pub struct Query {
    id: ComponentId,
    settings: QuerySettings,
    generation: u64,
    loaded: Option<(Frame, QuerySettings)>,
    segments: Option<SegmentBuffers>,
    /// The line pipelines it draws and picks with.
    lines: crate::lines::Lines,
    legend: Vec<Legend>,
    rows: u64,
    skipped: u64,
    /// Result row of every drawn segment or point (picking).
    row_of: Vec<u64>,
    /// What the last styled draw found (the density colour bar's range, the alpha opacity).
    drawn: Drawn,
}

fn palette(i: usize) -> [u8; 4] {
    let c = colorous::TABLEAU10[i % colorous::TABLEAU10.len()];
    [c.r, c.g, c.b, 255]
}

impl Query {
    pub fn new(id: ComponentId, sources: &crate::sources::Sources, settings: &serde_json::Value) -> Result<Query> {
        sources.can_query().map_err(|message| Error::Layer { layer: "query".into(), message })?;
        let mut q = Query {
            id,
            settings: QuerySettings::default(),
            generation: 0,
            loaded: None,
            segments: None,
            lines: crate::lines::Lines::new(crate::draw::LineShape::Segments),
            legend: Vec::new(),
            rows: 0,
            skipped: 0,
            row_of: Vec::new(),
            drawn: Drawn::default(),
        };
        q.set_settings(settings)?;
        Ok(q)
    }

    fn load(&mut self, ctx: &RenderCtx) -> Result<()> {
        let gpu = ctx.gpu;
        let batches = ctx.sources.query(&self.settings.sql)?;
        let Some(schema) = batches.first().map(|b| b.schema()) else {
            self.segments = Some(SegmentBuffers::new(gpu));
            self.loaded = Some((ctx.frame, self.settings.clone()));
            return Ok(());
        };
        let has = |n: &[&str]| n.iter().all(|c| schema.index_of(c).is_ok());
        let as_segments = has(&SEGMENT_COLUMNS);
        if !as_segments && !has(&POINT_COLUMNS) {
            return Err(Error::Columns(format!(
                "the query layer needs origin_x, origin_y, origin_z, dir_x, dir_y, dir_z (and t) for segments, or x, y, z for points; the query returned {}",
                schema.fields().iter().map(|f| f.name().as_str()).collect::<Vec<_>>().join(", ")
            )));
        }
        let Colouring { values: all, lo, hi, categories: categories_in_order } = self.colouring(&batches)?;
        let map = colour_map(&self.settings.map)?;
        // Categories numbered in legend order (sorted values for numbers, else first seen), with
        // the rows drawn of each.
        let mut names: BTreeMap<String, usize> =
            categories_in_order.iter().enumerate().map(|(i, k)| (k.clone(), i)).collect();
        let mut counts: BTreeMap<String, u64> = BTreeMap::new();
        let mut bufs = SegmentBuffers::new(gpu);
        let mut builder = SegmentBuilder::new(ctx.sources.bounds, ctx.frame);
        let mut rows = 0;
        let mut row_of = Vec::new();
        for (b, vals) in batches.iter().zip(&all) {
            let first = rows;
            rows += b.num_rows() as u64;
            let mut colour = |r: usize, names: &mut BTreeMap<String, usize>| -> [u8; 4] {
                match vals {
                    Values::None => [255, 120, 0, 255],
                    Values::Numbers(n) if n[r].is_finite() => {
                        let t = if hi > lo { (n[r] - lo) / (hi - lo) } else { 0.5 };
                        let c = map.eval_continuous(t);
                        [c.r, c.g, c.b, 255]
                    }
                    Values::Numbers(_) => [128, 128, 128, 255],
                    Values::Names(s) => {
                        let k = s[r].clone().unwrap_or_else(|| "null".into());
                        let next = names.len();
                        *counts.entry(k.clone()).or_default() += 1;
                        palette(*names.entry(k).or_insert(next))
                    }
                }
            };
            if as_segments {
                let [ox, oy, oz, dx, dy, dz] = f32_columns(b, SEGMENT_COLUMNS)?;
                let t = match b.column_by_name("t") {
                    Some(_) => {
                        let [t] = f32_columns(b, ["t"])?;
                        Some(t)
                    }
                    None => None,
                };
                for r in 0..b.num_rows() {
                    let tv =
                        t.as_ref().map_or(f32::INFINITY, |t| if t.is_null(r) { f32::INFINITY } else { t.value(r) });
                    let Some((a, e)) = builder.end(
                        [ox.value(r), oy.value(r), oz.value(r)],
                        [dx.value(r), dy.value(r), dz.value(r)],
                        tv,
                    ) else {
                        continue;
                    };
                    let c = colour(r, &mut names);
                    bufs.push(gpu, builder.segment(a, e, c, 0));
                    row_of.push(first + r as u64);
                }
            } else {
                let cols: Vec<_> = POINT_COLUMNS
                    .iter()
                    .map(|n| arrow::compute::cast(b.column_by_name(n).expect("checked above"), &DataType::Float64))
                    .collect::<std::result::Result<_, _>>()?;
                let p: Vec<_> = cols.iter().map(|c| c.as_primitive::<Float64Type>()).collect();
                for r in 0..b.num_rows() {
                    let q = [p[0].value(r), p[1].value(r), p[2].value(r)];
                    if q.iter().any(|v| !v.is_finite()) || p.iter().any(|c| c.is_null(r)) {
                        builder.skipped += 1;
                        continue;
                    }
                    let c = colour(r, &mut names);
                    bufs.push(gpu, builder.segment(q, q, c, 0));
                    row_of.push(first + r as u64);
                }
            }
        }
        bufs.finish(gpu);
        self.rows = rows;
        self.row_of = row_of;
        self.skipped = builder.skipped;
        self.legend = self.legend_of(lo, hi, names, &counts);
        self.segments = Some(bufs);
        self.loaded = Some((ctx.frame, self.settings.clone()));
        Ok(())
    }
}

/// How a query's rows are coloured: each batch's values of `colour_by`, their range where they are
/// numbers, and the categories in legend order (sorted values where a number column holds few).
struct Colouring {
    values: Vec<Values>,
    lo: f64,
    hi: f64,
    categories: Vec<String>,
}

impl Query {
    /// The colouring of `batches` by the `colour_by` column.
    fn colouring(&self, batches: &[RecordBatch]) -> Result<Colouring> {
        let mut categories_in_order: Vec<String> = Vec::new();
        let values = |b: &RecordBatch| -> Result<Values> {
            let Some(name) = &self.settings.colour_by else { return Ok(Values::None) };
            let c = b
                .column_by_name(name)
                .ok_or_else(|| Error::Columns(format!("colour_by column `{name}` is not in the query's result")))?;
            let numeric = c.data_type().is_numeric() || matches!(c.data_type(), DataType::Boolean);
            Ok(if numeric {
                let f = arrow::compute::cast(c, &DataType::Float64)?;
                let f = f.as_primitive::<Float64Type>();
                Values::Numbers((0..f.len()).map(|i| if f.is_null(i) { f64::NAN } else { f.value(i) }).collect())
            } else {
                Values::Names(kind_names(c.as_ref())?)
            })
        };
        let mut all: Vec<Values> = batches.iter().map(values).collect::<Result<_>>()?;
        let (lo, hi) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |acc, v| match v {
            Values::Numbers(n) => n.iter().filter(|x| x.is_finite()).fold(acc, |(a, b), &x| (a.min(x), b.max(x))),
            _ => acc,
        });
        // A number column of a few distinct values (a constant, depths, material ids) is a set of
        // categories: each value gets its own colour and a count, not a place on a colour bar.
        if lo <= hi {
            let mut distinct: Vec<f64> = Vec::new();
            let few = all.iter().all(|v| match v {
                Values::Numbers(n) => n.iter().filter(|x| x.is_finite()).all(|&x| {
                    if !distinct.contains(&x) {
                        distinct.push(x);
                    }
                    distinct.len() <= MAX_CATEGORIES
                }),
                _ => true,
            });
            if few && (distinct.len() == 1 || distinct.iter().all(|x| x.fract() == 0.0)) {
                all = all
                    .into_iter()
                    .map(|v| match v {
                        Values::Numbers(n) => Values::Names(
                            n.into_iter().map(|x| x.is_finite().then(|| crate::legend::label(x))).collect(),
                        ),
                        other => other,
                    })
                    .collect();
                distinct.sort_by(f64::total_cmp);
                categories_in_order = distinct.iter().map(|x| crate::legend::label(*x)).collect();
            }
        }
        let (lo, hi) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |acc, v| match v {
            Values::Numbers(n) => n.iter().filter(|x| x.is_finite()).fold(acc, |(a, b), &x| (a.min(x), b.max(x))),
            _ => acc,
        });
        Ok(Colouring { values: all, lo, hi, categories: categories_in_order })
    }

    /// The legend of a colouring: a colour bar over `lo..hi`, or the categories drawn with their
    /// counts.
    fn legend_of(
        &self,
        lo: f64,
        hi: f64,
        names: BTreeMap<String, usize>,
        counts: &BTreeMap<String, u64>,
    ) -> Vec<Legend> {
        match (&self.settings.colour_by, lo <= hi, names.is_empty()) {
            (Some(c), true, _) => {
                vec![Legend::ColourBar {
                    title: c.clone(),
                    map: self.settings.map.clone(),
                    min: lo,
                    max: hi,
                    log: false,
                }]
            }
            (Some(c), false, false) => {
                let mut e: Vec<(usize, String)> = names.into_iter().map(|(k, i)| (i, k)).collect();
                e.sort();
                vec![Legend::Swatches {
                    title: c.clone(),
                    entries: e
                        .into_iter()
                        .filter(|(_, k)| counts.contains_key(k))
                        .map(|(i, k)| (format!("{k} ({})", counts[&k]), palette(i)))
                        .collect(),
                }]
            }
            _ => Vec::new(),
        }
    }
}

impl Layer for Query {
    type Settings = QuerySettings;

    fn id(&self) -> ComponentId {
        self.id
    }
    fn role(&self) -> LayerRole {
        LayerRole::Scene
    }
    fn reads_occluder(&self) -> bool {
        self.settings.style != RayStyle::Lines
    }
    fn generation(&self) -> u64 {
        self.generation
    }
    fn current(&self) -> &QuerySettings {
        &self.settings
    }
    fn apply(&mut self, s: QuerySettings) -> Result<()> {
        if s.sql.trim().is_empty() {
            return Err(Error::Settings("query: the layer needs a SQL query (--sql)".into()));
        }
        colour_map(&s.map)?;
        if let Some(m) = &s.density_map {
            colour_map(m)?;
        }
        crate::component::check_lines("query", s.line_width, s.opacity)?;
        crate::component::replace_settings(&mut self.settings, s, &mut self.generation);
        Ok(())
    }
    fn render(&mut self, ctx: &mut RenderCtx) -> Result<()> {
        if self.loaded.as_ref() != Some(&(ctx.frame, self.settings.clone())) {
            self.load(ctx)?;
        }
        let s = &self.settings;
        let view = ViewUniform::new(ctx.view_proj(), ctx.target.width, ctx.target.height, s.line_width, s.opacity, 1.0);
        self.drawn = self.lines.draw_styled(ctx, &view, &[self.segments.as_ref()], false, &s.style_params())?;
        Ok(())
    }
    fn pick(&mut self, ctx: &mut crate::component::PickCtx) -> Result<bool> {
        Ok(self.lines.pick(ctx, self.settings.line_width, &[self.segments.as_ref()]))
    }
    fn picked(&self, index: u32) -> Option<crate::component::Picked> {
        let row = *self.row_of.get(index as usize)?;
        Some(crate::component::Picked::Row { row })
    }
    fn legend(&self) -> Vec<Legend> {
        let s = self.settings.style_params();
        let mut l = if s.style == RayStyle::Density && s.map.is_some() { Vec::new() } else { self.legend.clone() };
        l.extend(crate::components::rays::density_legend(&s, self.drawn.density));
        l
    }
    fn report(&self) -> Vec<String> {
        let mut r = vec![format!("query: {} rows drawn", self.segments.as_ref().map_or(0, |s| s.count))];
        r.extend(crate::splat::style_report("query", &self.settings.style_params(), &self.drawn));
        if self.skipped > 0 {
            r.push(format!("query: skipped {} of {} rows with NaN or infinite positions", self.skipped, self.rows));
        }
        r
    }
}
