#![allow(clippy::unwrap_used)]
//! The `rtvtk` command line end to end, and plain-Parquet readers (DuckDB from PyPI) on its output.

use std::path::Path;
use std::process::Command;

use serde_json::Value;

mod common;
use common::rtvtk;

fn demo(dir: &Path) {
    let out = rtvtk(&["demo", "--out", dir.to_str().unwrap(), "--size", "32x24", "--spp", "2"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = String::from_utf8_lossy(&out.stdout);
    assert!(s.contains("recorded 1536 trees"), "{s}");
    assert!(s.contains("rays by kind") && s.contains("shadow"), "{s}");
}

#[test]
fn demo_info_tree_check() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    demo(&dir);
    let d = dir.to_str().unwrap();

    let out = rtvtk(&["info", d, "--json"]);
    assert!(out.status.success());
    let info: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(info["trees"], 1536);
    assert_eq!(info["format_version"], store::FORMAT_VERSION);
    assert_eq!(info["encoding"], "lossless");
    let rays = info["rays"].as_u64().unwrap();
    let by_kind: u64 = info["rays_by_kind"].as_object().unwrap().values().map(|v| v.as_u64().unwrap()).sum();
    assert_eq!(by_kind, rays);
    assert!(info["bytes_per_ray"].as_f64().unwrap() > 1.0);
    let payload: Vec<&str> = info["payload"].as_array().unwrap().iter().map(|p| p["name"].as_str().unwrap()).collect();
    assert_eq!(payload, ["throughput", "radiance", "material", "nodes_visited", "box_tests", "tri_tests"]);
    assert!(dir.join("image.png").exists() && dir.join("image.exr").exists());
    // What the demo's trace left out, and why: no visits or sites recorded, no glass.
    let left: Vec<&str> = info["left_out"].as_array().unwrap().iter().map(|v| v["what"].as_str().unwrap()).collect();
    for want in ["table ray_nodes", "table sites", "kind transmission"] {
        assert!(left.contains(&want), "{left:?}");
    }
    for kept in ["table triangles", "table lights", "table bvh_nodes", "column throughput", "kind shadow"] {
        assert!(!left.contains(&kept), "{left:?}");
    }
    let text = String::from_utf8_lossy(&rtvtk(&["info", d]).stdout).to_string();
    assert!(text.contains("left out") && text.contains("record --record-visits"), "{text}");

    let out = rtvtk(&["tree", d, "--pixel", "16,18", "--json"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let trees: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(trees.as_array().unwrap().len(), 2, "two samples");
    assert_eq!(trees[0]["rays"][0]["kind"], "camera");
    let text = String::from_utf8_lossy(&rtvtk(&["tree", d, "--tree", "7"]).stdout).to_string();
    assert!(text.starts_with("tree 7 ") && text.contains("└─ #0 camera"), "{text}");

    let out = rtvtk(&["check", d, "--json"]);
    assert!(out.status.success());
    let r: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(r["ok"], true);
    assert_eq!(r["report"]["rays"].as_u64().unwrap(), rays);
}

#[test]
fn bad_input_gets_clear_errors_and_exit_codes() {
    let tmp = tempfile::tempdir().unwrap();
    let out = rtvtk(&["info", tmp.path().join("nope").to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(2));
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("no manifest") && e.contains("nope"), "{e}");

    let dir = tmp.path().join("t");
    demo(&dir);
    let d = dir.to_str().unwrap();
    let out = rtvtk(&["tree", d, "--tree", "999999"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no tree with id 999999"));
    let out = rtvtk(&["tree", d, "--pixel", "12"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("X,Y"));

    // A corrupted segment: `check` names it and fails.
    let seg = dir.join("segments/000001.rays.parquet");
    let mut bytes = std::fs::read(&seg).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    std::fs::write(&seg, bytes).unwrap();
    let out = rtvtk(&["check", d]);
    assert_eq!(out.status.code(), Some(1));
    let s = String::from_utf8_lossy(&out.stdout);
    assert!(s.contains("CRC32") && s.contains("000001.rays.parquet"), "{s}");
}

/// DuckDB (from PyPI; `scripts/check.sh` installs it) reads the ray and tree tables as plain Parquet and
/// counts what rtvtk counts: on the lossless files as recorded (kinds as codes) and on their plain
/// export (kinds as names).
#[test]
fn duckdb_reads_the_dataset_as_plain_parquet() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    demo(&dir);
    let plain = tmp.path().join("plain");
    assert!(rtvtk(&["export", dir.to_str().unwrap(), plain.to_str().unwrap()]).status.success());
    let info: Value = serde_json::from_slice(&rtvtk(&["info", dir.to_str().unwrap(), "--json"]).stdout).unwrap();
    let script = r#"
import sys, duckdb
for tag, d, shadow, t in [("", sys.argv[1], "kind_code = 1", "enc_t"), ("plain-", sys.argv[2], "kind = 'shadow'", "t")]:
    rays = f"read_parquet('{d}/segments/*.rays.parquet')"
    trees = f"read_parquet('{d}/segments/*.trees.parquet')"
    q = lambda s: duckdb.sql(s).fetchall()[0][0]
    print(tag + "rays", q(f"select count(*) from {rays}"))
    print(tag + "trees", q(f"select count(*) from {trees}"))
    print(tag + "shadow", q(f"select count(*) from {rays} where {shadow}"))
    print(tag + "misses", q(f"select count(*) from {rays} where {t} is null"))
    print(tag + "joined", q(f"select count(*) from {rays} r join {trees} t using (tree_id) where t.pixel_x = 3"))
"#;
    let out = Command::new("python3")
        .args(["-c", script, dir.to_str().unwrap(), plain.to_str().unwrap()])
        .output()
        .expect("python3 is needed for this test");
    assert!(
        out.status.success(),
        "DuckDB could not read the dataset (install it with `pip install duckdb`):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let s = String::from_utf8_lossy(&out.stdout);
    let get =
        |k: &str| -> u64 { s.lines().find_map(|l| l.strip_prefix(&format!("{k} "))).unwrap().trim().parse().unwrap() };
    for tag in ["", "plain-"] {
        assert_eq!(get(&format!("{tag}rays")), info["rays"].as_u64().unwrap());
        assert_eq!(get(&format!("{tag}trees")), info["trees"].as_u64().unwrap());
        assert_eq!(get(&format!("{tag}shadow")), info["rays_by_kind"]["shadow"].as_u64().unwrap());
        assert_eq!(get(&format!("{tag}misses")), info["misses"].as_u64().unwrap());
        assert_eq!(get(&format!("{tag}joined")), get("joined"));
    }
    // Pixel column x = 3 holds 24 rows x 2 samples of trees; their rays, counted by rtvtk.
    let ds = rl::Dataset::open(&dir).unwrap();
    let mut want = 0;
    for y in 0..24 {
        want += ds.trees_at_pixel(3, y, None).unwrap().iter().map(|t| t.rays.len() as u64).sum::<u64>();
    }
    assert_eq!(get("joined"), want);
}

/// `rtvtk export` turns a lossless dataset into a plain one whose float columns DuckDB reads with
/// exactly the values the store decodes from the original.
#[test]
fn export_gives_duckdb_the_plain_values() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    let plain = tmp.path().join("plain");
    demo(&dir);
    let out = rtvtk(&["export", dir.to_str().unwrap(), plain.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let info: Value = serde_json::from_slice(&rtvtk(&["info", plain.to_str().unwrap(), "--json"]).stdout).unwrap();
    assert_eq!(info["encoding"], "plain");
    assert!(rtvtk(&["check", plain.to_str().unwrap()]).status.success());
    // Exporting over a non-empty directory is refused and names it.
    let again = rtvtk(&["export", dir.to_str().unwrap(), plain.to_str().unwrap()]);
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("not empty"), "{}", String::from_utf8_lossy(&again.stderr));

    let ds = rl::Dataset::open(&dir).unwrap();
    let trees = ds.trees_at_pixel(5, 7, None).unwrap();
    let ids: Vec<String> = trees.iter().map(|t| t.info.id.0.to_string()).collect();
    let script = r#"
import sys, duckdb
d, ids = sys.argv[1], sys.argv[2]
for r in duckdb.sql(f"select tree_id, ray, origin_x::double, origin_y::double, origin_z::double, dir_x::double, dir_y::double, dir_z::double from read_parquet('{d}/segments/*.rays.parquet') where tree_id in ({ids}) order by tree_id, ray").fetchall():
    print(*[repr(v) for v in r])
"#;
    let out = Command::new("python3")
        .args(["-c", script, plain.to_str().unwrap(), &ids.join(",")])
        .output()
        .expect("python3 is needed for this test");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let want: Vec<(u64, u32, [u32; 6])> = trees
        .iter()
        .flat_map(|t| {
            t.rays.iter().map(move |r| {
                let v = [r.origin, r.direction].concat();
                (t.info.id.0, r.index, [0, 1, 2, 3, 4, 5].map(|k| v[k].to_bits()))
            })
        })
        .collect();
    let got: Vec<(u64, u32, [u32; 6])> = text
        .lines()
        .map(|l| {
            let w: Vec<&str> = l.split_whitespace().collect();
            let f = |k: usize| (w[k].parse::<f64>().unwrap() as f32).to_bits();
            (w[0].parse().unwrap(), w[1].parse().unwrap(), [f(2), f(3), f(4), f(5), f(6), f(7)])
        })
        .collect();
    assert!(!want.is_empty());
    assert_eq!(got, want);
}

#[test]
fn record_replays_a_sample_and_refuses_bad_input() {
    let tmp = tempfile::tempdir().unwrap();
    let full = tmp.path().join("full");
    let one = tmp.path().join("one");
    let base = ["record", "--scene", "cornell", "--size", "24x20", "--spp", "3", "--seed", "7", "--threads", "2"];
    let out = rtvtk(&[&base[..], &["--out", full.to_str().unwrap()]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let out = rtvtk(&[&base[..], &["--out", one.to_str().unwrap(), "--pixel", "11,9", "--sample", "2"]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let tree = |d: &Path| -> Value {
        let o = rtvtk(&["tree", d.to_str().unwrap(), "--pixel", "11,9", "--sample", "2", "--json"]);
        let mut v: Value = serde_json::from_slice(&o.stdout).unwrap();
        v[0]["tree_id"] = Value::Null; // ids differ between the runs; the rays must not
        v
    };
    assert_eq!(tree(&full), tree(&one));
    let info: Value = serde_json::from_slice(&rtvtk(&["info", one.to_str().unwrap(), "--json"]).stdout).unwrap();
    assert_eq!(info["trees"], 1);

    let bad = |args: &[&str], needle: &str| {
        let o = rtvtk(args);
        assert!(!o.status.success(), "{args:?} should fail");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(needle), "{args:?}: expected {needle:?} in {e}");
    };
    let d = tmp.path().join("x");
    let d = d.to_str().unwrap();
    bad(&["record", "--scene", "nowhere.obj", "--out", d], "nowhere.obj");
    bad(&["record", "--scene", "box", "--out", d], "unknown scene");
    bad(&["record", "--size", "0x5", "--out", d], "positive");
    bad(&["record", "--size", "24x20", "--window", "0,0,30,5", "--out", d], "window");
    bad(&["record", "--size", "24x20", "--pixel", "24,0", "--out", d], "outside");
    bad(&["record", "--record-kinds", "camera,photon", "--out", d], "unknown kind");
    bad(&["record", "--out", full.to_str().unwrap()], "not empty");
    bad(&["record", "--camera-pos", "0,nan,0", "--camera-target", "0,0,0", "--out", d], "NaN");
}

/// Output into a pipe closed early (`rtvtk ... | head`) ends the process quietly, not in a panic.
#[test]
fn closed_stdout_pipe_is_not_a_panic() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    // 256 trees of one pixel: far more JSON than a pipe buffer holds, so the write must fail.
    let out = rtvtk(&["record", "--size", "2x2", "--spp", "256", "--quiet", "--out", dir.to_str().unwrap()]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let mut child = Command::new(env!("CARGO_BIN_EXE_rtvtk"))
        .args(["tree", dir.to_str().unwrap(), "--pixel", "1,1", "--json"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_ne!(out.status.code(), Some(101), "exit code 101 is a Rust panic");
}

/// `rtvtk bench record` times the same record command with and without recording and reports
/// the ratio; it refuses arguments it sets itself and reports a failing record command.
#[test]
fn bench_record_reports_the_recording_overhead() {
    let args =
        ["bench", "record", "--runs", "1", "--scene", "cornell", "--size", "12x10", "--spp", "1", "--threads", "1"];
    let out = rtvtk(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = String::from_utf8_lossy(&out.stdout);
    assert!(s.contains("| 1 |") && s.contains("overhead"), "{s}");
    assert!(s.contains("recorded 120 trees"), "{s}");
    let o = rtvtk(&["bench", "record", "--scene", "cornell", "--out", "/tmp/x"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("sets --out itself"));
    let o = rtvtk(&["bench", "record", "--runs", "1", "--scene", "nowhere.obj"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("failed"), "{}", String::from_utf8_lossy(&o.stderr));
}

/// `rtvtk bench payload` records a scene lossless and with the lossy payload option, and sizes
/// each against pyarrow's default zstd Parquet of the same rays; bad bits and a missing scene
/// are refused by name.
#[test]
fn bench_payload_sizes_each_variant_against_pyarrow() {
    let out = rtvtk(&["bench", "payload", "--scenes", "cornell", "--size", "12x10", "--spp", "2", "--bits", "10"]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = String::from_utf8_lossy(&out.stdout);
    for want in ["pyarrow default zstd (baseline)", "| lossless |", "| payload 10 bits |", "| payload 10 bits, oct16 |"]
    {
        assert!(s.contains(want), "{want}: {s}");
    }
    // Each variant's ratio is a positive number (at 240 rays their order is noise: the trees'
    // order in the files depends on the tracing threads).
    let ratio = |name: &str| -> f64 {
        let line = s.lines().find(|l| l.contains(&format!("| {name} |"))).unwrap();
        line.split('|').nth(5).unwrap().trim().trim_end_matches('x').parse().unwrap()
    };
    for name in ["lossless", "payload 10 bits", "payload 10 bits, oct16"] {
        assert!(ratio(name) > 0.0, "{name}: {s}");
    }
    let o = rtvtk(&["bench", "payload", "--scenes", "cornell", "--bits", "30"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--bits 30"), "{}", String::from_utf8_lossy(&o.stderr));
    let o = rtvtk(&["bench", "payload", "--scenes", "nowhere.obj", "--size", "8x8", "--spp", "1"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("nowhere.obj"), "{}", String::from_utf8_lossy(&o.stderr));
}

/// `rtvtk bench scale` records a trace per step and times every whole-trace command on each in
/// its own process, then says how each grew; a bad step count is refused by name.
#[test]
fn bench_scale_times_every_command_at_every_step() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("scale");
    let d = dir.to_str().unwrap();
    let out = rtvtk(&["bench", "scale", "--steps", "3K,12K", "--spp", "2", "--no-render", "--dir", d]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let s = String::from_utf8_lossy(&out.stdout);
    for row in [
        "| record |",
        "| info |",
        "| check |",
        "| one pixel's tree",
        "| one tree by id",
        "| 2000 random tree fetches",
        "| SQL at one pixel |",
        "| per-pixel group-by",
    ] {
        assert!(s.contains(row), "{row}: {s}");
    }
    // Each step's fetch latencies, from `bench fetch` on its trace.
    assert_eq!(s.lines().filter(|l| l.contains(": one-tree fetch (lossless")).count(), 2, "{s}");
    assert!(s.contains("time growth") && s.contains("rays grew"), "{s}");
    // Each step's trace is about the rays asked for (the image size comes from a calibration).
    let rays: Vec<f64> = s.lines().filter_map(|l| l.split_once(" rays: ")?.0.trim().parse().ok()).collect();
    assert_eq!(rays.len(), 2, "{s}");
    assert!((rays[0] / 3e3 - 1.0).abs() < 0.5 && (rays[1] / 12e3 - 1.0).abs() < 0.3, "{rays:?}");
    // Traces are removed after their step unless --keep.
    assert!(std::fs::read_dir(&dir).unwrap().all(|e| !e.unwrap().file_name().to_string_lossy().starts_with("trace-")));
    let o = rtvtk(&["bench", "scale", "--steps", "lots"]);
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("expected a ray count"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

#[test]
fn demo_draws_a_picture_and_render_draws_layers() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    demo(&dir);
    // The demo's layered picture: 32x24 drawn 8x larger (small images are enlarged up to 8x), the
    // same on every backend (check.sh runs this test on Vulkan and on GL).
    let pic = image::open(dir.join("demo.png")).unwrap_or_else(|e| panic!("demo.png: {e}")).to_rgba8();
    assert_eq!(pic.dimensions(), (256, 192));
    common::snapshot::snapshot("demo", &pic);
    let d = dir.to_str().unwrap();
    let out_png = tmp.path().join("layers.png");
    let out = rtvtk(&[
        "render",
        d,
        "--layers",
        "image,composition,rays,bvh",
        "--pixel",
        "16,18",
        "--bvh-levels",
        "0..2",
        "--size",
        "320x240",
        "--out",
        out_png.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(&out_png).unwrap().to_rgba8();
    assert_eq!(img.dimensions(), (320, 240));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("rays: ") && err.contains("segments") && err.contains("bvh: "), "{err}");
    // Bad input: unknown layers list the known ones; a query layer without --sql; a query without
    // positions names the columns it needs.
    let e = rtvtk(&["render", d, "--layers", "image,trees", "--out", out_png.to_str().unwrap()]);
    assert_eq!(e.status.code(), Some(2));
    let msg = String::from_utf8_lossy(&e.stderr);
    assert!(msg.contains("unknown layer \"trees\"") && msg.contains("geometry, composition, rays"), "{msg}");
    let e = rtvtk(&["render", d, "--layers", "query", "--out", out_png.to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&e.stderr).contains("--sql"));
    let e = rtvtk(&[
        "render",
        d,
        "--layers",
        "query",
        "--sql",
        "SELECT kind FROM rays",
        "--out",
        out_png.to_str().unwrap(),
    ]);
    let msg = String::from_utf8_lossy(&e.stderr);
    assert!(msg.contains("origin_x") && msg.contains("x, y, z") && msg.contains("kind"), "{msg}");
    // No adapter at all (a backend this machine does not have, DX12 on Linux): exit 2, and the
    // error names both packages that give one. The demo still writes its trace first.
    let without_adapter = |args: &[&str]| {
        let e = Command::new(env!("CARGO_BIN_EXE_rtvtk")).args(args).env("WGPU_BACKEND", "dx12").output().unwrap();
        let msg = String::from_utf8_lossy(&e.stderr).to_string();
        assert_eq!(e.status.code(), Some(2), "{args:?}: {msg}");
        assert!(msg.contains("no GPU adapter") && msg.contains("mesa-vulkan-drivers") && msg.contains("libegl-mesa0"));
        msg
    };
    if cfg!(target_os = "linux") {
        without_adapter(&["render", d, "--out", out_png.to_str().unwrap()]);
        let bare = tmp.path().join("no-adapter");
        let msg = without_adapter(&["demo", "--out", bare.to_str().unwrap(), "--size", "16x12", "--spp", "1"]);
        assert!(msg.contains("the trace is written"), "{msg}");
        assert!(!bare.join("demo.png").exists());
        let check = rtvtk(&["check", bare.to_str().unwrap()]);
        assert!(check.status.success(), "the trace is whole: {}", String::from_utf8_lossy(&check.stdout));
    }
}

/// The real window under Xvfb (`scripts/check.sh` installs it): `rtvtk view DATASET --screenshot`
/// opens eframe's wgpu window, draws the pipeline, writes a screenshot and closes. Without Xvfb
/// the test fails at once naming it; a window that never draws fails it within minutes.
#[test]
fn view_opens_a_window_and_writes_a_screenshot() {
    let Some(xvfb) = ["/usr/bin/Xvfb", "/usr/local/bin/Xvfb"].into_iter().find(|p| Path::new(p).exists()) else {
        panic!(
            "this test needs Xvfb, the virtual X server (apt-get install xvfb xauth libxkbcommon-x11-0 libxcursor1 \
             libxi6 libxrandr2; scripts/check.sh installs it)"
        );
    };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("t");
    demo(&dir);
    // Xvfb picks a free display and writes its number once it accepts connections (-displayfd):
    // no guessing at a display nobody holds, nor at how long a loaded machine takes to start it.
    let args = ["-displayfd", "1", "-screen", "0", "1400x900x24", "-nolisten", "tcp"];
    let (mut x, number) = common::spawn_with_first_line(Command::new(xvfb).args(args));
    assert!(number.trim().parse::<u32>().is_ok(), "Xvfb did not start (it said {number:?})");
    let display = format!(":{}", number.trim());
    let shot = tmp.path().join("window.png");
    let mut view = Command::new(env!("CARGO_BIN_EXE_rtvtk"))
        .args(["view", dir.to_str().unwrap(), "--screenshot", shot.to_str().unwrap()])
        .env("DISPLAY", &display)
        .env_remove("WAYLAND_DISPLAY")
        .env("HOME", tmp.path())
        .env("XDG_DATA_HOME", tmp.path())
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(tmp.path().join("view.err")).unwrap())
        .spawn()
        .unwrap();
    let status = common::wait_at_most(&mut view, std::time::Duration::from_secs(300), "rtvtk view --screenshot");
    let stderr = std::fs::read(tmp.path().join("view.err")).unwrap_or_default();
    let out = std::process::Output { status, stdout: Vec::new(), stderr };
    let _ = x.kill();
    let _ = x.wait();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let img = image::open(&shot).unwrap_or_else(|e| panic!("{}: {e}", shot.display())).to_rgba8();
    assert_eq!(img.dimensions(), (1400, 860), "the window's size");
    // The render window shows the picture: many distinct colours on its left half.
    let mut colours = std::collections::HashSet::new();
    for y in (100..760).step_by(7) {
        for x in (20..700).step_by(7) {
            colours.insert(img.get_pixel(x, y).0);
        }
    }
    assert!(colours.len() > 200, "the render window looks empty ({} colours)", colours.len());
}
