//! The image: linear radiance per pixel, written as PNG (tone-mapped, sRGB) or EXR (linear).

use std::path::Path;

use glam::Vec3A;

use crate::{Error, Result};

/// A width × height image of linear RGB radiance.
#[derive(Clone, Debug, PartialEq)]
pub struct Film {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<Vec3A>,
}

fn srgb(x: f32) -> u8 {
    let x = if x.is_finite() { x.clamp(0.0, 1.0) } else { 0.0 };
    let v = if x <= 0.003_130_8 { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 };
    (v * 255.0 + 0.5) as u8
}

impl Film {
    pub fn new(width: u32, height: u32) -> Film {
        Film { width, height, pixels: vec![Vec3A::ZERO; width as usize * height as usize] }
    }

    /// A film from `width` × `height` linear RGB triples, row-major from the top-left pixel
    /// (another renderer's image, handed over as flat floats).
    pub fn from_rgb(width: u32, height: u32, rgb: &[f32]) -> Result<Film> {
        let n = width as usize * height as usize;
        if width == 0 || height == 0 || rgb.len() != n * 3 {
            return Err(Error::Settings(format!(
                "a {width}x{height} image needs {} floats (RGB per pixel), got {}",
                n * 3,
                rgb.len()
            )));
        }
        Ok(Film { width, height, pixels: rgb.chunks_exact(3).map(|c| Vec3A::new(c[0], c[1], c[2])).collect() })
    }

    pub fn get(&self, x: u32, y: u32) -> Vec3A {
        self.pixels[(y * self.width + x) as usize]
    }

    /// Mean of all pixels.
    pub fn mean(&self) -> Vec3A {
        self.pixels.iter().copied().sum::<Vec3A>() / self.pixels.len().max(1) as f32
    }

    /// Tone-mapped 8-bit sRGB pixels, `channels` (3: RGB, 4: RGBA with opaque alpha) per pixel.
    pub fn to_srgb8(&self, exposure: f32, channels: usize) -> Vec<u8> {
        let mut buf = Vec::with_capacity(self.pixels.len() * channels);
        for p in &self.pixels {
            let p = *p * exposure;
            buf.extend_from_slice(&[srgb(p.x), srgb(p.y), srgb(p.z), 255][..channels.clamp(3, 4)]);
        }
        buf
    }

    /// Tone-mapped 8-bit sRGB PNG (exposure `exposure`, then clamped).
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<()> {
        let buf = self.to_srgb8(exposure, 3);
        image::save_buffer(path, &buf, self.width, self.height, image::ColorType::Rgb8)
            .map_err(|e| Error::Image { path: path.into(), message: e.to_string() })
    }

    /// Linear 32-bit float OpenEXR.
    pub fn write_exr(&self, path: &Path) -> Result<()> {
        exr::prelude::write_rgb_file(path, self.width as usize, self.height as usize, |x, y| {
            let p = self.pixels[y * self.width as usize + x];
            (p.x, p.y, p.z)
        })
        .map_err(|e| Error::Image { path: path.into(), message: e.to_string() })
    }
}
