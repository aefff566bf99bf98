#![allow(clippy::unwrap_used)]
//! The viewer driven through its UI with egui_kittest (on lavapipe, like every GPU test here):
//! tabs added, reordered, toggled and removed; a timer advancing trees; a console query drawn and
//! a row clicked selecting its ray; ctrl-click tracing a tree with no dataset; clicking a ray
//! picking it; a snapshot of the whole window.

use std::time::{Duration, Instant};

use egui_kittest::Harness;
use egui_kittest::kittest::Queryable;
use rtvtk_viewer::{Source, Viewer, ViewerOptions};
use rtvtk_viz::components::rays::RaysSettings;

#[path = "../../../tests/common/fixture.rs"]
mod fixture;
use fixture::{H, W, dataset};

fn harness(sources: Vec<Source>) -> Harness<'static, Viewer> {
    harness_with(ViewerOptions { sources, ..Default::default() })
}

fn harness_with(options: ViewerOptions) -> Harness<'static, Viewer> {
    // No adapter: fail in a second naming the package, not after waiting for frames.
    if let Err(e) = rtvtk_gpu::Gpu::shared() {
        panic!("the viewer tests need a GPU adapter: {e}");
    }
    let v = Viewer::new(options, None).unwrap();
    Harness::builder()
        .with_size([1280.0, 800.0])
        .with_max_steps(100_000)
        .wgpu()
        .build_ui_state(|ui, v: &mut Viewer| v.ui(ui), v)
}

/// Steps the UI until `done` holds (the worker and queries run on their own threads).
fn wait(h: &mut Harness<'static, Viewer>, what: &str, done: impl Fn(&Viewer) -> bool) {
    let t0 = Instant::now();
    loop {
        h.step();
        if done(h.state()) {
            // One more frame so the UI shows what arrived.
            h.step();
            return;
        }
        let errors: Vec<_> = h.state().state.messages.iter().filter(|m| m.0).map(|m| m.1.clone()).collect();
        // A GPU that cannot draw fails the test now, not after the time limit.
        if let Some(e) = errors.iter().find(|e| e.contains("GPU") || e.contains("adapter")) {
            panic!("waiting for {what}: the GPU failed: {e}");
        }
        let v = h.state();
        assert!(
            t0.elapsed() < Duration::from_secs(240),
            "timed out waiting for {what}; errors: {errors:?}; worker busy {}, connecting {}, console running {}",
            v.worker.busy(),
            v.queries.connecting,
            v.queries.is_running(&rtvtk_viewer::query_service::Tag::Console)
        );
        std::thread::sleep(Duration::from_millis(15));
    }
}

/// Clicks the widget labelled `label` and runs two frames (the click, then the frame that shows
/// its effect, whose layout the next query sees).
fn click(h: &mut Harness<'static, Viewer>, label: &str) {
    h.get_by_label(label).click();
    h.run_steps(2);
}

fn ready(v: &Viewer) -> bool {
    v.state.shown.is_some() && v.settled() && !v.state.layers.is_empty()
}

fn kinds(v: &Viewer) -> Vec<(String, bool)> {
    v.state.layers.iter().map(|l| (l.kind.clone(), l.enabled)).collect()
}

fn errors(v: &Viewer) -> Vec<String> {
    v.state.messages.iter().filter(|m| m.0).map(|m| m.1.clone()).collect()
}

#[test]
fn components_are_added_reordered_toggled_and_removed_from_the_pipeline_tab() {
    let mut h = harness(vec![Source::Dataset(dataset().to_path_buf())]);
    wait(&mut h, "the dataset to open and draw", ready);
    assert_eq!(
        kinds(h.state()),
        [("image", true), ("geometry", false), ("composition", true), ("rays", true)].map(|(k, e)| (k.to_string(), e))
    );
    // Every component has a tab.
    for l in h.state().state.layers.clone() {
        assert!(h.state().tree.tiles.find_pane(&rtvtk_viewer::app::Pane::Component(l.id.0)).is_some());
    }
    h.get_by_label("Add bvh").click();
    wait(&mut h, "the bvh component", |v| v.state.layers.iter().any(|l| l.kind == "bvh") && v.settled());
    let bvh = h.state().state.layers.iter().find(|l| l.kind == "bvh").unwrap().id.0;
    assert!(h.state().tree.tiles.find_pane(&rtvtk_viewer::app::Pane::Component(bvh)).is_some(), "a tab for bvh");
    assert_eq!(h.state().state.layers.last().unwrap().kind, "bvh", "added on top");
    // Move it one down: below rays.
    h.get_all_by_label("Down").last().unwrap().click();
    wait(&mut h, "the reorder", |v| v.state.layers.len() == 5 && v.state.layers[3].kind == "bvh" && v.settled());
    assert_eq!(h.state().state.layers[4].kind, "rays");
    // Hide the rays.
    let rays = h.state().state.layers.iter().find(|l| l.kind == "rays").unwrap().clone();
    h.get_by_label(&format!("{} #{}", rays.name, rays.id.0)).click();
    wait(&mut h, "rays hidden", |v| v.state.layers.iter().any(|l| l.kind == "rays" && !l.enabled) && v.settled());
    // Remove the bvh component: its tab goes too.
    let removes = h.get_all_by_label("Remove").count();
    assert!(removes >= 5, "a Remove per component in the pipeline tab, found {removes}");
    h.get_all_by_label("Remove").nth(3).unwrap().click();
    wait(&mut h, "bvh removed", |v| !v.state.layers.iter().any(|l| l.kind == "bvh") && v.settled());
    h.step();
    assert!(h.state().tree.tiles.find_pane(&rtvtk_viewer::app::Pane::Component(bvh)).is_none(), "its tab is gone");
    assert!(errors(h.state()).is_empty(), "{:?}", errors(h.state()));
    // A bad setting is refused with a message and the old settings stay.
    let id = rays.id.0;
    h.state_mut().state.patch(id, |r: &mut RaysSettings| r.line_width = -3.0);
    wait(&mut h, "the refusal", |v| v.state.layer_errors.contains_key(&id) && v.settled());
    let lw = h.state().state.layers.iter().find(|l| l.id.0 == id).unwrap().settings["line_width"].as_f64();
    assert_eq!(lw, Some(1.5), "the old line width stays");
}

#[test]
fn a_timer_advances_trees_and_steps_rays() {
    let mut h = harness(vec![Source::Dataset(dataset().to_path_buf())]);
    wait(&mut h, "the dataset", ready);
    click(&mut h, "Timers");
    click(&mut h, "Add timer");
    {
        let t = &mut h.state_mut().state.timers[0];
        t.every_ms = 30;
    }
    click(&mut h, "running");
    let tree_of =
        |v: &Viewer| v.state.layers.iter().find(|l| l.kind == "rays").and_then(|l| l.settings["tree"].as_u64());
    wait(&mut h, "a first tree", |v| tree_of(v).is_some());
    let first = tree_of(h.state()).unwrap();
    wait(&mut h, "the next tree", |v| tree_of(v).is_some_and(|t| t > first));
    let second = tree_of(h.state()).unwrap();
    assert!(second > first);
    assert!(h.state().state.timers[0].fired >= 2);
    // Stop it; step through the tree ray by ray with the buttons.
    h.get_by_label("running").click();
    wait(&mut h, "the timer to stop", |v| !v.state.timers[0].running && v.settled());
    let rays = h.state().state.layers.iter().find(|l| l.kind == "rays").unwrap().id.0;
    let tab = h.state().state.layers.iter().find(|l| l.id.0 == rays).map(|l| format!("#{rays} {}", l.name)).unwrap();
    click(&mut h, &tab);
    // A tree from the middle of the image (at the edge trees see nothing but the camera ray).
    let ds = store::Dataset::open(dataset()).unwrap();
    let tree = ds.trees_at_pixel(W / 2, H / 2, None).unwrap().into_iter().find(|t| t.rays.len() >= 3).unwrap();
    let t = tree.info.id.0;
    h.state_mut().state.tree_rays.insert(t, tree.rays.len() as u32);
    h.state_mut().state.patch(rays, |r: &mut RaysSettings| r.tree = Some(t));
    wait(&mut h, "the middle tree", |v| tree_of(v) == Some(t) && v.settled());
    click(&mut h, "First ray");
    wait(&mut h, "ray 0", |v| {
        v.state.layers.iter().any(|l| l.id.0 == rays && l.settings["ray_upto"].as_u64() == Some(0)) && v.settled()
    });
    click(&mut h, "Next ray");
    wait(&mut h, "ray 1", |v| {
        v.state.layers.iter().any(|l| l.id.0 == rays && l.settings["ray_upto"].as_u64() == Some(1)) && v.settled()
    });
    let report = h.state().state.layers.iter().find(|l| l.id.0 == rays).unwrap().report[0].clone();
    assert!(report.starts_with("rays: 2 segments"), "{report}");
    // Past the last ray, stepping starts again at the first.
    for _ in 1..tree.rays.len() {
        click(&mut h, "Next ray");
    }
    wait(&mut h, "the wrap to ray 0", |v| {
        v.state.layers.iter().any(|l| l.id.0 == rays && l.settings["ray_upto"].as_u64() == Some(0)) && v.settled()
    });
}

#[test]
fn a_console_query_is_drawn_and_a_clicked_row_selects_its_ray() {
    let dir = dataset();
    let opened = store::Dataset::opened();
    let mut h = harness(vec![Source::Dataset(dir.to_path_buf())]);
    wait(&mut h, "the dataset", ready);
    h.state_mut().state.console.sql =
        "SELECT concat('row-', CAST(tree_id AS VARCHAR), '-', CAST(ray AS VARCHAR)) AS label, \
         tree_id, ray, kind, depth, origin_x, origin_y, origin_z, dir_x, dir_y, dir_z, t FROM rays WHERE depth = 1 ORDER BY tree_id, ray LIMIT 40"
            .into();
    // A frame with the new text (the editor grows), so the button is where the click goes.
    h.run_steps(2);
    click(&mut h, "Run");
    assert!(h.state().state.console.history.last().is_some_and(|q| q.contains("row-")), "the query ran");
    wait(&mut h, "the query", |v| v.state.console.result.is_some() || v.state.console.error.is_some());
    let r = h.state().state.console.result.clone().unwrap_or_else(|| panic!("{:?}", h.state().state.console.error));
    assert_eq!(r.rows, 40);
    assert!(h.state().state.console.history.last().unwrap().contains("row-"));
    // Draw it with the query layer.
    click(&mut h, "Draw");
    wait(&mut h, "the query layer", |v| v.state.layers.iter().any(|l| l.kind == "query") && v.settled());
    let q = h.state().state.layers.iter().find(|l| l.kind == "query").unwrap().clone();
    assert_eq!(q.report[0], "query: 40 rows drawn", "{:?}", q.report);
    // Click the third row.
    let (tree, ray) = (r.int(2, "tree_id").unwrap(), r.int(2, "ray").unwrap());
    h.get_by_label(&format!("row-{tree}-{ray}")).click();
    wait(&mut h, "the inspector", |v| {
        v.state.inspector.fields.is_some() && v.state.inspector.tree.is_some() && v.settled()
    });
    let s = &h.state().state;
    assert_eq!(s.selection, Some(rtvtk_viewer::app::Selection { tree, ray: ray as u32 }));
    assert_eq!(s.console.selected_row, Some(2));
    let f = s.inspector.fields.as_ref().unwrap();
    assert_eq!(f.rows, 1);
    assert_eq!(f.int(0, "tree_id"), Some(tree));
    assert!(f.schema.fields().len() > 10, "every column, payload included");
    let t = s.inspector.tree.as_ref().unwrap();
    assert!(t.rows >= 2, "the tree has its camera ray and this one");
    let rays = s.layers.iter().find(|l| l.kind == "rays").unwrap();
    assert_eq!(rays.settings["selected_tree"].as_u64(), Some(tree), "the tree is highlighted");
    // A bad query is an inline error; the last result stays.
    h.state_mut().state.console.sql = "SELECT nope FROM rays".into();
    h.run_steps(2);
    click(&mut h, "Run");
    wait(&mut h, "the error", |v| v.state.console.error.is_some());
    assert!(h.state().state.console.error.as_ref().unwrap().contains("nope"));
    assert_eq!(h.state().state.console.result.as_ref().unwrap().rows, 40);
    // The layers, the console, the query layer and the inspector all asked one engine over one
    // open dataset.
    assert_eq!(store::Dataset::opened() - opened, 1, "the viewer opened the dataset once");
}

#[test]
fn ctrl_click_traces_a_pixel_with_no_dataset() {
    ctrl_click_traces(false);
}

/// `rtvtk view --tracer gpu`: the image is path-traced on the GPU and Ctrl-click records the
/// pixel's rays on the GPU.
#[test]
fn ctrl_click_traces_a_pixel_on_the_gpu() {
    ctrl_click_traces(true);
}

fn ctrl_click_traces(gpu: bool) {
    let mut h = harness_with(ViewerOptions {
        sources: vec![Source::Scene("cornell".into())],
        tracer: if gpu { renderers::TracerChoice::Gpu } else { renderers::TracerChoice::Path },
        ..Default::default()
    });
    wait(&mut h, "the scene", ready);
    let layer = |v: &Viewer, kind: &str| v.state.layers.iter().find(|l| l.kind == kind).unwrap().clone();
    let tracer = if gpu { "gpu" } else { "path" };
    assert_eq!(layer(h.state(), "rays").settings["tracer"], tracer);
    assert_eq!(layer(h.state(), "image").settings["source"], if gpu { "gpu" } else { "auto" });
    let (rect, size) = h.state().state.image_rect.unwrap();
    let (px, py) = (size[0] / 2, size[1] * 2 / 3);
    let pos = rect.min
        + egui::vec2(
            (px as f32 + 0.5) / size[0] as f32 * rect.width(),
            (py as f32 + 0.5) / size[1] as f32 * rect.height(),
        );
    h.hover_at(pos);
    h.step();
    for pressed in [true, false] {
        h.event_modifiers(
            egui::Event::PointerButton {
                pos,
                button: egui::PointerButton::Primary,
                pressed,
                modifiers: egui::Modifiers::COMMAND,
            },
            egui::Modifiers::COMMAND,
        );
        h.step();
    }
    wait(&mut h, "the traced tree", |v| v.state.traced.is_some() && v.settled());
    let (pixel, rays) = h.state().state.traced.unwrap();
    assert_eq!(pixel, [px, py]);
    assert!(rays >= 2, "a camera ray and at least a shadow ray, got {rays}");
    assert!(errors(h.state()).is_empty(), "{:?}", errors(h.state()));
    // The image layer path-traces progressively: the Plots tab draws its convergence curve.
    wait(&mut h, "a convergence curve", |v| v.state.layers.iter().any(|l| l.convergence.len() >= 3));
    let report = layer(h.state(), "image").report;
    assert!(report.iter().any(|r| r.contains("path traced")), "{report:?}");
    if gpu {
        assert!(report.iter().any(|r| r.contains("on the GPU")), "{report:?}");
    }
    click(&mut h, "Plots");
    h.get_by_label_contains("Convergence of the progressive image");
}

#[test]
fn clicking_a_ray_picks_it_and_the_window_matches_its_snapshot() {
    let mut h = harness(vec![Source::Dataset(dataset().to_path_buf())]);
    wait(&mut h, "the dataset", ready);
    // Only the trees of one pixel, drawn at the dataset's size: their camera rays and first hits
    // project onto that pixel.
    h.state_mut().state.resolution = rtvtk_viewer::app::Resolution::Dataset;
    let rays = h.state().state.layers.iter().find(|l| l.kind == "rays").unwrap().id.0;
    h.state_mut().state.patch(rays, |r: &mut RaysSettings| r.pixel = Some([40, 30]));
    wait(&mut h, "the pixel's trees", |v| {
        v.state.shown.as_ref().is_some_and(|s| s.size == [W, H])
            && v.state.layers.iter().any(|l| l.id.0 == rays && l.settings["pixel"] == serde_json::json!([40, 30]))
            && v.settled()
    });
    let (rect, size) = h.state().state.image_rect.unwrap();
    let pos = rect.min + egui::vec2(40.5 / size[0] as f32 * rect.width(), 30.5 / size[1] as f32 * rect.height());
    h.hover_at(pos);
    h.step();
    for pressed in [true, false] {
        h.event(egui::Event::PointerButton {
            pos,
            button: egui::PointerButton::Primary,
            pressed,
            modifiers: Default::default(),
        });
        h.step();
    }
    wait(&mut h, "the pick", |v| v.state.picked.is_some() && v.state.inspector.fields.is_some() && v.settled());
    let p = h.state().state.picked.unwrap();
    let rtvtk_viz::component::Picked::Ray { tree, .. } = p.item else { panic!("a recorded ray: {p:?}") };
    let f = h.state().state.inspector.fields.clone().unwrap();
    assert_eq!(
        (f.int(0, "pixel_x"), f.int(0, "pixel_y")),
        (Some(40), Some(30)),
        "a ray of pixel 40,30's trees (tree {tree})"
    );
    // The whole window, after a settled frame: the pixel's trees over the image at half the
    // window's resolution (the rays of a pixel do not depend on the tracing threads; tree ids
    // do, so the picked label is cleared; the top bar's temporary path and the status bar's
    // timings are masked).
    h.state_mut().state.resolution = rtvtk_viewer::app::Resolution::Fit(0.5);
    h.state_mut().state.picked = None;
    wait(&mut h, "the full view", |v| v.state.shown.as_ref().is_some_and(|s| s.size != [W, H]) && v.settled());
    for r in [h.state().state.status_rect, h.state().state.top_rect].into_iter().flatten() {
        h.mask(r);
    }
    h.snapshot_options("viewer", &egui_kittest::SnapshotOptions::new().threshold(2.0).max_failed_pixels(3000));
}

#[test]
fn the_console_runs_against_a_flight_sql_service_and_survives_losing_it() {
    // `rtvtk serve` in-process: the read-only Flight SQL service over the dataset.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let src = query::TraceSource { name: "trace".into(), path: dataset().to_path_buf() };
    let ctx = rt.block_on(query::session(&[src])).unwrap();
    let want = rt.block_on(async { ctx.sql("SELECT count(*) AS n FROM rays").await.unwrap().collect().await.unwrap() });
    let want = arrow::util::display::ArrayFormatter::try_new(want[0].column(0).as_ref(), &Default::default())
        .unwrap()
        .value(0)
        .to_string();
    let listener = query::service::bind("127.0.0.1:0").unwrap();
    let addr = query::service::local_addr(&listener).unwrap();
    // With a bearer token, as a shared service runs: the viewer must send it.
    let options = query::service::ServiceOptions { token: Some("viewer-T0ken".into()), ..Default::default() };
    let service = query::service::TraceService::with_options(ctx.clone(), options).unwrap();
    rt.spawn(async move { query::service::serve_with(service, listener, std::future::pending()).await });

    // The viewer is not told where the dataset lies: everything it draws comes from the service.
    let v = Viewer::new(
        ViewerOptions {
            sources: vec![Source::Served(String::new())],
            connect: Some(format!("grpc://{addr}")),
            token: Some("viewer-T0ken".into()),
            ..Default::default()
        },
        None,
    )
    .unwrap();
    let mut h = Harness::builder()
        .with_size([1280.0, 800.0])
        .with_max_steps(100_000)
        .wgpu()
        .build_ui_state(|ui, v: &mut Viewer| v.ui(ui), v);
    wait(&mut h, "the dataset and the connection", ready);
    assert!(h.state().queries.engine().unwrap().is_remote(), "the console asks the service");
    assert!(errors(h.state()).is_empty(), "{:?}", errors(h.state()));
    // The ray layer read its rays through the service: as many as the same layer reads locally.
    let rays_report = |v: &Viewer| {
        v.state.layers.iter().find(|l| l.kind == "rays").map(|l| l.report[0].split(" (").next().unwrap().to_string())
    };
    let remote = rays_report(h.state()).unwrap();
    let mut local = harness(vec![Source::Dataset(dataset().to_path_buf())]);
    wait(&mut local, "the local dataset", ready);
    assert_eq!(rays_report(local.state()).unwrap(), remote);
    assert!(!remote.starts_with("rays: 0 segments"), "{remote}");
    // The console lists the service's tables and functions (asked through information_schema).
    let (tables, functions) = h.state().queries.catalog();
    for t in ["rays", "trees", "bvh_nodes"] {
        assert!(tables.iter().any(|n| n == t), "{t} in {tables:?}");
    }
    assert!(functions.iter().any(|f| f == "aims_at_light"), "{functions:?}");
    h.state_mut().state.console.sql = "SELECT count(*) AS n FROM rays".into();
    h.run_steps(2);
    click(&mut h, "Run");
    wait(&mut h, "the service's answer", |v| v.state.console.result.is_some() || v.state.console.error.is_some());
    let r = h.state().state.console.result.clone().unwrap_or_else(|| panic!("{:?}", h.state().state.console.error));
    assert_eq!(r.value(0, "n"), Some(want.clone()), "the service's count is the local one");
    // The service goes away: the next query is an inline error, the last result stays, the UI runs.
    rt.shutdown_background();
    h.state_mut().state.console.sql = "SELECT 1 AS one".into();
    h.run_steps(2);
    click(&mut h, "Run");
    wait(&mut h, "the lost connection", |v| v.state.console.error.is_some());
    assert_eq!(h.state().state.console.result.as_ref().unwrap().value(0, "n"), Some(want));
    assert!(h.state().state.shown.is_some(), "the picture stays");
}
