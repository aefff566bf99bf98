//! The Arrow schema of the ray and tree tables: the one place it is defined.
//!
//! Ray table (one row per ray, rays of one tree contiguous and in recording order):
//! `tree_id, ray, parent, depth, kind, origin_{x,y,z}, dir_{x,y,z}, t, prim`, then the client's
//! typed payload columns, then `payload` (opaque bytes) when the client declared one.
//! Tree table (one row per tree, sorted by `tree_id`):
//! `tree_id, pixel_x, pixel_y, sample, ray_count, max_depth, segment, first_row`.

use std::collections::HashMap;
use std::sync::Arc;

use arrow::datatypes::{DataType, Field, Schema, SchemaRef, TimeUnit};
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// The kind column of encoded ray files: the kind code of each ray.
pub const KIND_CODE: &str = "kind_code";

/// The column `name` of a ray-file batch, or an error naming the file.
pub(crate) fn file_column<'a>(
    batch: &'a arrow::array::RecordBatch,
    name: &str,
    path: &std::path::Path,
) -> Result<&'a arrow::array::ArrayRef> {
    batch.column_by_name(name).ok_or_else(|| Error::Schema {
        path: path.to_path_buf(),
        field: name.into(),
        expected: "an encoded column".into(),
        found: "no such column".into(),
    })
}

/// The column `name` of a ray-file batch as a primitive array of `T`, or an error naming the file.
pub(crate) fn typed_column<'a, T: arrow::datatypes::ArrowPrimitiveType>(
    batch: &'a arrow::array::RecordBatch,
    name: &str,
    path: &std::path::Path,
) -> Result<&'a arrow::array::PrimitiveArray<T>> {
    use arrow::array::AsArray;
    file_column(batch, name, path)?.as_primitive_opt::<T>().ok_or_else(|| Error::Corrupt {
        path: path.to_path_buf(),
        what: "ray file".into(),
        message: format!("column {name} is not {}", T::DATA_TYPE),
    })
}

/// The kind of a ray: a built-in one or one a client registered by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Kind(pub u8);

impl Kind {
    pub const CAMERA: Kind = Kind(0);
    pub const SHADOW: Kind = Kind(1);
    pub const DIFFUSE: Kind = Kind(2);
    pub const SPECULAR: Kind = Kind(3);
    pub const TRANSMISSION: Kind = Kind(4);
    /// Codes from here on are handed out to kinds registered by name.
    pub const FIRST_CUSTOM: u8 = 16;
}

/// Names of the built-in kinds, by code.
pub const BUILTIN_KINDS: [(&str, Kind); 5] = [
    ("camera", Kind::CAMERA),
    ("shadow", Kind::SHADOW),
    ("diffuse", Kind::DIFFUSE),
    ("specular", Kind::SPECULAR),
    ("transmission", Kind::TRANSMISSION),
];

/// Kind names by code: the built-ins plus the ones a client registered.
#[derive(Clone, Debug)]
pub struct KindTable {
    names: Vec<Option<Arc<str>>>,
    next_custom: u16,
}

impl Default for KindTable {
    fn default() -> Self {
        let mut names = vec![None; 256];
        for (name, kind) in BUILTIN_KINDS {
            names[kind.0 as usize] = Some(Arc::from(name));
        }
        Self { names, next_custom: u16::from(Kind::FIRST_CUSTOM) }
    }
}

impl KindTable {
    /// The name of a kind code, if that code is known.
    pub fn name(&self, kind: Kind) -> Option<&str> {
        self.names[kind.0 as usize].as_deref()
    }

    /// The kind of a name, if known.
    pub fn lookup(&self, name: &str) -> Option<Kind> {
        self.names.iter().position(|n| n.as_deref() == Some(name)).map(|i| Kind(i as u8))
    }

    /// Registers a kind by name (or returns the existing one of that name).
    pub fn register(&mut self, name: &str) -> Result<Kind> {
        if let Some(kind) = self.lookup(name) {
            return Ok(kind);
        }
        if name.is_empty() || name.len() > 64 {
            return Err(Error::PayloadDecl(format!("kind name must be 1 to 64 bytes long, got {name:?}")));
        }
        if self.next_custom > 255 {
            return Err(Error::PayloadDecl(format!(
                "cannot register kind {name:?}: all {} custom kind codes are in use",
                256 - u16::from(Kind::FIRST_CUSTOM)
            )));
        }
        let code = self.next_custom as u8;
        self.next_custom += 1;
        self.names[code as usize] = Some(Arc::from(name));
        Ok(Kind(code))
    }

    /// Sets a code's name (used when reading a manifest).
    pub fn insert(&mut self, kind: Kind, name: &str) {
        self.names[kind.0 as usize] = Some(Arc::from(name));
        if u16::from(kind.0) >= self.next_custom {
            self.next_custom = u16::from(kind.0) + 1;
        }
    }

    /// Map from name to kind for every known code.
    pub fn by_name(&self) -> HashMap<String, Kind> {
        self.names.iter().enumerate().filter_map(|(i, n)| n.as_ref().map(|n| (n.to_string(), Kind(i as u8)))).collect()
    }
}

/// Element types a typed payload column may hold (Arrow primitives and booleans).
fn scalar_type_name(dt: &DataType) -> Option<String> {
    let unit = |u: &TimeUnit| match u {
        TimeUnit::Second => "s",
        TimeUnit::Millisecond => "ms",
        TimeUnit::Microsecond => "us",
        TimeUnit::Nanosecond => "ns",
    };
    Some(match dt {
        DataType::Boolean => "bool".into(),
        DataType::Int8 => "int8".into(),
        DataType::Int16 => "int16".into(),
        DataType::Int32 => "int32".into(),
        DataType::Int64 => "int64".into(),
        DataType::UInt8 => "uint8".into(),
        DataType::UInt16 => "uint16".into(),
        DataType::UInt32 => "uint32".into(),
        DataType::UInt64 => "uint64".into(),
        DataType::Float16 => "float16".into(),
        DataType::Float32 => "float32".into(),
        DataType::Float64 => "float64".into(),
        DataType::Date32 => "date32".into(),
        DataType::Date64 => "date64".into(),
        DataType::Timestamp(u, None) => format!("timestamp_{}", unit(u)),
        DataType::Duration(u) => format!("duration_{}", unit(u)),
        _ => return None,
    })
}

fn parse_scalar_type(name: &str) -> Option<DataType> {
    let unit = |s: &str| match s {
        "s" => Some(TimeUnit::Second),
        "ms" => Some(TimeUnit::Millisecond),
        "us" => Some(TimeUnit::Microsecond),
        "ns" => Some(TimeUnit::Nanosecond),
        _ => None,
    };
    Some(match name {
        "bool" => DataType::Boolean,
        "int8" => DataType::Int8,
        "int16" => DataType::Int16,
        "int32" => DataType::Int32,
        "int64" => DataType::Int64,
        "uint8" => DataType::UInt8,
        "uint16" => DataType::UInt16,
        "uint32" => DataType::UInt32,
        "uint64" => DataType::UInt64,
        "float16" => DataType::Float16,
        "float32" => DataType::Float32,
        "float64" => DataType::Float64,
        "date32" => DataType::Date32,
        "date64" => DataType::Date64,
        _ => {
            if let Some(u) = name.strip_prefix("timestamp_") {
                DataType::Timestamp(unit(u)?, None)
            } else if let Some(u) = name.strip_prefix("duration_") {
                DataType::Duration(unit(u)?)
            } else {
                return None;
            }
        }
    })
}

/// How a payload scalar is held in memory while recording: width in bytes, or a boolean.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Storage {
    Bool,
    Int(u8),
    UInt(u8),
    Float(u8),
}

impl Storage {
    pub fn of(dt: &DataType) -> Option<Storage> {
        Some(match dt {
            DataType::Boolean => Storage::Bool,
            DataType::Int8 => Storage::Int(1),
            DataType::Int16 => Storage::Int(2),
            DataType::Int32 | DataType::Date32 => Storage::Int(4),
            DataType::Int64 | DataType::Date64 | DataType::Timestamp(_, None) | DataType::Duration(_) => {
                Storage::Int(8)
            }
            DataType::UInt8 => Storage::UInt(1),
            DataType::UInt16 => Storage::UInt(2),
            DataType::UInt32 => Storage::UInt(4),
            DataType::UInt64 => Storage::UInt(8),
            DataType::Float16 => Storage::Float(2),
            DataType::Float32 => Storage::Float(4),
            DataType::Float64 => Storage::Float(8),
            _ => return None,
        })
    }

    /// Bytes per element in the recording buffers (booleans take one byte there).
    pub fn width(self) -> usize {
        match self {
            Storage::Bool => 1,
            Storage::Int(w) | Storage::UInt(w) | Storage::Float(w) => w as usize,
        }
    }
}

/// One typed payload column a client declares when it creates a recorder.
#[derive(Clone, Debug, PartialEq)]
pub struct PayloadField {
    pub name: String,
    /// Element type (an Arrow primitive or boolean).
    pub element: DataType,
    /// `Some(n)`: each ray holds a fixed-size list of `n` elements (e.g. RGB throughput, n = 3).
    pub list_len: Option<usize>,
}

/// Column names the core ray table uses: payload fields may not take them.
pub const CORE_RAY_COLUMNS: [&str; 14] = [
    col::TREE_ID,
    col::RAY,
    col::PARENT,
    col::DEPTH,
    col::KIND,
    col::ORIGIN[0],
    col::ORIGIN[1],
    col::ORIGIN[2],
    col::DIR[0],
    col::DIR[1],
    col::DIR[2],
    col::T,
    col::PRIM,
    col::PAYLOAD,
];

impl PayloadField {
    /// A scalar column.
    pub fn scalar(name: &str, element: DataType) -> Result<Self> {
        Self::new(name, element, None)
    }

    /// A fixed-size list column (`len` elements per ray).
    pub fn list(name: &str, element: DataType, len: usize) -> Result<Self> {
        Self::new(name, element, Some(len))
    }

    fn new(name: &str, element: DataType, list_len: Option<usize>) -> Result<Self> {
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            return Err(Error::PayloadDecl(format!(
                "payload column name must be non-empty ASCII letters, digits or '_', got {name:?}"
            )));
        }
        if CORE_RAY_COLUMNS.contains(&name) {
            return Err(Error::PayloadDecl(format!("payload column name {name:?} is taken by a core ray column")));
        }
        let storage = Storage::of(&element).ok_or_else(|| {
            Error::PayloadDecl(format!(
                "payload column {name:?}: type {element} is not supported; expected a boolean, integer, float, date, timestamp or duration"
            ))
        })?;
        if let Some(n) = list_len {
            if n == 0 || n > 4096 {
                return Err(Error::PayloadDecl(format!(
                    "payload column {name:?}: list length must be 1 to 4096, got {n}"
                )));
            }
            if storage == Storage::Bool {
                return Err(Error::PayloadDecl(format!(
                    "payload column {name:?}: lists of booleans are not supported"
                )));
            }
        }
        Ok(Self { name: name.to_string(), element, list_len })
    }

    pub fn storage(&self) -> Storage {
        // Validated on construction.
        Storage::of(&self.element).unwrap_or(Storage::UInt(1))
    }

    /// Bytes one ray takes in this column's recording buffer.
    pub fn row_width(&self) -> usize {
        self.storage().width() * self.list_len.unwrap_or(1)
    }

    /// The Arrow type of the column as stored.
    pub fn data_type(&self) -> DataType {
        match self.list_len {
            None => self.element.clone(),
            Some(n) => DataType::FixedSizeList(Arc::new(Field::new("item", self.element.clone(), false)), n as i32),
        }
    }

    /// The type as written in the manifest, e.g. `float32` or `float32[3]`.
    pub fn type_name(&self) -> String {
        let base = scalar_type_name(&self.element).unwrap_or_else(|| "unknown".into());
        match self.list_len {
            None => base,
            Some(n) => format!("{base}[{n}]"),
        }
    }

    /// Parses [`PayloadField::type_name`] output.
    pub fn from_type_name(name: &str, type_name: &str) -> Result<Self> {
        let (base, len) = match type_name.split_once('[') {
            Some((base, rest)) => {
                let n = rest
                    .strip_suffix(']')
                    .and_then(|n| n.parse::<usize>().ok())
                    .ok_or_else(|| Error::PayloadDecl(format!("bad list type {type_name:?} for column {name:?}")))?;
                (base, Some(n))
            }
            None => (type_name, None),
        };
        let element = parse_scalar_type(base)
            .ok_or_else(|| Error::PayloadDecl(format!("unknown payload type {type_name:?} for column {name:?}")))?;
        Self::new(name, element, len)
    }
}

/// The opaque bytes payload column, for clients that hand over `(&data, sizeof data)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BytesPayload {
    /// Every ray carries exactly this many bytes (stored as `FixedSizeBinary`).
    Fixed(usize),
    /// Each ray carries any number of bytes (stored as `Binary`).
    Variable,
}

/// What a recording's ray table holds beyond the core columns.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PayloadSchema {
    pub fields: Vec<PayloadField>,
    pub bytes: Option<BytesPayload>,
}

impl PayloadSchema {
    pub fn new(fields: Vec<PayloadField>, bytes: Option<BytesPayload>) -> Result<Self> {
        for (i, f) in fields.iter().enumerate() {
            if fields[..i].iter().any(|g| g.name == f.name) {
                return Err(Error::PayloadDecl(format!("payload column {:?} is declared twice", f.name)));
            }
        }
        if let Some(BytesPayload::Fixed(n)) = bytes
            && (n == 0 || n > i32::MAX as usize)
        {
            return Err(Error::PayloadDecl(format!(
                "fixed bytes payload size must be 1 to {} bytes, got {n}",
                i32::MAX
            )));
        }
        Ok(Self { fields, bytes })
    }

    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.fields.iter().position(|f| f.name == name)
    }
}

fn meta(field: Field, pairs: &[(&str, &str)]) -> Field {
    field.with_metadata(pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect())
}

/// Column names of every table of a dataset: the ray and tree tables and the scene tables
/// (`triangles`, `lights`, `bvh_nodes`, `ray_nodes`), one constant per name.
pub mod col {
    pub const TREE_ID: &str = "tree_id";
    pub const RAY: &str = "ray";
    pub const DEPTH: &str = "depth";
    pub const KIND: &str = "kind";
    pub const ORIGIN: [&str; 3] = ["origin_x", "origin_y", "origin_z"];
    pub const DIR: [&str; 3] = ["dir_x", "dir_y", "dir_z"];
    pub const T: &str = "t";
    pub const PAYLOAD: &str = "payload";
    pub const PIXEL_X: &str = "pixel_x";
    pub const PIXEL_Y: &str = "pixel_y";
    pub const SAMPLE: &str = "sample";
    pub const RAY_COUNT: &str = "ray_count";
    pub const MAX_DEPTH: &str = "max_depth";
    pub const SEGMENT: &str = "segment";
    pub const FIRST_ROW: &str = "first_row";
    pub const PRIM: &str = "prim";
    pub const LIGHT_ID: &str = "light_id";
    pub const NODE_ID: &str = "node_id";
    pub const PARENT: &str = "parent";
    pub const LEVEL: &str = "level";
    pub const IS_LEAF: &str = "is_leaf";
    pub const PRIMS: &str = "prims";
    pub const STEP: &str = "step";
    pub const LEAF_HIT: &str = "leaf_hit";
    pub const AREA: &str = "area";
    pub const MATERIAL: &str = "material";
    pub const MATERIAL_NAME: &str = "material_name";
    pub const MATERIAL_KIND: &str = "material_kind";
    pub const EXPONENT: &str = "exponent";
    pub const IOR: &str = "ior";
    /// Vertex `v` (0..3), axis `a` (0..3): `v0_x` ... `v2_z`.
    pub const VERTEX: [[&str; 3]; 3] = [["v0_x", "v0_y", "v0_z"], ["v1_x", "v1_y", "v1_z"], ["v2_x", "v2_y", "v2_z"]];
    pub const BOX_MIN: [&str; 3] = ["min_x", "min_y", "min_z"];
    pub const BOX_MAX: [&str; 3] = ["max_x", "max_y", "max_z"];
    pub const EMISSION: [&str; 3] = ["emission_r", "emission_g", "emission_b"];
    pub const DIFFUSE: [&str; 3] = ["diffuse_r", "diffuse_g", "diffuse_b"];
    pub const SPECULAR: [&str; 3] = ["specular_r", "specular_g", "specular_b"];
}

/// The kind column type: dictionary-encoded names, so plain Parquet readers see `'shadow'`.
pub fn kind_data_type() -> DataType {
    DataType::Dictionary(Box::new(DataType::UInt8), Box::new(DataType::Utf8))
}

/// The Arrow schema of the ray table for a payload schema.
pub fn ray_schema(payload: &PayloadSchema) -> SchemaRef {
    let world = [("space", "world")];
    let mut fields = vec![
        meta(Field::new(col::TREE_ID, DataType::UInt64, false), &[("description", "id of the ray tree")]),
        meta(
            Field::new(col::RAY, DataType::UInt32, false),
            &[("description", "index of the ray within its tree, in recording order")],
        ),
        meta(
            Field::new(col::PARENT, DataType::UInt32, true),
            &[("description", "index of the parent ray within the tree; null for a root ray")],
        ),
        meta(Field::new(col::DEPTH, DataType::UInt16, false), &[("description", "0 for root rays")]),
        meta(Field::new(col::KIND, kind_data_type(), false), &[("description", "ray kind name")]),
        meta(Field::new(col::ORIGIN[0], DataType::Float32, false), &world),
        meta(Field::new(col::ORIGIN[1], DataType::Float32, false), &world),
        meta(Field::new(col::ORIGIN[2], DataType::Float32, false), &world),
        meta(Field::new(col::DIR[0], DataType::Float32, false), &world),
        meta(Field::new(col::DIR[1], DataType::Float32, false), &world),
        meta(Field::new(col::DIR[2], DataType::Float32, false), &world),
        meta(
            Field::new(col::T, DataType::Float32, true),
            &[
                ("unit", "multiples of the direction vector (world distance when it is unit length)"),
                ("description", "hit distance; null when the ray missed"),
            ],
        ),
        meta(
            Field::new(col::PRIM, DataType::UInt32, true),
            &[("description", "hit primitive; null when the ray missed or hit no primitive")],
        ),
    ];
    for f in &payload.fields {
        fields.push(meta(Field::new(&f.name, f.data_type(), true), &[("rtvtk.payload", "typed")]));
    }
    match payload.bytes {
        Some(BytesPayload::Fixed(n)) => fields.push(meta(
            Field::new("payload", DataType::FixedSizeBinary(n as i32), true),
            &[("rtvtk.payload", "bytes")],
        )),
        Some(BytesPayload::Variable) => {
            fields.push(meta(Field::new("payload", DataType::Binary, true), &[("rtvtk.payload", "bytes")]))
        }
        None => {}
    }
    Arc::new(Schema::new(fields))
}

/// Columns of the `rays` table SQL shows that are stored with the ray's tree, not the ray.
pub const TREE_COLUMNS: [&str; 3] = [col::PIXEL_X, col::PIXEL_Y, col::SAMPLE];

/// The `rays` table as SQL shows it: the stored ray columns (`base`, a [`ray_schema`]) and,
/// from each ray's tree, `pixel_x`, `pixel_y` and `sample` (all `UInt32`).
pub fn ray_table_schema(base: &SchemaRef) -> SchemaRef {
    let mut fields: Vec<Arc<Field>> = base.fields().iter().cloned().collect();
    for name in TREE_COLUMNS {
        if base.index_of(name).is_err() {
            let f = meta(
                Field::new(name, DataType::UInt32, false),
                &[("description", "of the ray's tree, from the tree table")],
            );
            fields.push(Arc::new(f));
        }
    }
    Arc::new(Schema::new_with_metadata(fields, base.metadata().clone()))
}

/// The Arrow schema of the tree table.
pub fn tree_schema() -> SchemaRef {
    Arc::new(Schema::new(vec![
        Field::new(col::TREE_ID, DataType::UInt64, false),
        Field::new(col::PIXEL_X, DataType::UInt32, false),
        Field::new(col::PIXEL_Y, DataType::UInt32, false),
        Field::new(col::SAMPLE, DataType::UInt32, false),
        Field::new(col::RAY_COUNT, DataType::UInt32, false),
        Field::new(col::MAX_DEPTH, DataType::UInt16, false),
        meta(
            Field::new(col::SEGMENT, DataType::UInt32, false),
            &[("description", "id of the segment whose ray file holds the tree")],
        ),
        meta(
            Field::new(col::FIRST_ROW, DataType::UInt64, false),
            &[("description", "row of the tree's first ray in that segment's ray file")],
        ),
    ]))
}

/// Number of core ray columns before the payload columns.
pub const CORE_COLUMN_COUNT: usize = 13;
