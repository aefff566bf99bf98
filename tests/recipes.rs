#![allow(clippy::unwrap_used)]
//! CODE_STYLE.md's recipes, kept true: each test here fails when a recipe stops describing the
//! code (the SQL-function, table and tracer recipes have theirs beside the code: `query`'s
//! function tests, `tests/sql.rs`, `renderers/tests/tracers.rs`).

use std::path::{Path, PathBuf};

mod common;
use common::rtvtk;

/// The workspace's Rust sources outside tests (no `tests/`, `benches/` criterion targets of a
/// crate, or `#[cfg(test)]` items: the code after a test module is kept), with their text.
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
                let code = common::without_test_items(&text);
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

/// Test items are cut out of a source and the code around them kept (a rule is not hidden by a
/// test helper above it).
#[test]
fn sources_lose_only_their_test_items() {
    let text = "fn a() {}\n#[cfg(test)]\nfn helper() { let s = \"}\"; let c = '{'; }\nfn b() {}\n#[cfg(test)]\nuse x::y;\nfn c<'a>() {}\n#[cfg(test)]\nmod tests {\n    fn t() { if x { } }\n}\nfn d() {}\n";
    let code = common::without_test_items(text);
    for kept in ["fn a()", "fn b()", "fn c<'a>()", "fn d()"] {
        assert!(code.contains(kept), "{kept} lost: {code}");
    }
    for cut in ["helper", "use x::y", "mod tests", "fn t()"] {
        assert!(!code.contains(cut), "{cut} kept: {code}");
    }
    // store/src/pages.rs has a test helper near its top: its code after that is still read.
    let pages = sources().into_iter().find(|(p, _)| p.ends_with("store/src/pages.rs")).unwrap().1;
    assert!(pages.lines().count() > 600, "{} lines of store/src/pages.rs read", pages.lines().count());
}

/// "a subcommand: one file with its clap arguments": `src/main.rs` declares none itself.
#[test]
fn subcommand_arguments_live_in_their_files() {
    let main =
        sources().into_iter().find(|(p, _)| p.ends_with("src/main.rs") && p.components().count() == 2).unwrap().1;
    assert!(!main.contains("#[arg("), "src/main.rs declares a subcommand's arguments: move them to its file");
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

/// "a viewer component": each kind is spelled once, as its settings' `KIND`; the registry, the
/// viewer and the worker name it through that constant.
#[test]
fn every_component_kind_is_spelled_once() {
    for k in rtvtk_viz::registry() {
        let k = k.kind;
        assert_eq!(files_with(&format!("const KIND: &'static str = \"{k}\"")).len(), 1, "the KIND of {k}");
        for pattern in [format!("kind: \"{k}\""), format!("kind == \"{k}\""), format!("kind() == \"{k}\"")] {
            assert_eq!(files_with(&pattern), Vec::<String>::new(), "`{pattern}`: use the component's KIND");
        }
    }
}

/// "a tracer": every choice is built by `renderers::tracer` (the GPU one once `gpu_tracer::register`
/// installed it) and renders (the GPU one on this
/// machine's adapter; `scripts/check.sh` installs lavapipe).
#[test]
fn every_tracer_choice_is_built_and_renders() {
    use renderers::TracerChoice;
    let scene = std::sync::Arc::new(renderers::BuiltinScene::Cornell.build(1).unwrap());
    let bvh = std::sync::Arc::new(renderers::Bvh::build(&scene.tris));
    assert!(renderers::tracer(TracerChoice::Gpu, scene.clone(), bvh.clone()).is_err(), "no GPU tracer registered yet");
    gpu_tracer::register();
    for choice in TracerChoice::ALL {
        let t = renderers::tracer(choice, scene.clone(), bvh.clone())
            .unwrap_or_else(|e| panic!("the {choice} tracer: {e}"));
        assert_eq!(t.choice(), choice);
        let opts = renderers::RenderOptions { width: 8, height: 6, spp: 1, threads: 1, ..Default::default() };
        let (film, stats) = t.render(&opts, None, &|_| {}).unwrap();
        assert_eq!(film.pixels.len(), 48);
        assert!(stats.rays >= 48, "{choice}: {} rays", stats.rays);
        assert_eq!(t.device().is_some(), choice.on_gpu());
    }
}
