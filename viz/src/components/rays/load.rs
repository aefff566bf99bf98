//! Loading the rays a selection keeps: the store's plan cut into pieces (a row group each where
//! row groups start at trees), decoded and sampled into segments on every core, handed over in
//! trace order.

use arrow::array::{Array, AsArray, RecordBatch};
use arrow::datatypes::UInt64Type;
use store::RaySelection;

use super::kind_color;
use crate::draw::GpuSegment;
use crate::lines::{SegmentBuilder, f32_columns};
use crate::{Error, Result};

/// Part of a load decoded on one thread: rows of one segment (whole row groups, or the tree
/// ranges a filter kept within one row group).
pub(super) struct Piece {
    pub(super) segment: usize,
    pub(super) rows: Option<Vec<std::ops::Range<u64>>>,
}

/// The pieces that read `plan`'s rows, in trace order: row group by row group where row groups
/// start at trees (format version 2 on, or plain columns), so each decodes alone; otherwise a
/// segment at a time.
pub(super) fn pieces(ds: &store::Dataset, plan: &store::AccessPlan) -> Result<Vec<Piece>> {
    let m = ds.manifest();
    let split = m.format_version >= 2 || m.encoding == store::Encoding::Plain;
    let mut out = Vec::new();
    for part in &plan.segments {
        let (i, ranges) = (part.segment, part.rows.as_deref().map(Vec::as_slice));
        if !split {
            out.push(Piece { segment: i, rows: ranges.map(<[_]>::to_vec) });
            continue;
        }
        for g in ds.segment_row_groups(i)? {
            let Some(ranges) = ranges else {
                out.push(Piece { segment: i, rows: Some(vec![g]) });
                continue;
            };
            let within: Vec<std::ops::Range<u64>> =
                ranges.iter().map(|r| r.start.max(g.start)..r.end.min(g.end)).filter(|r| !r.is_empty()).collect();
            if !within.is_empty() {
                out.push(Piece { segment: i, rows: Some(within) });
            }
        }
    }
    Ok(out)
}

/// The columns a load reads, in [`RowSampler::batch`]'s order.
pub(super) fn load_columns() -> Vec<String> {
    use store::scene::col;
    let [ox, oy, oz] = col::ORIGIN;
    let [dx, dy, dz] = col::DIR;
    [col::TREE_ID, col::RAY, col::DEPTH, col::KIND, ox, oy, oz, dx, dy, dz, col::T].map(String::from).to_vec()
}

/// What one batch of rows became: the segments of the rows kept (in row order) with their tree
/// and ray ids and kinds, and what was counted on the way.
#[derive(Debug, Default)]
pub(super) struct Kept {
    /// Rows read.
    pub(super) rows: u64,
    /// Rows the filters kept (before sampling).
    pub(super) matched: u64,
    pub(super) skipped: u64,
    pub(super) misses: u64,
    pub(super) segments: Vec<GpuSegment>,
    pub(super) picks: Vec<(u64, u32)>,
    /// Per kept segment, its kind's index in `kind_names`.
    pub(super) kind_of: Vec<u16>,
    pub(super) kind_names: Vec<String>,
}

impl Kept {
    /// Only the first `n` segments (the end of the budget).
    pub(super) fn truncate(&mut self, n: usize) {
        self.segments.truncate(n);
        self.picks.truncate(n);
        self.kind_of.truncate(n);
    }

    /// Segments kept per kind name.
    pub(super) fn kinds(&self) -> Vec<(&str, u64)> {
        let mut n = vec![0u64; self.kind_names.len()];
        for &k in &self.kind_of {
            n[usize::from(k)] += 1;
        }
        self.kind_names.iter().map(String::as_str).zip(n).filter(|(_, n)| *n > 0).collect()
    }
}

/// Turns rows (columns in the load's order: tree, ray, depth, kind, origin, direction, t) into
/// segments: the rows the selection keeps, then, where `p` < 1, a sample keeping share `p` of each
/// (kind, depth) stratum. Within a stratum the sample is systematic (every 1/p-th ray: rows
/// arrive tree by tree in pixel order, so the kept rays spread over the image too), from a
/// start drawn from `seed` and the stratum: each piece of a load samples alone, and a fixed
/// start would keep nothing of a stratum with fewer than 1/p rays per piece.
pub(super) struct RowSampler<'a> {
    sel: &'a RaySelection,
    /// The tree drawn highlighted.
    selected_tree: Option<u64>,
    p: f64,
    builder: SegmentBuilder,
    seed: u64,
    /// Each stratum's accumulator, by kind id and then depth (a lookup per row: no hashing).
    strata: Vec<Vec<f64>>,
    kind_ids: Vec<String>,
}

impl<'a> RowSampler<'a> {
    pub(super) fn new(
        sel: &'a RaySelection,
        selected_tree: Option<u64>,
        p: f64,
        builder: SegmentBuilder,
        seed: u64,
    ) -> Self {
        RowSampler { sel, selected_tree, p, builder, seed, strata: Vec::new(), kind_ids: Vec::new() }
    }

    /// The start of a stratum's systematic sample in [0, 1): a hash of the seed, kind and depth.
    fn start(&self, kind: &str, depth: usize) -> f64 {
        let mut h = self.seed ^ 0x9E37_79B9_7F4A_7C15;
        for b in kind.bytes().chain((depth as u64).to_le_bytes()) {
            h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01B3);
        }
        // splitmix64's finalizer, then the top 53 bits as a fraction.
        h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        h ^= h >> 31;
        (h >> 11) as f64 / (1u64 << 53) as f64
    }

    pub(super) fn batch(&mut self, b: &RecordBatch) -> Result<Kept> {
        use store::scene::col;
        let [ox, oy, oz] = col::ORIGIN;
        let [dx, dy, dz] = col::DIR;
        let sel = self.sel;
        let mut out = Kept { rows: b.num_rows() as u64, ..Kept::default() };
        let [ox, oy, oz, dx, dy, dz, t] = f32_columns(b, [ox, oy, oz, dx, dy, dz, col::T])?;
        let tree = arrow::compute::cast(b.column(0), &arrow::datatypes::DataType::UInt64)?;
        let tree = tree.as_primitive::<UInt64Type>();
        let ray = arrow::compute::cast(b.column(1), &arrow::datatypes::DataType::UInt32)?;
        let ray = ray.as_primitive::<arrow::datatypes::UInt32Type>();
        let depth = arrow::compute::cast(b.column(2), &arrow::datatypes::DataType::UInt32)?;
        let depth = depth.as_primitive::<arrow::datatypes::UInt32Type>();
        let (names_of, codes) = store::selection::kind_codes(b.column(3).as_ref())?;
        // Per kind value: its colour, whether the kind filter keeps it, and its stratum id.
        let per_kind: Vec<([u8; 4], bool, usize)> = names_of
            .iter()
            .map(|n| {
                let n = n.as_deref().unwrap_or("?");
                let id = match self.kind_ids.iter().position(|k| k == n) {
                    Some(i) => i,
                    None => {
                        self.kind_ids.push(n.to_string());
                        self.kind_ids.len() - 1
                    }
                };
                (kind_color(n), sel.keeps_kind(n), id)
            })
            .collect();
        out.kind_names = names_of.iter().map(|n| n.clone().unwrap_or_default()).collect();
        let keep_share = self.p;
        for (r, &k) in codes.iter().enumerate() {
            let (colour, keep, stratum) = per_kind[k];
            if !keep || !sel.keeps_depth_and_ray(u64::from(depth.value(r)), u64::from(ray.value(r))) {
                continue;
            }
            out.matched += 1;
            if keep_share < 1.0 {
                let d = depth.value(r) as usize;
                if self.strata.len() <= stratum {
                    self.strata.resize_with(stratum + 1, Vec::new);
                }
                if self.strata[stratum].len() <= d {
                    let starts: Vec<f64> = (self.strata[stratum].len()..=d)
                        .map(|depth| self.start(&self.kind_ids[stratum], depth))
                        .collect();
                    self.strata[stratum].extend(starts);
                }
                let acc = &mut self.strata[stratum][d];
                *acc += keep_share;
                if *acc < 1.0 {
                    continue;
                }
                *acc -= 1.0;
            }
            // A miss has a null t.
            let tv = if t.is_null(r) { f32::INFINITY } else { t.value(r) };
            let Some((a, e)) =
                self.builder.end([ox.value(r), oy.value(r), oz.value(r)], [dx.value(r), dy.value(r), dz.value(r)], tv)
            else {
                continue;
            };
            let flags = u32::from(self.selected_tree == Some(tree.value(r)));
            out.segments.push(self.builder.segment(a, e, colour, flags));
            out.picks.push((tree.value(r), ray.value(r)));
            out.kind_of.push(k as u16);
        }
        out.skipped = std::mem::take(&mut self.builder.skipped);
        out.misses = std::mem::take(&mut self.builder.misses);
        Ok(out)
    }
}

/// Pieces decoded ahead of the one being consumed, at most: the decoders keep working while
/// this thread waits for the device to take a chunk of segments (what a piece keeps is at most
/// a row group's segments, ~128K of 46 bytes).
pub(super) const PIECES_AHEAD: usize = 8;

/// Decodes `pieces` of `ds` (the columns `names`) and samples them into segments on all cores,
/// each piece with its own `sampler(index)`, at most [`PIECES_AHEAD`] ahead, and hands what they
/// kept to `consume` in trace order on this thread. When `consume` returns false the decoders
/// stop after their batch in progress. Decoding on one thread and building segments on another
/// made a 50M-ray load 1.5x a SQL scan of the same columns (which decodes on every core).
pub(super) fn read_pieces<'s>(
    ds: &store::Dataset,
    names: &[String],
    pieces: Vec<Piece>,
    sampler: &(dyn Fn(usize) -> RowSampler<'s> + Sync),
    consume: &mut dyn FnMut(Kept) -> Result<bool>,
) -> Result<()> {
    use std::sync::mpsc;
    type Out = mpsc::SyncSender<Result<Kept>>;
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()).clamp(1, 8).min(pieces.len().max(1));
    let (work, jobs) = mpsc::channel::<(usize, Piece, Out)>();
    let jobs = std::sync::Mutex::new(jobs);
    std::thread::scope(|sc| -> Result<()> {
        // Owned here: returning drops it, which closes the queue and ends the decoders.
        let work = work;
        for t in 0..threads {
            let jobs = &jobs;
            let spawned =
                std::thread::Builder::new().name(format!("rtvtk-rays-read-{t}")).spawn_scoped(sc, move || {
                    loop {
                        // The lock is held only to take a job: a closed queue ends the thread.
                        let job = jobs.lock().map_err(|_| ()).and_then(|q| q.recv().map_err(|_| ()));
                        let Ok((index, piece, out)) = job else { return };
                        let batches = match ds.segment_columns_in(
                            piece.segment,
                            names,
                            piece.rows.as_deref(),
                            store::READ_BATCH_ROWS,
                        ) {
                            Ok(it) => it,
                            Err(e) => {
                                let _ = out.send(Err(e.into()));
                                continue;
                            }
                        };
                        let mut smp = sampler(index);
                        for b in batches {
                            let kept = b.map_err(Error::from).and_then(|b| smp.batch(&b));
                            let failed = kept.is_err();
                            if out.send(kept).is_err() || failed {
                                break;
                            }
                        }
                    }
                });
            if let Err(e) = spawned {
                return Err(Error::from(store::Error::Io {
                    action: "starting a thread that reads rays",
                    path: ds.dir().to_path_buf(),
                    source: e,
                }));
            }
        }
        // Pieces handed out and not yet consumed, oldest first.
        let mut ahead: std::collections::VecDeque<mpsc::Receiver<Result<Kept>>> = Default::default();
        let mut pieces = pieces.into_iter().enumerate();
        loop {
            while ahead.len() < PIECES_AHEAD {
                let Some((index, piece)) = pieces.next() else { break };
                // Room for a whole row group's batches (64K rows each): its decoder never
                // waits; a whole segment (older files) waits after four.
                let (tx, rx) = mpsc::sync_channel(4);
                if work.send((index, piece, tx)).is_err() {
                    break;
                }
                ahead.push_back(rx);
            }
            let Some(rx) = ahead.pop_front() else { return Ok(()) };
            // Ends when its decoder is done with the piece (the sender dropped).
            for kept in rx {
                if !consume(kept?)? {
                    // Dropping the queue and the receivers stops the decoders.
                    return Ok(());
                }
            }
        }
    })
}

/// Traces of more rays than this load a sample from some of their row groups only (see
/// [`store::Dataset::spread_row_groups`]); smaller ones are read whole and sampled ray by ray.
pub(super) const SUBSET_ABOVE: u64 = 32_000_000;
/// A subset reads this many times the rays a sample keeps ...
pub(super) const SUBSET_OVERSAMPLE: f64 = 16.0;
/// ... and at least this many row groups (about 4M rays: patches spread over the image).
pub(super) const SUBSET_MIN_GROUPS: usize = 32;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::component::Frame;
    use std::collections::BTreeMap;
    use store::{DatasetWriter, KindTable, PayloadSchema, RayColumns, RayFields, TreeRow, WriteOptions};

    /// A lossless dataset of 3 segments with row groups of ~64 rays (trees of 1..=5 rays).
    fn dataset(dir: &std::path::Path) -> store::Dataset {
        let schema = PayloadSchema::default();
        let options = WriteOptions { row_group_rows: 64, page_rows: 16, ..WriteOptions::default() };
        let w = DatasetWriter::create(dir, schema.clone(), options).unwrap();
        let kinds = KindTable::default();
        let mut id = 0u64;
        for _ in 0..3 {
            let mut seg = w.open_segment().unwrap();
            let mut cols = RayColumns::new(&schema);
            for _ in 0..1500 {
                let first = cols.len() as u64;
                let n = (id % 5 + 1) as u32;
                for r in 0..n {
                    let f = RayFields {
                        origin: [r as f32, id as f32, 0.5],
                        direction: [0.0, 0.0, -1.0],
                        t: Some(1.0),
                        kind: if r == 0 { store::Kind::CAMERA } else { store::Kind::DIFFUSE },
                        prim: Some(1),
                    };
                    cols.push_core(id, r, if r == 0 { store::NONE_U32 } else { r - 1 }, r as u16, &f);
                }
                cols.trees.push(TreeRow {
                    tree_id: id,
                    pixel_x: (id % 64) as u32,
                    pixel_y: (id / 64) as u32,
                    sample: 0,
                    ray_count: n,
                    max_depth: n as u16 - 1,
                    first_row: first,
                });
                id += 1;
            }
            seg.write(cols, &schema, &kinds).unwrap();
            seg.seal(&w, &kinds).unwrap();
        }
        w.mark_complete().unwrap();
        store::Dataset::open(dir).unwrap()
    }

    /// The subset of a large trace's row groups is as many as asked (at least the minimum),
    /// spread evenly from the first segment to the last, made of whole row groups that start at
    /// trees; asking for most of the trace reads it whole.
    #[test]
    fn row_group_subsets_are_evenly_spread_whole_row_groups() {
        let dir = tempfile::tempdir().unwrap();
        let ds = dataset(&dir.path().join("ds"));
        let groups: Vec<(usize, std::ops::Range<u64>)> =
            (0..3).flat_map(|i| ds.segment_row_groups(i).unwrap().into_iter().map(move |r| (i, r))).collect();
        let all = groups.len();
        assert!(all > 4 * SUBSET_MIN_GROUPS, "{all} row groups");
        for p in [0.0001, 0.01] {
            let whole = ds.plan(&RaySelection::all()).unwrap();
            let (plan, read, total) =
                ds.spread_row_groups(&whole, p, SUBSET_OVERSAMPLE, SUBSET_MIN_GROUPS).unwrap().unwrap();
            let rows: BTreeMap<usize, Vec<std::ops::Range<u64>>> =
                plan.segments.iter().map(|s| (s.segment, s.rows.as_deref().unwrap().clone())).collect();
            let want = ((p * SUBSET_OVERSAMPLE * all as f64).ceil() as usize).max(SUBSET_MIN_GROUPS);
            assert_eq!((read, total), (want, all));
            let chosen: Vec<(usize, std::ops::Range<u64>)> = groups
                .iter()
                .filter(|(i, g)| rows.get(i).is_some_and(|v| v.iter().any(|r| r.start <= g.start && g.end <= r.end)))
                .cloned()
                .collect();
            assert_eq!(chosen.len(), want, "p = {p}");
            assert_eq!(rows.keys().copied().collect::<Vec<_>>(), vec![0, 1, 2], "every segment is sampled");
            // Each range starts at a tree.
            for (i, v) in &rows {
                let starts: std::collections::HashSet<u64> =
                    ds.segment_tree_entries(*i).unwrap().iter().map(|e| e.first_row).collect();
                assert!(v.iter().all(|r| starts.contains(&r.start)), "segment {i}: {v:?}");
            }
            // Gaps between chosen groups differ by at most one group.
            let pos: Vec<usize> = chosen.iter().map(|c| groups.iter().position(|g| g == c).unwrap()).collect();
            let gaps: Vec<usize> = pos.windows(2).map(|w| w[1] - w[0]).collect();
            assert!(gaps.iter().max().unwrap() - gaps.iter().min().unwrap() <= 1, "{gaps:?}");
        }
        let whole = ds.plan(&RaySelection::all()).unwrap();
        assert!(
            ds.spread_row_groups(&whole, 0.5, SUBSET_OVERSAMPLE, SUBSET_MIN_GROUPS).unwrap().is_none(),
            "most of the trace: read whole"
        );
    }

    /// The load's pieces, decoded on several threads, hand over every row asked for exactly once
    /// and in trace order, each piece within one row group; with tree ranges that cross row
    /// groups too; and a consumer that stops early ends the read.
    #[test]
    fn pieces_read_on_all_cores_come_back_in_trace_order() {
        let dir = tempfile::tempdir().unwrap();
        let ds = dataset(&dir.path().join("ds"));
        let names = load_columns();
        let sel = RaySelection::all();
        let frame = Frame { anchor: [0.0; 3], radius: 10.0 };
        let whole = ds.plan(&sel).unwrap();
        let read = |plan: &store::AccessPlan, stop_after: usize| {
            let mut got: Vec<(u64, u32, f32)> = Vec::new();
            let sampler = |_: usize| RowSampler::new(&sel, None, 1.0, SegmentBuilder::new(None, frame), 0);
            read_pieces(&ds, &names, pieces(&ds, plan).unwrap(), &sampler, &mut |k| {
                for (seg, &(tree, ray)) in k.segments.iter().zip(&k.picks) {
                    got.push((tree, ray, seg.a[1]));
                }
                Ok(got.len() < stop_after)
            })
            .unwrap();
            got
        };
        // Every row: the trees in id order (as written), rays 0..n each, origins decoded.
        let all = read(&whole, usize::MAX);
        assert_eq!(all.len() as u64, ds.ray_count());
        let mut want = Vec::new();
        for id in 0..4500u64 {
            for r in 0..(id % 5 + 1) as u32 {
                want.push((id, r, id as f32));
            }
        }
        assert_eq!(all, want);
        let groups = ds.segment_row_groups(1).unwrap();
        let total: usize = (0..3).map(|i| ds.segment_row_groups(i).unwrap().len()).sum();
        assert_eq!(pieces(&ds, &whole).unwrap().len(), total, "a piece per row group");
        // Tree ranges crossing row groups: split at the groups, rows the same.
        let (a, b) = (groups[1].start, groups[3].end);
        let entries = ds.segment_tree_entries(1).unwrap();
        let (a, b) = (
            entries.iter().map(|e| e.first_row).filter(|&r| r >= a + 3).min().unwrap(),
            entries.iter().map(|e| e.first_row).filter(|&r| r <= b - 3).max().unwrap(),
        );
        let rows = store::AccessPlan {
            segments: vec![store::SegmentAccess {
                segment: 1,
                rows: Some(std::sync::Arc::new(std::iter::once(a..b).collect())),
                trees: 0,
                rays: b - a,
                entries: None,
            }],
        };
        let ps = pieces(&ds, &rows).unwrap();
        assert_eq!(ps.len(), 3, "three row groups touched");
        for p in &ps {
            let r = &p.rows.as_ref().unwrap()[0];
            assert!(groups.iter().any(|g| g.start <= r.start && r.end <= g.end), "{r:?} within one row group");
        }
        let part = read(&rows, usize::MAX);
        assert_eq!(part.len() as u64, b - a);
        let first = want.iter().position(|w| w.0 == part[0].0 && w.1 == 0).unwrap();
        assert_eq!(part[..], want[first..first + part.len()]);
        // Stopping early returns promptly with what was consumed.
        let some = read(&whole, 10);
        assert!(some.len() >= 10 && some.len() < all.len() && some[..] == want[..some.len()]);
    }

    /// Pieces sampled apart keep share p of every (kind, depth) stratum, rare ones included: a
    /// stratum of less than 1/p rays per piece is still sampled (a fixed start of the systematic
    /// sample would keep none of it).
    #[test]
    fn pieces_sampled_apart_keep_their_share_of_every_stratum() {
        let dir = tempfile::tempdir().unwrap();
        let ds = dataset(&dir.path().join("ds"));
        let sel = RaySelection::all();
        let frame = Frame { anchor: [0.0; 3], radius: 10.0 };
        let p = 0.02;
        let sampler = |piece: usize| RowSampler::new(&sel, None, p, SegmentBuilder::new(None, frame), piece as u64);
        let ps = pieces(&ds, &ds.plan(&sel).unwrap()).unwrap();
        let n_pieces = ps.len();
        let mut kept: BTreeMap<(String, u32), u64> = BTreeMap::new();
        let mut matched = 0;
        read_pieces(&ds, &load_columns(), ps, &sampler, &mut |k| {
            matched += k.matched;
            for (i, &(_, ray)) in k.picks.iter().enumerate() {
                // In this trace a ray's depth is its index.
                *kept.entry((k.kind_names[usize::from(k.kind_of[i])].clone(), ray)).or_default() += 1;
            }
            Ok(true)
        })
        .unwrap();
        assert_eq!(matched, ds.ray_count());
        // Rays per stratum: trees 0..4500 of id % 5 + 1 rays; ray r at depth r (camera at 0).
        for depth in 0..5u32 {
            let n = (0..4500u64).filter(|id| id % 5 + 1 > u64::from(depth)).count() as f64;
            let kind = if depth == 0 { "camera" } else { "diffuse" };
            let got = kept.get(&(kind.to_string(), depth)).copied().unwrap_or(0) as f64;
            assert!(n * p / n_pieces as f64 <= 0.5, "a stratum rarer than 1/p per piece");
            // Within four standard deviations of a sum of one Bernoulli draw per piece.
            let tolerance = 4.0 * (n * p).sqrt() + 1.0;
            assert!(
                got >= 1.0 && (got - n * p).abs() <= tolerance,
                "{kind} depth {depth}: kept {got} of {n}, expected {}",
                n * p
            );
        }
    }
}
