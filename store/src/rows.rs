//! Row buffers for recording: what a tracing thread fills per ray (one struct of core fields and
//! one fixed-width slot of typed payload values), turned into [`RayColumns`] by a writer thread.
//!
//! A tree recorded into columns costs its tracing thread a push into each of some 20 column
//! buffers per ray and a copy of each of them when the tree ends; as rows it is two pushes per
//! ray and two copies per tree. The transposition into columns happens where the rays are
//! encoded anyway, off the tracing threads.

use crate::columns::{
    BytesBuf, ListValue, NONE_U32, PayloadBuf, PayloadMismatch, RayColumns, RayFields, TreeRow, Value, le_into,
    write_fitting,
};
use crate::schema::{PayloadSchema, Storage};
use crate::{Error, Result};

/// One ray's core fields as a tracing thread records it (tree id and ray index come from the
/// tree rows: a tree's rays are contiguous and numbered from 0).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CoreRow {
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    /// Hit distance; 0 for a miss.
    pub t: f32,
    /// Hit primitive, [`NONE_U32`] for none.
    pub prim: u32,
    /// Parent ray within the tree, [`NONE_U32`] for a root.
    pub parent: u32,
    pub depth: u16,
    pub kind: u8,
    pub hit: bool,
}

impl CoreRow {
    #[inline]
    pub fn new(parent: u32, depth: u16, f: &RayFields) -> Self {
        Self {
            origin: f.origin,
            direction: f.direction,
            t: f.t.unwrap_or(0.0),
            prim: f.prim.unwrap_or(NONE_U32),
            parent,
            depth,
            kind: f.kind.0,
            hit: f.t.is_some(),
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Slot {
    offset: usize,
    width: usize,
    storage: Storage,
    list_len: Option<usize>,
    common: Common,
}

/// The column types tracers record most (a path tracer's colours and counters), written without
/// `write_fitting`'s dispatch on the value: the branch is on the slot, the same for every ray,
/// where a dispatch on the value mispredicted as the values' types alternated along the row
/// (with `push_payload`, 15% of a recording whose chunks were dropped at the sink: `perf record`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Common {
    /// `float32[n]`.
    F32List,
    /// `uint32`.
    U32,
    /// `float32`.
    F32,
    Other,
}

impl Common {
    fn of(storage: Storage, list_len: Option<usize>) -> Self {
        match (storage, list_len) {
            (Storage::Float(4), Some(_)) => Common::F32List,
            (Storage::UInt(4), None) => Common::U32,
            (Storage::Float(4), None) => Common::F32,
            _ => Common::Other,
        }
    }

    /// Writes `value` into `out` when it is this slot's common type; None otherwise.
    #[inline(always)]
    fn write(self, value: Value<'_>, out: &mut [u8]) -> Option<()> {
        match self {
            Common::F32List => {
                let Value::List(ListValue::F32(s)) = value else { return None };
                if s.len() * 4 != out.len() {
                    return None;
                }
                le_into!(out, s, 4);
            }
            Common::U32 => {
                let Value::U32(v) = value else { return None };
                out.copy_from_slice(&v.to_le_bytes());
            }
            Common::F32 => {
                let Value::F32(v) = value else { return None };
                out.copy_from_slice(&v.to_le_bytes());
            }
            Common::Other => return None,
        }
        Some(())
    }
}

/// Where each typed payload column sits in a payload row: its value bytes at `offset`
/// (little-endian, as in the column buffers), then one validity byte per column at the end.
#[derive(Clone, Debug, Default)]
pub struct RowLayout {
    slots: Vec<Slot>,
    valid_at: usize,
    stride: usize,
}

impl RowLayout {
    pub fn new(schema: &PayloadSchema) -> Self {
        let mut offset = 0;
        let slots: Vec<Slot> = schema
            .fields
            .iter()
            .map(|f| {
                let (storage, list_len) = (f.storage(), f.list_len);
                let common = Common::of(storage, list_len);
                let s = Slot { offset, width: f.row_width(), storage, list_len, common };
                offset += s.width;
                s
            })
            .collect();
        let stride = offset + slots.len();
        Self { slots, valid_at: offset, stride }
    }

    /// Bytes of one payload row.
    pub fn stride(&self) -> usize {
        self.stride
    }
}

/// Rays of whole trees as rows, plus their tree rows (`first_row` within this buffer).
#[derive(Clone, Debug, Default)]
pub struct RayRows {
    pub core: Vec<CoreRow>,
    /// Payload rows, [`RowLayout::stride`] bytes per ray (empty without typed payload columns).
    pub payload: Vec<u8>,
    pub bytes: Option<BytesBuf>,
    pub trees: Vec<TreeRow>,
}

impl RayRows {
    /// Empty buffers for a payload schema.
    pub fn new(schema: &PayloadSchema) -> Self {
        Self { bytes: schema.bytes.map(|_| BytesBuf::default()), ..Default::default() }
    }

    /// Empty buffers with room for `rays` rays.
    pub fn with_capacity(schema: &PayloadSchema, layout: &RowLayout, rays: usize) -> Self {
        Self {
            core: Vec::with_capacity(rays),
            payload: Vec::with_capacity(rays * layout.stride),
            bytes: schema.bytes.map(|_| BytesBuf::default()),
            trees: Vec::with_capacity(rays / 4 + 1),
        }
    }

    /// Number of rays held.
    #[inline]
    pub fn len(&self) -> usize {
        self.core.len()
    }

    pub fn is_empty(&self) -> bool {
        self.core.is_empty()
    }

    /// Empties the buffers, keeping their allocations.
    pub fn clear(&mut self) {
        self.core.clear();
        self.payload.clear();
        if let Some(b) = &mut self.bytes {
            b.clear();
        }
        self.trees.clear();
    }

    /// Approximate heap bytes held (for the memory budget).
    pub fn heap_bytes(&self) -> usize {
        let bytes = self.bytes.as_ref().map_or(0, |b| b.data.len() + b.offsets.len() * 4 + b.valid.len());
        self.core.len() * std::mem::size_of::<CoreRow>()
            + self.payload.len()
            + bytes
            + self.trees.len() * std::mem::size_of::<TreeRow>()
    }

    /// Appends one ray's core fields (its payload, if any, must follow with `push_payload`).
    #[inline]
    pub fn push_core(&mut self, parent: u32, depth: u16, fields: &RayFields) {
        self.core.push(CoreRow::new(parent, depth, fields));
    }

    /// Appends one ray's payload; a value that does not fit its column is stored as null and
    /// reported.
    pub fn push_payload(
        &mut self,
        schema: &PayloadSchema,
        layout: &RowLayout,
        values: &[Value<'_>],
        bytes: Option<&[u8]>,
        mismatches: &mut Vec<PayloadMismatch>,
    ) {
        if layout.stride > 0 {
            let start = self.payload.len();
            self.payload.resize(start + layout.stride, 0);
            let row = &mut self.payload[start..];
            for (i, slot) in layout.slots.iter().enumerate() {
                let value = values.get(i).copied().unwrap_or(Value::Null);
                let out = &mut row[slot.offset..slot.offset + slot.width];
                if slot.common.write(value, out).is_some() || write_fitting(value, slot.storage, slot.list_len, out) {
                    row[layout.valid_at + i] = 1;
                } else if value != Value::Null
                    && let Some(field) = schema.fields.get(i)
                {
                    mismatches.push(PayloadMismatch {
                        column: field.name.clone(),
                        expected: field.type_name(),
                        found: value.describe(),
                    });
                }
            }
        }
        if values.len() > layout.slots.len() {
            mismatches.push(PayloadMismatch {
                column: "(payload)".into(),
                expected: format!("{} typed values", layout.slots.len()),
                found: format!("{} values", values.len()),
            });
        }
        crate::columns::push_bytes(&mut self.bytes, schema.bytes, bytes, mismatches);
    }

    /// Sets typed column `slot` of the last ray's payload row to `value` (valid): the recorder
    /// fills the `site` column this way, after the caller's values. False when there is no row
    /// or the column cannot hold the value.
    pub fn set_last_value(&mut self, layout: &RowLayout, slot: usize, value: Value<'_>) -> bool {
        let Some(s) = layout.slots.get(slot) else { return false };
        let Some(start) = self.payload.len().checked_sub(layout.stride) else { return false };
        let row = &mut self.payload[start..];
        if !write_fitting(value, s.storage, s.list_len, &mut row[s.offset..s.offset + s.width]) {
            return false;
        }
        row[layout.valid_at + slot] = 1;
        true
    }

    /// Appends all rays of `other` (whose `trees` must describe them) after the rays held.
    pub fn append(&mut self, other: &RayRows) {
        let base = self.len() as u64;
        self.core.extend_from_slice(&other.core);
        self.payload.extend_from_slice(&other.payload);
        if let (Some(b), Some(o)) = (&mut self.bytes, &other.bytes) {
            b.append(o);
        }
        self.trees.extend(other.trees.iter().map(|t| TreeRow { first_row: t.first_row + base, ..*t }));
    }

    /// The rays as columns. The tree rows must cover the rays in order, each from its
    /// `first_row`, as trees recorded through `rl` do.
    pub fn into_columns(mut self, layout: &RowLayout) -> Result<RayColumns> {
        let bytes = self.bytes.take();
        let trees = std::mem::take(&mut self.trees);
        self.columns_with(layout, bytes, trees)
    }

    /// The rays as columns, leaving these buffers as they are (to be cleared and filled again:
    /// a writer hands them back to the tracing threads instead of freeing them).
    pub fn to_columns(&self, layout: &RowLayout) -> Result<RayColumns> {
        self.columns_with(layout, self.bytes.clone(), self.trees.clone())
    }

    fn columns_with(&self, layout: &RowLayout, bytes: Option<BytesBuf>, trees: Vec<TreeRow>) -> Result<RayColumns> {
        let n = self.len();
        let mut tree_id = Vec::with_capacity(n);
        let mut ray = Vec::with_capacity(n);
        for t in &trees {
            if t.first_row != tree_id.len() as u64 {
                return Err(uncovered(format!(
                    "tree {} starts at row {}, expected {}",
                    t.tree_id,
                    t.first_row,
                    tree_id.len()
                )));
            }
            tree_id.extend(std::iter::repeat_n(t.tree_id, t.ray_count as usize));
            ray.extend(0..t.ray_count);
        }
        if tree_id.len() != n {
            return Err(uncovered(format!("the trees hold {} rays, the buffer {n}", tree_id.len())));
        }
        if self.payload.len() != n * layout.stride {
            return Err(uncovered(format!(
                "{} payload bytes for {n} rays of {} bytes",
                self.payload.len(),
                layout.stride
            )));
        }
        let core = &self.core;
        let col = |f: fn(&CoreRow) -> f32| core.iter().map(f).collect::<Vec<f32>>();
        let payload = layout
            .slots
            .iter()
            .enumerate()
            .map(|(i, s)| {
                let mut bytes = vec![0; n * s.width];
                let (rows, stride) = (&self.payload, layout.stride.max(1));
                // The widths of a float32[3] and of a 4-byte scalar given as constants, so that
                // the inlined copy is a move, not a memcpy call per value.
                match s.width {
                    4 => gather(rows, stride, s.offset, 4, &mut bytes),
                    12 => gather(rows, stride, s.offset, 12, &mut bytes),
                    w => gather(rows, stride, s.offset, w, &mut bytes),
                }
                let at = layout.valid_at + i;
                let valid = rows.chunks_exact(stride).map(|row| row[at] != 0).collect();
                PayloadBuf { bytes, valid }
            })
            .collect();
        Ok(RayColumns {
            tree_id,
            ray,
            parent: core.iter().map(|r| r.parent).collect(),
            depth: core.iter().map(|r| r.depth).collect(),
            kind: core.iter().map(|r| r.kind).collect(),
            origin: [col(|r| r.origin[0]), col(|r| r.origin[1]), col(|r| r.origin[2])],
            direction: [col(|r| r.direction[0]), col(|r| r.direction[1]), col(|r| r.direction[2])],
            t: col(|r| r.t),
            hit: core.iter().map(|r| r.hit).collect(),
            prim: core.iter().map(|r| r.prim).collect(),
            payload,
            bytes,
            trees,
        })
    }
}

/// Copies the `width` bytes at `offset` of every `stride`-byte row into `out`, row after row:
/// the transposition of one payload column. Inlined, so a constant `width` makes each copy a move.
#[inline(always)]
fn gather(rows: &[u8], stride: usize, offset: usize, width: usize, out: &mut [u8]) {
    if width == 0 {
        return;
    }
    for (o, row) in out.chunks_exact_mut(width).zip(rows.chunks_exact(stride)) {
        o.copy_from_slice(&row[offset..offset + width]);
    }
}

fn uncovered(message: String) -> Error {
    Error::Corrupt { path: std::path::PathBuf::new(), what: "recorded rows".into(), message }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::schema::{BytesPayload, PayloadField};
    use crate::{Kind, TreeRow};
    use arrow::datatypes::DataType;

    fn schema(bytes: Option<BytesPayload>) -> PayloadSchema {
        PayloadSchema {
            fields: vec![
                PayloadField::list("tp", DataType::Float32, 3).unwrap(),
                PayloadField::scalar("mat", DataType::UInt32).unwrap(),
                PayloadField::scalar("flag", DataType::Boolean).unwrap(),
                PayloadField::scalar("w", DataType::Float64).unwrap(),
                PayloadField::scalar("pdf", DataType::Float32).unwrap(),
            ],
            bytes,
        }
    }

    fn fields(i: u32, hit: bool) -> RayFields {
        let f = i as f32;
        RayFields {
            origin: [f, -f, 0.5 * f],
            direction: [0.0, 1.0, -0.0],
            t: hit.then_some(f + 0.25),
            kind: Kind((i % 5) as u8),
            prim: hit.then_some(i * 7),
        }
    }

    /// Records the same trees into rows and into columns; the rows' columns must equal them.
    fn both(schema: &PayloadSchema) -> (RayRows, RayColumns, Vec<PayloadMismatch>, Vec<PayloadMismatch>) {
        let layout = RowLayout::new(schema);
        let mut rows = RayRows::new(schema);
        let mut cols = RayColumns::new(schema);
        let (mut m_rows, mut m_cols) = (Vec::new(), Vec::new());
        for tree in 0..5u64 {
            let mut tree_rows = RayRows::new(schema);
            let mut tree_cols = RayColumns::new(schema);
            let n = tree as u32 + 1;
            for i in 0..n {
                let parent = if i == 0 { NONE_U32 } else { i - 1 };
                let f = fields(i + tree as u32, i % 2 == 0);
                let tp = [i as f32, 2.0, f32::NAN];
                let bytes = [i as u8; 4];
                let values = [
                    // Mismatches on the common types' path too: a list one short, a u32 for a float.
                    Value::List(ListValue::F32(if i == 3 { &tp[..2] } else { &tp })),
                    if i == 1 { Value::Null } else { Value::U32(i * 3) },
                    if i == 2 { Value::U8(1) } else { Value::Bool(i % 2 == 1) }, // a mismatch
                    Value::F64(-(i as f64)),
                    if i == 4 { Value::U32(1) } else { Value::F32(0.5 * i as f32) },
                ];
                let b = (i != 3).then_some(&bytes[..]);
                tree_rows.push_core(parent, i as u16, &f);
                tree_rows.push_payload(schema, &layout, &values, b, &mut m_rows);
                tree_cols.push_core(tree, i, parent, i as u16, &f);
                tree_cols.push_payload(schema, &values, b, &mut m_cols);
            }
            let row = TreeRow {
                tree_id: tree + 100,
                pixel_x: 1,
                pixel_y: 2,
                sample: 3,
                ray_count: n,
                max_depth: n as u16 - 1,
                first_row: 0,
            };
            tree_rows.trees.push(row);
            tree_cols.trees.push(row);
            tree_cols.tree_id.iter_mut().for_each(|t| *t = tree + 100);
            rows.append(&tree_rows);
            cols.append(&tree_cols);
        }
        (rows, cols, m_rows, m_cols)
    }

    #[test]
    fn rows_become_the_columns_recorded_directly() {
        for bytes in [None, Some(BytesPayload::Fixed(4)), Some(BytesPayload::Variable)] {
            let schema = schema(bytes);
            let (rows, cols, m_rows, m_cols) = both(&schema);
            assert_eq!(m_rows, m_cols);
            for column in ["tp", "flag", "pdf"] {
                assert!(m_rows.iter().any(|m| m.column == column), "a mismatch in `{column}` is reported: {m_rows:?}");
            }
            assert_eq!(rows.len(), 15);
            let kept = rows.to_columns(&RowLayout::new(&schema)).unwrap();
            let got = rows.into_columns(&RowLayout::new(&schema)).unwrap();
            // NaN payloads compare by bits through the byte buffers.
            assert_eq!(format!("{got:?}"), format!("{cols:?}"));
            assert_eq!(format!("{kept:?}"), format!("{cols:?}"), "to_columns reads the same columns");
        }
    }

    #[test]
    fn rows_without_payload_have_no_payload_bytes() {
        let schema = PayloadSchema::default();
        let layout = RowLayout::new(&schema);
        assert_eq!(layout.stride(), 0);
        let mut rows = RayRows::new(&schema);
        let mut m = Vec::new();
        rows.push_core(NONE_U32, 0, &fields(1, true));
        rows.push_payload(&schema, &layout, &[Value::U8(1)], None, &mut m);
        assert!(rows.payload.is_empty());
        assert_eq!(m.len(), 1, "an undeclared value is reported");
        rows.trees.push(TreeRow {
            tree_id: 9,
            pixel_x: 0,
            pixel_y: 0,
            sample: 0,
            ray_count: 1,
            max_depth: 0,
            first_row: 0,
        });
        let cols = rows.clone().into_columns(&layout).unwrap();
        assert_eq!(cols.tree_id, vec![9]);
        assert_eq!(cols.t, vec![1.25]);
        rows.clear();
        assert!(rows.is_empty() && rows.trees.is_empty());
    }

    #[test]
    fn rows_not_covered_by_their_trees_are_an_error() {
        let schema = PayloadSchema::default();
        let layout = RowLayout::new(&schema);
        let mut rows = RayRows::new(&schema);
        rows.push_core(NONE_U32, 0, &fields(1, false));
        rows.push_core(0, 1, &fields(2, false));
        let tree = TreeRow { tree_id: 1, pixel_x: 0, pixel_y: 0, sample: 0, ray_count: 1, max_depth: 0, first_row: 0 };
        rows.trees.push(tree);
        let e = rows.clone().into_columns(&layout).unwrap_err().to_string();
        assert!(e.contains("the trees hold 1 rays, the buffer 2"), "{e}");
        rows.trees[0] = TreeRow { first_row: 1, ..tree };
        let e = rows.into_columns(&layout).unwrap_err().to_string();
        assert!(e.contains("starts at row 1, expected 0"), "{e}");
    }
}
