//! [`TracerChoice`]: which tracer renders, the one enum that says it (a leaf module: the render
//! driver and the `Tracer` trait both read it).

use crate::{Error, Result};

/// A tracer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum TracerChoice {
    /// The CPU path tracer.
    #[default]
    Path,
    /// The CPU Whitted tracer.
    Whitted,
    /// The GPU path tracer (WGSL compute through wgpu; lavapipe or llvmpipe without a GPU): the
    /// same scene, camera, materials and recorded columns as `Path`.
    Gpu,
}

impl TracerChoice {
    /// Every tracer, in the order of [`TracerChoice::NAMES`].
    pub const ALL: [TracerChoice; 3] = [TracerChoice::Path, TracerChoice::Whitted, TracerChoice::Gpu];
    /// The names the choice is written with (`cpu` is also read, as `path`).
    pub const NAMES: &'static [&'static str] = &["path", "whitted", "gpu"];

    pub fn name(self) -> &'static str {
        match self {
            TracerChoice::Path => "path",
            TracerChoice::Whitted => "whitted",
            TracerChoice::Gpu => "gpu",
        }
    }

    /// Whether it traces on the GPU.
    pub fn on_gpu(self) -> bool {
        self == TracerChoice::Gpu
    }
}

impl std::fmt::Display for TracerChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for TracerChoice {
    type Err = Error;

    fn from_str(s: &str) -> Result<TracerChoice> {
        match s {
            "path" | "cpu" => Ok(TracerChoice::Path),
            "whitted" => Ok(TracerChoice::Whitted),
            "gpu" => Ok(TracerChoice::Gpu),
            _ => Err(Error::Settings(format!("tracer {s:?}: expected path (or cpu), whitted or gpu"))),
        }
    }
}
