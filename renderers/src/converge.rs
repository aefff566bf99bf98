//! Error against run time: how fast the path tracer converges to a high-sample reference.

use std::path::Path;
use std::time::Instant;

use crate::bvh::Bvh;
use crate::film::Film;
use crate::plot::{plot_font, tick};
use crate::render::{RenderOptions, render};
use crate::scene::Scene;
use crate::{Error, Result};

/// One measurement: error of an image rendered at `spp` samples per pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConvergencePoint {
    pub spp: u32,
    pub secs: f64,
    /// Root mean squared error over pixels and channels.
    pub rmse: f64,
    /// Mean of (x − ref)² / (ref² + 0.01).
    pub rel_mse: f64,
}

/// RMSE and relative MSE of `img` against `reference`.
pub fn image_error(img: &Film, reference: &Film) -> (f64, f64) {
    let mut se = 0.0f64;
    let mut rel = 0.0f64;
    let mut n = 0.0f64;
    for (a, b) in img.pixels.iter().zip(&reference.pixels) {
        for c in 0..3 {
            let d = f64::from(a[c]) - f64::from(b[c]);
            se += d * d;
            rel += d * d / (f64::from(b[c]).powi(2) + 0.01);
            n += 1.0;
        }
    }
    ((se / n.max(1.0)).sqrt(), rel / n.max(1.0))
}

/// Renders a reference at `reference_spp` (seed + 1000), then `spps` (each with its own seed) and
/// measures error and wall time. Returns the reference and the points.
pub fn convergence(
    scene: &Scene,
    bvh: &Bvh,
    base: &RenderOptions,
    reference_spp: u32,
    spps: &[u32],
) -> Result<(Film, Vec<ConvergencePoint>)> {
    if spps.is_empty() || spps.iter().any(|&s| s == 0 || s >= reference_spp) {
        return Err(Error::Settings(format!(
            "sample counts must be positive and below the reference's {reference_spp}"
        )));
    }
    let reference = reference(scene, bvh, base, reference_spp)?;
    let points = measure(&reference, base.seed, spps, |opts_spp, seed| {
        let opts = RenderOptions { spp: opts_spp, seed, ..base.clone() };
        render(scene, bvh, &opts, None, &|_| {}).map(|(img, _)| img)
    })?;
    Ok((reference, points))
}

/// The reference image every tracer's error is measured against: the CPU path tracer at
/// `reference_spp` with seed `base.seed + 1000` (no measured image shares its samples).
pub fn reference(scene: &Scene, bvh: &Bvh, base: &RenderOptions, reference_spp: u32) -> Result<Film> {
    let opts = RenderOptions { spp: reference_spp, seed: base.seed.wrapping_add(1000), ..base.clone() };
    Ok(render(scene, bvh, &opts, None, &|_| {})?.0)
}

/// Times `render(spp, seed)` for each of `spps` (seed `seed + i + 1` for the i-th) and measures
/// its image's error against `reference`: any tracer's convergence against the same reference.
pub fn measure<E>(
    reference: &Film,
    seed: u64,
    spps: &[u32],
    mut render: impl FnMut(u32, u64) -> std::result::Result<Film, E>,
) -> std::result::Result<Vec<ConvergencePoint>, E> {
    let mut points = Vec::new();
    for (i, &spp) in spps.iter().enumerate() {
        let t = Instant::now();
        let img = render(spp, seed.wrapping_add(i as u64 + 1))?;
        let secs = t.elapsed().as_secs_f64();
        let (rmse, rel_mse) = image_error(&img, reference);
        points.push(ConvergencePoint { spp, secs, rmse, rel_mse });
    }
    Ok(points)
}

/// Least-squares slope of log(y) against log(x).
pub fn log_log_slope(points: &[(f64, f64)]) -> f64 {
    let pts: Vec<(f64, f64)> =
        points.iter().filter(|(x, y)| *x > 0.0 && *y > 0.0).map(|(x, y)| (x.ln(), y.ln())).collect();
    let n = pts.len() as f64;
    if n < 2.0 {
        return f64::NAN;
    }
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// The colours of the curves of the i-th tracer of a plot: (RMSE, sqrt(relMSE)).
pub const CURVE_COLOURS: [([u8; 3], [u8; 3]); 3] =
    [([30, 60, 200], [200, 40, 40]), ([0, 150, 90], [230, 130, 0]), ([120, 40, 170], [140, 110, 40])];

/// Writes a log-log plot of RMSE (blue) and relative MSE's square root (red) against seconds,
/// with a grey line of slope −1/2 through the first RMSE point: axes with decade ticks and
/// values, labels and a legend (plotters).
pub fn write_plot(points: &[ConvergencePoint], path: &Path) -> Result<()> {
    write_plots(&[("", points)], path)
}

/// The same for several tracers side by side (`(name, points)`; colours `CURVE_COLOURS`, the
/// slope line through the first tracer's first point).
pub fn write_plots(tracers: &[(&str, &[ConvergencePoint])], path: &Path) -> Result<()> {
    use plotters::prelude::*;
    let bad = |e: String| Error::Image { path: path.into(), message: e };
    if tracers.is_empty() || tracers.len() > CURVE_COLOURS.len() {
        return Err(bad(format!("{} tracers: expected 1 to {}", tracers.len(), CURVE_COLOURS.len())));
    }
    let (w, h) = (800u32, 560u32);
    let font = plot_font();
    let all: Vec<&ConvergencePoint> = tracers.iter().flat_map(|(_, p)| p.iter()).collect();
    let xs: Vec<f64> = all.iter().map(|p| p.secs.max(1e-9)).collect();
    let ys: Vec<f64> = all.iter().flat_map(|p| [p.rmse.max(1e-12), p.rel_mse.max(1e-24).sqrt()]).collect();
    let decade = |v: f64, up: bool| 10f64.powf(if up { v.log10().ceil() } else { v.log10().floor() });
    let (x0, x1) = (
        decade(xs.iter().cloned().fold(f64::INFINITY, f64::min), false),
        decade(xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max), true),
    );
    let (y0, y1) = (
        decade(ys.iter().cloned().fold(f64::INFINITY, f64::min), false),
        decade(ys.iter().cloned().fold(f64::NEG_INFINITY, f64::max), true),
    );
    let (x0, x1, y0, y1) = (
        if x0.is_finite() { x0 } else { 1e-3 },
        if x1.is_finite() && x1 > x0 { x1 } else { x0 * 10.0 },
        if y0.is_finite() { y0 } else { 1e-3 },
        if y1.is_finite() && y1 > y0 { y1 } else { y0 * 10.0 },
    );
    crate::plot::png(path, (w, h), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption("Error against render time", (font, 22))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(64)
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
            .map_err(|e| bad(e.to_string()))?;
        chart
            .configure_mesh()
            .x_desc("seconds")
            .y_desc("error")
            .label_style((font, 14))
            .axis_desc_style((font, 16))
            .x_labels(12)
            .y_labels(12)
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()
            .map_err(|e| bad(e.to_string()))?;
        let mut first = None;
        for (i, (name, points)) in tracers.iter().enumerate() {
            let ([br, bg, bb], [rr, rg, rb]) = CURVE_COLOURS[i];
            let (blue, red) = (RGBColor(br, bg, bb), RGBColor(rr, rg, rb));
            let label = |what: &str| if name.is_empty() { what.to_string() } else { format!("{what}, {name}") };
            let series = |f: &dyn Fn(&ConvergencePoint) -> f64| -> Vec<(f64, f64)> {
                points.iter().map(|p| (p.secs.max(1e-9), f(p))).collect()
            };
            let rmse = series(&|p| p.rmse.max(1e-12));
            let rel = series(&|p| p.rel_mse.max(1e-24).sqrt());
            chart
                .draw_series(LineSeries::new(rmse.clone(), blue.stroke_width(2)))
                .map_err(|e| bad(e.to_string()))?
                .label(label("RMSE"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], blue.stroke_width(2)));
            chart
                .draw_series(rmse.iter().map(|&p| Circle::new(p, 3, blue.filled())))
                .map_err(|e| bad(e.to_string()))?;
            chart
                .draw_series(LineSeries::new(rel.clone(), red.stroke_width(2)))
                .map_err(|e| bad(e.to_string()))?
                .label(label("sqrt(relMSE)"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], red.stroke_width(2)));
            chart.draw_series(rel.iter().map(|&p| Circle::new(p, 3, red.filled()))).map_err(|e| bad(e.to_string()))?;
            first = first.or(rmse.first().copied());
        }
        if let Some((sx, sy)) = first {
            let grey = RGBColor(140, 140, 140);
            // From the first point to the plot's edge, or to where it leaves through the bottom.
            let end = x1.min(sx * (sy / y0).powi(2));
            let line: Vec<(f64, f64)> = [sx, end].iter().map(|&x| (x, sy * (x / sx).powf(-0.5))).collect();
            chart
                .draw_series(LineSeries::new(line, grey.stroke_width(1)))
                .map_err(|e| bad(e.to_string()))?
                .label("slope -1/2 (Monte Carlo)")
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], grey.stroke_width(1)));
        }
        chart
            .configure_series_labels()
            .label_font((font, 14))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| bad(e.to_string()))?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plot_has_text_and_curves() {
        let pts: Vec<ConvergencePoint> = [1u32, 2, 4, 8]
            .iter()
            .map(|&spp| ConvergencePoint {
                spp,
                secs: 0.01 * f64::from(spp),
                rmse: 0.5 / f64::from(spp).sqrt(),
                rel_mse: 0.2 / f64::from(spp),
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.png");
        write_plot(&pts, &p).unwrap();
        let img = image::open(&p).unwrap().to_rgb8();
        let blue = img.pixels().filter(|q| q.0 == [30, 60, 200]).count();
        let red = img.pixels().filter(|q| q.0 == [200, 40, 40]).count();
        // Dark pixels that are neither curve: text, ticks and axes.
        let ink = img.pixels().filter(|q| q.0.iter().all(|c| *c < 90)).count();
        assert!(blue > 200 && red > 200, "curves drawn: {blue} {red}");
        assert!(ink > 2000, "axes and labels drawn: {ink}");
    }
}
