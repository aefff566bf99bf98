#![allow(clippy::unwrap_used)]
//! The dependency direction of the workspace, checked over `cargo metadata` (tests'
//! dev-dependencies included): store <- rl <- renderers; store <- query; viz may use all;
//! nothing below viz pulls in wgpu/egui; rl and store never pull in datafusion; the demo's build
//! (`--no-default-features`) pulls in no SQL engine and no GUI; and inside each crate no two
//! modules import each other, directly or around a circle.

mod common;

use std::collections::{BTreeSet, HashMap};
use std::process::Command;

use serde_json::Value;

struct Graph {
    /// Package name by id.
    names: HashMap<String, String>,
    /// Normal (non-dev) dependencies by package id.
    deps: HashMap<String, Vec<String>>,
    /// Dev-dependencies by package id.
    dev: HashMap<String, Vec<String>>,
}

fn graph() -> Graph {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--locked", "--offline"])
        .current_dir(std::env::var_os("CARGO_MANIFEST_DIR").unwrap_or_else(|| env!("CARGO_MANIFEST_DIR").into()))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut names = HashMap::new();
    for p in v["packages"].as_array().unwrap() {
        names.insert(p["id"].as_str().unwrap().to_string(), p["name"].as_str().unwrap().to_string());
    }
    let mut deps = HashMap::new();
    let mut dev = HashMap::new();
    for n in v["resolve"]["nodes"].as_array().unwrap() {
        let dev_only: Vec<String> = n["deps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| d["dep_kinds"].as_array().unwrap().iter().any(|k| k["kind"] == "dev"))
            .map(|d| d["pkg"].as_str().unwrap().to_string())
            .collect();
        dev.insert(n["id"].as_str().unwrap().to_string(), dev_only);
        let normal: Vec<String> = n["deps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| d["dep_kinds"].as_array().unwrap().iter().any(|k| k["kind"].is_null() || k["kind"] == "build"))
            .map(|d| d["pkg"].as_str().unwrap().to_string())
            .collect();
        deps.insert(n["id"].as_str().unwrap().to_string(), normal);
    }
    Graph { names, deps, dev }
}

impl Graph {
    fn id(&self, name: &str) -> String {
        self.names.iter().find(|(_, n)| *n == name).map(|(i, _)| i.clone()).unwrap()
    }

    /// Every package `name` pulls in (transitively, normal and build dependencies).
    fn closure(&self, name: &str) -> BTreeSet<String> {
        self.closure_from(vec![self.id(name)])
    }

    /// Every package `name`'s tests pull in: its dev-dependencies and everything they need.
    fn test_closure(&self, name: &str) -> BTreeSet<String> {
        let id = self.id(name);
        let mut start = self.dev.get(&id).cloned().unwrap_or_default();
        start.push(id);
        let mut c = self.closure_from(start.clone());
        c.extend(start.iter().map(|i| self.names[i].clone()).filter(|n| n != name));
        c
    }

    fn closure_from(&self, start: Vec<String>) -> BTreeSet<String> {
        let mut seen = BTreeSet::new();
        let mut stack = start;
        while let Some(id) = stack.pop() {
            for d in self.deps.get(&id).into_iter().flatten() {
                if seen.insert(d.clone()) {
                    stack.push(d.clone());
                }
            }
        }
        seen.iter().map(|i| self.names[i].clone()).collect()
    }
}

fn forbid(g: &Graph, krate: &str, banned: &[&str]) {
    for (what, c) in [("", g.closure(krate)), (" (in its tests)", g.test_closure(krate))] {
        for b in banned {
            let hits: Vec<_> = c.iter().filter(|n| n == b || n.starts_with(&format!("{b}-"))).collect();
            assert!(hits.is_empty(), "{krate} must not depend on {b}{what}, but pulls in {hits:?}");
        }
    }
}

#[test]
fn dependency_direction_holds() {
    let g = graph();
    let gpu = ["wgpu", "egui", "eframe", "winit"];
    forbid(&g, "rtvtk-store", &["datafusion", "rl", "rtvtk-query", "rtvtk-renderers", "rtvtk-viz"]);
    forbid(&g, "rtvtk-store", &gpu);
    forbid(&g, "rl", &["datafusion", "rtvtk-query", "rtvtk-renderers", "rtvtk-viz"]);
    forbid(&g, "rl", &gpu);
    forbid(&g, "rtvtk-query", &["rl", "rtvtk-renderers", "rtvtk-viz"]);
    forbid(&g, "rtvtk-query", &gpu);
    // Ballista lives in the cluster crate alone: the query crate's codec needs datafusion-proto only.
    forbid(&g, "rtvtk-query", &["ballista"]);
    forbid(&g, "rtvtk-cluster", &gpu);
    forbid(&g, "rtvtk-cluster", &["rl", "rtvtk-renderers", "rtvtk-viz"]);
    assert!(g.closure("rtvtk-cluster").contains("ballista-executor"));
    forbid(&g, "rtvtk-renderers", &["rtvtk-query", "rtvtk-viz", "datafusion"]);
    forbid(&g, "rtvtk-renderers", &["egui", "eframe", "winit"]);
    // The one GPU context: wgpu alone, nothing of ours; the GPU tracer, viz and the viewer share it.
    forbid(
        &g,
        "rtvtk-gpu",
        &["rtvtk-store", "rl", "rtvtk-renderers", "rtvtk-query", "rtvtk-viz", "datafusion", "egui", "eframe", "winit"],
    );
    for user in ["rtvtk-gpu-tracer", "rtvtk-viz", "rtvtk-viewer"] {
        assert!(g.closure(user).contains("rtvtk-gpu"), "{user} must draw on rtvtk-gpu's device");
    }
    // The GPU tracer: wgpu over the renderers' scenes, nothing of the SQL engine, viz or GUI.
    forbid(&g, "rtvtk-gpu-tracer", &["datafusion", "rtvtk-query", "rtvtk-viz", "egui", "eframe", "winit"]);
    assert!(g.closure("rtvtk-gpu-tracer").contains("rtvtk-renderers"));
    // The visualizer's GPU layer knows no egui; only the viewer on top of it does.
    forbid(&g, "rtvtk-viz", &["egui", "eframe", "winit", "rtvtk-viewer"]);
    assert!(g.closure("rtvtk-viewer").contains("rtvtk-viz"));
    assert!(g.closure("rtvtk-viewer").contains("eframe"));
    assert!(g.closure("rl").contains("rtvtk-store"));
    assert!(g.closure("rtvtk-renderers").contains("rl"));
    assert!(g.closure("rtvtk-query").contains("rtvtk-store"));
    // The benchmarks: everything headless, no GUI; the CLI's `bench` calls them.
    forbid(&g, "rtvtk-bench", &["egui", "eframe", "winit", "rtvtk-viewer", "rtvtk-cluster"]);
    assert!(g.closure("rtvtk").contains("rtvtk-bench"));
    // The Python package's native module: the engine, the recorder, the headless pictures and
    // the viewer (`session.view()`, through `rtvtk-viewer` only: no egui of its own), no
    // Ballista (a user's notebook gets the same engine the CLI has).
    forbid(&g, "rtvtk-python", &["rtvtk-cluster", "ballista"]);
    let python = g.id("rtvtk-python");
    for gui in ["egui", "eframe", "winit"] {
        assert!(
            !g.deps[&python].iter().any(|d| g.names[d] == gui),
            "rtvtk-python reaches {gui} only through rtvtk-viewer"
        );
    }
    for needed in ["rtvtk-query", "rl", "rtvtk-viz", "rtvtk-viewer", "pyo3"] {
        assert!(g.closure("rtvtk-python").contains(needed), "rtvtk-python goes through {needed}");
    }
    // The Python package's pins: third-party crates only, and never under the demo's build.
    forbid(&g, "rtvtk-python-pins", &["rtvtk-store", "rl", "rtvtk-query", "rtvtk-renderers", "rtvtk-viz"]);
    assert!(!g.closure("rtvtk").contains("rtvtk-python-pins"));
    // The feature pins (scripts/feature-pins.py) pin third-party crates, none of ours.
    forbid(&g, "rtvtk-workspace-hack", &["rtvtk-store", "rl", "rtvtk-query", "rtvtk-renderers", "rtvtk-viz"]);
}

/// Every crate of the workspace is named by the checks above (a new crate gets its rules).
#[test]
fn every_crate_has_its_rules() {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["metadata", "--format-version", "1", "--locked", "--offline", "--no-deps"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let this = include_str!("layering.rs");
    let mut names = Vec::new();
    for p in v["packages"].as_array().unwrap() {
        let name = p["name"].as_str().unwrap();
        names.push(name.to_string());
        assert!(this.contains(&format!("\"{name}\"")), "tests/layering.rs has no rule naming {name}");
    }
    assert!(names.len() >= 12, "{names:?}");
}

/// The packages `cargo build -p PACKAGE --no-default-features` builds (normal and build
/// dependencies, as `cargo tree` resolves them).
fn minimal_build(package: &str) -> BTreeSet<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["tree", "--offline", "-p", package, "--no-default-features", "-e", "normal,build"])
        .args(["--prefix", "none", "-f", "{p}"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .collect()
}

#[test]
fn the_demo_build_has_no_sql_engine_and_no_gui() {
    // `cargo run --no-default-features -- demo`, the README's first command (issue 29).
    for package in ["rtvtk", "rtvtk-viz"] {
        let c = minimal_build(package);
        assert!(c.contains("wgpu") && c.contains("parquet"), "{package}: {c:?}");
        for banned in [
            "datafusion",
            "tonic",
            "arrow-flight",
            "egui",
            "eframe",
            "winit",
            "rtvtk-query",
            "rtvtk-viewer",
            "ballista",
        ] {
            assert!(!c.contains(banned), "{package} --no-default-features must not build {banned}");
        }
    }
}

/// The modules of the crate under `src` and the modules each one names as `crate::NAME` (test
/// modules left out): top-level modules only, `lib.rs`/`main.rs` being the root.
fn module_graph(src: &std::path::Path) -> std::collections::BTreeMap<String, BTreeSet<String>> {
    let mut g: std::collections::BTreeMap<String, BTreeSet<String>> = Default::default();
    let mut dirs = vec![src.to_path_buf()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                dirs.push(p);
                continue;
            }
            if p.extension().is_none_or(|x| x != "rs") {
                continue;
            }
            let rel = p.strip_prefix(src).unwrap();
            let first = rel.components().next().unwrap().as_os_str().to_string_lossy().to_string();
            let module = first.trim_end_matches(".rs").to_string();
            if module == "lib" || module == "main" {
                continue;
            }
            let text = std::fs::read_to_string(&p).unwrap();
            let code = common::without_test_items(&text);
            let code = code.as_str();
            let uses = g.entry(module.clone()).or_default();
            for (i, _) in code.match_indices("crate::") {
                let name: String =
                    code[i + 7..].chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
                if !name.is_empty() && name != module {
                    uses.insert(name);
                }
            }
        }
    }
    let known: BTreeSet<String> = g.keys().cloned().collect();
    for uses in g.values_mut() {
        uses.retain(|u| known.contains(u));
    }
    g
}

/// A circle of modules, if there is one (depth-first search).
fn circle(g: &std::collections::BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        g: &std::collections::BTreeMap<String, BTreeSet<String>>,
        m: &str,
        state: &mut HashMap<String, bool>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(m.to_string(), false);
        path.push(m.to_string());
        for n in g.get(m).into_iter().flatten() {
            match state.get(n) {
                Some(false) => {
                    let start = path.iter().position(|p| p == n).unwrap();
                    let mut c = path[start..].to_vec();
                    c.push(n.clone());
                    return Some(c);
                }
                Some(true) => {}
                None => {
                    if let Some(c) = visit(g, n, state, path) {
                        return Some(c);
                    }
                }
            }
        }
        path.pop();
        state.insert(m.to_string(), true);
        None
    }
    let mut state = HashMap::new();
    for m in g.keys() {
        if !state.contains_key(m)
            && let Some(c) = visit(g, m, &mut state, &mut Vec::new())
        {
            return Some(c);
        }
    }
    None
}

#[test]
fn no_module_imports_itself_around_a_circle() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    for dir in [
        "store/src",
        "rl-writer/src",
        "query/src",
        "renderers/src",
        "gpu/src",
        "gpu-tracer/src",
        "viz/src",
        "viz/viewer/src",
        "cluster/src",
        "benches/src",
        "python/src",
        "src",
    ] {
        let g = module_graph(&root.join(dir));
        assert!(g.len() > 1 || ["gpu/src", "cluster/src", "python/src"].contains(&dir), "{dir}: modules found {g:?}");
        if let Some(c) = circle(&g) {
            panic!("{dir}: modules import each other around a circle: {}", c.join(" -> "));
        }
    }
    // The check can fail: a circle is found where there is one.
    let mut g: std::collections::BTreeMap<String, BTreeSet<String>> = Default::default();
    g.insert("a".into(), ["b".to_string()].into());
    g.insert("b".into(), ["c".to_string()].into());
    g.insert("c".into(), ["a".to_string()].into());
    assert_eq!(circle(&g).unwrap(), ["a", "b", "c", "a"]);
}
