//! The viewer's state: what the UI shows and edits (layout panes, layers, console, inspector,
//! plots, timers, selection), shared by the application and its panes. It imports no pane, so
//! the panes sit on top of it and the application on top of them.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};
use viz::component::{Pick, Settings};
use viz::components::rays::RaysSettings;
use viz::{ComponentId, ViewCamera};

use crate::camera_ctl::Mode;
use crate::query_service::{QueryResult, QueryService, Tag};
use crate::worker::{Cmd, LayerInfo, LayerSpec, Opened, Source};

/// A tab of the layout.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Pane {
    Render,
    Pipeline,
    Component(u64),
    Console,
    Inspector,
    Plots,
    Timers,
}

/// How big the pipeline renders, relative to the render window.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Resolution {
    /// The window's pixels times a scale (0.25 ... 1).
    Fit(f32),
    /// The dataset's image size.
    Dataset,
}

impl Default for Resolution {
    fn default() -> Self {
        Resolution::Fit(0.5)
    }
}

/// What is saved between runs (eframe storage).
#[derive(Clone, Default, Serialize, Deserialize)]
#[serde(default)]
pub struct Saved {
    pub layout: Option<egui_tiles::Tree<Pane>>,
    pub source: Option<Source>,
    pub layers: Vec<LayerSpec>,
    pub camera: Option<ViewCamera>,
    pub history: Vec<String>,
    pub timers: Vec<Timer>,
    pub resolution: Resolution,
    pub mode: Mode,
}

/// The storage key of [`Saved`].
pub const STORAGE_KEY: &str = "rtvtk-viewer";

/// The selected ray (from the console, the inspector's tree or a pick).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Selection {
    pub tree: u64,
    pub ray: u32,
}

#[derive(Default)]
pub struct ConsoleState {
    pub sql: String,
    pub history: Vec<String>,
    pub result: Option<QueryResult>,
    pub error: Option<String>,
    pub selected_row: Option<usize>,
    pub tables: Vec<String>,
    pub functions: Vec<String>,
}

#[derive(Default)]
pub struct InspectorState {
    pub fields: Option<QueryResult>,
    pub tree: Option<QueryResult>,
    pub note: Option<String>,
    pub error: Option<String>,
}

#[derive(Default)]
pub struct PlotState {
    pub counts: Option<QueryResult>,
    pub error: Option<String>,
    pub for_settings: Option<serde_json::Value>,
}

/// The last frame the worker delivered.
/// The texture the render window shows.
pub enum ShownTexture {
    /// Uploaded by egui from read-back RGBA.
    Egui(egui::TextureHandle),
    /// The pipeline's output texture on the window's device, registered with egui-wgpu once.
    Native { id: egui::TextureId, texture: wgpu::Texture },
}

impl ShownTexture {
    pub fn id(&self) -> egui::TextureId {
        match self {
            ShownTexture::Egui(h) => h.id(),
            ShownTexture::Native { id, .. } => *id,
        }
    }
}

pub struct Shown {
    pub texture: ShownTexture,
    pub size: [u32; 2],
    pub ms: f64,
    pub frames: u64,
}

/// Everything the panes read and change (the tile tree is kept apart, to be drawn with it).
pub struct State {
    pub sources: Vec<Source>,
    pub opened: Option<Opened>,
    pub opening: Option<Source>,
    pub layers: Vec<LayerInfo>,
    /// Settings as edited in the component tabs (sent on change).
    pub edits: HashMap<u64, serde_json::Value>,
    pub layer_errors: HashMap<u64, String>,
    pub messages: Vec<(bool, String)>,
    pub shown: Option<Shown>,
    pub camera: ViewCamera,
    pub mode: Mode,
    pub resolution: Resolution,
    pub requested_size: [u32; 2],
    pub console: ConsoleState,
    pub inspector: InspectorState,
    pub plots: PlotState,
    pub timers: Vec<Timer>,
    pub selection: Option<Selection>,
    pub picked: Option<Pick>,
    pub tree_rays: HashMap<u64, u32>,
    pub traced: Option<([u32; 2], usize)>,
    pub next_id: u64,
    pub open_path: String,
    pub cmds: Vec<Cmd>,
    pub saved_layers: Option<Vec<LayerSpec>>,
    pub saved_camera: Option<ViewCamera>,
    /// Where the last frame was drawn and its size (pointer to pixel).
    pub image_rect: Option<(egui::Rect, [u32; 2])>,
    pub status_rect: Option<egui::Rect>,
    pub top_rect: Option<egui::Rect>,
}

impl State {
    pub fn error(&mut self, m: impl Into<String>) {
        self.messages.push((true, m.into()));
    }
    pub fn info(&mut self, m: impl Into<String>) {
        self.messages.push((false, m.into()));
    }
    fn rays_layers(&self) -> Vec<u64> {
        self.layers_of::<RaysSettings>()
    }
    /// The components of the kind whose settings are `S`, bottom to top.
    pub(crate) fn layers_of<S: Settings>(&self) -> Vec<u64> {
        self.layers.iter().filter(|l| l.kind == S::KIND).map(|l| l.id.0).collect()
    }
    /// Component `id`'s settings as its kind's type (`None`: no such component, or another kind).
    pub(crate) fn typed<S: Settings>(&self, id: u64) -> Option<S> {
        let kind = &self.layers.iter().find(|l| l.id.0 == id)?.kind;
        if kind != S::KIND {
            return None;
        }
        S::decode(&self.settings_of(id)?).ok()
    }
    pub(crate) fn settings_of(&self, id: u64) -> Option<serde_json::Value> {
        self.edits.get(&id).cloned().or_else(|| self.layers.iter().find(|l| l.id.0 == id).map(|l| l.settings.clone()))
    }
    /// Changes component `id`'s settings, typed (`S` is its kind's settings: a component of
    /// another kind is left alone and the UI says so), and sends them.
    pub fn patch<S: Settings>(&mut self, id: u64, f: impl FnOnce(&mut S)) {
        let Some(mut s) = self.typed::<S>(id) else {
            self.error(format!("component #{id} is not a {} component", S::KIND));
            return;
        };
        f(&mut s);
        let v = s.encode();
        self.edits.insert(id, v.clone());
        self.cmds.push(Cmd::Settings(ComponentId(id), v));
    }
    pub(crate) fn has_dataset(&self) -> bool {
        self.opened.as_ref().is_some_and(|o| o.has_dataset)
    }
}

/// An action a timer (or a button) performs on a ray layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Action {
    NextTree,
    PreviousTree,
    /// One more ray of the shown tree (back to the first after the last).
    NextRay,
}

impl Action {
    pub const ALL: [Action; 3] = [Action::NextTree, Action::PreviousTree, Action::NextRay];
    pub fn label(self) -> &'static str {
        match self {
            Action::NextTree => "advance tree",
            Action::PreviousTree => "previous tree",
            Action::NextRay => "advance ray",
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Timer {
    pub every_ms: u64,
    pub action: Action,
    /// The ray component it drives.
    pub component: u64,
    pub running: bool,
    /// Times it fired.
    #[serde(skip)]
    pub fired: u64,
    #[serde(skip)]
    pub last: Option<f64>,
}

/// Selects a ray: highlights its tree in the ray layers and loads it into the inspector.
pub fn select(s: &mut State, q: &mut QueryService, sel: Selection) {
    s.selection = Some(sel);
    for id in s.rays_layers() {
        s.patch(id, |r: &mut RaysSettings| r.selected_tree = Some(sel.tree));
    }
    s.inspector.note = Some(format!("ray {} of tree {}", sel.ray, sel.tree));
    if s.has_dataset() {
        let tree = store::RaySelection::all().only_trees_of(Some(sel.tree), None, None);
        let ray = tree.clone().only(store::scene::col::RAY, [(u64::from(sel.ray), u64::from(sel.ray))]);
        q.submit(Tag::Inspect, format!("SELECT * FROM rays WHERE {}", ray.to_sql()));
        q.submit(
            Tag::InspectTree,
            format!("SELECT ray, parent, depth, kind, t FROM rays WHERE {} ORDER BY ray", tree.to_sql()),
        );
    }
}
