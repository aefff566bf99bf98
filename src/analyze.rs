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
            Analysis::Bvh { dataset, level } => {
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
