//! Colour maps, and the legends and colour bars drawn onto a rendered picture (text rasterized
//! on the CPU with egui's own font, so figures need no system fonts).

use ab_glyph::{Font, FontRef, PxScale, ScaleFont};

use crate::component::Legend;
use crate::{Error, Result};

/// The colour maps by name (`greys`: black to white, the density style's brightness).
pub const COLOUR_MAPS: [&str; 7] = ["viridis", "magma", "inferno", "plasma", "turbo", "cividis", "greys"];

/// A colour map: a colorous gradient, or the black-to-white ramp.
#[derive(Clone, Copy)]
pub struct ColourMap(Option<colorous::Gradient>);

impl std::fmt::Debug for ColourMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let c = self.eval_continuous(0.5);
        write!(f, "ColourMap(mid {:?})", [c.r, c.g, c.b])
    }
}

impl ColourMap {
    /// The colour at `t` in 0..1.
    pub fn eval_continuous(&self, t: f64) -> colorous::Color {
        match self.0 {
            Some(g) => g.eval_continuous(t.clamp(0.0, 1.0)),
            None => {
                let v = (t.clamp(0.0, 1.0) * 255.0).round() as u8;
                colorous::Color { r: v, g: v, b: v }
            }
        }
    }
}

/// A colour map by name, or an error listing the known ones.
pub fn colour_map(name: &str) -> Result<ColourMap> {
    Ok(ColourMap(Some(match name {
        "viridis" => colorous::VIRIDIS,
        "magma" => colorous::MAGMA,
        "inferno" => colorous::INFERNO,
        "plasma" => colorous::PLASMA,
        "turbo" => colorous::TURBO,
        "cividis" => colorous::CIVIDIS,
        "greys" => return Ok(ColourMap(None)),
        _ => {
            return Err(Error::Settings(format!(
                "unknown colour map {name:?}: expected one of {}",
                COLOUR_MAPS.join(", ")
            )));
        }
    })))
}

/// Where `v` sits on a colour bar from `min` to `max` (0..1), on a log scale when `log`.
pub fn bar_position(v: f64, min: f64, max: f64, log: bool) -> f64 {
    if max <= min {
        return 0.5;
    }
    if log && min > 0.0 && v > 0.0 {
        return ((v.ln() - min.ln()) / (max.ln() - min.ln())).clamp(0.0, 1.0);
    }
    ((v - min) / (max - min)).clamp(0.0, 1.0)
}

/// Tick values of a colour bar from `min` to `max`: the ends and round values between them
/// (powers of ten on a log scale; steps of 1, 2 or 5 times a power of ten otherwise), each
/// labelled differently from its neighbours, at least a sixth of the bar apart (a label's
/// height on the drawn bar).
pub fn ticks(min: f64, max: f64, log: bool) -> Vec<f64> {
    if !(min.is_finite() && max.is_finite()) || max <= min {
        return vec![min];
    }
    let mut inner = Vec::new();
    if log && min > 0.0 {
        let mut p = 10f64.powf(min.log10().ceil());
        while p < max {
            inner.push(p);
            p *= 10.0;
        }
    } else {
        let raw = (max - min) / 5.0;
        let mag = 10f64.powf(raw.log10().floor());
        let step = [1.0, 2.0, 5.0, 10.0].into_iter().map(|k| k * mag).find(|s| *s >= raw).unwrap_or(10.0 * mag);
        let mut v = (min / step).ceil() * step;
        while v < max {
            inner.push(v);
            v += step;
        }
    }
    let mut out = vec![min];
    for v in inner.into_iter().chain([max]) {
        let far_enough = |a: f64| (bar_position(v, min, max, log) - bar_position(a, min, max, log)).abs() >= 1.0 / 6.0;
        if out.last().is_some_and(|&a| label(a) != label(v) && far_enough(a)) {
            out.push(v);
        } else if v == max {
            // The end always shows: it replaces a neighbour too close to it.
            if out.len() > 1 {
                out.pop();
            }
            if out.last().is_some_and(|&a| label(a) != label(v)) {
                out.push(v);
            }
        }
    }
    out
}

/// An RGBA8 picture being annotated.
pub struct Canvas<'a> {
    pub rgba: &'a mut [u8],
    pub width: u32,
    pub height: u32,
}

impl Canvas<'_> {
    fn blend(&mut self, x: i64, y: i64, c: [u8; 3], a: f32) {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) || a <= 0.0 {
            return;
        }
        let i = (y as usize * self.width as usize + x as usize) * 4;
        for (k, &ck) in c.iter().enumerate() {
            let d = f32::from(self.rgba[i + k]);
            self.rgba[i + k] = (d + (f32::from(ck) - d) * a.min(1.0)).round() as u8;
        }
        self.rgba[i + 3] = 255;
    }

    pub fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, c: [u8; 3], a: f32) {
        for yy in y..y + h {
            for xx in x..x + w {
                self.blend(xx, yy, c, a);
            }
        }
    }

    /// Draws `text` with its top-left at (x, y); returns its width in pixels.
    pub fn text(&mut self, x: i64, y: i64, size: f32, text: &str, c: [u8; 3]) -> i64 {
        let Ok(font) = FontRef::try_from_slice(epaint_default_fonts::UBUNTU_LIGHT) else { return 0 };
        let scaled = font.as_scaled(PxScale::from(size));
        let mut pen = x as f32;
        let base = y as f32 + scaled.ascent();
        let mut prev = None;
        for ch in text.chars() {
            let id = scaled.glyph_id(ch);
            if let Some(p) = prev {
                pen += scaled.kern(p, id);
            }
            let g = id.with_scale_and_position(PxScale::from(size), ab_glyph::point(pen, base));
            pen += scaled.h_advance(id);
            prev = Some(id);
            if let Some(o) = font.outline_glyph(g) {
                let b = o.px_bounds();
                o.draw(|gx, gy, cov| {
                    self.blend(b.min.x as i64 + i64::from(gx), b.min.y as i64 + i64::from(gy), c, cov)
                });
            }
        }
        (pen - x as f32).ceil() as i64
    }

    /// Width of `text` in pixels.
    pub fn text_width(size: f32, text: &str) -> i64 {
        let Ok(font) = FontRef::try_from_slice(epaint_default_fonts::UBUNTU_LIGHT) else { return 0 };
        let scaled = font.as_scaled(PxScale::from(size));
        text.chars().map(|c| scaled.h_advance(scaled.glyph_id(c))).sum::<f32>().ceil() as i64
    }
}

/// A number for a colour bar label (3 significant digits, no trailing noise).
pub fn label(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e6).contains(&a) {
        return format!("{v:.2e}");
    }
    let digits = (2 - a.log10().floor() as i32).clamp(0, 6) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.').to_string() } else { s }
}

/// Draws the legends in a column at the picture's top-right corner, on a translucent panel.
pub fn draw_legends(canvas: &mut Canvas, legends: &[Legend]) {
    if legends.is_empty() {
        return;
    }
    let size = (canvas.height as f32 / 34.0).clamp(11.0, 22.0);
    let line = (size * 1.3) as i64;
    let pad = (size * 0.5) as i64;
    // Measure.
    let mut w = 0i64;
    let mut h = pad;
    for l in legends {
        match l {
            Legend::Swatches { title, entries } => {
                w = w.max(Canvas::text_width(size, title));
                for (n, _) in entries {
                    w = w.max(line + Canvas::text_width(size, n));
                }
                h += line * (1 + entries.len() as i64) + pad;
            }
            Legend::ColourBar { title, min, max, .. } if max <= min => {
                w = w.max(Canvas::text_width(size, title)).max(line + Canvas::text_width(size, &label(*min)));
                h += line * 2 + pad;
            }
            Legend::ColourBar { title, min, max, .. } => {
                w = w.max(Canvas::text_width(size, title));
                let lw = Canvas::text_width(size, &label(*max)).max(Canvas::text_width(size, &label(*min)));
                w = w.max(line + pad + lw);
                h += line + line * 6 + pad;
            }
        }
    }
    let w = w + 2 * pad;
    let x0 = i64::from(canvas.width) - w - pad;
    let y0 = pad;
    canvas.rect(x0, y0, w, h, [0, 0, 0], 0.6);
    let mut y = y0 + pad;
    let x = x0 + pad;
    for l in legends {
        match l {
            Legend::Swatches { title, entries } => {
                canvas.text(x, y, size, title, [255, 255, 255]);
                y += line;
                for (n, c) in entries {
                    let s = (size * 0.8) as i64;
                    canvas.rect(x, y + (line - s) / 2, s, s, [c[0], c[1], c[2]], 1.0);
                    canvas.text(x + line, y, size, n, [230, 230, 230]);
                    y += line;
                }
                y += pad;
            }
            Legend::ColourBar { title, map, min, max, log } => {
                let grad = colour_map(map).unwrap_or(ColourMap(Some(colorous::VIRIDIS)));
                canvas.text(x, y, size, title, [255, 255, 255]);
                y += line;
                if max <= min {
                    // A constant: one swatch with its value.
                    let s = (size * 0.8) as i64;
                    let c = grad.eval_continuous(0.5);
                    canvas.rect(x, y + (line - s) / 2, s, s, [c.r, c.g, c.b], 1.0);
                    canvas.text(x + line, y, size, &label(*min), [230, 230, 230]);
                    y += line + pad;
                    continue;
                }
                let bar_h = line * 6;
                for i in 0..bar_h {
                    let t = 1.0 - i as f64 / (bar_h - 1).max(1) as f64;
                    let c = grad.eval_continuous(t);
                    canvas.rect(x, y + i, line - pad / 2, 1, [c.r, c.g, c.b], 1.0);
                }
                let lx = x + line + pad / 2;
                for v in ticks(*min, *max, *log) {
                    let f = 1.0 - bar_position(v, *min, *max, *log);
                    let ty = y + ((bar_h - 1) as f64 * f) as i64;
                    canvas.rect(x + line - pad / 2, ty, pad / 2, 1, [255, 255, 255], 1.0);
                    canvas.text(lx, ty - line / 2, size * 0.85, &label(v), [230, 230, 230]);
                }
                y += bar_h + pad;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_are_short_and_exact_enough() {
        assert_eq!(label(0.0), "0");
        assert_eq!(label(1234.0), "1234");
        assert_eq!(label(0.5), "0.5");
        assert_eq!(label(12.345), "12.3");
        assert_eq!(label(3e7), "3.00e7");
        assert!(colour_map("nope").unwrap_err().to_string().contains("viridis"));
    }

    #[test]
    fn ticks_are_distinct_and_round() {
        // A constant gets one value, not five copies of it.
        assert_eq!(ticks(1.0, 1.0, false), vec![1.0]);
        assert_eq!(ticks(0.0, 10.0, false), vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        // Depths 0..3: integers, none repeated.
        let t = ticks(0.0, 3.0, false);
        let labels: Vec<String> = t.iter().map(|v| label(*v)).collect();
        let mut d = labels.clone();
        d.dedup();
        assert_eq!(labels, d, "{labels:?}");
        assert_eq!(t.first(), Some(&0.0));
        assert_eq!(t.last(), Some(&3.0));
        // Log: the ends and the powers of ten between them.
        assert_eq!(ticks(1.0, 5000.0, true), vec![1.0, 10.0, 100.0, 1000.0, 5000.0]);
        // An end too close to a round tick replaces it.
        assert_eq!(ticks(1.0, 1100.0, true), vec![1.0, 10.0, 100.0, 1100.0]);
        assert_eq!(ticks(1.0, 33668.0, true), vec![1.0, 10.0, 100.0, 1000.0, 33668.0]);
        assert!((bar_position(100.0, 1.0, 10000.0, true) - 0.5).abs() < 1e-12);
        let g = colour_map("greys").unwrap();
        assert_eq!((g.eval_continuous(0.0).r, g.eval_continuous(1.0).r), (0, 255));
    }

    #[test]
    fn text_draws_pixels() {
        let mut px = vec![0u8; 200 * 40 * 4];
        let mut c = Canvas { rgba: &mut px, width: 200, height: 40 };
        let w = c.text(2, 2, 20.0, "rays 42", [255, 255, 255]);
        assert!(w > 40);
        assert!(px.chunks(4).filter(|p| p[0] > 128).count() > 50);
    }
}
