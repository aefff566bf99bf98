//! The C ABI declared in `include/rl.h`. Every function catches panics and reports errors
//! through its return value and `rlLastError`.

#![allow(clippy::missing_safety_doc)]

use std::cell::RefCell;
use std::ffi::{CStr, CString, c_char, c_void};
use std::panic::{AssertUnwindSafe, catch_unwind};

use arrow::array::{Array, AsArray};

use crate::{BytesPayload, Kind, Payload, PayloadSchema, RayFields, Reader, Recorder, RecorderOptions, TreeBuilder};

/// `rlInitColumns` / `rlInitImmediate` flag: record each ray's site (`rlAddRayAt`).
const RL_RECORD_SITES: u32 = 1;

/// Opaque recorder handle (`rl_recorder`).
pub struct RlRecorder {
    rec: Recorder,
    id: usize,
    /// The typed payload columns as `rlAddRay` reads them from a packed row.
    columns: Vec<Column>,
    /// Bytes of one packed payload row: the typed columns (`typed_size`), then the opaque bytes.
    row_size: usize,
    typed_size: usize,
    /// The scene's triangles, point lights and the rays' BVH visits, from which the `lights` and
    /// `ray_nodes` tables are written (at `rlFlush` and `rlFinish`, when they changed).
    scene: std::sync::Mutex<SceneTables>,
    /// Immediate mode: the recording in memory, readable while recording (`rlOpenRecording`).
    memory: Option<crate::MemoryTrace>,
}

#[derive(Default)]
struct SceneTables {
    triangles: Option<arrow::array::RecordBatch>,
    points: Vec<store::scene::PointLight>,
    changed: bool,
    /// BVH nodes the rays visited (`rlAddRayVisits`), written as `ray_nodes` at flush and finish.
    visits: Vec<store::scene::Visit>,
    /// Visits in the `ray_nodes` table written last.
    visits_written: usize,
}

/// A BVH node as `rl.h` declares it (`rl_bvh_node`).
#[repr(C)]
pub struct RlBvhNode {
    pub parent: i64,
    pub min: [f32; 3],
    pub max: [f32; 3],
    pub first_prim: u32,
    pub prim_count: u32,
}

/// A typed payload column of `rlInitColumns`: its element type and how many per ray.
#[derive(Clone, Copy, Debug)]
struct Column {
    element: Element,
    count: usize,
}

/// Element types of `rl_column.type` (`RL_F32` ...).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Element {
    F32,
    F64,
    I32,
    U32,
    I64,
    U64,
    U8,
    U16,
}

impl Element {
    fn of(code: i32) -> Option<(Element, crate::DataType)> {
        use crate::DataType as D;
        Some(match code {
            1 => (Element::F32, D::Float32),
            2 => (Element::F64, D::Float64),
            3 => (Element::I32, D::Int32),
            4 => (Element::U32, D::UInt32),
            5 => (Element::I64, D::Int64),
            6 => (Element::U64, D::UInt64),
            7 => (Element::U8, D::UInt8),
            8 => (Element::U16, D::UInt16),
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Element::U8 => 1,
            Element::U16 => 2,
            Element::F32 | Element::I32 | Element::U32 => 4,
            Element::F64 | Element::I64 | Element::U64 => 8,
        }
    }
}

/// A typed payload column as `rl.h` declares it.
#[repr(C)]
pub struct RlColumn {
    pub name: *const c_char,
    pub element: i32,
    pub count: u32,
}

/// The typed values of one packed payload row, in owned buffers the `Value`s borrow.
#[derive(Default)]
struct Decoded {
    f32s: Vec<f32>,
    f64s: Vec<f64>,
    i32s: Vec<i32>,
    u32s: Vec<u32>,
    i64s: Vec<i64>,
    u64s: Vec<u64>,
    u8s: Vec<u8>,
    u16s: Vec<u16>,
}

impl Decoded {
    /// Reads every column of `row` (packed, native byte order, no padding) into the buffers.
    fn read(&mut self, columns: &[Column], row: &[u8]) {
        macro_rules! take {
            ($buf:expr, $t:ty, $at:expr, $n:expr) => {
                $buf.extend(
                    row[$at..$at + $n * std::mem::size_of::<$t>()]
                        .chunks_exact(std::mem::size_of::<$t>())
                        .map(|c| <$t>::from_ne_bytes(c.try_into().unwrap_or_default())),
                )
            };
        }
        // Cleared, not replaced: the buffers keep their capacity from ray to ray.
        self.f32s.clear();
        self.f64s.clear();
        self.i32s.clear();
        self.u32s.clear();
        self.i64s.clear();
        self.u64s.clear();
        self.u8s.clear();
        self.u16s.clear();
        let mut at = 0;
        for c in columns {
            match c.element {
                Element::F32 => take!(self.f32s, f32, at, c.count),
                Element::F64 => take!(self.f64s, f64, at, c.count),
                Element::I32 => take!(self.i32s, i32, at, c.count),
                Element::U32 => take!(self.u32s, u32, at, c.count),
                Element::I64 => take!(self.i64s, i64, at, c.count),
                Element::U64 => take!(self.u64s, u64, at, c.count),
                Element::U8 => take!(self.u8s, u8, at, c.count),
                Element::U16 => take!(self.u16s, u16, at, c.count),
            }
            at += c.element.size() * c.count;
        }
    }

    /// The values, one per column (a list for a column of more than one element).
    fn values(&self, columns: &[Column]) -> Vec<crate::Value<'_>> {
        use crate::{ListValue, Value};
        let mut next = [0usize; 8];
        let mut out = Vec::with_capacity(columns.len());
        for c in columns {
            let n = c.count;
            macro_rules! pick {
                ($k:expr, $buf:expr, $scalar:ident) => {{
                    let s = &$buf[next[$k]..next[$k] + n];
                    next[$k] += n;
                    if n == 1 { Value::$scalar(s[0]) } else { Value::List(ListValue::$scalar(s)) }
                }};
            }
            out.push(match c.element {
                Element::F32 => pick!(0, self.f32s, F32),
                Element::F64 => pick!(1, self.f64s, F64),
                Element::I32 => pick!(2, self.i32s, I32),
                Element::U32 => pick!(3, self.u32s, U32),
                Element::I64 => pick!(4, self.i64s, I64),
                Element::U64 => pick!(5, self.u64s, U64),
                Element::U8 => pick!(6, self.u8s, U8),
                Element::U16 => pick!(7, self.u16s, U16),
            });
        }
        out
    }
}

/// Opaque reader handle (`rl_reader`).
pub struct RlReader {
    reader: Reader,
    counts: Counts,
}

/// A reader's tree and ray counts: a dataset's, fixed; an immediate-mode recording's, as they
/// are now (trees evicted over the memory budget are no longer held).
enum Counts {
    Fixed { trees: u64, rays: u64 },
    Live(crate::MemoryTrace),
}

impl Counts {
    fn trees(&self) -> u64 {
        match self {
            Counts::Fixed { trees, .. } => *trees,
            Counts::Live(m) => m.tree_count() as u64,
        }
    }
    fn rays(&self) -> u64 {
        match self {
            Counts::Fixed { rays, .. } => *rays,
            Counts::Live(m) => m.stats().rays,
        }
    }
}

#[repr(C)]
pub struct RlTree {
    pub id: u64,
    pub x: u32,
    pub y: u32,
    pub sample: u32,
    pub ray_count: u32,
    pub max_depth: u16,
}

#[repr(C)]
pub struct RlRay {
    pub index: u32,
    pub parent: i64,
    pub depth: u16,
    pub kind: i32,
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    pub hit: i32,
    pub t: f32,
    pub prim: i64,
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
    /// The typed payload of the ray being added (reused, so `rlAddRay` allocates once per thread).
    static DECODED: RefCell<Decoded> = RefCell::new(Decoded::default());
    /// Open trees of this thread, with the id of the recorder each belongs to.
    static OPEN: RefCell<Vec<(usize, TreeBuilder)>> = const { RefCell::new(Vec::new()) };
}

fn set_error(msg: impl Into<String>) {
    let msg = msg.into().replace('\0', " ");
    LAST_ERROR.with(|e| *e.borrow_mut() = CString::new(msg).unwrap_or_default());
}

fn guard<T>(fail: T, f: impl FnOnce() -> Result<T, String>) -> T {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => v,
        Ok(Err(msg)) => {
            set_error(msg);
            fail
        }
        Err(_) => {
            set_error("internal error: rl panicked");
            fail
        }
    }
}

unsafe fn path_arg(path: *const c_char) -> Result<String, String> {
    if path.is_null() {
        return Err("path is NULL".into());
    }
    // SAFETY: the caller passes a NUL-terminated string.
    let s = unsafe { CStr::from_ptr(path) };
    s.to_str().map(str::to_string).map_err(|_| "path is not valid UTF-8".into())
}

unsafe fn rec_arg<'a>(rec: *mut RlRecorder) -> Result<&'a RlRecorder, String> {
    // SAFETY: the caller passes a handle from rlInit that was not finished.
    unsafe { rec.as_ref() }.ok_or_else(|| "recorder is NULL".to_string())
}

fn with_tree<T>(id: usize, f: impl FnOnce(&mut TreeBuilder) -> T) -> Result<T, String> {
    OPEN.with(|open| {
        let mut open = open.borrow_mut();
        match open.iter_mut().rev().find(|(r, _)| *r == id) {
            Some((_, t)) => Ok(f(t)),
            None => Err("no open tree on this thread: call rlBeginTree first".into()),
        }
    })
}

/// Where `make_recorder` records: a dataset directory, or memory within a byte budget (0: the
/// default).
enum Target<'a> {
    Dir(&'a str),
    Memory(usize),
}

/// A recorder with typed payload `columns` and `bytes_size` opaque bytes per ray.
fn make_recorder(
    target: Target<'_>,
    columns: Vec<(String, Column, crate::DataType)>,
    bytes_size: usize,
    flags: u32,
) -> Result<*mut RlRecorder, String> {
    if flags & !RL_RECORD_SITES != 0 {
        return Err(format!("flags {flags:#x}: only RL_RECORD_SITES (1) is known"));
    }
    let bytes = (bytes_size > 0).then_some(BytesPayload::Fixed(bytes_size));
    let fields = columns
        .iter()
        .map(|(name, c, t)| crate::PayloadField {
            name: name.clone(),
            element: t.clone(),
            list_len: (c.count > 1).then_some(c.count),
        })
        .collect();
    let payload = PayloadSchema::new(fields, bytes).map_err(|e| e.to_string())?;
    let mut options = RecorderOptions { payload, sites: flags & RL_RECORD_SITES != 0, ..Default::default() };
    let (rec, memory) = match target {
        Target::Dir(path) => (Recorder::create(path, options).map_err(|e| e.to_string())?, None),
        Target::Memory(budget) => {
            if budget > 0 {
                options.memory_budget = budget;
            }
            let (rec, memory) = Recorder::immediate(options).map_err(|e| e.to_string())?;
            (rec, Some(memory))
        }
    };
    let typed_size = columns.iter().map(|(_, c, _)| c.element.size() * c.count).sum::<usize>();
    let columns = columns.into_iter().map(|(_, c, _)| c).collect();
    let row_size = typed_size + bytes_size;
    let boxed = Box::new(RlRecorder { rec, id: 0, columns, row_size, typed_size, scene: Default::default(), memory });
    let ptr = Box::into_raw(boxed);
    // SAFETY: just allocated.
    unsafe { (*ptr).id = ptr as usize };
    Ok(ptr)
}

/// The typed payload columns of `rl_column`s, checked.
unsafe fn columns_arg(
    columns: *const RlColumn,
    column_count: usize,
) -> Result<Vec<(String, Column, crate::DataType)>, String> {
    // SAFETY: `column_count` columns at `columns`.
    let cols = unsafe { slice_arg(columns, column_count, "columns") }?;
    let mut out = Vec::with_capacity(cols.len());
    for (i, c) in cols.iter().enumerate() {
        // SAFETY: a NUL-terminated name per column.
        let name = unsafe { path_arg(c.name) }.map_err(|e| format!("column {i}: name: {e}"))?;
        let (element, t) = Element::of(c.element).ok_or_else(|| {
            format!("column {i} ({name}): type {} is not one of RL_F32 .. RL_U16 (1 to 8)", c.element)
        })?;
        if c.count == 0 {
            return Err(format!("column {i} ({name}): count 0 (at least one value per ray)"));
        }
        out.push((name, Column { element, count: c.count as usize }, t));
    }
    Ok(out)
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlInit(path: *const c_char, payload_size: usize) -> *mut RlRecorder {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let path = unsafe { path_arg(path) }?;
        make_recorder(Target::Dir(&path), Vec::new(), payload_size, 0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlInitColumns(
    path: *const c_char,
    columns: *const RlColumn,
    column_count: usize,
    bytes_size: usize,
    flags: u32,
) -> *mut RlRecorder {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let path = unsafe { path_arg(path) }?;
        // SAFETY: forwarded caller contract.
        let columns = unsafe { columns_arg(columns, column_count) }?;
        make_recorder(Target::Dir(&path), columns, bytes_size, flags)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlInitImmediate(
    columns: *const RlColumn,
    column_count: usize,
    bytes_size: usize,
    memory_budget: usize,
    flags: u32,
) -> *mut RlRecorder {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let columns = unsafe { columns_arg(columns, column_count) }?;
        make_recorder(Target::Memory(memory_budget), columns, bytes_size, flags)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlOpenRecording(rec: *mut RlRecorder) -> *mut RlReader {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        let memory = rec.memory.clone().ok_or(
            "rlOpenRecording: only an immediate-mode recorder (rlInitImmediate) is read while recording; \
             open a dataset with rlOpen",
        )?;
        let reader = Reader::new(Box::new(memory.clone()));
        Ok(Box::into_raw(Box::new(RlReader { reader, counts: Counts::Live(memory) })))
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlPayloadRowSize(rec: *mut RlRecorder) -> i64 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        Ok(rec.row_size as i64)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlRegisterKind(rec: *mut RlRecorder, name: *const c_char) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        // SAFETY: forwarded caller contract.
        let name = unsafe { path_arg(name) }?;
        rec.rec.register_kind(&name).map(|k| i32::from(k.0)).map_err(|e| e.to_string())
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlBeginTree(rec: *mut RlRecorder, x: u32, y: u32, sample: u32) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        let tree = rec.rec.begin_tree(x, y, sample);
        OPEN.with(|o| o.borrow_mut().push((rec.id, tree)));
        Ok(0)
    })
}

#[unsafe(no_mangle)]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn rlAddRay(
    rec: *mut RlRecorder,
    origin: *const f32,
    direction: *const f32,
    t: f32,
    kind: i32,
    prim: i64,
    payload: *const c_void,
    payload_size: usize,
) -> i32 {
    // SAFETY: forwarded caller contract.
    unsafe { add_ray(rec, origin, direction, t, kind, prim, payload, payload_size, None) }
}

#[unsafe(no_mangle)]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn rlAddRayAt(
    rec: *mut RlRecorder,
    origin: *const f32,
    direction: *const f32,
    t: f32,
    kind: i32,
    prim: i64,
    payload: *const c_void,
    payload_size: usize,
    file: *const c_char,
    line: u32,
    function: *const c_char,
) -> i32 {
    let text = |p: *const c_char| -> Option<String> {
        // SAFETY: a NUL-terminated string or NULL, as rl.h documents.
        (!p.is_null()).then(|| unsafe { CStr::from_ptr(p) }.to_string_lossy().into_owned())
    };
    let (file, function) = (text(file), text(function));
    let site = file.as_deref().map(|f| (f, line, function.as_deref()));
    // SAFETY: forwarded caller contract.
    unsafe { add_ray(rec, origin, direction, t, kind, prim, payload, payload_size, site) }
}

/// `rlAddRay`, with the call site when the caller names it.
#[allow(clippy::too_many_arguments)]
unsafe fn add_ray(
    rec: *mut RlRecorder,
    origin: *const f32,
    direction: *const f32,
    t: f32,
    kind: i32,
    prim: i64,
    payload: *const c_void,
    payload_size: usize,
    site: Option<(&str, u32, Option<&str>)>,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        if origin.is_null() || direction.is_null() {
            return Err("origin and direction must point at 3 floats".into());
        }
        let kind = u8::try_from(kind).map_err(|_| format!("kind {kind} out of range 0..=255"))?;
        // SAFETY: the caller passes 3 floats each.
        let (o, d) = unsafe { (*(origin as *const [f32; 3]), *(direction as *const [f32; 3])) };
        let row = if payload.is_null() || payload_size == 0 {
            None
        } else {
            // SAFETY: the caller passes `payload_size` readable bytes.
            Some(unsafe { std::slice::from_raw_parts(payload as *const u8, payload_size) })
        };
        let typed = rec.typed_size;
        if let Some(r) = row
            && r.len() != rec.row_size
        {
            return Err(format!(
                "payload of {} bytes: this recorder's row is {} bytes ({typed} of typed columns, then {} opaque)",
                r.len(),
                rec.row_size,
                rec.row_size - typed
            ));
        }
        let fields = RayFields {
            origin: o,
            direction: d,
            t: (prim >= 0).then_some(t),
            kind: Kind(kind),
            prim: u32::try_from(prim).ok(),
        };
        DECODED.with(|decoded| {
            let mut decoded = decoded.borrow_mut();
            let (values, bytes) = match row {
                Some(r) => {
                    decoded.read(&rec.columns, &r[..typed]);
                    (decoded.values(&rec.columns), (r.len() > typed).then(|| &r[typed..]))
                }
                None => (Vec::new(), None),
            };
            with_tree(rec.id, |tree| {
                let payload = Payload { values: &values, bytes };
                match site {
                    Some((file, line, function)) => {
                        tree.add_ray_at(crate::SiteRef::Named { file, line, function }, &fields, payload)
                    }
                    None => tree.add_ray(&fields, payload),
                };
            })
        })?;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlDescendTree(rec: *mut RlRecorder) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        with_tree(rec.id, TreeBuilder::descend)?;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlAscendTree(rec: *mut RlRecorder) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        with_tree(rec.id, TreeBuilder::ascend)?;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlEndTree(rec: *mut RlRecorder) -> i64 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        let tree = OPEN.with(|open| {
            let mut open = open.borrow_mut();
            let pos = open.iter().rposition(|(r, _)| *r == rec.id);
            pos.map(|p| open.remove(p).1)
        });
        let tree = tree.ok_or("no open tree on this thread: call rlBeginTree first")?;
        Ok(tree.end().0 as i64)
    })
}

/// A slice of `n` values from a C pointer (NULL only when `n` is 0).
unsafe fn slice_arg<'a, T>(p: *const T, n: usize, what: &str) -> Result<&'a [T], String> {
    if n == 0 {
        return Ok(&[]);
    }
    if p.is_null() {
        return Err(format!("{what} is NULL"));
    }
    // SAFETY: the caller passes `n` readable values at `p`.
    Ok(unsafe { std::slice::from_raw_parts(p, n) })
}

#[unsafe(no_mangle)]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn rlSetTriangles(
    rec: *mut RlRecorder,
    count: usize,
    vertices: *const f32,
    materials: *const u32,
    material_count: usize,
    colors: *const f32,
    emission: *const f32,
    names: *const *const c_char,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        let n9 = count.checked_mul(9).ok_or("triangle count overflows")?;
        let nm3 = material_count.checked_mul(3).ok_or("material count overflows")?;
        // SAFETY: forwarded caller contract (sizes as rl.h documents them).
        let (v, m, c, e) = unsafe {
            (
                slice_arg(vertices, n9, "vertices")?,
                slice_arg(materials, count, "materials")?,
                slice_arg(colors, nm3, "colors")?,
                slice_arg(emission, nm3, "emission")?,
            )
        };
        let mut mat_names = Vec::with_capacity(material_count);
        for i in 0..material_count {
            let name = if names.is_null() {
                format!("material{i}")
            } else {
                // SAFETY: `names` holds `material_count` NUL-terminated strings.
                unsafe { path_arg(*names.add(i)) }.map_err(|e| format!("material name {i}: {e}"))?
            };
            mat_names.push(name);
        }
        let batch =
            store::scene::triangles_from_arrays(v, m, c, e, &mat_names).map_err(|e| format!("rlSetTriangles: {e}"))?;
        // The emissive triangles become emitters (`aims_at_light`, the paper's query, reads the
        // `lights` table): written with the point lights at the next flush or finish.
        store::scene::lights_from_triangles(&batch).map_err(|e| format!("rlSetTriangles: {e}"))?;
        rec.rec.write_table(store::scene::TRIANGLES_TABLE, batch.clone()).map_err(|e| e.to_string())?;
        let mut scene = rec.scene.lock().unwrap_or_else(|p| p.into_inner());
        scene.triangles = Some(batch);
        scene.changed = true;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlSetPointLights(
    rec: *mut RlRecorder,
    count: usize,
    positions: *const f32,
    intensities: *const f32,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        let n3 = count.checked_mul(3).ok_or("point light count overflows")?;
        // SAFETY: 3 floats per light each, as rl.h documents.
        let (p, i) = unsafe { (slice_arg(positions, n3, "positions")?, slice_arg(intensities, n3, "intensities")?) };
        let points: Vec<store::scene::PointLight> = (0..count)
            .map(|k| store::scene::PointLight {
                position: [p[k * 3], p[k * 3 + 1], p[k * 3 + 2]],
                intensity: [i[k * 3], i[k * 3 + 1], i[k * 3 + 2]],
            })
            .collect();
        store::scene::lights_table(None, &points).map_err(|e| format!("rlSetPointLights: {e}"))?;
        let mut scene = rec.scene.lock().unwrap_or_else(|p| p.into_inner());
        scene.points = points;
        scene.changed = true;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlSetBvh(
    rec: *mut RlRecorder,
    node_count: usize,
    nodes: *const RlBvhNode,
    prim_count: usize,
    prims: *const u32,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        // SAFETY: `node_count` nodes and `prim_count` triangle ids, as rl.h documents.
        let (nodes, prims) =
            unsafe { (slice_arg(nodes, node_count, "nodes")?, slice_arg(prims, prim_count, "prims")?) };
        let mut rows = Vec::with_capacity(nodes.len());
        for (i, n) in nodes.iter().enumerate() {
            let end = n.first_prim as usize + n.prim_count as usize;
            if end > prims.len() {
                return Err(format!(
                    "rlSetBvh: node {i}: triangles {}..{end} past the {} given",
                    n.first_prim,
                    prims.len()
                ));
            }
            let parent = match n.parent {
                -1 => None,
                p => Some(u32::try_from(p).map_err(|_| format!("rlSetBvh: node {i}: parent {p} (-1 for the root)"))?),
            };
            rows.push(store::scene::BvhNodeRow {
                parent,
                min: n.min,
                max: n.max,
                leaf: n.prim_count > 0,
                prims: &prims[n.first_prim as usize..end],
            });
        }
        let batch = store::scene::bvh_nodes_batch(&rows).map_err(|e| format!("rlSetBvh: {e}"))?;
        rec.rec.write_table(store::scene::BVH_NODES_TABLE, batch).map_err(|e| e.to_string())?;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlAddRayVisits(
    rec: *mut RlRecorder,
    count: usize,
    nodes: *const u32,
    leaf_hit: *const i8,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        // SAFETY: `count` node ids and (unless NULL) `count` flags.
        let nodes = unsafe { slice_arg(nodes, count, "nodes") }?;
        let hits = if leaf_hit.is_null() { None } else { Some(unsafe { slice_arg(leaf_hit, count, "leaf_hit") }?) };
        let (tree, ray) = with_tree(rec.id, |t| (t.id().0, t.last_ray()))?;
        let ray = ray.ok_or("rlAddRayVisits: the current tree has no ray yet (call it after rlAddRay)")?;
        let mut scene = rec.scene.lock().unwrap_or_else(|p| p.into_inner());
        for (k, &node) in nodes.iter().enumerate() {
            let hit = hits.and_then(|h| match h[k] {
                0 => Some(false),
                1 => Some(true),
                _ => None,
            });
            scene.visits.push((tree, ray.0, node, hit));
        }
        Ok(0)
    })
}

/// Writes the tables the recorder gathers across calls: `ray_nodes` when visits were recorded,
/// `lights` when the triangles or point lights changed since it was written.
fn write_scene_tables(rec: &RlRecorder) -> Result<(), String> {
    let mut scene = rec.scene.lock().unwrap_or_else(|p| p.into_inner());
    if scene.visits.len() > scene.visits_written {
        // A table is written whole (it replaces the last one), so the visits stay held.
        let batch = store::scene::ray_nodes_batch(scene.visits.clone()).map_err(|e| e.to_string())?;
        rec.rec.write_table(store::scene::RAY_NODES_TABLE, batch).map_err(|e| e.to_string())?;
        scene.visits_written = scene.visits.len();
    }
    if !scene.changed {
        return Ok(());
    }
    let lights = store::scene::lights_table(scene.triangles.as_ref(), &scene.points).map_err(|e| e.to_string())?;
    rec.rec.write_table(store::scene::LIGHTS_TABLE, lights).map_err(|e| e.to_string())?;
    scene.changed = false;
    Ok(())
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlSetCameraMatrix(
    rec: *mut RlRecorder,
    camera_to_world: *const f32,
    forward_z: f32,
    fov: f32,
    fov_axis: i32,
    width: u32,
    height: u32,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        // SAFETY: 16 floats, row-major, as rl.h documents.
        let m = unsafe { slice_arg(camera_to_world, 16, "camera_to_world") }?;
        if forward_z != 1.0 && forward_z != -1.0 {
            return Err(format!("forward_z {forward_z}: +1 (the camera looks along its +z) or -1 (along -z)"));
        }
        if width == 0 || height == 0 {
            return Err(format!("image size {width}x{height}: both at least 1"));
        }
        let col = |k: usize| [m[k], m[4 + k], m[8 + k]];
        let position = col(3);
        let forward = col(2).map(|v| v * forward_z);
        let up = col(1);
        let target = [position[0] + forward[0], position[1] + forward[1], position[2] + forward[2]];
        let aspect = width as f32 / height as f32;
        let fov_y = match fov_axis {
            1 => fov,
            0 => 2.0 * ((fov.to_radians() / 2.0).tan() / aspect).atan().to_degrees(),
            other => return Err(format!("fov_axis {other}: RL_FOV_X (0) or RL_FOV_Y (1)")),
        };
        let cam = store::scene::CameraAttrs { position, target, up, fov_y, width, height };
        let attrs: std::collections::BTreeMap<String, String> = cam.to_attributes().into_iter().collect();
        store::scene::CameraAttrs::from_attributes(&attrs).map_err(|e| format!("rlSetCameraMatrix: {e}"))?;
        rec.rec.set_attributes(cam.to_attributes()).map_err(|e| e.to_string())?;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlSetCamera(
    rec: *mut RlRecorder,
    position: *const f32,
    target: *const f32,
    up: *const f32,
    fov_y: f32,
    width: u32,
    height: u32,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        // SAFETY: three floats each, as rl.h documents.
        let v = |p: *const f32, what: &str| -> Result<[f32; 3], String> {
            let s = unsafe { slice_arg(p, 3, what) }?;
            Ok([s[0], s[1], s[2]])
        };
        let cam = store::scene::CameraAttrs {
            position: v(position, "position")?,
            target: v(target, "target")?,
            up: v(up, "up")?,
            fov_y,
            width,
            height,
        };
        // Round trip through the reader's checks, so a bad camera is refused here, not when read.
        let attrs: std::collections::BTreeMap<String, String> = cam.to_attributes().into_iter().collect();
        store::scene::CameraAttrs::from_attributes(&attrs)?;
        rec.rec.set_attributes(cam.to_attributes()).map_err(|e| e.to_string())?;
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlFlush(rec: *mut RlRecorder) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        write_scene_tables(rec)?;
        rec.rec.flush().map(|_| 0).map_err(|e| e.to_string())
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlFinish(rec: *mut RlRecorder) -> i32 {
    guard(-1, || {
        if rec.is_null() {
            return Err("recorder is NULL".into());
        }
        // SAFETY: a handle from rlInit, finished once.
        let boxed = unsafe { Box::from_raw(rec) };
        // Trees this thread left open are not part of the trace (finish reports them).
        OPEN.with(|o| o.borrow_mut().retain(|(r, _)| *r != boxed.id));
        let lights = write_scene_tables(&boxed);
        let finished = boxed.rec.finish().map(|_| 0).map_err(|e| e.to_string());
        lights.and(finished)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlOpen(path: *const c_char) -> *mut RlReader {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let path = unsafe { path_arg(path) }?;
        let ds = crate::Dataset::open(&path).map_err(|e| e.to_string())?;
        let (trees, rays) = (ds.tree_count(), ds.ray_count());
        Ok(Box::into_raw(Box::new(RlReader {
            reader: Reader::new(Box::new(ds)),
            counts: Counts::Fixed { trees, rays },
        })))
    })
}

unsafe fn reader_arg<'a>(r: *mut RlReader) -> Result<&'a mut RlReader, String> {
    // SAFETY: the caller passes a handle from rlOpen that was not closed.
    unsafe { r.as_mut() }.ok_or_else(|| "reader is NULL".to_string())
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlClose(reader: *mut RlReader) {
    if !reader.is_null() {
        // SAFETY: a handle from rlOpen, closed once.
        drop(unsafe { Box::from_raw(reader) });
    }
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlTreeCount(reader: *mut RlReader) -> u64 {
    // SAFETY: forwarded caller contract.
    guard(0, || Ok(unsafe { reader_arg(reader) }?.counts.trees()))
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlRayCount(reader: *mut RlReader) -> u64 {
    // SAFETY: forwarded caller contract.
    guard(0, || Ok(unsafe { reader_arg(reader) }?.counts.rays()))
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlReadTree(reader: *mut RlReader, out: *mut RlTree) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let r = unsafe { reader_arg(reader) }?;
        let Some(tree) = r.reader.read_tree().map_err(|e| e.to_string())? else {
            return Ok(0);
        };
        if !out.is_null() {
            let i = tree.info;
            // SAFETY: the caller passes a writable rl_tree.
            unsafe {
                *out = RlTree {
                    id: i.id.0,
                    x: i.pixel[0],
                    y: i.pixel[1],
                    sample: i.sample,
                    ray_count: i.ray_count,
                    max_depth: i.max_depth,
                }
            };
        }
        Ok(1)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlReadRay(
    reader: *mut RlReader,
    out: *mut RlRay,
    payload: *mut c_void,
    capacity: usize,
) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let r = unsafe { reader_arg(reader) }?;
        let Some(ray) = r.reader.read_ray().map_err(|e| e.to_string())? else {
            return Ok(0);
        };
        if !payload.is_null() && capacity > 0 {
            let tree = r.reader.read_tree().map_err(|e| e.to_string())?;
            if let Some(col) = tree.and_then(|t| t.column("payload")) {
                let i = ray.index as usize;
                let bytes: &[u8] = if let Some(a) = col.as_fixed_size_binary_opt() {
                    if a.is_valid(i) { a.value(i) } else { &[] }
                } else if let Some(a) = col.as_binary_opt::<i32>() {
                    if a.is_valid(i) { a.value(i) } else { &[] }
                } else {
                    &[]
                };
                let n = bytes.len().min(capacity);
                // SAFETY: the caller passes `capacity` writable bytes.
                unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), payload as *mut u8, n) };
            }
        }
        if !out.is_null() {
            // SAFETY: the caller passes a writable rl_ray.
            unsafe {
                *out = RlRay {
                    index: ray.index,
                    parent: ray.parent.map_or(-1, i64::from),
                    depth: ray.depth,
                    kind: i32::from(ray.kind.0),
                    origin: ray.origin,
                    direction: ray.direction,
                    hit: i32::from(ray.t.is_some()),
                    t: ray.t.unwrap_or(f32::INFINITY),
                    prim: ray.prim.map_or(-1, i64::from),
                }
            };
        }
        Ok(1)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlNextTree(reader: *mut RlReader) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let r = unsafe { reader_arg(reader) }?;
        r.reader.next_tree().map(i32::from).map_err(|e| e.to_string())
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlSeekTree(reader: *mut RlReader, id: u64) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let r = unsafe { reader_arg(reader) }?;
        r.reader.seek_tree_id(crate::TreeId(id)).map(|_| 0).map_err(|e| e.to_string())
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlSeekRay(reader: *mut RlReader, index: u32) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let r = unsafe { reader_arg(reader) }?;
        r.reader.seek_ray(index as usize);
        Ok(0)
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlResetRead(reader: *mut RlReader) -> i32 {
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let r = unsafe { reader_arg(reader) }?;
        r.reader.reset().map(|_| 0).map_err(|e| e.to_string())
    })
}

#[unsafe(no_mangle)]
pub extern "C" fn rlLastError() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}
