//! `rtvtk._rtvtk`: the native half of the Python package (`python/rtvtk/__init__.py` is the
//! other). It adds no road of its own: SQL goes through `query::Engine` (results cross to pyarrow
//! through the Arrow C stream interface, `__arrow_c_stream__`, with no copy), recording through
//! `rl::Recorder`, pictures through `rtvtk_viz::headless::render` and the window through
//! `rtvtk_viewer::run` — what the CLI calls. Long calls run with the GIL released, Ctrl-C
//! cancels them, and every error is an `rtvtk.Error` subclass carrying the library's message
//! (`work`).

mod work;

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use arrow::array::{RecordBatch, RecordBatchReader};
use arrow::datatypes::{DataType, SchemaRef};
use arrow::error::ArrowError;
use arrow::ffi_stream::FFI_ArrowArrayStream;
use futures::StreamExt;
use pyo3::buffer::PyBuffer;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyCapsule, PyDict};
use query::Engine;
use rl::{Kind, ListValue, Payload, PayloadField, PayloadSchema, RayFields, RayId, Recorder, RecorderOptions, Value};

use work::{
    DatasetError, Error, InternalError, QueryError, RecordError, RenderError, err, guarded, on_engine, on_thread,
    record_err,
};

/// Why a query's stream stopped early: Ctrl-C (the `KeyboardInterrupt` to raise) or the engine's
/// error (raised as `rtvtk.QueryError`). pyarrow sees only an Arrow error; the Python side asks
/// the stream for this to raise the right exception.
type Failure = Arc<Mutex<Option<PyErr>>>;

/// A query's batches as an Arrow `RecordBatchReader`, pulled from the engine's stream on demand.
struct EngineReader {
    engine: Arc<Engine>,
    stream: datafusion::execution::SendableRecordBatchStream,
    schema: SchemaRef,
    failure: Failure,
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
    fn fail(&self, e: PyErr, what: &str) -> Option<Result<RecordBatch, ArrowError>> {
        if let Ok(mut f) = self.failure.lock() {
            f.get_or_insert(e);
        }
        Some(Err(ArrowError::ExternalError(what.into())))
    }

    fn pull(&mut self) -> Option<Result<RecordBatch, ArrowError>> {
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
struct ArrowStream {
    reader: Mutex<Option<Box<dyn RecordBatchReader + Send>>>,
    failure: Failure,
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
struct NativeReport {
    report: query::analyze::Report,
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
struct Session {
    engine: Arc<Engine>,
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

/// An analysis and its options, checked before it runs.
enum Analysis {
    Coherence(query::analyze::CoherenceOptions),
    Bvh(u16),
    Numerics,
    Diff { a: String, b: String, tile: usize },
}

impl Analysis {
    fn parse(name: &str, o: &Bound<'_, PyDict>, engine: &Engine) -> PyResult<Analysis> {
        let get = |key: &str| o.get_item(key).ok().flatten().filter(|v| !v.is_none());
        let a = match name {
            "coherence" => {
                let mut c = query::analyze::CoherenceOptions::default();
                if let Some(w) = get("width") {
                    c.width = w.extract()?;
                    if !(1..=1024).contains(&c.width) {
                        return Err(QueryError::new_err(format!("coherence: width {} is not in 1..=1024", c.width)));
                    }
                }
                if let Some(v) = get("orders") {
                    c.orders = v.extract()?;
                }
                if let Some(v) = get("kind") {
                    c.kind = Some(v.extract()?);
                }
                Analysis::Coherence(c)
            }
            "bvh" => Analysis::Bvh(get("level").map(|v| v.extract()).transpose()?.unwrap_or(3)),
            "numerics" | "bugs" => Analysis::Numerics,
            "diff" => {
                let names: Vec<String> = engine.datasets().iter().map(|d| d.name.clone()).collect();
                let pick = |v: Option<Bound<'_, PyAny>>, i: usize| -> PyResult<String> {
                    match v {
                        Some(v) => v.extract(),
                        None => names.get(i).cloned().ok_or_else(|| {
                            QueryError::new_err(
                                "diff compares two datasets: open two (rtvtk.open([a, b])) or name them with a=, b=",
                            )
                        }),
                    }
                };
                let a = pick(get("a"), 0)?;
                let b = pick(get("b"), 1)?;
                let tile = get("tile").map(|v| v.extract()).transpose()?.unwrap_or(16usize).max(1);
                Analysis::Diff { a, b, tile }
            }
            other => {
                return Err(QueryError::new_err(format!(
                    "unknown analysis {other:?}: expected coherence, bvh, numerics (or bugs) or diff"
                )));
            }
        };
        let known: &[&str] = match name {
            "coherence" => &["width", "orders", "kind"],
            "bvh" => &["level"],
            "diff" => &["a", "b", "tile"],
            _ => &[],
        };
        for k in o.keys() {
            let k: String = k.extract()?;
            if !known.contains(&k.as_str()) {
                return Err(QueryError::new_err(format!("analyze {name}: unknown option {k:?} (it takes {known:?})")));
            }
        }
        Ok(a)
    }

    async fn run(&self, engine: &Engine) -> query::Result<query::analyze::Report> {
        use query::analyze;
        match self {
            Analysis::Coherence(o) => analyze::coherence(engine, o).await,
            Analysis::Bvh(level) => analyze::bvh(engine, *level).await,
            Analysis::Numerics => analyze::numerics(engine).await,
            Analysis::Diff { a, b, tile } => analyze::diff(engine, a, b, *tile).await,
        }
    }
}

impl Session {
    fn dataset(&self, name: Option<&str>) -> PyResult<Arc<store::Dataset>> {
        self.engine.dataset(name).ok_or_else(|| match name {
            Some(n) => DatasetError::new_err(format!("no dataset {n:?} is open in this session")),
            None => DatasetError::new_err(
                "this session's traces are not datasets opened here (a service's, or a recording in memory): info and check need rtvtk.open",
            ),
        })
    }
}

/// `camera=((x, y, z), (x, y, z), fov_y)`: position, target, vertical field of view in degrees.
type CameraArg = ((f64, f64, f64), (f64, f64, f64), f64);

/// A render request from Python keyword arguments (unknown names are refused, naming them).
fn render_request(o: &Bound<'_, PyDict>) -> PyResult<rtvtk_viz::headless::RenderRequest> {
    let mut r = rtvtk_viz::headless::RenderRequest::default();
    for (k, v) in o.iter() {
        let key: String = k.extract()?;
        match key.as_str() {
            "layers" => r.layers = v.extract()?,
            "sql" => r.sql = v.extract()?,
            "colour_by" | "color_by" => r.colour_by = v.extract()?,
            "tree" => r.tree = v.extract()?,
            "pixel" => r.pixel = v.extract::<Option<(u32, u32)>>()?.map(|(x, y)| [x, y]),
            "sample" => r.sample = v.extract()?,
            "kinds" => r.kinds = v.extract()?,
            "depth" => r.depth = v.extract::<Option<(u32, u32)>>()?.map(|(a, b)| [a, b]),
            "max_rays" => r.max_rays = v.extract()?,
            "bvh_levels" => r.bvh_levels = v.extract::<Option<(u32, u32)>>()?.map(|(a, b)| [a, b]),
            "bvh_visited" => r.bvh_visited = v.extract()?,
            "geometry" => r.geometry = v.extract()?,
            "size" => r.size = v.extract::<Option<(u32, u32)>>()?.map(|(w, h)| [w, h]),
            "line_width" => r.line_width = v.extract()?,
            "image_source" => r.image_source = v.extract()?,
            "image_spp" => r.image_spp = v.extract()?,
            "legend" => r.legend = v.extract()?,
            "style" => {
                let name: String = v.extract()?;
                r.style = name.parse().map_err(RenderError::new_err)?;
            }
            "opacity" => r.opacity = v.extract()?,
            "density_scale" => {
                let name: String = v.extract()?;
                r.density_scale = name.parse().map_err(RenderError::new_err)?;
            }
            "density_map" => r.density_map = v.extract()?,
            "map" | "colour_map" | "color_map" => r.map = v.extract()?,
            "camera" => {
                let c: Option<CameraArg> = v.extract()?;
                r.camera = match c {
                    Some((p, t, fov)) => {
                        let c = rtvtk_viz::ViewCamera {
                            position: [p.0, p.1, p.2],
                            target: [t.0, t.1, t.2],
                            up: [0.0, 1.0, 0.0],
                            fov_y: fov,
                        };
                        c.validate().map_err(|e| RenderError::new_err(e.to_string()))?;
                        Some(c)
                    }
                    None => None,
                };
            }
            other => return Err(RenderError::new_err(format!("render: unknown option {other:?}"))),
        }
    }
    Ok(r)
}

/// `f32`, `u32x4`, ...: a payload column's declaration.
fn describe_field(f: &PayloadField) -> String {
    let t = match f.element {
        DataType::Boolean => "bool",
        DataType::Int8 => "i8",
        DataType::Int16 => "i16",
        DataType::Int32 => "i32",
        DataType::Int64 => "i64",
        DataType::UInt8 => "u8",
        DataType::UInt16 => "u16",
        DataType::UInt32 => "u32",
        DataType::UInt64 => "u64",
        DataType::Float32 => "f32",
        DataType::Float64 => "f64",
        _ => "?",
    };
    match f.list_len {
        Some(n) => format!("{t}x{n}"),
        None => t.to_string(),
    }
}

/// The payload column `name` declared as `spec` (`f32`, `f32x3`, `u32`, `i64`, `f64x4`, ...).
fn parse_field(name: &str, spec: &str) -> PyResult<PayloadField> {
    let (t, n) = match spec.split_once('x') {
        Some((t, n)) => {
            let n: usize = n.parse().ok().filter(|n| *n >= 1).ok_or_else(|| {
                record_err(format!("payload {name:?}: {spec:?}: expected TYPE or TYPExN with N >= 1 (f32x3)"))
            })?;
            (t, Some(n))
        }
        None => (spec, None),
    };
    let element = match t {
        "f32" => DataType::Float32,
        "f64" => DataType::Float64,
        "i32" => DataType::Int32,
        "i64" => DataType::Int64,
        "u8" => DataType::UInt8,
        "u16" => DataType::UInt16,
        "u32" => DataType::UInt32,
        "u64" => DataType::UInt64,
        _ => {
            return Err(record_err(format!(
                "payload {name:?}: type {t:?} is not one of f32, f64, i32, i64, u8, u16, u32, u64 (with xN for N per ray)"
            )));
        }
    };
    Ok(PayloadField { name: name.to_string(), element, list_len: n })
}

/// A payload column's values for a run of rays, as read from a Python buffer.
enum Column {
    F32(Vec<f32>),
    F64(Vec<f64>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
    U16(Vec<u16>),
    U32(Vec<u32>),
    U64(Vec<u64>),
}

impl Column {
    /// Ray `i`'s value (`n` elements per ray for a list column).
    fn value(&self, i: usize, n: Option<usize>) -> Value<'_> {
        macro_rules! pick {
            ($v:expr, $scalar:ident, $list:ident) => {
                match n {
                    None => Value::$scalar($v[i]),
                    Some(n) => Value::List(ListValue::$list(&$v[i * n..(i + 1) * n])),
                }
            };
        }
        match self {
            Column::F32(v) => pick!(v, F32, F32),
            Column::F64(v) => pick!(v, F64, F64),
            Column::I32(v) => pick!(v, I32, I32),
            Column::I64(v) => pick!(v, I64, I64),
            Column::U8(v) => pick!(v, U8, U8),
            Column::U16(v) => pick!(v, U16, U16),
            Column::U32(v) => pick!(v, U32, U32),
            Column::U64(v) => pick!(v, U64, U64),
        }
    }
}

/// The elements of a buffer (numpy array, memoryview, array.array) of element type `T`, as
/// many as `want` (naming `what` when the type or the count is wrong).
fn elements<T: pyo3::buffer::Element + Copy>(obj: &Bound<'_, PyAny>, what: &str, want: usize) -> PyResult<Vec<T>> {
    let buf = PyBuffer::<T>::get(obj).map_err(|e| {
        record_err(format!(
            "{what}: expected a contiguous buffer of {} (a numpy array of that dtype): {e}",
            std::any::type_name::<T>()
        ))
    })?;
    let v = buf.to_vec(obj.py())?;
    if v.len() != want {
        return Err(record_err(format!("{what}: {} values, expected {want}", v.len())));
    }
    Ok(v)
}

fn column(obj: &Bound<'_, PyAny>, f: &PayloadField, rays: usize) -> PyResult<Column> {
    let want = rays * f.list_len.unwrap_or(1);
    let what = format!("payload {:?} ({})", f.name, describe_field(f));
    Ok(match f.element {
        DataType::Float32 => Column::F32(elements(obj, &what, want)?),
        DataType::Float64 => Column::F64(elements(obj, &what, want)?),
        DataType::Int32 => Column::I32(elements(obj, &what, want)?),
        DataType::Int64 => Column::I64(elements(obj, &what, want)?),
        DataType::UInt8 => Column::U8(elements(obj, &what, want)?),
        DataType::UInt16 => Column::U16(elements(obj, &what, want)?),
        DataType::UInt32 => Column::U32(elements(obj, &what, want)?),
        DataType::UInt64 => Column::U64(elements(obj, &what, want)?),
        _ => return Err(record_err(format!("{what}: unsupported type"))),
    })
}

/// Records rays into a dataset (write mode) or into memory (immediate mode).
#[pyclass(module = "rtvtk._rtvtk", frozen)]
struct NativeRecorder {
    rec: Mutex<Option<Recorder>>,
    kinds: Mutex<HashMap<String, Kind>>,
    /// Immediate mode: the trace in memory, queryable while recording.
    memory: Option<rl::MemoryTrace>,
    /// Write mode: the dataset directory (pictures are written beside the trace).
    dir: Option<std::path::PathBuf>,
}

fn options(payload: Vec<(String, String)>, sites: bool) -> PyResult<RecorderOptions> {
    let fields = payload.iter().map(|(n, s)| parse_field(n, s)).collect::<PyResult<Vec<_>>>()?;
    let schema = PayloadSchema::new(fields, None).map_err(record_err)?;
    Ok(RecorderOptions { payload: schema, sites, ..Default::default() })
}

/// The payload columns the caller gives values for (not the recorder's own `site` column).
fn given_fields(rec: &Recorder) -> Vec<PayloadField> {
    let fields = &rec.payload_schema().fields;
    let own = usize::from(rec.records_sites());
    fields[..fields.len() - own].to_vec()
}

impl NativeRecorder {
    fn with<T>(&self, f: impl FnOnce(&Recorder) -> PyResult<T>) -> PyResult<T> {
        let g = self.rec.lock().map_err(record_err)?;
        let rec = g.as_ref().ok_or_else(|| record_err("the recorder is finished: nothing more can be recorded"))?;
        guarded(|| f(rec))
    }

    fn kind(&self, rec: &Recorder, name: &str) -> PyResult<Kind> {
        let mut kinds = self.kinds.lock().map_err(record_err)?;
        if let Some(k) = kinds.get(name) {
            return Ok(*k);
        }
        let k = rec.register_kind(name).map_err(record_err)?;
        kinds.insert(name.to_string(), k);
        Ok(k)
    }
}

/// An immediate-mode recording as SQL sees it (`query::LiveTrace`): read anew at every query.
struct Memory(rl::MemoryTrace);

impl query::LiveTrace for Memory {
    fn ray_schema(&self) -> SchemaRef {
        store::ray_table_schema(&store::ray_schema(self.0.payload_schema()))
    }
    fn rays(&self) -> store::Result<Vec<RecordBatch>> {
        self.0.ray_batches()
    }
    fn trees(&self) -> store::Result<Vec<RecordBatch>> {
        self.0.tree_batches()
    }
    fn table(&self, name: &str) -> Option<RecordBatch> {
        self.0.table(name)
    }
    fn table_names(&self) -> Vec<String> {
        self.0.table_names()
    }
    fn attributes(&self) -> Vec<(String, String)> {
        self.0.attributes()
    }
    fn stats(&self) -> store::Stats {
        self.0.stats()
    }
}

#[pymethods]
impl NativeRecorder {
    /// Write mode: a dataset at `path` with payload columns `[(name, "f32x3"), ...]`; with
    /// `sites`, each ray's recording site too.
    #[staticmethod]
    #[pyo3(signature = (path, payload, sites=false))]
    fn create(py: Python<'_>, path: String, payload: Vec<(String, String)>, sites: bool) -> PyResult<NativeRecorder> {
        let options = options(payload, sites)?;
        let rec = py.detach(|| Recorder::create(&path, options)).map_err(record_err)?;
        Ok(NativeRecorder { rec: Mutex::new(Some(rec)), kinds: Mutex::default(), memory: None, dir: Some(path.into()) })
    }

    /// Immediate mode: the trace stays in memory.
    #[staticmethod]
    #[pyo3(signature = (payload, sites=false))]
    fn immediate(payload: Vec<(String, String)>, sites: bool) -> PyResult<NativeRecorder> {
        let (rec, memory) = Recorder::immediate(options(payload, sites)?).map_err(record_err)?;
        Ok(NativeRecorder { rec: Mutex::new(Some(rec)), kinds: Mutex::default(), memory: Some(memory), dir: None })
    }

    /// The payload columns as declared, `[(name, spec)]`.
    fn payload(&self) -> PyResult<Vec<(String, String)>> {
        self.with(|r| Ok(given_fields(r).iter().map(|f| (f.name.clone(), describe_field(f))).collect()))
    }

    /// Whether rays record their site.
    fn records_sites(&self) -> PyResult<bool> {
        self.with(|r| Ok(r.records_sites()))
    }

    /// Records whole trees at once. Rays of one tree are contiguous and share `tree` (any
    /// integer naming the tree in this call); `parent` is the parent's index within its tree
    /// (-1: a root); `pixel` (n × 2) and `sample` of a tree come from its first ray; `t` NaN is a
    /// miss; `prim` -1 is none; `kind` names per ray index into `kind_names`; `site` per ray
    /// indexes `site_names` (file, line, function), when sites are recorded. Returns the
    /// dataset's tree ids, one per tree, in order.
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (tree, parent, origin, direction, t, kind, kind_names, pixel, sample, prim, payload, site=None, site_names=Vec::new()))]
    fn add_rays(
        &self,
        py: Python<'_>,
        tree: &Bound<'_, PyAny>,
        parent: &Bound<'_, PyAny>,
        origin: &Bound<'_, PyAny>,
        direction: &Bound<'_, PyAny>,
        t: &Bound<'_, PyAny>,
        kind: &Bound<'_, PyAny>,
        kind_names: Vec<String>,
        pixel: &Bound<'_, PyAny>,
        sample: &Bound<'_, PyAny>,
        prim: &Bound<'_, PyAny>,
        payload: Vec<(String, Bound<'_, PyAny>)>,
        site: Option<&Bound<'_, PyAny>>,
        site_names: Vec<(String, u32, Option<String>)>,
    ) -> PyResult<Vec<u64>> {
        let n = PyBuffer::<i64>::get(tree)
            .map(|b| b.item_count())
            .map_err(|e| record_err(format!("tree: expected int64 values: {e}")))?;
        let tree: Vec<i64> = elements(tree, "tree (int64)", n)?;
        let parent: Vec<i32> = elements(parent, "parent (int32)", n)?;
        let origin: Vec<f32> = elements(origin, "origin (float32, n x 3)", n * 3)?;
        let direction: Vec<f32> = elements(direction, "direction (float32, n x 3)", n * 3)?;
        let t: Vec<f32> = elements(t, "t (float32)", n)?;
        let kind: Vec<u8> = elements(kind, "kind (uint8 indices into kind_names)", n)?;
        let pixel: Vec<u32> = elements(pixel, "pixel (uint32, n x 2)", n * 2)?;
        let sample: Vec<u32> = elements(sample, "sample (uint32)", n)?;
        let prim: Vec<i64> = elements(prim, "prim (int64, -1 for none)", n)?;
        let site: Option<Vec<u32>> =
            site.map(|s| elements(s, "site (uint32 indices into site_names)", n)).transpose()?;
        if let Some(k) = site.as_ref().and_then(|s| s.iter().find(|k| **k as usize >= site_names.len())) {
            return Err(record_err(format!("site index {k} is outside site_names ({} sites)", site_names.len())));
        }
        self.with(|rec| {
            let kinds: Vec<Kind> = kind_names.iter().map(|k| self.kind(rec, k)).collect::<PyResult<_>>()?;
            let fields = given_fields(rec);
            let mut cols = Vec::with_capacity(fields.len());
            for f in &fields {
                let obj = payload
                    .iter()
                    .find(|(name, _)| *name == f.name)
                    .ok_or_else(|| record_err(format!("payload {:?} is declared but not given", f.name)))?;
                cols.push(column(&obj.1, f, n)?);
            }
            if let Some((name, _)) = payload.iter().find(|(name, _)| !fields.iter().any(|f| f.name == *name)) {
                return Err(record_err(format!("payload {name:?} was not declared when the recorder was made")));
            }
            if let Some(k) = kind.iter().find(|k| usize::from(**k) >= kinds.len()) {
                return Err(record_err(format!("kind index {k} is outside kind_names ({} names)", kinds.len())));
            }
            // Checked before anything is recorded: a bad call records nothing.
            let mut start = 0;
            while start < n {
                let mut end = start + 1;
                while end < n && tree[end] == tree[start] {
                    end += 1;
                }
                for (k, &p) in parent[start..end].iter().enumerate() {
                    if p >= 0 && p as usize >= k {
                        return Err(record_err(format!(
                            "ray {}: parent {p} is not an earlier ray of its tree (it has {k} before it)",
                            start + k
                        )));
                    }
                }
                start = end;
            }
            Ok(py.detach(|| {
                let mut ids = Vec::new();
                let mut start = 0;
                let mut values: Vec<Value<'_>> = Vec::with_capacity(fields.len());
                let mut rays: Vec<RayId> = Vec::new();
                while start < n {
                    let mut end = start + 1;
                    while end < n && tree[end] == tree[start] {
                        end += 1;
                    }
                    let mut b = rec.begin_tree(pixel[start * 2], pixel[start * 2 + 1], sample[start]);
                    rays.clear();
                    for i in start..end {
                        let fields_i = RayFields {
                            origin: [origin[i * 3], origin[i * 3 + 1], origin[i * 3 + 2]],
                            direction: [direction[i * 3], direction[i * 3 + 1], direction[i * 3 + 2]],
                            t: (!t[i].is_nan()).then_some(t[i]),
                            kind: kinds[usize::from(kind[i])],
                            prim: u32::try_from(prim[i]).ok(),
                        };
                        values.clear();
                        values.extend(cols.iter().zip(&fields).map(|(c, f)| c.value(i, f.list_len)));
                        let at = match &site {
                            Some(s) => {
                                let (file, line, function) = &site_names[s[i] as usize];
                                rl::SiteRef::Named { file, line: *line, function: function.as_deref() }
                            }
                            None => rl::SiteRef::Named { file: "(python)", line: 0, function: None },
                        };
                        let id = match usize::try_from(parent[i]) {
                            Ok(p) => b.add_ray_under_at(at, rays[p], &fields_i, Payload::values(&values)),
                            Err(_) => b.add_ray_at(at, &fields_i, Payload::values(&values)),
                        };
                        rays.push(id);
                    }
                    ids.push(b.end().0);
                    start = end;
                }
                ids
            }))
        })
    }

    /// The scene's triangles: `vertices` (n × 3 × 3 float32), `materials` (n uint32 indices),
    /// per material its RGB colour and emission (m × 3 float32) and name; and point lights,
    /// positions and RGB intensities (k × 3 float32 each). The emissive triangles and the point
    /// lights become the `lights` table.
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (vertices, materials, colors, emission, names, point_positions=None, point_intensities=None))]
    fn set_triangles(
        &self,
        vertices: &Bound<'_, PyAny>,
        materials: &Bound<'_, PyAny>,
        colors: &Bound<'_, PyAny>,
        emission: &Bound<'_, PyAny>,
        names: Vec<String>,
        point_positions: Option<&Bound<'_, PyAny>>,
        point_intensities: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<()> {
        let m = names.len();
        let n = PyBuffer::<u32>::get(materials)
            .map(|b| b.item_count())
            .map_err(|e| record_err(format!("materials: expected uint32 values: {e}")))?;
        let v: Vec<f32> = elements(vertices, "vertices (float32, n x 3 x 3)", n * 9)?;
        let mats: Vec<u32> = elements(materials, "materials (uint32)", n)?;
        let c: Vec<f32> = elements(colors, "colors (float32, m x 3)", m * 3)?;
        let e: Vec<f32> = elements(emission, "emission (float32, m x 3)", m * 3)?;
        let points = match (point_positions, point_intensities) {
            (None, None) => Vec::new(),
            (Some(p), Some(i)) => {
                let k = PyBuffer::<f32>::get(p)
                    .map(|b| b.item_count() / 3)
                    .map_err(|e| record_err(format!("point light positions: expected float32 values: {e}")))?;
                let p: Vec<f32> = elements(p, "point light positions (float32, k x 3)", k * 3)?;
                let i: Vec<f32> = elements(i, "point light intensities (float32, k x 3)", k * 3)?;
                (0..k)
                    .map(|j| store::scene::PointLight {
                        position: [p[j * 3], p[j * 3 + 1], p[j * 3 + 2]],
                        intensity: [i[j * 3], i[j * 3 + 1], i[j * 3 + 2]],
                    })
                    .collect()
            }
            _ => return Err(record_err("point lights need both positions and intensities")),
        };
        let batch = store::scene::triangles_from_arrays(&v, &mats, &c, &e, &names)
            .map_err(|e| record_err(format!("set_triangles: {e}")))?;
        // The emitters (the paper's wrong-shadow query reads them).
        let lights =
            store::scene::lights_table(Some(&batch), &points).map_err(|e| record_err(format!("set_scene: {e}")))?;
        self.with(|r| {
            r.write_table(store::scene::TRIANGLES_TABLE, batch).map_err(record_err)?;
            r.write_table(store::scene::LIGHTS_TABLE, lights).map_err(record_err)
        })
    }

    /// The camera the rays were traced from (the CODE_STYLE camera convention of `rl.h`).
    fn set_camera(
        &self,
        position: [f32; 3],
        target: [f32; 3],
        up: [f32; 3],
        fov_y: f32,
        width: u32,
        height: u32,
    ) -> PyResult<()> {
        let cam = store::scene::CameraAttrs { position, target, up, fov_y, width, height };
        let attrs: std::collections::BTreeMap<String, String> = cam.to_attributes().into_iter().collect();
        store::scene::CameraAttrs::from_attributes(&attrs).map_err(record_err)?;
        self.with(|r| r.set_attributes(cam.to_attributes()).map_err(record_err))
    }

    /// The renderer's picture of the recording: `width` × `height` linear RGB floats, written
    /// beside the trace as `image.png` (sRGB, clamped) and `image.exr` (linear), and named by the
    /// manifest, so the image layer shows the renderer's own picture.
    fn set_image(&self, py: Python<'_>, width: u32, height: u32, rgb: &Bound<'_, PyAny>) -> PyResult<()> {
        let dir =
            self.dir.clone().ok_or_else(|| record_err("set_image: an immediate-mode recording has no directory"))?;
        let want = width as usize * height as usize * 3;
        let rgb: Vec<f32> = elements(rgb, "image (float32, height x width x 3)", want)?;
        let film = renderers::film::Film::from_rgb(width, height, &rgb).map_err(record_err)?;
        py.detach(|| -> renderers::Result<()> {
            film.write_png(&dir.join("image.png"), 1.0)?;
            film.write_exr(&dir.join("image.exr"))
        })
        .map_err(record_err)?;
        let names = [store::scene::attr::IMAGE_PNG, store::scene::attr::IMAGE_EXR];
        self.with(|r| r.set_attributes(names.map(|n| (n.to_string(), n.to_string()))).map_err(record_err))
    }

    /// Attributes of the recording (`image.png` names its picture, for example).
    fn set_attributes(&self, attributes: Vec<(String, String)>) -> PyResult<()> {
        self.with(|r| r.set_attributes(attributes).map_err(record_err))
    }

    /// Seals what was recorded so far (write mode: readable, crash-safe).
    fn flush(&self, py: Python<'_>) -> PyResult<()> {
        self.with(|r| py.detach(|| r.flush()).map_err(record_err))
    }

    /// Ends the recording; `(trees, rays, segments, bytes)`. Recording after it raises.
    fn finish(&self, py: Python<'_>) -> PyResult<(u64, u64, u64, u64)> {
        let rec = self
            .rec
            .lock()
            .map_err(record_err)?
            .take()
            .ok_or_else(|| record_err("the recorder is already finished"))?;
        let s = py.detach(|| rec.finish()).map_err(record_err)?;
        Ok((s.trees, s.rays, s.segments, s.bytes))
    }

    /// Immediate mode: SQL over the trace in memory, seeing every ray recorded before each query.
    fn session(&self, py: Python<'_>) -> PyResult<Session> {
        let m = self.memory.as_ref().ok_or_else(|| {
            record_err(
                "only an immediate-mode recorder is queried while recording (open a written dataset with rtvtk.open)",
            )
        })?;
        let trace: Arc<dyn query::LiveTrace> = Arc::new(Memory(m.clone()));
        let engine = py
            .detach(|| Engine::blocking(Engine::live(trace, &query::SessionOptions::default())))
            .map_err(|e| QueryError::new_err(e.to_string()))?;
        Ok(Session { engine: Arc::new(engine) })
    }

    /// Immediate mode: rays recorded so far, readable while recording.
    fn immediate_rays(&self) -> PyResult<u64> {
        let m = self
            .memory
            .as_ref()
            .ok_or_else(|| record_err("only an immediate-mode recorder holds its trace in memory"))?;
        Ok(m.stats().rays)
    }
}

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
