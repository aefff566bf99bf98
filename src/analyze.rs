//! `rtvtk analyze`: the canned analyses of `query::analyze` as a markdown report with PNG
//! heatmaps.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use query::analyze::{self, CoherenceOptions, Grid, Report};

#[derive(Args, Debug)]
pub struct AnalyzeArgs {
    #[command(subcommand)]
    what: Analysis,
    /// Directory for `report.md` and the PNG plots (the report goes to stdout without it).
    #[arg(long, global = true)]
    out: Option<PathBuf>,
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
    /// Shadow rays aiming at no light, broken directions, self-intersections.
    Bugs { dataset: PathBuf },
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
    let report = rt.block_on(async {
        let report: query::Result<Report> = match &a.what {
            Analysis::Coherence { dataset, width, orders, kind } => {
                let ctx = query::session(&[source("trace", dataset)]).await?;
                let opts = CoherenceOptions { width: *width as usize, orders: orders.clone(), kind: kind.clone() };
                analyze::coherence(&ctx, &opts).await
            }
            Analysis::Bvh { dataset, level } => {
                let ctx = query::session(&[source("trace", dataset)]).await?;
                analyze::bvh(&ctx, *level).await
            }
            Analysis::Bugs { dataset } => {
                let ctx = query::session(&[source("trace", dataset)]).await?;
                analyze::bugs(&ctx).await
            }
            Analysis::Diff { a, b, tile } => {
                let ctx = query::session(&[source("a", a), source("b", b)]).await?;
                analyze::diff(&ctx, "a", "b", *tile).await
            }
        };
        report
    })?;
    match &a.out {
        Some(dir) => {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let md = dir.join("report.md");
            std::fs::write(&md, &report.markdown).with_context(|| format!("writing {}", md.display()))?;
            for g in &report.grids {
                write_heatmap(g, &dir.join(format!("{}.png", g.name)))?;
            }
            eprintln!("report: {} ({} plots)", md.display(), report.grids.len());
        }
        None => print!("{}", report.markdown),
    }
    Ok(())
}

fn source(name: &str, path: &Path) -> query::TraceSource {
    query::TraceSource { name: name.into(), path: path.to_path_buf() }
}

/// A perceptually ordered colour ramp (dark blue, purple, orange, yellow): `t` in 0..=1.
fn ramp(t: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 5] =
        [[13.0, 8.0, 135.0], [126.0, 3.0, 168.0], [204.0, 71.0, 120.0], [248.0, 149.0, 64.0], [240.0, 249.0, 33.0]];
    let x = t.clamp(0.0, 1.0) * (STOPS.len() - 1) as f64;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f64;
    [0, 1, 2].map(|k| (STOPS[i][k] + (STOPS[i + 1][k] - STOPS[i][k]) * f).round() as u8)
}

/// Writes a grid as a PNG, each cell scaled up to at least 256 pixels across; black where NaN.
fn write_heatmap(g: &Grid, path: &Path) -> Result<()> {
    if g.width == 0 || g.height == 0 {
        bail!("{}: empty grid", g.name);
    }
    let scale = (256 / g.width.max(g.height)).max(1) as u32;
    let (lo, hi) = g.range().unwrap_or((0.0, 1.0));
    let span = if hi > lo { hi - lo } else { 1.0 };
    let img = image::RgbImage::from_fn(g.width as u32 * scale, g.height as u32 * scale, |x, y| {
        let v = g.values[(y / scale) as usize * g.width + (x / scale) as usize];
        image::Rgb(if v.is_finite() { ramp((v - lo) / span) } else { [0, 0, 0] })
    });
    img.save(path).with_context(|| format!("writing {}", path.display()))
}
