//! The one error type of the renderers crate.

use std::path::PathBuf;

/// What loading a scene or rendering can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot read {what}: {source} ({path})")]
    Io {
        what: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("{path}:{line}: {message}")]
    ObjLine { path: PathBuf, line: usize, message: String },

    #[error("cannot load OBJ/MTL: {message} ({path})")]
    Obj { path: PathBuf, message: String },

    #[error("invalid scene: {0}")]
    Scene(String),

    #[error("invalid render settings: {0}")]
    Settings(String),

    /// A tracer outside this crate failed (the GPU tracer: no adapter, a device error), in its words.
    #[error("{0}")]
    Tracer(String),

    #[error("cannot write image: {message} ({path})")]
    Image { path: PathBuf, message: String },

    #[error(transparent)]
    Record(#[from] rl::Error),

    #[error("cannot build a table: {0}")]
    Arrow(#[from] arrow::error::ArrowError),
}

/// Result alias of the renderers crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
