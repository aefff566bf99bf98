#![doc = include_str!("../README.md")]

// The visualizer under its short name, as the rest of the workspace writes `store`, `query`.
extern crate rtvtk_viz as viz;

pub mod app;
pub mod camera_ctl;
pub mod console;
mod error;
pub mod plots;
pub mod query_service;
pub mod render_pane;
pub mod settings_ui;
pub mod state;
pub mod timers;
pub mod worker;

pub use app::{Saved, Viewer, ViewerOptions};
pub use error::{Error, Result};
pub use worker::Source;

struct App(Viewer);

impl eframe::App for App {
    fn ui(&mut self, ui: &mut egui::Ui, _frame: &mut eframe::Frame) {
        self.0.ui(ui);
    }
    fn save(&mut self, storage: &mut dyn eframe::Storage) {
        eframe::set_value(storage, app::STORAGE_KEY, &self.0.saved());
    }
}

/// Opens the viewer window (eframe, wgpu backend) and runs until it is closed.
pub fn run(options: ViewerOptions) -> Result<()> {
    let native = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default().with_inner_size([1400.0, 860.0]).with_title("rtvtk viewer"),
        renderer: eframe::Renderer::Wgpu,
        // A screenshot run must not overwrite the user's saved layout.
        persist_window: options.screenshot.is_none(),
        ..Default::default()
    };
    let screenshot = options.screenshot.is_some();
    eframe::run_native(
        "rtvtk-viewer",
        native,
        Box::new(move |cc| {
            let saved = if screenshot { None } else { cc.storage.and_then(|s| eframe::get_value(s, app::STORAGE_KEY)) };
            let v = Viewer::new(options, saved).map_err(|e| Box::new(e) as Box<dyn std::error::Error + Send + Sync>)?;
            Ok(Box::new(App(v)))
        }),
    )
    .map_err(|e| Error::Window(e.to_string()))
}
