//! Pictures against stored PNGs, shared by the root tests (`tests/common`) and the visualizer's
//! layer tests (`viz/tests/layers.rs` includes this file): each crate keeps its pictures in its
//! own `tests/snapshots/`.

#![allow(clippy::unwrap_used)]

use std::path::Path;

/// Compares a picture with the crate's `tests/snapshots/NAME.png` (written when missing outside
/// CI, rewritten with UPDATE_SNAPSHOTS=1): at most 0.5% of the pixels may differ by more than
/// 24/255 in a channel (rasterizers, lavapipe and llvmpipe among them, differ slightly at edges).
pub fn snapshot(name: &str, img: &image::RgbaImage) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/snapshots").join(format!("{name}.png"));
    if std::env::var_os("UPDATE_SNAPSHOTS").is_some() || !path.exists() && std::env::var_os("CI").is_none() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        img.save(&path).unwrap();
        return;
    }
    let want = image::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_rgba8();
    assert_eq!(want.dimensions(), img.dimensions(), "{name}: size");
    let bad = want
        .pixels()
        .zip(img.pixels())
        .filter(|(a, b)| a.0.iter().zip(b.0.iter()).any(|(x, y)| x.abs_diff(*y) > 24))
        .count();
    let allowed = (want.width() * want.height()) as usize / 200;
    if bad > allowed {
        let new = path.with_extension("new.png");
        img.save(&new).unwrap();
        panic!("{name}: {bad} pixels differ (allowed {allowed}); wrote {}", new.display());
    }
}
