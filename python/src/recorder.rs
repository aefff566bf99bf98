//! `NativeRecorder`: rays recorded from Python buffers into a dataset or into memory.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use arrow::array::RecordBatch;
use arrow::datatypes::{DataType, SchemaRef};
use pyo3::buffer::PyBuffer;
use pyo3::prelude::*;
use query::Engine;
use rl::{Kind, ListValue, Payload, PayloadField, PayloadSchema, RayFields, RayId, Recorder, RecorderOptions, Value};

use crate::options::{describe_field, parse_field};
use crate::session::Session;
use crate::work::{QueryError, guarded, record_err};

/// A payload column's values for a run of rays, as read from a Python buffer.
pub(crate) enum Column {
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
    pub(crate) fn value(&self, i: usize, n: Option<usize>) -> Value<'_> {
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
pub(crate) fn elements<T: pyo3::buffer::Element + Copy>(
    obj: &Bound<'_, PyAny>,
    what: &str,
    want: usize,
) -> PyResult<Vec<T>> {
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

pub(crate) fn column(obj: &Bound<'_, PyAny>, f: &PayloadField, rays: usize) -> PyResult<Column> {
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
pub(crate) struct NativeRecorder {
    pub(crate) rec: Mutex<Option<Recorder>>,
    pub(crate) kinds: Mutex<HashMap<String, Kind>>,
    /// Immediate mode: the trace in memory, queryable while recording.
    pub(crate) memory: Option<rl::MemoryTrace>,
    /// Write mode: the dataset directory (pictures are written beside the trace).
    pub(crate) dir: Option<std::path::PathBuf>,
}

pub(crate) fn options(payload: Vec<(String, String)>, sites: bool) -> PyResult<RecorderOptions> {
    let fields = payload.iter().map(|(n, s)| parse_field(n, s)).collect::<PyResult<Vec<_>>>()?;
    let schema = PayloadSchema::new(fields, None).map_err(record_err)?;
    Ok(RecorderOptions { payload: schema, sites, ..Default::default() })
}

/// The payload columns the caller gives values for (not the recorder's own `site` column).
pub(crate) fn given_fields(rec: &Recorder) -> Vec<PayloadField> {
    let fields = &rec.payload_schema().fields;
    let own = usize::from(rec.records_sites());
    fields[..fields.len() - own].to_vec()
}

impl NativeRecorder {
    pub(crate) fn with<T>(&self, f: impl FnOnce(&Recorder) -> PyResult<T>) -> PyResult<T> {
        let g = self.rec.lock().map_err(record_err)?;
        let rec = g.as_ref().ok_or_else(|| record_err("the recorder is finished: nothing more can be recorded"))?;
        guarded(|| f(rec))
    }

    pub(crate) fn kind(&self, rec: &Recorder, name: &str) -> PyResult<Kind> {
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
pub(crate) struct Memory(rl::MemoryTrace);

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
