#![allow(clippy::unwrap_used)]
//! A third-party renderer through the C API: `rl-writer/examples/cpp_tracer.cpp` (C++, three
//! tracing threads) records typed payload columns and opaque bytes, an emissive quad and a point
//! light, and its camera as a camera-to-world matrix. The dataset passes `rtvtk check`; SQL reads
//! every column with its type; the paper's query finds no wrong shadow ray in the correct trace
//! and finds the injected bug's, and its recording sites name the C++ line that adds them; the
//! camera ray of a pixel lands on that pixel.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use common::{WRONG_SHADOWS, ok, scalar};

#[path = "../rl-writer/tests/support/static_lib.rs"]
mod support;
use support::static_lib;

/// Compiles the example with the system's C++ compiler (`CXX`, else `c++`).
fn build(dir: &Path) -> PathBuf {
    let root =
        std::env::var_os("CARGO_MANIFEST_DIR").map_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")), PathBuf::from);
    let bin = dir.join("cpp_tracer");
    let cxx = std::env::var("CXX").unwrap_or_else(|_| "c++".into());
    let out = Command::new(&cxx)
        .args(["-std=c++17", "-O1", "-Wall", "-Werror", "-I"])
        .arg(root.join("rl-writer/include"))
        .arg(root.join("rl-writer/examples/cpp_tracer.cpp"))
        .arg(static_lib())
        .args(["-lpthread", "-ldl", "-lm", "-o"])
        .arg(&bin)
        .output()
        .unwrap_or_else(|e| panic!("cannot run the C++ compiler {cxx:?} (install g++; scripts/check.sh does): {e}"));
    assert!(out.status.success(), "{cxx}: {}", String::from_utf8_lossy(&out.stderr));
    bin
}

fn run(bin: &Path, out: &Path, args: &[&str]) -> [u64; 3] {
    let r = Command::new(bin).arg(out).args(args).output().unwrap();
    assert!(
        r.status.success(),
        "cpp_tracer: {}{}",
        String::from_utf8_lossy(&r.stdout),
        String::from_utf8_lossy(&r.stderr)
    );
    let text = String::from_utf8_lossy(&r.stdout).to_string();
    let n: Vec<u64> = text.split_whitespace().filter_map(|w| w.parse().ok()).collect();
    assert_eq!(n.len(), 3, "{text}");
    [n[0], n[1], n[2]]
}

#[test]
fn a_cpp_renderer_records_typed_payload_lights_and_a_matrix_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let bin = build(tmp.path());
    let good = tmp.path().join("good");
    let [camera, shadow, diffuse] = run(&bin, &good, &[]);
    let g = good.to_str().unwrap();
    ok(&["check", g]);
    // Counts by kind as the tracer counted them.
    assert_eq!(scalar(&[g], "SELECT count(*) FROM rays WHERE kind = 'camera'"), camera.to_string());
    assert_eq!(scalar(&[g], "SELECT count(*) FROM rays WHERE kind = 'shadow'"), shadow.to_string());
    assert_eq!(scalar(&[g], "SELECT count(*) FROM rays WHERE kind = 'diffuse'"), diffuse.to_string());
    assert_eq!(camera, 24 * 18 * 2);
    // Every typed column, with its type, and the opaque bytes.
    let types = scalar(
        &[g],
        "SELECT concat_ws(',', arrow_typeof(throughput), arrow_typeof(material), arrow_typeof(bounce), \
         arrow_typeof(pdf), arrow_typeof(payload)) FROM rays LIMIT 1",
    );
    assert!(types.contains("FixedSizeList") && types.contains("Float32"), "{types}");
    assert!(types.contains("UInt32") && types.contains("UInt8") && types.contains("Float64"), "{types}");
    assert!(types.contains("FixedSizeBinary(8)"), "{types}");
    assert_eq!(scalar(&[g], "SELECT max(bounce) FROM rays WHERE kind = 'diffuse'"), "2");
    assert_eq!(scalar(&[g], "SELECT count(*) FROM rays WHERE throughput[1] > 1.0 OR pdf <> 1.0"), "0");
    // The emissive quad (two triangles) and the point light.
    assert_eq!(scalar(&[g], "SELECT count(*) FROM lights"), "3");
    assert_eq!(scalar(&[g], "SELECT count(*) FROM lights WHERE area = 0"), "1");
    // Its BVH (the root and a leaf per quad) and the nodes every camera and diffuse ray visited:
    // the root first, and `rtvtk analyze bvh` reads them.
    assert_eq!(scalar(&[g], "SELECT count(*) FROM bvh_nodes"), "7");
    assert_eq!(scalar(&[g], "SELECT max(level) FROM bvh_nodes"), "1");
    assert_eq!(
        scalar(&[g], "SELECT count(*) FROM (SELECT DISTINCT tree_id, ray FROM ray_nodes)"),
        (camera + diffuse).to_string()
    );
    assert_eq!(scalar(&[g], "SELECT count(*) FROM ray_nodes WHERE step = 0 AND node_id <> 0"), "0");
    assert_eq!(scalar(&[g], "SELECT count(*) FROM ray_nodes WHERE node_id = 0 AND leaf_hit IS NOT NULL"), "0");
    let report = ok(&["analyze", "bvh", g]);
    assert!(report.contains("nodes") && report.contains("camera"), "{report}");
    assert_eq!(scalar(&[g], "SELECT count(*) FROM rays WHERE box_tests <> 7"), "0");
    // A correct trace: every shadow ray aims at a light (the quad's or the point light).
    assert_eq!(scalar(&[g], WRONG_SHADOWS), "0");
    // The camera from the matrix: the camera ray of a pixel lands on that pixel.
    let attrs = ok(&["sql", g, "SELECT key, value FROM attributes", "--format", "csv"]);
    let get = |k: &str| -> Vec<f64> {
        let line = attrs.lines().find(|l| l.starts_with(&format!("{k},"))).unwrap();
        line[k.len() + 1..].trim_matches('"').split(',').map(|v| v.parse().unwrap()).collect()
    };
    let (pos, target, up) = (get("camera.position"), get("camera.target"), get("camera.up"));
    assert!(pos.iter().zip([0.5, 0.5, 1.6]).all(|(a, b)| (a - b).abs() < 1e-6), "{pos:?}");
    assert_eq!(up, vec![0.0, 1.0, 0.0]);
    let (fov, w, h) = (get("camera.fov_y")[0].to_radians(), get("width")[0], get("height")[0]);
    let cams = ok(&[
        "sql",
        g,
        "SELECT pixel_x, pixel_y, dir_x, dir_y, dir_z FROM rays WHERE kind = 'camera'",
        "--format",
        "csv",
    ]);
    let f: Vec<f64> = (0..3).map(|k| target[k] - pos[k]).collect();
    assert!(f[2] < 0.0 && f[0].abs() < 1e-9, "looks down -z: {f:?}");
    let k = (fov / 2.0).tan();
    let mut n = 0;
    for line in cams.lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        // right = +x, up = +y, forward = -z for this camera.
        let (sx, sy) = (v[2] / -v[4], v[3] / -v[4]);
        let px = (sx / (k * w / h) + 1.0) * w / 2.0;
        let py = (1.0 - sy / k) * h / 2.0;
        assert_eq!((px.floor(), py.floor()), (v[0], v[1]), "{line}");
        n += 1;
    }
    assert_eq!(n, camera);
    // The injected bug: the point light's shadow rays from the floor aim below it.
    let bad = tmp.path().join("bad");
    let counts = run(&bin, &bad, &["--bug"]);
    let b = bad.to_str().unwrap();
    let wrong: u64 = scalar(&[b], WRONG_SHADOWS).parse().unwrap();
    assert!(wrong > 0 && wrong < counts[1], "{wrong} of {}", counts[1]);
    // Its recording sites (RL_ADD_RAY) name the line that adds the wrong rays: the point
    // light's shadow ray, alone.
    let source = std::fs::read_to_string(build_root().join("rl-writer/examples/cpp_tracer.cpp")).unwrap();
    let line = source.lines().position(|l| l.contains("// point light")).unwrap() + 1;
    let sites = ok(&[
        "sql",
        b,
        &format!("{} GROUP BY site", WRONG_SHADOWS.replace("count(*)", "site, count(*)")),
        "--format",
        "csv",
    ]);
    let rows: Vec<&str> = sites.lines().skip(1).collect();
    assert_eq!(rows.len(), 1, "{sites}");
    assert!(rows[0].contains(&format!("cpp_tracer.cpp:{line} ")) && rows[0].ends_with(&format!(",{wrong}")), "{sites}");
    assert_eq!(
        scalar(&[b], "SELECT count(DISTINCT site) FROM rays"),
        "3",
        "camera/diffuse, area-light and point-light lines"
    );
}

fn build_root() -> PathBuf {
    std::env::var_os("CARGO_MANIFEST_DIR").map_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")), PathBuf::from)
}
