//! Heatmap pictures with axes, ticks, a title and a colour bar with values (plotters), for the
//! per-pixel grids of `rtvtk analyze` (nodes visited per pixel, coherence per pixel, trace diffs
//! per tile).

use std::path::Path;

use crate::{Error, Result};

/// What a heatmap shows: a `width` × `height` grid of values, row-major, row 0 at the top (as
/// in the image); NaN cells have no value (drawn grey, named in the colour bar's caption).
pub struct Heatmap<'a> {
    pub title: &'a str,
    pub width: usize,
    pub height: usize,
    pub values: &'a [f64],
    /// Axis descriptions (for example `pixel x`, `pixel y`).
    pub x_desc: &'a str,
    pub y_desc: &'a str,
    /// What one cell spans along each axis in the axis' unit (1 for pixels, the tile size for
    /// tiles), so ticks read in that unit.
    pub cell: f64,
}

impl<'a> Heatmap<'a> {
    /// A grid over an image (`rtvtk analyze`'s per-pixel and per-tile grids): axes in pixels,
    /// each cell `cell` pixels across.
    pub fn pixels(title: &'a str, width: usize, height: usize, values: &'a [f64], cell: usize) -> Heatmap<'a> {
        Heatmap { title, width, height, values, x_desc: "pixel x", y_desc: "pixel y", cell: cell as f64 }
    }
}

/// A tick value in at most 3 significant digits (`0.25`, `1200`, `3e-5`).
pub fn tick(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let a = v.abs();
    if !(1e-3..1e5).contains(&a) {
        let s = format!("{v:.1e}");
        return s.replace(".0e", "e");
    }
    let digits = (2 - a.log10().floor() as i32).clamp(0, 6) as usize;
    let s = format!("{v:.digits$}");
    if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.').to_string() } else { s }
}

/// Registers egui's font as plotters' "sans-serif" (once): plots need no system fonts.
pub fn plot_font() -> &'static str {
    static DONE: std::sync::Once = std::sync::Once::new();
    DONE.call_once(|| {
        // A font that cannot be registered leaves the plot without text; nothing else fails.
        let _ = plotters::style::register_font(
            "sans-serif",
            plotters::style::FontStyle::Normal,
            epaint_default_fonts::UBUNTU_LIGHT,
        );
    });
    "sans-serif"
}

/// Draws a `w` × `h` plot with plotters on a white page (`draw` gets the page) and writes it to
/// `path` as an RGB PNG.
pub(crate) fn png(
    path: &Path,
    (w, h): (u32, u32),
    draw: impl FnOnce(
        &plotters::drawing::DrawingArea<plotters::prelude::BitMapBackend<'_>, plotters::coord::Shift>,
    ) -> Result<()>,
) -> Result<()> {
    use plotters::prelude::*;
    let bad = |e: String| Error::Image { path: path.into(), message: e };
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| bad(e.to_string()))?;
        draw(&root)?;
        root.present().map_err(|e| bad(e.to_string()))?;
    }
    image::save_buffer(path, &buf, w, h, image::ColorType::Rgb8).map_err(|e| bad(e.to_string()))
}

/// Smallest and largest finite value.
fn finite_range(values: &[f64]) -> Option<(f64, f64)> {
    let mut it = values.iter().copied().filter(|v| v.is_finite());
    let first = it.next()?;
    Some(it.fold((first, first), |(lo, hi), v| (lo.min(v), hi.max(v))))
}

fn colour(t: f64) -> plotters::style::RGBColor {
    let c = colorous::PLASMA.eval_continuous(t.clamp(0.0, 1.0));
    plotters::style::RGBColor(c.r, c.g, c.b)
}

/// Writes `map` as a PNG: the grid with axes in the grid's unit, the title above, and a colour
/// bar on the right with tick values (the value range of the finite cells).
pub fn write_heatmap(map: &Heatmap, path: &Path) -> Result<()> {
    use plotters::prelude::*;
    let bad = |e: String| Error::Image { path: path.into(), message: e };
    let (gw, gh) = (map.width, map.height);
    if gw == 0 || gh == 0 || map.values.len() != gw * gh {
        return Err(bad(format!("a {gw}x{gh} heatmap needs {} values, got {}", gw * gh, map.values.len())));
    }
    if !(map.cell.is_finite() && map.cell > 0.0) {
        return Err(bad(format!("cell size {} is not a positive number", map.cell)));
    }
    let font = plot_font();
    // The grid's area about 560 pixels on its long side, cells square.
    let long = gw.max(gh) as f64;
    let (pw, ph) = ((560.0 * gw as f64 / long).max(120.0) as u32, (560.0 * gh as f64 / long).max(120.0) as u32);
    let (bar_w, margin_l, margin_b, top) = (150u32, 70u32, 56u32, 48u32);
    let (w, h) = (margin_l + pw + 20 + bar_w, top + ph + margin_b);
    let (lo, hi) = finite_range(map.values).unwrap_or((0.0, 1.0));
    let (lo, hi) = if hi > lo { (lo, hi) } else { (lo - 0.5, hi + 0.5) };
    let missing = map.values.iter().filter(|v| !v.is_finite()).count();
    let (xw, yh) = (gw as f64 * map.cell, gh as f64 * map.cell);
    crate::plot::png(path, (w, h), |root| {
        let (left, right) = root.split_horizontally(margin_l + pw + 20);
        let mut chart = ChartBuilder::on(&left)
            .caption(map.title, (font, 18))
            .margin_right(20)
            .margin_top(8)
            .x_label_area_size(margin_b - 8)
            .y_label_area_size(margin_l)
            // Row 0 at the top, as in the image.
            .build_cartesian_2d(0.0..xw, yh..0.0)
            .map_err(|e| bad(e.to_string()))?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc(map.x_desc)
            .y_desc(map.y_desc)
            .label_style((font, 13))
            .axis_desc_style((font, 15))
            .x_labels(8)
            .y_labels(8)
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .draw()
            .map_err(|e| bad(e.to_string()))?;
        let grey = RGBColor(190, 190, 190);
        let c = map.cell;
        chart
            .draw_series((0..gh).flat_map(|y| (0..gw).map(move |x| (x, y))).map(|(x, y)| {
                let v = map.values[y * gw + x];
                let fill = if v.is_finite() { colour((v - lo) / (hi - lo)) } else { grey };
                let (x0, y0) = (x as f64 * c, y as f64 * c);
                Rectangle::new([(x0, y0), (x0 + c, y0 + c)], fill.filled())
            }))
            .map_err(|e| bad(e.to_string()))?;
        // The colour bar: the value range bottom to top, with tick values.
        let caption = if missing > 0 { format!("value ({missing} cells without one: grey)") } else { "value".into() };
        let mut bar = ChartBuilder::on(&right)
            .margin_top(top)
            .margin_bottom(margin_b)
            .margin_right(24)
            .y_label_area_size(80)
            .build_cartesian_2d(0.0..1.0, lo..hi)
            .map_err(|e| bad(e.to_string()))?;
        bar.configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .y_desc(caption)
            .label_style((font, 13))
            .axis_desc_style((font, 13))
            .y_labels(8)
            // Ticks are computed in floating point: a tick at zero may come out as 1e-17.
            .y_label_formatter(&|v| tick(if v.abs() < (hi - lo) * 1e-9 { 0.0 } else { *v }))
            .draw()
            .map_err(|e| bad(e.to_string()))?;
        let steps = 128;
        bar.draw_series((0..steps).map(|i| {
            let (a, b) = (i as f64 / steps as f64, (i + 1) as f64 / steps as f64);
            Rectangle::new([(0.0, lo + (hi - lo) * a), (1.0, lo + (hi - lo) * b)], colour(a).filled())
        }))
        .map_err(|e| bad(e.to_string()))?;
        Ok(())
    })
}

/// Writes an analysis report into `dir` (made if missing): its markdown as `report.md` and each
/// named heatmap as `NAME.png` beside it (the report's pictures refer to them by those names).
/// Returns the path of `report.md`. `rtvtk analyze --out` and the Python package's
/// `Report.save` write reports this way.
pub fn write_report(dir: &Path, markdown: &str, maps: &[(&str, Heatmap)]) -> Result<std::path::PathBuf> {
    let io = |what, path: &Path| {
        let path = path.to_path_buf();
        move |source| Error::Io { what, path, source }
    };
    std::fs::create_dir_all(dir).map_err(io("the report's directory", dir))?;
    let md = dir.join("report.md");
    std::fs::write(&md, markdown).map_err(io("report.md", &md))?;
    for (name, map) in maps {
        write_heatmap(map, &dir.join(format!("{name}.png")))?;
    }
    Ok(md)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_short() {
        assert_eq!(tick(0.1), "0.1");
        assert_eq!(tick(0.25), "0.25");
        assert_eq!(tick(1200.0), "1200");
        assert_eq!(tick(3e-5), "3e-5");
        assert_eq!(tick(1.0), "1");
    }

    #[test]
    fn a_heatmap_has_axes_cells_and_a_colour_bar() {
        let (gw, gh) = (32usize, 16usize);
        let mut values: Vec<f64> = (0..gw * gh).map(|i| (i % gw) as f64).collect();
        values[5] = f64::NAN;
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.png");
        let map = Heatmap {
            title: "nodes per pixel",
            width: gw,
            height: gh,
            values: &values,
            x_desc: "pixel x",
            y_desc: "pixel y",
            cell: 1.0,
        };
        write_heatmap(&map, &p).unwrap();
        let img = image::open(&p).unwrap().to_rgb8();
        // Low values dark blue-purple at the left, high values yellow at the right, grey for NaN.
        let purple = img.pixels().filter(|p| p.0[2] > 100 && p.0[0] < 60 && p.0[1] < 30).count();
        let yellow = img.pixels().filter(|p| p.0[0] > 220 && p.0[1] > 200 && p.0[2] < 80).count();
        let grey = img.pixels().filter(|p| p.0 == [190, 190, 190]).count();
        assert!(purple > 500 && yellow > 500, "purple {purple}, yellow {yellow}");
        assert!(grey > 50, "the NaN cell is drawn grey: {grey}");
        // Text (dark anti-aliased glyphs) left of the grid: the y tick values and description.
        let dark_left = (0..60)
            .flat_map(|x| (0..img.height()).map(move |y| (x, y)))
            .filter(|&(x, y)| img.get_pixel(x, y).0.iter().all(|&c| c < 120))
            .count();
        assert!(dark_left > 100, "axis text: {dark_left}");
    }

    #[test]
    fn bad_grids_are_errors_not_panics() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.png");
        let v = [1.0, 2.0];
        let m = |w, h, cell| Heatmap { title: "t", width: w, height: h, values: &v, x_desc: "x", y_desc: "y", cell };
        assert!(write_heatmap(&m(3, 1, 1.0), &p).unwrap_err().to_string().contains("needs 3 values"));
        assert!(write_heatmap(&m(0, 0, 1.0), &p).is_err());
        assert!(write_heatmap(&m(2, 1, f64::NAN), &p).is_err());
        // All NaN, or all equal: a picture all the same.
        let nan = [f64::NAN; 2];
        let all_nan = Heatmap { values: &nan, ..m(2, 1, 1.0) };
        write_heatmap(&all_nan, &p).unwrap();
        write_heatmap(&Heatmap { values: &[4.0, 4.0], ..m(2, 1, 1.0) }, &p).unwrap();
    }
}
