//! `rtvtk tree`: one pixel's (or one id's) ray trees as an indented hierarchy or JSON.

use std::path::Path;

use anyhow::{Result, bail};
use rl::{Dataset, Tree, TreeId};
use serde_json::json;

/// `rtvtk tree`: one ray tree as an indented hierarchy.
#[derive(clap::Args)]
pub struct TreeArgs {
    pub dataset: std::path::PathBuf,
    /// The pixel whose trees to print, X,Y.
    #[arg(long, value_parser = crate::args::parse_pixel, conflicts_with = "tree", required_unless_present = "tree")]
    pub pixel: Option<(u32, u32)>,
    /// Only this sample of the pixel.
    #[arg(long, requires = "pixel")]
    pub sample: Option<u32>,
    /// The tree with this id.
    #[arg(long)]
    pub tree: Option<u64>,
    #[arg(long)]
    pub json: bool,
}

impl TreeArgs {
    pub fn run(&self) -> Result<()> {
        run(&self.dataset, self.pixel, self.sample, self.tree, self.json)
    }
}

fn ray_line(ds: &Dataset, r: &rl::Ray) -> String {
    let kind = ds.kinds().name(r.kind).unwrap_or("?");
    let hit = match (r.t, r.prim) {
        (Some(t), Some(p)) => format!("t={t} prim {p}"),
        (Some(t), None) => format!("t={t}"),
        (None, _) => "miss".into(),
    };
    format!(
        "#{} {kind} o=({}, {}, {}) d=({}, {}, {}) {hit}",
        r.index, r.origin[0], r.origin[1], r.origin[2], r.direction[0], r.direction[1], r.direction[2]
    )
}

pub fn print_tree(ds: &Dataset, t: &Tree) {
    let i = &t.info;
    println!(
        "tree {}  pixel ({}, {})  sample {}  {} rays  max depth {}",
        i.id, i.pixel[0], i.pixel[1], i.sample, i.ray_count, i.max_depth
    );
    fn walk(ds: &Dataset, t: &Tree, idx: u32, prefix: &str, last: bool) {
        let Some(r) = t.rays.get(idx as usize) else { return };
        println!("{prefix}{}{}", if last { "└─ " } else { "├─ " }, ray_line(ds, r));
        let kids: Vec<u32> = t.children(idx).map(|c| c.index).collect();
        let next = format!("{prefix}{}", if last { "   " } else { "│  " });
        for (k, c) in kids.iter().enumerate() {
            walk(ds, t, *c, &next, k + 1 == kids.len());
        }
    }
    let roots: Vec<u32> = t.roots().map(|r| r.index).collect();
    for (k, r) in roots.iter().enumerate() {
        walk(ds, t, *r, "", k + 1 == roots.len());
    }
}

fn tree_json(ds: &Dataset, t: &Tree) -> serde_json::Value {
    let rays: Vec<_> = t
        .rays
        .iter()
        .map(|r| {
            json!({
                "index": r.index,
                "parent": r.parent,
                "depth": r.depth,
                "kind": ds.kinds().name(r.kind),
                "origin": r.origin.map(f64::from),
                "direction": r.direction.map(f64::from),
                "t": r.t,
                "prim": r.prim,
            })
        })
        .collect();
    json!({
        "tree_id": t.info.id.0,
        "pixel": t.info.pixel,
        "sample": t.info.sample,
        "ray_count": t.info.ray_count,
        "max_depth": t.info.max_depth,
        "rays": rays,
    })
}

pub fn run(dir: &Path, pixel: Option<(u32, u32)>, sample: Option<u32>, id: Option<u64>, as_json: bool) -> Result<()> {
    let ds = Dataset::open(dir)?;
    let trees = match (pixel, id) {
        (_, Some(id)) => vec![ds.tree(TreeId(id))?],
        (Some((x, y)), None) => {
            let t = ds.trees_at_pixel(x, y, sample)?;
            if t.is_empty() {
                bail!(
                    "no tree at pixel ({x}, {y}){} in {}",
                    sample.map(|s| format!(" sample {s}")).unwrap_or_default(),
                    dir.display()
                );
            }
            t
        }
        (None, None) => bail!("give --pixel X,Y or --tree ID"),
    };
    if as_json {
        let v: Vec<_> = trees.iter().map(|t| tree_json(&ds, t)).collect();
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for t in &trees {
            print_tree(&ds, t);
        }
    }
    Ok(())
}
