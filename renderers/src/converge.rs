//! Error against run time: how fast the path tracer converges to a high-sample reference.

use std::path::Path;
use std::time::Instant;

use crate::bvh::Bvh;
use crate::choice::TracerChoice;
use crate::film::Film;
use crate::plot::{plot_font, tick};
use crate::render::{RenderOptions, render};
use crate::scene::Scene;
use crate::{Error, Result};

/// One measurement: error of an image rendered at `spp` samples per pixel, timed over `runs`
/// renders (the same image each time).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ConvergencePoint {
    pub spp: u32,
    /// Median wall time of the runs.
    pub secs: f64,
    /// Fastest and slowest run.
    pub secs_min: f64,
    pub secs_max: f64,
    pub runs: u32,
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
    let points = measure(&reference, base.seed, spps, 1, |opts_spp, seed| {
        let opts = RenderOptions { spp: opts_spp, seed, ..base.clone() };
        render(scene, bvh, TracerChoice::Path, &opts, None, &|_| {}).map(|(img, _)| img)
    })?;
    Ok((reference, points))
}

/// The reference image every tracer's error is measured against: the CPU path tracer at
/// `reference_spp` with seed `base.seed + 1000` (no measured image shares its samples).
pub fn reference(scene: &Scene, bvh: &Bvh, base: &RenderOptions, reference_spp: u32) -> Result<Film> {
    let opts = RenderOptions { spp: reference_spp, seed: base.seed.wrapping_add(1000), ..base.clone() };
    Ok(render(scene, bvh, TracerChoice::Path, &opts, None, &|_| {})?.0)
}

/// Times `render(spp, seed)` `runs` times for each of `spps` (seed `seed + i + 1` for the i-th,
/// the same each run, so every run makes the same image) and measures the image's error against
/// `reference`: any tracer's convergence against the same reference, with the median time and
/// the spread of the runs (one timing alone is at the mercy of the machine: 4 spp once took
/// 0.042 s and 8 spp 0.033 s).
pub fn measure<E>(
    reference: &Film,
    seed: u64,
    spps: &[u32],
    runs: u32,
    mut render: impl FnMut(u32, u64) -> std::result::Result<Film, E>,
) -> std::result::Result<Vec<ConvergencePoint>, E> {
    let runs = runs.max(1);
    let mut points = Vec::new();
    for (i, &spp) in spps.iter().enumerate() {
        let mut times = Vec::with_capacity(runs as usize);
        let mut error = None;
        for _ in 0..runs {
            let t = Instant::now();
            let img = render(spp, seed.wrapping_add(i as u64 + 1))?;
            times.push(t.elapsed().as_secs_f64());
            if error.is_none() {
                error = Some(image_error(&img, reference));
            }
        }
        times.sort_by(f64::total_cmp);
        let (rmse, rel_mse) = error.unwrap_or((f64::NAN, f64::NAN));
        points.push(ConvergencePoint {
            spp,
            secs: median(&times),
            secs_min: times[0],
            secs_max: times[times.len() - 1],
            runs,
            rmse,
            rel_mse,
        });
    }
    Ok(points)
}

/// The median of sorted values.
fn median(sorted: &[f64]) -> f64 {
    let n = sorted.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 { sorted[n / 2] } else { 0.5 * (sorted[n / 2 - 1] + sorted[n / 2]) }
}

/// A least-squares line through log(y) against log(x): its slope and the half-width of the
/// slope's 95% confidence interval (Student's t with n − 2 degrees of freedom; NaN with fewer
/// than 3 points).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogLogFit {
    pub slope: f64,
    pub ci95: f64,
    pub points: usize,
}

impl std::fmt::Display for LogLogFit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.ci95.is_finite() {
            write!(f, "{:.3} ± {:.3}", self.slope, self.ci95)
        } else {
            write!(f, "{:.3}", self.slope)
        }
    }
}

/// The 0.975 quantile of Student's t with `dof` degrees of freedom.
fn t975(dof: usize) -> f64 {
    const T: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
        2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042,
    ];
    match dof {
        0 => f64::NAN,
        d if d <= T.len() => T[d - 1],
        _ => 1.96,
    }
}

/// The least-squares fit of log(y) against log(x), with the slope's 95% confidence interval.
pub fn log_log_fit(points: &[(f64, f64)]) -> LogLogFit {
    let pts: Vec<(f64, f64)> =
        points.iter().filter(|(x, y)| *x > 0.0 && *y > 0.0).map(|(x, y)| (x.ln(), y.ln())).collect();
    let n = pts.len();
    if n < 2 {
        return LogLogFit { slope: f64::NAN, ci95: f64::NAN, points: n };
    }
    let nf = n as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / nf;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / nf;
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let slope = sxy / sxx;
    let ci95 = if n > 2 {
        let rss: f64 = pts.iter().map(|p| (p.1 - my - slope * (p.0 - mx)).powi(2)).sum();
        t975(n - 2) * (rss / (nf - 2.0) / sxx).sqrt()
    } else {
        f64::NAN
    };
    LogLogFit { slope, ci95, points: n }
}

/// Least-squares slope of log(y) against log(x).
pub fn log_log_slope(points: &[(f64, f64)]) -> f64 {
    log_log_fit(points).slope
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
            // The spread of the runs' times: a bar from the fastest to the slowest at each point.
            for (f, colour) in [
                (&(|p: &ConvergencePoint| p.rmse.max(1e-12)) as &dyn Fn(&ConvergencePoint) -> f64, blue),
                (&|p: &ConvergencePoint| p.rel_mse.max(1e-24).sqrt(), red),
            ] {
                chart
                    .draw_series(points.iter().filter(|p| p.secs_max > p.secs_min).map(|p| {
                        let y = f(p);
                        PathElement::new([(p.secs_min.max(1e-9), y), (p.secs_max.max(1e-9), y)], colour.stroke_width(1))
                    }))
                    .map_err(|e| bad(e.to_string()))?;
            }
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
                secs_min: 0.009 * f64::from(spp),
                secs_max: 0.012 * f64::from(spp),
                runs: 3,
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

    #[test]
    fn the_fit_gives_the_slope_and_an_interval_that_holds_it() {
        // An exact power law: the slope, and no width.
        let exact: Vec<(f64, f64)> = [1.0f64, 2.0, 4.0, 8.0, 16.0].iter().map(|&x| (x, 3.0 * x.powf(-0.5))).collect();
        let f = log_log_fit(&exact);
        assert!((f.slope + 0.5).abs() < 1e-12 && f.ci95 < 1e-9 && f.points == 5, "{f:?}");
        // Noisy: multiplicative noise of a few percent; the interval holds -1/2 and is narrow.
        let noise = [1.03, 0.97, 1.05, 0.96, 1.02, 0.99, 1.04, 0.98];
        let noisy: Vec<(f64, f64)> =
            (0..8).map(|i| 2f64.powi(i)).zip(noise).map(|(x, k)| (x, k * x.powf(-0.5))).collect();
        let f = log_log_fit(&noisy);
        assert!((f.slope + 0.5).abs() <= f.ci95 && f.ci95 < 0.05, "{f:?}");
        // Two points: a slope, no interval; one: nothing.
        assert!(log_log_fit(&exact[..2]).ci95.is_nan());
        assert!(log_log_fit(&exact[..1]).slope.is_nan());
        assert_eq!(format!("{}", LogLogFit { slope: -0.5, ci95: 0.01, points: 5 }), "-0.500 ± 0.010");
    }

    #[test]
    fn each_point_is_timed_over_its_runs_with_one_image() {
        let reference = Film::new(2, 2);
        let mut calls = Vec::new();
        let points = measure(&reference, 7, &[1, 4], 3, |spp, seed| {
            calls.push((spp, seed));
            Ok::<_, ()>(Film::new(2, 2))
        })
        .unwrap();
        assert_eq!(calls, vec![(1, 8), (1, 8), (1, 8), (4, 9), (4, 9), (4, 9)]);
        for p in &points {
            assert_eq!(p.runs, 3);
            assert!(p.secs_min <= p.secs && p.secs <= p.secs_max);
            assert_eq!(p.rmse, 0.0);
        }
    }
}
