//! Tree navigation of a ray layer (next/previous tree, trees of a pixel, ray-by-ray stepping)
//! and timers connected to those actions (the paper's animated playback: *advance tree* every
//! N ms).

use egui::Ui;

use viz::components::rays::RaysSettings;

use crate::query_service::{QueryService, Tag};
use crate::state::State;
pub use crate::state::{Action, Timer};

fn current(s: &State, id: u64) -> (Option<u64>, Option<u32>) {
    s.typed::<RaysSettings>(id).map_or((None, None), |r| (r.tree, r.ray_upto))
}

/// Performs `action` on ray component `id`.
pub fn perform(s: &mut State, q: &mut QueryService, id: u64, action: Action) {
    let (tree, upto) = current(s, id);
    match action {
        Action::NextTree | Action::PreviousTree => {
            let (op, order) = if action == Action::NextTree { (">", "ASC") } else { ("<", "DESC") };
            let filter = tree.map_or(String::new(), |t| format!(" WHERE tree_id {op} {t}"));
            q.submit(
                Tag::NextTree(id),
                format!("SELECT tree_id, ray_count FROM trees{filter} ORDER BY tree_id {order} LIMIT 1"),
            );
        }
        Action::NextRay => {
            let count = tree.and_then(|t| s.tree_rays.get(&t).copied()).unwrap_or(u32::MAX);
            let next = match upto {
                None => 0,
                Some(r) if r + 1 >= count => 0,
                Some(r) => r + 1,
            };
            s.patch(id, |r: &mut RaysSettings| r.ray_upto = Some(next));
        }
    }
}

/// Fires the timers that are due; asks for a repaint when the next one is.
pub fn tick(s: &mut State, q: &mut QueryService, ctx: &egui::Context) {
    let now = ctx.input(|i| i.time);
    let mut due = Vec::new();
    let mut next_in = f64::INFINITY;
    for (i, t) in s.timers.iter_mut().enumerate() {
        if !t.running {
            t.last = None;
            continue;
        }
        let every = (t.every_ms.max(10) as f64) / 1000.0;
        match t.last {
            None => t.last = Some(now),
            Some(l) if now - l >= every => {
                t.last = Some(now);
                t.fired += 1;
                due.push(i);
            }
            Some(l) => next_in = next_in.min(every - (now - l)),
        }
        next_in = next_in.min(every);
    }
    for i in due {
        let (c, a) = (s.timers[i].component, s.timers[i].action);
        if s.layers.iter().any(|l| l.id.0 == c) {
            perform(s, q, c, a);
        }
    }
    if next_in.is_finite() {
        ctx.request_repaint_after(std::time::Duration::from_secs_f64(next_in.max(0.005)));
    }
}

/// The timers tab.
pub fn ui(ui: &mut Ui, s: &mut State) {
    let rays: Vec<u64> = s.layers_of::<RaysSettings>();
    ui.label("Timers drive a ray component's actions: the animated playback of trees.");
    let mut remove = None;
    for (i, t) in s.timers.iter_mut().enumerate() {
        ui.horizontal(|ui| {
            ui.checkbox(&mut t.running, "running");
            egui::ComboBox::new(("timer-action", i), "action").selected_text(t.action.label()).show_ui(ui, |ui| {
                for a in Action::ALL {
                    ui.selectable_value(&mut t.action, a, a.label());
                }
            });
            ui.label("every");
            ui.add(egui::DragValue::new(&mut t.every_ms).range(10..=60_000).suffix(" ms"));
            egui::ComboBox::new(("timer-target", i), "of").selected_text(format!("rays #{}", t.component)).show_ui(
                ui,
                |ui| {
                    for r in &rays {
                        ui.selectable_value(&mut t.component, *r, format!("rays #{r}"));
                    }
                },
            );
            ui.label(format!("fired {}", t.fired));
            if ui.button("Remove").clicked() {
                remove = Some(i);
            }
        });
    }
    if let Some(i) = remove {
        s.timers.remove(i);
    }
    ui.add_enabled_ui(!rays.is_empty(), |ui| {
        if ui.button("Add timer").clicked()
            && let Some(r) = rays.first()
        {
            s.timers.push(Timer {
                every_ms: 500,
                action: Action::NextTree,
                component: *r,
                running: false,
                fired: 0,
                last: None,
            });
        }
    });
}

/// The tree navigation of a ray component's tab.
pub fn tree_navigation(ui: &mut Ui, s: &mut State, q: &mut QueryService, id: u64) {
    let (tree, upto) = current(s, id);
    let has_dataset = s.opened.as_ref().is_some_and(|o| o.has_dataset);
    ui.label(egui::RichText::new("Trees").strong());
    ui.add_enabled_ui(has_dataset, |ui| {
        ui.horizontal(|ui| {
            if ui.button("Previous tree").clicked() {
                perform(s, q, id, Action::PreviousTree);
            }
            if ui.button("Next tree").clicked() {
                perform(s, q, id, Action::NextTree);
            }
            if ui.button("All trees").clicked() {
                s.patch(id, |r: &mut RaysSettings| {
                    (r.tree, r.pixel, r.ray_upto, r.selected_tree) = (None, None, None, None);
                });
            }
            ui.label(match tree {
                Some(t) => format!("tree {t}"),
                None => "all trees".into(),
            });
        });
        ui.horizontal(|ui| {
            ui.add_enabled_ui(tree.is_some(), |ui| {
                if ui.button("First ray").clicked() {
                    s.patch(id, |r: &mut RaysSettings| r.ray_upto = Some(0));
                }
                if ui.button("Next ray").clicked() {
                    perform(s, q, id, Action::NextRay);
                }
                if ui.button("Whole tree").clicked() {
                    s.patch(id, |r: &mut RaysSettings| r.ray_upto = None);
                }
            });
            let count = tree.and_then(|t| s.tree_rays.get(&t).copied());
            ui.label(match (upto, count) {
                (Some(r), Some(c)) => format!("rays 0..={r} of {c}"),
                (Some(r), None) => format!("rays 0..={r}"),
                (None, _) => "every ray".into(),
            });
        });
    });
    ui.horizontal(|ui| {
        let key = egui::Id::unique(("pixel-entry", id));
        let mut px: [u32; 2] = ui.data_mut(|d| d.get_temp(key).unwrap_or([0, 0]));
        ui.label("trees of pixel");
        ui.add(egui::DragValue::new(&mut px[0]).prefix("x "));
        ui.add(egui::DragValue::new(&mut px[1]).prefix("y "));
        ui.data_mut(|d| d.insert_temp(key, px));
        if ui.add_enabled(has_dataset, egui::Button::new("Show")).clicked() {
            s.patch(id, |r: &mut RaysSettings| {
                (r.pixel, r.tree, r.ray_upto) = (Some(px), None, None);
            });
        }
    });
    if let Some((p, n)) = s.traced {
        ui.label(format!("immediate mode: pixel {},{} traced, {n} rays (ctrl-click another pixel)", p[0], p[1]));
    } else {
        ui.label("ctrl-click a pixel in the render window to trace its ray tree (immediate mode)");
    }
}
