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

/// Fuzzing the C ABI (a stable-toolchain harness, run with the tests): random sequences of
/// `rlBeginTree`, `rlAddRay` (NULL or valid pointers, NaN/Inf/huge values, any kind and prim,
/// payloads of the wrong size), `rlDescendTree`/`rlAscendTree` out of order, `rlEndTree` with
/// no tree open, `rlRegisterKind` (NULL, empty, over-long names), `rlSetPointLights` (NULL) and
/// `rlFlush`, then `rlFinish`, then reading back through `rlOpen`/`rlNextTree`/`rlReadTree`/
/// `rlReadRay`/`rlSeekTree` with NULL outputs. No call may panic (the ABI would report
/// "internal error: rl panicked"), each refused call sets `rlLastError`, and the dataset
/// written holds exactly the trees whose `rlEndTree` succeeded and passes `check`.
/// Cases: `PROPTEST_CASES` (default 256); shrunk failures in `tests/c_abi.regressions`.
mod fuzz {
    use proptest::prelude::*;
    use rl::capi::*;
    use std::ffi::{CStr, CString, c_void};

    #[derive(Clone, Debug)]
    enum Op {
        Begin(u32, u32, u32),
        Add { origin: Option<[f32; 3]>, dir: Option<[f32; 3]>, t: f32, kind: i32, prim: i64, payload: Option<usize> },
        Descend,
        Ascend,
        End,
        Kind(Option<String>),
        Lights(Option<usize>),
        Flush,
    }

    fn float() -> impl Strategy<Value = f32> {
        prop_oneof![Just(f32::NAN), Just(f32::INFINITY), Just(-0.0), Just(f32::MAX), Just(1e-40), -10.0f32..10.0]
    }

    fn op() -> impl Strategy<Value = Op> {
        let v3 = || proptest::option::weighted(0.9, [float(), float(), float()]);
        prop_oneof![
            2 => (0u32..4, 0u32..4, 0u32..3).prop_map(|(x, y, s)| Op::Begin(x, y, s)),
            6 => (v3(), v3(), float(), -2i32..40, -2i64..5, proptest::option::of(0usize..16))
                .prop_map(|(origin, dir, t, kind, prim, payload)| Op::Add { origin, dir, t, kind, prim, payload }),
            2 => Just(Op::Descend),
            2 => Just(Op::Ascend),
            2 => Just(Op::End),
            1 => proptest::option::of("[a-z]{0,80}").prop_map(Op::Kind),
            1 => proptest::option::of(0usize..3).prop_map(Op::Lights),
            1 => Just(Op::Flush),
        ]
    }

    fn last_error() -> String {
        // SAFETY: rlLastError returns a NUL-terminated string owned by this thread.
        unsafe { CStr::from_ptr(rlLastError()) }.to_string_lossy().into_owned()
    }

    /// A refused call's error, which must not be a caught panic.
    fn refused(what: &str) -> Result<(), TestCaseError> {
        let e = last_error();
        prop_assert!(!e.contains("panicked"), "{what}: {e}");
        prop_assert!(!e.is_empty(), "{what}: refused without an error message");
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig {
            failure_persistence: Some(Box::new(proptest::test_runner::FileFailurePersistence::WithSource("regressions"))),
            ..ProptestConfig::default()
        })]

        #[test]
        fn any_call_sequence_gives_errors_or_a_sound_trace(
            payload_size in prop_oneof![Just(0usize), Just(4), Just(12)],
            ops in proptest::collection::vec(op(), 0..60),
        ) {
            run(payload_size, &ops)?;
        }
    }

    /// Found by the harness: a ray of a kind code neither built in nor registered made the
    /// dataset fail `check` (its kind was not declared in the manifest); it is now `kind5`.
    #[test]
    fn an_unregistered_kind_code_is_declared() {
        let ray =
            Op::Add { origin: Some([0.0; 3]), dir: Some([0.0, 0.0, 1.0]), t: 1.0, kind: 5, prim: 0, payload: None };
        run(0, &[Op::Begin(0, 0, 0), ray, Op::End]).unwrap();
    }

    /// Found by the harness: an empty tree ended inside another starts at the same row as it,
    /// and `check`'s tiling order put it second.
    #[test]
    fn an_empty_nested_tree_tiles_the_file() {
        let ray = Op::Add {
            origin: Some([f32::NAN; 3]),
            dir: Some([f32::NAN; 3]),
            t: f32::NAN,
            kind: 0,
            prim: 0,
            payload: None,
        };
        run(0, &[Op::Begin(0, 0, 0), ray, Op::Begin(0, 0, 0), Op::End, Op::End]).unwrap();
    }

    /// Found by the harness: a code recorded without a name, then named after its segment was
    /// sealed, was left undeclared when the last segment (one empty tree) did not use it.
    #[test]
    fn a_code_named_after_its_segment_stays_declared() {
        let ray =
            Op::Add { origin: Some([0.0; 3]), dir: Some([0.0, 0.0, 1.0]), t: 1.0, kind: 16, prim: 0, payload: None };
        let ops =
            [Op::Begin(0, 0, 0), ray, Op::End, Op::Flush, Op::Begin(0, 0, 0), Op::End, Op::Kind(Some("a".into()))];
        run(0, &ops).unwrap();
    }

    fn run(payload_size: usize, ops: &[Op]) -> Result<(), TestCaseError> {
        {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("trace");
            let c_path = CString::new(path.to_str().unwrap()).unwrap();
            // SAFETY: a NUL-terminated path.
            let rec = unsafe { rlInit(c_path.as_ptr(), payload_size) };
            prop_assert!(!rec.is_null(), "{}", last_error());
            let buf = [7u8; 16];
            let mut ended = 0u64;
            for op in ops {
                // SAFETY: `rec` is live until rlFinish; every pointer is NULL or points at as many
                // values as the call reads.
                let rc: i64 = unsafe {
                    match op {
                        Op::Begin(x, y, s) => i64::from(rlBeginTree(rec, *x, *y, *s)),
                        Op::Add { origin, dir, t, kind, prim, payload } => {
                            let o = origin.as_ref().map_or(std::ptr::null(), |v| v.as_ptr());
                            let d = dir.as_ref().map_or(std::ptr::null(), |v| v.as_ptr());
                            let (p, n) = match payload {
                                Some(n) => (buf.as_ptr().cast::<c_void>(), *n),
                                None => (std::ptr::null(), 0),
                            };
                            i64::from(rlAddRay(rec, o, d, *t, *kind, *prim, p, n))
                        }
                        Op::Descend => i64::from(rlDescendTree(rec)),
                        Op::Ascend => i64::from(rlAscendTree(rec)),
                        Op::End => {
                            let id = rlEndTree(rec);
                            if id >= 0 {
                                ended += 1;
                            }
                            id
                        }
                        Op::Kind(name) => {
                            let c = name.as_ref().map(|n| CString::new(n.as_str()).unwrap());
                            i64::from(rlRegisterKind(rec, c.as_ref().map_or(std::ptr::null(), |c| c.as_ptr())))
                        }
                        Op::Lights(n) => {
                            let v = [0.5f32; 9];
                            match n {
                                Some(n) => i64::from(rlSetPointLights(rec, *n, v.as_ptr(), v.as_ptr())),
                                None => i64::from(rlSetPointLights(rec, 2, std::ptr::null(), std::ptr::null())),
                            }
                        }
                        Op::Flush => i64::from(rlFlush(rec)),
                    }
                };
                if rc < 0 {
                    refused(&format!("{op:?}"))?;
                }
            }
            // SAFETY: finished once.
            if unsafe { rlFinish(rec) } < 0 {
                refused("rlFinish")?;
            }
            // What was ended is there, and sound.
            let ds = rl::Dataset::open(&path);
            prop_assert!(ds.is_ok(), "{:?}", ds.err());
            let ds = ds.unwrap();
            prop_assert_eq!(ds.tree_count(), ended);
            let report = ds.check();
            prop_assert!(report.is_ok(), "{:?}", report.errors);
            // Reading back through the C reader, NULL outputs included.
            // SAFETY: a NUL-terminated path; the reader is closed once.
            unsafe {
                let reader = rlOpen(c_path.as_ptr());
                prop_assert!(!reader.is_null(), "{}", last_error());
                let mut trees = 0u64;
                let mut payload = [0u8; 16];
                let mut rays = 0u64;
                loop {
                    let mut t = std::mem::zeroed::<RlTree>();
                    let rc = rlReadTree(reader, if trees.is_multiple_of(2) { &mut t } else { std::ptr::null_mut() });
                    if rc < 0 {
                        refused("rlReadTree")?;
                    }
                    if rc <= 0 {
                        break;
                    }
                    trees += 1;
                    loop {
                        let mut r = std::mem::zeroed::<RlRay>();
                        let rc = rlReadRay(reader, &mut r, payload.as_mut_ptr().cast(), payload.len());
                        if rc < 0 {
                            refused("rlReadRay")?;
                        }
                        if rc <= 0 {
                            break;
                        }
                        rays += 1;
                    }
                    let rc = rlNextTree(reader);
                    if rc < 0 {
                        refused("rlNextTree")?;
                    }
                    if rc == 0 {
                        break;
                    }
                }
                prop_assert_eq!((trees, rays), (ended, ds.ray_count()));
                if rlSeekTree(reader, u64::MAX) < 0 {
                    refused("rlSeekTree")?;
                }
                rlClose(reader);
            }
        }
        Ok(())
    }
}
