#![allow(clippy::unwrap_used)]
//! `rtvtk analyze`: the canned reports on small traces, their plots, and bad input.

mod common;
use common::{ok, rtvtk};

const SETTINGS: [&str; 9] =
    ["--scene", "cornell", "--size", "32x24", "--spp", "2", "--threads", "2", "--record-visits"];

/// The number after `**` in the bug report's summary line.
fn wrong_count(report: &str) -> u64 {
    let line = report.lines().find(|l| l.contains("point at no emitter")).unwrap();
    line.split("**").nth(1).unwrap().parse().unwrap()
}

#[test]
fn reports_find_the_bug_and_draw_it() {
    let tmp = tempfile::tempdir().unwrap();
    let (good, bad) = common::record_good_and_bad(tmp.path(), &SETTINGS);
    let (g, b) = (good.to_str().unwrap(), bad.to_str().unwrap());

    assert_eq!(wrong_count(&ok(&["analyze", "bugs", g])), 0);
    let out = tmp.path().join("bugs");
    ok(&["analyze", "bugs", b, "--out", out.to_str().unwrap()]);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(wrong_count(&report) > 0, "{report}");
    // The bug's condition: shadow rays leaving diffuse surfaces after the first bounce.
    assert!(report.contains("| diffuse |"), "{report}");
    let png = image::open(out.join("wrong_shadow_rays.png")).unwrap().to_rgb8();
    // A heatmap with axes and a colour bar (plotters): inside the grid's area some cell is above
    // the lowest colour (dark blue): a pixel with wrong shadow rays; grey is no data, white the page.
    let (w, h) = png.dimensions();
    assert!(w > 600 && h > 400, "{w}x{h}");
    let hot = (75..600)
        .flat_map(|x| (55..h.min(560)).map(move |y| (x, y)))
        .map(|(x, y)| png.get_pixel(x, y).0)
        .filter(|p| p[0] > 60 && *p != [190, 190, 190] && *p != [255, 255, 255])
        .count();
    assert!(hot > 0, "some pixel has wrong shadow rays");

    let report = ok(&["analyze", "coherence", g, "--width", "4"]);
    for order in ["trace", "morton", "octant", "material"] {
        assert!(report.contains(&format!("| {order} | camera |")), "{report}");
    }
    assert!(report.contains("simd_utilization"), "{report}");

    let report = ok(&["analyze", "bvh", g]);
    assert!(report.contains("False-positive leaf tests") && report.contains("| shadow |"), "{report}");

    // What-ifs: the rays replayed against other builds and the recorded tree, every replayed
    // closest hit the recorded one, the SAH's rank correlation and the subset's prediction.
    let report = ok(&["analyze", "bvh", g, "--whatif", "--share", "0.1"]);
    let builds: Vec<&str> =
        report.lines().filter(|l| l.starts_with("| ") && l.ends_with(" |") && l.contains(" of ")).collect();
    assert!(builds.len() >= 7, "{report}");
    assert!(builds.iter().any(|l| l.starts_with("| recorded (bvh_nodes) |")), "{report}");
    assert!(builds.iter().any(|l| l.starts_with("| binned sah, leaf 4 |")), "{report}");
    for l in &builds {
        let cells: Vec<&str> = l.split('|').map(str::trim).collect();
        let verified: Vec<u64> = cells[cells.len() - 2].split(" of ").map(|n| n.parse().unwrap()).collect();
        assert!(verified[1] > 0 && verified[0] == verified[1], "{l}");
    }
    assert!(report.contains("SAH against measured tests per ray **"), "{report}");
    assert!(report.contains("predict each build's tests per ray within **"), "{report}");
    let out = rtvtk(&["analyze", "bvh", g, "--whatif", "--share", "2"]);
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("(0, 1]"));

    let out = tmp.path().join("diff");
    ok(&["analyze", "diff", g, b, "--tile", "8", "--out", out.to_str().unwrap()]);
    let report = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(report.contains("lit_change"), "{report}");
    assert!(out.join("rays_change_per_tile.png").exists() && out.join("lit_change_per_tile.png").exists());

    // Bad input: a clear error, no panic.
    for (args, expect) in [
        (vec!["analyze", "coherence", g, "--orders", "zigzag"], "expected trace, morton, octant or material"),
        (vec!["analyze", "bugs", "/no/such/trace"], "/no/such/trace"),
    ] {
        let out = rtvtk(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(expect) && !err.contains("panicked"), "{args:?}: {err}");
    }
}
