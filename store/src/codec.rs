//! Compact encodings of the origin and direction columns (format version 2).
//!
//! Generic codecs leave float columns near 3.3–3.6 bytes per value. A ray tree has structure
//! they cannot see, and the encodings here use it:
//!
//! - **Origins** are predicted from rays decoded before them in the same tree: a ray shares the
//!   origin of its previous sibling (a shadow ray and the bounce leaving the same hit point), or
//!   starts where its parent hit (`origin + t * dir` of the parent, in `f32`). What is stored is
//!   the distance to the prediction in units in the last place (ULPs), zig-zag coded: a few bits
//!   where the renderer offsets a secondary ray off the surface, zero for shared origins.
//! - **Directions** are nearly unit vectors: the largest component is predicted from the other two
//!   as `±sqrt(1 - b² - c²)` (in `f64`) and stored as its ULP distance to that prediction; the two
//!   others are stored as their bits. Non-finite or zero directions are stored raw.
//! - **Hit distances** (format version 3) are predicted from the plane of the hit primitive,
//!   learned by the writer per segment (see [`crate::planes`]): the ULP distance to the
//!   prediction is stored instead of the `t` bits.
//! - **Lossy** `octN`: directions quantized to N bits per octahedral coordinate (unit length after
//!   decoding). Predictions then use decoded values, so origins stay lossless.
//!
//! Every encoding is a bijection on bit patterns for lossless modes: NaN payloads, infinities,
//! negative zero and non-unit directions round-trip exactly (they only cost more bytes).
//!
//! Encoding and decoding only look at earlier rays of the same tree, so any run of whole trees
//! decodes on its own: one tree fetched by id reads only its own rows.

use std::path::Path;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, Float32Array, RecordBatch, UInt8Array, UInt32Array};
use arrow::buffer::NullBuffer;
use arrow::datatypes::{DataType, Field, Schema, SchemaRef, UInt8Type, UInt32Type, UInt64Type};

use crate::columns::{NONE_U32, RayColumns, kind_array};
use crate::planes::{PlaneLearner, Planes};
use crate::schema::{KindTable, file_column};
use crate::stats::Stats;
use crate::ulp::{apply, residual};
use crate::{Error, Result};

/// How a dataset stores the origin and direction columns of its ray files.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Encoding {
    /// Plain `Float32` columns (format version 1 layout): what external tools read directly.
    Plain,
    /// Predicted from the tree structure, stored as residuals; bit-exact.
    #[default]
    Lossless,
    /// Directions quantized to this many bits per octahedral coordinate (8..=16); the rest lossless.
    Oct(u8),
}

impl Encoding {
    /// The name used on the command line and in the manifest.
    pub fn name(&self) -> String {
        match self {
            Encoding::Plain => "plain".into(),
            Encoding::Lossless => "lossless".into(),
            Encoding::Oct(bits) => format!("oct{bits}"),
        }
    }

    /// Parses `plain`, `lossless` or `octN` (N from 8 to 16).
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "plain" => return Ok(Encoding::Plain),
            "lossless" => return Ok(Encoding::Lossless),
            _ => {}
        }
        if let Some(bits) = s.strip_prefix("oct").and_then(|b| b.parse::<u8>().ok())
            && (8..=16).contains(&bits)
        {
            return Ok(Encoding::Oct(bits));
        }
        Err(Error::Encoding(format!("unknown encoding {s:?}: expected plain, lossless or octN with N from 8 to 16")))
    }

    pub fn is_lossy(&self) -> bool {
        matches!(self, Encoding::Oct(_))
    }
}

impl serde::Serialize for Encoding {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.serialize_str(&self.name())
    }
}

impl<'de> serde::Deserialize<'de> for Encoding {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        Encoding::parse(&s).map_err(serde::de::Error::custom)
    }
}

/// Names of the encoded core columns, in file order, replacing `origin_*` and `dir_*`.
pub const ENCODED_COLUMNS: [&str; 7] =
    ["enc_origin_x", "enc_origin_y", "enc_origin_z", "enc_dir_code", "enc_dir_u", "enc_dir_v", "enc_dir_r"];

pub use crate::schema::KIND_CODE;

/// The hit-distance column of encoded ray files from format version 3 on (`t` before).
pub const ENC_T: &str = "enc_t";

/// Bit of `enc_dir_code`: `enc_t` is the residual of `t` against the hit primitive's plane
/// (otherwise it holds the bits of `t`).
const T_PREDICTED: u8 = 1 << 6;

/// Residuals of `t` at least this large are stored as raw bits instead (a prediction that far
/// off is no prediction).
const T_RESIDUAL_LIMIT: u32 = 1 << 20;

/// Direction codes (low 3 bits of `enc_dir_code`): 0..=5 predicted axis (`axis + 3 * negative`),
/// raw bits, octahedral. Bits 3..=5 flag origin components stored raw instead of predicted.
const DIR_RAW: u8 = 6;
const DIR_OCT: u8 = 7;

/// The schema of the ray files for `plain` (the ray table schema) and encoded layouts, as
/// `format_version` writes them (`t` is encoded from version 3 on, the path payload's
/// `throughput` and `radiance` from version 4).
pub fn file_schema(plain: &SchemaRef, encoding: Encoding, format_version: u32) -> SchemaRef {
    if encoding == Encoding::Plain {
        return plain.clone();
    }
    let mut fields: Vec<Field> = Vec::with_capacity(plain.fields().len() + 1);
    let path_payload = format_version >= 4 && crate::path_payload::predicts_path_payload(plain);
    for f in plain.fields() {
        match f.name().as_str() {
            crate::path_payload::RADIANCE | crate::path_payload::THROUGHPUT if path_payload => {
                fields.extend(crate::path_payload::encoded_fields(f))
            }
            "origin_y" | "origin_z" | "dir_x" | "dir_y" | "dir_z" => {}
            // Kind codes as recorded (names in the manifest's `kinds`): writing a string
            // dictionary column costs a hash per row.
            "kind" => fields.push(Field::new(KIND_CODE, DataType::UInt8, false)),
            "t" if format_version >= 3 => fields.push(Field::new(ENC_T, DataType::UInt32, true)),
            // The encoded columns go where origin_x was.
            "origin_x" => {
                for name in ENCODED_COLUMNS {
                    let dt = if name == "enc_dir_code" { DataType::UInt8 } else { DataType::UInt32 };
                    fields.push(Field::new(name, dt, false));
                }
            }
            _ => fields.push(f.as_ref().clone()),
        }
    }
    Arc::new(Schema::new_with_metadata(fields, plain.metadata().clone()))
}

/// The predicted largest component of a unit vector from the two others.
#[inline]
fn unit_component(b: f32, c: f32, negative: bool) -> f32 {
    let (b, c) = (f64::from(b), f64::from(c));
    let p = (1.0 - b * b - c * c).max(0.0).sqrt() as f32;
    if negative { -p } else { p }
}

/// Octahedral encoding of a finite non-zero vector: (u, v) in [0, 2^bits - 1], the nearest of the
/// four surrounding lattice points by angle.
fn oct_encode(d: [f32; 3], bits: u8) -> Option<u32> {
    let v = [f64::from(d[0]), f64::from(d[1]), f64::from(d[2])];
    let [x, y] = crate::geom::oct_fold(v)?;
    let max = f64::from((1u32 << bits) - 1);
    let (fx, fy) = ((x * 0.5 + 0.5) * max, (y * 0.5 + 0.5) * max);
    let n = normalize(v);
    let mut best = (f64::NEG_INFINITY, 0u32);
    for qx in [fx.floor(), fx.ceil()] {
        for qy in [fy.floor(), fy.ceil()] {
            let (qx, qy) = (qx.clamp(0.0, max), qy.clamp(0.0, max));
            let code = ((qx as u32) << 16) | qy as u32;
            let dec = oct_decode64(code, bits);
            let dot = dec[0] * n[0] + dec[1] * n[1] + dec[2] * n[2];
            if dot > best.0 {
                best = (dot, code);
            }
        }
    }
    Some(best.1)
}

fn normalize(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / l, v[1] / l, v[2] / l]
}

fn oct_decode64(code: u32, bits: u8) -> [f64; 3] {
    let max = f64::from((1u32 << bits) - 1);
    let x = f64::from(code >> 16) / max * 2.0 - 1.0;
    let y = f64::from(code & 0xffff) / max * 2.0 - 1.0;
    crate::geom::oct_unfold([x, y])
}

fn oct_decode(code: u32, bits: u8) -> [f32; 3] {
    let d = oct_decode64(code, bits);
    [d[0] as f32, d[1] as f32, d[2] as f32]
}

/// One ray of the tree being coded, as the decoder will see it.
#[derive(Clone, Copy)]
struct Node {
    origin: [f32; 3],
    dir: [f32; 3],
    t: f32,
    hit: bool,
    /// Last child (index + 1), 0 when none yet.
    last_child: u32,
}

/// The rays of the tree being coded, as the decoder will see them.
#[derive(Default)]
struct TreeState {
    tree: u64,
    nodes: Vec<Node>,
    /// Last root (index + 1), 0 when none yet.
    last_root: u32,
}

impl TreeState {
    #[inline]
    fn len(&self) -> usize {
        self.nodes.len()
    }

    /// Checks `(tree, ray, parent)` continues the current tree or starts a new one.
    #[inline]
    fn advance(&mut self, tree: u64, ray: u32, parent: u32) -> std::result::Result<(), String> {
        if ray == 0 {
            self.tree = tree;
            self.nodes.clear();
            self.last_root = 0;
        } else if tree != self.tree || ray as usize != self.len() {
            return Err(format!(
                "tree {tree} ray {ray}: rays of a tree must be contiguous from ray 0 (expected ray {} of tree {})",
                self.len(),
                self.tree
            ));
        }
        if parent != NONE_U32 && parent >= ray {
            return Err(format!("tree {tree} ray {ray}: parent {parent} is not an earlier ray"));
        }
        Ok(())
    }

    #[inline]
    fn predict_origin(&self, parent: u32) -> [f32; 3] {
        let last = match self.nodes.get(parent as usize) {
            Some(p) => p.last_child,
            None => self.last_root,
        };
        if let Some(sib) = last.checked_sub(1).and_then(|s| self.nodes.get(s as usize)) {
            return sib.origin;
        }
        match self.nodes.get(parent as usize) {
            Some(p) if p.hit => {
                let (o, d, t) = (p.origin, p.dir, p.t);
                [o[0] + d[0] * t, o[1] + d[1] * t, o[2] + d[2] * t]
            }
            _ => [0.0; 3],
        }
    }

    #[inline]
    fn push(&mut self, parent: u32, origin: [f32; 3], dir: [f32; 3], t: Option<f32>) {
        let me = self.nodes.len() as u32 + 1;
        match self.nodes.get_mut(parent as usize) {
            Some(p) => p.last_child = me,
            None => self.last_root = me,
        }
        self.nodes.push(Node { origin, dir, t: t.unwrap_or(0.0), hit: t.is_some(), last_child: 0 });
    }
}

/// The encoded origin and direction columns of a run of whole trees.
#[derive(Default)]
pub(crate) struct EncodedCore {
    pub origin: [Vec<u32>; 3],
    pub code: Vec<u8>,
    pub dir: [Vec<u32>; 3],
    /// `enc_t` values (0 where the ray missed).
    pub t: Vec<u32>,
}

impl EncodedCore {
    /// The encoded columns in file order; `enc_t` gets `t_nulls`, the misses (the plain `t`
    /// column's null buffer, built once for both).
    pub fn into_arrays(self, t_nulls: Option<NullBuffer>) -> Vec<ArrayRef> {
        let [ox, oy, oz] = self.origin;
        let [u, v, r] = self.dir;
        vec![
            Arc::new(UInt32Array::from(ox)),
            Arc::new(UInt32Array::from(oy)),
            Arc::new(UInt32Array::from(oz)),
            Arc::new(UInt8Array::from(self.code)),
            Arc::new(UInt32Array::from(u)),
            Arc::new(UInt32Array::from(v)),
            Arc::new(UInt32Array::from(r)),
            Arc::new(UInt32Array::new(self.t.into(), t_nulls)),
        ]
    }
}

fn encode_dir(d: [f32; 3], encoding: Encoding) -> (u8, [u32; 3], [f32; 3]) {
    if let Encoding::Oct(bits) = encoding
        && let Some(code) = oct_encode(d, bits)
    {
        return (DIR_OCT, [code, 0, 0], oct_decode(code, bits));
    }
    if !(d[0].is_finite() && d[1].is_finite() && d[2].is_finite()) {
        return (DIR_RAW, [d[0].to_bits(), d[1].to_bits(), d[2].to_bits()], d);
    }
    let (ax, ay, az) = (d[0].abs(), d[1].abs(), d[2].abs());
    let axis = if ax >= ay && ax >= az {
        0
    } else if ay >= az {
        1
    } else {
        2
    };
    let (b, c) = (d[(axis + 1) % 3], d[(axis + 2) % 3]);
    let negative = d[axis].is_sign_negative();
    let pred = unit_component(b, c, negative);
    (axis as u8 + 3 * u8::from(negative), [b.to_bits(), c.to_bits(), residual(d[axis], pred)], d)
}

#[inline]
fn decode_dir(code: u8, w: [u32; 3], bits: u8) -> std::result::Result<[f32; 3], String> {
    if code < 6 {
        // One ray through the batch loop: one decoder of predicted directions.
        let (mut x, mut y, mut z) = ([0.0f32], [0.0f32], [0.0f32]);
        predicted_dirs(&[code], [&w[..1], &w[1..2], &w[2..]], [&mut x, &mut y, &mut z]);
        return Ok([x[0], y[0], z[0]]);
    }
    match code {
        DIR_RAW => Ok([f32::from_bits(w[0]), f32::from_bits(w[1]), f32::from_bits(w[2])]),
        DIR_OCT if bits > 0 => Ok(oct_decode(w[0], bits)),
        _ => Err(format!("direction code {code} is not valid for this encoding")),
    }
}

/// Decodes every ray of `codes` as a direction with a predicted axis (codes 0..=5: the two stored
/// components and the residual of the third against the magnitude [`unit_component`] predicts
/// for it) into `out`. Returns whether
/// some ray has another code (raw, octahedral, or unknown bits), which the caller decodes again.
///
/// One pass without branches or bounds checks, so the compiler vectorizes it: the axis is chosen
/// by selects, not by indexing.
fn predicted_dirs(codes: &[u8], e: [&[u32]; 3], out: [&mut [f32]; 3]) -> bool {
    let n = codes.len();
    let (e0, e1, e2) = (&e[0][..n], &e[1][..n], &e[2][..n]);
    let [dx, dy, dz] = out;
    let (dx, dy, dz) = (&mut dx[..n], &mut dy[..n], &mut dz[..n]);
    let mut other = 0u8;
    for i in 0..n {
        let c = codes[i];
        let code = c & 7;
        other |= (c & 0x80) | u8::from(code >= 6);
        let (b, cc) = (f32::from_bits(e0[i]), f32::from_bits(e1[i]));
        let (bd, cd) = (f64::from(b), f64::from(cc));
        let p = (1.0 - bd * bd - cd * cd).max(0.0).sqrt() as f32;
        let negative = code >= 3;
        let a = apply(e2[i], if negative { -p } else { p });
        let axis = if negative { code - 3 } else { code };
        // axis 0: (a, b, c); axis 1: (c, a, b); axis 2: (b, c, a)
        dx[i] = if axis == 0 {
            a
        } else if axis == 1 {
            cc
        } else {
            b
        };
        dy[i] = if axis == 1 {
            a
        } else if axis == 2 {
            cc
        } else {
            b
        };
        dz[i] = if axis == 2 {
            a
        } else if axis == 0 {
            cc
        } else {
            b
        };
    }
    other != 0
}

/// Rays whose bounds are added to the statistics at a time while encoding.
const STATS_BLOCK: usize = 256;

/// Encodes the origin, direction and hit-distance columns of `cols` (whole trees, each
/// contiguous from ray 0), learning primitive planes into `planes` (the segment's) on the way.
/// Adds every ray's bounds to `stats` too (one pass over the columns instead of two).
pub(crate) fn encode(
    cols: &RayColumns,
    encoding: Encoding,
    stats: &mut Stats,
    planes: &mut PlaneLearner,
) -> Result<EncodedCore> {
    let n = cols.len();
    let mut out = EncodedCore {
        origin: [vec![0; n], vec![0; n], vec![0; n]],
        code: vec![0; n],
        dir: [vec![0; n], vec![0; n], vec![0; n]],
        t: vec![0; n],
    };
    let mut st = TreeState::default();
    let (tree, ray, parent) = (&cols.tree_id[..n], &cols.ray[..n], &cols.parent[..n]);
    let (ox, oy, oz) = (&cols.origin[0][..n], &cols.origin[1][..n], &cols.origin[2][..n]);
    let (dx, dy, dz) = (&cols.direction[0][..n], &cols.direction[1][..n], &cols.direction[2][..n]);
    let (t, hit, prim) = (&cols.t[..n], &cols.hit[..n], &cols.prim[..n]);
    let [eox, eoy, eoz] = &mut out.origin;
    let [eu, ev, er] = &mut out.dir;
    let (eox, eoy, eoz, code_out) = (&mut eox[..n], &mut eoy[..n], &mut eoz[..n], &mut out.code[..n]);
    let (eu, ev, er) = (&mut eu[..n], &mut ev[..n], &mut er[..n]);
    let et = &mut out.t[..n];
    for i in 0..n {
        if i % STATS_BLOCK == 0 {
            // Bounds block by block, just before the block is encoded, while its rays are in L1.
            let b = i..(i + STATS_BLOCK).min(n);
            stats.add_rays(
                [&ox[b.clone()], &oy[b.clone()], &oz[b.clone()]],
                [&dx[b.clone()], &dy[b.clone()], &dz[b.clone()]],
                &t[b.clone()],
                &hit[b],
            );
        }
        let p = parent[i];
        st.advance(tree[i], ray[i], p).map_err(Error::Encoding)?;
        let o = [ox[i], oy[i], oz[i]];
        let d = [dx[i], dy[i], dz[i]];
        let pred = st.predict_origin(p);
        let mut raw_flags = 0u8;
        let mut res = [0u32; 3];
        for k in 0..3 {
            // Near zero a prediction a few µm off is millions of ULPs away: store such a
            // coordinate raw instead (repeated raw values are what zstd compresses well).
            let (pr, r) = (residual(o[k], pred[k]), residual(o[k], 0.0));
            if r < pr {
                raw_flags |= 1 << k;
            }
            res[k] = pr.min(r);
        }
        (eox[i], eoy[i], eoz[i]) = (res[0], res[1], res[2]);
        let (code, w, decoded) = encode_dir(d, encoding);
        let mut t_flag = 0u8;
        if hit[i] {
            // The plane's prediction from what the decoder will have (the decoded direction).
            let pred = if prim[i] == NONE_U32 { None } else { planes.predict_or_observe(prim[i], o, decoded, d, t[i]) };
            et[i] = match pred.map(|p| residual(t[i], p)) {
                Some(r) if r < T_RESIDUAL_LIMIT => {
                    t_flag = T_PREDICTED;
                    r
                }
                _ => t[i].to_bits(),
            };
        }
        code_out[i] = code | (raw_flags << 3) | t_flag;
        (eu[i], ev[i], er[i]) = (w[0], w[1], w[2]);
        st.push(p, o, decoded, hit[i].then_some(t[i]));
    }
    Ok(out)
}

/// The `kind` dictionary column of a `kind_code` column.
pub(crate) fn kinds_of_codes(codes: &ArrayRef, kinds: &KindTable, path: &Path) -> Result<ArrayRef> {
    let codes = codes.as_primitive_opt::<UInt8Type>().ok_or_else(|| Error::Corrupt {
        path: path.to_path_buf(),
        what: "ray file".into(),
        message: format!("column {KIND_CODE} is not UInt8"),
    })?;
    Ok(Arc::new(kind_array(codes.values(), kinds)?))
}

/// Turns ray-file batches back into ray-table batches. Keeps the tree being decoded across
/// batches, so a file read in any batch size decodes; the first batch must start at a tree.
pub struct Decoder {
    encoding: Encoding,
    plain: SchemaRef,
    kinds: KindTable,
    state: TreeState,
    /// The planes of the segment being decoded (its ray file's `rtvtk.planes`).
    planes: Arc<Planes>,
    /// The throughput colours of the segment being decoded (its ray file's `rtvtk.chromas`).
    chromas: Arc<crate::path_payload::Chromas>,
    /// The last tree id of the batch decoded before, where `radiance` is predicted from whole
    /// trees: the next batch must not go on with that tree.
    last_tree: Option<u64>,
}

impl Decoder {
    /// A decoder to the ray table schema `plain`; `kinds` names the kind codes. Files of format
    /// version 3 also need their segment's planes ([`Decoder::with_planes`]).
    pub fn new(encoding: Encoding, plain: SchemaRef, kinds: KindTable) -> Self {
        Self {
            encoding,
            plain,
            kinds,
            state: TreeState::default(),
            planes: Arc::default(),
            chromas: Arc::default(),
            last_tree: None,
        }
    }

    /// The decoder for a segment whose ray file holds throughput colours `chromas`.
    pub fn with_chromas(mut self, chromas: Arc<crate::path_payload::Chromas>) -> Self {
        self.chromas = chromas;
        self
    }

    /// The decoder for a segment whose ray file holds `planes`.
    pub fn with_planes(mut self, planes: Arc<Planes>) -> Self {
        self.planes = planes;
        self
    }

    /// Decodes one batch of a ray file at `path` (named in errors). Where the file predicts
    /// `radiance` (`enc_radiance_*`), batches must end at tree ends
    /// ([`crate::Dataset::segment_batches_in`] cuts them so).
    pub fn decode(&mut self, batch: RecordBatch, path: &Path) -> Result<RecordBatch> {
        if self.encoding == Encoding::Plain {
            return Ok(batch);
        }
        let corrupt = |message: String| Error::Corrupt { path: path.to_path_buf(), what: "ray file".into(), message };
        let g = self.decode_geometry(&batch, path, true)?;
        let mut floats: Vec<(&str, ArrayRef)> = g.columns();
        if crate::path_payload::predicted_in(batch.schema_ref()) {
            let throughput = self.decode_throughput(&batch, path)?;
            floats.push((crate::path_payload::RADIANCE, self.decode_radiance(&batch, &throughput, path)?));
            floats.push((crate::path_payload::THROUGHPUT, throughput));
        }
        let kind = kinds_of_codes(file_column(&batch, KIND_CODE, path)?, &self.kinds, path)?;
        let mut columns = Vec::with_capacity(self.plain.fields().len());
        for f in self.plain.fields() {
            if let Some(pos) = floats.iter().position(|(name, _)| name == f.name()) {
                columns.push(floats.swap_remove(pos).1);
            } else if f.name() == "kind" {
                columns.push(kind.clone());
            } else {
                columns.push(file_column(&batch, f.name(), path)?.clone());
            }
        }
        RecordBatch::try_new(self.plain.clone(), columns).map_err(|e| corrupt(format!("decoded batch: {e}")))
    }

    /// The `throughput` column of a batch of a ray file that predicts it (`enc_throughput_*`,
    /// `enc_chroma`).
    pub(crate) fn decode_throughput(&self, batch: &RecordBatch, path: &Path) -> Result<ArrayRef> {
        crate::path_payload::decode_throughput(batch, &self.chromas, path)
    }

    /// The `radiance` column of a batch of whole trees of a ray file that predicts it (columns
    /// `enc_radiance_*`, `enc_chroma`, `tree_id`, `kind_code`), with the batch's decoded
    /// `throughput`.
    pub(crate) fn decode_radiance(
        &mut self,
        batch: &RecordBatch,
        throughput: &ArrayRef,
        path: &Path,
    ) -> Result<ArrayRef> {
        let ids = crate::schema::typed_column::<UInt64Type>(batch, crate::schema::col::TREE_ID, path)?;
        if !ids.is_empty() {
            let first = ids.value(0);
            if self.last_tree == Some(first) {
                return Err(Error::Corrupt {
                    path: path.to_path_buf(),
                    what: "ray file".into(),
                    message: format!("tree {first} goes on past the end of a batch: radiance decodes from whole trees"),
                });
            }
            self.last_tree = Some(ids.value(ids.len() - 1));
        }
        crate::path_payload::decode_radiance(batch, throughput, path)
    }

    /// Decodes the directions of a batch of a ray file, and its origins (and encoded hit
    /// distances) when `origins` is set. Directions need only `enc_dir_*`; origins also need
    /// `tree_id`, `ray`, `parent`, `t` (or `enc_t` and `prim`) and `enc_origin_*` (the tree
    /// structure they are predicted from), and batches that start at a tree, in file order.
    pub(crate) fn decode_geometry(&mut self, batch: &RecordBatch, path: &Path, origins: bool) -> Result<Geometry> {
        let corrupt = |message: String| Error::Corrupt { path: path.to_path_buf(), what: "ray file".into(), message };
        let typed_u32 = |name: &str| -> Result<&UInt32Array> {
            file_column(batch, name, path)?
                .as_primitive_opt::<UInt32Type>()
                .ok_or_else(|| corrupt(format!("column {name} is not UInt32")))
        };
        let code = file_column(batch, "enc_dir_code", path)?
            .as_primitive_opt::<UInt8Type>()
            .ok_or_else(|| corrupt("column enc_dir_code is not UInt8".into()))?;
        let ed = [typed_u32(ENCODED_COLUMNS[4])?, typed_u32(ENCODED_COLUMNS[5])?, typed_u32(ENCODED_COLUMNS[6])?];
        let bits = match self.encoding {
            Encoding::Oct(b) => b,
            _ => 0,
        };
        let n = batch.num_rows();
        // The tree structure, when origins are asked for (also names rows in errors).
        let structure = if origins {
            let tree = file_column(batch, crate::schema::col::TREE_ID, path)?
                .as_primitive_opt::<UInt64Type>()
                .ok_or_else(|| corrupt("column tree_id is not UInt64".into()))?;
            let t = match batch.column_by_name(ENC_T) {
                Some(e) => {
                    let e = e
                        .as_primitive_opt::<UInt32Type>()
                        .ok_or_else(|| corrupt(format!("column {ENC_T} is not UInt32")))?;
                    HitDistances::Encoded(e, typed_u32("prim")?)
                }
                None => HitDistances::Plain(
                    file_column(batch, "t", path)?
                        .as_primitive_opt::<arrow::datatypes::Float32Type>()
                        .ok_or_else(|| corrupt("column t is not Float32".into()))?,
                ),
            };
            let eo = [typed_u32(ENCODED_COLUMNS[0])?, typed_u32(ENCODED_COLUMNS[1])?, typed_u32(ENCODED_COLUMNS[2])?];
            Some((tree, typed_u32("ray")?, typed_u32("parent")?, t, eo))
        } else {
            None
        };
        let row_name = |i: usize| match &structure {
            Some((tree, ray, ..)) => format!("tree {} ray {}", tree.value(i), ray.value(i)),
            None => format!("row {i} of the batch"),
        };
        // Directions: every ray decoded as if its axis were predicted, in one branch-free loop the
        // compiler vectorizes; then the rare rays stored otherwise (raw, octahedral, or a code
        // with unknown bits) again, one by one.
        let (codes, e0, e1, e2) =
            (&code.values()[..n], &ed[0].values()[..n], &ed[1].values()[..n], &ed[2].values()[..n]);
        let mut dir = [vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]];
        {
            let [dx, dy, dz] = &mut dir;
            if predicted_dirs(codes, [e0, e1, e2], [dx, dy, dz]) {
                for (i, &c) in codes.iter().enumerate() {
                    if c >> 7 != 0 {
                        return Err(corrupt(format!("{}: enc_dir_code {c} has unknown bits", row_name(i))));
                    }
                    let code = c & 7;
                    if code >= 6 {
                        let d = decode_dir(code, [e0[i], e1[i], e2[i]], bits)
                            .map_err(|m| corrupt(format!("{}: {m}", row_name(i))))?;
                        (dx[i], dy[i], dz[i]) = (d[0], d[1], d[2]);
                    }
                }
            }
        }
        let Some((tree, ray, parent, t, eo)) = structure else {
            return Ok(Geometry { origin: None, dir: dir.map(Float32Array::from), t: None });
        };
        // Origins, predicted from the tree (previous sibling, else the parent's hit point); then
        // encoded hit distances, predicted from the hit primitive's plane.
        let mut origin = [Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n)];
        let mut decoded_t: Vec<f32> = Vec::with_capacity(if matches!(t, HitDistances::Encoded(..)) { n } else { 0 });
        let st = &mut self.state;
        for (i, &c) in codes.iter().enumerate() {
            let p = if parent.is_null(i) { NONE_U32 } else { parent.value(i) };
            st.advance(tree.value(i), ray.value(i), p).map_err(corrupt)?;
            let pred = st.predict_origin(p);
            let o = [0, 1, 2].map(|k| apply(eo[k].value(i), if c & (8 << k) != 0 { 0.0 } else { pred[k] }));
            for (out, v) in origin.iter_mut().zip(o) {
                out.push(v);
            }
            let d = [dir[0][i], dir[1][i], dir[2][i]];
            let ti = match t {
                HitDistances::Plain(t) => {
                    if c & T_PREDICTED != 0 {
                        return Err(corrupt(format!(
                            "{}: enc_dir_code {c} flags a predicted t in a file without {ENC_T}",
                            row_name(i)
                        )));
                    }
                    (!t.is_null(i)).then(|| t.value(i))
                }
                HitDistances::Encoded(e, prim) => {
                    let v = if e.is_null(i) {
                        None
                    } else if c & T_PREDICTED != 0 {
                        let pr = if prim.is_null(i) { NONE_U32 } else { prim.value(i) };
                        let tp = self.planes.get(pr).and_then(|plane| plane.predict(o, d)).ok_or_else(|| {
                            corrupt(format!(
                                "{}: t is predicted from primitive {pr}, which has no usable plane",
                                row_name(i)
                            ))
                        })?;
                        Some(apply(e.value(i), tp))
                    } else {
                        Some(f32::from_bits(e.value(i)))
                    };
                    decoded_t.push(v.unwrap_or(0.0));
                    v
                }
            };
            st.push(p, o, d, ti);
        }
        let t = match t {
            HitDistances::Encoded(e, _) => Some(Float32Array::new(decoded_t.into(), e.nulls().cloned())),
            HitDistances::Plain(_) => None,
        };
        Ok(Geometry { origin: Some(origin.map(Float32Array::from)), dir: dir.map(Float32Array::from), t })
    }
}

/// The hit-distance column of a ray file: plain (format version 2), or encoded with the
/// primitive column that names each ray's plane.
#[derive(Clone, Copy)]
enum HitDistances<'a> {
    Plain(&'a Float32Array),
    Encoded(&'a UInt32Array, &'a UInt32Array),
}

/// Decoded origins (when asked for), directions, and hit distances (when encoded and origins
/// were asked for) of a batch.
pub(crate) struct Geometry {
    pub origin: Option<[Float32Array; 3]>,
    pub dir: [Float32Array; 3],
    pub t: Option<Float32Array>,
}

impl Geometry {
    /// The decoded columns under their ray-table names.
    pub(crate) fn columns(self) -> Vec<(&'static str, ArrayRef)> {
        let mut out: Vec<(&'static str, ArrayRef)> = Vec::with_capacity(6);
        if let Some([x, y, z]) = self.origin {
            out.extend([("origin_x", Arc::new(x) as ArrayRef), ("origin_y", Arc::new(y)), ("origin_z", Arc::new(z))]);
        }
        let [x, y, z] = self.dir;
        out.extend([("dir_x", Arc::new(x) as ArrayRef), ("dir_y", Arc::new(y)), ("dir_z", Arc::new(z))]);
        if let Some(t) = self.t {
            out.push(("t", Arc::new(t)));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directions_round_trip_bit_exactly() {
        let dirs = [
            [0.0f32, 0.0, 1.0],
            [0.0, -1.0, 0.0],
            [0.6, 0.8, 0.0],
            [-0.57735026, 0.57735026, -0.57735026],
            [1e-30, -1.0, 1e-38],
            [3.0, 4.0, 12.0],
            [0.0, 0.0, 0.0],
            [f32::NAN, 0.0, 1.0],
            [0.0, f32::INFINITY, 0.0],
            [-0.0, -0.0, -1.0],
        ];
        for d in dirs {
            let (code, w, dec) = encode_dir(d, Encoding::Lossless);
            assert_eq!(dec.map(f32::to_bits), d.map(f32::to_bits));
            let back = decode_dir(code, w, 0).unwrap();
            assert_eq!(back.map(f32::to_bits), d.map(f32::to_bits), "{d:?}");
        }
        // A normalized vector costs a small residual.
        let (_, w, _) = encode_dir([0.26726124, 0.5345225, 0.8017837], Encoding::Lossless);
        assert!(w[2] < 16, "residual {}", w[2]);
    }

    #[test]
    fn the_vectorized_direction_loop_matches_the_per_ray_decoder() {
        // Directions along every axis and sign, non-unit and non-finite ones (raw codes), and
        // octahedral codes: each row decoded by the batch loop, then by `decode_dir`.
        let mut dirs = Vec::new();
        for i in 0..3000 {
            let a = i as f64 * 0.37;
            let z = (i as f64 / 1500.0) - 1.0;
            let r = (1.0 - z * z).sqrt();
            let v = [(r * a.cos()) as f32, (r * a.sin()) as f32, z as f32];
            dirs.push([v[(i / 7) % 3], v[(i / 7 + 1) % 3], v[(i / 7 + 2) % 3]]);
        }
        dirs.extend([
            [3.0, -4.0, 12.0],
            [0.0, 0.0, 0.0],
            [f32::NAN, 0.0, 1.0],
            [-0.0, -0.0, -1.0],
            [1e-30, -1.0, 1e-38],
        ]);
        for (encoding, bits) in [(Encoding::Lossless, 0u8), (Encoding::Oct(12), 12)] {
            let (mut codes, mut w) = (Vec::new(), [Vec::new(), Vec::new(), Vec::new()]);
            for (i, &d) in dirs.iter().enumerate() {
                let (code, wi, _) = encode_dir(d, encoding);
                // Origin and t flags in the upper bits must not change the direction.
                codes.push(code | (((i % 8) as u8) << 3) | if i % 3 == 0 { T_PREDICTED } else { 0 });
                for k in 0..3 {
                    w[k].push(wi[k]);
                }
            }
            let n = dirs.len();
            let mut out = [vec![0.0f32; n], vec![0.0f32; n], vec![0.0f32; n]];
            let [ox, oy, oz] = &mut out;
            let other = predicted_dirs(&codes, [&w[0], &w[1], &w[2]], [ox, oy, oz]);
            assert!(other, "raw or octahedral codes are reported");
            for i in 0..n {
                let code = codes[i] & 7;
                let want = decode_dir(code, [w[0][i], w[1][i], w[2][i]], bits).unwrap();
                if code < 6 {
                    let got = [out[0][i], out[1][i], out[2][i]];
                    assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits), "row {i}: {:?}", dirs[i]);
                    if encoding == Encoding::Lossless {
                        assert_eq!(got.map(f32::to_bits), dirs[i].map(f32::to_bits), "row {i}");
                    }
                }
            }
        }
        // Only predicted codes: nothing left for the per-ray pass; an unknown bit is reported.
        let unit = [[0.6f32, 0.8, 0.0]; 4];
        let enc: Vec<_> = unit.iter().map(|&d| encode_dir(d, Encoding::Lossless)).collect();
        let mut codes: Vec<u8> = enc.iter().map(|e| e.0).collect();
        let w: [Vec<u32>; 3] = [0, 1, 2].map(|k| enc.iter().map(|e| e.1[k]).collect());
        let mut out = [vec![0.0f32; 4], vec![0.0f32; 4], vec![0.0f32; 4]];
        let [ox, oy, oz] = &mut out;
        assert!(!predicted_dirs(&codes, [&w[0], &w[1], &w[2]], [ox, oy, oz]));
        assert_eq!([out[0][2], out[1][2], out[2][2]], unit[2]);
        codes[1] |= 0x80;
        let [ox, oy, oz] = &mut out;
        assert!(predicted_dirs(&codes, [&w[0], &w[1], &w[2]], [ox, oy, oz]));
    }

    #[test]
    fn octahedral_error_shrinks_with_bits() {
        let mut worst = [0.0f64; 2];
        for (k, bits) in [8u8, 16].into_iter().enumerate() {
            for i in 0..2000 {
                let a = i as f64 * 0.7;
                let z = (i as f64 / 1000.0) - 1.0;
                let r = (1.0 - z * z).sqrt();
                let d = [(r * a.cos()) as f32, (r * a.sin()) as f32, z as f32];
                let (code, w, dec) = encode_dir(d, Encoding::Oct(bits));
                assert_eq!(code, DIR_OCT);
                assert_eq!(decode_dir(code, w, bits).unwrap(), dec);
                worst[k] = worst[k].max(crate::geom::angle_between_f32(d, dec));
            }
        }
        assert!(worst[0] < 0.02, "8-bit error {} rad", worst[0]);
        assert!(worst[1] < 5e-5, "16-bit error {} rad", worst[1]);
        assert!(worst[1] < worst[0] / 100.0);
    }

    #[test]
    fn encoding_names_parse_back() {
        for e in [Encoding::Plain, Encoding::Lossless, Encoding::Oct(8), Encoding::Oct(16)] {
            assert_eq!(Encoding::parse(&e.name()).unwrap(), e);
        }
        for bad in ["oct", "oct7", "oct17", "zip", ""] {
            let err = Encoding::parse(bad).unwrap_err().to_string();
            assert!(err.contains("expected plain, lossless or octN"), "{err}");
        }
    }
}
