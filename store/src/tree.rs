//! Trees and rays as readers see them.

use std::collections::HashMap;
use std::fmt;
use std::path::Path;

use arrow::array::{Array, ArrayRef, AsArray, PrimitiveArray, RecordBatch};
use arrow::datatypes::{ArrowPrimitiveType, Float32Type, UInt8Type, UInt16Type, UInt32Type, UInt64Type};

use crate::{Error, Kind, Result};

/// Id of a ray tree, unique within a recording.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize, serde::Deserialize)]
pub struct TreeId(pub u64);

impl fmt::Display for TreeId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// Metadata of one tree (one row of the tree table).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct TreeInfo {
    pub id: TreeId,
    pub pixel: [u32; 2],
    pub sample: u32,
    pub ray_count: u32,
    pub max_depth: u16,
}

/// One recorded ray.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Ray {
    /// Index within the tree (recording order).
    pub index: u32,
    /// Index of the parent ray; `None` for a root ray.
    pub parent: Option<u32>,
    pub depth: u16,
    #[serde(serialize_with = "ser_kind")]
    pub kind: Kind,
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    /// Hit distance; `None` for a miss.
    pub t: Option<f32>,
    pub prim: Option<u32>,
}

fn ser_kind<S: serde::Serializer>(k: &Kind, s: S) -> std::result::Result<S::Ok, S::Error> {
    s.serialize_u8(k.0)
}

impl Ray {
    /// The hit point, if the ray hit something.
    pub fn hit_point(&self) -> Option<[f32; 3]> {
        self.t.map(|t| std::array::from_fn(|i| self.origin[i] + t * self.direction[i]))
    }
}

/// A whole ray tree: its metadata, its rays, and all its columns (payload included).
#[derive(Clone, Debug)]
pub struct Tree {
    pub info: TreeInfo,
    pub rays: Vec<Ray>,
    /// The tree's rows of the ray table, every column.
    pub batch: RecordBatch,
}

impl Tree {
    /// The rays whose parent is `index`.
    pub fn children(&self, index: u32) -> impl Iterator<Item = &Ray> + '_ {
        self.rays.iter().filter(move |r| r.parent == Some(index))
    }

    /// The root rays (normally one: the camera ray).
    pub fn roots(&self) -> impl Iterator<Item = &Ray> + '_ {
        self.rays.iter().filter(|r| r.parent.is_none())
    }

    /// Indices from `index` up to its root, `index` first. Empty if `index` is out of range.
    pub fn path_to_root(&self, index: u32) -> Vec<u32> {
        let mut path = Vec::new();
        let mut cur = Some(index);
        while let Some(i) = cur {
            let Some(ray) = self.rays.get(i as usize) else { break };
            path.push(i);
            if path.len() > self.rays.len() {
                break; // a cycle: only possible in corrupt data, which `check` reports
            }
            cur = ray.parent;
        }
        path
    }

    /// A payload column (or any column) of this tree's rays by name.
    pub fn column(&self, name: &str) -> Option<&ArrayRef> {
        self.batch.column_by_name(name)
    }
}

/// Column `name` of `batch` as a `T` array; `Error::Schema` naming the file and the column when
/// it is missing or of another type.
pub(crate) fn primitive<'a, T: ArrowPrimitiveType>(
    batch: &'a RecordBatch,
    name: &str,
    path: &Path,
) -> Result<&'a PrimitiveArray<T>> {
    batch.column_by_name(name).and_then(|c| c.as_primitive_opt::<T>()).ok_or_else(|| Error::Schema {
        path: path.to_path_buf(),
        field: name.into(),
        expected: format!("a {} column", T::DATA_TYPE),
        found: batch.column_by_name(name).map_or("no such column".into(), |c| c.data_type().to_string()),
    })
}

/// Decodes the core columns of ray-table rows into [`Ray`]s (kinds mapped through `kinds`).
pub fn rays_from_batch(batch: &RecordBatch, kinds: &HashMap<String, Kind>, path: &Path) -> Result<Vec<Ray>> {
    let ray = primitive::<UInt32Type>(batch, "ray", path)?;
    let parent = primitive::<UInt32Type>(batch, "parent", path)?;
    let depth = primitive::<UInt16Type>(batch, "depth", path)?;
    let f = |n: &str| primitive::<Float32Type>(batch, n, path);
    let (ox, oy, oz) = (f("origin_x")?, f("origin_y")?, f("origin_z")?);
    let (dx, dy, dz) = (f("dir_x")?, f("dir_y")?, f("dir_z")?);
    let t = f("t")?;
    let prim = primitive::<UInt32Type>(batch, "prim", path)?;
    let kind_col = batch.column_by_name("kind").ok_or_else(|| Error::Schema {
        path: path.to_path_buf(),
        field: "kind".into(),
        expected: "Dictionary(UInt8, Utf8)".into(),
        found: "no such column".into(),
    })?;
    let kind_dict = kind_col.as_dictionary_opt::<UInt8Type>().ok_or_else(|| Error::Schema {
        path: path.to_path_buf(),
        field: "kind".into(),
        expected: "Dictionary(UInt8, Utf8)".into(),
        found: format!("{}", kind_col.data_type()),
    })?;
    let names = kind_dict.values().as_string_opt::<i32>().ok_or_else(|| Error::Schema {
        path: path.to_path_buf(),
        field: "kind".into(),
        expected: "Dictionary(UInt8, Utf8)".into(),
        found: format!("{}", kind_col.data_type()),
    })?;
    let mut key_to_kind = Vec::with_capacity(names.len());
    for i in 0..names.len() {
        let name = names.value(i);
        let kind = kinds.get(name).copied().ok_or_else(|| Error::Corrupt {
            path: path.to_path_buf(),
            what: "column `kind`".into(),
            message: format!("kind {name:?} is not declared in the manifest"),
        })?;
        key_to_kind.push(kind);
    }
    let keys = kind_dict.keys();
    let mut out = Vec::with_capacity(batch.num_rows());
    for i in 0..batch.num_rows() {
        let key = keys.value(i) as usize;
        let kind = *key_to_kind.get(key).ok_or_else(|| Error::Corrupt {
            path: path.to_path_buf(),
            what: "column `kind`".into(),
            message: format!("dictionary key {key} out of range"),
        })?;
        out.push(Ray {
            index: ray.value(i),
            parent: parent.is_valid(i).then(|| parent.value(i)),
            depth: depth.value(i),
            kind,
            origin: [ox.value(i), oy.value(i), oz.value(i)],
            direction: [dx.value(i), dy.value(i), dz.value(i)],
            t: t.is_valid(i).then(|| t.value(i)),
            prim: prim.is_valid(i).then(|| prim.value(i)),
        });
    }
    Ok(out)
}

/// Tree ids of ray-table rows.
pub fn tree_ids_of(batch: &RecordBatch, path: &Path) -> Result<Vec<u64>> {
    Ok(primitive::<UInt64Type>(batch, crate::schema::col::TREE_ID, path)?.values().to_vec())
}

/// Checks that `rays` form the tree `info`: ids, order, parents one level up.
pub fn validate_tree(info: &TreeInfo, tree_ids: &[u64], rays: &[Ray]) -> std::result::Result<(), String> {
    let mut v = TreeValidator::default();
    v.start(*info);
    for (r, &id) in rays.iter().zip(tree_ids) {
        v.push(id, r.index, r.parent, r.depth);
    }
    if tree_ids.len() < rays.len() {
        return Err(format!("tree {}: {} tree ids for {} rays", info.id, tree_ids.len(), rays.len()));
    }
    v.finish()
}

/// [`validate_tree`] one row at a time, so a scan can check trees straight from decoded columns
/// (trees may span batches) without building [`Ray`]s. The first problem of a tree is kept.
#[derive(Debug, Default)]
pub struct TreeValidator {
    info: Option<TreeInfo>,
    /// Depths of the tree's rows so far.
    depths: Vec<u16>,
    max_depth: u16,
    error: Option<String>,
}

impl TreeValidator {
    /// Begins tree `info` (forgetting the previous one).
    pub fn start(&mut self, info: TreeInfo) {
        self.info = Some(info);
        self.depths.clear();
        self.max_depth = 0;
        self.error = None;
    }

    /// The tree's next row.
    #[inline]
    pub fn push(&mut self, tree_id: u64, index: u32, parent: Option<u32>, depth: u16) {
        let i = self.depths.len();
        self.depths.push(depth);
        if self.error.is_some() {
            return;
        }
        let Some(info) = &self.info else { return };
        let id = info.id;
        let problem = if tree_id != id.0 {
            Some(format!("tree {id}: row {i} belongs to tree {tree_id}"))
        } else if index as usize != i {
            Some(format!("tree {id}: ray at position {i} has index {index}"))
        } else {
            match parent {
                None if depth != 0 => Some(format!("tree {id}: root ray {i} has depth {depth}, expected 0")),
                Some(p) if p as usize >= i => {
                    Some(format!("tree {id}: ray {i} has parent {p}, expected an earlier ray"))
                }
                Some(p) if self.depths[p as usize].checked_add(1) != Some(depth) => Some(format!(
                    "tree {id}: ray {i} at depth {depth} has parent {p} at depth {}, expected one level up",
                    self.depths[p as usize]
                )),
                _ => None,
            }
        };
        self.error = problem;
        self.max_depth = self.max_depth.max(depth);
    }

    /// The verdict on the tree begun last: its rows' count and deepest ray against its metadata.
    pub fn finish(&mut self) -> std::result::Result<(), String> {
        let Some(info) = self.info.take() else { return Ok(()) };
        let n = self.depths.len();
        if n != info.ray_count as usize {
            return Err(format!("tree {} lists {} rays, found {n}", info.id, info.ray_count));
        }
        if let Some(e) = self.error.take() {
            return Err(e);
        }
        if n > 0 && self.max_depth != info.max_depth {
            return Err(format!(
                "tree {}: tree table says max depth {}, rays reach {}",
                info.id, info.max_depth, self.max_depth
            ));
        }
        Ok(())
    }
}
