//! `Session`: SQL, analyses, checks and pictures over `query::Engine`; query results as Arrow
//! streams pyarrow takes without a copy.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use arrow::array::{RecordBatch, RecordBatchReader};
use arrow::datatypes::SchemaRef;
use arrow::error::ArrowError;
use arrow::ffi_stream::FFI_ArrowArrayStream;
use futures::StreamExt;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyCapsule, PyDict};
use query::Engine;

use crate::options::{Analysis, describe_field, render_request};
use crate::work;
use crate::work::{DatasetError, Error, InternalError, QueryError, RenderError, err, guarded, on_engine, on_thread};

/// Why a query's stream stopped early: Ctrl-C (the `KeyboardInterrupt` to raise) or the engine's
/// error (raised as `rtvtk.QueryError`). pyarrow sees only an Arrow error; the Python side asks
/// the stream for this to raise the right exception.
pub(crate) type Failure = Arc<Mutex<Option<PyErr>>>;

/// A query's batches as an Arrow `RecordBatchReader`, pulled from the engine's stream on demand.
pub(crate) struct EngineReader {
    pub(crate) engine: Arc<Engine>,
    pub(crate) stream: datafusion::execution::SendableRecordBatchStream,
    pub(crate) schema: SchemaRef,
    pub(crate) failure: Failure,
}

impl Iterator for EngineReader {
    type Item = Result<RecordBatch, ArrowError>;

    /// The next batch; every 50 ms of waiting, a look for Ctrl-C (which stops the query). It is
    /// called through the C stream interface, where a panic must not unwind: one becomes the
    /// stream's `rtvtk.InternalError`.
    fn next(&mut self) -> Option<Self::Item> {
        match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.pull())) {
            Ok(item) => item,
            Err(p) => {
                let message = work::panic_text(p);
                self.fail(InternalError::new_err(message.clone()), &message)
            }
        }
    }
}

impl EngineReader {
    pub(crate) fn fail(&self, e: PyErr, what: &str) -> Option<Result<RecordBatch, ArrowError>> {
        if let Ok(mut f) = self.failure.lock() {
            f.get_or_insert(e);
        }
        Some(Err(ArrowError::ExternalError(what.into())))
    }

    pub(crate) fn pull(&mut self) -> Option<Result<RecordBatch, ArrowError>> {
        let engine = self.engine.clone();
        loop {
            // `Stream::next` is cancel-safe: a timed-out wait loses no batch.
            let next = self.stream.next();
            match engine.block_on(async { tokio::time::timeout(Duration::from_millis(50), next).await }) {
                Ok(None) => return None,
                Ok(Some(Ok(b))) => return Some(Ok(b)),
                Ok(Some(Err(e))) => {
                    let message = e.to_string();
                    return self.fail(work::query_err(&message), &message);
                }
                Err(_) => {
                    if let Some(interrupt) = Python::attach(|py| py.check_signals().err()) {
                        return self.fail(interrupt, "the query was interrupted (Ctrl-C)");
                    }
                }
            }
        }
    }
}

impl RecordBatchReader for EngineReader {
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }
}

/// A query's result not yet read: pyarrow takes it through the Arrow PyCapsule interface
/// (`pa.table(x)`, `pa.RecordBatchReader.from_stream(x)`), once.
#[pyclass(module = "rtvtk._rtvtk")]
pub(crate) struct ArrowStream {
    pub(crate) reader: Mutex<Option<Box<dyn RecordBatchReader + Send>>>,
    pub(crate) failure: Failure,
}

#[pymethods]
impl ArrowStream {
    #[pyo3(signature = (requested_schema=None))]
    fn __arrow_c_stream__<'py>(
        &self,
        py: Python<'py>,
        requested_schema: Option<Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyCapsule>> {
        let _ = requested_schema;
        let reader = self
            .reader
            .lock()
            .map_err(err)?
            .take()
            .ok_or_else(|| QueryError::new_err("this result was already read (a query's stream is read once)"))?;
        // The capsule points at the stream struct; the consumer moves it out (leaving `release`
        // null), and whatever is left is released when the capsule goes.
        PyCapsule::new_with_value(py, FFI_ArrowArrayStream::new(reader), c"arrow_array_stream")
    }

    /// Why the stream stopped early, if it did (a `KeyboardInterrupt` or `rtvtk.QueryError`),
    /// handed over once.
    fn failure(&self) -> PyResult<Option<PyErr>> {
        Ok(self.failure.lock().map_err(err)?.take())
    }
}

/// An analysis's report (`query::analyze::Report`): markdown and the grids it shows.
#[pyclass(module = "rtvtk._rtvtk", frozen)]
pub(crate) struct NativeReport {
    pub(crate) report: query::analyze::Report,
}

#[pymethods]
impl NativeReport {
    #[getter]
    fn markdown(&self) -> &str {
        &self.report.markdown
    }

    /// `[(name, title, width, height, cell, values)]`, values row-major from the top-left cell.
    #[allow(clippy::type_complexity)]
    fn grids(&self) -> Vec<(String, String, usize, usize, usize, Vec<f64>)> {
        let g = &self.report.grids;
        g.iter().map(|g| (g.name.clone(), g.title.clone(), g.width, g.height, g.cell, g.values.clone())).collect()
    }

    /// Writes `report.md` and a heatmap PNG per grid into `dir`, as `rtvtk analyze --out` does;
    /// returns the path of `report.md`.
    fn save(&self, py: Python<'_>, dir: std::path::PathBuf) -> PyResult<String> {
        let r = &self.report;
        py.detach(|| {
            let maps: Vec<(&str, renderers::plot::Heatmap)> = r
                .grids
                .iter()
                .map(|g| {
                    (g.name.as_str(), renderers::plot::Heatmap::pixels(&g.title, g.width, g.height, &g.values, g.cell))
                })
                .collect();
            renderers::plot::write_report(&dir, &r.markdown, &maps)
        })
        .map(|p| p.display().to_string())
        .map_err(|e| Error::new_err(e.to_string()))
    }
}

/// SQL over datasets, in this process or at an `rtvtk serve` service.
#[pyclass(module = "rtvtk._rtvtk", frozen)]
pub(crate) struct Session {
    pub(crate) engine: Arc<Engine>,
}

#[pymethods]
impl Session {
    /// Opens datasets, `[(name, path), ...]`: the first one's tables are also unqualified.
    #[staticmethod]
    fn open(py: Python<'_>, datasets: Vec<(String, String)>) -> PyResult<Session> {
        let sources: Vec<query::TraceSource> =
            datasets.into_iter().map(|(name, path)| query::TraceSource { name, path: path.into() }).collect();
        if sources.is_empty() {
            return Err(DatasetError::new_err("no dataset given"));
        }
        guarded(|| {
            let engine = py
                .detach(|| Engine::blocking(Engine::open(&sources, &query::SessionOptions::default())))
                .map_err(|e| DatasetError::new_err(e.to_string()))?;
            Ok(Session { engine: Arc::new(engine) })
        })
    }

    /// Connects to `rtvtk serve` at `url` (`grpc://HOST:PORT`).
    #[staticmethod]
    #[pyo3(signature = (url, token=None))]
    fn connect(py: Python<'_>, url: String, token: Option<String>) -> PyResult<Session> {
        guarded(|| {
            let engine = py
                .detach(|| Engine::blocking(Engine::connect(&url, token)))
                .map_err(|e| QueryError::new_err(e.to_string()))?;
            Ok(Session { engine: Arc::new(engine) })
        })
    }

    /// A read-only query's result as a stream (see `ArrowStream`); planning can be interrupted.
    fn stream(&self, py: Python<'_>, sql: String) -> PyResult<ArrowStream> {
        let engine = self.engine.clone();
        let job = on_engine(&self.engine, async move { engine.stream(&sql).await.map_err(|e| e.to_string()) });
        let stream = job.wait(py, None)?.map_err(work::query_err)?;
        let schema = stream.schema();
        let failure = Failure::default();
        let reader = EngineReader { engine: self.engine.clone(), stream, schema, failure: failure.clone() };
        Ok(ArrowStream { reader: Mutex::new(Some(Box::new(reader))), failure })
    }

    /// The tables queries can name (schema-qualified outside `public`).
    fn tables(&self, py: Python<'_>) -> PyResult<Vec<String>> {
        let engine = self.engine.clone();
        let job = on_engine(&self.engine, async move { engine.catalog().await.map_err(|e| e.to_string()) });
        Ok(job.wait(py, None)?.map_err(QueryError::new_err)?.tables)
    }

    /// Where queries run, in words.
    fn describe(&self) -> String {
        self.engine.describe()
    }

    /// Queries this session has run (analyses run many).
    fn queries_run(&self) -> u64 {
        self.engine.queries_run()
    }

    /// Counts, segments, payload and attributes of a dataset open here (`None`: the first).
    #[pyo3(signature = (name=None))]
    fn info<'py>(&self, py: Python<'py>, name: Option<&str>) -> PyResult<Bound<'py, PyDict>> {
        let ds = self.dataset(name)?;
        let d = PyDict::new(py);
        let m = ds.manifest();
        d.set_item("path", ds.dir().display().to_string())?;
        d.set_item("rays", ds.ray_count())?;
        d.set_item("trees", ds.tree_count())?;
        d.set_item("segments", m.segments.len())?;
        d.set_item("tables", m.tables.keys().cloned().collect::<Vec<_>>())?;
        d.set_item("attributes", m.attributes.clone())?;
        d.set_item(
            "payload",
            ds.payload_schema().fields.iter().map(|f| (f.name.clone(), describe_field(f))).collect::<Vec<_>>(),
        )?;
        Ok(d)
    }

    /// `rtvtk check`: the dataset's invariants; the errors found (empty: consistent).
    #[pyo3(signature = (name=None))]
    fn check(&self, py: Python<'_>, name: Option<&str>) -> PyResult<Vec<String>> {
        let ds = self.dataset(name)?;
        let job = on_thread(|| {}, move || Ok(ds.check().errors));
        job.wait(py, None)?.map_err(DatasetError::new_err)
    }

    /// `rtvtk render` over this session's first dataset: the picture as PNG bytes, and what the
    /// layers reported. `options` holds `rtvtk_viz::headless::RenderRequest`'s fields by name;
    /// `progress(what, done, total)` hears the ray loads; Ctrl-C cancels them.
    #[pyo3(signature = (options, progress=None))]
    fn render<'py>(
        &self,
        py: Python<'py>,
        options: &Bound<'py, PyDict>,
        progress: Option<Bound<'py, PyAny>>,
    ) -> PyResult<(Bound<'py, PyBytes>, Vec<String>)> {
        let request = render_request(options)?;
        let engine = self.engine.clone();
        let shared: Arc<rtvtk_viz::component::Progress> = Arc::default();
        let (p, c) = (shared.clone(), shared.clone());
        let job = on_thread(
            move || c.cancel(),
            move || -> Result<(Vec<u8>, Vec<String>), String> {
                let sources = rtvtk_viz::Sources::with_engine(engine, None).map_err(|e| e.to_string())?;
                let (img, report) =
                    rtvtk_viz::headless::render_with(sources, &request, p).map_err(|e| e.to_string())?;
                let mut png = Vec::new();
                img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                    .map_err(|e| e.to_string())?;
                Ok((png, report))
            },
        );
        let poll = || shared.get();
        let (png, report) =
            job.wait(py, progress.as_ref().map(|cb| (cb, &poll as work::Poll)))?.map_err(RenderError::new_err)?;
        Ok((PyBytes::new(py, &png), report))
    }

    /// One of `rtvtk analyze`'s analyses (`coherence`, `bvh`, `bugs`, `diff`) with its options by
    /// name; `progress(what, done, total)` hears the queries run; Ctrl-C stops it.
    #[pyo3(signature = (name, options, progress=None))]
    fn analyze(
        &self,
        py: Python<'_>,
        name: &str,
        options: &Bound<'_, PyDict>,
        progress: Option<Bound<'_, PyAny>>,
    ) -> PyResult<NativeReport> {
        let analysis = Analysis::parse(name, options, &self.engine)?;
        let engine = self.engine.clone();
        let job = on_engine(&self.engine, async move { analysis.run(&engine).await.map_err(|e| e.to_string()) });
        let start = self.engine.queries_run();
        let e = self.engine.clone();
        let what = format!("analyze {name}");
        let poll = move || Some((what.clone(), e.queries_run() - start, 0u64));
        let report = job.wait(py, progress.as_ref().map(|cb| (cb, &poll as work::Poll)))?.map_err(work::query_err)?;
        Ok(NativeReport { report })
    }

    /// Opens the interactive viewer on this session's engine (its first dataset, or `dataset`),
    /// and returns when the window is closed; with `screenshot`, writes the window once drawn
    /// and closes. One window per process (winit's event loop is made once), on the main thread.
    #[pyo3(signature = (dataset=None, screenshot=None, tracer=None))]
    fn view(
        &self,
        py: Python<'_>,
        dataset: Option<String>,
        screenshot: Option<std::path::PathBuf>,
        tracer: Option<&str>,
    ) -> PyResult<()> {
        let tracer = match tracer {
            Some(t) => t.parse::<renderers::TracerChoice>().map_err(|e| RenderError::new_err(e.to_string()))?,
            None => renderers::TracerChoice::default(),
        };
        let options = rtvtk_viewer::ViewerOptions {
            // By name, so the window's source menu names it (the first dataset when not given).
            sources: vec![rtvtk_viewer::Source::Served(
                dataset.or_else(|| self.engine.datasets().first().map(|d| d.name.clone())).unwrap_or_default(),
            )],
            screenshot,
            tracer,
            engine: Some(self.engine.clone()),
            ..Default::default()
        };
        guarded(|| py.detach(|| rtvtk_viewer::run(options)).map_err(|e| RenderError::new_err(e.to_string())))
    }
}

impl Session {
    pub(crate) fn dataset(&self, name: Option<&str>) -> PyResult<Arc<store::Dataset>> {
        self.engine.dataset(name).ok_or_else(|| match name {
            Some(n) => DatasetError::new_err(format!("no dataset {n:?} is open in this session")),
            None => DatasetError::new_err(
                "this session's traces are not datasets opened here (a service's, or a recording in memory): info and check need rtvtk.open",
            ),
        })
    }
}
