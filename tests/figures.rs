#![allow(clippy::unwrap_used)]
//! The README's section "The paper's figures": its `cargo run -- ...` lines are run as they are
//! written (paths under /tmp moved to a temporary directory) and each picture is compared with
//! the stored one the README shows (`tests/snapshots/`), so the recipes and pictures stay true.
//! Needs a GPU adapter (lavapipe or llvmpipe without a GPU), as `viz/tests/layers.rs` does.

mod common;

/// The command lines of the README's figure section, split into arguments (double quotes group).
fn recipes() -> Vec<Vec<String>> {
    let readme = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md")).unwrap();
    let section = readme.split("## The paper's figures").nth(1).expect("the README's figure section");
    let block = section.split("```sh").nth(1).and_then(|b| b.split("```").next()).expect("its sh block");
    block
        .lines()
        .filter_map(|l| l.strip_prefix("cargo run -- "))
        .map(|l| {
            let mut args = Vec::new();
            let (mut cur, mut quoted) = (String::new(), false);
            for c in l.chars() {
                match c {
                    '"' => quoted = !quoted,
                    ' ' if !quoted => {
                        if !cur.is_empty() {
                            args.push(std::mem::take(&mut cur));
                        }
                    }
                    c => cur.push(c),
                }
            }
            if !cur.is_empty() {
                args.push(cur);
            }
            args
        })
        .collect()
}

#[test]
fn the_readme_recipes_draw_the_papers_figures() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_str().unwrap().to_string();
    let lines = recipes();
    assert!(lines.iter().filter(|a| a[0] == "record").count() >= 2, "{lines:?}");
    let mut figures = Vec::new();
    for args in lines {
        let mut args: Vec<String> = args.into_iter().map(|a| a.replace("/tmp/", &format!("{root}/"))).collect();
        let out = args.iter().position(|a| a == "--out").map(|i| i + 1);
        let mut name = None;
        if let Some(i) = out.filter(|_| args[0] == "render") {
            let file = args[i].clone();
            name = Some(file.trim_end_matches(".png").to_string());
            args[i] = format!("{root}/{file}");
        }
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let run = common::rtvtk(&refs);
        let stdout = format!("{}{}", String::from_utf8_lossy(&run.stdout), String::from_utf8_lossy(&run.stderr));
        assert!(run.status.success(), "rtvtk {args:?}: {stdout}");
        if let Some(name) = name {
            let path = format!("{root}/{name}.png");
            let img = image::open(&path).unwrap_or_else(|e| panic!("{path}: {e}\n{stdout}")).to_rgba8();
            common::snapshot::snapshot(&name, &img);
            figures.push((name, stdout));
        }
    }
    let names: Vec<&str> = figures.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["fig3_ray_trees", "fig5_shadow_density", "fig6_wrong_shadows", "fig7_bvh_visits"]);
    // What each figure is of, from what the layers reported (on stderr).
    let said = |name: &str| figures.iter().find(|(n, _)| n == name).map(|(_, s)| s.clone()).unwrap();
    assert!(said("fig5_shadow_density").contains("density style, at most"), "{}", said("fig5_shadow_density"));
    let wrong = said("fig6_wrong_shadows");
    let rows: u64 = wrong
        .lines()
        .find_map(|l| l.strip_prefix("query: ")?.strip_suffix(" rows drawn")?.parse().ok())
        .unwrap_or_else(|| panic!("{wrong}"));
    assert!(rows > 20, "the bug's wrong shadow rays of the region: {rows}");
}
