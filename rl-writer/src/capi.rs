//! The C ABI declared in `include/rl.h`. Every function catches panics and reports errors
//! through its return value and `rlLastError`.

#![allow(clippy::missing_safety_doc)]

use std::cell::RefCell;
use std::ffi::{CStr, CString, c_char, c_void};
use std::panic::{AssertUnwindSafe, catch_unwind};

use arrow::array::{Array, AsArray};

use crate::{BytesPayload, Kind, Payload, PayloadSchema, RayFields, Reader, Recorder, RecorderOptions, TreeBuilder};

/// Opaque recorder handle (`rl_recorder`).
pub struct RlRecorder {
    rec: Recorder,
    id: usize,
}

/// Opaque reader handle (`rl_reader`).
pub struct RlReader {
    reader: Reader,
    trees: u64,
    rays: u64,
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

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlInit(path: *const c_char, payload_size: usize) -> *mut RlRecorder {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let path = unsafe { path_arg(path) }?;
        let bytes = (payload_size > 0).then_some(BytesPayload::Fixed(payload_size));
        let payload = PayloadSchema::new(Vec::new(), bytes).map_err(|e| e.to_string())?;
        let options = RecorderOptions { payload, ..Default::default() };
        let rec = Recorder::create(&path, options).map_err(|e| e.to_string())?;
        let boxed = Box::new(RlRecorder { rec, id: 0 });
        let ptr = Box::into_raw(boxed);
        // SAFETY: just allocated.
        unsafe { (*ptr).id = ptr as usize };
        Ok(ptr)
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
    guard(-1, || {
        // SAFETY: forwarded caller contract.
        let rec = unsafe { rec_arg(rec) }?;
        if origin.is_null() || direction.is_null() {
            return Err("origin and direction must point at 3 floats".into());
        }
        let kind = u8::try_from(kind).map_err(|_| format!("kind {kind} out of range 0..=255"))?;
        // SAFETY: the caller passes 3 floats each.
        let (o, d) = unsafe { (*(origin as *const [f32; 3]), *(direction as *const [f32; 3])) };
        let bytes = if payload.is_null() || payload_size == 0 {
            None
        } else {
            // SAFETY: the caller passes `payload_size` readable bytes.
            Some(unsafe { std::slice::from_raw_parts(payload as *const u8, payload_size) })
        };
        let fields = RayFields {
            origin: o,
            direction: d,
            t: (prim >= 0).then_some(t),
            kind: Kind(kind),
            prim: u32::try_from(prim).ok(),
        };
        with_tree(rec.id, |tree| {
            tree.add_ray(&fields, Payload { values: &[], bytes });
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
        // The emissive triangles as the emitters (`aims_at_light`, the paper's query, reads them).
        let lights = store::scene::lights_from_triangles(&batch).map_err(|e| format!("rlSetTriangles: {e}"))?;
        rec.rec.write_table(store::scene::TRIANGLES_TABLE, batch).map_err(|e| e.to_string())?;
        rec.rec.write_table(store::scene::LIGHTS_TABLE, lights).map_err(|e| e.to_string())?;
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
        boxed.rec.finish().map(|_| 0).map_err(|e| e.to_string())
    })
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlOpen(path: *const c_char) -> *mut RlReader {
    guard(std::ptr::null_mut(), || {
        // SAFETY: forwarded caller contract.
        let path = unsafe { path_arg(path) }?;
        let ds = crate::Dataset::open(&path).map_err(|e| e.to_string())?;
        let (trees, rays) = (ds.tree_count(), ds.ray_count());
        Ok(Box::into_raw(Box::new(RlReader { reader: Reader::new(Box::new(ds)), trees, rays })))
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
    guard(0, || Ok(unsafe { reader_arg(reader) }?.trees))
}

#[unsafe(no_mangle)]
pub unsafe extern "C" fn rlRayCount(reader: *mut RlReader) -> u64 {
    // SAFETY: forwarded caller contract.
    guard(0, || Ok(unsafe { reader_arg(reader) }?.rays))
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
