#![doc = include_str!("../README.md")]

// The visualizer under its short name, as the rest of the workspace writes `store`, `query`.
extern crate rtvtk_viz as viz;

pub mod app;
pub mod camera_ctl;
pub mod component_ui;
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

use std::sync::Arc;

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
    // The window's device is the process's one GPU device: chosen and described as
    // `rtvtk_gpu` chooses every device (Vulkan before GL, the adapter's own limits), and handed to
    // the render worker and the GPU tracer (`Gpu::share`) when the app is created.
    let mut setup = egui_wgpu::WgpuSetupCreateNew::without_display_handle();
    setup.native_adapter_selector =
        Some(Arc::new(|adapters: &[wgpu::Adapter], surface: Option<&wgpu::Surface<'_>>| {
            rtvtk_gpu::ranked(adapters.to_vec())
                .into_iter()
                .find(|a| surface.is_none_or(|s| a.is_surface_supported(s)))
                .ok_or_else(|| format!("no GPU adapter can draw into the window; {}", rtvtk_gpu::INSTALL_HINT))
        }));
    setup.device_descriptor = Arc::new(rtvtk_gpu::device_descriptor);
    let native = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default().with_inner_size([1400.0, 860.0]).with_title("rtvtk viewer"),
        renderer: eframe::Renderer::Wgpu,
        wgpu_options: egui_wgpu::WgpuConfiguration {
            wgpu_setup: egui_wgpu::WgpuSetup::CreateNew(setup),
            ..Default::default()
        },
        // A screenshot run must not overwrite the user's saved layout.
        persist_window: options.screenshot.is_none(),
        ..Default::default()
    };
    let screenshot = options.screenshot.is_some();
    eframe::run_native(
        "rtvtk-viewer",
        native,
        Box::new(move |cc| {
            if let Some(rs) = &cc.wgpu_render_state {
                rtvtk_gpu::Gpu::share(rtvtk_gpu::Gpu::from_device(&rs.adapter, rs.device.clone(), rs.queue.clone()));
            }
            let saved = if screenshot { None } else { cc.storage.and_then(|s| eframe::get_value(s, app::STORAGE_KEY)) };
            let v = Viewer::with_display(options, saved, cc.wgpu_render_state.clone())
                .map_err(|e| Box::new(e) as Box<dyn std::error::Error + Send + Sync>)?;
            Ok(Box::new(App(v)))
        }),
    )
    .map_err(|e| Error::Window(e.to_string()))
}
