#![doc = include_str!("../README.md")]
//!
//! rtvtk's whole-system benchmarks, each beside a baseline in the same run and reported as
//! ratios; `rtvtk bench ...` (the CLI's thin `src/bench.rs`) parses the arguments and calls
//! them. A tool crate, like the binary: its errors are `anyhow`'s.
//!
//! - [`store_bench`], [`fetch_bench`]: recording throughput, bytes per ray and one-tree fetches
//!   beside Parquet and DuckDB (`bench store`, `bench fetch`)
//! - [`record`]: `rtvtk record` against `record --no-record`, end to end (`bench record`)
//! - [`scale`]: time and memory of every whole-trace command as the trace grows (`bench scale`)
//! - [`query`]: the SQL suite beside DuckDB and on Ballista clusters (`bench query`)
//! - [`serve`]: many Flight SQL clients against one service (`bench serve`)
//! - [`trace`]: BVH traversal beside obvhs (and Embree) (`bench trace`)
//! - [`gpu`]: the GPU tracer beside the CPU's (`bench gpu`)
//! - [`viz`]: the visualizer's frames, on the GPU and read back (`bench viz`)

#[cfg(feature = "embree")]
mod embree;
pub mod gpu;
pub mod payload;
pub mod query;
pub mod record;
pub mod scale;
pub mod serve;
pub mod trace;
pub mod viz;

use std::fs::File;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use arrow::array::RecordBatch;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;
use rl::demo::{RayList, pixel_rays};
use rl::{Dataset, Payload, RayId, Recorder, RecorderOptions, TreeId};
use store::{Encoding, KindTable, PayloadSchema, RayColumns, TreeRow};

/// Traced trees: (pixel x, pixel y, sample, rays).
struct Trace {
    trees: Vec<(u32, u32, u32, RayList)>,
    rays: u64,
}

/// Ray trees of the path tracer on `scene` (core fields only), traced up front.
fn path_traced(scene_name: &str, min_rays: u64) -> Result<Trace> {
    use renderers::tracer::{SampleRecord, TraceCtx, path_sample};
    let scene = renderers::load_scene(scene_name, None, 1)?;
    let bvh = renderers::Bvh::build(&scene.tris);
    let ctx = TraceCtx::new(&scene, &bvh, 8, None, false);
    let (w, h) = (1024u32, 768u32);
    let mut trees = Vec::new();
    let mut rays = 0u64;
    let mut rec = SampleRecord::new(true);
    'outer: for sample in 0.. {
        for y in 0..h {
            for x in 0..w {
                let mut rng = renderers::sampling::Rng::for_sample(0, x, y, sample);
                rec.clear();
                path_sample(&ctx, x as f32 + rng.next_f32(), y as f32 + rng.next_f32(), w, h, &mut rng, Some(&mut rec));
                let mut list = RayList::default();
                for r in &rec.rays {
                    let f = rl::RayFields {
                        origin: r.origin.to_array(),
                        direction: r.dir.to_array(),
                        t: r.t,
                        kind: r.kind,
                        prim: r.prim,
                    };
                    list.rays.push((r.parent, f));
                }
                rays += list.rays.len() as u64;
                trees.push((x, y, sample, list));
                if rays >= min_rays {
                    break 'outer;
                }
            }
        }
    }
    Ok(Trace { trees, rays })
}

/// Ray trees of the demo scene, traced up front so that only recording is timed.
fn make_trace(min_rays: u64) -> Trace {
    let (w, h) = (1024u32, 768u32);
    let per_thread = std::thread::available_parallelism().map_or(2, |n| n.get()) as u32;
    // Trace rows in parallel until enough rays exist.
    let mut trees = Vec::new();
    let mut rays = 0u64;
    let mut sample = 0;
    'outer: loop {
        for y0 in (0..h).step_by(per_thread as usize * 8) {
            let parts: Vec<Vec<(u32, u32, u32, RayList)>> = std::thread::scope(|s| {
                let handles: Vec<_> = (0..per_thread)
                    .map(|t| {
                        s.spawn(move || {
                            let mut out = Vec::new();
                            for y in (y0 + t * 8)..(y0 + t * 8 + 8).min(h) {
                                for x in 0..w {
                                    out.push((x, y, sample, pixel_rays(x, y, sample, w, h)));
                                }
                            }
                            out
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().unwrap_or_default()).collect()
            });
            for p in parts {
                for t in p {
                    rays += t.3.rays.len() as u64;
                    trees.push(t);
                }
            }
            if rays >= min_rays {
                break 'outer;
            }
        }
        sample += 1;
    }
    Trace { trees, rays }
}

/// CPU seconds (user + system) this process has used so far, all threads.
fn cpu_seconds() -> f64 {
    // SAFETY: getrusage only writes the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } != 0 {
        return f64::NAN;
    }
    let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    tv(u.ru_utime) + tv(u.ru_stime)
}

/// Bytes of the files under `dir`.
pub(crate) fn dir_bytes(dir: &std::path::Path) -> u64 {
    dir_bytes_where(dir, &|_| true)
}

/// Bytes of the files under `dir` (recursively) whose name `keep` accepts; unreadable entries
/// count 0.
pub(crate) fn dir_bytes_where(dir: &std::path::Path, keep: &dyn Fn(&str) -> bool) -> u64 {
    std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| {
                    let m = e.metadata().ok();
                    if m.as_ref().is_some_and(|m| m.is_dir()) {
                        dir_bytes_where(&e.path(), keep)
                    } else if keep(&e.file_name().to_string_lossy()) {
                        m.map_or(0, |m| m.len())
                    } else {
                        0
                    }
                })
                .sum()
        })
        .unwrap_or(0)
}

pub struct StoreArgs {
    /// fsync at seal (what a crash-safe recording pays).
    pub sync: bool,
    pub rounds: u32,
    pub threads: usize,
    pub workers: usize,
    pub chunk_rays: usize,
    pub page_rows: usize,
    pub fetches: usize,
    /// DuckDB's fetch beside ours.
    pub duckdb: bool,
}

/// Records `trace` through the `rl` API in write mode; returns seconds, the summary and the tree
/// id each trace entry got.
fn record_trace(
    trace: &Trace,
    path: &std::path::Path,
    args: &StoreArgs,
    encoding: Encoding,
) -> Result<(f64, rl::Summary, Vec<TreeId>)> {
    let mut options = RecorderOptions { workers: args.workers, chunk_rays: args.chunk_rays, ..Default::default() };
    options.write.encoding = encoding;
    options.write.sync = args.sync;
    options.write.page_rows = args.page_rows;
    let threads = args.threads.max(1);
    // The id each tree gets, written into memory faulted in before the clock starts (a vector
    // grown while timed cost the replay thread ~20K fresh pages per 10M rays, which is the
    // benchmark's bookkeeping, not recording).
    let mut by_entry = vec![TreeId(u64::MAX); trace.trees.len()];
    let per_thread = trace.trees.len().div_ceil(threads).max(1);
    let t = Instant::now();
    let rec = Recorder::create(path, options)?;
    std::thread::scope(|s| {
        for (trees, ids) in trace.trees.chunks(per_thread).zip(by_entry.chunks_mut(per_thread)) {
            let rec = rec.clone();
            s.spawn(move || {
                for ((x, y, sample, list), id) in trees.iter().zip(ids.iter_mut()) {
                    let mut tree = rec.begin_tree(*x, *y, *sample);
                    *id = tree.id();
                    for (parent, f) in &list.rays {
                        match parent {
                            Some(p) => tree.add_ray_under(RayId(*p), f, Payload::NONE),
                            None => tree.add_ray(f, Payload::NONE),
                        };
                    }
                    tree.end();
                }
            });
        }
    });
    let summary = rec.finish()?;
    let secs = t.elapsed().as_secs_f64();
    Ok((secs, summary, by_entry))
}

/// Error of a (lossy) dataset against the traced rays: max and mean angle between directions,
/// max origin and hit-point distance.
#[derive(Default)]
struct Errors {
    max_angle: f64,
    sum_angle: f64,
    n_angle: u64,
    max_origin: f64,
    max_hit: f64,
    mismatched_rays: u64,
}

fn measure_errors(ds: &Dataset, trace: &Trace, ids: &[TreeId]) -> Result<Errors> {
    let mut entry_of = std::collections::HashMap::with_capacity(ids.len());
    for (k, id) in ids.iter().enumerate() {
        entry_of.insert(*id, k);
    }
    let dist = |a: [f32; 3], b: [f32; 3]| -> f64 {
        let d = [0, 1, 2].map(|i| f64::from(a[i]) - f64::from(b[i]));
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
    };
    let mut e = Errors::default();
    for tree in ds.trees() {
        let tree = tree?;
        let Some(&k) = entry_of.get(&tree.info.id) else {
            e.mismatched_rays += tree.rays.len() as u64;
            continue;
        };
        let list = &trace.trees[k].3;
        for (r, (_, f)) in tree.rays.iter().zip(&list.rays) {
            let ok = |v: [f32; 3]| v.iter().all(|c| c.is_finite());
            if !(ok(f.origin) && ok(f.direction)) {
                continue;
            }
            let a = store::geom::angle_between_f32(f.direction, r.direction);
            if a.is_finite() {
                e.max_angle = e.max_angle.max(a);
                e.sum_angle += a;
                e.n_angle += 1;
            }
            e.max_origin = e.max_origin.max(dist(f.origin, r.origin));
            if let (Some(t0), Some(t1)) = (f.t, r.t) {
                let h0 = [0, 1, 2].map(|i| f.origin[i] + f.direction[i] * t0);
                let h1 = [0, 1, 2].map(|i| r.origin[i] + r.direction[i] * t1);
                if ok(h0) && ok(h1) {
                    e.max_hit = e.max_hit.max(dist(h0, h1));
                }
            }
        }
    }
    Ok(e)
}

/// p50 and p99 in milliseconds.
fn percentiles(v: &mut [f64]) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v.get(((v.len().max(1) - 1) as f64 * q) as usize).copied().unwrap_or(f64::NAN) * 1e3;
    (at(0.5), at(0.99))
}

/// DuckDB's `SELECT * ... WHERE tree_id = k` over `files` for each id (warm: each query once
/// before timing); p50 and p99 in milliseconds, or why it could not run.
fn duckdb_fetch(files: &[PathBuf], ids: &[u64]) -> std::result::Result<(f64, f64), String> {
    let script = r#"
import sys, time, json
import duckdb
files = json.loads(sys.argv[1]); ids = json.loads(sys.argv[2])
con = duckdb.connect()
con.execute("CREATE VIEW rays AS SELECT * FROM read_parquet([" + ",".join("'" + f.replace("'", "''") + "'" for f in files) + "])")
q = "SELECT * FROM rays WHERE tree_id = ?"
for k in ids[:5]:
    con.execute(q, [k]).fetchall()
times = []
for k in ids:
    t = time.perf_counter(); rows = con.execute(q, [k]).fetchall(); times.append(time.perf_counter() - t)
    assert len(rows) > 0, k
times.sort()
print(times[len(times)//2] * 1e3, times[int((len(times)-1)*0.99)] * 1e3)
"#;
    let files: Vec<String> = files.iter().map(|p| p.display().to_string()).collect();
    let out = std::process::Command::new("python3")
        .arg("-c")
        .arg(script)
        .arg(serde_json::to_string(&files).map_err(|e| e.to_string())?)
        .arg(serde_json::to_string(ids).map_err(|e| e.to_string())?)
        .output()
        .map_err(|e| format!("cannot run python3: {e}"))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        return Err(format!("python3/duckdb failed: {}", err.lines().last().unwrap_or("")));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let v: Vec<f64> = text.split_whitespace().filter_map(|x| x.parse().ok()).collect();
    match v[..] {
        [p50, p99] => Ok((p50, p99)),
        _ => Err(format!("unexpected output from the DuckDB script: {text}")),
    }
}

pub fn store_bench(
    min_rays: u64,
    args: &StoreArgs,
    dir: Option<PathBuf>,
    scene: Option<&str>,
    encodings: &[Encoding],
) -> Result<()> {
    let tmp = match &dir {
        Some(_) => None,
        None => Some(tempfile::tempdir().context("creating a temporary directory")?),
    };
    let root = dir.unwrap_or_else(|| tmp.as_ref().map(|t| t.path().to_path_buf()).unwrap_or_default());
    std::fs::create_dir_all(&root)?;
    let source = scene.map_or_else(|| "the demo scene".to_string(), |s| format!("the path tracer on {s}"));
    eprintln!("tracing {source} for at least {min_rays} rays ...");
    let t0 = Instant::now();
    let trace = match scene {
        Some(s) => path_traced(s, min_rays)?,
        None => make_trace(min_rays),
    };
    eprintln!(
        "  {} rays in {} trees ({:.1} s, not timed below)",
        trace.rays,
        trace.trees.len(),
        t0.elapsed().as_secs_f64()
    );

    // Baseline input: the same rays as record batches of the plain ray table schema (built untimed).
    let payload = PayloadSchema::default();
    let kinds = KindTable::default();
    let mut batches = Vec::new();
    let mut cols = RayColumns::new(&payload);
    for (i, (x, y, sample, list)) in trace.trees.iter().enumerate() {
        let first = cols.len() as u64;
        let mut depth = Vec::with_capacity(list.rays.len());
        for (k, (parent, f)) in list.rays.iter().enumerate() {
            let d = parent.map_or(0, |p| depth[p as usize] + 1);
            depth.push(d);
            cols.push_core(i as u64, k as u32, parent.unwrap_or(store::NONE_U32), d, f);
        }
        cols.trees.push(TreeRow {
            tree_id: i as u64,
            pixel_x: *x,
            pixel_y: *y,
            sample: *sample,
            ray_count: list.rays.len() as u32,
            max_depth: depth.iter().copied().max().unwrap_or(0),
            first_row: first,
        });
        if cols.len() >= 64 * 1024 {
            batches.push(std::mem::replace(&mut cols, RayColumns::new(&payload)).into_ray_batch(&payload, &kinds)?);
        }
    }
    if !cols.is_empty() {
        batches.push(cols.into_ray_batch(&payload, &kinds)?);
    }

    // Baseline: arrow-rs ArrowWriter, default properties with zstd(1), one file.
    let base_path = root.join("baseline.parquet");
    let write_baseline = |batches: &[RecordBatch]| -> Result<(f64, f64)> {
        let cpu0 = cpu_seconds();
        let t = Instant::now();
        let props = WriterProperties::builder().set_compression(Compression::ZSTD(ZstdLevel::try_new(1)?)).build();
        let file = File::create(&base_path)?;
        let mut w = ArrowWriter::try_new(file, batches[0].schema(), Some(props))?;
        for b in batches {
            w.write(b)?;
        }
        w.close()?;
        Ok((t.elapsed().as_secs_f64(), cpu_seconds() - cpu0))
    };
    // Rounds: the baseline, then every encoding; (seconds, CPU seconds) per round.
    let mut base_runs: Vec<(f64, f64)> = Vec::new();
    let mut runs: Vec<Vec<(f64, f64)>> = vec![Vec::new(); encodings.len()];
    let mut last: Vec<Option<(rl::Summary, Vec<TreeId>)>> = vec![None; encodings.len()];
    for round in 0..args.rounds {
        eprintln!("round {}/{}: writing the baseline ...", round + 1, args.rounds);
        base_runs.push(write_baseline(&batches)?);
        if round + 1 == args.rounds {
            batches.clear();
            batches.shrink_to_fit();
        }
        for (k, &encoding) in encodings.iter().enumerate() {
            let ds_path = root.join(format!("trace-{}", encoding.name()));
            if ds_path.exists() {
                std::fs::remove_dir_all(&ds_path).with_context(|| format!("removing {}", ds_path.display()))?;
            }
            eprintln!("round {}/{}: recording {} ...", round + 1, args.rounds, encoding.name());
            let cpu0 = cpu_seconds();
            let (secs, summary, ids) = record_trace(&trace, &ds_path, args, encoding)?;
            runs[k].push((secs, cpu_seconds() - cpu0));
            last[k] = Some((summary, ids));
        }
    }
    let base_bytes = std::fs::metadata(&base_path)?.len();
    let n = trace.rays as f64;
    // Smallest seconds (`.0`) or CPU seconds (`.1`) over the rounds.
    let best = |v: &[(f64, f64)], pick: fn(&(f64, f64)) -> f64| v.iter().map(pick).fold(f64::INFINITY, f64::min);
    let best_secs = |v: &[(f64, f64)]| best(v, |r| r.0);
    // Median over rounds of f(baseline round, our round), and the sorted per-round values.
    let median_ratio = |ours: &[(f64, f64)], f: &dyn Fn((f64, f64), (f64, f64)) -> f64| {
        let mut r: Vec<f64> = base_runs.iter().zip(ours).map(|(&b, &o)| f(b, o)).collect();
        r.sort_by(f64::total_cmp);
        (crate::query::median(&r), r)
    };

    println!("## rtvtk bench store ({} rays, {} trees of {source})", trace.rays, trace.trees.len());
    println!();
    println!(
        "rtvtk: the rl recording API from {} tracing thread(s), encoding and writing on {} worker thread(s), \
         segments {}; core ray columns only (no payload). {} round(s), each writing the baseline and then every \
         encoding: Mrays/s, time and CPU from the best round, ratios are medians of per-round ratios.",
        args.threads,
        args.workers,
        if args.sync { "fsynced when sealed" } else { "not fsynced" },
        args.rounds
    );
    println!();
    println!(
        "| writer | Mrays/s | B/ray | time s | CPU s | write speed vs baseline | CPU vs baseline | bytes vs baseline | max angle error (rad) | mean angle error (rad) | max origin error / scene | max hit-point error / scene |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    println!(
        "| arrow-rs ArrowWriter, default properties, zstd-1 (baseline) | {:.2} | {:.2} | {:.2} | {:.2} | 1.00x | 1.00x | 1.00x | 0 | 0 | 0 | 0 |",
        n / best_secs(&base_runs) / 1e6,
        base_bytes as f64 / n,
        best_secs(&base_runs),
        best(&base_runs, |r| r.1)
    );
    let mut fetch_ds: Option<PathBuf> = None;
    let mut peak = 0u64;
    let mut per_round = Vec::new();
    for ((&encoding, runs), last) in encodings.iter().zip(&runs).zip(last) {
        let Some((summary, ids)) = last else { continue };
        let ds_path = root.join(format!("trace-{}", encoding.name()));
        peak = peak.max(summary.peak_buffered_bytes);
        let bytes = dir_bytes(&ds_path);
        let (mut errs, mut scene_size) = (Errors::default(), f64::NAN);
        let ds = Dataset::open(&ds_path)?;
        if encoding.is_lossy() {
            errs = measure_errors(&ds, &trace, &ids)?;
            let st = ds.stats();
            let (o, h) = (&st.origin_bounds, &st.hit_bounds);
            let d = [0, 1, 2].map(|i| f64::from(o.max[i].max(h.max[i])) - f64::from(o.min[i].min(h.min[i])));
            scene_size = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if errs.mismatched_rays > 0 {
                anyhow::bail!("{} rays of {} could not be matched to the trace", errs.mismatched_rays, encoding.name());
            }
        }
        let err_cols = if encoding.is_lossy() {
            format!(
                "{:.2e} | {:.2e} | {:.2e} | {:.2e}",
                errs.max_angle,
                errs.sum_angle / errs.n_angle.max(1) as f64,
                errs.max_origin / scene_size,
                errs.max_hit / scene_size
            )
        } else {
            "0 (bit-exact) | 0 | 0 | 0".to_string()
        };
        let (speed, speeds) = median_ratio(runs, &|b, o| b.0 / o.0);
        let (cpu_ratio, _) = median_ratio(runs, &|b, o| o.1 / b.1);
        println!(
            "| rtvtk {} ({} segments) | {:.2} | {:.2} | {:.2} | {:.2} | {speed:.2}x | {cpu_ratio:.2}x | {:.2}x | {err_cols} |",
            encoding.name(),
            summary.segments,
            n / best_secs(runs) / 1e6,
            bytes as f64 / n,
            best_secs(runs),
            best(runs, |r| r.1),
            bytes as f64 / base_bytes as f64,
        );
        per_round.push(format!(
            "{}: {}",
            encoding.name(),
            speeds.iter().map(|r| format!("{r:.2}x")).collect::<Vec<_>>().join(" ")
        ));
        if fetch_ds.is_none() {
            fetch_ds = Some(ds_path);
        }
    }
    println!();
    println!(
        "write speed vs baseline per round (sorted); baseline Mrays/s per round: {}",
        base_runs.iter().map(|r| format!("{:.2}", n / r.0 / 1e6)).collect::<Vec<_>>().join(" ")
    );
    for line in per_round {
        println!("  {line}");
    }
    println!();
    println!(
        "peak rays buffered for the writers: {:.1} MiB (budget {:.0} MiB)",
        peak as f64 / (1 << 20) as f64,
        RecorderOptions::default().memory_budget as f64 / (1 << 20) as f64
    );
    let Some(fetch_path) = fetch_ds else { return Ok(()) };
    fetch_bench(&fetch_path, args.fetches, args.duckdb)
}

/// One-tree fetch latency on an existing dataset: by id, first touch (the tree's tree-table page
/// and ray pages read for the first time in this process: from the page cache or the disk) and
/// again (warm), and by (pixel, sample), warm; beside DuckDB's `WHERE tree_id = k` on the same
/// files. Nothing is loaded whole (no tree index, no page-cache warming), so memory stays that
/// of a few pages whatever the trace's length.
pub fn fetch_bench(fetch_path: &std::path::Path, fetches: usize, duckdb: bool) -> Result<()> {
    let ds = Dataset::open(fetch_path)?;
    let segments = &ds.manifest().segments;
    let n_trees = ds.tree_count().max(1);
    let mut rng = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        rng
    };
    // A random tree: a segment chosen in proportion to its trees, an id in its range (ids a
    // segment's range skips are drawn again, untimed).
    let mut pick = |ds: &Dataset| -> Result<(TreeId, store::Tree, f64)> {
        for _ in 0..10_000 {
            let mut k = next() % n_trees;
            let Some(seg) = segments.iter().find(|s| {
                let hit = k < s.trees.rows;
                k = k.saturating_sub(s.trees.rows);
                hit
            }) else {
                continue;
            };
            let span = seg.tree_id_max.saturating_sub(seg.tree_id_min).saturating_add(1);
            let id = TreeId(seg.tree_id_min.saturating_add(next() % span));
            let t = Instant::now();
            match ds.tree(id) {
                Ok(tree) => return Ok((id, tree, t.elapsed().as_secs_f64())),
                Err(store::Error::NoSuchTree(_)) => continue,
                Err(e) => return Err(e.into()),
            }
        }
        anyhow::bail!("no tree found by 10,000 random ids in the manifest's segment ranges")
    };
    // The first fetches also read each segment's tree-file footer (kept afterwards).
    let t = Instant::now();
    for _ in 0..200.min(fetches) {
        pick(&ds)?;
    }
    eprintln!("  {} warm-up fetches in {:.2} s", 200.min(fetches), t.elapsed().as_secs_f64());
    let mut first = Vec::with_capacity(fetches);
    let mut picked = Vec::with_capacity(fetches);
    let mut pixels = Vec::with_capacity(fetches);
    while first.len() < fetches {
        let (id, tree, secs) = pick(&ds)?;
        first.push(secs);
        picked.push(id.0);
        pixels.push((tree.info.pixel, tree.info.sample));
    }
    let mut by_id = Vec::with_capacity(fetches);
    for &id in &picked {
        let t = Instant::now();
        let tree = ds.tree(TreeId(id))?;
        by_id.push(t.elapsed().as_secs_f64());
        std::hint::black_box(tree);
    }
    let mut by_pixel = Vec::with_capacity(fetches);
    for &([x, y], sample) in &pixels {
        let t = Instant::now();
        let trees = ds.trees_at_pixel(x, y, Some(sample))?;
        by_pixel.push(t.elapsed().as_secs_f64());
        std::hint::black_box(trees);
    }
    let (first50, first99) = percentiles(&mut first);
    let (id50, id99) = percentiles(&mut by_id);
    let (px50, px99) = percentiles(&mut by_pixel);
    println!();
    println!(
        "one-tree fetch ({}, {} rays, {} fetches): by id p50 {id50:.3} ms, p99 {id99:.3} ms (warm); \
         first touch p50 {first50:.3} ms, p99 {first99:.3} ms (a random tree of the trace); \
         by pixel and sample p50 {px50:.3} ms, p99 {px99:.3} ms (warm)",
        ds.encoding().name(),
        ds.ray_count(),
        fetches,
    );
    if duckdb {
        let ids: Vec<u64> = picked.iter().copied().take(60).collect();
        match duckdb_fetch(&ds.ray_files(), &ids) {
            Ok((d50, d99)) => println!(
                "DuckDB `SELECT * FROM rays WHERE tree_id = k` on the same files ({} queries, warm): p50 {d50:.2} ms, p99 {d99:.2} ms; \
                 rtvtk by id is {:.0}x faster at p50",
                ids.len(),
                d50 / id50
            ),
            Err(e) => println!("DuckDB comparison skipped: {e}"),
        }
    }
    Ok(())
}
