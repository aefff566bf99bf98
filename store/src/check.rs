//! `check`: every invariant of a dataset, verified and reported.

use std::collections::{BTreeMap, HashSet};
use std::fs;

use std::fs::File;
use std::io::Read;
use std::path::Path;

use crate::dataset::Dataset;
use crate::manifest::Manifest;
use crate::stats::Stats;

const MAX_PER_SEGMENT: usize = 20;

/// What `check` found.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct CheckReport {
    pub segments: usize,
    pub trees: u64,
    pub rays: u64,
    /// Broken invariants: the dataset is not as its manifest says.
    pub errors: Vec<String>,
    /// Harmless leftovers (for example temporary files of an interrupted recording).
    pub warnings: Vec<String>,
}

impl CheckReport {
    pub fn is_ok(&self) -> bool {
        self.errors.is_empty()
    }
}

fn crc_of(path: &Path) -> std::io::Result<(u32, u64)> {
    let mut f = File::open(path)?;
    let mut h = crc32fast::Hasher::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf)?;
        if k == 0 {
            break;
        }
        h.update(&buf[..k]);
        n += k as u64;
    }
    Ok((h.finalize(), n))
}

fn listed_files(m: &Manifest) -> HashSet<String> {
    m.segments.iter().flat_map(|s| [s.rays.path.clone(), s.trees.path.clone()]).collect()
}

impl Dataset {
    /// Verifies every invariant of the dataset; problems are collected, not returned as errors.
    pub fn check(&self) -> CheckReport {
        check(self)
    }
}

fn check(ds: &Dataset) -> CheckReport {
    let m = ds.manifest();
    let mut r = CheckReport { segments: m.segments.len(), ..Default::default() };
    let mut all_ids: HashSet<u64> = HashSet::new();
    let mut total = Stats::default();
    for (i, seg) in m.segments.iter().enumerate() {
        total.merge(&seg.stats);
        let before = r.errors.len();
        // Files: present, same size and checksum as the manifest says.
        for f in [&seg.rays, &seg.trees] {
            let path = ds.dir().join(&f.path);
            match crc_of(&path) {
                Ok((_, n)) if n != f.bytes => r.errors.push(format!(
                    "segment {}: expected {} bytes, found {n} ({})",
                    seg.id,
                    f.bytes,
                    path.display()
                )),
                Ok((crc, _)) if crc != f.crc32 => r.errors.push(format!(
                    "segment {}: expected CRC32 {:08x}, computed {crc:08x}: file is corrupted ({})",
                    seg.id,
                    f.crc32,
                    path.display()
                )),
                Ok(_) => {}
                Err(e) => r.errors.push(format!("segment {}: cannot read: {e} ({})", seg.id, path.display())),
            }
        }
        if r.errors.len() > before {
            continue;
        }
        if let Err(e) = ds.segment_meta_checked(i) {
            r.errors.push(format!("segment {}: {e}", seg.id));
            continue;
        }
        // Tree table: ids in range and unique, rows tiling the ray file exactly.
        let mut entries = match ds.segment_entries(i) {
            Ok(e) => e,
            Err(e) => {
                r.errors.push(format!("segment {}: {e}", seg.id));
                continue;
            }
        };
        for e in &entries {
            let id = e.info.id.0;
            if id < seg.tree_id_min || id > seg.tree_id_max {
                r.errors.push(format!(
                    "segment {}: tree {id} outside the manifest's id range {}..={}",
                    seg.id, seg.tree_id_min, seg.tree_id_max
                ));
            }
            let pb = &seg.stats.pixel_bounds;
            if !pb.is_empty() && !pb.contains(e.info.pixel) {
                r.errors.push(format!(
                    "segment {}: tree {id} at pixel ({}, {}) outside the manifest's pixel bounds {:?}..={:?}",
                    seg.id, e.info.pixel[0], e.info.pixel[1], pb.min, pb.max
                ));
            }
            if !all_ids.insert(id) {
                r.errors.push(format!("segment {}: tree {id} appears more than once in the dataset", seg.id));
            }
        }
        entries.sort_unstable_by_key(|e| e.first_row);
        let mut row = 0u64;
        for e in &entries {
            if e.first_row != row {
                r.errors.push(format!(
                    "segment {}: tree {} starts at row {}, expected row {row} (trees must tile the ray file)",
                    seg.id, e.info.id, e.first_row
                ));
                break;
            }
            row += u64::from(e.info.ray_count);
        }
        if row != seg.rays.rows {
            r.errors.push(format!(
                "segment {}: tree table covers {row} rays, the ray file holds {}",
                seg.id, seg.rays.rows
            ));
        }
        // Version 2: every row group starts with a whole tree (so each decodes on its own).
        if m.format_version >= 2 && m.encoding != crate::Encoding::Plain {
            match ds.row_group_starts(i) {
                Ok(starts) => {
                    let tree_starts: HashSet<u64> = entries.iter().map(|e| e.first_row).collect();
                    if let Some(bad) = starts.iter().find(|s| !tree_starts.contains(s)) {
                        r.errors.push(format!(
                            "segment {}: a row group starts at row {bad}, inside a tree (row groups must start at trees)",
                            seg.id
                        ));
                    }
                }
                Err(e) => r.errors.push(format!("segment {}: {e}", seg.id)),
            }
        }
        if r.errors.len() > before {
            continue;
        }
        // Rays: every tree whole and well formed; kinds as counted.
        let mut by_kind: BTreeMap<String, u64> = BTreeMap::new();
        let mut trees = ds.trees_of_segment(i, entries);
        let mut seg_errors = 0;
        while let Some(t) = trees.next() {
            match t {
                Ok(t) => {
                    r.trees += 1;
                    r.rays += t.rays.len() as u64;
                    for ray in &t.rays {
                        let name = ds.kinds().name(ray.kind).unwrap_or("?").to_string();
                        *by_kind.entry(name).or_default() += 1;
                    }
                }
                Err(e) => {
                    seg_errors += 1;
                    r.errors.push(format!("segment {}: {e}", seg.id));
                    if seg_errors >= MAX_PER_SEGMENT {
                        r.errors.push(format!("segment {}: more errors not shown", seg.id));
                        break;
                    }
                    if trees.is_broken() {
                        break;
                    }
                }
            }
        }
        if seg_errors == 0 && by_kind != seg.stats.rays_by_kind() {
            r.errors.push(format!(
                "segment {}: rays by kind in the file {by_kind:?} differ from the manifest's {:?}",
                seg.id,
                seg.stats.rays_by_kind()
            ));
        }
    }
    if total.rays != m.stats.rays || total.trees != m.stats.trees {
        r.errors.push(format!(
            "manifest totals ({} rays, {} trees) differ from the sum of its segments ({} rays, {} trees)",
            m.stats.rays, m.stats.trees, total.rays, total.trees
        ));
    }
    for (name, f) in &m.tables {
        let path = ds.dir().join(&f.path);
        match crc_of(&path) {
            Ok((crc, n)) if n != f.bytes || crc != f.crc32 => r.errors.push(format!(
                "table `{name}`: expected {} bytes with CRC32 {:08x}, found {n} bytes with CRC32 {crc:08x} ({})",
                f.bytes,
                f.crc32,
                path.display()
            )),
            Ok(_) => {}
            Err(e) => r.errors.push(format!("table `{name}`: cannot read: {e} ({})", path.display())),
        }
        // Its columns against the table's known schema (`store::scene`).
        if let Err(e) = ds.table_schema(name) {
            r.errors.push(e.to_string());
        }
    }
    // Leftovers not listed in the manifest.
    let listed = listed_files(m);
    if let Ok(dir) = fs::read_dir(ds.dir().join("segments")) {
        let mut extra: Vec<String> = dir
            .filter_map(|e| e.ok())
            .map(|e| format!("segments/{}", e.file_name().to_string_lossy()))
            .filter(|p| !listed.contains(p))
            .collect();
        extra.sort();
        for p in extra {
            if p.ends_with(".tmp") {
                r.warnings.push(format!("{p}: temporary file of an interrupted recording (not part of the trace)"));
            } else {
                r.warnings.push(format!("{p}: file not listed in the manifest (ignored by readers)"));
            }
        }
    }
    if !m.complete {
        r.warnings.push(
            "the recording did not finish cleanly: the dataset holds the segments sealed before it stopped".into(),
        );
    }
    r
}
