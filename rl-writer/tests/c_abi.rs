#![allow(clippy::unwrap_used)]
//! The C ABI: a recursive C tracer records through `rl.h`, reads back in C, then Rust checks
//! the trees.

use std::path::PathBuf;
use std::process::Command;

use rl::Dataset;

#[path = "support/static_lib.rs"]
mod support;
use support::static_lib;

#[test]
fn c_tracer_records_and_reads_back() {
    // At run time: a target directory reused from a checkout elsewhere keeps env!'s old path.
    let manifest_dir =
        std::env::var_os("CARGO_MANIFEST_DIR").map_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")), PathBuf::from);
    let tmp = tempfile::tempdir().unwrap();
    let bin = tmp.path().join("tracer");
    let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
    let out = Command::new(&cc)
        .arg("-std=c99")
        .arg("-Wall")
        .arg("-Werror")
        .arg(manifest_dir.join("tests/c/tracer.c"))
        .arg("-I")
        .arg(manifest_dir.join("include"))
        .arg(static_lib())
        .args(["-lpthread", "-ldl", "-lm", "-o"])
        .arg(&bin)
        .output()
        .unwrap_or_else(|e| panic!("cannot run the C compiler {cc:?}: {e}"));
    assert!(out.status.success(), "compiling tracer.c failed:\n{}", String::from_utf8_lossy(&out.stderr));

    let trace = tmp.path().join("trace");
    let out = Command::new(&bin).arg(&trace).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "tracer failed:\n{stdout}\n{}", String::from_utf8_lossy(&out.stderr));
    let nums = |prefix: &str| -> (u64, u64) {
        let line = stdout.lines().find(|l| l.starts_with(prefix)).unwrap();
        let v: Vec<u64> = line.split_whitespace().skip(1).map(|x| x.parse().unwrap()).collect();
        (v[0], v[1])
    };
    let (trees, rays) = nums("recorded");
    assert_eq!(nums("read"), (trees, rays));
    assert_eq!(trees, 16 * 12);

    let ds = Dataset::open(&trace).unwrap();
    assert_eq!((ds.tree_count(), ds.ray_count()), (trees, rays));
    let report = ds.check();
    assert!(report.is_ok(), "{:?}", report.errors);
    // The scene and camera set through rlSetTriangles / rlSetCamera.
    let tris = ds.table("triangles").unwrap().expect("a triangles table");
    assert_eq!(tris.num_rows(), 2);
    let cam = store::scene::CameraAttrs::from_attributes(&ds.manifest().attributes).unwrap().unwrap();
    assert_eq!((cam.target, cam.fov_y, cam.width, cam.height), ([0.0, 0.0, -1.0], 60.0, 16, 12));
    // Some rays recurse (specular under camera, shadow rays one level down).
    let s = ds.stats();
    assert!(s.rays_by_kind()["specular"] > 0 && s.rays_by_kind()["shadow"] > 0);
    assert!(s.rays_by_depth().len() >= 3);
    // The opaque payload is there, 16 bytes per ray; its bounce field equals the depth.
    assert_eq!(ds.manifest().bytes_payload, Some(rl::BytesPayload::Fixed(16)));
    let t = ds.tree(rl::TreeId(100)).unwrap();
    let col = arrow::array::AsArray::as_fixed_size_binary(t.column("payload").unwrap());
    for r in &t.rays {
        let p = col.value(r.index as usize);
        let bounce = i32::from_le_bytes(p[12..16].try_into().unwrap());
        assert_eq!(bounce, i32::from(r.depth));
    }
}
