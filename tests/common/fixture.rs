//! The recorded dataset the visualizer's and the viewer's tests draw (included by
//! `viz/tests/layers.rs` and `viz/viewer/tests/ui.rs` with `#[path]`): a 96x72, 2-spp
//! path-traced Cornell box with every ray, its scene, BVH, the BVH nodes each ray visited and the
//! image, recorded once per test process.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use rl::{Recorder, RecorderOptions};

/// The recording's image size.
pub const W: u32 = 96;
pub const H: u32 = 72;

/// The dataset's directory (removed when the process ends).
pub fn dataset() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("trace");
        let scene = renderers::BuiltinScene::Cornell.build(1).unwrap();
        let bvh = renderers::Bvh::build(&scene.tris);
        let opts = renderers::RenderOptions {
            width: W,
            height: H,
            spp: 2,
            threads: 2,
            record_visits: true,
            ..Default::default()
        };
        let rec =
            Recorder::create(&dir, RecorderOptions { payload: renderers::payload_schema(), ..Default::default() })
                .unwrap();
        renderers::describe_recording(&rec, &scene, &bvh, &opts).unwrap();
        rec.set_attributes([("image.png", "image.png")]).unwrap();
        let (film, _) = renderers::render(&scene, &bvh, &opts, Some(&rec), &|_| {}).unwrap();
        rec.finish().unwrap();
        film.write_png(&dir.join("image.png"), 1.0).unwrap();
        (tmp, dir)
    })
    .1
}
