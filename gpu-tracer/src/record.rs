//! Rendering with every ray recorded: the GPU writes each path's rays, packed, into buffers
//! that are read back tile by tile and handed to `rl` as one tree per pixel sample, with the
//! CPU tracers' columns and payload (`renderers::render::emit`).

use std::time::Instant;

use glam::Vec3A;
use renderers::tracer::{RecRay, SampleRecord};
use renderers::{Film, RenderOptions, RenderStats, TraversalStats};
use rl::{Kind, Recorder};

use crate::{Error, GpuRay, GpuTracer, MAX_RECORDED_DEPTH, NONE, RAY_BYTES, RecordBuffers, Result};

/// Bytes of ray slots one recording pass may use (twice: the paths' slots and the packed copy).
const PASS_BYTES: u64 = 128 << 20;

impl GpuTracer {
    /// Renders as `renderers::render` does — same options, same film, same statistics — on the
    /// GPU, recording every ray into `rec` when given (`window` and `samples` replay a part of a
    /// render exactly: a sample's random numbers depend on its pixel, index and seed only).
    /// The path tracer only; `record_visits` is not available on the GPU.
    pub fn render_recorded(
        &self,
        opts: &RenderOptions,
        rec: Option<&Recorder>,
        progress: &(dyn Fn(u32) + Sync),
    ) -> Result<(Film, RenderStats)> {
        if let Some(bug) = opts.bug.filter(|b| *b != renderers::Bug::ShadowDir) {
            return Err(Error::Input(format!(
                "--inject-bug {}: the GPU tracer injects shadow-dir only; the CPU tracers (path, whitted) inject every bug",
                bug.name()
            )));
        }
        if opts.record_visits && rec.is_some() {
            return Err(Error::Input(
                "the GPU tracer does not record the BVH nodes each ray visits: record them with the CPU tracer".into(),
            ));
        }
        if rec.is_some() && opts.max_depth > MAX_RECORDED_DEPTH {
            return Err(Error::Input(format!(
                "max depth {}: the GPU records paths of depth {MAX_RECORDED_DEPTH} at most",
                opts.max_depth
            )));
        }
        if opts.spp == 0 {
            return Err(Error::Input("samples per pixel must be positive".into()));
        }
        let [x0, y0, x1, y1] = opts.window.unwrap_or([0, 0, opts.width, opts.height]);
        if x0 >= x1 || y0 >= y1 || x1 > opts.width || y1 > opts.height {
            return Err(Error::Input(format!(
                "window {x0},{y0},{x1},{y1} must satisfy x0 < x1 <= {} and y0 < y1 <= {}",
                opts.width, opts.height
            )));
        }
        let samples: Vec<u32> = opts.samples.clone().unwrap_or(0..opts.spp).collect();
        if samples.is_empty() {
            return Err(Error::Input("sample range is empty".into()));
        }
        let start = Instant::now();
        let seed = (opts.seed ^ (opts.seed >> 32)) as u32;
        let mut p = self.progressive(opts.width, opts.height, seed, opts.max_depth)?;
        let bug = opts.bug.is_some();
        let (ww, wh) = (x1 - x0, y1 - y0);
        match rec {
            None => {
                let batch: Vec<(u32, u32)> = samples.iter().map(|&s| (s, 0)).collect();
                self.dispatch(&mut p, [x0, y0, ww, wh], &batch, None, bug)?;
                progress(wh);
            }
            Some(rec) => {
                let slots = 2 * (opts.max_depth + 1);
                let per_path = u64::from(slots) * RAY_BYTES;
                let budget = PASS_BYTES.min(self.gpu.max_storage_binding()).max(per_path);
                let tw = ww.min((budget / per_path).clamp(1, u64::from(u32::MAX)) as u32);
                let batch = (samples.len() as u64).min(budget / (u64::from(tw) * per_path)).max(1) as usize;
                let th =
                    wh.min((budget / (u64::from(tw) * batch as u64 * per_path)).clamp(1, u64::from(u32::MAX)) as u32);
                let paths = u64::from(tw) * u64::from(th) * batch as u64;
                let buffer = |label: &str, size: u64, read: bool| {
                    let mut usage = wgpu::BufferUsages::STORAGE;
                    if read {
                        usage |= wgpu::BufferUsages::COPY_SRC;
                    }
                    self.gpu.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some(label),
                        size,
                        usage,
                        mapped_at_creation: false,
                    })
                };
                let bufs = RecordBuffers {
                    scratch: buffer("ray slots", paths * per_path, false),
                    packed: buffer("packed rays", paths * per_path, true),
                    spans: buffer("path spans", paths * 8, true),
                    slots,
                };
                let threads = opts.threads.max(1);
                let keep = opts.record_kinds.as_deref();
                for ty in (y0..y1).step_by(th as usize) {
                    let ch = th.min(y1 - ty);
                    for tx in (x0..x1).step_by(tw as usize) {
                        let cw = tw.min(x1 - tx);
                        for chunk in samples.chunks(batch) {
                            let work: Vec<(u32, u32)> = chunk.iter().enumerate().map(|(i, &s)| (s, i as u32)).collect();
                            let packed = self.dispatch(&mut p, [tx, ty, cw, ch], &work, Some(&bufs), bug)?;
                            let tile = u64::from(cw) * u64::from(ch);
                            let spans: Vec<[u32; 2]> = self.read_back(&bufs.spans, tile * chunk.len() as u64 * 8)?;
                            let rays: Vec<GpuRay> = self.read_back(&bufs.packed, u64::from(packed) * RAY_BYTES)?;
                            emit_tile(rec, [tx, ty, cw, ch], chunk, &spans, &rays, keep, threads)?;
                        }
                    }
                    progress(ty + ch - y0);
                }
            }
        }
        let film = self.film(&p)?;
        let rays_by_kind: Vec<(Kind, u64)> =
            p.rays_by_kind.iter().enumerate().filter(|(_, n)| **n > 0).map(|(k, n)| (Kind(k as u8), *n)).collect();
        let stats = RenderStats {
            samples: u64::from(ww) * u64::from(wh) * samples.len() as u64,
            rays: p.rays_by_kind.iter().sum(),
            rays_by_kind,
            secs: start.elapsed().as_secs_f64(),
        };
        Ok((film, stats))
    }
}

/// One recorded ray as the CPU tracers record it.
fn rec_ray(r: &GpuRay) -> RecRay {
    let some = |v: u32| (v != NONE).then_some(v);
    RecRay {
        parent: some(r.parent),
        origin: Vec3A::from_array(r.o),
        dir: Vec3A::from_array(r.d),
        t: some(r.prim).map(|_| r.t),
        prim: some(r.prim),
        kind: Kind(r.kind as u8),
        throughput: Vec3A::from_array(r.beta),
        radiance: Vec3A::from_array(r.rad),
        material: some(r.material),
        stats: TraversalStats { nodes: r.nodes, boxes: r.boxes, tris: r.tris },
        visits: (0, 0),
        // Traced in WGSL: the site is where the GPU's rays are handed over.
        site: std::panic::Location::caller(),
    }
}

/// Hands a tile's paths to `rec`, pixel by pixel (each pixel's samples in order), on `threads`
/// threads. `spans[i]` is path i's (offset, count) in `rays`; paths are numbered sample after
/// sample, row-major over the tile within each.
fn emit_tile(
    rec: &Recorder,
    [tx, ty, cw, ch]: [u32; 4],
    samples: &[u32],
    spans: &[[u32; 2]],
    rays: &[GpuRay],
    keep: Option<&[Kind]>,
    threads: usize,
) -> Result<()> {
    let tile = (cw * ch) as usize;
    let bad = std::sync::atomic::AtomicBool::new(false);
    std::thread::scope(|scope| {
        for t in 0..threads.min(tile) {
            let bad = &bad;
            scope.spawn(move || {
                let mut sr = SampleRecord::new(true);
                let mut map = Vec::new();
                for local in (t..tile).step_by(threads) {
                    let (x, y) = (tx + local as u32 % cw, ty + local as u32 / cw);
                    for (b, &s) in samples.iter().enumerate() {
                        let [at, n] = spans[b * tile + local];
                        let Some(path) = rays.get(at as usize..at as usize + n as usize) else {
                            bad.store(true, std::sync::atomic::Ordering::Relaxed);
                            return;
                        };
                        sr.clear();
                        sr.rays.extend(path.iter().map(rec_ray));
                        renderers::render::emit(rec, [x, y, s], &sr, keep, None, &mut map);
                    }
                }
            });
        }
    });
    if bad.load(std::sync::atomic::Ordering::Relaxed) {
        return Err(Error::Gpu(rtvtk_gpu::Error::Gpu("the GPU's path spans point outside the rays it packed".into())));
    }
    Ok(())
}
