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
}
