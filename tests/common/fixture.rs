//! The recorded dataset the visualizer's and the viewer's tests draw (included by
//! `viz/tests/layers.rs` and `viz/viewer/tests/ui.rs` with `#[path]`): a 96x72, 2-spp
//! path-traced Cornell box with every ray, its scene, BVH, the BVH nodes each ray visited and the
//! image, recorded once per test process (`tests/faults.rs` records its own with `record_cornell`).

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
        let options = RecorderOptions { payload: renderers::payload_schema(), ..Default::default() };
        record_cornell(&dir, [W, H], options, |rec| rec.set_attributes([("image.png", "image.png")]).unwrap());
        (tmp, dir)
    })
    .1
}

/// Records the path-traced Cornell box at `size`, 2 samples per pixel on two threads, every ray
/// with its scene, BVH and the BVH nodes each ray visited, into `dir` with `options`; `more`
/// adds what else the recording holds before it finishes. The image goes to `dir/image.png`.
pub fn record_cornell(dir: &Path, [width, height]: [u32; 2], options: RecorderOptions, more: impl FnOnce(&Recorder)) {
    let scene = renderers::BuiltinScene::Cornell.build(1).unwrap();
    let bvh = renderers::Bvh::build(&scene.tris);
    let opts =
        renderers::RenderOptions { width, height, spp: 2, threads: 2, record_visits: true, ..Default::default() };
    let rec = Recorder::create(dir, options).unwrap();
    renderers::describe_recording(&rec, &scene, &bvh, renderers::TracerChoice::Path, &opts).unwrap();
    more(&rec);
    let (film, _) = renderers::render(&scene, &bvh, renderers::TracerChoice::Path, &opts, Some(&rec), &|_| {}).unwrap();
    rec.finish().unwrap();
    film.write_png(&dir.join("image.png"), 1.0).unwrap();
}
