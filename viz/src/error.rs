//! The one error type of the viz crate.

use std::path::PathBuf;

/// What building or rendering a pipeline can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// No adapter, a device error, a failed read-back (`rtvtk_gpu`).
    #[error(transparent)]
    Gpu(#[from] rtvtk_gpu::Error),

    #[error("unknown layer {name:?}: expected one of {known}")]
    UnknownLayer { name: String, known: String },

    #[error("layer `{layer}` cannot be drawn: {message}")]
    Layer { layer: String, message: String },

    #[error("query result cannot be drawn: {0}")]
    Columns(String),

    #[error("invalid setting: {0}")]
    Settings(String),

    #[error("cannot read or write {what}: {message} ({path})")]
    File { what: &'static str, path: PathBuf, message: String },

    #[error(transparent)]
    Store(#[from] store::Error),

    #[cfg(feature = "sql")]
    #[error(transparent)]
    Query(#[from] query::Error),

    #[cfg(feature = "sql")]
    #[error("SQL: {0}")]
    DataFusion(#[from] datafusion::error::DataFusionError),

    #[error(
        "this rtvtk was built without its SQL engine (the `sql` feature, on by default): \
         rebuild with default features for queries, the query and heatmap layers and BVH visits"
    )]
    NoSql,

    #[error(transparent)]
    Render(#[from] renderers::Error),

    #[error(transparent)]
    Record(#[from] rl::Error),

    #[error(transparent)]
    GpuTracer(#[from] gpu_tracer::Error),

    #[error("Arrow: {0}")]
    Arrow(#[from] arrow::error::ArrowError),
}

/// Result alias of the viz crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
