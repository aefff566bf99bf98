//! The render worker: a thread that owns the visualizer's pipeline (its own headless GPU device)
//! and turns commands from the UI into composited frames. The UI thread never waits for the GPU:
//! it sends commands, keeps drawing the last frame, and picks up new frames and events when they
//! arrive. Commands that supersede each other (camera moves, resizes) are coalesced, so a slow
//! device (lavapipe on two cores) renders the latest view, not a backlog.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, Sender, TryRecvError, channel};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use viz::component::Pick;
use viz::{ComponentId, Gpu, Legend, Pipeline, Sources, ViewCamera};

/// What the viewer shows: a recorded dataset, a dataset an `rtvtk serve` service serves, or a
/// scene with no dataset (immediate mode only).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Source {
    Dataset(PathBuf),
    /// A dataset of the service the viewer was started with (`view --connect`) or of the engine
    /// it was given (`ViewerOptions::engine`), by its name there (empty: its first, the
    /// unqualified tables).
    Served(String),
    /// A built-in scene name (`cornell`, ...) or an OBJ file.
    Scene(String),
}

impl Source {
    pub fn label(&self) -> String {
        match self {
            Source::Dataset(p) => p.display().to_string(),
            Source::Served(n) if n.is_empty() => "the served dataset".into(),
            Source::Served(n) => format!("{n} (served)"),
            Source::Scene(s) => format!("scene {s}"),
        }
    }
}

/// Where the `Source::Served` datasets come from: an `rtvtk serve` service (`view --connect`;
/// every layer and the console ask it), or an engine the caller already holds (the Python
/// package's `session.view()`: the window asks the script's own engine).
#[derive(Clone, Debug)]
pub enum Service {
    Remote {
        /// `grpc://HOST:PORT`.
        url: String,
        /// Its bearer token, when it asks for one.
        token: Option<String>,
    },
    Engine(Arc<query::Engine>),
}

/// A component as it is saved and restored: kind, settings, shown or not.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerSpec {
    pub id: u64,
    pub kind: String,
    pub settings: serde_json::Value,
    pub enabled: bool,
}

/// A component as the UI shows it.
#[derive(Clone, Debug)]
pub struct LayerInfo {
    pub id: ComponentId,
    pub kind: String,
    pub name: String,
    pub enabled: bool,
    pub settings: serde_json::Value,
    /// Settings that take one of a few values, with those values (drawn as drop-downs).
    pub choices: Vec<(&'static str, &'static [&'static str])>,
    pub legend: Vec<Legend>,
    pub report: Vec<String>,
    pub renders: u64,
    /// A progressive layer's error against time (the Plots tab draws it).
    pub convergence: Vec<viz::component::ConvergencePoint>,
}

impl LayerInfo {
    pub fn spec(&self) -> LayerSpec {
        LayerSpec { id: self.id.0, kind: self.kind.clone(), settings: self.settings.clone(), enabled: self.enabled }
    }
}

/// A component kind the registry offers for the open source (or why not).
#[derive(Clone, Debug)]
pub struct Offer {
    pub kind: &'static str,
    pub name: &'static str,
    pub description: &'static str,
    pub available: Result<(), String>,
}

/// What opening a source found.
#[derive(Clone, Debug)]
pub struct Opened {
    pub source: Source,
    pub name: String,
    pub camera: ViewCamera,
    pub image_size: [u32; 2],
    pub has_dataset: bool,
    pub missing: Vec<String>,
    pub offers: Vec<Offer>,
    /// The engine the layers ask, for the console, plots and inspector too (`Err`: why there is
    /// none: no dataset, or one whose SQL session cannot be made).
    pub engine: Result<Arc<query::Engine>, String>,
}

/// A composited frame, read back (RGBA8, rows top to bottom).
pub struct Rendered {
    pub size: [u32; 2],
    pub pixels: Pixels,
    /// Milliseconds the render (and read-back, for RGBA) took.
    pub ms: f64,
    pub camera: ViewCamera,
}

/// How a frame crosses to the UI.
pub enum Pixels {
    /// Read back (a UI on another device: the kittest harness's).
    Rgba(Vec<u8>),
    /// The pipeline's output texture on the window's own device (`Pipeline::render`): nothing
    /// read back.
    Texture(wgpu::Texture),
}

pub enum Cmd {
    /// Opens a source and makes these components on it (none: the default pipeline); the
    /// datasets listed also go into its engine, under their names (the console's other tables).
    Open(Source, Vec<LayerSpec>, Vec<PathBuf>),
    Camera(ViewCamera),
    Resize([u32; 2]),
    Add(LayerSpec),
    Remove(ComponentId),
    /// Moves a component to a position (0: bottom).
    Reorder(ComponentId, usize),
    Enable(ComponentId, bool),
    Settings(ComponentId, serde_json::Value),
    /// Immediate mode: trace this pixel's tree with the first ray layer.
    Trace([u32; 2]),
    /// Picking at a pixel of the view.
    Pick([u32; 2]),
    /// Writes the composited picture (with legends) to a PNG.
    Screenshot(PathBuf),
    Quit,
}

pub enum Event {
    Opened(Opened),
    /// Opening failed: the UI keeps what it had.
    OpenFailed {
        source: Source,
        message: String,
    },
    Frame(Rendered),
    Layers(Vec<LayerInfo>),
    /// A command on a component (or the pipeline, `None`) failed.
    Error {
        layer: Option<ComponentId>,
        message: String,
    },
    Traced {
        pixel: [u32; 2],
        rays: usize,
    },
    Picked {
        pixel: [u32; 2],
        picked: Option<Pick>,
    },
    Screenshot(Result<PathBuf, String>),
}

/// The handle the UI holds.
pub struct Worker {
    tx: Sender<Cmd>,
    rx: Receiver<Event>,
    thread: Option<std::thread::JoinHandle<()>>,
    /// Commands sent and not yet answered by a frame or event (for "rendering…" and tests).
    pending: Arc<std::sync::atomic::AtomicUsize>,
    /// The running load's progress (every pipeline the thread opens reports to it); cancellable.
    pub progress: Arc<viz::component::Progress>,
}

impl Worker {
    /// Starts the thread; `wake` is called whenever an event is ready (the UI's repaint).
    /// The render thread; `gpu`: the default layers trace with the GPU path tracer (image
    /// source and immediate mode).
    /// The render thread; with `share_frames` a frame crosses as the pipeline's display texture
    /// (the caller's window draws on the process's device, `rtvtk_gpu::Gpu::share`), else as RGBA.
    pub fn spawn(
        wake: Arc<dyn Fn() + Send + Sync>,
        tracer: renderers::TracerChoice,
        share_frames: bool,
        service: Option<Service>,
    ) -> Worker {
        let (tx, crx) = channel();
        let (etx, rx) = channel();
        let pending = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let p = pending.clone();
        let progress: Arc<viz::component::Progress> = Arc::default();
        let pr = progress.clone();
        let thread = std::thread::Builder::new()
            .name("rtvtk-render".into())
            .spawn(move || {
                let opener = Opener { service, tracer, open: std::collections::HashMap::new() };
                run(crx, etx, wake, p, pr, share_frames, opener)
            })
            .ok();
        Worker { tx, rx, thread, pending, progress }
    }

    pub fn send(&self, cmd: Cmd) {
        self.pending.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        if self.tx.send(cmd).is_err() {
            self.pending.fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
        }
    }

    /// Events that arrived since the last call.
    pub fn poll(&self) -> Vec<Event> {
        self.rx.try_iter().collect()
    }

    /// Whether commands are still being worked on.
    pub fn busy(&self) -> bool {
        self.pending.load(std::sync::atomic::Ordering::SeqCst) > 0
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.tx.send(Cmd::Quit);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The components a fresh pipeline starts with, where the source offers them; with a tracer
/// other than the CPU path tracer (the default), the image is traced with it away from the
/// recorded view, and Ctrl-click traces with it.
pub fn default_layers(has_dataset: bool, [w, h]: [u32; 2], tracer: renderers::TracerChoice) -> Vec<LayerSpec> {
    use viz::component::Settings;
    use viz::components::geometry::{GeometrySettings, SurfaceStyle};
    use viz::components::picture::{ImageSettings, ImageSource};
    use viz::components::rays::RaysSettings;
    fn spec<S: Settings>(id: u64, s: S) -> LayerSpec {
        LayerSpec { id, kind: S::KIND.into(), settings: s.encode(), enabled: true }
    }
    let source = if tracer == renderers::TracerChoice::Path { ImageSource::Auto } else { ImageSource::Traced(tracer) };
    // The ray trees of the centre pixel to start with (readable, as the paper's Figure 3): all
    // trees are one click away in the rays tab ("All trees"). With no dataset, none.
    let rays = match has_dataset {
        true => RaysSettings {
            pixel: Some([w / 2, h / 2]),
            max_rays: Some(100_000),
            refine: true,
            tracer,
            ..Default::default()
        },
        false => RaysSettings { max_rays: Some(0), tracer, ..Default::default() },
    };
    let geometry = GeometrySettings { style: SurfaceStyle::Wireframe, opacity: 0.6, line_width: 1.0 };
    vec![
        spec(1, ImageSettings { source, ..Default::default() }),
        LayerSpec { enabled: false, ..spec(2, geometry) },
        LayerSpec {
            id: 3,
            kind: <viz::components::geometry::CompositionSettings as viz::component::Settings>::KIND.into(),
            settings: serde_json::Value::Null,
            enabled: true,
        },
        spec(4, rays),
    ]
}

/// Opens sources and the one engine over them; each dataset directory is opened once in the
/// worker's life (kept for the next open), and the engine registers that same dataset.
struct Opener {
    service: Option<Service>,
    /// The tracer of the default layers' image and Ctrl-click.
    tracer: renderers::TracerChoice,
    open: std::collections::HashMap<PathBuf, Arc<store::Dataset>>,
}

impl Opener {
    fn dataset(&mut self, dir: &std::path::Path) -> viz::Result<Arc<store::Dataset>> {
        let key = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
        if let Some(d) = self.open.get(&key) {
            return Ok(d.clone());
        }
        let d = Arc::new(store::Dataset::open(dir)?);
        self.open.insert(key, d.clone());
        Ok(d)
    }

    /// The sources of `source` and the engine over it (the shown dataset as `trace` and
    /// unqualified, then `others` under their names).
    fn open(
        &mut self,
        source: &Source,
        others: &[PathBuf],
    ) -> viz::Result<(Sources, Result<Arc<query::Engine>, String>)> {
        if let Source::Served(name) = source {
            let engine = match self.service.clone() {
                Some(Service::Engine(e)) => e,
                Some(Service::Remote { url, token }) => {
                    Arc::new(query::Engine::blocking(query::Engine::connect(&url, token))?)
                }
                None => return Err(viz::Error::Settings("the viewer was not started with --connect".into())),
            };
            let sources = Sources::with_engine(engine.clone(), Some(name.as_str()).filter(|n| !n.is_empty()))?;
            return Ok((sources, Ok(engine)));
        }
        let mut datasets = Vec::new();
        let shown = match source {
            Source::Dataset(dir) => {
                let d = self.dataset(dir)?;
                datasets.push(query::Registered { name: "trace".into(), dataset: d.clone() });
                Some(d)
            }
            _ => None,
        };
        for dir in others {
            let name = query::TraceSource::parse(&dir.display().to_string()).name;
            let Ok(d) = self.dataset(dir) else { continue };
            if shown.as_ref().is_some_and(|s| Arc::ptr_eq(s, &d)) || datasets.iter().any(|r| r.name == name) {
                continue;
            }
            datasets.push(query::Registered { name, dataset: d });
        }
        let engine = if datasets.is_empty() {
            Err("no dataset is open: there is nothing to query".to_string())
        } else {
            query::Engine::blocking(query::Engine::with_datasets(datasets, &Default::default()))
                .map(Arc::new)
                .map_err(|e| format!("cannot open the datasets for SQL: {e}"))
        };
        let sources = match (source, shown, &engine) {
            (Source::Dataset(_), Some(_), Ok(e)) => Sources::with_engine(e.clone(), None)?,
            (Source::Dataset(_), Some(d), Err(_)) => Sources::of_dataset(d)?,
            (Source::Scene(name), ..) => {
                let scene = renderers::load_scene(name, None, 0)?;
                Sources::from_scene(scene, 512, 512)?
            }
            _ => return Err(viz::Error::Settings(format!("cannot open {}", source.label()))),
        };
        Ok((sources, engine))
    }
}

struct State {
    pipeline: Pipeline,
}

/// Segments a ray layer draws per frame while the camera moves, when full frames are slow, to
/// start with: then as many as fit the frame time asked for.
const PREVIEW_SEGMENTS: u64 = 200_000;
/// The frame time previews aim at.
const PREVIEW_TARGET_MS: f64 = 50.0;
/// Full frames slower than this get previews while the camera moves.
const PREVIEW_ABOVE_MS: f64 = 100.0;
/// The camera counts as resting after this long without a camera command.
const PREVIEW_REST: std::time::Duration = std::time::Duration::from_millis(250);

fn run(
    rx: Receiver<Cmd>,
    tx: Sender<Event>,
    wake: Arc<dyn Fn() + Send + Sync>,
    pending: Arc<std::sync::atomic::AtomicUsize>,
    progress: Arc<viz::component::Progress>,
    share_frames: bool,
    mut opener: Opener,
) {
    let send = |e: Event| {
        let _ = tx.send(e);
        wake();
    };
    let mut state: Option<State> = None;
    let mut dirty = false;
    let mut refining = false;
    // A preview frame was drawn while the camera moved: draw in full once it rests.
    let mut full_pending = false;
    // How long the last full frame took: previews only where full frames are slow.
    let mut last_full_ms = 0.0f64;
    // The preview budget, adapted to the measured frame time of previews.
    let mut preview_budget = PREVIEW_SEGMENTS;
    loop {
        let mut cmds = Vec::new();
        if dirty || refining {
            loop {
                match rx.try_recv() {
                    Ok(c) => cmds.push(c),
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => return,
                }
            }
        } else if full_pending {
            match rx.recv_timeout(PREVIEW_REST) {
                Ok(c) => {
                    cmds.push(c);
                    cmds.extend(rx.try_iter());
                }
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return,
            }
        } else {
            match rx.recv() {
                Ok(c) => cmds.push(c),
                Err(_) => return,
            }
            cmds.extend(rx.try_iter());
        }
        let n = cmds.len();
        if n > 0 {
            // A cancel was for the load that ran before these commands.
            progress.reset();
        }
        // Only the last camera and size count.
        let last_camera = cmds.iter().rposition(|c| matches!(c, Cmd::Camera(_)));
        let last_size = cmds.iter().rposition(|c| matches!(c, Cmd::Resize(_)));
        for (i, cmd) in cmds.into_iter().enumerate() {
            match cmd {
                Cmd::Quit => return,
                Cmd::Camera(_) if Some(i) != last_camera => {}
                Cmd::Resize(_) if Some(i) != last_size => {}
                cmd => {
                    if let Some(e) = apply(&mut state, cmd, &progress, &mut opener) {
                        send(e);
                    }
                    dirty = true;
                }
            }
        }
        if let Some(s) = &mut state {
            // While the camera moves and full frames are slow (millions of rays on a CPU
            // rasterizer), the ray layers draw an evenly thinned preview; once no camera command
            // came for PREVIEW_REST, everything again.
            let preview = (last_camera.is_some() && last_full_ms > PREVIEW_ABOVE_MS).then_some(preview_budget);
            if s.pipeline.preview != preview {
                s.pipeline.preview = preview;
                dirty = true;
            }
            full_pending = preview.is_some();
            match s.pipeline.idle() {
                Ok(changed) => {
                    refining = changed;
                    dirty |= changed;
                }
                Err(e) => {
                    refining = false;
                    send(Event::Error { layer: None, message: e.to_string() });
                }
            }
            if dirty {
                dirty = false;
                let t0 = Instant::now();
                let frame = if share_frames {
                    s.pipeline.render().map(|t| Pixels::Texture(t.clone()))
                } else {
                    s.pipeline.snapshot(false).map(|img| Pixels::Rgba(img.into_raw()))
                };
                match frame {
                    Ok(pixels) => {
                        let size = s.pipeline.size();
                        let ms = t0.elapsed().as_secs_f64() * 1e3;
                        match s.pipeline.preview {
                            None => last_full_ms = ms,
                            // Halfway (geometrically) to the budget that would have met the
                            // target, so one slow frame does not swing it.
                            Some(b) => preview_budget = adapt_budget(b, ms),
                        }
                        let camera = s.pipeline.camera();
                        send(Event::Frame(Rendered { size, pixels, ms, camera }));
                    }
                    Err(e) => send(Event::Error { layer: None, message: e.to_string() }),
                }
                send(Event::Layers(layers(&s.pipeline)));
            }
        }
        pending
            .fetch_sub(n.min(pending.load(std::sync::atomic::Ordering::SeqCst)), std::sync::atomic::Ordering::SeqCst);
        wake();
    }
}

/// The next preview budget after a preview of `budget` segments took `ms`: halfway
/// (geometrically) to the one that meets [`PREVIEW_TARGET_MS`], within 10K..50M segments.
fn adapt_budget(budget: u64, ms: f64) -> u64 {
    let ratio = (PREVIEW_TARGET_MS / ms.max(0.1)).sqrt().clamp(0.25, 4.0);
    ((budget as f64 * ratio) as u64).clamp(10_000, 50_000_000)
}

fn layers(p: &Pipeline) -> Vec<LayerInfo> {
    p.layers()
        .iter()
        .map(|l| LayerInfo {
            id: l.component.id(),
            kind: l.component.kind().to_string(),
            name: l.component.display_name(),
            enabled: l.enabled,
            settings: l.component.settings(),
            choices: l.component.choices(),
            legend: l.component.legend(),
            report: match l.failed() {
                Some(why) => vec![format!("not drawn: {why}")],
                None => l.component.report(),
            },
            renders: l.renders,
            convergence: l.component.convergence(),
        })
        .collect()
}

fn make(p: &mut Pipeline, spec: &LayerSpec) -> viz::Result<()> {
    let c = viz::make(&spec.kind, ComponentId(spec.id), &p.sources, &spec.settings)?;
    p.push(c);
    p.layer_mut(ComponentId(spec.id))?.enabled = spec.enabled;
    Ok(())
}

fn apply(
    state: &mut Option<State>,
    cmd: Cmd,
    progress: &Arc<viz::component::Progress>,
    opener: &mut Opener,
) -> Option<Event> {
    let err = |layer, e: viz::Error| Some(Event::Error { layer, message: e.to_string() });
    if let Cmd::Open(source, specs, others) = cmd {
        let (sources, engine) = match opener.open(&source, &others) {
            Ok(s) => s,
            Err(e) => return Some(Event::OpenFailed { source, message: e.to_string() }),
        };
        let gpu = match Gpu::shared() {
            Ok(g) => g,
            Err(e) => return Some(Event::OpenFailed { source, message: e.to_string() }),
        };
        let offers = viz::registry()
            .iter()
            .map(|i| Offer {
                kind: i.kind,
                name: i.display_name,
                description: i.description,
                available: (i.offered)(&sources),
            })
            .collect();
        let has_dataset = sources.has_rays();
        let size = sources.image_size;
        let mut pipeline = Pipeline::new(gpu, sources);
        pipeline.progress = progress.clone();
        let specs = if specs.is_empty() { default_layers(has_dataset, size, opener.tracer) } else { specs };
        let mut failed = Vec::new();
        for spec in &specs {
            if let Err(e) = make(&mut pipeline, spec) {
                failed.push(format!("{} #{}: {e}", spec.kind, spec.id));
            }
        }
        let opened = Opened {
            source,
            name: pipeline.sources.name.clone(),
            camera: pipeline.camera(),
            image_size: pipeline.size(),
            has_dataset,
            missing: pipeline.sources.missing.iter().cloned().chain(failed).collect(),
            offers,
            engine,
        };
        *state = Some(State { pipeline });
        return Some(Event::Opened(opened));
    }
    let Some(s) = state.as_mut() else {
        return Some(Event::Error { layer: None, message: "nothing is open".into() });
    };
    let p = &mut s.pipeline;
    match cmd {
        Cmd::Open(..) | Cmd::Quit => None,
        Cmd::Camera(c) => p.set_camera(c).err().and_then(|e| err(None, e)),
        Cmd::Resize([w, h]) => p.resize(w, h).err().and_then(|e| err(None, e)),
        Cmd::Add(spec) => {
            let id = ComponentId(spec.id);
            let r = make(p, &spec);
            r.err().and_then(|e| err(Some(id), e)).or(Some(Event::Layers(layers(p))))
        }
        Cmd::Remove(id) => p.remove(id).err().and_then(|e| err(Some(id), e)).or(Some(Event::Layers(layers(p)))),
        Cmd::Reorder(id, to) => {
            p.reorder(id, to).err().and_then(|e| err(Some(id), e)).or(Some(Event::Layers(layers(p))))
        }
        Cmd::Enable(id, on) => match p.layer_mut(id) {
            Ok(l) => {
                l.enabled = on;
                Some(Event::Layers(layers(p)))
            }
            Err(e) => err(Some(id), e),
        },
        Cmd::Settings(id, v) => match p.layer_mut(id) {
            Ok(l) => l.component.set_settings(&v).err().and_then(|e| err(Some(id), e)),
            Err(e) => err(Some(id), e),
        },
        Cmd::Trace(pixel) => {
            let Some(id) = p
                .layers()
                .iter()
                .find(|l| l.component.kind() == <viz::components::rays::RaysSettings as viz::component::Settings>::KIND)
                .map(|l| l.component.id())
            else {
                return Some(Event::Error {
                    layer: None,
                    message: "immediate mode needs a rays component: add one".into(),
                });
            };
            match p.trace_ray(id, pixel) {
                Ok(Some(t)) => Some(Event::Traced { pixel: t.pixel, rays: t.rays }),
                Ok(None) => Some(Event::Error {
                    layer: Some(id),
                    message: "this source has no scene to trace (no triangles table)".into(),
                }),
                Err(e) => err(Some(id), e),
            }
        }
        Cmd::Pick(pixel) => {
            if let Err(e) = p.render() {
                return err(None, e);
            }
            match p.pick(pixel, 4) {
                Ok(picked) => Some(Event::Picked { pixel, picked }),
                Err(e) => err(None, e),
            }
        }
        Cmd::Screenshot(path) => {
            let r = p
                .snapshot(true)
                .map_err(|e| e.to_string())
                .and_then(|img| img.save(&path).map_err(|e| format!("cannot write {}: {e}", path.display())))
                .map(|_| path);
            Some(Event::Screenshot(r))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_preview_budget_follows_the_frame_time() {
        // Four times too slow: halves (the square root of the ratio, damped).
        assert_eq!(adapt_budget(200_000, 200.0), 100_000);
        // Four times faster than the target: doubles.
        assert_eq!(adapt_budget(200_000, 12.5), 400_000);
        // Bounded both ways, whatever the measurement.
        assert_eq!(adapt_budget(20_000, 10_000.0), 10_000);
        assert_eq!(adapt_budget(40_000_000, 0.0), 50_000_000);
    }
}
