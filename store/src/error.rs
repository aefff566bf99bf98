//! The one error type of the store crate.

use std::path::PathBuf;

/// Everything that can go wrong reading or writing a trace dataset.
///
/// Messages say what was expected and put the path last.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("I/O error while {action}: {source} ({path})")]
    Io {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },

    #[error("invalid manifest: {message} ({path})")]
    Manifest { path: PathBuf, message: String },

    #[error(
        "dataset format version {found} is newer than this build supports (up to {supported}); upgrade rtvtk ({path})"
    )]
    NewerFormat { path: PathBuf, found: u32, supported: u32 },

    #[error("segment {segment} file is missing: expected it to exist as the manifest lists it ({path})")]
    MissingFile { segment: u32, path: PathBuf },

    #[error("segment {segment} file is truncated or was changed: expected {expected} bytes, found {found} ({path})")]
    SizeMismatch { segment: u32, path: PathBuf, expected: u64, found: u64 },

    #[error("segment {segment} file is corrupted: expected CRC32 {expected:08x}, computed {found:08x} ({path})")]
    Checksum { segment: u32, path: PathBuf, expected: u32, found: u32 },

    #[error("segment {segment}'s tree table is unavailable: {message} ({path})")]
    TreeTable { segment: u32, path: PathBuf, message: String },

    #[error("optional table `{name}`: {message} ({path})")]
    Table { name: String, path: PathBuf, message: String },

    #[error("cannot decode Parquet: {source} ({path})")]
    Parquet {
        path: PathBuf,
        #[source]
        source: parquet::errors::ParquetError,
    },

    #[error("cannot build Arrow data: {source} ({context})")]
    Arrow {
        context: String,
        #[source]
        source: arrow::error::ArrowError,
    },

    #[error("column `{field}` does not match the declared schema: expected {expected}, found {found} ({path})")]
    Schema { path: PathBuf, field: String, expected: String, found: String },

    #[error("inconsistent data in {what}: {message} ({path})")]
    Corrupt { path: PathBuf, what: String, message: String },

    #[error("invalid payload declaration: {0}")]
    PayloadDecl(String),

    #[error("dataset directory is not empty; refusing to overwrite an existing trace ({path})")]
    NotEmpty { path: PathBuf },

    #[error("invalid encoding: {0}")]
    Encoding(String),

    #[error("no tree with id {0} in this trace")]
    NoSuchTree(u64),
}

/// The message of something that cannot be read (a broken table, or what is made from one):
/// "`what` is unavailable: `why`". Every layer says it in these words, so a caller tells a broken
/// table from a wrong request by [`says_unavailable`], on this side of a service or the other.
pub fn unavailable(what: &str, why: impl std::fmt::Display) -> String {
    format!("{what} is unavailable: {why}")
}

/// Whether `message` says something is [`unavailable`] (a broken table), rather than that the
/// request was wrong.
pub fn says_unavailable(message: &str) -> bool {
    message.contains(" is unavailable: ")
}

/// Why a whole-dataset or tree table's file cannot be read, from the error reading it gave, in
/// words that do not repeat the path (the `Table` / `TreeTable` error around it names it).
pub(crate) fn unreadable(e: Error) -> String {
    match e {
        Error::Table { message, .. } | Error::TreeTable { message, .. } => message,
        Error::Parquet { source, .. } => format!("cannot be read as Parquet: {source}"),
        Error::Corrupt { what, message, .. } => format!("inconsistent data in {what}: {message}"),
        Error::Schema { field, expected, found, .. } => {
            format!("column `{field}` does not match the table's schema: expected {expected}, found {found}")
        }
        e => e.to_string(),
    }
}

/// Result alias of the store crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

pub(crate) fn io_err(action: &'static str, path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> Error {
    let path = path.into();
    move |source| Error::Io { action, path, source }
}

pub(crate) fn pq_err(path: impl Into<PathBuf>) -> impl FnOnce(parquet::errors::ParquetError) -> Error {
    let path = path.into();
    move |source| Error::Parquet { path, source }
}

pub(crate) fn arrow_err(context: impl Into<String>) -> impl FnOnce(arrow::error::ArrowError) -> Error {
    let context = context.into();
    move |source| Error::Arrow { context, source }
}
