//! `rtvtk info`: counts, bytes per ray, kinds, payload schema and format version of a dataset.

use std::path::Path;

use anyhow::Result;
use rl::Dataset;
use serde_json::json;

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
