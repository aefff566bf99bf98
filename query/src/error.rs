//! The one error type of the query crate.

/// Everything that can go wrong setting up or running a query over traces.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(transparent)]
    Store(#[from] store::Error),

    #[error("query error: {0}")]
    DataFusion(#[from] datafusion::error::DataFusionError),

    #[error("dataset name {name:?} is not valid: expected letters, digits or '_', not starting with a digit")]
    BadName { name: String },

    #[error("{0}")]
    BadArgument(String),

    #[error("query service: {0}")]
    Service(String),

    #[error("dataset name {name:?} is given twice")]
    DuplicateName { name: String },
}

/// Result alias of the query crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
