//! `rtvtk bench`: the arguments of each benchmark; the benchmarks are the `rtvtk-bench` crate
//! (`benches/`).

use std::path::PathBuf;

use anyhow::Result;
use clap::Subcommand;
use rl::RecorderOptions;
use store::Encoding;

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
        /// Timing rounds; each round runs every traversal once, in turn, so slow phases of a
        /// shared machine hit all of them (best time and median per-round ratio are reported).
        #[arg(long, default_value_t = 5)]
        rounds: u32,
    },
    /// Bytes of path-tracer traces with their payload against pyarrow's default zstd Parquet of
    /// the same ray table: lossless, with the lossy payload option, and with lossy payload and
    /// oct16 directions (needs `python3` with `pyarrow`).
    Payload {
        /// Scenes, each `cornell`, `cornell-glass`, `glossy` or an OBJ file (camera framed
        /// automatically).
        #[arg(long, value_delimiter = ',', default_value = "cornell,cornell-glass")]
        scenes: Vec<String>,
        #[arg(long, default_value = "256x256")]
        size: String,
        #[arg(long, default_value_t = 16)]
        spp: u32,
        /// Mantissa bits of each lossy payload variant (1 to 22).
        #[arg(long, value_delimiter = ',', default_value = "10,7")]
        bits: Vec<u8>,
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
        /// Rays per chunk handed from the tracing threads to the writers.
        #[arg(long, default_value_t = RecorderOptions::default().chunk_rays)]
        chunk_rays: usize,
        /// Rows per Parquet data page of the ray files (the unit a one-tree fetch decompresses).
        #[arg(long, default_value_t = store::WriteOptions::default().page_rows)]
        page_rows: usize,
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
        /// Encodings to record the trace in, each timed and sized against the baseline; the first
        /// one is used for the fetch figures.
        #[arg(long, value_delimiter = ',', default_value = "lossless,plain,oct16,oct12")]
        encodings: Vec<String>,
        /// Skip the DuckDB comparison (needs `python3` with the `duckdb` module).
        #[arg(long)]
        no_duckdb: bool,
        /// Do not fsync sealed segments (the baseline does not either; crash safety against
        /// power loss needs it, a killed process does not).
        #[arg(long)]
        no_sync: bool,
        /// Write rounds; each writes the baseline and then every encoding, so slow phases of a
        /// shared machine hit both (best speed and median per-round ratios are reported).
        #[arg(long, default_value_t = 3)]
        rounds: u32,
    },
    /// A fixed query suite (anchors' six queries, coherence, BVH cost) on a dataset, beside
    /// DuckDB on the same Parquet files: time and peak-memory ratios.
    Query {
        dataset: PathBuf,
        /// A plain export of the dataset for DuckDB (made in a temporary directory when absent and
        /// the dataset is encoded).
        #[arg(long)]
        plain: Option<PathBuf>,
        /// Timed runs per query (after one untimed).
        #[arg(long, default_value_t = 3)]
        runs: usize,
        /// rtvtk's memory limit, e.g. 2GiB.
        #[arg(long)]
        memory_limit: Option<String>,
        #[arg(long)]
        no_duckdb: bool,
        /// Instead of DuckDB: the suite on Ballista clusters of this many executors (comma
        /// separated, e.g. 1,2,4) started on this machine, beside the in-process session.
        #[arg(long, value_delimiter = ',')]
        cluster: Vec<usize>,
        /// Task slots per executor with --cluster.
        #[arg(long, default_value_t = 1)]
        executor_cores: usize,
    },
    /// Recording overhead: wall time of `rtvtk record ARGS` with write-mode recording over the
    /// same command with `--no-record` (same scene, seed and threads), alternating pairs of runs.
    Record {
        /// Pairs of runs.
        #[arg(long, default_value_t = 5)]
        runs: usize,
        /// Arguments of `rtvtk record` without `--out`, e.g. `--scene cornell --subdivide 118
        /// --size 256x256 --spp 8 --threads 1`. Without them, the standard suite: the Cornell box
        /// (384²×32) and the 1M-triangle box (`--subdivide 128`, 384²×16) at 1, 2 and all tracing
        /// threads.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// How time and memory grow with the trace: record a Cornell-box trace of about N rays per
    /// step, then time `record`, `info`, `check`, one pixel's tree, one tree by id, 2000 random
    /// tree fetches, SQL at one pixel, a per-pixel group-by and the first ray picture, each in a
    /// fresh process with its peak memory.
    Scale {
        /// Ray counts, one trace each (e.g. 10M,100M; K, M and B suffixes).
        #[arg(long, value_delimiter = ',', default_value = "10M,100M", value_parser = bench::scale::parse_count)]
        steps: Vec<u64>,
        #[arg(long, default_value_t = 32)]
        spp: u32,
        /// Where to write the traces (default: a temporary directory).
        #[arg(long)]
        dir: Option<PathBuf>,
        /// Keep each step's trace (default: removed after its step).
        #[arg(long)]
        keep: bool,
        /// Skip the first-picture step (it needs a GPU adapter; lavapipe will do).
        #[arg(long)]
        no_render: bool,
        /// `--memory-limit` of the SQL steps, e.g. 2GiB.
        #[arg(long)]
        memory_limit: Option<String>,
    },
    /// The query service under load: N Flight SQL clients for S seconds (queries per second,
    /// p50/p99 latency per query type, every answer checked), beside the same queries alone
    /// in-process.
    Serve {
        dataset: PathBuf,
        #[arg(long, default_value_t = 32)]
        clients: usize,
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
        /// Against a running `rtvtk serve` (http://HOST:PORT) instead of one started in-process.
        #[arg(long)]
        connect: Option<String>,
        /// Bearer token to send (default: RTVTK_TOKEN).
        #[arg(long)]
        token: Option<String>,
        /// Mix in a query over the per-query memory limit (4 MiB in-process; with --connect,
        /// start the server with --query-memory 4MiB; needs a trace of 200K rays or more): it
        /// must fail alone.
        #[arg(long)]
        over_limit: bool,
    },
    /// The visualizer's ray layer: load time of N rays beside `rtvtk sql` scanning the same
    /// columns, frame time of the layer, GPU memory per segment.
    Viz {
        dataset: PathBuf,
        /// Ray counts to load (comma separated; each at most the dataset's rays).
        #[arg(long, value_delimiter = ',', default_value = "1000000")]
        rays: Vec<u64>,
        /// Frame size WxH.
        #[arg(long, default_value = "1920x1080", value_parser = crate::args::parse_size)]
        size: (u32, u32),
        /// Timed frames per ray count.
        #[arg(long, default_value_t = 20)]
        frames: usize,
        /// Untimed frames drawn first in each style (0 for counts whose frames take minutes on a
        /// CPU adapter).
        #[arg(long, default_value_t = 2)]
        warmup: usize,
        /// Load rounds (the baseline scan and our load alternate).
        #[arg(long, default_value_t = 3)]
        rounds: usize,
        /// Styles to draw (comma separated; `none` for the load alone).
        #[arg(long, value_delimiter = ',', default_value = "lines,alpha,density")]
        styles: Vec<String>,
    },
    /// The GPU tracer beside the CPU in the same run: primary rays per second (same rays, hits
    /// compared), path-traced samples and rays per second by kind, frames of one sample per
    /// pixel per second, and with --record rays recorded per second.
    Gpu {
        #[arg(long, default_value = "cornell")]
        scene: String,
        /// Subdivide every triangle into n² (a larger scene from the same geometry).
        #[arg(long, default_value_t = 1)]
        subdivide: u32,
        #[arg(long, default_value = "1920x1080", value_parser = crate::args::parse_size)]
        size: (u32, u32),
        #[arg(long, default_value_t = 5)]
        rounds: usize,
        /// Samples per pixel of each GPU path-tracing round (one dispatch per sample).
        #[arg(long, default_value_t = 4)]
        spp: u32,
        /// Leave out the CPU baselines (the CPU path tracer at 1080p takes long in a dev build).
        #[arg(long)]
        no_cpu: bool,
        /// Also record one sample per pixel into a dataset with each tracer (rays recorded per
        /// second, through `rl` into the store).
        #[arg(long)]
        record: bool,
    },
    /// One-tree fetch latency on an existing dataset (by id, first touch and warm, and by
    /// pixel), beside DuckDB; reads only the pages of the trees fetched, whatever the trace's size.
    Fetch {
        dataset: PathBuf,
        #[arg(long, default_value_t = 2000)]
        fetches: usize,
        #[arg(long)]
        no_duckdb: bool,
    },
}

pub fn run(cmd: BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Trace { subdivide, rotate, width, spp, rounds } => {
            bench::trace::run(subdivide, rotate, width, spp, rounds.max(1))
        }
        BenchCommand::Serve { dataset, clients, seconds, connect, token, over_limit } => {
            let token = token.or_else(|| std::env::var("RTVTK_TOKEN").ok());
            let o = bench::serve::ServeBench { connect, token, clients, seconds, over_limit };
            bench::serve::run(&dataset, &o)
        }
        BenchCommand::Viz { dataset, rays, size, frames, warmup, rounds, styles } => {
            let styles: Vec<String> = styles.into_iter().filter(|s| s != "none").collect();
            bench::viz::run(&dataset, &rays, size, (frames.max(1), warmup), rounds.max(1), &styles)
        }
        BenchCommand::Gpu { scene, subdivide, size, rounds, spp, no_cpu, record } => {
            let o = bench::gpu::GpuBench { rounds: rounds.max(1), spp: spp.max(1), cpu: !no_cpu, record };
            bench::gpu::run(&scene, subdivide, size, &o)
        }
        BenchCommand::Fetch { dataset, fetches, no_duckdb } => bench::fetch_bench(&dataset, fetches, !no_duckdb),
        BenchCommand::Record { runs, args } => bench::record::run(runs, &args),
        BenchCommand::Payload { scenes, size, spp, bits } => {
            bench::payload::run(&bench::payload::PayloadArgs { scenes, size, spp: spp.max(1), bits })
        }
        BenchCommand::Scale { steps, spp, dir, keep, no_render, memory_limit } => {
            if let Some(m) = &memory_limit {
                crate::sql::parse_bytes(m).map_err(anyhow::Error::msg)?;
            }
            bench::scale::run(&bench::scale::ScaleArgs { steps, spp, dir, keep, render: !no_render, memory_limit })
        }
        BenchCommand::Query { dataset, plain, runs, memory_limit, no_duckdb, cluster, executor_cores } => {
            if let Some(m) = &memory_limit {
                crate::sql::parse_bytes(m).map_err(anyhow::Error::msg)?;
            }
            if !cluster.is_empty() {
                return bench::query::run_cluster(&dataset, &cluster, executor_cores.max(1), runs.max(1));
            }
            bench::query::run(&dataset, plain, runs.max(1), memory_limit.as_deref(), !no_duckdb)
        }
        BenchCommand::Store {
            rays,
            threads,
            workers,
            chunk_rays,
            page_rows,
            fetches,
            dir,
            scene,
            encodings,
            no_duckdb,
            no_sync,
            rounds,
        } => {
            let encodings = encodings.iter().map(|e| Encoding::parse(e)).collect::<Result<Vec<_>, _>>()?;
            let args = bench::StoreArgs {
                threads: threads.max(1),
                workers: workers.max(1),
                chunk_rays: chunk_rays.max(1),
                page_rows: page_rows.max(1),
                fetches,
                duckdb: !no_duckdb,
                sync: !no_sync,
                rounds: rounds.max(1),
            };
            bench::store_bench(rays, &args, dir, scene.as_deref(), &encodings)
        }
    }
}
