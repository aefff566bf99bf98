//! Error against run time: how fast the path tracer converges to a high-sample reference.

use std::path::Path;
use std::time::Instant;

use crate::bvh::Bvh;
use crate::film::Film;
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
    let reference_opts = RenderOptions { spp: reference_spp, seed: base.seed.wrapping_add(1000), ..base.clone() };
    let (reference, _) = render(scene, bvh, &reference_opts, None, &|_| {})?;
    let mut points = Vec::new();
    for (i, &spp) in spps.iter().enumerate() {
        let opts = RenderOptions { spp, seed: base.seed.wrapping_add(i as u64 + 1), ..base.clone() };
        let t = Instant::now();
        let (img, _) = render(scene, bvh, &opts, None, &|_| {})?;
        let secs = t.elapsed().as_secs_f64();
        let (rmse, rel_mse) = image_error(&img, &reference);
        points.push(ConvergencePoint { spp, secs, rmse, rel_mse });
    }
    Ok((reference, points))
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

/// Writes a log-log plot of RMSE (blue) and relative MSE's square root (red) against time, with a
/// grey line of slope −1/2 through the first RMSE point. Axes span whole decades, gridlines at each.
pub fn write_plot(points: &[ConvergencePoint], path: &Path) -> Result<()> {
    let (w, h, m) = (640u32, 480u32, 40u32);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let xs: Vec<f64> = points.iter().map(|p| p.secs.max(1e-9).log10()).collect();
    let ys: Vec<f64> =
        points.iter().flat_map(|p| [p.rmse.max(1e-12).log10(), p.rel_mse.max(1e-24).sqrt().log10()]).collect();
    let (x0, x1) = (
        xs.iter().cloned().fold(f64::INFINITY, f64::min).floor(),
        xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max).ceil(),
    );
    let (y0, y1) = (
        ys.iter().cloned().fold(f64::INFINITY, f64::min).floor(),
        ys.iter().cloned().fold(f64::NEG_INFINITY, f64::max).ceil(),
    );
    let (x1, y1) = (if x1 <= x0 { x0 + 1.0 } else { x1 }, if y1 <= y0 { y0 + 1.0 } else { y1 });
    let px = |x: f64| m as f64 + (x - x0) / (x1 - x0) * f64::from(w - 2 * m);
    let py = |y: f64| f64::from(h - m) - (y - y0) / (y1 - y0) * f64::from(h - 2 * m);
    let put = |img: &mut image::RgbImage, x: f64, y: f64, c: [u8; 3]| {
        if x >= 0.0 && y >= 0.0 && (x as u32) < w && (y as u32) < h {
            img.put_pixel(x as u32, y as u32, image::Rgb(c));
        }
    };
    let grey = [200, 200, 200];
    for d in (x0 as i32)..=(x1 as i32) {
        for y in m..h - m {
            put(&mut img, px(f64::from(d)), f64::from(y), grey);
        }
    }
    for d in (y0 as i32)..=(y1 as i32) {
        for x in m..w - m {
            put(&mut img, f64::from(x), py(f64::from(d)), grey);
        }
    }
    let line = |img: &mut image::RgbImage, a: (f64, f64), b: (f64, f64), c: [u8; 3]| {
        let steps = 400;
        for i in 0..=steps {
            let t = f64::from(i) / f64::from(steps);
            let (x, y) = (a.0 + (b.0 - a.0) * t, a.1 + (b.1 - a.1) * t);
            if y >= y0 && y <= y1 {
                for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)] {
                    put(img, px(x) + dx, py(y) + dy, c);
                }
            }
        }
    };
    if let Some(first) = points.first() {
        let (lx, ly) = (first.secs.max(1e-9).log10(), first.rmse.max(1e-12).log10());
        line(&mut img, (lx, ly), (x1, ly - 0.5 * (x1 - lx)), [150, 150, 150]);
    }
    for pair in points.windows(2) {
        let f = |p: &ConvergencePoint| (p.secs.max(1e-9).log10(), p.rmse.max(1e-12).log10());
        let g = |p: &ConvergencePoint| (p.secs.max(1e-9).log10(), p.rel_mse.max(1e-24).sqrt().log10());
        line(&mut img, f(&pair[0]), f(&pair[1]), [30, 60, 200]);
        line(&mut img, g(&pair[0]), g(&pair[1]), [200, 40, 40]);
    }
    img.save(path).map_err(|e| Error::Image { path: path.into(), message: e.to_string() })
}
