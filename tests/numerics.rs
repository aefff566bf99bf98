#![allow(clippy::unwrap_used)]
//! `rtvtk analyze numerics` and the `numerics` view: each injected bug is found by its check,
//! and clean traces of every built-in scene, at extreme scales and far from the origin, report 0.

mod common;
use common::{ok, record, rtvtk, scalar};

const SETTINGS: [&str; 8] = ["--size", "24x18", "--spp", "2", "--threads", "2", "--max-depth", "5"];

/// The checks' counts in the report's table: `None` for a check not run.
fn counts(report: &str) -> Vec<(String, Option<u64>)> {
    let checks =
        ["non_finite", "bad_direction", "self_hit", "detached_origin", "leak", "energy", "wrong_shadow", "firefly"];
    let mut out = Vec::new();
    for line in report.lines() {
        let cells: Vec<&str> = line.split('|').map(str::trim).collect();
        if cells.len() >= 5 && checks.contains(&cells[1]) {
            out.push((cells[1].to_string(), cells[3].replace(',', "").parse().ok()));
        }
    }
    assert_eq!(out.len(), checks.len(), "{report}");
    out
}

fn count(report: &str, check: &str) -> Option<u64> {
    counts(report).into_iter().find(|(c, _)| c == check).unwrap().1
}

/// Every bug check (all but fireflies) that ran found nothing.
fn assert_clean(report: &str, what: &str) {
    for (check, n) in counts(report) {
        if check != "firefly" {
            assert!(n.unwrap_or(0) == 0, "{what}: {check} found {n:?}\n{report}");
        }
    }
    assert!(count(report, "leak").is_some() && count(report, "self_hit").is_some(), "{what}: {report}");
}

#[test]
fn each_injected_bug_is_found_by_its_check() {
    let tmp = tempfile::tempdir().unwrap();
    let clean = tmp.path().join("clean");
    record(&clean, &SETTINGS);
    let c = clean.to_str().unwrap();
    assert_clean(&ok(&["analyze", "numerics", c]), "clean cornell");

    for (bug, check) in
        [("nan", "non_finite"), ("no-offset", "self_hit"), ("leak", "leak"), ("shadow-dir", "wrong_shadow")]
    {
        let dir = tmp.path().join(bug);
        record(&dir, &[&SETTINGS[..], &["--inject-bug", bug]].concat());
        let d = dir.to_str().unwrap();
        let out = tmp.path().join(format!("{bug}-report"));
        ok(&["analyze", "numerics", d, "--out", out.to_str().unwrap()]);
        let report = std::fs::read_to_string(out.join("report.md")).unwrap();
        let n = count(&report, check).unwrap();
        assert!(n > 0, "--inject-bug {bug}: {check} found nothing\n{report}");
        // The same count from the view, and its rows carry the rays' coordinates for drawing.
        let sql = format!("SELECT count(*) FROM numerics WHERE problem = '{check}'");
        assert_eq!(scalar(&[d], &sql), n.to_string(), "{bug}");
        let sql = format!("SELECT count(*) FROM numerics WHERE problem = '{check}' AND origin_x IS NOT NULL");
        assert_eq!(scalar(&[d], &sql), n.to_string(), "{bug}");
        if check != "wrong_shadow" {
            assert!(out.join(format!("numerics_{check}.png")).exists(), "{bug}: no heatmap");
        }
        match bug {
            // Infinite shadow-ray weights: the throughput column names itself.
            "nan" => assert!(report.contains("throughput["), "{report}"),
            // Origins pushed along the direction are detached from the hit point too.
            "leak" => assert!(count(&report, "detached_origin").unwrap() > 0, "{report}"),
            _ => {}
        }
    }

    // Bad input: a clear error naming the dataset.
    let out = rtvtk(&["analyze", "numerics", "/no/such/trace"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("/no/such/trace") && !err.contains("panicked"), "{err}");
    // The GPU tracer injects shadow-dir only, and says so.
    let out = rtvtk(&["record", "--tracer", "gpu", "--inject-bug", "leak", "--out", "/tmp/never", "--size", "8x8"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("shadow-dir only"), "{err}");
    let out = rtvtk(&["record", "--inject-bug", "nope", "--out", "/tmp/never"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("no-offset"), "{err}");
}

#[test]
fn clean_traces_report_nothing_on_every_scene_and_scale() {
    let tmp = tempfile::tempdir().unwrap();
    let cases: [(&str, &[&str]); 6] = [
        ("glass", &["--scene", "cornell-glass"]),
        ("glossy", &["--scene", "glossy"]),
        ("whitted", &["--scene", "cornell-glass", "--tracer", "whitted"]),
        ("tiny", &["--scale", "1e-4"]),
        ("huge", &["--scale", "1e5"]),
        ("far", &["--offset", "1e6,1e6,1e6"]),
    ];
    for (name, args) in cases {
        let dir = tmp.path().join(name);
        record(&dir, &[&SETTINGS[..], args].concat());
        assert_clean(&ok(&["analyze", "numerics", dir.to_str().unwrap()]), name);
    }
    // A curved closed mesh (a glossy sphere of 256 triangles on a floor, under a lamp), as the
    // scanned models users bring: tiny, huge and far from the origin.
    let obj = sphere_obj(tmp.path());
    for (name, args) in
        [("obj-tiny", ["--scale", "1e-4"]), ("obj-huge", ["--scale", "1e5"]), ("obj-far", ["--offset", "1e6,-1e6,1e6"])]
    {
        let dir = tmp.path().join(name);
        let camera = ["--camera-pos", "0,1.5,4.5", "--camera-target", "0,1,0", "--fov", "40"];
        record(&dir, &[&SETTINGS[..], &["--scene", obj.to_str().unwrap()], &camera[..], &args[..]].concat());
        let report = ok(&["analyze", "numerics", dir.to_str().unwrap()]);
        assert_clean(&report, name);
        assert!(count(&report, "wrong_shadow").is_some(), "{name}: the lamp is an emitter\n{report}");
        let on_sphere =
            "SELECT count(*) FROM rays r JOIN triangles t ON r.prim = t.prim WHERE t.material_name = 'shiny'";
        let n: u64 = scalar(&[dir.to_str().unwrap()], on_sphere).parse().unwrap();
        assert!(n > 100, "{name}: {n} rays hit the sphere");
    }
}

/// Writes a UV sphere (16 x 8, radius 1 at y = 1) on a floor under an emissive quad, with its
/// materials; the OBJ's path.
fn sphere_obj(dir: &std::path::Path) -> std::path::PathBuf {
    use std::fmt::Write as _;
    let mut o = String::from("mtllib s.mtl\n");
    let (seg, rings) = (16usize, 8usize);
    let _ = writeln!(o, "v 0 2 0");
    for r in 1..rings {
        let th = std::f64::consts::PI * r as f64 / rings as f64;
        for k in 0..seg {
            let ph = 2.0 * std::f64::consts::PI * k as f64 / seg as f64;
            let _ = writeln!(o, "v {} {} {}", th.sin() * ph.cos(), 1.0 + th.cos(), th.sin() * ph.sin());
        }
    }
    let _ = writeln!(o, "v 0 0 0");
    let south = 2 + (rings - 1) * seg;
    let at = |r: usize, k: usize| 2 + (r - 1) * seg + k % seg;
    o.push_str("usemtl shiny\n");
    for k in 0..seg {
        let _ = writeln!(o, "f 1 {} {}", at(1, k + 1), at(1, k));
        let _ = writeln!(o, "f {south} {} {}", at(rings - 1, k), at(rings - 1, k + 1));
        for r in 1..rings - 1 {
            let _ = writeln!(o, "f {} {} {}", at(r, k), at(r, k + 1), at(r + 1, k + 1));
            let _ = writeln!(o, "f {} {} {}", at(r, k), at(r + 1, k + 1), at(r + 1, k));
        }
    }
    let v = south + 1;
    o.push_str("v -4 -0.001 -4\nv 4 -0.001 -4\nv 4 -0.001 4\nv -4 -0.001 4\nusemtl white\n");
    let _ = writeln!(o, "f {} {} {}\nf {} {} {}", v, v + 2, v + 1, v, v + 3, v + 2);
    o.push_str("v -1 4 -1\nv 1 4 -1\nv 1 4 1\nv -1 4 1\nusemtl lamp\n");
    let _ = writeln!(o, "f {} {} {}\nf {} {} {}", v + 4, v + 5, v + 6, v + 4, v + 6, v + 7);
    std::fs::write(dir.join("s.mtl"), "newmtl white\nKd 0.7 0.7 0.7\nnewmtl shiny\nKd 0.4 0.3 0.3\nKs 0.4 0.4 0.4\nNs 32\nnewmtl lamp\nKd 0 0 0\nKe 15 15 15\n").unwrap();
    let path = dir.join("sphere.obj");
    std::fs::write(&path, o).unwrap();
    path
}
