//! From a [`RaySelection`] to the rows to read: the segments that can hold a kept ray (by their
//! tree-id range, pixel bounds and per-kind, per-depth ray counts), and within a segment the rows
//! of the trees that can (by the tree table: id, pixel, sample, deepest ray, ray count). The SQL
//! scan and the viewer's layers read what [`Dataset::plan`] says; the rows it gives are a superset
//! of the kept rays (whole trees), which [`RaySelection::keeps_row`] narrows.

use super::*;
use crate::schema::col;
use crate::selection::{RaySelection, in_ranges, meets, span};
use arrow::array::AsArray;

/// One segment to read, with the rows to read when not all.
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentAccess {
    /// Index of the segment in the manifest's list.
    pub segment: usize,
    /// Sorted, disjoint row ranges of whole trees (`None`: every row).
    pub rows: Option<Arc<Vec<std::ops::Range<u64>>>>,
    /// The trees (0 where not counted: a row-group sample) and rays in those rows.
    pub trees: u64,
    pub rays: u64,
    /// The kept trees' entries when only they were read from the tree table (a narrow tree-id or
    /// pixel selection): a reader that needs their pixels takes them from here.
    pub entries: Option<Arc<Vec<TreeEntry>>>,
}

/// What to read for a selection: the segments, in trace order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AccessPlan {
    pub segments: Vec<SegmentAccess>,
}

impl AccessPlan {
    /// The rays in the planned rows.
    pub fn rays(&self) -> u64 {
        self.segments.iter().map(|s| s.rays).sum()
    }

    /// The trees in the planned rows.
    pub fn trees(&self) -> u64 {
        self.segments.iter().map(|s| s.trees).sum()
    }

    /// Whether every planned segment is read whole.
    pub fn whole_segments(&self) -> bool {
        self.segments.iter().all(|s| s.rows.is_none())
    }
}

/// Tree-id selections at most this wide read only the tree-table pages that hold those ids.
const NARROW_TREE_IDS: u64 = 1 << 16;
/// Pixel selections (on both `pixel_x` and `pixel_y`) covering at most this many pixels read only
/// the tree-table pages whose pixel statistics can hold them.
const NARROW_PIXELS: u64 = 1 << 16;

/// Whether pruning by the tree table pays for reading it. A tree, pixel or sample range always
/// does. A lower bound on depth or ray index alone keeps every tree that reaches it: worth it only
/// when few rays are that deep (the segment's ray counts per depth say how many), otherwise the
/// row selection would cut the segment into millions of ranges to skip little.
fn trees_worth_reading(sel: &RaySelection, by_kind_depth: &std::collections::BTreeMap<String, Vec<u64>>) -> bool {
    if sel.has_tree_filters() {
        return true;
    }
    let min_depth = sel.min(col::DEPTH);
    let (mut all, mut deep) = (0u64, 0u64);
    for counts in by_kind_depth.values() {
        for (d, &n) in counts.iter().enumerate() {
            all += n;
            if d as u64 >= min_depth {
                deep += n;
            }
        }
    }
    // No statistics (older datasets): prune.
    all == 0 || deep.saturating_mul(20) < all
}

impl Dataset {
    /// The rows that can hold the rays `sel` keeps: segments ruled out by their manifest entry
    /// are left out, and where a tree-level range (or a rare depth) makes it pay, only the rows
    /// of the trees that can hold a kept ray are read. Reads tree tables only then (a narrow
    /// tree-id or pixel selection only the pages of them that can hold its trees), each checked
    /// whole first (size, CRC32, columns).
    pub fn plan(&self, sel: &RaySelection) -> Result<AccessPlan> {
        let mut out = Vec::new();
        let depths = sel.ranges(col::DEPTH);
        for (i, seg) in self.manifest().segments.iter().enumerate() {
            if !meets(sel.ranges(col::TREE_ID), seg.tree_id_min, seg.tree_id_max) {
                continue;
            }
            let pb = &seg.stats.pixel_bounds;
            let pixels_may_match = pb.is_empty()
                || (meets(sel.ranges(col::PIXEL_X), u64::from(pb.min[0]), u64::from(pb.max[0]))
                    && meets(sel.ranges(col::PIXEL_Y), u64::from(pb.min[1]), u64::from(pb.max[1])));
            if !pixels_may_match {
                continue;
            }
            let by_kind = &seg.stats.rays_by_kind_depth;
            if !by_kind.is_empty() {
                let any = by_kind.iter().any(|(kind, counts)| {
                    sel.keeps_kind(kind)
                        && counts.iter().enumerate().any(|(d, &n)| n > 0 && in_ranges(depths, d as u64))
                });
                if !any {
                    continue;
                }
            }
            let deep = sel.min(col::DEPTH) > 0;
            if !(sel.has_tree_filters() || deep) || !trees_worth_reading(sel, by_kind) {
                out.push(SegmentAccess {
                    segment: i,
                    rows: None,
                    trees: seg.trees.rows,
                    rays: seg.rays.rows,
                    entries: None,
                });
                continue;
            }
            let narrow_ids = sel.ranges(col::TREE_ID).is_some_and(|r| span(r) <= NARROW_TREE_IDS);
            let narrow_pixels = match (sel.ranges(col::PIXEL_X), sel.ranges(col::PIXEL_Y)) {
                (Some(x), Some(y)) => span(x).saturating_mul(span(y)) <= NARROW_PIXELS,
                _ => false,
            };
            // The segment's tree file is checked whole (size, CRC32, columns) once per process
            // before it is planned over: a corrupted file is refused naming the segment instead
            // of answering with damaged pixels or ids.
            self.verify_trees(i)?;
            let entries = if narrow_ids || narrow_pixels {
                let mut kept = self.segment_tree_entries_where(i, &sel.tree_filter())?;
                kept.retain(|e| sel.keeps_tree(&e.info));
                Arc::new(kept)
            } else {
                self.segment_tree_entries(i)?
            };
            let mut rows: Vec<std::ops::Range<u64>> = Vec::new();
            let mut rays = 0u64;
            for e in entries.iter().filter(|e| sel.keeps_tree(&e.info)) {
                let n = u64::from(e.info.ray_count);
                rays += n;
                rows.push(e.first_row..e.first_row + n);
            }
            if rows.is_empty() {
                continue;
            }
            let trees = rows.len() as u64;
            let rows = if trees == seg.trees.rows {
                None
            } else {
                rows.sort_unstable_by_key(|r| r.start);
                let mut merged: Vec<std::ops::Range<u64>> = Vec::with_capacity(rows.len());
                for r in rows {
                    match merged.last_mut() {
                        Some(last) if last.end == r.start => last.end = r.end,
                        _ => merged.push(r),
                    }
                }
                Some(Arc::new(merged))
            };
            out.push(SegmentAccess {
                segment: i,
                rows,
                trees,
                rays,
                entries: (narrow_ids || narrow_pixels).then_some(entries),
            });
        }
        Ok(AccessPlan { segments: out })
    }

    /// How many rays `sel` keeps: from the manifest's counts where they say it, otherwise
    /// [`Dataset::count_planned`] over its plan.
    pub fn count(&self, sel: &RaySelection) -> Result<u64> {
        match self.counted_by_manifest(sel) {
            Some(n) => Ok(n),
            None => self.count_planned(sel, &self.plan(sel)?),
        }
    }

    /// The rays `sel` keeps by the manifest's per-kind, per-depth counts: when it constrains
    /// nothing but kind and depth and the counts cover every ray (`None` otherwise).
    fn counted_by_manifest(&self, sel: &RaySelection) -> Option<u64> {
        let counts = &self.manifest().stats.rays_by_kind_depth;
        let recorded: u64 = counts.values().flatten().sum();
        if sel.has_tree_filters() || sel.ranges(col::RAY).is_some() || recorded != self.ray_count() {
            return None;
        }
        let depths = sel.ranges(col::DEPTH);
        Some(
            counts
                .iter()
                .filter(|(k, _)| sel.keeps_kind(k))
                .flat_map(|(_, v)| v.iter().enumerate())
                .filter(|(d, _)| in_ranges(depths, *d as u64))
                .map(|(_, &n)| n)
                .sum(),
        )
    }

    /// How many rays of `plan` (a plan of `sel`) `sel` keeps: the planned rays when `sel` has no
    /// row-level range (kind, depth, ray index), the manifest's counts where they say it, else a
    /// scan of those three columns.
    pub fn count_planned(&self, sel: &RaySelection, plan: &AccessPlan) -> Result<u64> {
        if !sel.has_row_filters() {
            return Ok(plan.rays());
        }
        if let Some(n) = self.counted_by_manifest(sel) {
            return Ok(n);
        }
        let names: Vec<String> = [col::KIND, col::DEPTH, col::RAY].map(String::from).to_vec();
        let mut n = 0u64;
        for part in &plan.segments {
            let path = self.dir.join(&self.segment(part.segment).rays.path);
            let rows = part.rows.as_deref().map(Vec::as_slice);
            for b in self.segment_columns_in(part.segment, &names, rows, READ_BATCH_ROWS)? {
                let b = b?;
                let kinds = crate::selection::kind_codes(b.column(0).as_ref())
                    .map_err(arrow_err(path.display().to_string()))?;
                let depth = arrow::compute::cast(b.column(1), &arrow::datatypes::DataType::UInt64)
                    .map_err(arrow_err(path.display().to_string()))?;
                let ray = arrow::compute::cast(b.column(2), &arrow::datatypes::DataType::UInt64)
                    .map_err(arrow_err(path.display().to_string()))?;
                let (depth, ray) = (depth.as_primitive::<UInt64Type>(), ray.as_primitive::<UInt64Type>());
                let keep: Vec<bool> = kinds.0.iter().map(|k| k.as_deref().is_some_and(|k| sel.keeps_kind(k))).collect();
                n += kinds
                    .1
                    .iter()
                    .enumerate()
                    .filter(|&(r, &k)| keep[k] && sel.keeps_depth_and_ray(depth.value(r), ray.value(r)))
                    .count() as u64;
            }
        }
        Ok(n)
    }

    /// A thinner plan for a sample keeping share `p` of `plan`'s rays (whole segments only): row
    /// groups evenly spaced over the planned segments' row groups in trace order (which lies in
    /// pixel order, so the sample spreads over the image), `oversample` times `p` of them and at
    /// least `min_groups`. Row groups of encoded files start at trees, so each decodes alone.
    /// Returns it with the row groups kept and their total; `None` when it would keep them all.
    pub fn spread_row_groups(
        &self,
        plan: &AccessPlan,
        p: f64,
        oversample: f64,
        min_groups: usize,
    ) -> Result<Option<(AccessPlan, usize, usize)>> {
        if !plan.whole_segments() {
            return Ok(None);
        }
        let mut groups: Vec<(usize, std::ops::Range<u64>)> = Vec::new();
        for part in &plan.segments {
            groups.extend(self.segment_row_groups(part.segment)?.into_iter().map(|r| (part.segment, r)));
        }
        let all = groups.len();
        let want = ((p * oversample * all as f64).ceil() as usize).max(min_groups);
        if want >= all {
            return Ok(None);
        }
        let mut per: std::collections::BTreeMap<usize, Vec<std::ops::Range<u64>>> = Default::default();
        // Group k of `want` is the one at (k + 1/2) * all / want: evenly spread, ends included.
        for k in 0..want {
            let g = (((k as f64 + 0.5) * all as f64 / want as f64) as usize).min(all - 1);
            let (i, r) = &groups[g];
            let v = per.entry(*i).or_default();
            match v.last_mut() {
                Some(last) if last.end == r.start => last.end = r.end,
                Some(last) if last.start == r.start => {}
                _ => v.push(r.clone()),
            }
        }
        let segments = per
            .into_iter()
            .map(|(segment, rows)| SegmentAccess {
                segment,
                rays: rows.iter().map(|r| r.end - r.start).sum(),
                trees: 0,
                rows: Some(Arc::new(rows)),
                entries: None,
            })
            .collect();
        Ok(Some((AccessPlan { segments }, want, all)))
    }
}
