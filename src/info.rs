//! `rtvtk info`: counts, bytes per ray, kinds, payload schema and format version of a dataset.

use std::path::Path;

use anyhow::Result;
use rl::Dataset;
use serde_json::json;

/// `rtvtk info`: counts, bytes per ray, kinds, payload schema and format version of a dataset.
#[derive(clap::Args)]
pub struct InfoArgs {
    pub dataset: std::path::PathBuf,
    #[arg(long)]
    pub json: bool,
}

impl InfoArgs {
    pub fn run(&self) -> Result<()> {
        run(&self.dataset, self.json)
    }
}

/// What the dataset does not hold that a recording can, and what needs it: the optional tables,
/// the payload columns the analyses read, the built-in kinds no ray has.
fn left_out(ds: &Dataset) -> Vec<(String, &'static str)> {
    use store::scene::{BVH_NODES_TABLE, LIGHTS_TABLE, RAY_NODES_TABLE, SITES_TABLE, TRIANGLES_TABLE};
    let tables = ds.table_names();
    let mut out = Vec::new();
    for (t, why) in [
        (TRIANGLES_TABLE, "the scene's triangles (the geometry layer, numerics' leak check, bvh --whatif)"),
        (LIGHTS_TABLE, "no emitters recorded (numerics' wrong_shadow check, aims_at_light)"),
        (BVH_NODES_TABLE, "no BVH recorded (the bvh layer, analyze bvh)"),
        (RAY_NODES_TABLE, "visited nodes not recorded (record --record-visits)"),
        (SITES_TABLE, "recording sites not recorded (record --sites)"),
    ] {
        if !tables.iter().any(|n| n == t) {
            out.push((format!("table {t}"), why));
        }
    }
    let payload = &ds.manifest().payload;
    for (c, why) in [
        ("throughput", "numerics' energy check"),
        ("radiance", "numerics' firefly check"),
        ("nodes_visited", "traversal cost per ray (analyze bvh, diff)"),
    ] {
        if !payload.iter().any(|p| p.name == c) {
            out.push((format!("column {c}"), why));
        }
    }
    let used = &ds.manifest().kinds;
    for (k, _) in store::BUILTIN_KINDS {
        if !used.contains_key(k) {
            out.push((format!("kind {k}"), "no ray of it (its tracer path never ran: no glass, mirror or light in the scene, or left out by --record-kinds)"));
        }
    }
    out
}

/// The tables the recording wrote, each with why it cannot be read (None when it can): its file
/// checked whole (size, checksum, columns), the segments' tree tables too.
fn tables(ds: &Dataset) -> Vec<(String, Option<String>)> {
    let mut out: Vec<(String, Option<String>)> =
        ds.table_names().into_iter().map(|t| (t.clone(), ds.verify_table(&t).err().map(|e| e.to_string()))).collect();
    let broken: Vec<String> =
        (0..ds.manifest().segments.len()).filter_map(|i| ds.verify_trees(i).err().map(|e| e.to_string())).collect();
    out.push(("trees".into(), (!broken.is_empty()).then(|| broken.join("; "))));
    out
}

fn dataset_bytes(ds: &Dataset) -> u64 {
    ds.manifest().segments.iter().map(|s| s.rays.bytes + s.trees.bytes).sum()
}

pub fn run(dir: &Path, as_json: bool) -> Result<()> {
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
            "payload_mantissa_bits": m.payload_mantissa_bits,
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
            "left_out": left_out(&ds).iter().map(|(what, why)| json!({"what": what, "why": why})).collect::<Vec<_>>(),
            "tables": tables(&ds)
                .iter()
                .map(|(name, broken)| json!({"name": name, "available": broken.is_none(), "unavailable_because": broken}))
                .collect::<Vec<_>>(),
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
    if let Some(bits) = m.payload_mantissa_bits {
        println!("payload        lossy: float values rounded to {bits} mantissa bits");
    }
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
    let tables = tables(&ds);
    println!("tables         {}", tables.iter().map(|(t, _)| t.as_str()).collect::<Vec<_>>().join(", "));
    for (t, broken) in &tables {
        if let Some(why) = broken {
            println!("  unavailable  {t}: {why}");
        }
    }
    let left = left_out(&ds);
    if left.is_empty() {
        println!("left out       nothing");
    } else {
        println!("left out");
        for (what, why) in left {
            println!("  {what:<22} {why}");
        }
    }
    Ok(())
}
