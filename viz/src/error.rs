//! The one error type of the viz crate.

use std::path::PathBuf;

/// What building or rendering a pipeline can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(
        "no GPU adapter found ({0}); install a Vulkan driver, e.g. Mesa's software rasterizer lavapipe: \
         `apt-get install mesa-vulkan-drivers libvulkan1` (Debian/Ubuntu)"
    )]
    NoAdapter(String),

    #[error("cannot open the GPU device: {0}")]
    Device(String),

    #[error("GPU error: {0}")]
    Gpu(String),

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

    #[error("Arrow: {0}")]
    Arrow(#[from] arrow::error::ArrowError),
}

/// Result alias of the viz crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
