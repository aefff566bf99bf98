//! The path payload's radiance predicted from the path's own arithmetic (format version 4,
//! encoded layouts).
//!
//! A path tracer that records each ray's `throughput` (the path weight it was spawned with) and
//! `radiance` (the light it carries back to its origin) writes numbers tied to each other: the
//! tree's root carries the whole sample's estimate `L`, the sum of what its shadow rays brought
//! (`throughput * radiance` of each, added in recording order), and every other ray carries what
//! was gathered after it, `(L - gathered before it) / throughput`. Stored as they are, those
//! radiance triples are nearly random floats (5.5 of the 23.6 bytes a ray of a path-traced
//! Cornell box took); predicted from the same arithmetic, in `f32` and in the same order, they
//! come out exactly and cost almost nothing.
//!
//! When the payload declares `throughput` and `radiance` both as `float32[3]`, encoded ray files
//! (from format version 4) store `radiance` as `enc_radiance` (`uint32[3]`): each component's
//! zig-zag ULP distance to its prediction, per tree of rows `s..e`:
//!
//! - shadow rays (kind code 1) other than the root: predicted 0 (the bits are stored; they are
//!   the emitter's radiance or zero);
//! - the root (row `s`): the sum over those shadow rays, in row order, of
//!   `throughput * radiance` (both present), starting from 0;
//! - every other ray: per component, `(L - acc) / b` where `b > 0`, else 0, with `L` the root's
//!   radiance, `acc` that sum over the shadow rays before it, and `b` its throughput; 0 when its
//!   throughput is null.
//!
//! Any other renderer's values round-trip too (every bit pattern does); they only cost more.
//! The prediction reads a whole tree before its root, so decoding needs batches that end at tree
//! ends ([`tree_aligned`]); a tree still decodes on its own.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, FixedSizeListArray, Float32Array, RecordBatch, UInt32Array};
use arrow::buffer::NullBuffer;
use arrow::datatypes::{DataType, Field, Float32Type, Schema, UInt8Type, UInt32Type, UInt64Type};

use crate::codec::{apply, residual};
use crate::schema::Kind;
use crate::{Error, Result};

/// The payload column of each ray's path weight.
pub const THROUGHPUT: &str = "throughput";
/// The payload column of the light each ray carries back.
pub const RADIANCE: &str = "radiance";
/// The ray-file column `radiance` is stored in (format version 4, encoded layouts).
pub const ENC_RADIANCE: &str = "enc_radiance";

/// Whether `f` is a `float32[3]` column.
fn is_rgb(f: &Field) -> bool {
    matches!(f.data_type(), DataType::FixedSizeList(item, 3) if item.data_type() == &DataType::Float32)
}

/// Whether the ray table `plain` holds the path payload whose radiance is predicted.
pub(crate) fn predicts_radiance(plain: &Schema) -> bool {
    let rgb = |name: &str| plain.field_with_name(name).is_ok_and(is_rgb);
    rgb(THROUGHPUT) && rgb(RADIANCE)
}

/// The `enc_radiance` field standing for the `radiance` field `f`.
pub(crate) fn encoded_field(f: &Field) -> Field {
    let item = Arc::new(Field::new("item", DataType::UInt32, false));
    Field::new(ENC_RADIANCE, DataType::FixedSizeList(item, 3), f.is_nullable()).with_metadata(f.metadata().clone())
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

/// The values of a `uint32[3]` column.
fn u32x3_values<'a>(a: &'a ArrayRef, what: &str) -> std::result::Result<(&'a [u32], Option<&'a NullBuffer>), String> {
    let list = a
        .as_fixed_size_list_opt()
        .filter(|l| l.value_length() == 3)
        .ok_or_else(|| format!("{what} is not a list of 3"))?;
    let v = list.values().as_primitive_opt::<UInt32Type>().ok_or_else(|| format!("{what} is not uint32[3]"))?;
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
    out: &mut [[f32; 3]],
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
                out[i] = v;
                if valid(tn, i) {
                    let t = triple(tv, i);
                    for c in 0..3 {
                        acc[c] += t[c] * v[c];
                    }
                }
            }
        }
        let l = resolve(s, acc);
        out[s] = l;
        let mut acc = [0.0f32; 3];
        for i in s + 1..e {
            if shadow(i) {
                if valid(tn, i) {
                    let (t, v) = (triple(tv, i), out[i]);
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
            out[i] = resolve(i, pred);
        }
        s = e;
    }
}

/// Only rows whose radiance is valid count in the sums: a null radiance reads as zero.
fn masked(v: [f32; 3], ok: bool) -> [f32; 3] {
    if ok { v } else { [0.0; 3] }
}

/// The `enc_radiance` column of whole trees: `tree`, `kind` codes, `throughput` and `radiance`
/// as the ray table holds them.
pub(crate) fn encode(tree: &[u64], kind: &[u8], throughput: &ArrayRef, radiance: &ArrayRef) -> Result<ArrayRef> {
    let thr = rgb_values(throughput, THROUGHPUT).map_err(Error::Encoding)?;
    let (rv, rn) = rgb_values(radiance, RADIANCE).map_err(Error::Encoding)?;
    let n = tree.len();
    if kind.len() != n || thr.0.len() != 3 * n || rv.len() != 3 * n {
        return Err(Error::Encoding(format!("path payload of {n} rows: columns of other lengths")));
    }
    let mut res = vec![0u32; 3 * n];
    let mut out = vec![[0.0f32; 3]; n];
    walk(
        tree,
        kind,
        thr,
        |i, pred| {
            let ok = valid(rn, i);
            let v = masked(triple(rv, i), ok);
            if ok {
                for c in 0..3 {
                    res[3 * i + c] = residual(v[c], pred[c]);
                }
            }
            v
        },
        &mut out,
    );
    Ok(u32x3(res, rn.cloned()))
}

/// A `uint32[3]` column of `values` (three per row).
fn u32x3(values: Vec<u32>, nulls: Option<NullBuffer>) -> ArrayRef {
    let item = Arc::new(Field::new("item", DataType::UInt32, false));
    Arc::new(FixedSizeListArray::new(item, 3, Arc::new(UInt32Array::from(values)), nulls))
}

/// The `radiance` column of a batch of whole trees of a ray file at `path`, from its
/// `enc_radiance`, `tree_id`, `kind_code` and `throughput` (decoded) columns.
pub(crate) fn decode(batch: &RecordBatch, throughput: &ArrayRef, path: &Path) -> Result<ArrayRef> {
    let corrupt = |message: String| Error::Corrupt { path: path.to_path_buf(), what: "ray file".into(), message };
    let col = |name: &str| crate::codec::file_column(batch, name, path);
    let tree = col(crate::schema::col::TREE_ID)?
        .as_primitive_opt::<UInt64Type>()
        .ok_or_else(|| corrupt("column tree_id is not UInt64".into()))?;
    let kind = col(crate::codec::KIND_CODE)?
        .as_primitive_opt::<UInt8Type>()
        .ok_or_else(|| corrupt(format!("column {} is not UInt8", crate::codec::KIND_CODE)))?;
    let thr = rgb_values(throughput, THROUGHPUT).map_err(corrupt)?;
    let (ev, en) = u32x3_values(col(ENC_RADIANCE)?, ENC_RADIANCE).map_err(corrupt)?;
    let n = batch.num_rows();
    let mut out = vec![[0.0f32; 3]; n];
    walk(
        tree.values(),
        kind.values(),
        thr,
        |i, pred| {
            let v = [0, 1, 2].map(|c| apply(ev[3 * i + c], pred[c]));
            masked(v, valid(en, i))
        },
        &mut out,
    );
    let values = Float32Array::from(out.into_iter().flatten().collect::<Vec<f32>>());
    let item = Arc::new(Field::new("item", DataType::Float32, false));
    Ok(Arc::new(FixedSizeListArray::new(item, 3, Arc::new(values), en.cloned())))
}

/// Re-cuts `batches` of a ray file (in file order, from a tree's first row) so that each ends at
/// a tree's end, as [`decode`] needs; `tree` is the position of `tree_id` in them. A tree longer
/// than a batch waits for the batches that complete it.
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
    let mut carry: Option<RecordBatch> = None;
    std::iter::from_fn(move || {
        loop {
            let Some(next) = batches.next() else {
                return carry.take().map(Ok);
            };
            let next = match next {
                Ok(b) => b,
                Err(e) => return Some(Err(e)),
            };
            let b = match carry.take() {
                Some(c) => match arrow::compute::concat_batches(&c.schema(), [&c, &next]) {
                    Ok(b) => b,
                    Err(e) => return Some(Err(crate::error::arrow_err(path.display().to_string())(e))),
                },
                None => next,
            };
            let Some(ids) = b.column(tree).as_primitive_opt::<UInt64Type>() else {
                return Some(Err(Error::Corrupt {
                    path: path.clone(),
                    what: "ray file".into(),
                    message: "column tree_id is not UInt64".into(),
                }));
            };
            let ids = ids.values();
            // The last tree of the batch may go on in the next one: held back.
            let last = ids.last().copied();
            let cut = ids.iter().rposition(|&id| Some(id) != last).map_or(0, |p| p + 1);
            if cut > 0 {
                carry = (cut < b.num_rows()).then(|| b.slice(cut, b.num_rows() - cut));
                return Some(Ok(b.slice(0, cut)));
            }
            carry = Some(b);
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

    fn batch(tree: &[u64], kind: &[u8], enc: ArrayRef) -> RecordBatch {
        let schema = Schema::new(vec![
            Field::new("tree_id", DataType::UInt64, false),
            Field::new(crate::codec::KIND_CODE, DataType::UInt8, false),
            Field::new(ENC_RADIANCE, enc.data_type().clone(), true),
        ]);
        RecordBatch::try_new(
            Arc::new(schema),
            vec![
                Arc::new(arrow::array::UInt64Array::from(tree.to_vec())),
                Arc::new(arrow::array::UInt8Array::from(kind.to_vec())),
                enc,
            ],
        )
        .unwrap()
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
        let enc = encode(&tree, &kind, &thr, &rad).unwrap();
        let (res, _) = u32x3_values(&enc, "enc").unwrap();
        assert!(res.iter().enumerate().all(|(i, &r)| kind[i / 3] == 1 || r == 0), "non-shadow rays predicted exactly");
        let back = decode(&batch(&tree, &kind, enc), &thr, Path::new("f")).unwrap();
        assert_eq!(back.as_ref(), rad.as_ref());
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
        let enc = encode(&tree, &kind, &thr, &rad).unwrap();
        let back = decode(&batch(&tree, &kind, enc), &thr, Path::new("f")).unwrap();
        let bits = |a: &ArrayRef| {
            let l = a.as_fixed_size_list();
            (0..l.len())
                .map(|i| {
                    l.is_valid(i).then(|| {
                        l.value(i)
                            .as_primitive::<Float32Type>()
                            .values()
                            .iter()
                            .map(|f| f.to_bits())
                            .collect::<Vec<_>>()
                    })
                })
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&back), bits(&rad));
    }

    #[test]
    fn batches_are_recut_at_tree_ends() {
        let ids: Vec<u64> = vec![0, 0, 1, 1, 1, 2, 3, 3, 3, 3, 3, 4];
        let b = batch(&ids, &vec![0; ids.len()], u32x3(vec![0; 3 * ids.len()], None));
        let parts = [(0, 3), (3, 4), (7, 1), (8, 4)].map(|(s, n)| Ok(b.slice(s, n)));
        let out: Vec<Vec<u64>> = tree_aligned(parts.into_iter(), 0, Path::new("f"))
            .map(|r| r.unwrap().column(0).as_primitive::<UInt64Type>().values().to_vec())
            .collect();
        assert_eq!(out, vec![vec![0, 0], vec![1, 1, 1, 2], vec![3, 3, 3, 3, 3], vec![4]]);
    }
}
