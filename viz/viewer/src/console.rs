//! The SQL console (query, history, tables and functions, virtualized result table, draw with
//! the query layer, row selection) and the inspector of the selected ray.

use egui::{Color32, RichText, Ui};
use egui_extras::{Column, TableBuilder};

use crate::query_service::{QueryResult, QueryService, Tag};
use crate::state::{Selection, State, select};
use viz::component::Settings;
use viz::components::query::QuerySettings;

use crate::worker::{Cmd, LayerSpec};

const HISTORY: usize = 200;

/// Runs the console's query.
pub fn run(s: &mut State, q: &mut QueryService) {
    let sql = s.console.sql.trim().to_string();
    if sql.is_empty() {
        return;
    }
    s.console.history.retain(|h| h != &sql);
    s.console.history.push(sql.clone());
    if s.console.history.len() > HISTORY {
        s.console.history.remove(0);
    }
    s.console.error = None;
    q.submit(Tag::Console, sql);
}

pub fn ui(ui: &mut Ui, s: &mut State, q: &mut QueryService) {
    let running = q.is_running(&Tag::Console);
    let ed = egui::TextEdit::multiline(&mut s.console.sql)
        .code_editor()
        .desired_rows(3)
        .desired_width(f32::INFINITY)
        .hint_text("SELECT kind, count(*) FROM rays GROUP BY kind   (Ctrl+Enter runs)");
    let r = ui.add(ed);
    let run_key = r.has_focus() && ui.input(|i| i.modifiers.command && i.key_pressed(egui::Key::Enter));
    ui.horizontal(|ui| {
        if (ui.add_enabled(!running, egui::Button::new("Run")).clicked() || run_key) && !running {
            run(s, q);
        }
        if running {
            ui.spinner();
            if ui.button("Cancel").clicked() {
                q.cancel(&Tag::Console);
                s.console.error = Some("cancelled".into());
            }
        }
        let mut pick = None;
        egui::ComboBox::new("history", "history").selected_text("previous queries").width(90.0).show_ui(ui, |ui| {
            for h in s.console.history.iter().rev() {
                let line: String = h.chars().take(80).collect();
                if ui.selectable_label(false, line).clicked() {
                    pick = Some(h.clone());
                }
            }
        });
        if let Some(h) = pick {
            s.console.sql = h;
        }
        let drawable = s.console.result.as_ref().is_some_and(drawable);
        if ui
            .add_enabled(drawable, egui::Button::new("Draw"))
            .on_hover_text("draw the result's rows with a query layer (needs origin/dir columns, or x, y, z)")
            .on_disabled_hover_text("the result needs origin_x..dir_z (and t) or x, y, z columns to be drawn")
            .clicked()
            && let Some(r) = &s.console.result
        {
            draw(s, r.sql.clone());
        }
        if let Some(r) = &s.console.result {
            ui.label(format!(
                "{} rows in {:.3} s{}",
                r.rows,
                r.secs,
                if r.truncated { format!(" (first {} kept)", crate::query_service::MAX_ROWS) } else { String::new() }
            ));
        }
    });
    if let Some(e) = &s.console.error {
        ui.colored_label(Color32::from_rgb(240, 90, 80), e);
    }
    egui::CollapsingHeader::new("Tables and functions").default_open(false).show(ui, |ui| {
        ui.label(RichText::new("tables").strong());
        ui.horizontal_wrapped(|ui| {
            for t in &s.console.tables {
                if ui.small_button(t).clicked() {
                    s.console.sql = format!("SELECT * FROM {t} LIMIT 100");
                }
            }
        });
        ui.label(RichText::new("functions").strong());
        egui::ScrollArea::vertical().id_salt("functions").max_height(80.0).show(ui, |ui| {
            ui.horizontal_wrapped(|ui| {
                for f in &s.console.functions {
                    ui.label(RichText::new(f).monospace().small());
                }
            });
        });
    });
    ui.separator();
    let Some(result) = s.console.result.take() else { return };
    if let Some(row) = table(ui, &result, s.console.selected_row) {
        s.console.selected_row = Some(row);
        if let (Some(tree), Some(ray)) = (result.int(row, "tree_id"), result.int(row, "ray")) {
            select(s, q, Selection { tree, ray: ray as u32 });
        } else if let Some(tree) = result.int(row, "tree_id") {
            select(s, q, Selection { tree, ray: 0 });
        }
    }
    s.console.result = Some(result);
}

fn drawable(r: &QueryResult) -> bool {
    let has = |c: &[&str]| c.iter().all(|n| r.schema.index_of(n).is_ok());
    has(&["origin_x", "origin_y", "origin_z", "dir_x", "dir_y", "dir_z"]) || has(&["x", "y", "z"])
}

/// Adds a query layer drawing `sql` (or points the first query layer at it).
pub fn draw(s: &mut State, sql: String) {
    let colour =
        ["depth", "kind"].into_iter().find(|c| s.console.result.as_ref().is_some_and(|r| r.schema.index_of(c).is_ok()));
    let colour = colour.map(String::from);
    match s.layers_of::<QuerySettings>().first().copied() {
        Some(id) => s.patch(id, |q: &mut QuerySettings| (q.sql, q.colour_by) = (sql, colour)),
        None => {
            let id = s.next_id;
            s.next_id += 1;
            let settings = QuerySettings { sql, colour_by: colour, ..Default::default() }.encode();
            s.cmds.push(Cmd::Add(LayerSpec { id, kind: QuerySettings::KIND.into(), settings, enabled: true }));
        }
    }
}

/// The result as a virtualized table (only the visible rows are laid out); returns a clicked row.
pub fn table(ui: &mut Ui, r: &QueryResult, selected: Option<usize>) -> Option<usize> {
    let cols = r.schema.fields().len();
    if cols == 0 {
        ui.label("(no columns)");
        return None;
    }
    let mut clicked = None;
    let h = ui.text_style_height(&egui::TextStyle::Monospace) + 4.0;
    egui::ScrollArea::horizontal().id_salt("result-h").show(ui, |ui| {
        TableBuilder::new(ui)
            .id_salt("result")
            .striped(true)
            .resizable(true)
            .sense(egui::Sense::click())
            .columns(Column::auto().at_least(60.0).clip(true), cols)
            .header(h + 2.0, |mut header| {
                for f in r.schema.fields() {
                    header.col(|ui| {
                        ui.strong(f.name()).on_hover_text(f.data_type().to_string());
                    });
                }
            })
            .body(|body| {
                body.rows(h, r.rows, |mut row| {
                    let i = row.index();
                    row.set_selected(selected == Some(i));
                    if let Some((b, k)) = r.locate(i) {
                        for c in b.columns() {
                            row.col(|ui| {
                                let text =
                                    arrow::util::display::ArrayFormatter::try_new(c.as_ref(), &Default::default())
                                        .map(|f| f.value(k).to_string())
                                        .unwrap_or_else(|e| e.to_string());
                                // Not selectable: a click on a cell is a click on its row.
                                ui.add(egui::Label::new(RichText::new(text).monospace()).selectable(false));
                            });
                        }
                    }
                    if row.response().clicked() {
                        clicked = Some(i);
                    }
                });
            });
    });
    clicked
}

/// The inspector: the selected ray's fields (payload and path included) and its tree as an
/// indented list; clicking a ray of the tree selects it.
pub fn inspector_ui(ui: &mut Ui, s: &mut State, q: &mut QueryService) {
    if let Some(n) = &s.inspector.note {
        ui.label(RichText::new(n).strong());
    } else {
        ui.label("Select a ray: click a console row, a ray in the render window, or a ray of a tree below.");
    }
    if let Some(e) = &s.inspector.error {
        ui.colored_label(Color32::from_rgb(240, 90, 80), e);
    }
    if let Some(f) = &s.inspector.fields {
        if f.rows == 0 {
            ui.label("(no such row)");
        }
        egui::Grid::new("fields").striped(true).num_columns(2).show(ui, |ui| {
            for field in f.schema.fields() {
                ui.label(field.name());
                ui.label(RichText::new(f.value(0, field.name()).unwrap_or_default()).monospace());
                ui.end_row();
            }
        });
        // The recording site's source line, when the file is at hand (`record --sites`).
        if let Some(site) = f.value(0, store::scene::SITE_COLUMN).filter(|v| !v.is_empty())
            && let Some(line) = source_line(&site)
        {
            ui.label(RichText::new(format!("{site}\n  {line}")).monospace().color(Color32::from_rgb(150, 200, 255)))
                .on_hover_text("the line of the renderer that added this ray");
        }
    }
    let mut chosen = None;
    if let (Some(t), Some(sel)) = (&s.inspector.tree, s.selection) {
        ui.separator();
        ui.label(RichText::new(format!("tree {} ({} rays)", sel.tree, t.rows)).strong());
        for row in 0..t.rows.min(10_000) {
            let depth = t.int(row, "depth").unwrap_or(0) as f32;
            let ray = t.int(row, "ray").unwrap_or(0) as u32;
            let kind = t.value(row, "kind").unwrap_or_default();
            let tv = t.value(row, "t").filter(|v| !v.is_empty()).unwrap_or_else(|| "miss".into());
            ui.horizontal(|ui| {
                ui.add_space(depth * 14.0);
                let c = viz::components::rays::kind_color(&kind);
                let text =
                    RichText::new(format!("ray {ray} · {kind} · t = {tv}")).color(Color32::from_rgb(c[0], c[1], c[2]));
                if ui.selectable_label(sel.ray == ray, text).clicked() {
                    chosen = Some(Selection { tree: sel.tree, ray });
                }
            });
        }
    }
    if let Some(c) = chosen {
        select(s, q, c);
    }
}

/// The text of a recording site's line (`file:line function`), read from the file when it is at
/// hand (a path relative to the working directory, as Rust's `file!()` gives, or absolute);
/// files are read once.
pub fn source_line(site: &str) -> Option<String> {
    use std::collections::HashMap;
    thread_local! {
        static FILES: std::cell::RefCell<HashMap<String, Option<Vec<String>>>> = std::cell::RefCell::new(HashMap::new());
    }
    let place = site.split(' ').next()?;
    let (file, line) = place.rsplit_once(':')?;
    let line: usize = line.parse().ok()?;
    FILES.with(|files| {
        let mut files = files.borrow_mut();
        let lines = files
            .entry(file.to_string())
            .or_insert_with(|| std::fs::read_to_string(file).ok().map(|t| t.lines().map(str::to_string).collect()));
        lines.as_ref()?.get(line.checked_sub(1)?).map(|l| l.trim().to_string())
    })
}

#[cfg(test)]
mod tests {
    use super::source_line;

    #[test]
    fn a_sites_source_line_is_read_when_the_file_is_at_hand() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("tracer.rs");
        std::fs::write(&f, "fn a() {}\n    let shadow = trace(o, d);\n").unwrap();
        let site = format!("{}:2 trace_path", f.display());
        assert_eq!(source_line(&site).as_deref(), Some("let shadow = trace(o, d);"));
        assert_eq!(source_line(&format!("{}:9", f.display())), None, "past the end");
        assert_eq!(source_line("nowhere.rs:1"), None, "no such file");
        assert_eq!(source_line("garbage"), None);
    }
}
