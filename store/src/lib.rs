#![doc = include_str!("../README.md")]

mod check;
mod codec;
mod columns;
mod dataset;
mod error;
pub mod geom;
mod manifest;
mod pages;
mod path_payload;
mod planes;
mod rows;
pub mod scene;
mod schema;
pub mod selection;
mod stats;
mod tree;
mod ulp;
mod writer;

pub use check::CheckReport;
pub use codec::{Decoder, ENC_T, ENCODED_COLUMNS, Encoding, KIND_CODE, file_schema};
pub use columns::{BytesBuf, ListValue, NONE_U32, PayloadBuf, PayloadMismatch, RayColumns, RayFields, TreeRow, Value};
pub use dataset::{AccessPlan, Dataset, READ_BATCH_ROWS, SegmentAccess, TreeEntry, TreeFilter, TreeIter};
pub use error::{Error, Result, says_unavailable, unavailable};
pub use manifest::{FORMAT_NAME, FORMAT_VERSION, FileEntry, MANIFEST_FILE, Manifest, PayloadColumnDecl, SegmentEntry};
pub use path_payload::{CHROMAS_KEY, Chromas, ENC_CHROMA, ENC_RADIANCE, ENC_THROUGHPUT, RADIANCE, THROUGHPUT};
pub use planes::{PLANES_KEY, Planes};
pub use rows::{CoreRow, RayRows, RowLayout};
pub use schema::{
    BUILTIN_KINDS, BytesPayload, CORE_COLUMN_COUNT, CORE_RAY_COLUMNS, Kind, KindTable, PayloadField, PayloadSchema,
    Storage, TREE_COLUMNS, kind_data_type, ray_schema, ray_table_schema, tree_schema,
};
pub use selection::RaySelection;
pub use stats::{Bounds, PixelBounds, Stats};
pub use tree::{Ray, Tree, TreeId, TreeInfo, TreeValidator, rays_from_batch, validate_tree};
pub use writer::{CrcWriter, DatasetWriter, SegmentWriter, WriteOptions, export_plain};
