//! How a native call works on Python's behalf: its errors as `rtvtk.Error` subclasses, panics as
//! `rtvtk.InternalError` (never a crashed interpreter), and long work off the calling thread with
//! the GIL released, where Ctrl-C cancels it and a progress callback hears how far it got.

use std::future::Future;
use std::panic::AssertUnwindSafe;
use std::sync::mpsc::{Receiver, RecvTimeoutError, sync_channel};
use std::time::Duration;

use futures::FutureExt;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use query::Engine;

pyo3::create_exception!(_rtvtk, Error, PyException, "An rtvtk call failed; the message says what and where.");
pyo3::create_exception!(_rtvtk, DatasetError, Error, "A dataset could not be opened or read (path, manifest, files).");
pyo3::create_exception!(_rtvtk, QueryError, Error, "A query was refused or failed (SQL, tables, functions).");
pyo3::create_exception!(_rtvtk, RecordError, Error, "Recording input was refused (arrays, payload, scene, camera).");
pyo3::create_exception!(_rtvtk, RenderError, Error, "A picture or the viewer could not be made (layers, GPU, window).");
pyo3::create_exception!(_rtvtk, InternalError, Error, "rtvtk itself failed (a Rust panic): please report it.");

/// An `rtvtk.Error` with `e`'s message.
pub(crate) fn err(e: impl std::fmt::Display) -> PyErr {
    Error::new_err(e.to_string())
}

/// The error of a failed query: `rtvtk.DatasetError` when it failed because a table of the
/// dataset cannot be read (a broken table is unavailable alone: its queries name it, the rest
/// answer), otherwise `rtvtk.QueryError`, with the engine's message.
pub(crate) fn query_err(e: impl std::fmt::Display) -> PyErr {
    let message = e.to_string();
    if store::says_unavailable(&message) { DatasetError::new_err(message) } else { QueryError::new_err(message) }
}

/// An `rtvtk.RecordError` with `e`'s message.
pub(crate) fn record_err(e: impl std::fmt::Display) -> PyErr {
    RecordError::new_err(e.to_string())
}

/// The message of a panic's payload.
pub(crate) fn panic_text(p: Box<dyn std::any::Any + Send>) -> String {
    let what = p
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into());
    format!("rtvtk panicked: {what}")
}

/// Runs `f`, turning a panic into `rtvtk.InternalError`.
pub(crate) fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    std::panic::catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|p| Err(InternalError::new_err(panic_text(p))))
}

/// What long work reports while it runs: what it does, done, total (0: not known).
pub(crate) type Poll<'a> = &'a dyn Fn() -> Option<(String, u64, u64)>;

/// Work running elsewhere: its answer (`Err(message)`: the library's error; a panic arrives as
/// `Err` of the outer result) and how to stop it.
pub(crate) struct Job<T> {
    rx: Receiver<Result<Result<T, String>, String>>,
    cancel: Box<dyn FnOnce() + Send>,
}

/// `work` on a thread of its own.
pub(crate) fn on_thread<T: Send + 'static>(
    cancel: impl FnOnce() + Send + 'static,
    work: impl FnOnce() -> Result<T, String> + Send + 'static,
) -> Job<T> {
    let (tx, rx) = sync_channel(1);
    let spawned = std::thread::Builder::new().name("rtvtk-python".into()).spawn(move || {
        let r = std::panic::catch_unwind(AssertUnwindSafe(work)).map_err(panic_text);
        let _ = tx.send(r);
    });
    if let Err(e) = spawned {
        let (tx, rx2) = sync_channel(1);
        let _ = tx.send(Ok(Err(format!("cannot start a thread: {e}"))));
        return Job { rx: rx2, cancel: Box::new(cancel) };
    }
    Job { rx, cancel: Box::new(cancel) }
}

/// `fut` as a task of the engine's runtime; cancelling it drops the future (a query stops).
pub(crate) fn on_engine<T, F>(engine: &Engine, fut: F) -> Job<T>
where
    T: Send + 'static,
    F: Future<Output = Result<T, String>> + Send + 'static,
{
    let (tx, rx) = sync_channel(1);
    let task = engine.spawn(async move {
        let r = AssertUnwindSafe(fut).catch_unwind().await.map_err(panic_text);
        let _ = tx.send(r);
    });
    let abort = task.abort_handle();
    Job { rx, cancel: Box::new(move || abort.abort()) }
}

impl<T: Send> Job<T> {
    /// Waits with the GIL released, looking up every 50 ms: a Ctrl-C (a pending Python signal)
    /// cancels the work and raises its `KeyboardInterrupt` at once; `progress` (a Python
    /// callable taking what, done, total) hears `poll()`. A panic is `rtvtk.InternalError`; the
    /// library's error is the inner `Err`, for the caller to raise as its subclass.
    pub(crate) fn wait(
        self,
        py: Python<'_>,
        progress: Option<(&Bound<'_, PyAny>, Poll<'_>)>,
    ) -> PyResult<Result<T, String>> {
        let Job { mut rx, cancel } = self;
        loop {
            // The receiver goes along into the GIL-free wait and comes back (it is not `Sync`).
            let (got, back) = py.detach(move || (rx.recv_timeout(Duration::from_millis(50)), rx));
            rx = back;
            match got {
                Ok(Ok(answer)) => return Ok(answer),
                Ok(Err(panic)) => return Err(InternalError::new_err(panic)),
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(InternalError::new_err("rtvtk's worker stopped without an answer"));
                }
                Err(RecvTimeoutError::Timeout) => {}
            }
            if let Err(interrupt) = py.check_signals() {
                cancel();
                return Err(interrupt);
            }
            if let Some((callback, poll)) = &progress
                && let Some((what, done, total)) = poll()
            {
                callback.call1((what, done, total))?;
            }
        }
    }
}
