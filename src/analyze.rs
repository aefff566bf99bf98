//! `rtvtk analyze`: the canned analyses of `query::analyze` as a markdown report with PNG
//! heatmaps.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use query::analyze::{self, CoherenceOptions, Grid, Report};

#[derive(Args, Debug)]
pub struct AnalyzeArgs {
    #[command(subcommand)]
    what: Analysis,
    /// Directory for `report.md` and the PNG plots (the report goes to stdout without it).
    #[arg(long, global = true)]
    out: Option<PathBuf>,
    /// Run the analysis's queries on a Ballista cluster (`df://HOST:PORT`, see `rtvtk cluster`).
    #[arg(long, global = true, value_name = "df://HOST:PORT")]
    cluster: Option<String>,
}

#[derive(Subcommand, Debug)]
enum Analysis {
    /// Direction coherence and origin spread by kind and depth, and which packet order would make
    /// the rays coherent (SIMD utilization from visited nodes when recorded).
    Coherence {
        dataset: PathBuf,
        /// Lanes per packet.
        #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=1024))]
        width: u32,
        /// Packet orders to compare.
        #[arg(long, value_delimiter = ',', default_value = "trace,morton,octant,material")]
        orders: Vec<String>,
        /// Only rays of this kind.
        #[arg(long)]
        kind: Option<String>,
    },
    /// BVH traversal cost per ray, false-positive leaf tests, hottest subtrees, cost per pixel.
    Bvh {
        dataset: PathBuf,
        /// Level of the subtree roots for the heat table.
        #[arg(long, default_value_t = 3)]
        level: u16,
        /// Instead: replay the trace's rays against other BVHs over its triangles (obvhs's PLOC
        /// presets, leaf sizes 1-8, a binned SAH, an 8-wide collapse, the recorded `bvh_nodes`),
        /// with each one's measured cost, SAH cost, their rank correlation, replayed hits checked
        /// against the recording, and how well a representative subset predicts the costs.
        #[arg(long)]
        whatif: bool,
        /// With --whatif: replay at most this many rays (every k-th tree beyond it).
        #[arg(long, default_value_t = 1_000_000, value_parser = clap::value_parser!(u64).range(1..))]
        max_rays: u64,
        /// With --whatif: the share of the replayed rays in the representative subset.
        #[arg(long, default_value_t = 0.01, value_parser = parse_share)]
        share: f64,
    },
    /// Numerical health: NaN/Inf values, broken directions, self-intersections, detached origins,
    /// leaks (rays replayed against the triangles), energy gain, shadow rays aiming at no light
    /// (the paper's bug) and fireflies, each with its first rays and a heatmap (the `numerics`
    /// view in SQL). `bugs` is its old name.
    #[command(alias = "bugs")]
    Numerics { dataset: PathBuf },
    /// Two traces side by side by kind, depth and image tile.
    Diff {
        a: PathBuf,
        b: PathBuf,
        /// Tile size in pixels.
        #[arg(long, default_value_t = 16)]
        tile: usize,
    },
}

pub fn run(a: &AnalyzeArgs) -> Result<()> {
    let rt = crate::runtime()?;
    let url = a.cluster.as_deref();
    let report = rt.block_on(async {
        let session = |sources: Vec<query::TraceSource>| async move {
            crate::query_engine(url, &sources, &query::SessionOptions::default()).await
        };
        let report: Result<Report> = match &a.what {
            Analysis::Coherence { dataset, width, orders, kind } => {
                let ctx = session(vec![source("trace", dataset)]).await?;
                let opts = CoherenceOptions { width: *width as usize, orders: orders.clone(), kind: kind.clone() };
                Ok(analyze::coherence(&ctx, &opts).await?)
            }
            Analysis::Bvh { dataset, whatif: true, max_rays, share, .. } => {
                let ctx = session(vec![source("trace", dataset)]).await?;
                whatif(&ctx, *max_rays, *share).await
            }
            Analysis::Bvh { dataset, level, .. } => {
                let ctx = session(vec![source("trace", dataset)]).await?;
                Ok(analyze::bvh(&ctx, *level).await?)
            }
            Analysis::Numerics { dataset } => {
                let ctx = session(vec![source("trace", dataset)]).await?;
                Ok(analyze::numerics(&ctx).await?)
            }
            Analysis::Diff { a, b, tile } => {
                let ctx = session(vec![source("a", a), source("b", b)]).await?;
                Ok(analyze::diff(&ctx, "a", "b", *tile).await?)
            }
        };
        report
    })?;
    match &a.out {
        Some(dir) => {
            let maps: Vec<(&str, renderers::plot::Heatmap)> =
                report.grids.iter().map(|g| (g.name.as_str(), heatmap(g))).collect();
            let md = renderers::plot::write_report(dir, &report.markdown, &maps)
                .with_context(|| format!("writing the report into {}", dir.display()))?;
            eprintln!("report: {} ({} plots)", md.display(), report.grids.len());
        }
        None => print!("{}", report.markdown),
    }
    Ok(())
}

fn source(name: &str, path: &Path) -> query::TraceSource {
    query::TraceSource { name: name.into(), path: path.to_path_buf() }
}

/// A grid as a heatmap with axes in pixels, its title and a colour bar (plotters).
fn heatmap(g: &Grid) -> renderers::plot::Heatmap<'_> {
    renderers::plot::Heatmap::pixels(&g.title, g.width, g.height, &g.values, g.cell)
}

fn parse_share(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v > 0.0 && v <= 1.0 => Ok(v),
        _ => Err(format!("bad share {s:?}: expected a number in (0, 1]")),
    }
}

/// The Float32 values of column `name` of `b` (cast when stored otherwise).
fn f32s(b: &arrow::array::RecordBatch, name: &str) -> Result<Vec<Option<f32>>> {
    use arrow::array::{Array, AsArray};
    let c = b.column_by_name(name).with_context(|| format!("no column {name}"))?;
    let c = arrow::compute::cast(c, &arrow::datatypes::DataType::Float32)?;
    let c = c.as_primitive::<arrow::datatypes::Float32Type>();
    Ok((0..c.len()).map(|i| c.is_valid(i).then(|| c.value(i))).collect())
}

/// A point from three nullable coordinates (NaN where one is null).
fn point(x: Option<f32>, y: Option<f32>, z: Option<f32>) -> glam::Vec3A {
    glam::Vec3A::new(x.unwrap_or(f32::NAN), y.unwrap_or(f32::NAN), z.unwrap_or(f32::NAN))
}

/// `analyze bvh --whatif`: the trace's rays replayed against other BVHs (`renderers::whatif`):
/// the triangles and a sample of the rays read, the builds made (and the recorded tree, when the
/// trace has `bvh_nodes`), every build replayed, the report written.
async fn whatif(ctx: &query::Engine, max_rays: u64, share: f64) -> Result<Report> {
    use renderers::whatif::{replay, representative};
    let tris = whatif_triangles(ctx).await?;
    let sample = whatif_rays(ctx, max_rays).await?;
    let mut all = renderers::whatif::builds(&tris);
    if ctx.catalog().await.is_ok_and(|c| c.tables.iter().any(|t| t == store::scene::BVH_NODES_TABLE)) {
        all.push(recorded_bvh(ctx, tris.len()).await?);
    }
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let sub = representative(&sample.rays, share);
    let replays: Vec<Replayed> = all
        .iter()
        .map(|b| Replayed {
            name: b.name.clone(),
            sah: b.tree.sah_cost(),
            shape: b.tree.shape(),
            build_ms: b.build_time.as_secs_f64() * 1e3,
            all: replay(&b.tree, &tris, &sample.rays, threads),
            subset: replay(&b.tree, &tris, &sub, threads),
        })
        .collect();
    let markdown = whatif_markdown(&sample, tris.len(), threads, sub.len(), share, &replays);
    Ok(Report { markdown, grids: Vec::new() })
}

/// The rays a what-if replays: every `every`-th tree of the trace's `total` rays, and the kind
/// names their `kind` ids index.
struct WhatifRays {
    rays: Vec<renderers::whatif::RecordedRay>,
    kinds: Vec<String>,
    total: u64,
    every: u64,
}

/// One build replayed: over every sampled ray and over the representative subset.
struct Replayed {
    name: String,
    sah: f64,
    shape: (usize, f64),
    build_ms: f64,
    all: renderers::whatif::Replay,
    subset: renderers::whatif::Replay,
}

/// The trace's triangles, in `prim` order (the ids rays and `bvh_nodes` use).
// Rows are read across several column vectors at once, by index.
#[allow(clippy::needless_range_loop)]
async fn whatif_triangles(ctx: &query::Engine) -> Result<Vec<[glam::Vec3A; 3]>> {
    let v3 = point;
    let mut tris: Vec<[glam::Vec3A; 3]> = Vec::new();
    let names = store::scene::col::VERTEX;
    let sql = format!(
        "SELECT prim, {} FROM triangles ORDER BY prim",
        names.iter().flatten().copied().collect::<Vec<_>>().join(", ")
    );
    let batches =
        ctx.collect(&sql).await.context("analyze bvh --whatif replays rays against the trace's `triangles` table")?;
    for b in &batches {
        let c: Vec<Vec<Option<f32>>> = names.iter().flatten().map(|n| f32s(b, n)).collect::<Result<_>>()?;
        for r in 0..b.num_rows() {
            let p = |v: usize| v3(c[v * 3][r], c[v * 3 + 1][r], c[v * 3 + 2][r]);
            tris.push([p(0), p(1), p(2)]);
        }
    }
    if tris.is_empty() {
        anyhow::bail!("the trace's `triangles` table is empty: there is nothing to replay rays against");
    }
    Ok(tris)
}

/// The rays to replay: every k-th tree past `max_rays`.
// Rows are read across several column vectors at once, by index.
#[allow(clippy::needless_range_loop)]
async fn whatif_rays(ctx: &query::Engine, max_rays: u64) -> Result<WhatifRays> {
    use arrow::array::{Array, AsArray};
    use renderers::whatif::RecordedRay;
    let v3 = point;
    let total = ctx.collect("SELECT count(*) AS n FROM rays").await?;
    let total = total.first().map_or(0, |b| b.column(0).as_primitive::<arrow::datatypes::Int64Type>().value(0)) as u64;
    let every = total.div_ceil(max_rays).max(1);
    let filter = if every > 1 { format!("WHERE tree_id % {every} = 0") } else { String::new() };
    let mut kinds: Vec<String> = Vec::new();
    let mut rays: Vec<RecordedRay> = Vec::new();
    let sql = format!(
        "SELECT CAST(kind AS VARCHAR) AS kind, origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t FROM rays {filter}"
    );
    for b in ctx.collect(&sql).await? {
        let k = arrow::compute::cast(b.column(0), &arrow::datatypes::DataType::Utf8)?;
        let k = k.as_string::<i32>();
        let c: Vec<Vec<Option<f32>>> = ["origin_x", "origin_y", "origin_z", "dir_x", "dir_y", "dir_z", "t"]
            .iter()
            .map(|n| f32s(&b, n))
            .collect::<Result<_>>()?;
        for r in 0..b.num_rows() {
            let name = if k.is_valid(r) { k.value(r) } else { "?" };
            let id = match kinds.iter().position(|n| n == name) {
                Some(i) => i,
                None if kinds.len() < 255 => {
                    kinds.push(name.to_string());
                    kinds.len() - 1
                }
                None => 254,
            };
            let (o, d) = (v3(c[0][r], c[1][r], c[2][r]), v3(c[3][r], c[4][r], c[5][r]));
            if !(o.is_finite() && d.is_finite()) || d.length_squared() == 0.0 {
                continue;
            }
            rays.push(RecordedRay { kind: id as u8, origin: o, dir: d, t: c[6][r], closest: name != "shadow" });
        }
    }
    Ok(WhatifRays { rays, kinds, total, every })
}

/// The trace's own BVH (`bvh_nodes`) as a build to replay.
// Rows are read across several column vectors at once, by index.
#[allow(clippy::needless_range_loop)]
async fn recorded_bvh(ctx: &query::Engine, triangles: usize) -> Result<renderers::whatif::Build> {
    use arrow::array::{Array, AsArray};
    let v3 = point;
    let t0 = std::time::Instant::now();
    let mut rows = Vec::new();
    let cols = "node_id, parent, min_x, min_y, min_z, max_x, max_y, max_z, is_leaf, prims";
    for b in ctx.collect(&format!("SELECT {cols} FROM bvh_nodes ORDER BY node_id")).await? {
        let parent = arrow::compute::cast(b.column(1), &arrow::datatypes::DataType::UInt32)?;
        let parent = parent.as_primitive::<arrow::datatypes::UInt32Type>();
        let f: Vec<Vec<Option<f32>>> = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"]
            .iter()
            .map(|n| f32s(&b, n))
            .collect::<Result<_>>()?;
        let leaf = b.column(8).as_boolean();
        let prims = b.column(9).as_list::<i32>();
        for r in 0..b.num_rows() {
            let p: Vec<u32> = match prims.is_valid(r) {
                true => prims.value(r).as_primitive::<arrow::datatypes::UInt32Type>().values().to_vec(),
                false => Vec::new(),
            };
            if let Some(bad) = p.iter().find(|&&p| p as usize >= triangles) {
                anyhow::bail!("bvh_nodes row {r}: triangle {bad} is not among the {} triangles", triangles);
            }
            rows.push((
                parent.is_valid(r).then(|| parent.value(r)),
                v3(f[0][r], f[1][r], f[2][r]),
                v3(f[3][r], f[4][r], f[5][r]),
                leaf.value(r),
                p,
            ));
        }
    }
    let tree = renderers::whatif::ReplayTree::from_parents(&rows)
        .map_err(|e| anyhow::anyhow!("the trace's bvh_nodes: {e}"))?;
    Ok(renderers::whatif::Build { name: "recorded (bvh_nodes)".into(), tree, build_time: t0.elapsed() })
}

/// The what-if report: the builds' table, disagreeing hits, tests per ray by kind, how well the
/// SAH ranks the builds, and how well the representative subset predicts them.
fn whatif_markdown(
    sample: &WhatifRays,
    triangles: usize,
    threads: usize,
    subset: usize,
    share: f64,
    replays: &[Replayed],
) -> String {
    use renderers::whatif::spearman;
    use std::fmt::Write as _;
    let (rays, kinds, total, every) = (&sample.rays, sample.kinds.as_slice(), sample.total, sample.every);
    let mut md = String::from("# BVH what-ifs\n\n");
    let _ = writeln!(
        md,
        "{} rays replayed ({} of the trace{}), {} triangles, {threads} threads. Closest-hit rays (all but shadow rays) are checked against the recorded hit; shadow rays are replayed as occlusion tests up to their recorded distance. Counts per ray: nodes visited, child boxes tested, triangles tested; `SAH` is the cost with unit box and triangle costs (area-weighted box tests of inner nodes and triangle tests of leaves).\n",
        rays.len(),
        total,
        if every > 1 { format!(", one tree in {every}") } else { String::new() },
        triangles
    );
    md.push_str("| build | nodes | leaf tris | SAH | nodes/ray | boxes/ray | tris/ray | tests/ray | replay ms | Mrays/s | build ms | hits verified |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for p in replays {
        let (r, (n, leaf)) = (&p.all, p.shape);
        let per = |v: u64| v as f64 / r.total.rays.max(1) as f64;
        let _ = writeln!(
            md,
            "| {} | {n} | {leaf:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.1} | {:.2} | {:.1} | {} of {} |",
            p.name,
            p.sah,
            per(r.total.nodes),
            per(r.total.boxes),
            per(r.total.tris),
            r.total.tests_per_ray(),
            r.time.as_secs_f64() * 1e3,
            r.total.rays as f64 / r.time.as_secs_f64().max(1e-9) / 1e6,
            p.build_ms,
            r.agree,
            r.checked,
        );
    }
    let rows: Vec<(&str, f64, &renderers::whatif::Replay, &renderers::whatif::Replay)> =
        replays.iter().map(|p| (p.name.as_str(), p.sah, &p.all, &p.subset)).collect();
    for (name, _, r, _) in &rows {
        if let Some((i, want, got)) = r.disagree.first() {
            let ray = &rays[*i];
            let _ = writeln!(
                md,
                "\n*{name}: {} replayed hits disagree with the recording; the first: a {} ray from {:?} along {:?}, recorded t {want:?}, replayed {got:?}.*",
                r.checked - r.agree,
                kinds.get(ray.kind as usize).map_or("?", String::as_str),
                ray.origin.to_array(),
                ray.dir.to_array()
            );
        }
    }
    md.push_str("\n## By kind: box and triangle tests per ray\n\n| build |");
    for k in kinds {
        let _ = write!(md, " {k} |");
    }
    md.push_str("\n|---|");
    md.push_str(&"---|".repeat(kinds.len()));
    md.push('\n');
    for (name, _, r, _) in &rows {
        let _ = write!(md, "| {name} |");
        for k in 0..kinds.len() {
            match r.by_kind.iter().find(|(id, _)| *id as usize == k) {
                Some((_, c)) => {
                    let _ = write!(md, " {:.2} |", c.tests_per_ray());
                }
                None => md.push_str(" - |"),
            }
        }
        md.push('\n');
    }
    let sah: Vec<f64> = rows.iter().map(|r| r.1).collect();
    let tests: Vec<f64> = rows.iter().map(|r| r.2.total.tests_per_ray()).collect();
    let time: Vec<f64> = rows.iter().map(|r| r.2.time.as_secs_f64()).collect();
    let _ = writeln!(
        md,
        "\n## Does the SAH rank the builds?\n\nSpearman rank correlation over the {} builds: SAH against measured tests per ray **{:.3}**, SAH against replay time {:.3}, tests per ray against replay time {:.3} (1: the same order; the times are one run each on a shared machine).\n",
        rows.len(),
        spearman(&sah, &tests),
        spearman(&sah, &time),
        spearman(&tests, &time)
    );
    let errors: Vec<f64> = rows
        .iter()
        .map(|(_, _, r, s)| (s.total.tests_per_ray() / r.total.tests_per_ray().max(1e-12) - 1.0).abs())
        .collect();
    let predicted: Vec<f64> = rows.iter().map(|r| r.3.total.tests_per_ray()).collect();
    let _ = writeln!(
        md,
        "## A representative subset\n\n{} rays ({:.2}% of those replayed: one ray in {} of each stratum of kind, direction octant and origin cell of a 4x4x4 grid) predict each build's tests per ray within **{:.2}%** (mean {:.2}%); they rank the builds as the full replay does with Spearman {:.3}.\n",
        subset,
        100.0 * subset as f64 / rays.len().max(1) as f64,
        (1.0 / share).round(),
        100.0 * errors.iter().copied().fold(0.0, f64::max),
        100.0 * errors.iter().sum::<f64>() / errors.len().max(1) as f64,
        spearman(&predicted, &tests)
    );
    md.push_str("| build | tests/ray (all) | tests/ray (subset) | error |\n|---|---|---|---|\n");
    for ((name, _, r, s), e) in rows.iter().zip(&errors) {
        let _ = writeln!(
            md,
            "| {name} | {:.3} | {:.3} | {:.2}% |",
            r.total.tests_per_ray(),
            s.total.tests_per_ray(),
            100.0 * e
        );
    }
    md
}
