#![doc = include_str!("../README.md")]

pub mod camera;
pub mod component;
pub mod components;
pub mod draw;
mod error;
pub mod formats;
pub mod headless;
pub mod legend;
pub mod lines;
pub mod pipeline;
pub mod registry;
pub mod sources;
pub mod splat;

pub use camera::ViewCamera;
pub use component::{Component, ComponentId, LayerRole, Legend, Picked};
pub use error::{Error, Result};
pub use pipeline::Pipeline;
pub use registry::{ComponentInfo, make, registry};
pub use rtvtk_gpu::Gpu;
pub use sources::Sources;
