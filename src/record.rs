//! `rtvtk record` and `rtvtk demo`: render a scene with a CPU or the GPU tracer, recording every ray.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use renderers::{Bug, Bvh, Camera, RenderOptions, TracerChoice};
use rl::{Kind, Recorder, RecorderOptions};

#[derive(Parser, Debug)]
pub struct RecordArgs {
    /// cornell, cornell-glass, glossy, or an OBJ file.
    #[arg(long, default_value = "cornell")]
    pub scene: String,
    /// Samples per pixel.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    /// Image size, WxH.
    #[arg(long, default_value = "256x256", value_parser = crate::args::parse_size)]
    pub size: (u32, u32),
    /// Dataset directory to write (required unless --no-record).
    #[arg(long, required_unless_present = "no_record")]
    pub out: Option<PathBuf>,
    /// path (the CPU path tracer), whitted (the CPU Whitted tracer) or gpu (the GPU path tracer:
    /// WGSL compute through wgpu, lavapipe or llvmpipe without a GPU; the same scene, camera,
    /// materials and recorded columns as path).
    #[arg(long, default_value = "path", value_parser = crate::args::parse_tracer)]
    pub tracer: TracerChoice,
    /// Only pixels in X0,Y0,X1,Y1 (X1, Y1 exclusive).
    #[arg(long, value_parser = parse_window)]
    pub window: Option<[u32; 4]>,
    /// Only this pixel, X,Y (with --sample: only that sample, traced exactly as in a full render).
    #[arg(long, value_parser = crate::args::parse_pixel, conflicts_with = "window")]
    pub pixel: Option<(u32, u32)>,
    #[arg(long, requires = "pixel")]
    pub sample: Option<u32>,
    /// Record only these kinds (comma separated); rays of other kinds are left out with their descendants.
    #[arg(long, value_delimiter = ',')]
    pub record_kinds: Option<Vec<String>>,
    /// Also record the BVH nodes every ray visits (the ray_nodes table; large).
    #[arg(long)]
    pub record_visits: bool,
    /// Record each ray's site: the line of the tracer that traced it (the `site` column and the
    /// `sites` table).
    #[arg(long)]
    pub sites: bool,
    /// Render without recording (for overhead figures).
    #[arg(long)]
    pub no_record: bool,
    /// How origins and directions are stored: lossless (residuals against the tree structure),
    /// plain (Float32 columns any Parquet reader sees directly) or octN (directions quantized to
    /// N bits per octahedral coordinate, 8..=16).
    #[arg(long, default_value = "lossless", value_parser = parse_encoding)]
    pub encoding: store::Encoding,
    /// Lossy payload: float payload values (throughput, radiance, ...) rounded to this many
    /// mantissa bits, 1 to 22 (10: half precision's, a relative error of at most 2^-11). Default:
    /// every bit kept.
    #[arg(long, value_parser = clap::value_parser!(u8).range(1..=22))]
    pub payload_bits: Option<u8>,
    /// Background threads that encode and write segments (default: all cores). The tracers
    /// outrun one writer, so a second one on two cores cut the wall time of a 25M-ray Cornell
    /// recording by 13% (7.68 to 6.69 s) for 58 MiB more resident memory.
    #[arg(long)]
    pub writers: Option<usize>,
    /// Rays per segment file (segments are the unit of parallel reads and of crash safety).
    #[arg(long, default_value_t = 4 << 20, value_parser = clap::value_parser!(u64).range(1..))]
    pub segment_rays: u64,
    /// Rays a tracing thread gathers before handing them to a writer thread as one chunk
    /// (smaller chunks keep the writers' working set out of the tracers' caches).
    #[arg(long, default_value_t = RecorderOptions::default().chunk_rays as u64, value_parser = clap::value_parser!(u64).range(1..))]
    pub chunk_rays: u64,
    /// Rows per Parquet data page of the ray files: the unit a one-tree fetch decompresses
    /// (smaller pages fetch faster and compress a little worse).
    #[arg(long, default_value_t = store::WriteOptions::default().page_rows as u64, value_parser = clap::value_parser!(u64).range(1..=1 << 20))]
    pub page_rows: u64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Tracing threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    #[arg(long, default_value_t = 8)]
    pub max_depth: u32,
    /// Where to write the PNG (default: OUT/image.png).
    #[arg(long)]
    pub image: Option<PathBuf>,
    /// Where to write the linear EXR (default: OUT/image.exr).
    #[arg(long)]
    pub exr: Option<PathBuf>,
    #[arg(long, default_value_t = 1.0)]
    pub exposure: f32,
    /// A bug to inject, to be found with the toolkit: shadow-dir (the paper's Figure 1: shadow
    /// rays aimed at no light, found by `analyze numerics` and `bugs`), nan (a zero light pdf at
    /// grazing angles: infinite weights, NaN pixels), no-offset (secondary rays start on the
    /// surface: self-intersections) or leak (secondary rays start 1% of the scene's size along
    /// their direction: through walls). The GPU tracer has shadow-dir only.
    #[arg(long, value_parser = Bug::parse)]
    pub inject_bug: Option<Bug>,
    /// Camera position X,Y,Z (with --camera-target and --fov; default: the scene's camera).
    #[arg(long, value_parser = parse_vec3, requires = "camera_target")]
    pub camera_pos: Option<[f32; 3]>,
    #[arg(long, value_parser = parse_vec3, requires = "camera_pos")]
    pub camera_target: Option<[f32; 3]>,
    /// Vertical field of view in degrees.
    #[arg(long)]
    pub fov: Option<f32>,
    /// Do not print the summary tables.
    #[arg(long)]
    pub quiet: bool,
    /// Split every quad of a built-in scene n × n (more triangles, same picture).
    #[arg(long, default_value_t = 1)]
    pub subdivide: u32,
    /// Scale the scene (and its camera) by S: the extreme-scale cases (1e-4, 1e5) of the
    /// numerical checks.
    #[arg(long, default_value_t = 1.0, value_parser = parse_scale)]
    pub scale: f32,
    /// Move the scene (and its camera) by X,Y,Z after scaling: far from the origin (1e6,1e6,1e6).
    #[arg(long, value_parser = parse_vec3)]
    pub offset: Option<[f32; 3]>,
}

fn parse_scale(s: &str) -> Result<f32, String> {
    match s.trim().parse::<f32>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("bad scale {s:?}: expected a positive finite number")),
    }
}

fn parse_window(s: &str) -> Result<[u32; 4], String> {
    let v: Vec<u32> = s
        .split(',')
        .map(|p| p.trim().parse().map_err(|_| format!("bad window {s:?}: expected X0,Y0,X1,Y1")))
        .collect::<Result<_, _>>()?;
    v.try_into().map_err(|_| format!("bad window {s:?}: expected 4 numbers X0,Y0,X1,Y1"))
}

fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse().map_err(|_| format!("bad vector {s:?}: expected X,Y,Z")))
        .collect::<Result<_, _>>()?;
    let v: [f32; 3] = v.try_into().map_err(|_| format!("bad vector {s:?}: expected 3 numbers X,Y,Z"))?;
    if v.iter().any(|c| !c.is_finite()) {
        return Err(format!("bad vector {s:?}: NaN or infinite"));
    }
    Ok(v)
}

fn kind_by_name(name: &str) -> Option<Kind> {
    store::KindTable::default().lookup(name)
}

pub fn run(a: &RecordArgs) -> Result<()> {
    let camera = match (a.camera_pos, a.camera_target) {
        (Some(p), Some(t)) => Some(Camera {
            position: glam::Vec3A::from_array(p),
            target: glam::Vec3A::from_array(t),
            up: glam::Vec3A::Y,
            fov_y: a.fov.unwrap_or(40.0),
        }),
        _ => None,
    };
    let mut scene = renderers::load_scene(&a.scene, camera, a.subdivide)?;
    if let (Some(f), None) = (a.fov, camera) {
        scene.camera.fov_y = f;
    }
    if a.scale != 1.0 || a.offset.is_some() {
        scene = scene.transformed(a.scale, glam::Vec3A::from_array(a.offset.unwrap_or([0.0; 3])));
    }
    if scene.report.degenerate_skipped > 0 {
        eprintln!("note: skipped {} degenerate triangles of {}", scene.report.degenerate_skipped, a.scene);
    }
    let (w, h) = a.size;
    let record_kinds = match &a.record_kinds {
        None => None,
        Some(names) => Some(
            names
                .iter()
                .map(|n| {
                    kind_by_name(n).with_context(|| {
                        format!("unknown kind {n:?}: expected camera, shadow, diffuse, specular or transmission")
                    })
                })
                .collect::<Result<Vec<_>>>()?,
        ),
    };
    let (window, samples) = match a.pixel {
        Some((x, y)) => {
            if x >= w || y >= h {
                bail!("pixel {x},{y} is outside the {w}x{h} image");
            }
            if let Some(s) = a.sample
                && s >= a.spp
            {
                bail!("sample {s} is outside 0..{} (--spp)", a.spp);
            }
            (Some([x, y, x + 1, y + 1]), a.sample.map(|s| s..s + 1))
        }
        None => (a.window, None),
    };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let opts = RenderOptions {
        width: w,
        height: h,
        spp: a.spp,
        seed: a.seed,
        max_depth: a.max_depth,
        window,
        samples,
        threads: a.threads.unwrap_or(cores),
        bug: a.inject_bug,
        record_kinds,
        record_visits: a.record_visits,
    };
    let t = std::time::Instant::now();
    let bvh = Bvh::build(&scene.tris);
    let build_secs = t.elapsed().as_secs_f64();
    if a.tracer.on_gpu() {
        if let Some(bug) = a.inject_bug.filter(|b| *b != Bug::ShadowDir) {
            bail!(
                "--inject-bug {}: the GPU tracer injects shadow-dir only (the path and whitted tracers inject every bug)",
                bug.name()
            );
        }
        if a.record_visits {
            bail!("--record-visits: the GPU tracer does not record the BVH nodes each ray visits (use --tracer path)");
        }
        if !a.no_record && a.max_depth > gpu_tracer::MAX_RECORDED_DEPTH {
            bail!(
                "--max-depth {}: the GPU records paths of depth {} at most",
                a.max_depth,
                gpu_tracer::MAX_RECORDED_DEPTH
            );
        }
    }
    let scene = std::sync::Arc::new(scene);
    let bvh = std::sync::Arc::new(bvh);
    let tracer =
        renderers::tracer(a.tracer, scene.clone(), bvh.clone()).with_context(|| format!("the {} tracer", a.tracer))?;
    let recorder = match (&a.out, a.no_record) {
        (Some(out), false) => {
            let mut options = RecorderOptions {
                payload: renderers::payload_schema(),
                workers: a.writers.unwrap_or(cores).max(1),
                ..Default::default()
            };
            options.write.encoding = a.encoding;
            options.segment_rays = a.segment_rays;
            options.write.page_rows = a.page_rows as usize;
            options.write.payload_mantissa_bits = a.payload_bits;
            options.chunk_rays = a.chunk_rays as usize;
            options.sites = a.sites;
            let rec = Recorder::create(out, options).with_context(|| format!("creating {}", out.display()))?;
            renderers::describe_recording(&rec, &scene, &bvh, tracer.choice(), &opts)?;
            if let Some(device) = tracer.device() {
                rec.set_attributes([("tracer".to_string(), tracer.choice().to_string()), ("gpu".to_string(), device)])?;
            }
            // The images beside the dataset, findable from its manifest.
            let inside = |p: &Option<PathBuf>, name: &str| match p {
                None => Some(name.to_string()),
                Some(p) => p.strip_prefix(out).ok().map(|r| r.to_string_lossy().to_string()),
            };
            let images = [
                (store::scene::attr::IMAGE_PNG, inside(&a.image, "image.png")),
                (store::scene::attr::IMAGE_EXR, inside(&a.exr, "image.exr")),
            ];
            rec.set_attributes(images.into_iter().filter_map(|(k, v)| v.map(|v| (k.to_string(), v))))?;
            Some(rec)
        }
        _ => None,
    };
    let rows = window.map_or(h, |w| w[3] - w[1]);
    let bar = ProgressBar::new(u64::from(rows));
    bar.set_style(
        ProgressStyle::with_template("{spinner} rendering [{bar:40}] {pos}/{len} rows {elapsed_precise} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let progress = |n: u32| bar.set_position(u64::from(n));
    let (film, stats) = tracer.render(&opts, recorder.as_ref(), &progress)?;
    bar.finish_and_clear();
    let summary = match recorder {
        Some(r) => Some(r.finish()?),
        None => None,
    };
    let total_secs = t.elapsed().as_secs_f64();
    let image = a.image.clone().or_else(|| a.out.as_ref().filter(|_| !a.no_record).map(|o| o.join("image.png")));
    let exr = a.exr.clone().or_else(|| a.out.as_ref().filter(|_| !a.no_record).map(|o| o.join("image.exr")));
    if let Some(p) = &image {
        film.write_png(p, a.exposure)?;
    }
    if let Some(p) = &exr {
        film.write_exr(p)?;
    }
    if a.quiet {
        return Ok(());
    }
    println!(
        "{} {}x{} spp {} ({} triangles, BVH {} nodes built in {:.3} s): {} samples, {} rays in {:.2} s ({:.2} Mrays/s)",
        scene.name,
        w,
        h,
        a.spp,
        scene.tris.len(),
        bvh.node_count(),
        build_secs,
        stats.samples,
        stats.rays,
        stats.secs,
        stats.rays as f64 / stats.secs / 1e6
    );
    if let Some(device) = tracer.device() {
        println!("  on the GPU: {device}");
    }
    let kinds = store::KindTable::default();
    for (k, n) in &stats.rays_by_kind {
        let name = kinds.name(*k).unwrap_or("?");
        println!("  {name:<13} {n:>12}");
    }
    if let Some(s) = summary {
        println!(
            "recorded {} trees, {} rays, {} segments, {} bytes; wall {:.2} s",
            s.trees, s.rays, s.segments, s.bytes, total_secs
        );
    }
    if let Some(p) = image {
        println!("image: {}", p.display());
    }
    Ok(())
}

fn parse_encoding(s: &str) -> Result<store::Encoding, String> {
    store::Encoding::parse(s).map_err(|e| e.to_string())
}
