//! `librl.a` for the tests that link a C or C++ program against it (`tests/c_abi.rs` here and
//! the workspace's `tests/cpp_renderer.rs`, which includes this file).

use std::path::PathBuf;

/// The static library cargo built beside this test: `target/<profile>/librl.a` when cargo uplifted
/// it (after `cargo build`), else the newest `target/<profile>/deps/librl-*.a` (a test-only build).
pub fn static_lib() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let deps = exe.parent().unwrap();
    let uplifted = deps.parent().unwrap().join("librl.a");
    let newest = std::fs::read_dir(deps)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n = e.file_name().to_string_lossy().to_string();
            n.starts_with("librl-") && n.ends_with(".a")
        })
        .max_by_key(|e| e.metadata().and_then(|m| m.modified()).ok())
        .map(|e| e.path());
    let candidates: Vec<PathBuf> =
        newest.into_iter().chain(std::iter::once(uplifted.clone()).filter(|p| p.exists())).collect();
    candidates
        .into_iter()
        .max_by_key(|p| p.metadata().and_then(|m| m.modified()).ok())
        .unwrap_or_else(|| panic!("expected {} or deps/librl-*.a (crate-type staticlib)", uplifted.display()))
}
