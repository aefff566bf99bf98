//! The render window: the pipeline's last frame, camera controls, ctrl-click immediate mode,
//! click picking, resolution and screenshots.

use egui::{Color32, Ui};

use crate::camera_ctl::{self, Mode};
use crate::query_service::QueryService;
use crate::state::{Resolution, State};
use crate::worker::Cmd;

fn toolbar(ui: &mut Ui, s: &mut State) {
    ui.horizontal(|ui| {
        if ui.button("Reset camera").on_hover_text("the dataset's camera").clicked()
            && let Some(o) = &s.opened
        {
            s.camera = o.camera;
            s.cmds.push(Cmd::Camera(s.camera));
        }
        ui.selectable_value(&mut s.mode, Mode::Orbit, "Orbit")
            .on_hover_text("drag: orbit · right/middle drag or shift-drag: pan · scroll: zoom");
        ui.selectable_value(&mut s.mode, Mode::Fly, "Fly")
            .on_hover_text("drag: look around · W/A/S/D/Q/E: move · scroll: zoom");
        let label = match s.resolution {
            Resolution::Fit(f) => format!("{:.0}% of the window", f * 100.0),
            Resolution::Dataset => "the dataset's image size".into(),
        };
        egui::ComboBox::new("resolution", "resolution").selected_text(label).show_ui(ui, |ui| {
            for f in [1.0, 0.75, 0.5, 0.25] {
                ui.selectable_value(&mut s.resolution, Resolution::Fit(f), format!("{:.0}% of the window", f * 100.0));
            }
            ui.selectable_value(&mut s.resolution, Resolution::Dataset, "the dataset's image size");
        });
        if ui.button("Save picture").on_hover_text("the composited picture with legends, as PNG").clicked() {
            let n = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or_default();
            s.cmds.push(Cmd::Screenshot(std::path::PathBuf::from(format!("rtvtk-view-{n}.png"))));
        }
    });
}

/// The pipeline size for a render window of `avail` points.
fn wanted_size(s: &State, avail: egui::Vec2, ppp: f32) -> [u32; 2] {
    match s.resolution {
        Resolution::Dataset => s.opened.as_ref().map_or([512, 512], |o| o.image_size),
        Resolution::Fit(f) => {
            let w = (avail.x * ppp * f).round().clamp(16.0, 4096.0) as u32;
            let h = (avail.y * ppp * f).round().clamp(16.0, 4096.0) as u32;
            [w, h]
        }
    }
}

pub fn ui(ui: &mut Ui, s: &mut State, _q: &mut QueryService) {
    toolbar(ui, s);
    let avail = ui.available_size();
    if avail.x < 8.0 || avail.y < 8.0 {
        return;
    }
    let want = wanted_size(s, avail, ui.ctx().pixels_per_point());
    if s.opened.is_some() && want != s.requested_size && !ui.ctx().input(|i| i.pointer.any_down()) {
        s.requested_size = want;
        s.cmds.push(Cmd::Resize(want));
    }
    let (rect, resp) = ui.allocate_exact_size(avail, egui::Sense::click_and_drag());
    let painter = ui.painter_at(rect);
    painter.rect_filled(rect, 0.0, Color32::from_rgb(5, 5, 7));
    let Some(sh) = &s.shown else {
        painter.text(
            rect.center(),
            egui::Align2::CENTER_CENTER,
            if s.opening.is_some() { "opening…" } else { "nothing drawn yet" },
            egui::FontId::proportional(16.0),
            Color32::GRAY,
        );
        return;
    };
    // The frame fitted into the window, aspect kept.
    let [fw, fh] = sh.size.map(|v| v.max(1) as f32);
    let scale = (rect.width() / fw).min(rect.height() / fh);
    let img = egui::Rect::from_center_size(rect.center(), egui::vec2(fw * scale, fh * scale));
    s.image_rect = Some((img, sh.size));
    painter.image(
        sh.texture.id(),
        img,
        egui::Rect::from_min_max(egui::pos2(0.0, 0.0), egui::pos2(1.0, 1.0)),
        Color32::WHITE,
    );
    // An image traced from the view says so where it is seen: the tracer and its samples per
    // pixel as it refines (or why the GPU cannot trace here).
    let notes: Vec<&String> = s
        .layers
        .iter()
        .filter(|l| l.enabled && l.kind == <viz::components::picture::ImageSettings as viz::component::Settings>::KIND)
        .flat_map(|l| l.report.iter())
        .collect();
    for (i, n) in notes.iter().rev().enumerate() {
        painter.text(
            img.left_bottom() + egui::vec2(6.0, -6.0 - 15.0 * i as f32),
            egui::Align2::LEFT_BOTTOM,
            n.trim_start_matches("image: "),
            egui::FontId::proportional(12.0),
            Color32::from_gray(225),
        );
    }
    let to_pixel = |p: egui::Pos2| -> Option<[u32; 2]> {
        let u = (p - img.min) / img.size();
        (u.x >= 0.0 && u.y >= 0.0 && u.x < 1.0 && u.y < 1.0).then_some([(u.x * fw) as u32, (u.y * fh) as u32])
    };
    let mut cam = s.camera;
    let mut moved = false;
    let (shift, ctrl) = ui.input(|i| (i.modifiers.shift, i.modifiers.command || i.modifiers.ctrl));
    if resp.dragged_by(egui::PointerButton::Primary) && !shift {
        let d = resp.drag_delta();
        camera_ctl::rotate(&mut cam, s.mode, f64::from(d.x), f64::from(d.y));
        moved = true;
    } else if resp.dragged_by(egui::PointerButton::Secondary)
        || resp.dragged_by(egui::PointerButton::Middle)
        || (resp.dragged_by(egui::PointerButton::Primary) && shift)
    {
        let d = resp.drag_delta() / scale;
        camera_ctl::pan(&mut cam, f64::from(d.x), f64::from(d.y), f64::from(fh));
        moved = true;
    }
    if resp.hovered() {
        let scroll = ui.input(|i| i.smooth_scroll_delta.y);
        if scroll != 0.0 {
            camera_ctl::zoom(&mut cam, f64::from(scroll) / 40.0);
            moved = true;
        }
        if s.mode == Mode::Fly {
            let dt = f64::from(ui.input(|i| i.stable_dt)).min(0.1);
            let key = |k| ui.input(|i| i.key_down(k));
            let f = f64::from(key(egui::Key::W) as u8) - f64::from(key(egui::Key::S) as u8);
            let r = f64::from(key(egui::Key::D) as u8) - f64::from(key(egui::Key::A) as u8);
            let u = f64::from(key(egui::Key::E) as u8) - f64::from(key(egui::Key::Q) as u8);
            if f != 0.0 || r != 0.0 || u != 0.0 {
                camera_ctl::fly(&mut cam, f, r, u, dt * 0.5);
                moved = true;
                ui.ctx().request_repaint();
            }
        }
    }
    if moved && cam.validate().is_ok() && cam != s.camera {
        s.camera = cam;
        s.cmds.push(Cmd::Camera(cam));
    }
    if resp.clicked()
        && let Some(px) = resp.interact_pointer_pos().and_then(to_pixel)
    {
        if ctrl {
            s.cmds.push(Cmd::Trace(px));
        } else {
            s.cmds.push(Cmd::Pick(px));
        }
    }
    // Legends of the shown layers, top left over the picture.
    let legends: Vec<_> = s.layers.iter().filter(|l| l.enabled).flat_map(|l| l.legend.clone()).collect();
    let mut y = img.min.y + 6.0;
    for l in &legends {
        if let viz::Legend::Swatches { entries, .. } = l {
            for (name, c) in entries {
                let at = egui::pos2(img.min.x + 8.0, y);
                painter.rect_filled(
                    egui::Rect::from_min_size(at, egui::vec2(10.0, 10.0)),
                    2.0,
                    Color32::from_rgb(c[0], c[1], c[2]),
                );
                painter.text(
                    at + egui::vec2(14.0, -2.0),
                    egui::Align2::LEFT_TOP,
                    name,
                    egui::FontId::proportional(12.0),
                    Color32::WHITE,
                );
                y += 15.0;
            }
        }
    }
    if let Some(p) = &s.picked {
        painter.text(
            egui::pos2(img.min.x + 8.0, img.max.y - 8.0),
            egui::Align2::LEFT_BOTTOM,
            format!("picked: {}", p.item.label()),
            egui::FontId::proportional(13.0),
            Color32::from_rgb(255, 210, 90),
        );
    }
}
