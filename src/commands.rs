//! The dataset subcommands: demo, info, tree, check.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rl::{Dataset, Tree, TreeId};
use serde_json::json;

pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or("expected WxH, e.g. 64x48")?;
    let w: u32 = w.trim().parse().map_err(|_| format!("bad width {w:?}: expected a positive integer"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("bad height {h:?}: expected a positive integer"))?;
    if w == 0 || h == 0 {
        return Err("width and height must be positive".into());
    }
    Ok((w, h))
}

pub fn parse_pixel(s: &str) -> Result<(u32, u32), String> {
    let (x, y) = s.split_once(',').ok_or("expected X,Y, e.g. 10,20")?;
    let x = x.trim().parse().map_err(|_| format!("bad x {x:?}: expected a non-negative integer"))?;
    let y = y.trim().parse().map_err(|_| format!("bad y {y:?}: expected a non-negative integer"))?;
    Ok((x, y))
}

/// Renders and records the Cornell box with the path tracer, then summarizes the trace.
pub fn demo(out: Option<PathBuf>, (w, h): (u32, u32), spp: u32, threads: usize) -> Result<()> {
    let dir = out.unwrap_or_else(|| std::env::temp_dir().join(format!("rtvtk-demo-{}", std::process::id())));
    // The `record` command with its own defaults, so the demo cannot drift from it.
    let (size, spp, threads) = (format!("{w}x{h}"), spp.to_string(), threads.max(1).to_string());
    let dir_arg = dir.to_string_lossy().to_string();
    let args = <crate::record::RecordArgs as clap::Parser>::try_parse_from([
        "record",
        "--scene",
        "cornell",
        "--out",
        &dir_arg,
        "--size",
        &size,
        "--spp",
        &spp,
        "--threads",
        &threads,
    ])?;
    crate::record::run(&args)?;
    println!();
    info(&dir, false)?;
    println!();
    let ds = Dataset::open(&dir)?;
    let (x, y) = (w / 2, h * 3 / 4);
    if let Some(t) = ds.trees_at_pixel(x, y, Some(0))?.first() {
        println!("the ray tree of pixel ({x}, {y}), sample 0:");
        print_tree(&ds, t);
    }
    println!();
    // The layered picture: the path-traced image, the scene's depth, and that tree's rays.
    let picture = dir.join("demo.png");
    let render = <crate::render::RenderArgs as clap::Parser>::try_parse_from([
        "render".to_string(),
        dir_arg.clone(),
        "--layers".into(),
        "image,composition,rays".into(),
        "--pixel".into(),
        format!("{x},{y}"),
        "--sample".into(),
        "0".into(),
        "--line-width".into(),
        "2".into(),
        "--out".into(),
        picture.to_string_lossy().to_string(),
    ])?;
    match crate::render::render_to_png(&render) {
        Ok(_) => println!(
            "picture: {} (that tree's rays over the path-traced image, hidden behind geometry)",
            picture.display()
        ),
        Err(e) => eprintln!("no picture: {e:#}"),
    }
    println!();
    if cfg!(feature = "sql") {
        println!("try: rtvtk view {}             # the interactive viewer", dir.display());
    } else {
        // The demo's quick first build leaves out the SQL engine, and the viewer with it.
        println!("try: cargo run -- view {}      # the interactive viewer (a default build)", dir.display());
    }
    println!("     rtvtk tree {} --pixel {},{}", dir.display(), w / 2, h / 2);
    println!(
        "     rtvtk render {} --layers image,composition,rays --pixel {},{} --out layers.png",
        dir.display(),
        w / 2,
        h / 2
    );
    println!("     rtvtk check {}", dir.display());
    Ok(())
}

/// `rtvtk converge`: error of the path tracer against time, as a table, a CSV and a plot.
pub fn converge(
    scene: &str,
    (w, h): (u32, u32),
    reference_spp: u32,
    spps: &[u32],
    out: &Path,
    threads: Option<usize>,
) -> Result<()> {
    use renderers::converge::{convergence, log_log_slope, write_plot};
    let scene = crate::record::load_scene(scene, None)?;
    let bvh = renderers::Bvh::build(&scene.tris);
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let base = renderers::RenderOptions { width: w, height: h, threads, ..Default::default() };
    eprintln!("rendering the {reference_spp}-spp reference of {} at {w}x{h} ...", scene.name);
    let (reference, points) = convergence(&scene, &bvh, &base, reference_spp, spps)?;
    std::fs::create_dir_all(out)?;
    reference.write_exr(&out.join("reference.exr"))?;
    reference.write_png(&out.join("reference.png"), 1.0)?;
    let mut csv = String::from("spp,seconds,rmse,rel_mse\n");
    println!("| spp | seconds | RMSE | relMSE |");
    println!("|---|---|---|---|");
    for p in &points {
        println!("| {} | {:.4} | {:.5} | {:.6} |", p.spp, p.secs, p.rmse, p.rel_mse);
        csv.push_str(&format!("{},{},{},{}\n", p.spp, p.secs, p.rmse, p.rel_mse));
    }
    std::fs::write(out.join("convergence.csv"), csv)?;
    write_plot(&points, &out.join("convergence.png"))?;
    let by_spp = log_log_slope(&points.iter().map(|p| (f64::from(p.spp), p.rmse)).collect::<Vec<_>>());
    let by_time = log_log_slope(&points.iter().map(|p| (p.secs, p.rmse)).collect::<Vec<_>>());
    let rel_spp = log_log_slope(&points.iter().map(|p| (f64::from(p.spp), p.rel_mse.sqrt())).collect::<Vec<_>>());
    let rel_time = log_log_slope(&points.iter().map(|p| (p.secs, p.rel_mse.sqrt())).collect::<Vec<_>>());
    println!();
    println!(
        "log-log slopes (Monte Carlo: -0.5): RMSE {by_spp:.3} vs spp, {by_time:.3} vs time; sqrt(relMSE) {rel_spp:.3} vs spp, {rel_time:.3} vs time"
    );
    println!(
        "wrote {}/convergence.csv, convergence.png (blue RMSE, red sqrt(relMSE), grey slope -1/2), reference.exr",
        out.display()
    );
    Ok(())
}

fn dataset_bytes(ds: &Dataset) -> u64 {
    ds.manifest().segments.iter().map(|s| s.rays.bytes + s.trees.bytes).sum()
}

pub fn info(dir: &Path, as_json: bool) -> Result<()> {
    let ds = Dataset::open(dir)?;
    let m = ds.manifest();
    let s = ds.stats();
    let bytes = dataset_bytes(&ds);
    let per_ray = if s.rays > 0 { bytes as f64 / s.rays as f64 } else { 0.0 };
    let payload: Vec<_> = m.payload.iter().map(|p| json!({"name": p.name, "type": p.type_name})).collect();
    if as_json {
        let v = json!({
            "path": dir,
            "format": m.format,
            "format_version": m.format_version,
            "encoding": m.encoding.name(),
            "complete": m.complete,
            "segments": m.segments.len(),
            "trees": s.trees,
            "rays": s.rays,
            "bytes": bytes,
            "bytes_per_ray": per_ray,
            "misses": s.misses,
            "non_finite_rays": s.non_finite,
            "rays_by_kind": s.rays_by_kind(),
            "rays_by_depth": s.rays_by_depth(),
            "rays_by_kind_and_depth": s.rays_by_kind_depth,
            "trees_by_max_depth": s.trees_by_max_depth,
            "kinds": m.kinds,
            "payload": payload,
            "bytes_payload": m.bytes_payload,
            "origin_bounds": (!s.origin_bounds.is_empty()).then_some(s.origin_bounds),
            "hit_bounds": (!s.hit_bounds.is_empty()).then_some(s.hit_bounds),
        });
        println!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    println!("dataset        {}", dir.display());
    println!(
        "format         {} v{}{}",
        m.format,
        m.format_version,
        if m.complete { "" } else { " (recording did not finish cleanly)" }
    );
    println!("encoding       {}", m.encoding.name());
    println!("segments       {}", m.segments.len());
    println!("trees          {}", s.trees);
    println!("rays           {}  ({} misses, {} with NaN/Inf)", s.rays, s.misses, s.non_finite);
    println!("bytes          {bytes}  ({per_ray:.2} B/ray)");
    println!("rays by kind");
    for (k, n) in s.rays_by_kind() {
        println!("  {k:<14} {n:>12}  {:5.1}%", 100.0 * n as f64 / s.rays.max(1) as f64);
    }
    println!("rays by depth");
    for (d, n) in s.rays_by_depth().iter().enumerate() {
        println!("  {d:<14} {n:>12}");
    }
    if m.payload.is_empty() && m.bytes_payload.is_none() {
        println!("payload        none");
    } else {
        println!("payload");
        for p in &m.payload {
            println!("  {:<14} {}", p.name, p.type_name);
        }
        if let Some(b) = m.bytes_payload {
            println!(
                "  {:<14} bytes ({})",
                "payload",
                match b {
                    rl::BytesPayload::Fixed(n) => format!("{n} per ray"),
                    rl::BytesPayload::Variable => "variable".into(),
                }
            );
        }
    }
    let b = |bb: &store::Bounds| {
        if bb.is_empty() { "empty".to_string() } else { format!("{:?} .. {:?}", bb.min, bb.max) }
    };
    println!("origin bounds  {}", b(&s.origin_bounds));
    println!("hit bounds     {}", b(&s.hit_bounds));
    Ok(())
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

fn print_tree(ds: &Dataset, t: &Tree) {
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

pub fn tree(dir: &Path, pixel: Option<(u32, u32)>, sample: Option<u32>, id: Option<u64>, as_json: bool) -> Result<()> {
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

pub fn check(dir: &Path, as_json: bool) -> Result<i32> {
    let ds = Dataset::open(dir)?;
    let r = ds.check();
    if as_json {
        println!("{}", serde_json::to_string_pretty(&json!({"ok": r.is_ok(), "report": r}))?);
    } else {
        for e in &r.errors {
            println!("error: {e}");
        }
        for w in &r.warnings {
            println!("warning: {w}");
        }
        println!(
            "{}: {} segments, {} trees, {} rays checked; {} errors, {} warnings",
            if r.is_ok() { "ok" } else { "FAILED" },
            r.segments,
            r.trees,
            r.rays,
            r.errors.len(),
            r.warnings.len()
        );
    }
    Ok(if r.is_ok() { 0 } else { 1 })
}

/// `rtvtk export`: a plain copy of a dataset.
pub fn export(dataset: &Path, out: &Path) -> Result<()> {
    let ds = Dataset::open(dataset).with_context(|| format!("opening {}", dataset.display()))?;
    let m = store::export_plain(&ds, out).with_context(|| format!("exporting to {}", out.display()))?;
    let bytes: u64 = m.segments.iter().map(|s| s.rays.bytes + s.trees.bytes).sum();
    println!(
        "exported {} rays in {} segments ({} encoding -> plain), {} bytes: {}",
        m.stats.rays,
        m.segments.len(),
        ds.encoding().name(),
        bytes,
        out.display()
    );
    Ok(())
}
