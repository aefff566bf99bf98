//! Columnar buffers rays are recorded into before they become Arrow record batches.

use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, BinaryArray, BooleanArray, DictionaryArray, FixedSizeBinaryArray, FixedSizeListArray,
    Float32Array, RecordBatch, StringArray, UInt8Array, UInt16Array, UInt32Array, UInt64Array, make_array,
};
use arrow::buffer::{BooleanBuffer, Buffer, NullBuffer, OffsetBuffer, ScalarBuffer};
use arrow::datatypes::{DataType, Field, SchemaRef, UInt8Type};

use crate::error::arrow_err;
use crate::schema::{BytesPayload, KindTable, PayloadSchema, Storage, ray_schema, tree_schema};
use crate::{Kind, Result};

/// "No parent" / "no primitive" in the recording buffers (null in Arrow).
pub const NONE_U32: u32 = u32::MAX;

/// A payload value handed to `add_ray` for one typed payload column.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Value<'a> {
    Null,
    Bool(bool),
    I8(i8),
    I16(i16),
    I32(i32),
    I64(i64),
    U8(u8),
    U16(u16),
    U32(u32),
    U64(u64),
    /// IEEE half float as raw bits.
    F16(u16),
    F32(f32),
    F64(f64),
    /// Elements of a fixed-size list column.
    List(ListValue<'a>),
}

/// The elements of a fixed-size list payload value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ListValue<'a> {
    I8(&'a [i8]),
    I16(&'a [i16]),
    I32(&'a [i32]),
    I64(&'a [i64]),
    U8(&'a [u8]),
    U16(&'a [u16]),
    U32(&'a [u32]),
    U64(&'a [u64]),
    F16(&'a [u16]),
    F32(&'a [f32]),
    F64(&'a [f64]),
}

impl Value<'_> {
    fn storage(&self) -> Option<Storage> {
        Some(match self {
            Value::Null | Value::List(_) => return None,
            Value::Bool(_) => Storage::Bool,
            Value::I8(_) => Storage::Int(1),
            Value::I16(_) => Storage::Int(2),
            Value::I32(_) => Storage::Int(4),
            Value::I64(_) => Storage::Int(8),
            Value::U8(_) => Storage::UInt(1),
            Value::U16(_) => Storage::UInt(2),
            Value::U32(_) => Storage::UInt(4),
            Value::U64(_) => Storage::UInt(8),
            Value::F16(_) => Storage::Float(2),
            Value::F32(_) => Storage::Float(4),
            Value::F64(_) => Storage::Float(8),
        })
    }

    /// A short description for error messages.
    pub fn describe(&self) -> String {
        match self {
            Value::Null => "null".into(),
            Value::List(l) => {
                let (name, n) = l.describe();
                format!("list of {n} {name}")
            }
            v => format!("{:?}", v.storage()),
        }
    }
}

impl ListValue<'_> {
    fn describe(&self) -> (&'static str, usize) {
        match self {
            ListValue::I8(s) => ("int8", s.len()),
            ListValue::I16(s) => ("int16", s.len()),
            ListValue::I32(s) => ("int32", s.len()),
            ListValue::I64(s) => ("int64", s.len()),
            ListValue::U8(s) => ("uint8", s.len()),
            ListValue::U16(s) => ("uint16", s.len()),
            ListValue::U32(s) => ("uint32", s.len()),
            ListValue::U64(s) => ("uint64", s.len()),
            ListValue::F16(s) => ("float16", s.len()),
            ListValue::F32(s) => ("float32", s.len()),
            ListValue::F64(s) => ("float64", s.len()),
        }
    }

    #[cfg(test)]
    fn storage(&self) -> Storage {
        match self {
            ListValue::I8(_) => Storage::Int(1),
            ListValue::I16(_) => Storage::Int(2),
            ListValue::I32(_) => Storage::Int(4),
            ListValue::I64(_) => Storage::Int(8),
            ListValue::U8(_) => Storage::UInt(1),
            ListValue::U16(_) => Storage::UInt(2),
            ListValue::U32(_) => Storage::UInt(4),
            ListValue::U64(_) => Storage::UInt(8),
            ListValue::F16(_) => Storage::Float(2),
            ListValue::F32(_) => Storage::Float(4),
            ListValue::F64(_) => Storage::Float(8),
        }
    }

    #[cfg(test)]
    fn len(&self) -> usize {
        self.describe().1
    }
}

/// Whether `value` fits a column of `storage` (a list of `list_len` elements when given). The
/// plain two-step reference [`write_fitting`] is tested against.
#[cfg(test)]
fn fits(value: Value<'_>, storage: Storage, list_len: Option<usize>) -> bool {
    match (value, list_len) {
        (Value::Null, _) => false,
        (Value::List(l), Some(n)) => l.storage() == storage && l.len() == n,
        (v, None) => v.storage() == Some(storage),
        _ => false,
    }
}

macro_rules! le_into {
    ($out:expr, $slice:expr, $w:expr) => {
        for (o, v) in $out.chunks_exact_mut($w).zip($slice.iter()) {
            o.copy_from_slice(&v.to_le_bytes());
        }
    };
}
pub(crate) use le_into;

/// Writes a value that [`fits`] its column into `out` (exactly its row width).
#[cfg(test)]
fn write_value(value: Value<'_>, out: &mut [u8]) {
    use ListValue as L;
    match value {
        Value::Bool(b) => out[0] = u8::from(b),
        Value::I8(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::I16(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::I32(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::I64(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::U8(v) => out[0] = v,
        Value::U16(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::U32(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::U64(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::F16(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::F32(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::F64(v) => out.copy_from_slice(&v.to_le_bytes()),
        Value::List(L::I8(s)) => le_into!(out, s, 1),
        Value::List(L::I16(s)) => le_into!(out, s, 2),
        Value::List(L::I32(s)) => le_into!(out, s, 4),
        Value::List(L::I64(s)) => le_into!(out, s, 8),
        Value::List(L::U8(s)) => out.copy_from_slice(s),
        Value::List(L::U16(s)) => le_into!(out, s, 2),
        Value::List(L::U32(s)) => le_into!(out, s, 4),
        Value::List(L::U64(s)) => le_into!(out, s, 8),
        Value::List(L::F16(s)) => le_into!(out, s, 2),
        Value::List(L::F32(s)) => le_into!(out, s, 4),
        Value::List(L::F64(s)) => le_into!(out, s, 8),
        Value::Null => {}
    }
}

/// Writes `value` into `out` (its column's row width) when it fits a column of `storage` (a
/// list of `list_len` elements when given), in one match: what [`fits`] then [`write_value`] do,
/// for both recording paths (rows and columns). Returns whether it was written.
#[inline]
pub(crate) fn write_fitting(value: Value<'_>, storage: Storage, list_len: Option<usize>, out: &mut [u8]) -> bool {
    use ListValue as L;
    use Storage::{Bool, Float, Int, UInt};
    macro_rules! list {
        ($s:expr, $st:expr, $w:expr) => {{
            if storage != $st || list_len != Some($s.len()) {
                return false;
            }
            le_into!(out, $s, $w);
        }};
    }
    if list_len.is_some() != matches!(value, Value::List(_)) {
        return false;
    }
    match value {
        Value::Null => return false,
        Value::Bool(b) if storage == Bool => out[0] = u8::from(b),
        Value::I8(v) if storage == Int(1) => out.copy_from_slice(&v.to_le_bytes()),
        Value::I16(v) if storage == Int(2) => out.copy_from_slice(&v.to_le_bytes()),
        Value::I32(v) if storage == Int(4) => out.copy_from_slice(&v.to_le_bytes()),
        Value::I64(v) if storage == Int(8) => out.copy_from_slice(&v.to_le_bytes()),
        Value::U8(v) if storage == UInt(1) => out[0] = v,
        Value::U16(v) if storage == UInt(2) => out.copy_from_slice(&v.to_le_bytes()),
        Value::U32(v) if storage == UInt(4) => out.copy_from_slice(&v.to_le_bytes()),
        Value::U64(v) if storage == UInt(8) => out.copy_from_slice(&v.to_le_bytes()),
        Value::F16(v) if storage == Float(2) => out.copy_from_slice(&v.to_le_bytes()),
        Value::F32(v) if storage == Float(4) => out.copy_from_slice(&v.to_le_bytes()),
        Value::F64(v) if storage == Float(8) => out.copy_from_slice(&v.to_le_bytes()),
        Value::List(L::I8(s)) => list!(s, Int(1), 1),
        Value::List(L::I16(s)) => list!(s, Int(2), 2),
        Value::List(L::I32(s)) => list!(s, Int(4), 4),
        Value::List(L::I64(s)) => list!(s, Int(8), 8),
        Value::List(L::U8(s)) => {
            if storage != UInt(1) || list_len != Some(s.len()) {
                return false;
            }
            out.copy_from_slice(s);
        }
        Value::List(L::U16(s)) => list!(s, UInt(2), 2),
        Value::List(L::U32(s)) => list!(s, UInt(4), 4),
        Value::List(L::U64(s)) => list!(s, UInt(8), 8),
        Value::List(L::F16(s)) => list!(s, Float(2), 2),
        Value::List(L::F32(s)) => list!(s, Float(4), 4),
        Value::List(L::F64(s)) => list!(s, Float(8), 8),
        _ => return false,
    }
    true
}

/// The buffer of one typed payload column.
#[derive(Clone, Debug, Default)]
pub struct PayloadBuf {
    pub bytes: Vec<u8>,
    pub valid: Vec<bool>,
}

/// Rounds the float32 or float64 values of a payload buffer (`element` values, little-endian)
/// to `keep` mantissa bits: round half to even on the bits; a value that would round to infinity
/// is truncated instead; NaN and infinities are left as they are. Other element types (and
/// `keep` at or above the type's mantissa width) are left untouched.
pub(crate) fn round_mantissas(element: &DataType, bytes: &mut [u8], keep: u8) {
    // (bytes per value, mantissa bits, exponent mask) of the float types.
    let (width, mantissa, exponent) = match element {
        DataType::Float32 => (4, 23, 0x7f80_0000u64),
        DataType::Float64 => (8, 52, 0x7ff0_0000_0000_0000),
        _ => return,
    };
    let keep = u32::from(keep);
    if keep >= mantissa {
        return;
    }
    let drop = mantissa - keep;
    let mask = (1u64 << drop) - 1;
    for v in bytes.chunks_exact_mut(width) {
        let mut a = [0u8; 8];
        a[..width].copy_from_slice(v);
        let b = u64::from_le_bytes(a);
        if b & exponent == exponent {
            continue; // NaN or infinity
        }
        // Half of the dropped range, plus the kept last bit (ties to even); a float32's bits
        // stay below 2^32, as the sum cannot pass the sign bit without making the exponent all ones.
        let r = (b + (mask >> 1) + ((b >> drop) & 1)) & !mask;
        let r = if r & exponent == exponent { b & !mask } else { r };
        v.copy_from_slice(&r.to_le_bytes()[..width]);
    }
}

/// The opaque bytes payload column buffer.
#[derive(Clone, Debug)]
pub struct BytesBuf {
    pub offsets: Vec<i32>,
    pub data: Vec<u8>,
    pub valid: Vec<bool>,
}

impl Default for BytesBuf {
    fn default() -> Self {
        Self { offsets: vec![0], data: Vec::new(), valid: Vec::new() }
    }
}

impl BytesBuf {
    /// Empties the buffer, keeping its allocations.
    pub fn clear(&mut self) {
        self.offsets.truncate(1);
        self.data.clear();
        self.valid.clear();
    }

    /// Appends the values of `other` (variable-size offsets shifted after the data held).
    pub fn append(&mut self, other: &BytesBuf) {
        let shift = self.data.len() as i32;
        self.data.extend_from_slice(&other.data);
        self.offsets.extend(other.offsets.iter().skip(1).map(|x| x + shift));
        self.valid.extend_from_slice(&other.valid);
    }
}

/// One row of the tree table, as recorded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TreeRow {
    pub tree_id: u64,
    pub pixel_x: u32,
    pub pixel_y: u32,
    pub sample: u32,
    pub ray_count: u32,
    pub max_depth: u16,
    /// Row of the tree's first ray in the buffer (or file) holding it.
    pub first_row: u64,
}

/// The core fields of one ray as a renderer records it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayFields {
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    /// Hit distance, `None` for a miss.
    pub t: Option<f32>,
    pub kind: Kind,
    /// Hit primitive, if any.
    pub prim: Option<u32>,
}

/// Why a payload did not fit its declared column: recorded, the value stored as null.
#[derive(Clone, Debug, PartialEq)]
pub struct PayloadMismatch {
    pub column: String,
    pub expected: String,
    pub found: String,
}

/// Rays of whole trees in columns, plus their tree rows.
#[derive(Clone, Debug, Default)]
pub struct RayColumns {
    pub tree_id: Vec<u64>,
    pub ray: Vec<u32>,
    pub parent: Vec<u32>,
    pub depth: Vec<u16>,
    pub kind: Vec<u8>,
    pub origin: [Vec<f32>; 3],
    pub direction: [Vec<f32>; 3],
    pub t: Vec<f32>,
    pub hit: Vec<bool>,
    pub prim: Vec<u32>,
    pub payload: Vec<PayloadBuf>,
    pub bytes: Option<BytesBuf>,
    pub trees: Vec<TreeRow>,
}

impl RayColumns {
    /// Empty buffers for a payload schema.
    pub fn new(schema: &PayloadSchema) -> Self {
        Self {
            payload: vec![PayloadBuf::default(); schema.fields.len()],
            bytes: schema.bytes.map(|_| BytesBuf::default()),
            ..Default::default()
        }
    }

    /// Number of rays held.
    pub fn len(&self) -> usize {
        self.tree_id.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tree_id.is_empty()
    }

    /// Approximate heap bytes held (for the memory budget).
    pub fn heap_bytes(&self) -> usize {
        let n = self.len();
        let core = n * (8 + 4 + 4 + 2 + 1 + 24 + 4 + 1 + 4);
        let payload: usize = self.payload.iter().map(|p| p.bytes.len() + p.valid.len()).sum();
        let bytes = self.bytes.as_ref().map_or(0, |b| b.data.len() + b.offsets.len() * 4 + b.valid.len());
        core + payload + bytes + self.trees.len() * std::mem::size_of::<TreeRow>()
    }

    /// Appends one ray's core fields (payload columns must be pushed separately, one per column).
    #[inline]
    pub fn push_core(&mut self, tree_id: u64, ray: u32, parent: u32, depth: u16, fields: &RayFields) {
        self.tree_id.push(tree_id);
        self.ray.push(ray);
        self.parent.push(parent);
        self.depth.push(depth);
        self.kind.push(fields.kind.0);
        for i in 0..3 {
            self.origin[i].push(fields.origin[i]);
            self.direction[i].push(fields.direction[i]);
        }
        self.t.push(fields.t.unwrap_or(0.0));
        self.hit.push(fields.t.is_some());
        self.prim.push(fields.prim.unwrap_or(NONE_U32));
    }

    /// Appends one ray's payload; a value that does not fit its column is stored as null and reported.
    pub fn push_payload(
        &mut self,
        schema: &PayloadSchema,
        values: &[Value<'_>],
        bytes: Option<&[u8]>,
        mismatches: &mut Vec<PayloadMismatch>,
    ) {
        for (i, field) in schema.fields.iter().enumerate() {
            let buf = &mut self.payload[i];
            let value = values.get(i).copied().unwrap_or(Value::Null);
            let start = buf.bytes.len();
            buf.bytes.resize(start + field.row_width(), 0);
            let ok = write_fitting(value, field.storage(), field.list_len, &mut buf.bytes[start..]);
            if !ok && value != Value::Null {
                mismatches.push(PayloadMismatch {
                    column: field.name.clone(),
                    expected: field.type_name(),
                    found: value.describe(),
                });
            }
            buf.valid.push(ok);
        }
        if values.len() > schema.fields.len() {
            mismatches.push(PayloadMismatch {
                column: "(payload)".into(),
                expected: format!("{} typed values", schema.fields.len()),
                found: format!("{} values", values.len()),
            });
        }
        push_bytes(&mut self.bytes, schema.bytes, bytes, mismatches);
    }

    /// Appends all rays of `other` (whose `trees` must describe them) after the rays held.
    pub fn append(&mut self, other: &RayColumns) {
        let base = self.len() as u64;
        self.tree_id.extend_from_slice(&other.tree_id);
        self.ray.extend_from_slice(&other.ray);
        self.parent.extend_from_slice(&other.parent);
        self.depth.extend_from_slice(&other.depth);
        self.kind.extend_from_slice(&other.kind);
        for i in 0..3 {
            self.origin[i].extend_from_slice(&other.origin[i]);
            self.direction[i].extend_from_slice(&other.direction[i]);
        }
        self.t.extend_from_slice(&other.t);
        self.hit.extend_from_slice(&other.hit);
        self.prim.extend_from_slice(&other.prim);
        for (p, q) in self.payload.iter_mut().zip(&other.payload) {
            p.bytes.extend_from_slice(&q.bytes);
            p.valid.extend_from_slice(&q.valid);
        }
        if let (Some(b), Some(o)) = (&mut self.bytes, &other.bytes) {
            b.append(o);
        }
        self.trees.extend(other.trees.iter().map(|t| TreeRow { first_row: t.first_row + base, ..*t }));
    }

    /// The rays as an Arrow record batch of the ray table schema.
    pub fn to_ray_batch(&self, schema: &PayloadSchema, kinds: &KindTable) -> Result<RecordBatch> {
        self.clone().into_ray_batch(schema, kinds)
    }

    /// Like [`RayColumns::to_ray_batch`], consuming the buffers instead of copying them.
    pub fn into_ray_batch(self, schema: &PayloadSchema, kinds: &KindTable) -> Result<RecordBatch> {
        let arrow_schema: SchemaRef = ray_schema(schema);
        let n = self.len();
        let nulls_where = |sentinel: &[u32]| -> Option<NullBuffer> {
            let valid: Vec<bool> = sentinel.iter().map(|&p| p != NONE_U32).collect();
            nullable(&valid)
        };
        let kind = kind_array(&self.kind, kinds)?;
        let parent_nulls = nulls_where(&self.parent);
        let prim_nulls = nulls_where(&self.prim);
        let mut columns: Vec<ArrayRef> = vec![
            Arc::new(UInt64Array::from(self.tree_id)),
            Arc::new(UInt32Array::from(self.ray)),
            Arc::new(UInt32Array::new(ScalarBuffer::from(self.parent), parent_nulls)),
            Arc::new(UInt16Array::from(self.depth)),
            Arc::new(kind),
        ];
        for c in self.origin.into_iter().chain(self.direction) {
            columns.push(Arc::new(Float32Array::from(c)));
        }
        columns.push(Arc::new(Float32Array::new(ScalarBuffer::from(self.t), nullable(&self.hit))));
        columns.push(Arc::new(UInt32Array::new(ScalarBuffer::from(self.prim), prim_nulls)));
        for (field, buf) in schema.fields.iter().zip(self.payload) {
            columns.push(payload_array(field, buf, n)?);
        }
        if let (Some(decl), Some(b)) = (schema.bytes, self.bytes) {
            let nulls = nullable(&b.valid);
            let arr: ArrayRef = match decl {
                BytesPayload::Fixed(size) => Arc::new(
                    FixedSizeBinaryArray::try_new(size as i32, Buffer::from_vec(b.data), nulls)
                        .map_err(arrow_err("bytes payload column"))?,
                ),
                BytesPayload::Variable => Arc::new(
                    BinaryArray::try_new(
                        OffsetBuffer::new(ScalarBuffer::from(b.offsets)),
                        Buffer::from_vec(b.data),
                        nulls,
                    )
                    .map_err(arrow_err("bytes payload column"))?,
                ),
            };
            columns.push(arr);
        }
        RecordBatch::try_new(arrow_schema, columns).map_err(arrow_err("ray batch"))
    }

    /// The tree table of `chunks` (runs each sorted by id) merged into one run sorted by id, as
    /// batches of at most `batch_rows` trees: the columns are built a batch at a time, never
    /// gathered whole (a 4M-ray segment holds ~1M trees; building them at once faulted in ~40 MB
    /// of fresh pages per segment on the writer threads).
    pub fn merged_tree_batches(
        chunks: &[Vec<TreeRow>],
        segment: u32,
        batch_rows: usize,
    ) -> impl Iterator<Item = Result<RecordBatch>> + '_ {
        let mut merge = RunMerge::new(chunks, |t: &TreeRow| t.tree_id);
        let batch_rows = batch_rows.max(1);
        std::iter::from_fn(move || {
            let mut cols = TreeCols::with_capacity(batch_rows);
            while cols.tree_id.len() < batch_rows {
                match merge.next() {
                    Some(t) => cols.push(t),
                    None => break,
                }
            }
            (!cols.tree_id.is_empty()).then(|| cols.into_batch(segment))
        })
    }
}

/// A merge of runs each sorted by a `u64` key into one run sorted by it (equal keys in no
/// particular order). Takes whole stretches of one run while they stay below every other run's head, so
/// runs that barely interleave cost about a comparison per element.
pub(crate) struct RunMerge<'a, T> {
    runs: &'a [Vec<T>],
    key: fn(&T) -> u64,
    /// (next key, run, position) of every run not yet drained, smallest key first.
    heads: std::collections::BinaryHeap<std::cmp::Reverse<(u64, usize, usize)>>,
    /// The run being drained and its position, while its keys stay below every other head.
    run: Option<(usize, usize)>,
}

impl<'a, T> RunMerge<'a, T> {
    pub(crate) fn new(runs: &'a [Vec<T>], key: fn(&T) -> u64) -> Self {
        let heads =
            runs.iter().enumerate().filter_map(|(c, v)| v.first().map(|t| std::cmp::Reverse((key(t), c, 0)))).collect();
        Self { runs, key, heads, run: None }
    }
}

impl<'a, T> Iterator for RunMerge<'a, T> {
    type Item = &'a T;

    fn next(&mut self) -> Option<&'a T> {
        if let Some((c, j)) = self.run {
            let run = &self.runs[c];
            match run.get(j) {
                Some(t) if self.heads.peek().is_none_or(|std::cmp::Reverse((k, _, _))| (self.key)(t) <= *k) => {
                    self.run = Some((c, j + 1));
                    return Some(t);
                }
                Some(t) => self.heads.push(std::cmp::Reverse(((self.key)(t), c, j))),
                None => {}
            }
            self.run = None;
        }
        let std::cmp::Reverse((_, c, j)) = self.heads.pop()?;
        self.run = Some((c, j + 1));
        self.runs[c].get(j)
    }
}

/// The columns of a tree table being built.
struct TreeCols {
    tree_id: Vec<u64>,
    pixel_x: Vec<u32>,
    pixel_y: Vec<u32>,
    sample: Vec<u32>,
    ray_count: Vec<u32>,
    max_depth: Vec<u16>,
    first_row: Vec<u64>,
}

impl TreeCols {
    fn with_capacity(n: usize) -> Self {
        Self {
            tree_id: Vec::with_capacity(n),
            pixel_x: Vec::with_capacity(n),
            pixel_y: Vec::with_capacity(n),
            sample: Vec::with_capacity(n),
            ray_count: Vec::with_capacity(n),
            max_depth: Vec::with_capacity(n),
            first_row: Vec::with_capacity(n),
        }
    }

    #[inline]
    fn push(&mut self, t: &TreeRow) {
        self.tree_id.push(t.tree_id);
        self.pixel_x.push(t.pixel_x);
        self.pixel_y.push(t.pixel_y);
        self.sample.push(t.sample);
        self.ray_count.push(t.ray_count);
        self.max_depth.push(t.max_depth);
        self.first_row.push(t.first_row);
    }

    fn into_batch(self, segment: u32) -> Result<RecordBatch> {
        let n = self.tree_id.len();
        RecordBatch::try_new(
            tree_schema(),
            vec![
                Arc::new(UInt64Array::from(self.tree_id)),
                Arc::new(UInt32Array::from(self.pixel_x)),
                Arc::new(UInt32Array::from(self.pixel_y)),
                Arc::new(UInt32Array::from(self.sample)),
                Arc::new(UInt32Array::from(self.ray_count)),
                Arc::new(UInt16Array::from(self.max_depth)),
                Arc::new(UInt32Array::from(vec![segment; n])),
                Arc::new(UInt64Array::from(self.first_row)),
            ],
        )
        .map_err(arrow_err("tree batch"))
    }
}

fn nullable(valid: &[bool]) -> Option<NullBuffer> {
    if valid.iter().all(|&v| v) { None } else { Some(NullBuffer::new(BooleanBuffer::from(valid.to_vec()))) }
}

fn payload_array(field: &crate::PayloadField, buf: PayloadBuf, n: usize) -> Result<ArrayRef> {
    let nulls = nullable(&buf.valid);
    let context = || format!("payload column {}", field.name);
    if field.storage() == Storage::Bool {
        let values = BooleanBuffer::from_iter(buf.bytes.iter().map(|&b| b != 0));
        return Ok(Arc::new(BooleanArray::new(values, nulls)));
    }
    let elems = n * field.list_len.unwrap_or(1);
    let data = arrow::array::ArrayData::builder(field.element.clone())
        .len(elems)
        .add_buffer(Buffer::from_vec(buf.bytes))
        .build()
        .map_err(arrow_err(context()))?;
    let values = make_array(data);
    match field.list_len {
        None => Ok(make_array(values.to_data().into_builder().nulls(nulls).build().map_err(arrow_err(context()))?)),
        Some(len) => Ok(Arc::new(
            FixedSizeListArray::try_new(
                Arc::new(Field::new("item", field.element.clone(), false)),
                len as i32,
                values,
                nulls,
            )
            .map_err(arrow_err(context()))?,
        )),
    }
}

/// The `kind` column for kind codes: a dictionary of only the kinds `codes` uses, so plain Parquet
/// readers see names.
pub(crate) fn kind_array(codes: &[u8], kinds: &KindTable) -> Result<DictionaryArray<UInt8Type>> {
    let mut seen = [false; 256];
    let mut used: Vec<u8> = Vec::new();
    for &k in codes {
        if !seen[k as usize] {
            seen[k as usize] = true;
            used.push(k);
        }
    }
    used.sort_unstable();
    let mut remap = [0u8; 256];
    let mut names = Vec::with_capacity(used.len());
    for (i, &k) in used.iter().enumerate() {
        remap[k as usize] = i as u8;
        names.push(kinds.name(Kind(k)).map_or_else(|| format!("kind{k}"), str::to_string));
    }
    let keys = UInt8Array::from(codes.iter().map(|&k| remap[k as usize]).collect::<Vec<_>>());
    DictionaryArray::try_new(keys, Arc::new(StringArray::from(names))).map_err(arrow_err("kind column"))
}

/// Appends one ray's opaque bytes payload to `buf` (declared as `decl`); bytes that do not fit
/// the declaration are stored as null and reported.
pub(crate) fn push_bytes(
    buf: &mut Option<BytesBuf>,
    decl: Option<BytesPayload>,
    bytes: Option<&[u8]>,
    mismatches: &mut Vec<PayloadMismatch>,
) {
    match (buf, decl) {
        (Some(buf), Some(decl)) => {
            let ok = match (bytes, decl) {
                (Some(b), BytesPayload::Fixed(n)) => {
                    if b.len() == n {
                        buf.data.extend_from_slice(b);
                        true
                    } else {
                        mismatches.push(PayloadMismatch {
                            column: "payload".into(),
                            expected: format!("{n} bytes"),
                            found: format!("{} bytes", b.len()),
                        });
                        buf.data.resize(buf.data.len() + n, 0);
                        false
                    }
                }
                (None, BytesPayload::Fixed(n)) => {
                    buf.data.resize(buf.data.len() + n, 0);
                    false
                }
                (Some(b), BytesPayload::Variable) => {
                    buf.data.extend_from_slice(b);
                    buf.offsets.push(buf.data.len() as i32);
                    true
                }
                (None, BytesPayload::Variable) => {
                    buf.offsets.push(buf.data.len() as i32);
                    false
                }
            };
            buf.valid.push(ok);
        }
        (_, _) => {
            if bytes.is_some() {
                mismatches.push(PayloadMismatch {
                    column: "payload".into(),
                    expected: "no bytes payload (none was declared)".into(),
                    found: "bytes".into(),
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::array::AsArray;
    use arrow::datatypes::{UInt32Type, UInt64Type};

    fn row(tree_id: u64, first_row: u64) -> TreeRow {
        TreeRow { tree_id, pixel_x: tree_id as u32 * 2, pixel_y: 7, sample: 1, ray_count: 3, max_depth: 2, first_row }
    }

    #[test]
    fn write_fitting_agrees_with_fits_and_write_value_for_every_value_and_column() {
        let (i8s, i16s, i32s, i64s) = ([1i8, -2], [3i16, -4], [5i32, -6, 7], [8i64, -9, 10]);
        let (u8s, u16s, u32s, u64s) = ([11u8, 12], [13u16, 14], [15u32, 16, 17], [18u64, 19, 20]);
        let (f16s, f32s, f64s) = ([0x3C00u16, 0xC000], [1.5f32, f32::NAN, -0.0], [2.5f64, f64::INFINITY, 1e300]);
        let values = [
            Value::Null,
            Value::Bool(true),
            Value::I8(-1),
            Value::I16(-300),
            Value::I32(-70_000),
            Value::I64(i64::MIN),
            Value::U8(255),
            Value::U16(65_535),
            Value::U32(u32::MAX),
            Value::U64(u64::MAX),
            Value::F16(0x7C00),
            Value::F32(f32::NAN),
            Value::F64(-0.0),
            Value::List(ListValue::I8(&i8s)),
            Value::List(ListValue::I16(&i16s)),
            Value::List(ListValue::I32(&i32s)),
            Value::List(ListValue::I64(&i64s)),
            Value::List(ListValue::U8(&u8s)),
            Value::List(ListValue::U16(&u16s)),
            Value::List(ListValue::U32(&u32s)),
            Value::List(ListValue::U64(&u64s)),
            Value::List(ListValue::F16(&f16s)),
            Value::List(ListValue::F32(&f32s)),
            Value::List(ListValue::F64(&f64s)),
        ];
        let storages = [1u8, 2, 4, 8]
            .into_iter()
            .flat_map(|w| [Storage::Int(w), Storage::UInt(w), Storage::Float(w)])
            .chain([Storage::Bool]);
        let mut written = 0;
        for storage in storages {
            for list_len in [None, Some(2), Some(3)] {
                let width = match storage {
                    Storage::Bool => 1,
                    Storage::Int(w) | Storage::UInt(w) | Storage::Float(w) => usize::from(w),
                } * list_len.unwrap_or(1);
                for v in values {
                    let (mut a, mut b) = (vec![0xAAu8; width], vec![0xAAu8; width]);
                    let ok = fits(v, storage, list_len);
                    if ok {
                        write_value(v, &mut a);
                        written += 1;
                    }
                    assert_eq!(
                        write_fitting(v, storage, list_len, &mut b),
                        ok,
                        "{v:?} into {storage:?} x {list_len:?}"
                    );
                    assert_eq!(a, b, "{v:?} into {storage:?} x {list_len:?}");
                }
            }
        }
        assert_eq!(written, 12 + 11, "every scalar fits its own column, every list its own length");
    }

    #[test]
    fn tree_chunks_merge_into_one_run_sorted_by_id() {
        // Three tracing threads' chunks: interleaved ids, runs, one empty chunk, one lone tree.
        let chunks = vec![
            vec![row(0, 0), row(3, 3), row(4, 6), row(5, 9), row(11, 12)],
            vec![],
            vec![row(1, 15), row(2, 18), row(6, 21), row(9, 24)],
            vec![row(7, 27), row(8, 30), row(10, 33)],
            vec![row(12, 36)],
        ];
        for batch_rows in [1, 4, 5, 13, 100] {
            let batches: Vec<RecordBatch> =
                RayColumns::merged_tree_batches(&chunks, 4, batch_rows).collect::<Result<_>>().unwrap();
            assert_eq!(batches.len(), 13usize.div_ceil(batch_rows));
            assert!(batches.iter().all(|b| b.num_rows() <= batch_rows));
            let batch = arrow::compute::concat_batches(&batches[0].schema(), &batches).unwrap();
            let ids: Vec<u64> = batch.column(0).as_primitive::<UInt64Type>().values().to_vec();
            assert_eq!(ids, (0..13).collect::<Vec<u64>>());
            // Every field travels with its id.
            let px = batch.column(1).as_primitive::<UInt32Type>();
            let first = batch.column(7).as_primitive::<UInt64Type>();
            for (k, id) in ids.iter().enumerate() {
                assert_eq!(px.value(k), *id as u32 * 2);
                let src = chunks.iter().flatten().find(|t| t.tree_id == *id).unwrap();
                assert_eq!(first.value(k), src.first_row);
            }
            assert!(batch.column(6).as_primitive::<UInt32Type>().values().iter().all(|&s| s == 4));
        }
        assert_eq!(RayColumns::merged_tree_batches(&[], 1, 8).count(), 0);
        assert_eq!(RayColumns::merged_tree_batches(&[vec![], vec![]], 1, 8).count(), 0);
    }
}
