#![allow(clippy::unwrap_used)]
//! The dependency direction of the workspace, checked over `cargo metadata`:
//! store <- rl <- renderers; store <- query; viz may use all; nothing below viz pulls in
//! wgpu/egui; rl and store never pull in datafusion; no cycles.

use std::collections::{BTreeSet, HashMap};
use std::process::Command;

use serde_json::Value;

struct Graph {
    /// Package name by id.
    names: HashMap<String, String>,
    /// Normal (non-dev) dependencies by package id.
    deps: HashMap<String, Vec<String>>,
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
    for n in v["resolve"]["nodes"].as_array().unwrap() {
        let normal: Vec<String> = n["deps"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|d| d["dep_kinds"].as_array().unwrap().iter().any(|k| k["kind"].is_null() || k["kind"] == "build"))
            .map(|d| d["pkg"].as_str().unwrap().to_string())
            .collect();
        deps.insert(n["id"].as_str().unwrap().to_string(), normal);
    }
    Graph { names, deps }
}

impl Graph {
    fn id(&self, name: &str) -> String {
        self.names.iter().find(|(_, n)| *n == name).map(|(i, _)| i.clone()).unwrap()
    }

    /// Every package `name` pulls in (transitively, normal and build dependencies).
    fn closure(&self, name: &str) -> BTreeSet<String> {
        let mut seen = BTreeSet::new();
        let mut stack = vec![self.id(name)];
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
    let c = g.closure(krate);
    for b in banned {
        let hits: Vec<_> = c.iter().filter(|n| n == b || n.starts_with(&format!("{b}-"))).collect();
        assert!(hits.is_empty(), "{krate} must not depend on {b}, but pulls in {hits:?}");
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
    forbid(&g, "rtvtk-renderers", &["rtvtk-query", "rtvtk-viz", "datafusion"]);
    forbid(&g, "rtvtk-renderers", &["egui", "eframe", "winit"]);
    // The visualizer's GPU layer knows no egui; only the viewer on top of it does.
    forbid(&g, "rtvtk-viz", &["egui", "eframe", "winit", "rtvtk-viewer"]);
    assert!(g.closure("rtvtk-viewer").contains("rtvtk-viz"));
    assert!(g.closure("rtvtk-viewer").contains("eframe"));
    assert!(g.closure("rl").contains("rtvtk-store"));
    assert!(g.closure("rtvtk-renderers").contains("rl"));
    assert!(g.closure("rtvtk-query").contains("rtvtk-store"));
}

#[test]
fn no_workspace_cycles() {
    let g = graph();
    for krate in ["rtvtk-store", "rl", "rtvtk-query", "rtvtk-renderers", "rtvtk-viz", "rtvtk-viewer", "rtvtk"] {
        assert!(!g.closure(krate).contains(krate), "{krate} depends on itself");
    }
}
