#![allow(clippy::unwrap_used)]
//! CODE_STYLE.md's recipes, kept true: each test here fails when a recipe stops describing the
//! code (the SQL-function, table and tracer recipes have theirs beside the code: `query`'s
//! function tests, `tests/sql.rs`, `renderers/tests/tracers.rs`).

use std::path::{Path, PathBuf};

mod common;
use common::rtvtk;

/// The workspace's Rust sources outside tests (no `tests/`, `benches/` criterion targets of a
/// crate, or code after `#[cfg(test)]`), with their text.
fn sources() -> Vec<(PathBuf, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut out = Vec::new();
    let mut dirs = vec![root.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_string_lossy().to_string();
            if p.is_dir() {
                // A crate's own `benches/` holds criterion targets; the root's is the bench crate.
                let skipped = ["target", "tests", ".git", ".venv", "__pycache__", "node_modules"]
                    .contains(&name.as_str())
                    || (name == "benches" && d != root);
                if !skipped {
                    dirs.push(p);
                }
            } else if name.ends_with(".rs") {
                let text = std::fs::read_to_string(&p).unwrap();
                let code = text.split("#[cfg(test)]").next().unwrap_or("").to_string();
                out.push((p.strip_prefix(root).unwrap().to_path_buf(), code));
            }
        }
    }
    assert!(out.len() > 100, "{} sources", out.len());
    out
}

/// The files of non-test code that contain `needle`.
fn files_with(needle: &str) -> Vec<String> {
    let mut v: Vec<String> =
        sources().into_iter().filter(|(_, t)| t.contains(needle)).map(|(p, _)| p.display().to_string()).collect();
    v.sort();
    v
}

/// "a subcommand: one file in `src/`": every such file is a command with its help.
#[test]
fn every_subcommand_file_is_a_command() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut n = 0;
    for e in std::fs::read_dir(src).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().trim_end_matches(".rs").to_string();
        if ["main", "args"].contains(&name.as_str()) {
            continue;
        }
        let out = rtvtk(&[&name, "--help"]);
        assert!(out.status.success(), "src/{name}.rs is not the command `rtvtk {name}`");
        n += 1;
    }
    assert!(n >= 14, "{n} commands");
}

/// "One device per process": nothing but `rtvtk_gpu` opens a device.
#[test]
fn only_the_gpu_crate_opens_a_device() {
    assert_eq!(files_with(".request_device("), ["gpu/src/lib.rs"]);
}

/// "SQL: one engine": sessions are built in the query crate (and Ballista's in the cluster
/// crate), Flight SQL clients in the engine (and the load generator of `bench serve`).
#[test]
fn sql_is_reached_through_the_engine() {
    for f in files_with("SessionContext::new") {
        assert!(f.starts_with("query/") || f.starts_with("cluster/"), "{f} builds a SessionContext of its own");
    }
    assert_eq!(files_with("FlightSqlServiceClient::new("), ["benches/src/serve.rs", "query/src/engine.rs"]);
}

/// "a viewer component": every kind of the registry has its row in `viz/README.md` and is
/// drawn by `viz/tests/layers.rs`.
#[test]
fn every_component_kind_is_documented_and_drawn() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("viz/README.md")).unwrap();
    let tests = std::fs::read_to_string(root.join("viz/tests/layers.rs")).unwrap();
    let kinds = rtvtk_viz::registry();
    assert!(kinds.len() >= 7);
    for k in kinds {
        assert!(readme.contains(&format!("| `{}` |", k.kind)), "viz/README.md has no row for {}", k.kind);
        assert!(tests.contains(&format!("\"{}\"", k.kind)), "viz/tests/layers.rs never draws {}", k.kind);
    }
}

/// "a tracer": every choice is built by `gpu_tracer::tracer` and renders (the GPU one on this
/// machine's adapter; `scripts/check.sh` installs lavapipe).
#[test]
fn every_tracer_choice_is_built_and_renders() {
    use renderers::TracerChoice;
    let scene = std::sync::Arc::new(renderers::BuiltinScene::Cornell.build(1).unwrap());
    let bvh = std::sync::Arc::new(renderers::Bvh::build(&scene.tris));
    for choice in TracerChoice::ALL {
        let t = gpu_tracer::tracer(choice, scene.clone(), bvh.clone(), None)
            .unwrap_or_else(|e| panic!("the {choice} tracer: {e}"));
        assert_eq!(t.choice(), choice);
        let opts = renderers::RenderOptions { width: 8, height: 6, spp: 1, threads: 1, ..Default::default() };
        let (film, stats) = t.render(&opts, None, &|_| {}).unwrap();
        assert_eq!(film.pixels.len(), 48);
        assert!(stats.rays >= 48, "{choice}: {} rays", stats.rays);
        assert_eq!(t.device().is_some(), choice.on_gpu());
    }
}
