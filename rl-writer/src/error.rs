//! The one error type of the rl crate.

/// What recording or reading with `rl` can report.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error(transparent)]
    Store(#[from] store::Error),

    /// Writing failed (disk full, permission denied, ...). Trees sealed before it stay intact.
    #[error(
        "writing the trace failed: {source}; {lost_trees} trees could not be written (trees sealed before the failure are intact)"
    )]
    Write {
        #[source]
        source: store::Error,
        lost_trees: u64,
    },

    /// The client used the API wrongly; the data was still recorded as well as it could be.
    #[error("{count} recording mistakes (trees were still written): {}", first.join("; "))]
    Misuse { count: u64, first: Vec<String> },

    #[error("a recording worker thread panicked")]
    WorkerPanicked,

    #[error("this recorder is in {mode} mode; {what} needs {needed} mode")]
    WrongMode { mode: &'static str, what: &'static str, needed: &'static str },

    #[error("invalid argument: {0}")]
    InvalidArgument(String),
}

/// Result alias of the rl crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;
