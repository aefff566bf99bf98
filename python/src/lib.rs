//! `rtvtk._rtvtk`: the native half of the Python package (`python/rtvtk/__init__.py` is the
//! other). It adds no road of its own: SQL goes through `query::Engine` (results cross to pyarrow
//! through the Arrow C stream interface, `__arrow_c_stream__`, with no copy), recording through
//! `rl::Recorder`, pictures through `rtvtk_viz::headless::render` and the window through
//! `rtvtk_viewer::run` — what the CLI calls. Long calls run with the GIL released, Ctrl-C
//! cancels them, and every error is an `rtvtk.Error` subclass carrying the library's message
//! (`work`).

mod options;
mod recorder;
mod session;
mod work;

use pyo3::prelude::*;

use recorder::NativeRecorder;
use session::{ArrowStream, NativeReport, Session};
use work::{DatasetError, Error, InternalError, QueryError, RecordError, RenderError, err, guarded, on_thread};

/// For the package's tests: panics inside a native call (`"call"`) or inside work running off
/// the calling thread (`"thread"`), which must reach Python as `rtvtk.InternalError`.
#[pyfunction]
fn _panic_for_tests(py: Python<'_>, place: &str) -> PyResult<()> {
    match place {
        "call" => guarded(|| -> PyResult<()> { panic!("a test asked for a panic in a call") }),
        "thread" => on_thread(|| {}, || -> Result<(), String> { panic!("a test asked for a panic in a worker") })
            .wait(py, None)?
            .map_err(err),
        other => Err(err(format!("unknown place {other:?}"))),
    }
}

#[pymodule]
fn _rtvtk(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("Error", py.get_type::<Error>())?;
    m.add("DatasetError", py.get_type::<DatasetError>())?;
    m.add("QueryError", py.get_type::<QueryError>())?;
    m.add("RecordError", py.get_type::<RecordError>())?;
    m.add("RenderError", py.get_type::<RenderError>())?;
    m.add("InternalError", py.get_type::<InternalError>())?;
    m.add_class::<Session>()?;
    m.add_class::<ArrowStream>()?;
    m.add_class::<NativeReport>()?;
    m.add_class::<NativeRecorder>()?;
    m.add_function(wrap_pyfunction!(_panic_for_tests, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
