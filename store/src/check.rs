//! `check`: every invariant of a dataset, verified and reported.

use std::collections::{BTreeMap, HashSet};
use std::fs;

use crate::dataset::{Dataset, crc_of};
use crate::manifest::Manifest;
use crate::stats::Stats;
use crate::tree::TreeValidator;

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

fn listed_files(m: &Manifest) -> HashSet<String> {
    m.segments.iter().flat_map(|s| [s.rays.path.clone(), s.trees.path.clone()]).collect()
}

impl Dataset {
    /// Verifies every invariant of the dataset; problems are collected, not returned as errors.
    pub fn check(&self) -> CheckReport {
        self.check_with(&|_| {})
    }

    /// [`Dataset::check`], calling `progress` with the rays of each segment once it is checked.
    /// Segments are checked on up to all cores at once; memory holds a few segments' tree tables
    /// (and a batch of ids per segment whose id range overlaps another's), whatever the trace's
    /// length.
    pub fn check_with(&self, progress: &(dyn Fn(u64) + Sync)) -> CheckReport {
        check(self, progress)
    }
}

/// What checking one segment found.
#[derive(Default)]
struct SegmentCheck {
    errors: Vec<String>,
    trees: u64,
    rays: u64,
}

/// Segments whose manifest id ranges overlap another segment's: only their ids can collide.
fn overlapping_segments(m: &Manifest) -> HashSet<usize> {
    let mut order: Vec<usize> = (0..m.segments.len()).collect();
    order.sort_unstable_by_key(|&i| (m.segments[i].tree_id_min, m.segments[i].tree_id_max));
    let mut out = HashSet::new();
    let mut reach: Option<(u64, usize)> = None; // the greatest max so far and its segment
    for &i in &order {
        let s = &m.segments[i];
        if let Some((hi, j)) = reach
            && s.tree_id_min <= hi
        {
            out.insert(i);
            out.insert(j);
        }
        if reach.is_none_or(|(hi, _)| s.tree_id_max > hi) {
            reach = Some((s.tree_id_max, i));
        }
    }
    out
}

fn check(ds: &Dataset, progress: &(dyn Fn(u64) + Sync)) -> CheckReport {
    let m = ds.manifest();
    let mut r = CheckReport { segments: m.segments.len(), ..Default::default() };
    let mut total = Stats::default();
    for seg in &m.segments {
        total.merge(&seg.stats);
    }
    let overlapping = overlapping_segments(m);
    // Segments on up to all cores (each segment decodes on one); results kept in segment order.
    let n = m.segments.len();
    let threads = crate::dataset::cores().clamp(1, 8).min(n.max(1));
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut results: Vec<Option<SegmentCheck>> = (0..n).map(|_| None).collect();
    let done: Vec<Vec<(usize, SegmentCheck)>> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..threads)
            .map(|_| {
                sc.spawn(|| {
                    let mut mine = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        if i >= n {
                            break;
                        }
                        let c = check_segment(ds, i);
                        progress(m.segments[i].rays.rows);
                        mine.push((i, c));
                    }
                    mine
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap_or_default()).collect()
    });
    for (i, c) in done.into_iter().flatten() {
        results[i] = Some(c);
    }
    for (i, c) in results.into_iter().enumerate() {
        let Some(c) = c else {
            r.errors.push(format!("segment {}: the thread checking it failed", m.segments[i].id));
            continue;
        };
        r.errors.extend(c.errors);
        r.trees += c.trees;
        r.rays += c.rays;
    }
    // Tree ids unique across segments: only segments with overlapping id ranges can share one;
    // their tree tables' sorted id columns are merged as streams.
    if overlapping.len() > 1 {
        let mut segs: Vec<usize> = overlapping.into_iter().collect();
        segs.sort_unstable();
        unique_across(ds, &segs, &mut r.errors);
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

/// Tree ids of segments `segs` (whose id ranges overlap) unique across them: a k-way merge of
/// their tree tables' `tree_id` columns, read as streams (a batch per segment in memory). An id
/// found in two segments is reported once per pair (ids repeated within one segment are reported
/// by its own check). A table that does not read, or is not sorted by id, is reported and leaves
/// the merge there.
fn unique_across(ds: &Dataset, segs: &[usize], errors: &mut Vec<String>) {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    type Ids = Box<dyn Iterator<Item = crate::Result<Vec<u64>>>>;
    struct Stream {
        ids: Ids,
        batch: Vec<u64>,
        at: usize,
        seg: u32,
    }
    // The next batch of a stream (empty at its end or after an error, which is reported).
    let refill = |s: &mut Stream, errors: &mut Vec<String>| {
        s.at = 0;
        s.batch = match s.ids.next() {
            Some(Ok(b)) => b,
            Some(Err(e)) => {
                errors.push(format!("segment {}: {e}", s.seg));
                Vec::new()
            }
            None => Vec::new(),
        };
    };
    let m = ds.manifest();
    let mut streams = Vec::with_capacity(segs.len());
    let mut heap = BinaryHeap::new();
    for &i in segs {
        let seg = m.segments[i].id;
        let ids: Ids = match ds.segment_tree_ids(i) {
            Ok(it) => Box::new(it),
            Err(e) => {
                errors.push(format!("segment {seg}: {e}"));
                continue;
            }
        };
        let mut s = Stream { ids, batch: Vec::new(), at: 0, seg };
        refill(&mut s, errors);
        if let Some(&id) = s.batch.first() {
            heap.push(Reverse((id, streams.len())));
        }
        streams.push(s);
    }
    let mut last: Option<(u64, usize)> = None;
    let mut reported = 0;
    while let Some(Reverse((id, k))) = heap.pop() {
        if let Some((prev, j)) = last
            && prev == id
            && j != k
            && reported < MAX_PER_SEGMENT
        {
            errors.push(format!("segment {}: tree {id} appears more than once in the dataset", streams[k].seg));
            reported += 1;
        }
        last = Some((id, k));
        let s = &mut streams[k];
        s.at += 1;
        if s.at == s.batch.len() {
            refill(s, errors);
        }
        if let Some(&next) = s.batch.get(s.at) {
            if next < id {
                errors.push(format!("segment {}: tree table not sorted by tree_id ({next} after {id})", s.seg));
                continue;
            }
            heap.push(Reverse((next, k)));
        }
    }
}

/// Every invariant of segment `i`: its files' sizes and checksums, its tree table (ids in the
/// manifest's range and unique, pixels in its bounds, trees tiling the ray file, row groups
/// starting at trees), and every ray decoded and checked against its tree, straight from the
/// decoded columns (no per-tree batches).
fn check_segment(ds: &Dataset, i: usize) -> SegmentCheck {
    let m = ds.manifest();
    let seg = &m.segments[i];
    let mut c = SegmentCheck::default();
    let r = &mut c.errors;
    // Files: present, same size and checksum as the manifest says.
    for (f, what) in [(&seg.rays, "ray file"), (&seg.trees, "tree table")] {
        let path = ds.dir().join(&f.path);
        match crc_of(&path) {
            Ok((_, n)) if n != f.bytes => r.push(format!(
                "segment {}: {what}: expected {} bytes, found {n} ({})",
                seg.id,
                f.bytes,
                path.display()
            )),
            Ok((crc, _)) if crc != f.crc32 => r.push(format!(
                "segment {}: {what}: expected CRC32 {:08x}, computed {crc:08x}: file is corrupted ({})",
                seg.id,
                f.crc32,
                path.display()
            )),
            Ok(_) => {}
            Err(e) => r.push(format!("segment {}: {what}: cannot read: {e} ({})", seg.id, path.display())),
        }
    }
    if !r.is_empty() {
        return c;
    }
    if let Err(e) = ds.segment_meta_checked(i) {
        r.push(format!("segment {}: {e}", seg.id));
        return c;
    }
    // Tree table (sorted by id): ids in range and unique, pixels in bounds.
    let mut entries = match ds.segment_entries(i) {
        Ok(e) => e,
        Err(e) => {
            r.push(format!("segment {}: {e}", seg.id));
            return c;
        }
    };
    let pb = &seg.stats.pixel_bounds;
    let mut last: Option<u64> = None;
    for e in &entries {
        let id = e.info.id.0;
        if id < seg.tree_id_min || id > seg.tree_id_max {
            r.push(format!(
                "segment {}: tree {id} outside the manifest's id range {}..={}",
                seg.id, seg.tree_id_min, seg.tree_id_max
            ));
        }
        if !pb.is_empty() && !pb.contains(e.info.pixel) {
            r.push(format!(
                "segment {}: tree {id} at pixel ({}, {}) outside the manifest's pixel bounds {:?}..={:?}",
                seg.id, e.info.pixel[0], e.info.pixel[1], pb.min, pb.max
            ));
        }
        if last == Some(id) {
            r.push(format!("segment {}: tree {id} appears more than once in the dataset", seg.id));
        }
        last = Some(id);
        if r.len() >= MAX_PER_SEGMENT {
            r.push(format!("segment {}: more errors not shown", seg.id));
            return c;
        }
    }
    // Rows tiling the ray file exactly.
    // A tree without rays starts where the next one does: it comes first (ties in any other
    // order broke the tiling check; found by the C ABI fuzz harness).
    entries.sort_unstable_by_key(|e| (e.first_row, e.info.ray_count));
    let mut row = 0u64;
    for e in &entries {
        if e.first_row != row {
            r.push(format!(
                "segment {}: tree {} starts at row {}, expected row {row} (trees must tile the ray file)",
                seg.id, e.info.id, e.first_row
            ));
            break;
        }
        row += u64::from(e.info.ray_count);
    }
    if row != seg.rays.rows {
        r.push(format!("segment {}: tree table covers {row} rays, the ray file holds {}", seg.id, seg.rays.rows));
    }
    // Version 2: every row group starts with a whole tree (so each decodes on its own).
    if m.format_version >= 2 && m.encoding != crate::Encoding::Plain {
        match ds.row_group_starts(i) {
            Ok(starts) => {
                let mut k = 0;
                for &s in &starts {
                    while k < entries.len() && entries[k].first_row < s {
                        k += 1;
                    }
                    if entries.get(k).is_none_or(|e| e.first_row != s) {
                        r.push(format!(
                            "segment {}: a row group starts at row {s}, inside a tree (row groups must start at trees)",
                            seg.id
                        ));
                        break;
                    }
                }
            }
            Err(e) => r.push(format!("segment {}: {e}", seg.id)),
        }
    }
    if !r.is_empty() {
        return c;
    }
    // Rays: every row decoded, every tree whole and well formed; kinds as counted.
    match check_rays(ds, i, &entries, &mut c) {
        Ok(by_kind) => {
            if c.errors.is_empty() && by_kind != seg.stats.rays_by_kind() {
                c.errors.push(format!(
                    "segment {}: rays by kind in the file {by_kind:?} differ from the manifest's {:?}",
                    seg.id,
                    seg.stats.rays_by_kind()
                ));
            }
        }
        Err(e) => c.errors.push(format!("segment {}: {e}", seg.id)),
    }
    c
}

/// Decodes the core columns of segment `i`'s ray file and checks each tree of `entries` (sorted by
/// first row, tiling the file) row by row; counts trees and rays into `c`, tree problems into its
/// errors. Returns the rays counted by kind name.
fn check_rays(
    ds: &Dataset,
    i: usize,
    entries: &[crate::TreeEntry],
    c: &mut SegmentCheck,
) -> crate::Result<BTreeMap<String, u64>> {
    use crate::schema::col;
    use crate::tree::primitive;
    use arrow::array::{Array, AsArray};
    use arrow::datatypes::{UInt8Type, UInt16Type, UInt32Type, UInt64Type};
    let seg = &ds.manifest().segments[i];
    let path = ds.dir().join(&seg.rays.path);
    let corrupt =
        |what: &str, message: String| crate::Error::Corrupt { path: path.clone(), what: what.into(), message };
    let mut by_code: BTreeMap<String, u64> = BTreeMap::new();
    let mut v = TreeValidator::default();
    let mut k = 0usize; // the current tree in `entries`
    let mut reported = 0usize;
    let finish = |v: &mut TreeValidator, c: &mut SegmentCheck, reported: &mut usize| {
        c.trees += 1;
        if let Err(message) = v.finish() {
            if *reported < MAX_PER_SEGMENT {
                c.errors.push(format!("segment {}: {}", seg.id, corrupt("ray file", message)));
            } else if *reported == MAX_PER_SEGMENT {
                c.errors.push(format!("segment {}: more errors not shown", seg.id));
            }
            *reported += 1;
        }
    };
    // Trees without rays come first in their place; start the first tree.
    let begin = |k: &mut usize, v: &mut TreeValidator, c: &mut SegmentCheck, reported: &mut usize| -> u64 {
        while let Some(e) = entries.get(*k) {
            v.start(e.info);
            if e.info.ray_count > 0 {
                return u64::from(e.info.ray_count);
            }
            finish(v, c, reported);
            *k += 1;
        }
        0
    };
    let mut left = begin(&mut k, &mut v, c, &mut reported); // rows of tree `k` still to come
    // The core columns, origins, directions and `t` decoded (their codec checked); payload
    // columns are covered by the files' checksums and not decoded (a fifth of the time).
    let core: Vec<String> = (ds.ray_schema().fields().iter())
        .filter(|f| crate::schema::CORE_RAY_COLUMNS.contains(&f.name().as_str()))
        .map(|f| f.name().clone())
        .collect();
    for b in ds.segment_columns(i, &core)? {
        let b = b?;
        let ids = primitive::<UInt64Type>(&b, col::TREE_ID, &path)?;
        let ray = primitive::<UInt32Type>(&b, col::RAY, &path)?;
        let parent = primitive::<UInt32Type>(&b, col::PARENT, &path)?;
        let depth = primitive::<UInt16Type>(&b, col::DEPTH, &path)?;
        let kind = b
            .column_by_name(col::KIND)
            .and_then(|c| c.as_dictionary_opt::<UInt8Type>())
            .ok_or_else(|| corrupt("column `kind`", "not Dictionary(UInt8, Utf8)".into()))?;
        let names =
            kind.values().as_string_opt::<i32>().ok_or_else(|| corrupt("column `kind`", "values not Utf8".into()))?;
        let mut counts = vec![0u64; names.len()];
        for (&key, n) in kind.keys().values().iter().zip(0..b.num_rows()) {
            let key = key as usize;
            if key >= counts.len() || kind.keys().is_null(n) {
                return Err(corrupt("column `kind`", format!("dictionary key {key} out of range")));
            }
            counts[key] += 1;
        }
        for (key, &n) in counts.iter().enumerate() {
            if n > 0 {
                let name = names.value(key);
                if !ds.manifest().kinds.contains_key(name) {
                    return Err(corrupt("column `kind`", format!("kind {name:?} is not declared in the manifest")));
                }
                *by_code.entry(name.to_string()).or_default() += n;
            }
        }
        let (ids, ray, depth) = (ids.values(), ray.values(), depth.values());
        for row in 0..b.num_rows() {
            if left == 0 {
                return Err(corrupt("ray file", format!("row {} is past the last tree of the tree table", c.rays)));
            }
            v.push(ids[row], ray[row], parent.is_valid(row).then(|| parent.value(row)), depth[row]);
            c.rays += 1;
            left -= 1;
            if left == 0 {
                finish(&mut v, c, &mut reported);
                k += 1;
                left = begin(&mut k, &mut v, c, &mut reported);
            }
        }
    }
    if left > 0 || k < entries.len() {
        return Err(corrupt(
            "ray file",
            format!("the file ends inside tree {} of the tree table", entries.get(k).map_or(0, |e| e.info.id.0)),
        ));
    }
    Ok(by_code)
}
