//! The render driver: pixels in parallel, every ray handed to `rl` when recording.

use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Instant;

use arrow::datatypes::DataType;
use glam::Vec3A;
use rl::{Kind, ListValue, Payload, PayloadField, PayloadSchema, RayFields, RayId, Recorder, Value};

use crate::bvh::Bvh;
use crate::choice::TracerChoice;
use crate::film::Film;
use crate::sampling::Rng;
use crate::scene::Scene;
use crate::tracer::{Bug, SampleRecord, TraceCtx, path_sample, whitted_sample};
use crate::{Error, Result};

/// How to render.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    pub width: u32,
    pub height: u32,
    pub spp: u32,
    pub seed: u64,
    pub max_depth: u32,
    /// Only pixels x0 <= x < x1, y0 <= y < y1.
    pub window: Option<[u32; 4]>,
    /// Only these sample indices (default 0..spp): `Some(s..s+1)` replays one sample.
    pub samples: Option<std::ops::Range<u32>>,
    pub threads: usize,
    pub bug: Option<Bug>,
    /// Record only rays of these kinds (a ray of another kind is left out with its descendants).
    pub record_kinds: Option<Vec<Kind>>,
    /// Record the BVH nodes each ray visits (the `ray_nodes` table; large).
    pub record_visits: bool,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            width: 256,
            height: 256,
            spp: 4,
            seed: 0,
            max_depth: 8,
            window: None,
            samples: None,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            bug: None,
            record_kinds: None,
            record_visits: false,
        }
    }
}

/// What a render did.
#[derive(Clone, Debug, Default)]
pub struct RenderStats {
    pub samples: u64,
    pub rays: u64,
    pub rays_by_kind: Vec<(Kind, u64)>,
    pub secs: f64,
}

/// The payload every instrumented tracer records per ray.
pub fn payload_schema() -> PayloadSchema {
    // Valid by construction (distinct names, supported types), so built directly.
    let field =
        |name: &str, element: DataType, list_len: Option<usize>| PayloadField { name: name.into(), element, list_len };
    PayloadSchema {
        fields: vec![
            field("throughput", DataType::Float32, Some(3)),
            field("radiance", DataType::Float32, Some(3)),
            field("material", DataType::UInt32, None),
            field("nodes_visited", DataType::UInt32, None),
            field("box_tests", DataType::UInt32, None),
            field("tri_tests", DataType::UInt32, None),
        ],
        bytes: None,
    }
}

impl RenderOptions {
    pub(crate) fn validate(&self) -> Result<()> {
        if self.width == 0 || self.height == 0 || self.spp == 0 {
            return Err(Error::Settings("width, height and samples per pixel must be positive".into()));
        }
        if let Some([x0, y0, x1, y1]) = self.window
            && (x0 >= x1 || y0 >= y1 || x1 > self.width || y1 > self.height)
        {
            return Err(Error::Settings(format!(
                "window {x0},{y0},{x1},{y1} must satisfy x0 < x1 <= {} and y0 < y1 <= {}",
                self.width, self.height
            )));
        }
        if let Some(s) = &self.samples
            && (s.start >= s.end)
        {
            return Err(Error::Settings("sample range is empty".into()));
        }
        Ok(())
    }
}

/// Writes what a recording of `scene` needs besides the rays: BVH nodes, lights, attributes.
pub fn describe_recording(
    rec: &Recorder,
    scene: &Scene,
    bvh: &Bvh,
    tracer: TracerChoice,
    opts: &RenderOptions,
) -> Result<()> {
    use store::scene::{BVH_NODES_TABLE, LIGHTS_TABLE, TRIANGLES_TABLE};
    rec.write_table(BVH_NODES_TABLE, bvh.node_table()?)?;
    rec.write_table(TRIANGLES_TABLE, scene.triangles_table()?)?;
    if !scene.lights.is_empty() {
        rec.write_table(LIGHTS_TABLE, scene.lights_table()?)?;
    }
    let c = scene.camera;
    rec.set_attributes([
        ("scene", scene.name.clone()),
        ("tracer", format!("{tracer:?}").to_lowercase()),
        ("spp", opts.spp.to_string()),
        ("seed", opts.seed.to_string()),
        ("max_depth", opts.max_depth.to_string()),
        ("inject_bug", opts.bug.map_or("none", Bug::name).into()),
        (
            "camera",
            format!(
                "{:?} -> {:?} up {:?} fov {}",
                c.position.to_array(),
                c.target.to_array(),
                c.up.to_array(),
                c.fov_y
            ),
        ),
        ("triangles", scene.tris.len().to_string()),
        ("bvh_nodes", bvh.node_count().to_string()),
    ])?;
    rec.set_attributes(scene.camera_attrs(opts.width, opts.height).to_attributes())?;
    Ok(())
}

struct ThreadOut {
    rows: Vec<(u32, Vec<Vec3A>)>,
    rays: [u64; 256],
    samples: u64,
    visits: Vec<(u64, u32, u32)>,
}

/// Hands one sample's rays to the recorder as one tree (`[x, y, sample]`), leaving out rays of
/// kinds not in `keep` (with their descendants); `map` is scratch space reused from tree to tree.
/// Shared by the CPU tracers and the GPU tracer, so both record the same columns and payload.
pub fn emit(
    rec: &Recorder,
    [x, y, s]: [u32; 3],
    sr: &SampleRecord,
    keep: Option<&[Kind]>,
    visits: Option<&mut Vec<(u64, u32, u32)>>,
    map: &mut Vec<Option<RayId>>,
) {
    let mut tree = rec.begin_tree(x, y, s);
    map.clear();
    let mut visits = visits;
    for r in &sr.rays {
        let parent = r.parent.and_then(|p| map[p as usize]);
        let dropped = r.parent.is_some() && parent.is_none();
        if dropped || keep.is_some_and(|k| !k.contains(&r.kind)) {
            map.push(None);
            continue;
        }
        let fields =
            RayFields { origin: r.origin.to_array(), direction: r.dir.to_array(), t: r.t, kind: r.kind, prim: r.prim };
        let tp = r.throughput.to_array();
        let rad = r.radiance.to_array();
        let values = [
            Value::List(ListValue::F32(&tp)),
            Value::List(ListValue::F32(&rad)),
            r.material.map_or(Value::Null, Value::U32),
            Value::U32(r.stats.nodes),
            Value::U32(r.stats.boxes),
            Value::U32(r.stats.tris),
        ];
        // The site where the tracer traced the ray, not this loop.
        let site = rl::SiteRef::Location(r.site);
        let id = match parent {
            Some(p) => tree.add_ray_under_at(site, p, &fields, Payload::values(&values)),
            None => tree.add_ray_at(site, &fields, Payload::values(&values)),
        };
        if let Some(v) = visits.as_deref_mut() {
            for &node in &sr.visits[r.visits.0 as usize..r.visits.1 as usize] {
                v.push((tree.id().0, id.0, node));
            }
        }
        map.push(Some(id));
    }
    tree.end();
}

/// Renders `scene` with the CPU tracer `tracer` (path or Whitted), recording every ray into
/// `rec` when given. `progress` is called with the
/// number of rows finished so far.
pub fn render(
    scene: &Scene,
    bvh: &Bvh,
    tracer: TracerChoice,
    opts: &RenderOptions,
    rec: Option<&Recorder>,
    progress: &(dyn Fn(u32) + Sync),
) -> Result<(Film, RenderStats)> {
    opts.validate()?;
    if tracer.on_gpu() {
        return Err(Error::Settings(
            "tracer gpu renders on the GPU (renderers::tracer builds it), not on the CPU tracers".into(),
        ));
    }
    let start = Instant::now();
    let [x0, y0, x1, y1] = opts.window.unwrap_or([0, 0, opts.width, opts.height]);
    let samples = opts.samples.clone().unwrap_or(0..opts.spp);
    let next_row = AtomicU32::new(y0);
    let done = AtomicU32::new(0);
    let ctx = TraceCtx::new(scene, bvh, opts.max_depth, opts.bug, opts.record_visits && rec.is_some());
    let keep = opts.record_kinds.as_deref();
    let outs: Vec<ThreadOut> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..opts.threads.max(1))
            .map(|_| {
                let (ctx, next_row, done, samples) = (&ctx, &next_row, &done, samples.clone());
                s.spawn(move || {
                    let mut out = ThreadOut { rows: Vec::new(), rays: [0; 256], samples: 0, visits: Vec::new() };
                    let mut sr = SampleRecord::new(rec.is_some());
                    let mut map = Vec::new();
                    loop {
                        let y = next_row.fetch_add(1, Ordering::Relaxed);
                        if y >= y1 {
                            break;
                        }
                        let mut row = Vec::with_capacity((x1 - x0) as usize);
                        for x in x0..x1 {
                            let mut sum = Vec3A::ZERO;
                            for s in samples.clone() {
                                let mut rng = Rng::for_sample(opts.seed, x, y, s);
                                let (fx, fy) = (x as f32 + rng.next_f32(), y as f32 + rng.next_f32());
                                sr.clear();
                                let r = Some(&mut sr);
                                let l = match tracer {
                                    TracerChoice::Path | TracerChoice::Gpu => {
                                        path_sample(ctx, fx, fy, opts.width, opts.height, &mut rng, r)
                                    }
                                    TracerChoice::Whitted => {
                                        whitted_sample(ctx, fx, fy, opts.width, opts.height, &mut rng, r)
                                    }
                                };
                                if let Some(rec) = rec {
                                    let v = ctx.record_visits.then_some(&mut out.visits);
                                    emit(rec, [x, y, s], &sr, keep, v, &mut map);
                                }
                                if l.is_finite() {
                                    sum += l;
                                }
                                out.samples += 1;
                            }
                            row.push(sum / (samples.end - samples.start) as f32);
                        }
                        out.rows.push((y, row));
                        progress(done.fetch_add(1, Ordering::Relaxed) + 1);
                    }
                    out.rays = sr.counts;
                    out
                })
            })
            .collect();
        handles.into_iter().filter_map(|h| h.join().ok()).collect()
    });
    if outs.len() != opts.threads.max(1) {
        return Err(Error::Settings("a render thread panicked".into()));
    }
    let mut film = Film::new(opts.width, opts.height);
    let mut stats = RenderStats::default();
    let mut by_kind = [0u64; 256];
    let mut visits = Vec::new();
    for o in outs {
        for (y, row) in o.rows {
            for (i, p) in row.into_iter().enumerate() {
                film.pixels[(y * opts.width + x0) as usize + i] = p;
            }
        }
        for (k, n) in o.rays.iter().enumerate() {
            by_kind[k] += n;
        }
        stats.samples += o.samples;
        visits.extend(o.visits);
    }
    if let Some(rec) = rec
        && opts.record_visits
    {
        let node = |v: &(u64, u32, u32)| v.2 & !crate::bvh::VISIT_HIT;
        let visits = visits
            .iter()
            .map(|v| (v.0, v.1, node(v), bvh.is_leaf(node(v)).then_some(v.2 & crate::bvh::VISIT_HIT != 0)))
            .collect();
        let batch = store::scene::ray_nodes_batch(visits)?;
        rec.write_table(store::scene::RAY_NODES_TABLE, batch)?;
    }
    stats.rays = by_kind.iter().sum();
    stats.rays_by_kind =
        by_kind.iter().enumerate().filter(|(_, n)| **n > 0).map(|(k, n)| (Kind(k as u8), *n)).collect();
    stats.secs = start.elapsed().as_secs_f64();
    Ok((film, stats))
}
