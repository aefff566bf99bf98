//! The viewer application: a render window over the pipeline's picture, a tab per component,
//! the SQL console, the inspector, plots and timers, laid out in `egui_tiles`.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use egui::{Color32, RichText, Ui};
use viz::component::{Picked, Settings};
use viz::components::query::QuerySettings;
use viz::components::rays::RaysSettings;
use viz::{Legend, ViewCamera};

use crate::query_service::{QueryService, Tag};
pub use crate::state::{
    ConsoleState, InspectorState, Pane, PlotState, Resolution, STORAGE_KEY, Saved, Selection, Shown, ShownTexture,
    State, select,
};
use crate::worker::{Cmd, Event, LayerInfo, LayerSpec, Pixels, Service, Source, Worker};

/// How the viewer starts.
#[derive(Clone, Debug, Default)]
pub struct ViewerOptions {
    /// Datasets (and scenes) to choose from; the first is opened.
    pub sources: Vec<Source>,
    /// Run the console against an `rtvtk serve` service: `grpc://HOST:PORT` (or `http://`).
    pub connect: Option<String>,
    pub token: Option<String>,
    /// Ignore the saved layout.
    pub reset_layout: bool,
    /// Take a screenshot of the window once everything is drawn, write it here, and close.
    pub screenshot: Option<PathBuf>,
    /// The default layers trace with the GPU path tracer (image and Ctrl-click).
    pub tracer: renderers::TracerChoice,
    /// Draw `Source::Served` datasets from this engine, already open in the process (the Python
    /// package's `session.view()`), instead of connecting to `connect`.
    pub engine: Option<Arc<query::Engine>>,
}

/// Wakes the UI from other threads (set once the UI's context is known).
#[derive(Clone, Default)]
pub struct Waker(Arc<Mutex<Option<egui::Context>>>);

impl Waker {
    pub fn wake(&self) {
        if let Some(c) = self.0.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
            c.request_repaint();
        }
    }
    fn set(&self, ctx: &egui::Context) {
        let mut g = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if g.is_none() {
            *g = Some(ctx.clone());
        }
    }
}

pub struct Viewer {
    pub state: State,
    pub tree: egui_tiles::Tree<Pane>,
    pub worker: Worker,
    pub queries: QueryService,
    waker: Waker,
    options: ViewerOptions,
    screenshot_asked: bool,
    settled_frames: u32,
    /// The window's render state, where frames are drawn from the pipeline's output texture.
    display: Option<egui_wgpu::RenderState>,
}

/// The pipeline's output texture `t` as egui draws it: registered with egui-wgpu once, the
/// registration pointed at a new texture when the size changed, nothing to do for the same one
/// (egui samples what the render worker drew last).
fn native_texture(rs: &egui_wgpu::RenderState, shown: Option<&ShownTexture>, t: wgpu::Texture) -> ShownTexture {
    let view = t.create_view(&Default::default());
    let mut r = rs.renderer.write();
    let id = match shown {
        Some(ShownTexture::Native { id, texture }) if *texture == t => *id,
        Some(ShownTexture::Native { id, .. }) => {
            r.update_egui_texture_from_wgpu_texture(&rs.device, &view, wgpu::FilterMode::Linear, *id);
            *id
        }
        _ => r.register_native_texture(&rs.device, &view, wgpu::FilterMode::Linear),
    };
    ShownTexture::Native { id, texture: t }
}

fn default_tree() -> egui_tiles::Tree<Pane> {
    let mut tiles = egui_tiles::Tiles::default();
    let render = tiles.insert_pane(Pane::Render);
    let pipeline = tiles.insert_pane(Pane::Pipeline);
    let timers = tiles.insert_pane(Pane::Timers);
    let components = tiles.insert_tab_tile(vec![pipeline, timers]);
    let console = tiles.insert_pane(Pane::Console);
    let inspector = tiles.insert_pane(Pane::Inspector);
    let plots = tiles.insert_pane(Pane::Plots);
    let bottom = tiles.insert_tab_tile(vec![console, inspector, plots]);
    let right = tiles.insert_vertical_tile(vec![components, bottom]);
    let root = tiles.insert_horizontal_tile(vec![render, right]);
    if let Some(egui_tiles::Tile::Container(c)) = tiles.get_mut(root)
        && let egui_tiles::Container::Linear(l) = c
    {
        l.shares.set_share(render, 1.6);
    }
    egui_tiles::Tree::new(egui::Id::unique("rtvtk-layout"), root, tiles)
}

impl Viewer {
    /// A viewer over `options.sources`, restoring what `saved` holds; its frames cross to the UI
    /// as RGBA (the UI may draw on another device, as egui_kittest's does).
    pub fn new(options: ViewerOptions, saved: Option<Saved>) -> crate::Result<Viewer> {
        Viewer::with_display(options, saved, None)
    }

    /// The same in a window drawn on the process's GPU device (`display`, eframe's render
    /// state, already shared through `rtvtk_gpu::Gpu::share`): frames stay on the GPU, sampled
    /// by egui from the pipeline's output texture.
    pub fn with_display(
        options: ViewerOptions,
        saved: Option<Saved>,
        display: Option<egui_wgpu::RenderState>,
    ) -> crate::Result<Viewer> {
        let waker = Waker::default();
        let w = waker.clone();
        let wake: Arc<dyn Fn() + Send + Sync> = Arc::new(move || w.wake());
        let service = match (&options.engine, &options.connect) {
            (Some(e), _) => Some(Service::Engine(e.clone())),
            (None, Some(url)) => Some(Service::Remote { url: url.clone(), token: options.token.clone() }),
            (None, None) => None,
        };
        let worker = Worker::spawn(wake.clone(), options.tracer, display.is_some(), service);
        let queries = QueryService::new(wake)?;
        let saved = saved.unwrap_or_default();
        let mut tree = saved.layout.clone().filter(|_| !options.reset_layout).unwrap_or_else(default_tree);
        if tree.tiles.find_pane(&Pane::Render).is_none() {
            tree = default_tree();
        }
        let first = options.sources.first().cloned();
        let same_source = first.is_some() && saved.source == first;
        let state = State {
            sources: options.sources.clone(),
            opened: None,
            opening: None,
            layers: Vec::new(),
            edits: HashMap::new(),
            layer_errors: HashMap::new(),
            messages: Vec::new(),
            shown: None,
            camera: ViewCamera { position: [0.0, 0.0, -5.0], target: [0.0; 3], up: [0.0, 1.0, 0.0], fov_y: 40.0 },
            mode: saved.mode,
            resolution: saved.resolution,
            requested_size: [0, 0],
            console: ConsoleState { history: saved.history.clone(), ..Default::default() },
            inspector: InspectorState::default(),
            plots: PlotState::default(),
            timers: saved.timers.clone(),
            selection: None,
            picked: None,
            tree_rays: HashMap::new(),
            traced: None,
            next_id: 1,
            open_path: String::new(),
            cmds: Vec::new(),
            saved_layers: same_source.then(|| saved.layers.clone()),
            saved_camera: if same_source { saved.camera } else { None },
            image_rect: None,
            status_rect: None,
            top_rect: None,
        };
        let mut v = Viewer {
            state,
            tree,
            worker,
            queries,
            waker,
            options,
            screenshot_asked: false,
            settled_frames: 0,
            display,
        };
        match first {
            Some(s) => v.open(s),
            None => v.state.info("nothing to show yet: open a dataset or a scene (top bar)"),
        }
        Ok(v)
    }

    /// Opens a source, keeping the current components (or the saved ones at start).
    pub fn open(&mut self, source: Source) {
        let specs = match self.state.saved_layers.take() {
            Some(s) => s,
            None => self.state.layers.iter().map(LayerInfo::spec).collect(),
        };
        self.state.opening = Some(source.clone());
        self.queries.connecting = true;
        let others = self
            .state
            .sources
            .iter()
            .filter_map(|s| match s {
                Source::Dataset(p) if Some(s) != Some(&source) => Some(p.clone()),
                _ => None,
            })
            .collect();
        self.worker.send(Cmd::Open(source, specs, others));
    }

    /// What to save (eframe storage).
    pub fn saved(&self) -> Saved {
        Saved {
            layout: Some(self.tree.clone()),
            source: self.state.opened.as_ref().map(|o| o.source.clone()),
            layers: self.state.layers.iter().map(LayerInfo::spec).collect(),
            camera: Some(self.state.camera),
            history: self.state.console.history.clone(),
            timers: self.state.timers.clone(),
            resolution: self.state.resolution,
            mode: self.state.mode,
        }
    }

    /// Whether the worker and the queries have nothing left to do (tests wait for it).
    pub fn settled(&self) -> bool {
        !self.worker.busy()
            && self.state.opening.is_none()
            && !self.queries.connecting
            && [Tag::Console, Tag::Inspect, Tag::InspectTree, Tag::Plot].iter().all(|t| !self.queries.is_running(t))
    }

    fn handle_events(&mut self, ctx: &egui::Context) {
        for e in self.worker.poll() {
            let s = &mut self.state;
            match e {
                Event::Opened(o) => {
                    self.queries.set_engine(o.engine.clone());
                    s.camera = s.saved_camera.take().unwrap_or(o.camera);
                    s.cmds.push(Cmd::Camera(s.camera));
                    for m in &o.missing {
                        s.info(format!("{}: {m}", o.name));
                    }
                    s.info(format!("opened {}", o.source.label()));
                    s.opening = None;
                    s.requested_size = [0, 0];
                    s.opened = Some(o);
                }
                Event::OpenFailed { source, message } => {
                    s.opening = None;
                    self.queries.connecting = false;
                    s.error(format!("cannot open {}: {message}", source.label()));
                }
                Event::Frame(f) => self.show_frame(ctx, f),
                Event::Layers(l) => {
                    for info in &l {
                        s.next_id = s.next_id.max(info.id.0 + 1);
                        // An edit the worker has taken is no longer pending.
                        if s.edits.get(&info.id.0) == Some(&info.settings) {
                            s.edits.remove(&info.id.0);
                            s.layer_errors.remove(&info.id.0);
                        }
                    }
                    s.layers = l;
                }
                Event::Error { layer, message } => match layer {
                    Some(id) => {
                        s.layer_errors.insert(id.0, message.clone());
                        s.edits.remove(&id.0);
                        s.error(format!("component {}: {message}", id.0));
                    }
                    None => s.error(message),
                },
                Event::Traced { pixel, rays } => {
                    s.traced = Some((pixel, rays));
                    s.info(format!("traced pixel {},{}: {rays} rays (immediate mode)", pixel[0], pixel[1]));
                }
                Event::Picked { pixel, picked } => self.picked(pixel, picked),
                Event::Screenshot(r) => match r {
                    Ok(p) => s.info(format!("wrote {}", p.display())),
                    Err(e) => s.error(e),
                },
            }
        }
        self.handle_query_results();
    }

    /// A frame from the worker on screen: its texture (the pipeline's own, or RGBA8 uploaded).
    fn show_frame(&mut self, ctx: &egui::Context, f: crate::worker::Rendered) {
        let s = &mut self.state;
        let texture = match (f.pixels, &self.display) {
            (Pixels::Texture(t), Some(rs)) => native_texture(rs, s.shown.as_ref().map(|sh| &sh.texture), t),
            (Pixels::Texture(_), None) => {
                s.error("a frame came as a GPU texture, but this UI has no GPU device to draw it");
                return;
            }
            (Pixels::Rgba(rgba), _) => {
                let img = egui::ColorImage::from_rgba_unmultiplied([f.size[0] as usize, f.size[1] as usize], &rgba);
                match s.shown.as_mut().map(|sh| &mut sh.texture) {
                    Some(ShownTexture::Egui(h)) => {
                        h.set(img, egui::TextureOptions::LINEAR);
                        ShownTexture::Egui(h.clone())
                    }
                    _ => ShownTexture::Egui(ctx.load_texture("pipeline", img, egui::TextureOptions::LINEAR)),
                }
            }
        };
        let frames = s.shown.as_ref().map_or(0, |sh| sh.frames) + 1;
        s.shown = Some(Shown { texture, size: f.size, ms: f.ms, frames });
    }

    /// What a click picked: a ray selects its tree, a node or a row is inspected.
    fn picked(&mut self, pixel: [u32; 2], picked: Option<viz::component::Pick>) {
        let s = &mut self.state;
        match picked {
            Some(p) => {
                let label = p.item.label();
                s.info(format!("picked {label} at {},{}", pixel[0], pixel[1]));
                match p.item {
                    Picked::Ray { tree, ray } => select(s, &mut self.queries, Selection { tree, ray }),
                    Picked::Traced { .. } => s.inspector.note = Some(label),
                    Picked::Node { node } => {
                        s.inspector.note = Some(label);
                        self.queries.submit(Tag::Inspect, format!("SELECT * FROM bvh_nodes WHERE node_id = {node}"));
                        s.inspector.tree = None;
                    }
                    Picked::Row { row } => {
                        s.console.selected_row = Some(row as usize);
                        s.inspector.note = Some(label);
                    }
                }
                s.picked = Some(p);
            }
            None => {
                s.picked = None;
                s.info(format!("nothing to pick at {},{}", pixel[0], pixel[1]));
            }
        }
    }

    /// The answers of the query tasks, each into its pane.
    fn handle_query_results(&mut self) {
        for r in self.queries.poll() {
            let s = &mut self.state;
            match (r.tag, r.result) {
                (Tag::Catalog, Ok(_)) => {
                    let (t, f) = self.queries.catalog();
                    s.console.tables = t;
                    s.console.functions = f;
                }
                (Tag::Catalog, Err(e)) => s.console.error = Some(e),
                (Tag::Console, Ok(q)) => {
                    s.console.error = None;
                    s.console.selected_row = None;
                    s.console.result = Some(q);
                }
                (Tag::Console, Err(e)) => s.console.error = Some(e),
                (Tag::Inspect, Ok(q)) => {
                    s.inspector.error = None;
                    s.inspector.fields = Some(q);
                }
                (Tag::InspectTree, Ok(q)) => s.inspector.tree = Some(q),
                (Tag::Inspect | Tag::InspectTree, Err(e)) => s.inspector.error = Some(e),
                (Tag::Plot, Ok(q)) => {
                    s.plots.error = None;
                    s.plots.counts = Some(q);
                }
                (Tag::Plot, Err(e)) => s.plots.error = Some(e),
                (Tag::NextTree(id), Ok(q)) => match (q.int(0, "tree_id"), q.int(0, "ray_count")) {
                    (Some(tree), count) => {
                        if let Some(c) = count {
                            s.tree_rays.insert(tree, c as u32);
                        }
                        s.patch(id, |r: &mut RaysSettings| {
                            (r.tree, r.selected_tree, r.pixel, r.ray_upto) = (Some(tree), Some(tree), None, None);
                        });
                    }
                    (None, _) => s.info("no further tree in that direction"),
                },
                (Tag::NextTree(_), Err(e)) => s.error(e),
            }
        }
    }

    /// The whole UI, into `ui` (the window's, or a test harness's).
    pub fn ui(&mut self, ui: &mut Ui) {
        let ctx = ui.ctx().clone();
        self.waker.set(&ctx);
        self.handle_events(&ctx);
        crate::timers::tick(&mut self.state, &mut self.queries, &ctx);

        let r = egui::Panel::top("top").show(ui, |ui| self.top_bar(ui));
        self.state.top_rect = Some(r.response.rect);
        let r = egui::Panel::bottom("status").show(ui, |ui| status_bar(ui, &self.state, &self.worker));
        self.state.status_rect = Some(r.response.rect);
        egui::CentralPanel::default().show(ui, |ui| {
            let mut b = Tabs { s: &mut self.state, q: &mut self.queries };
            self.tree.ui(&mut b, ui);
        });
        self.sync_panes();
        for c in std::mem::take(&mut self.state.cmds) {
            self.worker.send(c);
        }
        self.screenshot(&ctx);
        if self.worker.busy() || self.queries.connecting || self.worker.progress.get().is_some() {
            ctx.request_repaint_after(std::time::Duration::from_millis(100));
        }
    }

    fn top_bar(&mut self, ui: &mut Ui) {
        ui.horizontal(|ui| {
            ui.strong("rtvtk");
            let current =
                self.state.opened.as_ref().map(|o| o.source.label()).unwrap_or_else(|| "(nothing open)".into());
            let mut chosen = None;
            egui::ComboBox::new("source", "source").selected_text(current).show_ui(ui, |ui| {
                for s in &self.state.sources {
                    if ui.selectable_label(false, s.label()).clicked() {
                        chosen = Some(s.clone());
                    }
                }
            });
            ui.label("open:");
            let r = ui.add(
                egui::TextEdit::singleline(&mut self.state.open_path)
                    .hint_text("dataset directory, or cornell / scene.obj")
                    .desired_width(260.0),
            );
            if (r.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter))) || ui.button("Open").clicked() {
                let p = self.state.open_path.trim().to_string();
                if !p.is_empty() {
                    let path = PathBuf::from(&p);
                    let src = if path.is_dir() { Source::Dataset(path) } else { Source::Scene(p) };
                    if !self.state.sources.contains(&src) {
                        self.state.sources.push(src.clone());
                    }
                    chosen = Some(src);
                }
            }
            if let Some(s) = chosen {
                self.open(s);
            }
            if ui.button("Reset layout").clicked() {
                self.tree = default_tree();
            }
            if self.state.opening.is_some() {
                ui.spinner();
                ui.label("opening…");
            }
        });
    }

    /// A tab for every component; tabs of removed components go.
    fn sync_panes(&mut self) {
        let ids: Vec<u64> = self.state.layers.iter().map(|l| l.id.0).collect();
        let stale: Vec<egui_tiles::TileId> = self
            .tree
            .tiles
            .iter()
            .filter_map(|(tid, t)| match t {
                egui_tiles::Tile::Pane(Pane::Component(id)) if !ids.contains(id) => Some(*tid),
                _ => None,
            })
            .collect();
        for t in stale {
            self.tree.remove_recursively(t);
        }
        for id in ids {
            if self.tree.tiles.find_pane(&Pane::Component(id)).is_some() {
                continue;
            }
            let pane = self.tree.tiles.insert_pane(Pane::Component(id));
            let parent = self
                .tree
                .tiles
                .find_pane(&Pane::Pipeline)
                .and_then(|p| self.tree.tiles.parent_of(p))
                .or(self.tree.root);
            if let Some(parent) = parent
                && let Some(egui_tiles::Tile::Container(c)) = self.tree.tiles.get_mut(parent)
            {
                c.add_child(pane);
            }
        }
    }

    /// `--screenshot`: once the pipeline has drawn and nothing is pending, a screenshot of the
    /// window is written and the window closes.
    fn screenshot(&mut self, ctx: &egui::Context) {
        let Some(path) = self.options.screenshot.clone() else { return };
        let ready = self.state.shown.is_some() && self.settled();
        self.settled_frames = if ready { self.settled_frames + 1 } else { 0 };
        if self.settled_frames > 5 && !self.screenshot_asked {
            self.screenshot_asked = true;
            let c = ctx.clone();
            ctx.request_screenshot(move |image| {
                let [w, h] = image.size;
                let bytes: Vec<u8> = image.pixels.iter().flat_map(|p| p.to_array()).collect();
                let r = image::RgbaImage::from_raw(w as u32, h as u32, bytes)
                    .ok_or_else(|| "a screenshot of the wrong size".to_string())
                    .and_then(|img| img.save(&path).map_err(|e| e.to_string()));
                match r {
                    Ok(()) => eprintln!("wrote {}", path.display()),
                    Err(e) => eprintln!("cannot write {}: {e}", path.display()),
                }
                c.send_viewport_cmd(egui::ViewportCommand::Close);
                c.request_repaint();
            });
        }
        ctx.request_repaint_after(std::time::Duration::from_millis(50));
    }
}

fn status_bar(ui: &mut Ui, s: &State, w: &Worker) {
    ui.horizontal(|ui| {
        if w.busy() {
            ui.spinner();
        }
        // A long load (millions of rays): how far it got, and a way out that keeps what it has.
        if let Some((what, done, total)) = w.progress.get() {
            let f = done as f32 / total as f32;
            ui.add(
                egui::ProgressBar::new(f).desired_width(160.0).text(format!("{what}: {:.0} % of {total}", f * 100.0)),
            );
            if ui.button("Cancel load").on_hover_text("stop loading; the rays loaded so far stay").clicked() {
                w.progress.cancel();
            }
            ui.separator();
        }
        if let Some(sh) = &s.shown {
            ui.label(format!("{}x{} · last frame {:.0} ms · {} frames", sh.size[0], sh.size[1], sh.ms, sh.frames));
        }
        ui.separator();
        if let Some((err, m)) = s.messages.last() {
            let t = RichText::new(m);
            ui.label(if *err { t.color(Color32::from_rgb(240, 90, 80)) } else { t });
        }
        if !s.messages.is_empty() {
            ui.menu_button(format!("messages ({})", s.messages.len()), |ui| {
                egui::ScrollArea::vertical().max_height(300.0).show(ui, |ui| {
                    for (err, m) in s.messages.iter().rev() {
                        let t = RichText::new(m);
                        ui.label(if *err { t.color(Color32::from_rgb(240, 90, 80)) } else { t });
                    }
                });
            });
        }
    });
}

/// The tile behaviour: one function per pane.
pub struct Tabs<'a> {
    pub s: &'a mut State,
    pub q: &'a mut QueryService,
}

impl egui_tiles::Behavior<Pane> for Tabs<'_> {
    fn tab_title_for_pane(&mut self, pane: &Pane) -> egui::WidgetText {
        match pane {
            Pane::Render => "Render".into(),
            Pane::Pipeline => "Pipeline".into(),
            Pane::Component(id) => match self.s.layers.iter().find(|l| l.id.0 == *id) {
                Some(l) => format!("#{id} {}", l.name).into(),
                None => format!("component #{id}").into(),
            },
            Pane::Console => "SQL console".into(),
            Pane::Inspector => "Inspector".into(),
            Pane::Plots => "Plots".into(),
            Pane::Timers => "Timers".into(),
        }
    }

    fn pane_ui(&mut self, ui: &mut Ui, _tile: egui_tiles::TileId, pane: &mut Pane) -> egui_tiles::UiResponse {
        match pane {
            Pane::Render => crate::render_pane::ui(ui, self.s, self.q),
            Pane::Pipeline => egui::ScrollArea::vertical().show(ui, |ui| pipeline_ui(ui, self.s)).inner,
            Pane::Component(id) => {
                let id = *id;
                egui::ScrollArea::vertical().show(ui, |ui| component_ui(ui, self.s, self.q, id)).inner
            }
            Pane::Console => crate::console::ui(ui, self.s, self.q),
            Pane::Inspector => {
                egui::ScrollArea::vertical().show(ui, |ui| crate::console::inspector_ui(ui, self.s, self.q)).inner
            }
            Pane::Plots => crate::plots::ui(ui, self.s, self.q),
            Pane::Timers => crate::timers::ui(ui, self.s),
        }
        egui_tiles::UiResponse::None
    }

    fn retain_pane(&mut self, pane: &Pane) -> bool {
        match pane {
            // Components not (yet) in the pipeline keep their tab until the pipeline is known.
            Pane::Component(id) => self.s.opened.is_none() || self.s.layers.iter().any(|l| l.id.0 == *id),
            _ => true,
        }
    }

    fn simplification_options(&self) -> egui_tiles::SimplificationOptions {
        egui_tiles::SimplificationOptions { all_panes_must_have_tabs: true, ..Default::default() }
    }
}

/// The pipeline tab: components bottom to top, shown or hidden, moved, removed, added.
fn pipeline_ui(ui: &mut Ui, s: &mut State) {
    ui.label("Components, drawn bottom (first) to top (last):");
    let n = s.layers.len();
    let mut cmds = Vec::new();
    for (i, l) in s.layers.iter().enumerate() {
        ui.horizontal(|ui| {
            let mut on = l.enabled;
            if ui.checkbox(&mut on, format!("{} #{}", l.name, l.id.0)).on_hover_text("show or hide").changed() {
                cmds.push(Cmd::Enable(l.id, on));
            }
            if ui.add_enabled(i > 0, egui::Button::new("Down")).on_hover_text("draw earlier (below)").clicked() {
                cmds.push(Cmd::Reorder(l.id, i - 1));
            }
            if ui.add_enabled(i + 1 < n, egui::Button::new("Up")).on_hover_text("draw later (above)").clicked() {
                cmds.push(Cmd::Reorder(l.id, i + 1));
            }
            if ui.button("Remove").clicked() {
                cmds.push(Cmd::Remove(l.id));
            }
        });
    }
    s.cmds.extend(cmds);
    ui.separator();
    ui.label("Add a component:");
    let offers = s.opened.as_ref().map(|o| o.offers.clone()).unwrap_or_default();
    ui.horizontal_wrapped(|ui| {
        for o in offers {
            let b = ui.add_enabled(o.available.is_ok(), egui::Button::new(format!("Add {}", o.kind)));
            let b = match &o.available {
                Ok(()) => b.on_hover_text(format!("{}: {}", o.name, o.description)),
                Err(why) => b.on_disabled_hover_text(format!("{}: not available: {why}", o.name)),
            };
            if b.clicked() {
                let id = s.next_id;
                s.next_id += 1;
                let settings = if o.kind == QuerySettings::KIND {
                    QuerySettings {
                        sql: "SELECT origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t, depth FROM rays WHERE kind = 'shadow' LIMIT 10000".into(),
                        colour_by: Some("depth".into()),
                        ..Default::default()
                    }
                    .encode()
                } else {
                    serde_json::Value::Null
                };
                s.cmds.push(Cmd::Add(LayerSpec { id, kind: o.kind.into(), settings, enabled: true }));
            }
        }
    });
}

fn legend_ui(ui: &mut Ui, legend: &[Legend]) {
    for l in legend {
        match l {
            Legend::Swatches { title, entries } => {
                ui.label(RichText::new(title).strong());
                ui.horizontal_wrapped(|ui| {
                    for (name, c) in entries {
                        let (r, _) = ui.allocate_exact_size(egui::vec2(12.0, 12.0), egui::Sense::hover());
                        ui.painter().rect_filled(r, 2.0, Color32::from_rgba_unmultiplied(c[0], c[1], c[2], c[3]));
                        ui.label(name);
                    }
                });
            }
            Legend::ColourBar { title, map, min, max, log } => {
                use rtvtk_viz::legend::{bar_position, colour_map, label, ticks};
                ui.label(RichText::new(title).strong());
                let grad = colour_map(map).ok();
                let rgb = |t: f64| {
                    grad.as_ref().map_or(Color32::GRAY, |g| {
                        let c = g.eval_continuous(t);
                        Color32::from_rgb(c.r, c.g, c.b)
                    })
                };
                if max <= min {
                    ui.horizontal(|ui| {
                        let (r, _) = ui.allocate_exact_size(egui::vec2(12.0, 12.0), egui::Sense::hover());
                        ui.painter().rect_filled(r, 2.0, rgb(0.5));
                        ui.label(label(*min));
                    });
                    continue;
                }
                let width = ui.available_width().clamp(80.0, 260.0);
                let (r, _) = ui.allocate_exact_size(egui::vec2(width, 28.0), egui::Sense::hover());
                let bar = egui::Rect::from_min_size(r.min, egui::vec2(width, 10.0));
                let steps = 64;
                for i in 0..steps {
                    let t = (i as f64 + 0.5) / steps as f64;
                    let x0 = bar.min.x + bar.width() * i as f32 / steps as f32;
                    let x1 = bar.min.x + bar.width() * (i + 1) as f32 / steps as f32;
                    let cell = egui::Rect::from_min_max(egui::pos2(x0, bar.min.y), egui::pos2(x1, bar.max.y));
                    ui.painter().rect_filled(cell, 0.0, rgb(t));
                }
                for v in ticks(*min, *max, *log) {
                    let x = bar.min.x + bar.width() * bar_position(v, *min, *max, *log) as f32;
                    ui.painter().vline(x, bar.max.y..=bar.max.y + 3.0, egui::Stroke::new(1.0, Color32::WHITE));
                    ui.painter().text(
                        egui::pos2(x, bar.max.y + 3.0),
                        egui::Align2::CENTER_TOP,
                        label(v),
                        egui::FontId::proportional(10.0),
                        Color32::LIGHT_GRAY,
                    );
                }
            }
        }
    }
}

/// A component's tab: shown or not, its report, its legend, its settings, and for ray layers the
/// tree navigation.
fn component_ui(ui: &mut Ui, s: &mut State, q: &mut QueryService, id: u64) {
    let Some(l) = s.layers.iter().find(|l| l.id.0 == id).cloned() else {
        ui.label("this component is not in the pipeline");
        return;
    };
    ui.horizontal(|ui| {
        let mut on = l.enabled;
        if ui.checkbox(&mut on, "shown").changed() {
            s.cmds.push(Cmd::Enable(l.id, on));
        }
        if ui.button("Remove").clicked() {
            s.cmds.push(Cmd::Remove(l.id));
        }
        ui.label(format!("rendered {} times", l.renders));
    });
    for r in &l.report {
        ui.label(RichText::new(r).small());
    }
    legend_ui(ui, &l.legend);
    if let Some(e) = s.layer_errors.get(&id) {
        ui.colored_label(Color32::from_rgb(240, 90, 80), e);
    }
    if let Some(extra) = crate::component_ui::of(&l.kind) {
        ui.separator();
        (extra.extras)(ui, s, q, id);
    }
    ui.separator();
    ui.label(RichText::new("Settings").strong());
    let mut v = s.settings_of(id).unwrap_or(serde_json::Value::Null);
    if crate::settings_ui::edit(ui, egui::Id::unique(("settings", id)), &mut v, &l.choices) {
        s.edits.insert(id, v.clone());
        s.cmds.push(Cmd::Settings(l.id, v));
    }
}
