//! The path payload predicted (format version 4, encoded layouts): `throughput` by its colour,
//! `radiance` from the path's own arithmetic.
//!
//! A path tracer that records each ray's `throughput` (the path weight it was spawned with) and
//! `radiance` (the light it carries back to its origin) writes numbers tied to each other. Stored
//! as they are, they are nearly random floats: 10.3 of the 23.6 bytes a ray of a path-traced
//! Cornell box took. When the payload declares both as `float32[3]`, encoded ray files store
//! them as residuals against predictions instead:
//!
//! - **Throughput by colour.** A shadow ray's weight is its parent's throughput times the
//!   material's colour times one scalar (geometry over pdf), so its three channels keep one of a
//!   few ratios: the Cornell box's 1M distinct shadow weights have 84 colours. The writer learns
//!   a segment's colours (the first triple seen of each, keyed by its two channel ratios to 13
//!   bits) and saves them in the ray file's key-value metadata (`rtvtk.chromas`, base64 of
//!   little-endian f32 triples). `enc_chroma` (`uint16`) names a ray's colour in its low 13 bits
//!   (1-based; 0: none) and flags null payloads; `enc_throughput_r/g/b` (`uint32` each) hold the
//!   first channel's bits and the two others' zig-zag ULP distances to `r * (g_ref / r_ref)` and
//!   `r * (b_ref / r_ref)` (computed in `f64` as `(r / r_ref) * g_ref`, rounded to `f32`), or
//!   their bits with colour 0. A colour never changes once learned, so one tree still decodes on
//!   its own.
//! - **Radiance by the path's arithmetic.** The tree's root carries the whole sample's estimate
//!   `L`, the sum of what its shadow rays brought (`throughput * radiance` of each, added in
//!   recording order), and every other ray carries what was gathered after it,
//!   `(L - gathered before it) / throughput`. `radiance` is stored as `enc_radiance_r/g/b`
//!   (`uint32` each): each component's zig-zag ULP distance to its prediction, per tree of rows
//!   `s..e`:
//!   - shadow rays (kind code 1) other than the root: predicted 0 (the bits are stored; they are
//!     the emitter's radiance or zero);
//!   - the root (row `s`): the sum over those shadow rays, in row order, of
//!     `throughput * radiance` (throughput present; a null radiance counts as 0), in `f32`,
//!     starting from 0;
//!   - every other ray: per component, `(L - acc) / b` where `b > 0`, else 0, with `L` the root's
//!     radiance, `acc` that sum over the shadow rays before it, and `b` its throughput; 0 when
//!     its throughput is null.
//!
//!   In `f32` and in the same order as the path tracer, the predictions come out exactly. A ray
//!   whose residuals against 0 have fewer significant bits (another renderer's arithmetic) is
//!   stored against 0 instead, flagged by bit 15 of `enc_chroma`.
//!
//! Any other renderer's values round-trip too (every bit pattern does); they only cost more.
//! The radiance prediction reads a whole tree before its root, so decoding it needs batches
//! that end at tree ends ([`tree_aligned`]); a tree still decodes on its own.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, FixedSizeListArray, Float32Array, RecordBatch, UInt16Array, UInt32Array};
use arrow::buffer::NullBuffer;
use arrow::datatypes::{DataType, Field, Float32Type, Schema, UInt8Type, UInt16Type, UInt32Type, UInt64Type};

use crate::schema::{KIND_CODE, Kind, typed_column};
use crate::ulp::{apply, residual};
use crate::{Error, Result};

/// The payload column of each ray's path weight.
pub const THROUGHPUT: &str = "throughput";
/// The payload column of the light each ray carries back.
pub const RADIANCE: &str = "radiance";
/// The ray-file columns `radiance` is stored in, one per channel (format version 4, encoded
/// layouts): flat columns without nulls read several times faster than a nullable list.
pub const ENC_RADIANCE: [&str; 3] = ["enc_radiance_r", "enc_radiance_g", "enc_radiance_b"];
/// The ray-file columns `throughput` is stored in (with [`ENC_CHROMA`]).
pub const ENC_THROUGHPUT: [&str; 3] = ["enc_throughput_r", "enc_throughput_g", "enc_throughput_b"];
/// The ray-file column naming each ray's throughput colour, with its payload's null flags.
pub const ENC_CHROMA: &str = "enc_chroma";
/// Key-value metadata key of a ray file's throughput colours.
pub const CHROMAS_KEY: &str = "rtvtk.chromas";
/// Colours a segment learns at most (`enc_chroma`'s low 13 bits, 1-based, 0 for none).
const MAX_CHROMAS: usize = 0x1fff;
/// Bits of `enc_chroma`: the colour; the ray's throughput is null; its radiance is null; its
/// radiance is stored against 0 (its bits) instead of its prediction, which was further off
/// (another renderer's arithmetic).
const COLOUR: u16 = 0x1fff;
const THROUGHPUT_NULL: u16 = 0x2000;
const RADIANCE_NULL: u16 = 0x4000;
const RADIANCE_RAW: u16 = 0x8000;

/// Whether `f` is a `float32[3]` column.
fn is_rgb(f: &Field) -> bool {
    matches!(f.data_type(), DataType::FixedSizeList(item, 3) if item.data_type() == &DataType::Float32)
}

/// Whether the ray table `plain` holds the path payload, which encoded layouts predict.
pub(crate) fn predicts_path_payload(plain: &Schema) -> bool {
    let rgb = |name: &str| plain.field_with_name(name).is_ok_and(is_rgb);
    rgb(THROUGHPUT) && rgb(RADIANCE)
}

/// Whether a ray file of schema `file` predicts the path payload (it has `enc_chroma`).
pub(crate) fn predicted_in(file: &Schema) -> bool {
    file.index_of(ENC_CHROMA).is_ok()
}

/// The ray-file fields standing for the payload field `f` (`throughput` or `radiance`).
pub(crate) fn encoded_fields(f: &Field) -> Vec<Field> {
    let flat = |name: &str| Field::new(name, DataType::UInt32, false);
    if f.name() == THROUGHPUT {
        let mut v: Vec<Field> = ENC_THROUGHPUT.iter().map(|n| flat(n)).collect();
        v.push(Field::new(ENC_CHROMA, DataType::UInt16, false));
        v
    } else {
        ENC_RADIANCE.iter().map(|n| flat(n)).collect()
    }
}

/// All the ray-file columns of the path payload, in file order.
pub(crate) fn encoded_columns() -> impl Iterator<Item = &'static str> {
    ENC_THROUGHPUT.into_iter().chain([ENC_CHROMA]).chain(ENC_RADIANCE)
}

/// The throughput colours of a segment, as its ray file saves them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Chromas {
    refs: Vec<[f32; 3]>,
}

impl Chromas {
    pub fn len(&self) -> usize {
        self.refs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.refs.is_empty()
    }

    /// The value of [`CHROMAS_KEY`].
    pub fn to_metadata(&self) -> String {
        use base64::Engine;
        let bytes: Vec<u8> = self.refs.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        base64::engine::general_purpose::STANDARD.encode(bytes)
    }

    /// Parses [`Chromas::to_metadata`] output.
    pub fn from_metadata(value: &str) -> std::result::Result<Self, String> {
        use base64::Engine;
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(value.trim())
            .map_err(|e| format!("{CHROMAS_KEY} is not base64: {e}"))?;
        if bytes.len() % 12 != 0 || bytes.len() / 12 > MAX_CHROMAS {
            return Err(format!(
                "{CHROMAS_KEY} holds {} bytes: expected up to {MAX_CHROMAS} triples of f32",
                bytes.len()
            ));
        }
        let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let refs: Vec<[f32; 3]> = bytes.chunks_exact(12).map(|r| [f(&r[0..4]), f(&r[4..8]), f(&r[8..12])]).collect();
        if let Some((k, _)) = refs.iter().enumerate().find(|(_, v)| !usable(**v)) {
            return Err(format!(
                "{CHROMAS_KEY}: colour {} is not a finite triple with a non-zero first channel",
                k + 1
            ));
        }
        Ok(Self { refs })
    }
}

/// Whether a colour can be predicted from: finite, first channel not zero.
#[inline]
fn usable(v: [f32; 3]) -> bool {
    v[0].is_finite() && v[0] != 0.0 && v[1].is_finite() && v[2].is_finite()
}

/// The second and third channels predicted from the first, `r`, and a colour's triple.
#[inline]
fn by_colour(r: f32, c: [f32; 3]) -> [f32; 2] {
    let k = f64::from(r) / f64::from(c[0]);
    [(k * f64::from(c[1])) as f32, (k * f64::from(c[2])) as f32]
}

/// Learns a segment's throughput colours while it is written.
#[derive(Default)]
pub(crate) struct ChromaLearner {
    slots: std::collections::HashMap<u64, u16, ahash::RandomState>,
    chromas: Chromas,
}

impl ChromaLearner {
    /// The colour of `v` (1-based), learned now if new; 0 for none.
    fn slot(&mut self, v: [f32; 3]) -> u16 {
        if !usable(v) {
            return 0;
        }
        // The two channel ratios to 13 mantissa bits (about 1e-4).
        let ratio = |c: f32| ((f64::from(c) / f64::from(v[0])) as f32).to_bits() >> 10;
        let key = (u64::from(ratio(v[1])) << 32) | u64::from(ratio(v[2]));
        if let Some(&s) = self.slots.get(&key) {
            return s;
        }
        if self.chromas.refs.len() >= MAX_CHROMAS {
            return 0;
        }
        self.chromas.refs.push(v);
        let s = self.chromas.refs.len() as u16;
        self.slots.insert(key, s);
        s
    }

    pub(crate) fn chromas(&self) -> &Chromas {
        &self.chromas
    }
}

/// The path payload's ray-file columns of whole trees ([`encoded_columns`], in that order):
/// `tree`, `kind` codes, `throughput` and `radiance` as the ray table holds them; colours
/// learned into `learner`.
pub(crate) fn encode_path(
    tree: &[u64],
    kind: &[u8],
    throughput: &ArrayRef,
    radiance: &ArrayRef,
    learner: &mut ChromaLearner,
) -> Result<Vec<ArrayRef>> {
    let (enc_throughput, mut flags) = encode_throughput(throughput, learner)?;
    let (enc_radiance, radiance_flags) = encode_radiance(tree, kind, throughput, radiance)?;
    for (s, f) in flags.iter_mut().zip(radiance_flags) {
        *s |= f;
    }
    let flat = |c: Vec<u32>| Arc::new(UInt32Array::from(c)) as ArrayRef;
    let mut out: Vec<ArrayRef> = enc_throughput.into_iter().map(flat).collect();
    out.push(Arc::new(UInt16Array::from(flags)));
    out.extend(enc_radiance.into_iter().map(flat));
    Ok(out)
}

/// The encoded throughput of a `throughput` column, one vector per channel, and each row's
/// `enc_chroma` (colour, null flag), learning colours.
fn encode_throughput(throughput: &ArrayRef, learner: &mut ChromaLearner) -> Result<([Vec<u32>; 3], Vec<u16>)> {
    let (tv, tn) = rgb_values(throughput, THROUGHPUT).map_err(Error::Encoding)?;
    let n = tv.len() / 3;
    let mut enc = [vec![0u32; n], vec![0u32; n], vec![0u32; n]];
    let mut slots = vec![0u16; n];
    for i in 0..n {
        if !valid(tn, i) {
            slots[i] = THROUGHPUT_NULL;
            continue;
        }
        let v = triple(tv, i);
        let s = learner.slot(v);
        let pred = if s == 0 { [0.0; 2] } else { by_colour(v[0], learner.chromas.refs[s as usize - 1]) };
        enc[0][i] = v[0].to_bits();
        enc[1][i] = residual(v[1], pred[0]);
        enc[2][i] = residual(v[2], pred[1]);
        slots[i] = s;
    }
    Ok((enc, slots))
}

/// The three flat `UInt32` columns `names` of a batch.
fn u32_channels<'a>(batch: &'a RecordBatch, names: [&str; 3], path: &Path) -> Result<[&'a [u32]; 3]> {
    let [r, g, b] = names;
    let values = |name: &str| Ok(typed_column::<UInt32Type>(batch, name, path)?.values().as_ref());
    Ok([values(r)?, values(g)?, values(b)?])
}

/// The `enc_chroma` column of a batch.
fn chroma_column<'a>(batch: &'a RecordBatch, path: &Path) -> Result<&'a [u16]> {
    Ok(typed_column::<UInt16Type>(batch, ENC_CHROMA, path)?.values())
}

/// The validity of rows whose `enc_chroma` lacks `flag` (None when every row is valid).
fn nulls_of(flags: &[u16], flag: u16) -> Option<NullBuffer> {
    flags.iter().any(|f| f & flag != 0).then(|| NullBuffer::from_iter(flags.iter().map(|f| f & flag == 0)))
}

/// A `float32[3]` column of `values` (three per row).
fn rgb_array(values: Vec<f32>, nulls: Option<NullBuffer>) -> ArrayRef {
    let item = Arc::new(Field::new("item", DataType::Float32, false));
    Arc::new(FixedSizeListArray::new(item, 3, Arc::new(Float32Array::from(values)), nulls))
}

/// The `throughput` column of a batch of a ray file at `path` that predicts it, from its
/// `enc_throughput_*` and `enc_chroma` columns and the segment's colours.
pub(crate) fn decode_throughput(batch: &RecordBatch, chromas: &Chromas, path: &Path) -> Result<ArrayRef> {
    let [er, eg, eb] = u32_channels(batch, ENC_THROUGHPUT, path)?;
    let flags = chroma_column(batch, path)?;
    let n = flags.len();
    let (er, eg, eb) = (&er[..n], &eg[..n], &eb[..n]);
    let mut out = Vec::with_capacity(3 * n);
    for i in 0..n {
        let s = flags[i] & COLOUR;
        let r = f32::from_bits(er[i]);
        let pred = match s {
            0 => [0.0; 2],
            s => by_colour(
                r,
                *chromas.refs.get(s as usize - 1).ok_or_else(|| Error::Corrupt {
                    path: path.to_path_buf(),
                    what: "ray file".into(),
                    message: format!("row {i} of the batch: colour {s} of {} the file saves", chromas.len()),
                })?,
            ),
        };
        out.extend([r, apply(eg[i], pred[0]), apply(eb[i], pred[1])]);
    }
    Ok(rgb_array(out, nulls_of(flags, THROUGHPUT_NULL)))
}

/// The values of a `float32[3]` column, and its validity.
fn rgb_values<'a>(a: &'a ArrayRef, what: &str) -> std::result::Result<(&'a [f32], Option<&'a NullBuffer>), String> {
    let list = a
        .as_fixed_size_list_opt()
        .filter(|l| l.value_length() == 3)
        .ok_or_else(|| format!("{what} is not a list of 3"))?;
    let v = list.values().as_primitive_opt::<Float32Type>().ok_or_else(|| format!("{what} is not float32[3]"))?;
    // (Null lists read back with null components; only the lists' validity counts.)
    if v.len() != 3 * list.len() {
        return Err(format!("{what} has {} components for {} rows", v.len(), list.len()));
    }
    Ok((&v.values()[..], list.nulls()))
}

#[inline]
fn valid(n: Option<&NullBuffer>, i: usize) -> bool {
    n.is_none_or(|n| n.is_valid(i))
}

#[inline]
fn triple(v: &[f32], i: usize) -> [f32; 3] {
    [v[3 * i], v[3 * i + 1], v[3 * i + 2]]
}

/// Walks the trees of rows `0..n` (each tree's rows contiguous, `tree[i]` its id), asking
/// `resolve(row, prediction)` for each row's radiance in the order the decoder can know it: the
/// shadow rays first, then the root, then the rest.
#[allow(clippy::needless_range_loop)] // rows index four columns at once
fn walk(
    tree: &[u64],
    kind: &[u8],
    thr: (&[f32], Option<&NullBuffer>),
    mut resolve: impl FnMut(usize, [f32; 3]) -> [f32; 3],
    out: &mut [f32],
) {
    let n = tree.len();
    let shadow = |i: usize| kind[i] == Kind::SHADOW.0;
    let (tv, tn) = thr;
    let mut s = 0;
    while s < n {
        let mut e = s + 1;
        while e < n && tree[e] == tree[s] {
            e += 1;
        }
        // Shadow rays: stored as they are; their sum predicts the root.
        let mut acc = [0.0f32; 3];
        for i in s + 1..e {
            if shadow(i) {
                let v = resolve(i, [0.0; 3]);
                out[3 * i..3 * i + 3].copy_from_slice(&v);
                if valid(tn, i) {
                    let t = triple(tv, i);
                    for c in 0..3 {
                        acc[c] += t[c] * v[c];
                    }
                }
            }
        }
        let l = resolve(s, acc);
        out[3 * s..3 * s + 3].copy_from_slice(&l);
        let mut acc = [0.0f32; 3];
        for i in s + 1..e {
            if shadow(i) {
                if valid(tn, i) {
                    let (t, v) = (triple(tv, i), triple(out, i));
                    for c in 0..3 {
                        acc[c] += t[c] * v[c];
                    }
                }
                continue;
            }
            let mut pred = [0.0f32; 3];
            if valid(tn, i) {
                let b = triple(tv, i);
                for c in 0..3 {
                    if b[c] > 0.0 {
                        pred[c] = (l[c] - acc[c]) / b[c];
                    }
                }
            }
            let v = resolve(i, pred);
            out[3 * i..3 * i + 3].copy_from_slice(&v);
        }
        s = e;
    }
}

/// The encoded radiance of whole trees, one vector per channel, and each row's `enc_chroma`
/// flags: radiance null, or stored against 0 instead of its prediction (fewer significant bits
/// in the residuals).
fn encode_radiance(
    tree: &[u64],
    kind: &[u8],
    throughput: &ArrayRef,
    radiance: &ArrayRef,
) -> Result<([Vec<u32>; 3], Vec<u16>)> {
    let thr = rgb_values(throughput, THROUGHPUT).map_err(Error::Encoding)?;
    let (rv, rn) = rgb_values(radiance, RADIANCE).map_err(Error::Encoding)?;
    let n = tree.len();
    if kind.len() != n || thr.0.len() != 3 * n || rv.len() != 3 * n {
        return Err(Error::Encoding(format!("path payload of {n} rows: columns of other lengths")));
    }
    let mut res = [vec![0u32; n], vec![0u32; n], vec![0u32; n]];
    let mut flags = vec![0u16; n];
    let mut out = vec![0.0f32; 3 * n];
    let bits = |r: [u32; 3]| r.iter().map(|r| 32 - r.leading_zeros()).sum::<u32>();
    walk(
        tree,
        kind,
        thr,
        |i, pred| {
            if !valid(rn, i) {
                flags[i] = RADIANCE_NULL;
                return [0.0; 3];
            }
            let v = triple(rv, i);
            let mut r = [0, 1, 2].map(|c| residual(v[c], pred[c]));
            if pred != [0.0; 3] {
                let z = [0, 1, 2].map(|c| residual(v[c], 0.0));
                if bits(z) < bits(r) {
                    (r, flags[i]) = (z, RADIANCE_RAW);
                }
            }
            for (res, r) in res.iter_mut().zip(r) {
                res[i] = r;
            }
            v
        },
        &mut out,
    );
    Ok((res, flags))
}

/// The `radiance` column of a batch of whole trees of a ray file at `path`, from its
/// `enc_radiance_*`, `enc_chroma`, `tree_id` and `kind_code` columns and its decoded `throughput`.
pub(crate) fn decode_radiance(batch: &RecordBatch, throughput: &ArrayRef, path: &Path) -> Result<ArrayRef> {
    let corrupt = |message: String| Error::Corrupt { path: path.to_path_buf(), what: "ray file".into(), message };
    let tree = typed_column::<UInt64Type>(batch, crate::schema::col::TREE_ID, path)?;
    let kind = typed_column::<UInt8Type>(batch, KIND_CODE, path)?;
    let thr = rgb_values(throughput, THROUGHPUT).map_err(corrupt)?;
    let e = u32_channels(batch, ENC_RADIANCE, path)?;
    let flags = chroma_column(batch, path)?;
    let n = batch.num_rows();
    let mut out = vec![0.0f32; 3 * n];
    walk(
        &tree.values()[..n],
        &kind.values()[..n],
        thr,
        |i, pred| {
            let f = flags[i];
            if f & RADIANCE_NULL != 0 {
                return [0.0; 3];
            }
            let pred = if f & RADIANCE_RAW != 0 { [0.0; 3] } else { pred };
            [0, 1, 2].map(|c| apply(e[c][i], pred[c]))
        },
        &mut out,
    );
    Ok(rgb_array(out, nulls_of(flags, RADIANCE_NULL)))
}

/// Re-cuts `batches` of a ray file (in file order, from a tree's first row) so that each ends at
/// a tree's end, as [`decode_radiance`] needs; `tree` is the position of `tree_id` in them. Each batch's
/// last tree is held back and joined to its rows at the head of the next batch (only those rows
/// are copied; the rest of the batch passes on as slices). A tree longer than a batch waits for
/// the batches that complete it.
pub(crate) fn tree_aligned<I>(
    batches: I,
    tree: usize,
    path: &Path,
) -> impl Iterator<Item = Result<RecordBatch>> + use<I>
where
    I: Iterator<Item = Result<RecordBatch>>,
{
    let path = path.to_path_buf();
    let mut batches = batches.fuse();
    // The batch's last tree, held back, and its id.
    let mut carry: Option<(u64, RecordBatch)> = None;
    let mut ready: std::collections::VecDeque<RecordBatch> = Default::default();
    let concat = |a: &RecordBatch, b: &RecordBatch, path: &Path| {
        arrow::compute::concat_batches(&a.schema(), [a, b]).map_err(crate::error::arrow_err(path.display().to_string()))
    };
    std::iter::from_fn(move || {
        loop {
            if let Some(b) = ready.pop_front() {
                return Some(Ok(b));
            }
            let next = match batches.next() {
                None => return carry.take().map(|(_, c)| Ok(c)),
                Some(Err(e)) => return Some(Err(e)),
                Some(Ok(b)) if b.num_rows() == 0 => continue,
                Some(Ok(b)) => b,
            };
            let Some(ids) = next.column(tree).as_primitive_opt::<UInt64Type>() else {
                return Some(Err(Error::Corrupt {
                    path: path.clone(),
                    what: "ray file".into(),
                    message: "column tree_id is not UInt64".into(),
                }));
            };
            let ids = ids.values();
            let n = ids.len();
            let mut start = 0;
            if let Some((held, c)) = carry.take() {
                // The held-back tree's rows that open this batch, joined to it.
                let end = ids.iter().position(|&id| id != held).unwrap_or(n);
                if end == n {
                    match concat(&c, &next, &path) {
                        Ok(b) => carry = Some((held, b)),
                        Err(e) => return Some(Err(e)),
                    }
                    continue;
                }
                ready.push_back(if end == 0 {
                    c
                } else {
                    match concat(&c, &next.slice(0, end), &path) {
                        Ok(b) => b,
                        Err(e) => return Some(Err(e)),
                    }
                });
                start = end;
            }
            // Whole trees up to the start of the batch's last tree, which is held back.
            let last = ids[n - 1];
            let cut = ids[start..].iter().rposition(|&id| id != last).map_or(start, |p| start + p + 1);
            if cut > start {
                ready.push_back(next.slice(start, cut - start));
            }
            carry = Some((last, next.slice(cut, n - cut)));
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rgb(v: &[[f32; 3]], nulls: Option<Vec<bool>>) -> ArrayRef {
        let item = Arc::new(Field::new("item", DataType::Float32, false));
        let values = Float32Array::from(v.iter().flatten().copied().collect::<Vec<f32>>());
        Arc::new(FixedSizeListArray::new(item, 3, Arc::new(values), nulls.map(NullBuffer::from)))
    }

    /// The path payload encoded into a ray-file batch (with `tree_id` and `kind_code`).
    fn encoded(tree: &[u64], kind: &[u8], thr: &ArrayRef, rad: &ArrayRef, learner: &mut ChromaLearner) -> RecordBatch {
        let cols = encode_path(tree, kind, thr, rad, learner).unwrap();
        let mut fields =
            vec![Field::new("tree_id", DataType::UInt64, false), Field::new(KIND_CODE, DataType::UInt8, false)];
        let mut arrays: Vec<ArrayRef> = vec![
            Arc::new(arrow::array::UInt64Array::from(tree.to_vec())),
            Arc::new(arrow::array::UInt8Array::from(kind.to_vec())),
        ];
        for (name, a) in encoded_columns().zip(cols) {
            fields.push(Field::new(name, a.data_type().clone(), false));
            arrays.push(a);
        }
        RecordBatch::try_new(Arc::new(Schema::new(fields)), arrays).unwrap()
    }

    /// The decoded (throughput, radiance) of such a batch.
    fn decoded(b: &RecordBatch, learner: &ChromaLearner) -> (ArrayRef, ArrayRef) {
        let thr = decode_throughput(b, learner.chromas(), Path::new("f")).unwrap();
        let rad = decode_radiance(b, &thr, Path::new("f")).unwrap();
        (thr, rad)
    }

    /// Every residual of `enc_radiance_*`, row by row.
    fn radiance_residuals(b: &RecordBatch) -> Vec<u32> {
        let e = u32_channels(b, ENC_RADIANCE, Path::new("f")).unwrap();
        (0..b.num_rows()).flat_map(|i| [e[0][i], e[1][i], e[2][i]]).collect()
    }

    fn bits(a: &ArrayRef) -> Vec<Option<Vec<u32>>> {
        let l = a.as_fixed_size_list();
        (0..l.len())
            .map(|i| {
                l.is_valid(i)
                    .then(|| l.value(i).as_primitive::<Float32Type>().values().iter().map(|f| f.to_bits()).collect())
            })
            .collect()
    }

    /// A path as the path tracer records it: camera ray, then per bounce a shadow ray and the
    /// next bounce; radiance as `(l - before) / beta`.
    fn path(seed: u32) -> (Vec<u8>, Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let mut x = seed.wrapping_mul(2_654_435_761).max(1);
        let mut rnd = move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x >> 8) as f32 / (1u32 << 24) as f32
        };
        let (mut kind, mut thr, mut chain) = (vec![0u8], vec![[1.0f32; 3]], vec![(0usize, [0.0f32; 3])]);
        let mut beta = [1.0f32; 3];
        let mut l = [0.0f32; 3];
        for _ in 0..4 {
            let albedo = [0.7, 0.5 * rnd() + 0.1, 0.3];
            let s = rnd() * 3.0;
            let w = [0, 1, 2].map(|c| beta[c] * (albedo[c] / std::f32::consts::PI) * s);
            let e = if rnd() < 0.7 { [17.0, 12.0, 4.0] } else { [0.0; 3] };
            for c in 0..3 {
                l[c] += w[c] * e[c];
            }
            kind.push(1);
            thr.push(w);
            chain.push((usize::MAX, e));
            beta = [0, 1, 2].map(|c| beta[c] * albedo[c]);
            kind.push(2);
            thr.push(beta);
            chain.push((chain.len(), l));
        }
        let rad = chain
            .iter()
            .zip(&thr)
            .map(|(&(i, v), b)| if i == usize::MAX { v } else { [0, 1, 2].map(|c| (l[c] - v[c]) / b[c]) })
            .collect();
        (kind, thr, rad)
    }

    #[test]
    fn path_tracer_radiance_is_predicted_exactly_and_round_trips() {
        let (mut tree, mut kind, mut thr, mut rad) = (vec![], vec![], vec![], vec![]);
        for t in 0..20u64 {
            let (k, th, r) = path(t as u32 + 1);
            tree.extend(std::iter::repeat_n(t, k.len()));
            kind.extend(k);
            thr.extend(th);
            rad.extend(r);
        }
        let (thr, rad) = (rgb(&thr, None), rgb(&rad, None));
        let mut learner = ChromaLearner::default();
        let b = encoded(&tree, &kind, &thr, &rad, &mut learner);
        let res = radiance_residuals(&b);
        assert!(res.iter().enumerate().all(|(i, &r)| kind[i / 3] == 1 || r == 0), "non-shadow rays predicted exactly");
        let flags = chroma_column(&b, Path::new("f")).unwrap();
        assert!(flags.iter().all(|f| f & (RADIANCE_RAW | RADIANCE_NULL | THROUGHPUT_NULL) == 0));
        let (back_thr, back) = decoded(&b, &learner);
        assert_eq!(back.as_ref(), rad.as_ref());
        assert_eq!(back_thr.as_ref(), thr.as_ref());
        // Another renderer's convention (radiance 0 on most rays): stored against 0, still exact.
        let other: Vec<[f32; 3]> =
            (0..tree.len()).map(|i| if i % 5 == 0 { [0.5, 0.25, 0.125] } else { [0.0; 3] }).collect();
        let other = rgb(&other, None);
        let b = encoded(&tree, &kind, &thr, &other, &mut learner);
        assert!(chroma_column(&b, Path::new("f")).unwrap().iter().any(|f| f & RADIANCE_RAW != 0));
        let res = radiance_residuals(&b);
        assert!(res.iter().filter(|&&r| r == 0).count() > res.len() * 3 / 4, "zeros stay zeros");
        assert_eq!(decoded(&b, &learner).1.as_ref(), other.as_ref());
    }

    #[test]
    fn any_values_round_trip_bit_for_bit() {
        let specials = [0.0f32, -0.0, 1.0, f32::NAN, -f32::INFINITY, f32::from_bits(1), f32::MAX, -3.5, 1e-30];
        let n = 40;
        let tree: Vec<u64> = (0..n).map(|i| (i / 7) as u64).collect();
        let kind: Vec<u8> = (0..n).map(|i| (i % 3) as u8).collect();
        let v = |k: usize| [0, 1, 2].map(|c| specials[(k * 5 + c * 3) % specials.len()]);
        let thr: Vec<[f32; 3]> = (0..n).map(v).collect();
        let rad: Vec<[f32; 3]> = (0..n).map(|i| v(i + 2)).collect();
        let nulls = |m: usize| Some((0..n).map(|i| i % m != 0).collect());
        let (thr, rad) = (rgb(&thr, nulls(5)), rgb(&rad, nulls(4)));
        let mut learner = ChromaLearner::default();
        let b = encoded(&tree, &kind, &thr, &rad, &mut learner);
        let (back_thr, back) = decoded(&b, &learner);
        assert_eq!(bits(&back), bits(&rad));
        assert_eq!(bits(&back_thr), bits(&thr));
    }

    #[test]
    fn throughput_round_trips_by_colour_and_bad_colour_tables_are_errors() {
        let n = 300;
        let colours = [[0.73f32, 0.42, 0.12], [0.2, 0.6, 0.9]];
        let mut v: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                let s = 0.001 + i as f32 * 0.37;
                colours[i % 2].map(|c| c * s)
            })
            .collect();
        v[7] = [0.0, 1.0, 2.0];
        v[8] = [f32::NAN, 1.0, f32::INFINITY];
        v[9] = [-0.0, f32::from_bits(1), f32::MAX];
        let thr = rgb(&v, Some((0..n).map(|i| i % 11 != 3).collect()));
        let rad = rgb(&vec![[0.0; 3]; n], None);
        let tree: Vec<u64> = (0..n as u64).collect();
        let mut learner = ChromaLearner::default();
        let b = encoded(&tree, &vec![0; n], &thr, &rad, &mut learner);
        let chromas = Chromas::from_metadata(&learner.chromas().to_metadata()).unwrap();
        assert_eq!(&chromas, learner.chromas());
        assert!(chromas.len() <= 6, "{} colours for two (plus rounding at the keys' edges)", chromas.len());
        let back = decode_throughput(&b, &chromas, Path::new("f")).unwrap();
        assert_eq!(bits(&back), bits(&thr));
        // A colour the file does not save, and tables that are not triples of usable floats.
        let err = decode_throughput(&b, &Chromas::default(), Path::new("seg.rays.parquet")).unwrap_err().to_string();
        assert!(err.contains("seg.rays.parquet") && err.contains("colour 1 of 0"), "{err}");
        assert!(Chromas::from_metadata("not base64!").is_err());
        let bad = Chromas { refs: vec![[0.0, 1.0, 1.0]] }.to_metadata();
        assert!(Chromas::from_metadata(&bad).unwrap_err().contains("colour 1"));
    }

    #[test]
    fn batches_are_recut_at_tree_ends() {
        let ids: Vec<u64> = vec![0, 0, 1, 1, 1, 2, 3, 3, 3, 3, 3, 4];
        let schema = Schema::new(vec![Field::new("tree_id", DataType::UInt64, false)]);
        let b = RecordBatch::try_new(Arc::new(schema), vec![Arc::new(arrow::array::UInt64Array::from(ids))]).unwrap();
        let parts = [(0, 3), (3, 4), (7, 0), (7, 1), (8, 4)].map(|(s, n)| Ok(b.slice(s, n)));
        let out: Vec<Vec<u64>> = tree_aligned(parts.into_iter(), 0, Path::new("f"))
            .map(|r| r.unwrap().column(0).as_primitive::<UInt64Type>().values().to_vec())
            .collect();
        // Every batch ends at a tree's end, and every row comes once, in order.
        assert_eq!(out, vec![vec![0, 0], vec![1, 1, 1], vec![2], vec![3, 3, 3, 3, 3], vec![4]]);
        let ends = [(0, 2), (2, 3), (5, 7)].map(|(s, n)| Ok(b.slice(s, n)));
        let out: Vec<Vec<u64>> = tree_aligned(ends.into_iter(), 0, Path::new("f"))
            .map(|r| r.unwrap().column(0).as_primitive::<UInt64Type>().values().to_vec())
            .collect();
        assert_eq!(out, vec![vec![0, 0], vec![1, 1, 1], vec![2, 3, 3, 3, 3, 3], vec![4]]);
    }
}
