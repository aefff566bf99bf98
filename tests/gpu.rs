#![allow(clippy::unwrap_used)]
//! The GPU path tracer from the command line: a GPU trace is a dataset like any other (check,
//! SQL, analyze diff against a CPU trace, the paper's bug found in it), replays a sample exactly,
//! converges side by side with the CPU tracer, and without an adapter says so and writes nothing.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

mod common;
use common::{WRONG_SHADOWS, ok, record, rtvtk, scalar};

/// The `| key | rays_a | rays_b | rays_change | ...` rows of a report's section `title`.
fn section_rows(report: &str, title: &str) -> Vec<Vec<String>> {
    let start = report.find(&format!("## {title}\n")).unwrap_or_else(|| panic!("no {title} in {report}"));
    report[start..]
        .lines()
        .skip_while(|l| !l.starts_with("|---"))
        .skip(1)
        .take_while(|l| l.starts_with('|'))
        .map(|l| l.trim_matches('|').split('|').map(|c| c.trim().to_string()).collect())
        .collect()
}

#[test]
fn a_gpu_trace_is_analyzed_like_a_cpu_trace() {
    let tmp = tempfile::tempdir().unwrap();
    let settings = ["--scene", "cornell", "--size", "48x36", "--spp", "8", "--seed", "3", "--quiet"];
    let (cpu, gpu) = (tmp.path().join("cpu"), tmp.path().join("gpu"));
    record(&cpu, &settings);
    record(&gpu, &[&settings[..], &["--tracer", "gpu"]].concat());
    assert!(ok(&["check", gpu.to_str().unwrap()]).starts_with("ok:"));
    let info: Value = serde_json::from_slice(&rtvtk(&["info", gpu.to_str().unwrap(), "--json"]).stdout).unwrap();
    assert_eq!(info["trees"], 48 * 36 * 8);
    assert_eq!(scalar(&[gpu.to_str().unwrap()], "SELECT count(*) FROM rays WHERE kind = 'camera'"), "13824");
    // analyze diff: the same rays per kind and depth within noise (camera rays exactly).
    let report = ok(&["analyze", "diff", cpu.to_str().unwrap(), gpu.to_str().unwrap()]);
    let rows = section_rows(&report, "By kind");
    let kinds: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    assert_eq!(kinds, ["camera", "diffuse", "shadow"], "{report}");
    for r in &rows {
        let (a, b): (f64, f64) = (r[1].parse().unwrap(), r[2].parse().unwrap());
        let tol = if r[0] == "camera" { 0.0 } else { 5.0 * a.sqrt() + 0.02 * a };
        assert!((a - b).abs() <= tol, "{}: {a} rays on the CPU, {b} on the GPU\n{report}", r[0]);
    }
    for r in section_rows(&report, "By depth") {
        let (a, b): (f64, f64) = (r[1].parse().unwrap(), r[2].parse().unwrap());
        if a >= 500.0 {
            assert!((a - b).abs() <= 5.0 * a.sqrt() + 0.03 * a, "depth {}: {a} against {b}\n{report}", r[0]);
        }
    }
    // A replayed sample is the same tree.
    let one = tmp.path().join("one");
    record(&one, &[&settings[..], &["--tracer", "gpu", "--pixel", "20,17", "--sample", "5"]].concat());
    let tree = |d: &Path| -> Value {
        let o = rtvtk(&["tree", d.to_str().unwrap(), "--pixel", "20,17", "--sample", "5", "--json"]);
        let mut v: Value = serde_json::from_slice(&o.stdout).unwrap();
        v[0]["tree_id"] = Value::Null;
        v
    };
    assert_eq!(tree(&gpu), tree(&one));
}

#[test]
fn the_papers_bug_is_found_in_a_gpu_trace() {
    let tmp = tempfile::tempdir().unwrap();
    let settings = ["--tracer", "gpu", "--size", "32x24", "--spp", "4", "--quiet"];
    let (good, bad) = (tmp.path().join("good"), tmp.path().join("bad"));
    record(&good, &settings);
    record(&bad, &[&settings[..], &["--inject-bug", "shadow-dir"]].concat());
    assert_eq!(scalar(&[good.to_str().unwrap()], WRONG_SHADOWS), "0");
    let n: u64 = scalar(&[bad.to_str().unwrap()], WRONG_SHADOWS).parse().unwrap();
    assert!(n > 50, "the injected bug's shadow rays aim at no light: {n}");
}

#[test]
fn converge_measures_both_tracers_against_one_reference() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("c");
    let args = [
        "converge",
        "--size",
        "24x18",
        "--reference-spp",
        "64",
        "--spp",
        "2,8,32",
        "--tracer",
        "cpu,gpu",
        "--runs",
        "3",
    ];
    let s = ok(&[&args[..], &["--out", out.to_str().unwrap()]].concat());
    assert!(s.contains("gpu against path at the same spp"), "{s}");
    // Slopes come with their 95% interval.
    assert!(s.contains("RMSE -") && s.contains(" ± "), "{s}");
    let csv = std::fs::read_to_string(out.join("convergence.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("tracer,spp,seconds,seconds_min,seconds_max,runs,rmse,rel_mse"));
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(
        rows.iter().map(|r| (r[0], r[1])).collect::<Vec<_>>(),
        [("path", "2"), ("path", "8"), ("path", "32"), ("gpu", "2"), ("gpu", "8"), ("gpu", "32")]
    );
    for r in &rows {
        // Each point timed over 3 runs: the median lies within their spread.
        let [secs, lo, hi]: [f64; 3] = [2, 3, 4].map(|k| r[k].parse().unwrap());
        assert!(lo <= secs && secs <= hi && r[5] == "3", "{r:?}");
    }
    for t in ["path", "gpu"] {
        let e: Vec<f64> = rows.iter().filter(|r| r[0] == t).map(|r| r[6].parse().unwrap()).collect();
        // 16x the samples: the error falls (by ~4x in expectation; noisy at this size).
        assert!(e[2] < e[0] * 0.6, "{t}: RMSE {e:?}");
    }
    let img = image::open(out.join("convergence.png")).unwrap().to_rgb8();
    let green = img.pixels().filter(|p| p.0 == renderers::converge::CURVE_COLOURS[1].0).count();
    assert!(green > 100, "the GPU's curve is drawn: {green}");
}

#[test]
fn without_an_adapter_the_gpu_tracer_says_so_and_writes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path().join("t");
    // wgpu finds no adapter for a backend this build lacks (Metal on Linux).
    let o = Command::new(env!("CARGO_BIN_EXE_rtvtk"))
        .env("WGPU_BACKEND", "metal")
        .args(["record", "--tracer", "gpu", "--size", "8x8", "--spp", "1", "--out", d.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("no GPU adapter") && e.contains("mesa-vulkan-drivers") && e.contains("libegl-mesa0"), "{e}");
    assert!(!d.exists(), "nothing written");
    let o = rtvtk(&["record", "--tracer", "gpu", "--record-visits", "--out", d.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("does not record the BVH nodes"));
    let o = rtvtk(&["record", "--tracer", "gpu", "--max-depth", "100", "--out", d.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("depth 63 at most"), "{}", String::from_utf8_lossy(&o.stderr));
}
