//! The components of the pipeline, one module each.

pub mod bvh;
pub mod geometry;
pub mod picture;
pub mod query;
pub mod rays;
