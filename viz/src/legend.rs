//! Colour maps, and the legends and colour bars drawn onto a rendered picture (text rasterized
//! on the CPU with egui's own font, so figures need no system fonts).

use ab_glyph::{Font, FontRef, PxScale, ScaleFont};

use crate::component::Legend;
use crate::{Error, Result};

/// The colour maps by name.
pub const COLOUR_MAPS: [&str; 6] = ["viridis", "magma", "inferno", "plasma", "turbo", "cividis"];

/// A colour map by name, or an error listing the known ones.
pub fn colour_map(name: &str) -> Result<colorous::Gradient> {
    Ok(match name {
        "viridis" => colorous::VIRIDIS,
        "magma" => colorous::MAGMA,
        "inferno" => colorous::INFERNO,
        "plasma" => colorous::PLASMA,
        "turbo" => colorous::TURBO,
        "cividis" => colorous::CIVIDIS,
        _ => {
            return Err(Error::Settings(format!(
                "unknown colour map {name:?}: expected one of {}",
                COLOUR_MAPS.join(", ")
            )));
        }
    })
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
            Legend::ColourBar { title, map, min, max } => {
                canvas.text(x, y, size, title, [255, 255, 255]);
                y += line;
                let bar_h = line * 6;
                let grad = colour_map(map).unwrap_or(colorous::VIRIDIS);
                for i in 0..bar_h {
                    let t = 1.0 - i as f64 / (bar_h - 1).max(1) as f64;
                    let c = grad.eval_continuous(t);
                    canvas.rect(x, y + i, line - pad / 2, 1, [c.r, c.g, c.b], 1.0);
                }
                let lx = x + line + pad / 2;
                let ticks = 4;
                for k in 0..=ticks {
                    let f = k as f64 / f64::from(ticks);
                    let v = max - (max - min) * f;
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
    fn text_draws_pixels() {
        let mut px = vec![0u8; 200 * 40 * 4];
        let mut c = Canvas { rgba: &mut px, width: 200, height: 40 };
        let w = c.text(2, 2, 20.0, "rays 42", [255, 255, 255]);
        assert!(w > 40);
        assert!(px.chunks(4).filter(|p| p[0] > 128).count() > 50);
    }
}
