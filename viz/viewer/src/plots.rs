//! Plots of the selection: how the rays a ray layer shows split by kind and by depth.

use egui::{Color32, Ui};
use egui_plot::{Bar, BarChart, Legend, Plot};

use crate::app::State;
use crate::query_service::{QueryService, Tag};

/// The SQL behind the histograms: the first shown ray layer's filters.
fn counts_sql(s: &State) -> Option<(serde_json::Value, String)> {
    let l = s.layers.iter().find(|l| l.kind == "rays" && l.enabled)?;
    let settings = s.edits.get(&l.id.0).cloned().unwrap_or_else(|| l.settings.clone());
    let rs: viz::components::rays::RaysSettings = serde_json::from_value(settings.clone()).ok()?;
    let pred = rs.predicate().ok()?;
    Some((
        settings,
        format!("SELECT kind, depth, count(*) AS n FROM rays WHERE {pred} GROUP BY kind, depth ORDER BY kind, depth"),
    ))
}

pub fn ui(ui: &mut Ui, s: &mut State, q: &mut QueryService) {
    let has_dataset = s.opened.as_ref().is_some_and(|o| o.has_dataset);
    if !has_dataset {
        ui.label("Plots need a dataset.");
        return;
    }
    let wanted = counts_sql(s);
    let stale = wanted.as_ref().map(|w| &w.0) != s.plots.for_settings.as_ref();
    ui.horizontal(|ui| {
        ui.label("Rays of the first shown ray layer, by kind and depth.");
        if (ui.button("Refresh").clicked() || stale)
            && let Some((settings, sql)) = &wanted
            && !q.is_running(&Tag::Plot)
        {
            s.plots.for_settings = Some(settings.clone());
            q.submit(Tag::Plot, sql.clone());
        }
        if q.is_running(&Tag::Plot) {
            ui.spinner();
        }
    });
    if let Some(e) = &s.plots.error {
        ui.colored_label(Color32::from_rgb(240, 90, 80), e);
    }
    let Some(c) = &s.plots.counts else { return };
    let mut by_kind: std::collections::BTreeMap<String, f64> = Default::default();
    let mut by_depth: std::collections::BTreeMap<u64, f64> = Default::default();
    for r in 0..c.rows {
        let n = c.int(r, "n").unwrap_or(0) as f64;
        *by_kind.entry(c.value(r, "kind").unwrap_or_default()).or_default() += n;
        *by_depth.entry(c.int(r, "depth").unwrap_or(0)).or_default() += n;
    }
    let h = (ui.available_height() / 2.0 - 10.0).max(80.0);
    let kind_bars: Vec<Bar> = by_kind
        .iter()
        .enumerate()
        .map(|(i, (k, n))| {
            let col = viz::components::rays::kind_color(k);
            Bar::new(i as f64, *n).name(k).fill(Color32::from_rgb(col[0], col[1], col[2]))
        })
        .collect();
    let names: Vec<String> = by_kind.keys().cloned().collect();
    Plot::new("by-kind")
        .height(h)
        .legend(Legend::default())
        .x_axis_formatter(move |m, _| names.get(m.value.round() as usize).cloned().unwrap_or_default())
        .y_axis_label("rays")
        .show(ui, |p| p.bar_chart(BarChart::new("rays by kind", kind_bars)));
    let depth_bars: Vec<Bar> = by_depth.iter().map(|(d, n)| Bar::new(*d as f64, *n)).collect();
    Plot::new("by-depth")
        .height(h)
        .x_axis_label("depth")
        .y_axis_label("rays")
        .show(ui, |p| p.bar_chart(BarChart::new("rays by depth", depth_bars).color(Color32::from_rgb(120, 170, 255))));
}
