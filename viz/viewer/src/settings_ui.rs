//! A component's settings (plain JSON, as every component serializes them) as widgets: booleans
//! as checkboxes, numbers as drag values, strings as text fields, arrays of numbers as rows of
//! drag values, settings with a few allowed values (`Component::choices`) as drop-downs, and
//! unset options as a field that takes any JSON value. The component checks
//! what it is given; its error is shown beside the settings and the worker keeps the old ones.

use egui::Ui;
use serde_json::Value;

/// Draws the editor; returns whether anything changed (the caller sends the new settings).
pub fn edit(ui: &mut Ui, id: egui::Id, settings: &mut Value, choices: &[(&str, &[&str])]) -> bool {
    let Value::Object(map) = settings else {
        ui.label("(no settings)");
        return false;
    };
    let mut changed = false;
    egui::Grid::new(id).num_columns(2).striped(true).show(ui, |ui| {
        for (key, value) in map.iter_mut() {
            ui.label(key.replace('_', " "));
            match choices.iter().find(|(k, _)| k == key) {
                Some((_, values)) => changed |= choice(ui, id.with(key.as_str()), value, values),
                None => changed |= field(ui, id.with(key.as_str()), value),
            }
            ui.end_row();
        }
    });
    changed
}

/// One of `values`, as a drop-down.
fn choice(ui: &mut Ui, id: egui::Id, value: &mut Value, values: &[&str]) -> bool {
    let current = value.as_str().unwrap_or_default().to_string();
    let mut changed = false;
    egui::ComboBox::from_id_salt(id).selected_text(current.clone()).show_ui(ui, |ui| {
        for v in values {
            if ui.selectable_label(current == *v, *v).clicked() && current != *v {
                *value = Value::String((*v).to_string());
                changed = true;
            }
        }
    });
    changed
}

fn field(ui: &mut Ui, id: egui::Id, value: &mut Value) -> bool {
    match value {
        Value::Bool(b) => ui.checkbox(b, "").changed(),
        Value::Number(n) => {
            if let Some(i) = n.as_u64() {
                let mut x = i;
                let r = ui.add(egui::DragValue::new(&mut x).speed(1.0)).changed();
                if r {
                    *value = Value::from(x);
                }
                r
            } else if let Some(i) = n.as_i64() {
                let mut x = i;
                let r = ui.add(egui::DragValue::new(&mut x).speed(1.0)).changed();
                if r {
                    *value = Value::from(x);
                }
                r
            } else {
                let mut x = n.as_f64().unwrap_or(0.0);
                let r = ui.add(egui::DragValue::new(&mut x).speed(0.01).max_decimals(4)).changed();
                if r {
                    *value = serde_json::Number::from_f64(x).map_or(Value::Null, Value::Number);
                }
                r
            }
        }
        Value::String(s) => {
            let multiline = s.len() > 40 || s.contains('\n');
            let r = if multiline {
                ui.add(egui::TextEdit::multiline(s).code_editor().desired_rows(3).desired_width(f32::INFINITY))
            } else {
                ui.text_edit_singleline(s)
            };
            r.lost_focus() || (r.changed() && !multiline && ui.input(|i| i.key_pressed(egui::Key::Enter)))
        }
        Value::Array(items) if items.iter().all(Value::is_number) && !items.is_empty() => {
            let (changed, unset) = ui
                .horizontal(|ui| {
                    let mut changed = false;
                    for (k, it) in items.iter_mut().enumerate() {
                        changed |= field(ui, id.with(k), it);
                    }
                    (changed, ui.small_button("unset").on_hover_text("no value (the filter is off)").clicked())
                })
                .inner;
            if unset {
                *value = Value::Null;
            }
            changed || unset
        }
        other => json_field(ui, id, other),
    }
}

/// Any value as JSON text, applied on Enter; `null` shown as "(none)".
fn json_field(ui: &mut Ui, id: egui::Id, value: &mut Value) -> bool {
    let mut text: String = ui.data_mut(|d| {
        d.get_temp::<String>(id).unwrap_or_else(|| if value.is_null() { String::new() } else { value.to_string() })
    });
    let r =
        ui.add(egui::TextEdit::singleline(&mut text).hint_text("(none) type a JSON value, Enter").desired_width(180.0));
    let mut changed = false;
    if r.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter)) {
        let t = text.trim();
        let parsed = if t.is_empty() {
            Ok(Value::Null)
        } else {
            serde_json::from_str::<Value>(t).or_else(|_| Ok::<Value, serde_json::Error>(Value::String(t.to_string())))
        };
        if let Ok(v) = parsed {
            changed = v != *value;
            *value = v;
        }
        ui.data_mut(|d| d.remove::<String>(id));
    } else if r.changed() {
        ui.data_mut(|d| d.insert_temp(id, text));
    } else if !r.has_focus() {
        ui.data_mut(|d| d.remove::<String>(id));
    }
    if !value.is_null() && ui.small_button("unset").clicked() {
        *value = Value::Null;
        changed = true;
    }
    changed
}
