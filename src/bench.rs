//! `rtvtk bench`: whole-system benchmarks, each beside a baseline in the same run.

use std::fs::File;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Subcommand;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;
use rl::demo::{RayList, pixel_rays};
use rl::{Dataset, Payload, RayId, Recorder, RecorderOptions, TreeId};
use store::{KindTable, PayloadSchema, RayColumns, TreeRow};

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Single-core traversal speed per ray kind: our BVH traversal beside obvhs's stock BVH2 and
    /// CWBVH traversals on the same rays (and Embree when built with `--features embree`).
    Trace {
        /// Split every quad of the Cornell box n × n (31 gives ~30K triangles, 130 ~0.5M).
        #[arg(long, default_value_t = 31)]
        subdivide: u32,
        /// Rotate the scene off the axes (the stock CWBVH is slow on axis-aligned walls).
        #[arg(long)]
        rotate: bool,
        /// Image width (and height) of the path-traced frame the rays come from.
        #[arg(long, default_value_t = 256)]
        width: u32,
        #[arg(long, default_value_t = 4)]
        spp: u32,
    },
    /// Write throughput and bytes per ray against plain arrow-rs Parquet, and one-tree fetch latency.
    Store {
        /// Rays to record (at least).
        #[arg(long, default_value_t = 2_000_000)]
        rays: u64,
        /// Tracing threads replaying the trees into the recorder.
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Recorder background writer threads.
        #[arg(long, default_value_t = 1)]
        workers: usize,
        /// Random trees fetched for the latency figures.
        #[arg(long, default_value_t = 2000)]
        fetches: usize,
        /// Where to write (default: a temporary directory, removed afterwards).
        #[arg(long)]
        dir: Option<PathBuf>,
        /// Take the rays from the path tracer on this scene (cornell, cornell-glass, glossy, FILE.obj)
        /// instead of the small demo tracer.
        #[arg(long)]
        scene: Option<String>,
    },
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Trace { subdivide, rotate, width, spp } => crate::bench_trace::run(subdivide, rotate, width, spp),
        BenchCommand::Store { rays, threads, workers, fetches, dir, scene } => {
            store_bench(rays, threads.max(1), workers.max(1), fetches, dir, scene.as_deref())
        }
    }
}

struct Trace {
    trees: Vec<(u32, u32, RayList)>,
    rays: u64,
}

/// Ray trees of the path tracer on `scene` (core fields only), traced up front.
fn path_traced(scene_name: &str, min_rays: u64) -> Result<Trace> {
    use renderers::tracer::{SampleRecord, TraceCtx, path_sample};
    let scene = crate::record::load_scene(scene_name, None)?;
    let bvh = renderers::Bvh::build(&scene.tris);
    let ctx = TraceCtx { scene: &scene, bvh: &bvh, max_depth: 8, bug: None, record_visits: false };
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
                trees.push((x, y, list));
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
            let parts: Vec<Vec<(u32, u32, RayList)>> = std::thread::scope(|s| {
                let handles: Vec<_> = (0..per_thread)
                    .map(|t| {
                        s.spawn(move || {
                            let mut out = Vec::new();
                            for y in (y0 + t * 8)..(y0 + t * 8 + 8).min(h) {
                                for x in 0..w {
                                    out.push((x, y, pixel_rays(x, y, sample, w, h)));
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
                    rays += t.2.rays.len() as u64;
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

fn dir_bytes(dir: &std::path::Path) -> u64 {
    fn walk(p: &std::path::Path) -> u64 {
        std::fs::read_dir(p)
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .map(|e| {
                        let m = e.metadata().ok();
                        if m.as_ref().is_some_and(|m| m.is_dir()) { walk(&e.path()) } else { m.map_or(0, |m| m.len()) }
                    })
                    .sum()
            })
            .unwrap_or(0)
    }
    walk(dir)
}

fn store_bench(
    min_rays: u64,
    threads: usize,
    workers: usize,
    fetches: usize,
    dir: Option<PathBuf>,
    scene: Option<&str>,
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

    // Baseline input: the same rays as record batches of the same schema (built untimed).
    let payload = PayloadSchema::default();
    let kinds = KindTable::default();
    let mut batches = Vec::new();
    let mut cols = RayColumns::new(&payload);
    for (i, (x, y, list)) in trace.trees.iter().enumerate() {
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
            sample: 0,
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
    let t = Instant::now();
    {
        let props = WriterProperties::builder().set_compression(Compression::ZSTD(ZstdLevel::try_new(1)?)).build();
        let file = File::create(&base_path)?;
        let mut w = ArrowWriter::try_new(file, batches[0].schema(), Some(props))?;
        for b in &batches {
            w.write(b)?;
        }
        w.close()?;
    }
    let base_secs = t.elapsed().as_secs_f64();
    let base_bytes = std::fs::metadata(&base_path)?.len();
    drop(batches);

    // rtvtk: the recording API from `threads` threads, encoding on `workers` background threads.
    let ds_path = root.join("trace");
    let options = RecorderOptions { workers, ..Default::default() };
    let t = Instant::now();
    let rec = Recorder::create(&ds_path, options)?;
    let trees = Arc::new(trace.trees);
    std::thread::scope(|s| {
        for th in 0..threads {
            let rec = rec.clone();
            let trees = trees.clone();
            s.spawn(move || {
                for (x, y, list) in trees.iter().skip(th).step_by(threads) {
                    let mut tree = rec.begin_tree(*x, *y, 0);
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
    let ours_secs = t.elapsed().as_secs_f64();
    let ours_bytes = dir_bytes(&ds_path);
    let n = trace.rays as f64;

    println!("## rtvtk bench store ({} rays, {} trees of {source})", trace.rays, summary.trees);
    println!();
    println!("| writer | Mrays/s | B/ray | time s |");
    println!("|---|---|---|---|");
    println!(
        "| arrow-rs ArrowWriter, default properties, zstd-1 (baseline) | {:.2} | {:.2} | {:.2} |",
        n / base_secs / 1e6,
        base_bytes as f64 / n,
        base_secs
    );
    println!(
        "| rtvtk rl write mode ({threads} tracing thread(s), {workers} worker(s), {} segments) | {:.2} | {:.2} | {:.2} |",
        summary.segments,
        n / ours_secs / 1e6,
        ours_bytes as f64 / n,
        ours_secs
    );
    println!();
    println!(
        "ratios vs baseline: write throughput {:.2}x, bytes {:.2}x; peak buffered {:.1} MiB",
        base_secs / ours_secs,
        ours_bytes as f64 / base_bytes as f64,
        summary.peak_buffered_bytes as f64 / (1 << 20) as f64
    );

    // Fetch latency: random trees by id and by pixel, warm (metadata cached, page cache warm).
    let ds = Dataset::open(&ds_path)?;
    let t = Instant::now();
    let entries = ds.tree_entries()?;
    let index_secs = t.elapsed().as_secs_f64();
    let mut rng = 0x2545_F491_4F6C_DD1Du64;
    let mut pick = || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        entries[(rng % entries.len() as u64) as usize]
    };
    for _ in 0..200.min(fetches) {
        ds.tree(pick().info.id)?;
    }
    let mut by_id = Vec::with_capacity(fetches);
    for _ in 0..fetches {
        let id: TreeId = pick().info.id;
        let t = Instant::now();
        let tree = ds.tree(id)?;
        by_id.push(t.elapsed().as_secs_f64());
        std::hint::black_box(tree);
    }
    let mut by_pixel = Vec::with_capacity(fetches);
    for _ in 0..fetches {
        let p = pick().info.pixel;
        let t = Instant::now();
        let trees = ds.trees_at_pixel(p[0], p[1], None)?;
        by_pixel.push(t.elapsed().as_secs_f64());
        std::hint::black_box(trees);
    }
    let pct = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * q) as usize] * 1e3
    };
    println!();
    println!(
        "one-tree fetch over {} rays ({} fetches, warm): by id p50 {:.3} ms, p99 {:.3} ms; by pixel (all samples) p50 {:.3} ms, p99 {:.3} ms; tree index load {:.3} s",
        ds.ray_count(),
        fetches,
        pct(&mut by_id, 0.5),
        pct(&mut by_id, 0.99),
        pct(&mut by_pixel, 0.5),
        pct(&mut by_pixel, 0.99),
        index_secs
    );
    Ok(())
}
