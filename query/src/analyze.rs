//! Canned analyses over a session: each returns a markdown report and the per-pixel or per-tile
//! grids worth drawing (the command line writes them as PNG heatmaps).
//!
//! - [`coherence`]: direction coherence and origin spread by kind and depth, and a what-if packet
//!   analysis: rays of one kind and bounce grouped into packets of `width` lanes under several
//!   orders (trace order, Morton order of origins, direction octant, material), with each order's
//!   directional coherence, origin spread and — when the trace recorded visited nodes — SIMD
//!   utilization of packet traversal (lanes that need a node over lanes that step through it).
//! - [`bvh`]: nodes visited, boxes and triangles tested per ray by kind and depth; false-positive
//!   leaf tests (a ray enters a leaf's box but hits none of its triangles) by kind and the leaves
//!   with most of them; the hottest subtrees by kind; nodes visited per camera ray per pixel.
//! - [`bugs`]: shadow rays aiming at no light (the paper's Figure 1 bug) by depth, by the surface
//!   they leave and by pixel; non-finite and non-unit directions; suspected self-intersections.
//! - [`diff`]: two traces side by side by kind, by depth and by image tile, with the change.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::sync::Arc;

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::{DataType, Float64Type, UInt32Type, UInt64Type};
use arrow::util::display::{ArrayFormatter, FormatOptions};

use crate::functions::{Coherence, Spread, XyzStat};
use crate::{Engine, Error, Result};

/// A grid of values to draw (NaN where there is no data), row-major from the top-left pixel.
#[derive(Clone, Debug)]
pub struct Grid {
    /// File stem of the picture (`nodes_per_pixel` → `nodes_per_pixel.png`).
    pub name: String,
    /// What a value means.
    pub title: String,
    pub width: usize,
    pub height: usize,
    /// Pixels one cell spans along each axis (1 per pixel, the tile size per tile).
    pub cell: usize,
    pub values: Vec<f64>,
}

impl Grid {
    /// Smallest and largest finite value.
    pub fn range(&self) -> Option<(f64, f64)> {
        let mut it = self.values.iter().copied().filter(|v| v.is_finite());
        let first = it.next()?;
        Some(it.fold((first, first), |(lo, hi), v| (lo.min(v), hi.max(v))))
    }
}

/// The cells a grid picture has across and down, and the pixels each spans.
#[derive(Clone, Copy, Debug)]
struct Cells {
    width: usize,
    height: usize,
    cell: usize,
}

impl Cells {
    /// One cell per pixel of a `(width, height)` image.
    fn pixels((width, height): (usize, usize)) -> Cells {
        Cells { width, height, cell: 1 }
    }
}

/// A report: markdown text and the grids it refers to.
#[derive(Clone, Debug, Default)]
pub struct Report {
    pub markdown: String,
    pub grids: Vec<Grid>,
}

impl Report {
    fn heading(&mut self, text: &str) {
        let _ = writeln!(self.markdown, "\n## {text}\n");
    }

    fn para(&mut self, text: &str) {
        let _ = writeln!(self.markdown, "{text}\n");
    }

    /// Adds a picture of the rows (x, y, value) of `sql` on a `size` grid under `heading`; nothing
    /// when the grid is empty (a trace without trees).
    async fn add_grid(
        &mut self,
        ctx: &Engine,
        heading: Option<&str>,
        sql: &str,
        cells: Cells,
        name: &str,
        title: &str,
    ) -> Result<()> {
        let size = (cells.width, cells.height);
        if size.0 == 0 || size.1 == 0 {
            return Ok(());
        }
        if let Some(h) = heading {
            self.heading(h);
        }
        let mut g = grid(ctx, sql, size, name, title).await?;
        g.cell = cells.cell.max(1);
        self.grid(g);
        Ok(())
    }

    fn grid(&mut self, grid: Grid) {
        let range = match grid.range() {
            Some((lo, hi)) => format!("{} to {}", num(lo), num(hi)),
            None => "no data".into(),
        };
        let _ = writeln!(
            self.markdown,
            "![{}]({}.png)\n\n*{}: {}×{}, dark (low) to bright (high), {range} (colour bar beside it); grey where there is no data.*\n",
            grid.title, grid.name, grid.title, grid.width, grid.height
        );
        self.grids.push(grid);
    }
}

/// Options of the coherence analysis.
#[derive(Clone, Debug)]
pub struct CoherenceOptions {
    /// Lanes per packet.
    pub width: usize,
    /// Orders to compare: `trace`, `morton`, `octant`, `material`.
    pub orders: Vec<String>,
    /// Only rays of this kind (all kinds when None).
    pub kind: Option<String>,
}

impl Default for CoherenceOptions {
    fn default() -> Self {
        Self { width: 8, orders: ["trace", "morton", "octant", "material"].map(String::from).to_vec(), kind: None }
    }
}

async fn run(ctx: &Engine, sql: &str) -> Result<Vec<RecordBatch>> {
    ctx.collect(sql).await
}

async fn has_table(ctx: &Engine, name: &str) -> bool {
    ctx.catalog().await.is_ok_and(|c| c.tables.iter().any(|t| t == name))
}

/// Whether `table` has `column` (a payload column some traces record and others do not).
/// Asked by planning a query of the column (a distributed engine's schemas may qualify names).
async fn has_column(ctx: &Engine, table: &str, column: &str) -> Result<bool> {
    match ctx.stream(&format!("SELECT {column} FROM {table} LIMIT 0")).await {
        Ok(_) => Ok(true),
        Err(e) if e.to_string().contains("No field named") => Ok(false),
        Err(e) => Err(e),
    }
}

/// The rays with a `material` column (the material of the surface each ray hit), as the
/// analyses read them: rtvtk's tracers record it as a payload column; for other renderers'
/// traces it is looked up in the `triangles` table by `prim`, and is null without one.
async fn rays_with_material(ctx: &Engine) -> Result<String> {
    Ok(if has_column(ctx, "rays", "material").await? {
        "rays".into()
    } else if has_table(ctx, store::scene::TRIANGLES_TABLE).await {
        "(SELECT r.*, tri.material FROM rays r LEFT JOIN triangles tri ON r.prim = tri.prim)".into()
    } else {
        "(SELECT *, CAST(NULL AS INT UNSIGNED) AS material FROM rays)".into()
    })
}

/// A number with 4 significant digits (integers as they are).
fn num(v: f64) -> String {
    if !v.is_finite() {
        return format!("{v}");
    }
    if v == v.trunc() && v.abs() < 1e15 {
        return format!("{}", v as i64);
    }
    let digits = (3 - v.abs().log10().floor() as i32).clamp(0, 12) as usize;
    format!("{v:.digits$}")
}

/// The batches as a markdown table.
fn markdown(batches: &[RecordBatch]) -> Result<String> {
    let Some(first) = batches.first() else { return Ok("*(no rows)*\n".into()) };
    let schema = first.schema();
    let mut out = String::new();
    let names: Vec<&str> = schema.fields().iter().map(|f| f.name().as_str()).collect();
    let _ = writeln!(out, "| {} |", names.join(" | "));
    let _ = writeln!(out, "|{}", "---|".repeat(names.len()));
    let mut rows = 0;
    for b in batches {
        let formatters = b
            .columns()
            .iter()
            .map(|c| ArrayFormatter::try_new(c.as_ref(), &FormatOptions::default()))
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| Error::DataFusion(e.into()))?;
        for r in 0..b.num_rows() {
            // Floats with 4 significant digits, the rest as Arrow displays them; NULL as empty.
            let cells: Vec<String> = b
                .columns()
                .iter()
                .zip(&formatters)
                .map(|(c, f)| match c.is_null(r) {
                    true => String::new(),
                    false => float_at(c.as_ref(), r).map_or_else(|| f.value(r).to_string(), num),
                })
                .collect();
            let _ = writeln!(out, "| {} |", cells.join(" | "));
            rows += 1;
        }
    }
    if rows == 0 {
        return Ok("*(no rows)*\n".into());
    }
    Ok(out)
}

fn float_at(c: &dyn Array, r: usize) -> Option<f64> {
    match c.data_type() {
        DataType::Float64 => Some(c.as_primitive::<Float64Type>().value(r)),
        DataType::Float32 => Some(f64::from(c.as_primitive::<arrow::datatypes::Float32Type>().value(r))),
        _ => None,
    }
}

/// A single number from a query (NaN when NULL or absent).
async fn scalar(ctx: &Engine, sql: &str) -> Result<f64> {
    let batches = run(ctx, &format!("SELECT CAST(({sql}) AS DOUBLE) AS v")).await?;
    Ok(batches
        .first()
        .filter(|b| b.num_rows() > 0)
        .and_then(|b| b.column(0).as_primitive_opt::<Float64Type>().filter(|a| a.is_valid(0)).map(|a| a.value(0)))
        .unwrap_or(f64::NAN))
}

/// Image size: from the trees' pixels.
async fn image_size(ctx: &Engine, schema: &str) -> Result<(usize, usize)> {
    let w = scalar(ctx, &format!("SELECT max(pixel_x) + 1 FROM {schema}trees")).await?;
    let h = scalar(ctx, &format!("SELECT max(pixel_y) + 1 FROM {schema}trees")).await?;
    if !(w.is_finite() && h.is_finite()) {
        return Ok((0, 0));
    }
    Ok((w as usize, h as usize))
}

/// A `w` × `h` grid from rows (x, y, value) of a query.
async fn grid(ctx: &Engine, sql: &str, (w, h): (usize, usize), name: &str, title: &str) -> Result<Grid> {
    let mut values = vec![f64::NAN; w * h];
    for b in run(ctx, sql).await? {
        let get = |i: usize| -> Result<Vec<f64>> {
            let c = arrow::compute::cast(b.column(i), &DataType::Float64).map_err(|e| Error::DataFusion(e.into()))?;
            let c = c.as_primitive::<Float64Type>();
            Ok((0..c.len()).map(|r| if c.is_valid(r) { c.value(r) } else { f64::NAN }).collect())
        };
        let (xs, ys, vs) = (get(0)?, get(1)?, get(2)?);
        for ((x, y), v) in xs.into_iter().zip(ys).zip(vs) {
            if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h {
                values[y as usize * w + x as usize] = v;
            }
        }
    }
    Ok(Grid { name: name.into(), title: title.into(), width: w, height: h, cell: 1, values })
}

/// Direction coherence and origin spread by kind and depth, and the packet what-if analysis.
pub async fn coherence(ctx: &Engine, opts: &CoherenceOptions) -> Result<Report> {
    let mut rep = Report::default();
    rep.para("# Ray coherence");
    let diag = scene_diagonal(ctx).await?;
    let kind_filter = match &opts.kind {
        Some(k) => format!("WHERE kind = '{}'", k.replace('\'', "''")),
        None => String::new(),
    };
    rep.heading("By kind and depth");
    rep.para(
        "`dir_coherence`: mean resultant length of the directions (1: parallel; near 0: spread over the sphere). \
         `origin_spread`: RMS distance of the origins from their centroid, over the scene diagonal.",
    );
    let t = run(
        ctx,
        &format!(
            "SELECT kind, depth, count(*) AS rays, dir_coherence(dir_x, dir_y, dir_z) AS dir_coherence, \
             origin_spread(origin_x, origin_y, origin_z) / {diag} AS origin_spread \
             FROM rays {kind_filter} GROUP BY kind, depth ORDER BY kind, depth"
        ),
    )
    .await?;
    rep.para(&markdown(&t)?);

    let width = opts.width.max(1);
    rep.heading(&format!("Packets of {width} lanes under different orders"));
    let visits = if has_table(ctx, "ray_nodes").await { Some(load_visits(ctx).await?) } else { None };
    rep.para(&format!(
        "Rays of one kind and depth (one wavefront bounce) are sorted by the order's key and cut into packets of \
         {width}. Per packet: `dir_coherence` of its directions, `origin_spread` of its origins (over the scene \
         diagonal){}. Means over packets; the best order per kind is the one with the highest coherence{}.",
        if visits.is_some() {
            ", and `simd_utilization`: the lanes that need each node the packet steps through, over the packet's \
             lanes times those nodes (1: every lane needs every node; 1/W: no sharing)"
        } else {
            " (record with `--record-visits` to also get SIMD utilization of packet traversal)"
        },
        if visits.is_some() { " and utilization" } else { "" }
    ));
    let mut table = String::from(
        "| order | kind | packets | dir_coherence | origin_spread | simd_utilization |\n|---|---|---|---|---|---|\n",
    );
    for order in &opts.orders {
        let key = match order.as_str() {
            "trace" => "tree_id",
            "morton" => "morton3(origin_x, origin_y, origin_z, 10)",
            "octant" => "octant(dir_x, dir_y, dir_z)",
            "material" => "material",
            other => {
                return Err(Error::BadArgument(format!(
                    "packet order {other:?}: expected trace, morton, octant or material"
                )));
            }
        };
        let from = if order == "material" { rays_with_material(ctx).await? } else { "rays".into() };
        let sql = format!(
            "SELECT kind, depth, tree_id, ray, dir_x, dir_y, dir_z, origin_x, origin_y, origin_z FROM {from} AS rays \
             {kind_filter} ORDER BY kind, depth, {key}, tree_id, ray"
        );
        let stats = packet_stats(&run(ctx, &sql).await?, width, visits.as_ref(), diag)?;
        for (kind, s) in stats {
            let n = s.packets.max(1) as f64;
            let util = if visits.is_some() { num(s.util / n) } else { "—".into() };
            let _ = writeln!(
                table,
                "| {order} | {kind} | {} | {} | {} | {util} |",
                s.packets,
                num(s.coherence / n),
                num(s.spread / n)
            );
        }
    }
    rep.para(&table);
    let size = image_size(ctx, "").await?;
    rep.add_grid(
        ctx,
        Some("Coherence of each pixel's secondary rays"),
        "SELECT pixel_x, pixel_y, dir_coherence(dir_x, dir_y, dir_z) FROM rays WHERE depth = 1 GROUP BY pixel_x, pixel_y",
        Cells::pixels(size),
        "coherence_per_pixel",
        "dir_coherence of the depth-1 rays of each pixel",
    )
    .await?;
    Ok(rep)
}

/// The scene diagonal (1 when unknown).
async fn scene_diagonal(ctx: &Engine) -> Result<f64> {
    let d = scalar(
        ctx,
        "SELECT sqrt(power(max(max_x) - min(min_x), 2) + power(max(max_y) - min(min_y), 2) + power(max(max_z) - min(min_z), 2)) \
         FROM bvh_nodes WHERE node_id = 0",
    )
    .await
    .unwrap_or(f64::NAN);
    Ok(if d.is_finite() && d > 0.0 { d } else { 1.0 })
}

/// Every ray's visited nodes, by (tree, ray).
async fn load_visits(ctx: &Engine) -> Result<HashMap<(u64, u32), Vec<u32>>> {
    let mut out: HashMap<(u64, u32), Vec<u32>> = HashMap::new();
    for b in run(ctx, "SELECT tree_id, ray, node_id FROM ray_nodes").await? {
        let (t, r, n) = (col_u64(&b, 0)?, col_u32(&b, 1)?, col_u32(&b, 2)?);
        for i in 0..b.num_rows() {
            out.entry((t.value(i), r.value(i))).or_default().push(n.value(i));
        }
    }
    Ok(out)
}

fn col_u64(b: &RecordBatch, i: usize) -> Result<&arrow::array::UInt64Array> {
    b.column(i).as_primitive_opt::<UInt64Type>().ok_or_else(|| Error::BadArgument(format!("column {i} is not UInt64")))
}

fn col_u32(b: &RecordBatch, i: usize) -> Result<&arrow::array::UInt32Array> {
    b.column(i).as_primitive_opt::<UInt32Type>().ok_or_else(|| Error::BadArgument(format!("column {i} is not UInt32")))
}

#[derive(Default)]
struct PacketSums {
    packets: u64,
    coherence: f64,
    spread: f64,
    util: f64,
}

/// Cuts rows (sorted by kind, depth, key) into packets within each (kind, depth) and sums the
/// per-packet measures by kind.
fn packet_stats(
    batches: &[RecordBatch],
    width: usize,
    visits: Option<&HashMap<(u64, u32), Vec<u32>>>,
    diag: f64,
) -> Result<Vec<(String, PacketSums)>> {
    let mut out: Vec<(String, PacketSums)> = Vec::new();
    let mut lanes: Vec<(u64, u32, [f64; 3], [f64; 3])> = Vec::with_capacity(width);
    let mut group: Option<(String, u16)> = None;
    let flush = |out: &mut Vec<(String, PacketSums)>, kind: &str, lanes: &mut Vec<(u64, u32, [f64; 3], [f64; 3])>| {
        if lanes.is_empty() {
            return;
        }
        if out.last().is_none_or(|(k, _)| k != kind) {
            out.push((kind.to_string(), PacketSums::default()));
        }
        let Some((_, s)) = out.last_mut() else { return };
        s.packets += 1;
        s.coherence += packet_coherence(lanes.iter().map(|l| l.3));
        s.spread += packet_spread(lanes.iter().map(|l| l.2)) / diag;
        if let Some(v) = visits {
            let mut need: HashMap<u32, u32> = HashMap::new();
            for l in lanes.iter() {
                for n in v.get(&(l.0, l.1)).map(Vec::as_slice).unwrap_or_default() {
                    *need.entry(*n).or_default() += 1;
                }
            }
            let used: u64 = need.values().map(|&c| u64::from(c)).sum();
            s.util += if need.is_empty() { 1.0 } else { used as f64 / (lanes.len() * need.len()) as f64 };
        }
        lanes.clear();
    };
    for b in batches {
        let kinds = arrow::compute::cast(b.column(0), &DataType::Utf8).map_err(|e| Error::DataFusion(e.into()))?;
        let kinds = kinds.as_string::<i32>();
        let depth = b
            .column(1)
            .as_primitive_opt::<arrow::datatypes::UInt16Type>()
            .ok_or_else(|| Error::BadArgument("depth is not UInt16".into()))?;
        let (tree, ray) = (col_u64(b, 2)?, col_u32(b, 3)?);
        let f: Vec<_> = (4..10)
            .map(|i| {
                arrow::compute::cast(b.column(i), &DataType::Float64)
                    .map_err(|e| Error::DataFusion(e.into()))
                    .map(|c| c.as_primitive::<Float64Type>().clone())
            })
            .collect::<Result<_>>()?;
        for i in 0..b.num_rows() {
            let key = (kinds.value(i).to_string(), depth.value(i));
            if group.as_ref() != Some(&key) {
                if let Some((k, _)) = &group {
                    flush(&mut out, k, &mut lanes);
                }
                group = Some(key);
            }
            lanes.push((
                tree.value(i),
                ray.value(i),
                [f[3].value(i), f[4].value(i), f[5].value(i)],
                [f[0].value(i), f[1].value(i), f[2].value(i)],
            ));
            if lanes.len() == width
                && let Some((k, _)) = &group
            {
                flush(&mut out, k, &mut lanes);
            }
        }
    }
    if let Some((k, _)) = &group {
        flush(&mut out, k, &mut lanes);
    }
    // One row per kind, in name order.
    let mut merged: Vec<(String, PacketSums)> = Vec::new();
    out.sort_by(|a, b| a.0.cmp(&b.0));
    for (k, s) in out {
        match merged.last_mut() {
            Some((mk, m)) if *mk == k => {
                m.packets += s.packets;
                m.coherence += s.coherence;
                m.spread += s.spread;
                m.util += s.util;
            }
            _ => merged.push((k, s)),
        }
    }
    Ok(merged)
}

/// Mean resultant length of finite, non-zero directions (1 for an empty packet).
fn packet_coherence(dirs: impl Iterator<Item = [f64; 3]>) -> f64 {
    let mut c = Coherence::default();
    dirs.for_each(|d| c.add(d));
    c.value().unwrap_or(1.0)
}

/// RMS distance of finite points from their centroid (0 for an empty packet).
fn packet_spread(points: impl Iterator<Item = [f64; 3]>) -> f64 {
    let mut s = Spread::default();
    points.for_each(|p| s.add(p));
    s.value().unwrap_or(0.0)
}

/// BVH traversal: cost per ray, false-positive leaf tests, hottest subtrees, cost per pixel.
pub async fn bvh(ctx: &Engine, subtree_level: u16) -> Result<Report> {
    let mut rep = Report::default();
    rep.para("# BVH traversal");
    rep.heading("Cost per ray by kind and depth");
    rep.para("Means per ray: nodes entered, boxes and triangles tested.");
    let t = run(
        ctx,
        "SELECT kind, depth, count(*) AS rays, avg(nodes_visited) AS nodes, avg(box_tests) AS boxes, \
         avg(tri_tests) AS triangles FROM rays GROUP BY kind, depth ORDER BY kind, depth",
    )
    .await
    .map_err(|e| {
        Error::BadArgument(format!("the trace lacks traversal counts (nodes_visited, box_tests, tri_tests): {e}"))
    })?;
    rep.para(&markdown(&t)?);
    if has_table(ctx, "ray_nodes").await {
        rep.heading("False-positive leaf tests (Figure 3's case)");
        rep.para(
            "A leaf visit is a false positive when the ray entered the leaf's box but none of its triangles gave a \
             (closer) hit.",
        );
        let t = run(
            ctx,
            "SELECT r.kind, count(*) AS leaf_visits, count(*) FILTER (WHERE NOT v.leaf_hit) AS false_positives, \
             CAST(count(*) FILTER (WHERE NOT v.leaf_hit) AS DOUBLE) / count(*) AS share \
             FROM ray_nodes v JOIN rays r USING (tree_id, ray) WHERE v.leaf_hit IS NOT NULL \
             GROUP BY r.kind ORDER BY r.kind",
        )
        .await?;
        rep.para(&markdown(&t)?);
        rep.para("Leaves with the most false positives:");
        let t = run(
            ctx,
            "SELECT v.node_id, b.level, count(*) FILTER (WHERE NOT v.leaf_hit) AS false_positives, count(*) AS visits, \
             b.min_x, b.min_y, b.min_z, b.max_x, b.max_y, b.max_z, cardinality(b.prims) AS triangles \
             FROM ray_nodes v JOIN bvh_nodes b USING (node_id) WHERE v.leaf_hit IS NOT NULL \
             GROUP BY v.node_id, b.level, b.min_x, b.min_y, b.min_z, b.max_x, b.max_y, b.max_z, b.prims \
             ORDER BY false_positives DESC, v.node_id LIMIT 10",
        )
        .await?;
        rep.para(&markdown(&t)?);
        rep.heading(&format!("Hottest subtrees (roots at level {subtree_level}) by kind"));
        let t = match ctx.session() {
            Some(session) => {
                register_subtrees(ctx, session, subtree_level).await?;
                run(
                    ctx,
                    "SELECT kind, subtree, visits, share FROM (\
               SELECT r.kind, s.subtree, count(*) AS visits, \
                 CAST(count(*) AS DOUBLE) / sum(count(*)) OVER (PARTITION BY r.kind) AS share, \
                 row_number() OVER (PARTITION BY r.kind ORDER BY count(*) DESC, s.subtree) AS rank \
               FROM ray_nodes v JOIN bvh_subtrees s USING (node_id) JOIN rays r USING (tree_id, ray) \
               GROUP BY r.kind, s.subtree) WHERE rank <= 5 ORDER BY kind, visits DESC, subtree",
                )
                .await?
            }
            None => Vec::new(),
        };
        match ctx.session() {
            Some(_) => rep.para(&markdown(&t)?),
            None => rep.para("*(subtree heat needs an in-process or cluster session, not a service's client)*"),
        }
    } else {
        rep.para("*(record with `--record-visits` for false-positive tests and subtree heat)*");
    }
    let size = image_size(ctx, "").await?;
    rep.add_grid(
        ctx,
        Some("Nodes visited per camera ray"),
        "SELECT pixel_x, pixel_y, avg(nodes_visited) FROM rays WHERE kind = 'camera' GROUP BY pixel_x, pixel_y",
        Cells::pixels(size),
        "nodes_per_pixel",
        "mean nodes visited by the camera rays of each pixel",
    )
    .await?;
    Ok(rep)
}

/// Registers `bvh_subtrees(node_id, subtree)`: each node at or below `level` with its ancestor
/// at `level`.
async fn register_subtrees(ctx: &Engine, session: &datafusion::prelude::SessionContext, level: u16) -> Result<()> {
    let mut parent: HashMap<u32, (Option<u32>, u16)> = HashMap::new();
    for b in run(ctx, "SELECT node_id, parent, level FROM bvh_nodes").await? {
        let (id, p) = (col_u32(&b, 0)?, col_u32(&b, 1)?);
        let l = b
            .column(2)
            .as_primitive_opt::<arrow::datatypes::UInt16Type>()
            .ok_or_else(|| Error::BadArgument("bvh_nodes.level is not UInt16".into()))?;
        for i in 0..b.num_rows() {
            parent.insert(id.value(i), (p.is_valid(i).then(|| p.value(i)), l.value(i)));
        }
    }
    let (mut ids, mut roots) = (Vec::new(), Vec::new());
    for (&id, &(_, l)) in &parent {
        if l < level {
            continue;
        }
        let mut n = id;
        let mut steps = 0;
        while let Some(&(Some(p), pl)) = parent.get(&n) {
            if pl <= level || steps > 10_000 {
                break;
            }
            n = p;
            steps += 1;
        }
        ids.push(id);
        roots.push(n);
    }
    let schema = Arc::new(arrow::datatypes::Schema::new(vec![
        arrow::datatypes::Field::new("node_id", DataType::UInt32, false),
        arrow::datatypes::Field::new("subtree", DataType::UInt32, false),
    ]));
    let batch = RecordBatch::try_new(
        schema.clone(),
        vec![Arc::new(arrow::array::UInt32Array::from(ids)), Arc::new(arrow::array::UInt32Array::from(roots))],
    )
    .map_err(|e| Error::DataFusion(e.into()))?;
    let table = datafusion::datasource::MemTable::try_new(schema, vec![vec![batch]])?;
    session.deregister_table("bvh_subtrees")?;
    session.register_table("bvh_subtrees", Arc::new(table))?;
    Ok(())
}

/// The paper's bug as a predicate on `rays`: shadow rays that aim at no emitter.
pub const WRONG_SHADOW: &str =
    "kind = 'shadow' AND NOT aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z)";

/// The numerical health of a trace: every check of the `numerics` view (`crate::numerics`)
/// with its count, first offending rays and a heatmap over the image, and the paper's bug (shadow
/// rays aiming at no light) by depth and parent.
pub async fn numerics(ctx: &Engine) -> Result<Report> {
    use crate::numerics::CHECKS;
    let mut rep = Report::default();
    rep.para("# Numerical health");
    // Which checks the view has, and why not the others (`numerics_checks`, made beside it).
    let mut missing = std::collections::HashMap::new();
    for b in run(ctx, "SELECT problem, missing FROM numerics_checks").await? {
        let utf8 =
            |i: usize| arrow::compute::cast(b.column(i), &DataType::Utf8).map_err(|e| Error::DataFusion(e.into()));
        let (p, m) = (utf8(0)?, utf8(1)?);
        let (p, m) = (p.as_string::<i32>(), m.as_string::<i32>());
        for r in 0..b.num_rows() {
            missing.insert(p.value(r).to_string(), m.is_valid(r).then(|| m.value(r).to_string()));
        }
    }
    let checks: Vec<(crate::numerics::Check, Option<String>)> = CHECKS
        .iter()
        .map(|c| (*c, missing.get(c.name).cloned().unwrap_or_else(|| Some("not in this engine's view".into()))))
        .collect();
    let total = scalar(ctx, "SELECT count(*) FROM rays").await?;
    let mut counts = std::collections::HashMap::new();
    for b in run(ctx, "SELECT problem, count(*) AS n FROM numerics GROUP BY problem").await? {
        let names = arrow::compute::cast(b.column(0), &DataType::Utf8).map_err(|e| Error::DataFusion(e.into()))?;
        let names = names.as_string::<i32>();
        let n = arrow::compute::cast(b.column(1), &DataType::Float64).map_err(|e| Error::DataFusion(e.into()))?;
        let n = n.as_primitive::<arrow::datatypes::Float64Type>();
        for r in 0..b.num_rows() {
            counts.insert(names.value(r).to_string(), n.value(r));
        }
    }
    let bugs: f64 = CHECKS.iter().filter(|c| c.bug).map(|c| counts.get(c.name).copied().unwrap_or(0.0)).sum();
    rep.para(&format!(
        "**{}** findings of the bug checks over {} rays (a ray can fail more than one check; `SELECT * FROM numerics` lists them, `WHERE problem = '...'` one check).",
        num(bugs),
        num(total)
    ));
    let mut table = String::from("| check | finds | rays | share |\n|---|---|---|---|\n");
    for (c, missing) in &checks {
        let (n, share) = match missing {
            Some(why) => ("not run".to_string(), format!("*{why}*")),
            None => {
                let n = counts.get(c.name).copied().unwrap_or(0.0);
                (num(n), format!("{}%", num(if total > 0.0 { 100.0 * n / total } else { 0.0 })))
            }
        };
        let _ = writeln!(
            table,
            "| {} | {}{} | {n} | {share} |",
            c.name,
            c.title,
            if c.bug { "" } else { " *(not a bug)*" }
        );
    }
    rep.para(&table);
    let size = image_size(ctx, "").await?;
    for (c, missing) in &checks {
        let n = counts.get(c.name).copied().unwrap_or(0.0);
        if c.name == "wrong_shadow" {
            // Its count is the view's, already taken with the others.
            wrong_shadow(ctx, &mut rep, missing.as_deref().map_or(Ok(n), Err), size).await?;
            continue;
        }
        if missing.is_some() || n == 0.0 {
            continue;
        }
        rep.heading(&format!("{}: {}", c.name, c.title));
        rep.para(&format!("**{}** rays. The first (open one with `rtvtk tree DATASET --pixel X,Y`):", num(n)));
        let t = run(
            ctx,
            &format!(
                "SELECT tree_id, ray, pixel_x, pixel_y, sample, depth, kind, value, detail FROM numerics \
                 WHERE problem = '{}' ORDER BY tree_id, ray LIMIT 5",
                c.name
            ),
        )
        .await?;
        rep.para(&markdown(&t)?);
        let sql = format!(
            "SELECT pixel_x, pixel_y, count(*) FROM numerics WHERE problem = '{}' GROUP BY pixel_x, pixel_y",
            c.name
        );
        let title = format!("{} rays per pixel", c.name);
        rep.add_grid(ctx, None, &sql, Cells::pixels(size), &format!("numerics_{}", c.name), &title).await?;
    }
    Ok(rep)
}

/// The paper's Figure-1 bug in detail: shadow rays aiming at no light, by depth and by the ray
/// they leave from, the pixels with the most, and their heatmap; `wrong` is their count, or why
/// the check did not run (no `lights` table, or a broken one).
async fn wrong_shadow(
    ctx: &Engine,
    rep: &mut Report,
    wrong: std::result::Result<f64, &str>,
    size: (usize, usize),
) -> Result<()> {
    rep.heading("Shadow rays aiming at no light (the paper's Figure 1 bug)");
    let n = match wrong {
        Ok(n) => n,
        Err(why) => {
            rep.para(&format!("*(not run: {why}; this check needs the emitters)*"));
            return Ok(());
        }
    };
    let all = scalar(ctx, "SELECT count(*) FROM rays WHERE kind = 'shadow'").await?;
    rep.para(&format!(
        "**{}** of {} shadow rays ({}%) point at no emitter.",
        num(n),
        num(all),
        num(if all > 0.0 { 100.0 * n / all } else { 0.0 })
    ));
    if n > 0.0 {
        rep.para("By depth, and by the ray they leave from (its kind and material):");
        let parents = rays_with_material(ctx).await?;
        let t = run(
            ctx,
            &format!(
                "SELECT s.depth, p.kind AS parent_kind, p.material AS parent_material, count(*) AS wrong \
                 FROM rays s JOIN {parents} p ON s.tree_id = p.tree_id AND s.parent = p.ray \
                 WHERE s.kind = 'shadow' AND NOT aims_at_light(s.origin_x, s.origin_y, s.origin_z, s.dir_x, s.dir_y, s.dir_z) \
                 GROUP BY s.depth, p.kind, p.material ORDER BY wrong DESC, s.depth LIMIT 20"
            ),
        )
        .await?;
        rep.para(&markdown(&t)?);
        rep.para("Pixels with the most (open one with `rtvtk tree DATASET --pixel X,Y`):");
        let t = run(
            ctx,
            &format!(
                "SELECT pixel_x, pixel_y, count(*) AS wrong FROM rays WHERE {WRONG_SHADOW} \
                 GROUP BY pixel_x, pixel_y ORDER BY wrong DESC, pixel_y, pixel_x LIMIT 10"
            ),
        )
        .await?;
        rep.para(&markdown(&t)?);
        let sql = format!("SELECT pixel_x, pixel_y, count(*) FROM rays WHERE {WRONG_SHADOW} GROUP BY pixel_x, pixel_y");
        let title = "shadow rays aiming at no light, per pixel";
        rep.add_grid(ctx, None, &sql, Cells::pixels(size), "wrong_shadow_rays", title).await?;
    }
    Ok(())
}

/// Two traces (`a.*` and `b.*` in the session) side by side by kind, depth and image tile.
pub async fn diff(ctx: &Engine, a: &str, b: &str, tile: usize) -> Result<Report> {
    let mut rep = Report::default();
    rep.para(&format!("# `{a}` against `{b}`"));
    let tile = tile.max(1);
    let lights = has_table(ctx, &format!("{a}.lights")).await && has_table(ctx, &format!("{b}.lights")).await;
    // Rays of a trace, with `nodes_visited` (null where the trace has no traversal counts, as
    // other renderers' traces) and `lit`: 1 when the ray hit an emitter.
    let mut rays = std::collections::HashMap::new();
    for s in [a, b] {
        let r = if has_column(ctx, &format!("{s}.rays"), "nodes_visited").await? {
            format!("{s}.rays")
        } else {
            format!("(SELECT *, CAST(NULL AS DOUBLE) AS nodes_visited FROM {s}.rays)")
        };
        rays.insert(s.to_string(), r);
    }
    let from = |s: &str| {
        let r = &rays[s];
        if lights {
            format!(
                "(SELECT r.*, CASE WHEN l.prim IS NULL THEN 0.0 ELSE 1.0 END AS lit FROM {r} r \
                 LEFT JOIN (SELECT DISTINCT prim FROM {s}.lights) l ON r.prim = l.prim)"
            )
        } else {
            format!("(SELECT *, CAST(NULL AS DOUBLE) AS lit FROM {r})")
        }
    };
    rep.para(
        "`nodes`: mean BVH nodes visited per ray; `lit`: share of rays that hit an emitter (for shadow rays: \
         the share that reached the light); `coherence`: `dir_coherence` of the directions.",
    );
    let stats = |group: &str, s: &str| {
        format!(
            "SELECT {group} AS g, count(*) AS rays, avg(nodes_visited) AS nodes, avg(lit) AS lit, \
             dir_coherence(dir_x, dir_y, dir_z) AS coherence FROM {} GROUP BY {group}",
            from(s)
        )
    };
    for (title, group) in [("By kind", "CAST(kind AS VARCHAR)"), ("By depth", "CAST(depth AS BIGINT)")] {
        rep.heading(title);
        let t = run(
            ctx,
            &format!(
                "SELECT coalesce(x.g, y.g) AS key, x.rays AS rays_a, y.rays AS rays_b, \
                 CAST(y.rays AS DOUBLE) / x.rays - 1 AS rays_change, \
                 x.nodes AS nodes_a, y.nodes AS nodes_b, x.lit AS lit_a, y.lit AS lit_b, y.lit - x.lit AS lit_change, \
                 x.coherence AS coherence_a, y.coherence AS coherence_b \
                 FROM ({}) x FULL JOIN ({}) y ON x.g = y.g ORDER BY key",
                stats(group, a),
                stats(group, b)
            ),
        )
        .await?;
        rep.para(&markdown(&t)?);
    }
    rep.heading(&format!("By image tile ({tile}×{tile} pixels): largest changes"));
    let tiles = |s: &str| {
        format!(
            "SELECT CAST(pixel_x / {tile} AS BIGINT) AS tx, CAST(pixel_y / {tile} AS BIGINT) AS ty, count(*) AS rays, \
             avg(nodes_visited) AS nodes, avg(lit) AS lit FROM {} GROUP BY 1, 2",
            from(s)
        )
    };
    let joined = format!(
        "SELECT coalesce(x.tx, y.tx) AS tile_x, coalesce(x.ty, y.ty) AS tile_y, x.rays AS rays_a, y.rays AS rays_b, \
         CAST(coalesce(y.rays, 0) AS DOUBLE) / x.rays - 1 AS rays_change, x.nodes AS nodes_a, y.nodes AS nodes_b, \
         x.lit AS lit_a, y.lit AS lit_b, coalesce(y.lit - x.lit, 0) AS lit_change \
         FROM ({}) x FULL JOIN ({}) y ON x.tx = y.tx AND x.ty = y.ty",
        tiles(a),
        tiles(b)
    );
    let t = run(
        ctx,
        &format!(
            "SELECT * FROM ({joined}) ORDER BY abs(rays_change) + abs(lit_change) DESC NULLS FIRST, tile_y, tile_x LIMIT 10"
        ),
    )
    .await?;
    rep.para(&markdown(&t)?);
    let (w, h) = image_size(ctx, &format!("{a}.")).await?;
    let cells = Cells { width: w.div_ceil(tile), height: h.div_ceil(tile), cell: tile };
    let title = format!("relative change of the ray count per {tile}×{tile} tile, {b} over {a} minus 1");
    let sql = format!("SELECT tile_x, tile_y, rays_change FROM ({joined})");
    rep.add_grid(ctx, None, &sql, cells, "rays_change_per_tile", &title).await?;
    if lights {
        let title = format!("change of the share of rays hitting an emitter per {tile}×{tile} tile, {b} minus {a}");
        let sql = format!("SELECT tile_x, tile_y, lit_change FROM ({joined})");
        rep.add_grid(ctx, None, &sql, cells, "lit_change_per_tile", &title).await?;
    }
    Ok(rep)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packet_measures() {
        assert!((packet_coherence([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]].into_iter()) - 1.0).abs() < 1e-12);
        assert!(packet_coherence([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]].into_iter()).abs() < 1e-12);
        let far = [[1e8, 0.0, 0.0], [1e8 + 2.0, 0.0, 0.0]];
        assert!((packet_spread(far.into_iter()) - 1.0).abs() < 1e-9);
        assert_eq!(num(2.0), "2");
        assert_eq!(num(0.123456), "0.1235");
        assert_eq!(num(1234.5678), "1235");
    }
}
