/// Errors of the viewer.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("cannot start a runtime: {0}")]
    Runtime(String),
    #[error("the window failed: {0}")]
    Window(String),
    #[error(transparent)]
    Viz(#[from] viz::Error),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
