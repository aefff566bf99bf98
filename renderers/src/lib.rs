#![doc = include_str!("../README.md")]

pub mod bvh;
mod choice;
pub mod converge;
mod error;
pub mod film;
pub mod geometry;
pub mod material;
pub mod plot;
pub mod render;
pub mod sampling;
pub mod scene;
mod scene_tables;
pub mod tracer;
pub mod tracers;
pub mod whatif;

pub use bvh::{Bvh, BvhLayout, Hit, TraversalStats};
pub use error::{Error, Result};
pub use film::Film;
pub use render::{RenderOptions, RenderStats, describe_recording, payload_schema, render};
pub use scene::{BuiltinScene, Camera, LoadReport, Material, MaterialKind, Scene, load_obj};
pub use scene_tables::load_scene;
pub use tracer::Bug;
pub use tracers::{CpuTracer, GpuTracerFactory, ProgressiveImage, Tracer, TracerChoice, register_gpu_tracer, tracer};
