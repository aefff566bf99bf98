//! Plots: the convergence of the progressive image (estimated error against render time), and
//! how the rays a ray layer shows split by kind and by depth.

use egui::{Color32, Ui};
use egui_plot::{Bar, BarChart, Legend, Line, LineStyle, Plot, PlotPoints};

use crate::query_service::{QueryService, Tag};
use crate::state::State;

/// The SQL behind the histograms: the first shown ray layer's filters.
fn counts_sql(s: &State) -> Option<(serde_json::Value, String)> {
    let l = s
        .layers
        .iter()
        .find(|l| l.kind == <viz::components::rays::RaysSettings as viz::component::Settings>::KIND && l.enabled)?;
    let settings = s.edits.get(&l.id.0).cloned().unwrap_or_else(|| l.settings.clone());
    let rs: viz::components::rays::RaysSettings = serde_json::from_value(settings.clone()).ok()?;
    let pred = rs.predicate().ok()?;
    Some((
        settings,
        format!("SELECT kind, depth, count(*) AS n FROM rays WHERE {pred} GROUP BY kind, depth ORDER BY kind, depth"),
    ))
}

/// Log-log plot of the first traced image layer's estimated RMSE against render time, with a
/// line of slope −1/2 (Monte Carlo) through its first point. Returns whether it drew one.
fn convergence_ui(ui: &mut Ui, s: &State, height: f32) -> bool {
    let Some(l) = s.layers.iter().find(|l| l.enabled && l.convergence.len() >= 2) else { return false };
    let pts: Vec<[f64; 2]> = l
        .convergence
        .iter()
        .filter(|c| c.rmse > 0.0 && c.secs > 0.0)
        .map(|c| [c.secs.log10(), c.rmse.log10()])
        .collect();
    let (Some(first), Some(last)) = (pts.first().copied(), l.convergence.last()) else { return false };
    ui.label(format!(
        "Convergence of the progressive image: {} samples per pixel in {:.2} s; error estimated from the \
         even- and odd-sample halves (no reference), log–log.",
        last.spp, last.secs
    ));
    let x_end = pts.last().map_or(first[0], |p| p[0]);
    let slope = vec![first, [x_end, first[1] - 0.5 * (x_end - first[0])]];
    let decimal = |v: f64| renderers::plot::tick(10f64.powf(v));
    Plot::new("convergence")
        .height(height)
        .legend(Legend::default())
        .x_axis_label("render time, s")
        .y_axis_label("estimated RMSE")
        .x_axis_formatter(move |m, _| decimal(m.value))
        .y_axis_formatter(move |m, _| decimal(m.value))
        .show(ui, |p| {
            p.line(Line::new("estimated RMSE", PlotPoints::from(pts)).color(Color32::from_rgb(90, 150, 255)));
            p.line(
                Line::new("slope −1/2 (Monte Carlo)", PlotPoints::from(slope))
                    .color(Color32::GRAY)
                    .style(LineStyle::dashed_loose()),
            );
        });
    true
}

pub fn ui(ui: &mut Ui, s: &mut State, q: &mut QueryService) {
    let has_dataset = s.opened.as_ref().is_some_and(|o| o.has_dataset);
    let converging = s.layers.iter().any(|l| l.enabled && l.convergence.len() >= 2);
    let parts: f32 = if has_dataset { 2.0 } else { 0.0 } + if converging { 1.0 } else { 0.0 };
    let plot_h = (ui.available_height() / parts.max(1.0) - 24.0).max(80.0);
    let drew = convergence_ui(ui, s, plot_h);
    if !has_dataset {
        if !drew {
            ui.label(
                "Plots need a dataset (rays by kind and depth) or an image layer tracing progressively \
                 (its convergence curve).",
            );
        }
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
    let h = plot_h;
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
