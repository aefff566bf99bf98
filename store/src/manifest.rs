//! The dataset manifest: the one file that says which segments are part of the trace.
//!
//! It is replaced atomically (write to a temporary file, fsync, rename, fsync the directory),
//! so a reader sees either the old or the new list of segments, never a torn one.

use std::collections::BTreeMap;
use std::fs;
use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::codec::Encoding;
use crate::error::io_err;
use crate::schema::{BytesPayload, KindTable, PayloadField, PayloadSchema};
use crate::stats::Stats;
use crate::{Error, Kind, Result};

/// Name of the manifest file inside a dataset directory.
pub const MANIFEST_FILE: &str = "manifest.json";
/// Value of the manifest's `format` field.
pub const FORMAT_NAME: &str = "rtvtk-trace";
/// The format version this build writes and the newest it reads.
pub const FORMAT_VERSION: u32 = 4;

/// A file of a segment, as the manifest records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Path relative to the dataset directory.
    pub path: String,
    pub bytes: u64,
    pub crc32: u32,
    pub rows: u64,
    /// A whole-dataset table's columns as written (`name: type`), so a file whose columns were
    /// changed is found for tables this build has no schema of too (a renderer's own); absent in
    /// segment entries and in datasets written before it (then only known tables are checked).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub columns: Option<Vec<String>>,
}

/// The `columns` a manifest records for a table of `schema`.
pub fn table_columns(schema: &arrow::datatypes::Schema) -> Vec<String> {
    schema.fields().iter().map(|f| format!("{}: {}", f.name(), f.data_type())).collect()
}

/// One sealed segment: a ray file and its tree file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SegmentEntry {
    pub id: u32,
    pub rays: FileEntry,
    pub trees: FileEntry,
    pub tree_id_min: u64,
    pub tree_id_max: u64,
    pub stats: Stats,
}

/// A typed payload column as the manifest records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PayloadColumnDecl {
    pub name: String,
    #[serde(rename = "type")]
    pub type_name: String,
}

/// The manifest of a dataset.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub format_version: u32,
    pub created_by: String,
    /// How the ray files store origins and directions (absent in version 1: plain).
    #[serde(default = "plain_encoding")]
    pub encoding: Encoding,
    /// Float payload values were rounded to this many mantissa bits when written (lossy
    /// payload); absent when the payload is bit-exact.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub payload_mantissa_bits: Option<u8>,
    /// Typed payload columns (absent when there are none).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub payload: Vec<PayloadColumnDecl>,
    /// The opaque bytes payload column, when declared.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bytes_payload: Option<BytesPayload>,
    /// Kind codes by name: only the kinds the trace uses.
    pub kinds: BTreeMap<String, u8>,
    pub segments: Vec<SegmentEntry>,
    /// Totals over all segments.
    pub stats: Stats,
    /// True once the recorder finished cleanly.
    pub complete: bool,
    /// Optional whole-dataset tables by name (`bvh_nodes`, `lights`, ...), absent when unused.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub tables: BTreeMap<String, FileEntry>,
    /// Free-form facts about the recording (scene, tracer, seed, image size, ...).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub attributes: BTreeMap<String, String>,
}

impl Manifest {
    /// An empty manifest for a new recording.
    pub fn new(payload: &PayloadSchema, encoding: Encoding) -> Self {
        Self {
            format: FORMAT_NAME.into(),
            format_version: FORMAT_VERSION,
            created_by: format!("rtvtk-store {}", env!("CARGO_PKG_VERSION")),
            encoding,
            payload_mantissa_bits: None,
            payload: payload
                .fields
                .iter()
                .map(|f| PayloadColumnDecl { name: f.name.clone(), type_name: f.type_name() })
                .collect(),
            bytes_payload: payload.bytes,
            kinds: BTreeMap::new(),
            segments: Vec::new(),
            stats: Stats::default(),
            complete: false,
            tables: BTreeMap::new(),
            attributes: BTreeMap::new(),
        }
    }

    /// The payload schema the manifest declares.
    pub fn payload_schema(&self, path: &Path) -> Result<PayloadSchema> {
        let bad = |e: Error| Error::Manifest { path: path.to_path_buf(), message: e.to_string() };
        let fields = self
            .payload
            .iter()
            .map(|d| PayloadField::from_type_name(&d.name, &d.type_name))
            .collect::<Result<Vec<_>>>()
            .map_err(bad)?;
        PayloadSchema::new(fields, self.bytes_payload).map_err(bad)
    }

    /// The kind table the manifest declares.
    pub fn kind_table(&self) -> KindTable {
        let mut t = KindTable::default();
        for (name, code) in &self.kinds {
            t.insert(Kind(*code), name);
        }
        t
    }

    /// Adds a sealed segment, updating totals and the used kinds.
    pub fn add_segment(&mut self, mut seg: SegmentEntry, kinds: &KindTable) {
        // A code recorded before a name was registered for it was counted as `kindN` by the
        // statistics of what was written before. From the name's registration on, the code goes
        // by that name, in this segment and in those committed before: the files hold the code,
        // and the manifest must name it once (found by the C ABI fuzz harness: the file read
        // `kind17` where the manifest counted `b`).
        let renamed: std::collections::BTreeSet<(String, String)> = seg
            .stats
            .rays_by_kind_depth
            .keys()
            .chain(self.kinds.keys())
            .filter_map(|name| Some((name.clone(), registered_name(name, kinds)?)))
            .collect();
        for (from, to) in &renamed {
            seg.stats.rename_kind(from, to);
            self.stats.rename_kind(from, to);
            for s in &mut self.segments {
                s.stats.rename_kind(from, to);
            }
            // The code stays declared under its name even when this segment does not use it
            // (found by the harness: a segment of only an empty tree sealed after the
            // registration left the code undeclared).
            if let Some(code) = self.kinds.remove(from) {
                self.kinds.insert(to.clone(), code);
            }
        }
        self.stats.merge(&seg.stats);
        for name in seg.stats.rays_by_kind_depth.keys() {
            // A code recorded without a name (neither built in nor registered) is counted as
            // `kindN` by the statistics, and declared by that name, so its rays stay readable
            // (found by the C ABI fuzz harness: such rays made the dataset fail `check`).
            if let Some(kind) = kinds.lookup(name).or(unnamed_code(name)) {
                self.kinds.insert(name.clone(), kind.0);
            }
        }
        self.segments.push(seg);
    }

    /// Reads and validates the manifest of the dataset at `dir`.
    pub fn load(dir: &Path) -> Result<Manifest> {
        let path = dir.join(MANIFEST_FILE);
        let text = fs::read_to_string(&path).map_err(|e| {
            if e.kind() == std::io::ErrorKind::NotFound {
                Error::Manifest {
                    path: path.clone(),
                    message: "no manifest: expected a dataset directory written by rtvtk".into(),
                }
            } else {
                Error::Io { action: "reading the manifest", path: path.clone(), source: e }
            }
        })?;
        // Check the version before the full structure, so a newer format gets the right error.
        let head: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::Manifest { path: path.clone(), message: format!("not valid JSON: {e}") })?;
        if head.get("format").and_then(|v| v.as_str()) != Some(FORMAT_NAME) {
            return Err(Error::Manifest { path, message: format!("field `format` must be {FORMAT_NAME:?}") });
        }
        let version = head.get("format_version").and_then(|v| v.as_u64()).ok_or_else(|| Error::Manifest {
            path: path.clone(),
            message: "field `format_version` must be a positive integer".into(),
        })?;
        if version > u64::from(FORMAT_VERSION) {
            return Err(Error::NewerFormat {
                path,
                found: u32::try_from(version).unwrap_or(u32::MAX),
                supported: FORMAT_VERSION,
            });
        }
        let manifest: Manifest =
            serde_json::from_value(head).map_err(|e| Error::Manifest { path: path.clone(), message: e.to_string() })?;
        manifest.check_paths().map_err(|message| Error::Manifest { path, message })?;
        Ok(manifest)
    }

    /// Every file the manifest lists must lie inside the dataset directory: a relative path of
    /// plain names (found by the reader's fuzz harness: a segment path of "/" read the root
    /// directory as a ray file).
    fn check_paths(&self) -> std::result::Result<(), String> {
        let files = self.segments.iter().enumerate().flat_map(|(i, s)| {
            [(format!("segments[{i}].rays.path"), &s.rays.path), (format!("segments[{i}].trees.path"), &s.trees.path)]
        });
        let tables = self.tables.iter().map(|(name, f)| (format!("tables.{name}.path"), &f.path));
        for (field, path) in files.chain(tables) {
            let inside =
                !path.is_empty() && Path::new(path).components().all(|c| matches!(c, std::path::Component::Normal(_)));
            if !inside {
                return Err(format!(
                    "field `{field}` is {path:?}: expected a relative path inside the dataset directory"
                ));
            }
        }
        Ok(())
    }

    /// Atomically replaces the manifest of the dataset at `dir`.
    pub fn store(&self, dir: &Path, sync: bool) -> Result<()> {
        let path = dir.join(MANIFEST_FILE);
        let tmp = dir.join(format!("{MANIFEST_FILE}.tmp"));
        let text = serde_json::to_vec_pretty(self)
            .map_err(|e| Error::Manifest { path: path.clone(), message: format!("cannot serialize: {e}") })?;
        write_atomic(&tmp, &path, &text, sync)
    }
}

/// Writes `bytes` to `tmp`, syncs it, and renames it over `path` (then syncs the directory).
pub(crate) fn write_atomic(tmp: &Path, path: &Path, bytes: &[u8], sync: bool) -> Result<()> {
    let mut f = fs::File::create(tmp).map_err(io_err("creating a temporary file", tmp))?;
    f.write_all(bytes).map_err(io_err("writing a temporary file", tmp))?;
    if sync {
        f.sync_all().map_err(io_err("syncing a temporary file", tmp))?;
    }
    drop(f);
    fs::rename(tmp, path).map_err(io_err("renaming into place", path))?;
    if sync {
        sync_dir(path.parent().unwrap_or(Path::new(".")))?;
    }
    Ok(())
}

pub(crate) fn sync_dir(dir: &Path) -> Result<()> {
    let d = fs::File::open(dir).map_err(io_err("opening the directory to sync it", dir))?;
    d.sync_all().map_err(io_err("syncing the directory", dir))
}

/// Path of a segment's file relative to the dataset directory.
pub fn segment_file(id: u32, table: &str) -> String {
    format!("segments/{id:06}.{table}.parquet")
}

fn plain_encoding() -> Encoding {
    Encoding::Plain
}

/// The code of a `kindN` name: how the statistics count a code that had no name.
fn unnamed_code(name: &str) -> Option<Kind> {
    name.strip_prefix("kind").and_then(|n| n.parse::<u8>().ok()).map(Kind)
}

/// The name registered since for the code of an unnamed `kindN` (None for any other name, and
/// for a `kindN` that is itself a registered name).
fn registered_name(name: &str, kinds: &KindTable) -> Option<String> {
    if kinds.lookup(name).is_some() {
        return None;
    }
    kinds.name(unnamed_code(name)?).map(str::to_string)
}
