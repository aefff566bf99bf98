//! The whole-recording tables a dataset may carry beside its rays (`triangles`, `lights`,
//! `bvh_nodes`, `ray_nodes`) and the camera and image attributes: their names, their schemas,
//! and the check that a table read from disk matches its schema.
//!
//! Renderers write these tables through `rl::Recorder::write_table`; `query` and the viewer read
//! them by the column names defined here. Every table is optional: a dataset without one still
//! opens, and the reader says what is missing. A table that is present but does not match its
//! schema is an error naming the table and the column ([`check_table`]).

use std::collections::BTreeMap;
use std::sync::Arc;

use arrow::datatypes::{DataType, Field, Schema, SchemaRef};

/// Name of the scene's triangles table (one row per triangle the renderer traced against).
pub const TRIANGLES_TABLE: &str = "triangles";
/// Name of the emitters table (one row per emissive triangle).
pub const LIGHTS_TABLE: &str = "lights";
/// Name of the BVH nodes table (one row per node of the binary BVH).
pub const BVH_NODES_TABLE: &str = "bvh_nodes";
/// Name of the visited-nodes table (one row per node a ray visited, in visit order).
pub const RAY_NODES_TABLE: &str = "ray_nodes";

pub use crate::schema::col;

fn f32s(names: &[&str]) -> impl Iterator<Item = Field> {
    names.iter().map(|n| Field::new(*n, DataType::Float32, false)).collect::<Vec<_>>().into_iter()
}

fn vertices() -> Vec<Field> {
    col::VERTEX.iter().flat_map(|v| f32s(v)).collect()
}

/// Schema of the `triangles` table: prim id, three vertices, the material (index, name, kind,
/// diffuse and specular colour, Phong exponent, index of refraction) and its emission.
pub fn triangles_schema() -> SchemaRef {
    let mut fields = vec![Field::new(col::PRIM, DataType::UInt32, false)];
    fields.extend(vertices());
    fields.push(Field::new(col::MATERIAL, DataType::UInt32, false));
    fields.push(Field::new(col::MATERIAL_NAME, DataType::Utf8, false));
    fields.push(Field::new(col::MATERIAL_KIND, DataType::Utf8, false));
    fields.extend(f32s(&col::DIFFUSE));
    fields.extend(f32s(&col::SPECULAR));
    fields.extend(f32s(&[col::EXPONENT, col::IOR]));
    fields.extend(f32s(&col::EMISSION));
    Arc::new(Schema::new(fields))
}

/// One row of the `triangles` table.
#[derive(Clone, Debug, PartialEq)]
pub struct TriangleRow<'a> {
    pub vertices: [[f32; 3]; 3],
    /// Material index (rows with the same index share one material).
    pub material: u32,
    pub material_name: &'a str,
    /// `diffuse`, `glossy`, `mirror` or `dielectric`.
    pub material_kind: &'a str,
    pub diffuse: [f32; 3],
    pub specular: [f32; 3],
    pub exponent: f32,
    pub ior: f32,
    pub emission: [f32; 3],
}

/// The `triangles` table of `rows` (prim ids are the row numbers).
pub fn triangles_batch(rows: &[TriangleRow]) -> Result<arrow::array::RecordBatch, arrow::error::ArrowError> {
    use arrow::array::{ArrayRef, Float32Array, StringArray, UInt32Array};
    let f = |get: &dyn Fn(&TriangleRow) -> f32| -> ArrayRef {
        Arc::new(Float32Array::from_iter_values(rows.iter().map(get)))
    };
    let mut cols: Vec<ArrayRef> = vec![Arc::new(UInt32Array::from_iter_values(0..rows.len() as u32))];
    for v in 0..3 {
        for a in 0..3 {
            cols.push(f(&|r| r.vertices[v][a]));
        }
    }
    cols.push(Arc::new(UInt32Array::from_iter_values(rows.iter().map(|r| r.material))));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.material_name))));
    cols.push(Arc::new(StringArray::from_iter_values(rows.iter().map(|r| r.material_kind))));
    for a in 0..3 {
        cols.push(f(&|r| r.diffuse[a]));
    }
    for a in 0..3 {
        cols.push(f(&|r| r.specular[a]));
    }
    cols.push(f(&|r| r.exponent));
    cols.push(f(&|r| r.ior));
    for a in 0..3 {
        cols.push(f(&|r| r.emission[a]));
    }
    arrow::array::RecordBatch::try_new(triangles_schema(), cols)
}

/// The `triangles` table from flat arrays, as `rlSetTriangles` and the Python package take them:
/// `vertices` 9 floats per triangle, one material index per triangle, per material 3 floats of
/// diffuse colour and 3 of emission and a name (diffuse materials). Refuses non-finite values
/// and a material index without a material, naming the triangle.
pub fn triangles_from_arrays(
    vertices: &[f32],
    materials: &[u32],
    colors: &[f32],
    emission: &[f32],
    names: &[String],
) -> Result<arrow::array::RecordBatch, String> {
    let (n, m) = (materials.len(), names.len());
    if vertices.len() != n * 9 || colors.len() != m * 3 || emission.len() != m * 3 {
        return Err(format!(
            "{n} triangles and {m} materials need {} vertex floats, {} colour and emission floats: got {}, {} and {}",
            n * 9,
            m * 3,
            vertices.len(),
            colors.len(),
            emission.len()
        ));
    }
    if vertices.iter().chain(colors).chain(emission).any(|x| !x.is_finite()) {
        return Err("vertices, colors and emission must be finite".into());
    }
    let mut rows = Vec::with_capacity(n);
    for (t, &mi) in materials.iter().enumerate() {
        let k = mi as usize;
        if k >= m {
            return Err(format!("triangle {t} uses material {mi}, but only {m} materials were given"));
        }
        let tri = |j: usize| [vertices[t * 9 + j * 3], vertices[t * 9 + j * 3 + 1], vertices[t * 9 + j * 3 + 2]];
        let rgb = |a: &[f32]| [a[k * 3], a[k * 3 + 1], a[k * 3 + 2]];
        rows.push(TriangleRow {
            vertices: [tri(0), tri(1), tri(2)],
            material: mi,
            material_name: &names[k],
            material_kind: "diffuse",
            diffuse: rgb(colors),
            specular: [0.0; 3],
            exponent: 0.0,
            ior: 1.0,
            emission: rgb(emission),
        });
    }
    triangles_batch(&rows).map_err(|e| e.to_string())
}

/// The `prim` of a light that is no triangle of the scene: a point light, whose row's three
/// vertices are its position (and whose area is 0).
pub const POINT_LIGHT_PRIM: u32 = u32::MAX;

/// A point light: its position and its intensity (RGB, the `emission` columns of its row).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointLight {
    pub position: [f32; 3],
    pub intensity: [f32; 3],
}

/// The `lights` table of a `triangles` table (one built by [`triangles_batch`]): every triangle
/// whose emission is positive in some channel, in triangle order, with its area, as rtvtk's
/// tracers list their emitters. The recording APIs (`rlSetTriangles`, the Python package's
/// `set_scene`) write it beside the triangles, so `aims_at_light` knows another renderer's
/// emitters. [`lights_table`] adds point lights.
pub fn lights_from_triangles(
    triangles: &arrow::array::RecordBatch,
) -> Result<arrow::array::RecordBatch, arrow::error::ArrowError> {
    lights_table(Some(triangles), &[])
}

/// The `lights` table: the emissive triangles of `triangles` (as [`lights_from_triangles`]),
/// then `points`, each a row whose three vertices are its position, with `prim`
/// [`POINT_LIGHT_PRIM`], its intensity as emission and area 0. Positions and intensities must
/// be finite, intensities not negative.
pub fn lights_table(
    triangles: Option<&arrow::array::RecordBatch>,
    points: &[PointLight],
) -> Result<arrow::array::RecordBatch, arrow::error::ArrowError> {
    if let Some((i, _)) = points.iter().enumerate().find(|(_, p)| {
        !p.position.iter().chain(&p.intensity).all(|v| v.is_finite()) || p.intensity.iter().any(|v| *v < 0.0)
    }) {
        return Err(arrow::error::ArrowError::InvalidArgumentError(format!(
            "point light {i}: position and intensity must be finite, intensity not negative"
        )));
    }
    let empty;
    let triangles = match triangles {
        Some(t) => t,
        None => {
            empty = arrow::array::RecordBatch::new_empty(triangles_schema());
            &empty
        }
    };
    use arrow::array::{Array, ArrayRef, AsArray, Float32Array, UInt32Array};
    use arrow::datatypes::{Float32Type, UInt32Type};
    use arrow::error::ArrowError;
    let f32s = |name: &str| -> Result<&Float32Array, ArrowError> {
        triangles.column_by_name(name).and_then(|c| c.as_primitive_opt::<Float32Type>()).ok_or_else(|| {
            ArrowError::SchemaError(format!("table `triangles`: column `{name}` missing or not Float32"))
        })
    };
    let prim =
        triangles.column_by_name(col::PRIM).and_then(|c| c.as_primitive_opt::<UInt32Type>()).ok_or_else(|| {
            ArrowError::SchemaError(format!("table `triangles`: column `{}` missing or not UInt32", col::PRIM))
        })?;
    let (er, eg, eb) = (f32s(col::EMISSION[0])?, f32s(col::EMISSION[1])?, f32s(col::EMISSION[2])?);
    let mut vertex = Vec::with_capacity(9);
    for name in col::VERTEX.iter().flatten() {
        vertex.push(f32s(name)?);
    }
    let rows: Vec<usize> =
        (0..triangles.num_rows()).filter(|&r| er.value(r).max(eg.value(r)).max(eb.value(r)) > 0.0).collect();
    let n = u32::try_from(rows.len() + points.len()).map_err(|_| ArrowError::ComputeError("too many lights".into()))?;
    let mut cols: Vec<ArrayRef> = vec![
        Arc::new(UInt32Array::from_iter_values(0..n)),
        Arc::new(UInt32Array::from_iter_values(
            rows.iter().map(|&r| prim.value(r)).chain(points.iter().map(|_| POINT_LIGHT_PRIM)),
        )),
    ];
    for (k, v) in vertex.iter().enumerate() {
        let point = points.iter().map(|p| p.position[k % 3]);
        cols.push(Arc::new(Float32Array::from_iter_values(rows.iter().map(|&r| v.value(r)).chain(point))));
    }
    for (k, e) in [er, eg, eb].into_iter().enumerate() {
        let point = points.iter().map(|p| p.intensity[k]);
        cols.push(Arc::new(Float32Array::from_iter_values(rows.iter().map(|&r| e.value(r)).chain(point))));
    }
    let area = rows.iter().map(|&r| {
        let p = |k: usize| [vertex[k * 3].value(r), vertex[k * 3 + 1].value(r), vertex[k * 3 + 2].value(r)];
        let (a, b, c) = (p(0), p(1), p(2));
        let (e1, e2) = ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
        let x = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
        0.5 * (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt()
    });
    cols.push(Arc::new(Float32Array::from_iter_values(area.chain(points.iter().map(|_| 0.0)))));
    if prim.null_count() > 0 {
        return Err(ArrowError::InvalidArgumentError("table `triangles`: `prim` has nulls".into()));
    }
    arrow::array::RecordBatch::try_new(lights_schema(), cols)
}

/// The table of recording sites: where in the renderer's source each ray was added.
pub const SITES_TABLE: &str = "sites";
/// The payload column holding each ray's site (an id of the `sites` table; SQL shows it as the
/// site's text, `file:line function`).
pub const SITE_COLUMN: &str = "site";

/// Schema of the `sites` table: site_id (the `site` payload column's value), the source file,
/// line, column (0 when unknown) and function (null when unknown).
pub fn sites_schema() -> SchemaRef {
    Arc::new(Schema::new(vec![
        Field::new("site_id", DataType::UInt32, false),
        Field::new("file", DataType::Utf8, false),
        Field::new("line", DataType::UInt32, false),
        Field::new("column", DataType::UInt32, false),
        Field::new("function", DataType::Utf8, true),
    ]))
}

/// One recording site.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Site {
    pub file: String,
    pub line: u32,
    pub column: u32,
    pub function: Option<String>,
}

impl Site {
    /// How SQL shows the site: `file:line` and the function where known.
    pub fn text(&self) -> String {
        match &self.function {
            Some(f) => format!("{}:{} {f}", self.file, self.line),
            None => format!("{}:{}", self.file, self.line),
        }
    }
}

/// The `sites` table of `sites`, whose ids are their positions.
pub fn sites_batch(sites: &[Site]) -> Result<arrow::array::RecordBatch, arrow::error::ArrowError> {
    use arrow::array::{StringArray, UInt32Array};
    let n = u32::try_from(sites.len()).map_err(|_| arrow::error::ArrowError::ComputeError("too many sites".into()))?;
    arrow::array::RecordBatch::try_new(
        sites_schema(),
        vec![
            Arc::new(UInt32Array::from_iter_values(0..n)),
            Arc::new(StringArray::from_iter_values(sites.iter().map(|s| s.file.as_str()))),
            Arc::new(UInt32Array::from_iter_values(sites.iter().map(|s| s.line))),
            Arc::new(UInt32Array::from_iter_values(sites.iter().map(|s| s.column))),
            Arc::new(StringArray::from_iter(sites.iter().map(|s| s.function.as_deref()))),
        ],
    )
}

/// Schema of the `lights` table: every emissive triangle with its vertices, emission and area.
pub fn lights_schema() -> SchemaRef {
    let mut fields =
        vec![Field::new(col::LIGHT_ID, DataType::UInt32, false), Field::new(col::PRIM, DataType::UInt32, false)];
    fields.extend(vertices());
    fields.extend(f32s(&col::EMISSION));
    fields.extend(f32s(&[col::AREA]));
    Arc::new(Schema::new(fields))
}

/// Schema of the `bvh_nodes` table: id, parent (null at the root), level, bounds, leaf flag and
/// the triangles of a leaf.
pub fn bvh_nodes_schema() -> SchemaRef {
    let item = Arc::new(Field::new("item", DataType::UInt32, false));
    let mut fields = vec![
        Field::new(col::NODE_ID, DataType::UInt32, false),
        Field::new(col::PARENT, DataType::UInt32, true),
        Field::new(col::LEVEL, DataType::UInt16, false),
    ];
    fields.extend(f32s(&col::BOX_MIN));
    fields.extend(f32s(&col::BOX_MAX));
    fields.push(Field::new(col::IS_LEAF, DataType::Boolean, false));
    fields.push(Field::new(col::PRIMS, DataType::List(item), false));
    Arc::new(Schema::new(fields))
}

/// One node of a renderer's BVH as the recording APIs take it: its parent (None at the root),
/// bounds, and, for a leaf, its triangles (`prims`, empty for an inner node).
#[derive(Clone, Debug, PartialEq)]
pub struct BvhNodeRow<'a> {
    pub parent: Option<u32>,
    pub min: [f32; 3],
    pub max: [f32; 3],
    pub leaf: bool,
    pub prims: &'a [u32],
}

/// The `bvh_nodes` table of `nodes` (ids are positions). Levels are counted from the parents;
/// a parent must be an existing node and the parents must form a tree under one root.
pub fn bvh_nodes_batch(nodes: &[BvhNodeRow<'_>]) -> Result<arrow::array::RecordBatch, String> {
    use arrow::array::{ArrayRef, BooleanArray, Float32Array, ListArray, UInt16Array, UInt32Array};
    let n = nodes.len();
    let mut level = vec![u16::MAX; n];
    for i in 0..n {
        // Walk up to a node whose level is known (or the root), then fill the path down.
        let mut path = vec![i];
        let mut at = i;
        let mut steps = 0;
        while level[at] == u16::MAX {
            match nodes[at].parent {
                None => {
                    level[at] = 0;
                    path.pop();
                    break;
                }
                Some(p) => {
                    let p = p as usize;
                    if p >= n {
                        return Err(format!("node {at}: parent {p} does not exist ({n} nodes)"));
                    }
                    steps += 1;
                    if steps > n {
                        return Err(format!("node {i}: its parents go round in a circle"));
                    }
                    at = p;
                    path.push(at);
                }
            }
        }
        while let Some(j) = path.pop() {
            if level[j] == u16::MAX {
                let p = nodes[j].parent.map_or(0, |p| p as usize);
                level[j] = level[p].saturating_add(1);
            }
        }
    }
    if let Some((i, _)) = nodes.iter().enumerate().find(|(_, nd)| nd.min.iter().chain(&nd.max).any(|v| v.is_nan())) {
        return Err(format!("node {i}: its bounds are NaN"));
    }
    let f = |get: &dyn Fn(&BvhNodeRow) -> f32| -> ArrayRef {
        Arc::new(Float32Array::from_iter_values(nodes.iter().map(get)))
    };
    let mut offsets = vec![0i32];
    let mut values: Vec<u32> = Vec::new();
    for nd in nodes {
        values.extend_from_slice(nd.prims);
        offsets.push(i32::try_from(values.len()).map_err(|_| "too many leaf triangles".to_string())?);
    }
    let schema = bvh_nodes_schema();
    let item = match schema.field_with_name(col::PRIMS).map_err(|e| e.to_string())?.data_type() {
        DataType::List(item) => item.clone(),
        other => return Err(format!("prims is {other}")),
    };
    let prims = ListArray::try_new(
        item,
        arrow::buffer::OffsetBuffer::new(offsets.into()),
        Arc::new(UInt32Array::from(values)),
        None,
    )
    .map_err(|e| e.to_string())?;
    let ids = u32::try_from(n).map_err(|_| "too many nodes".to_string())?;
    arrow::array::RecordBatch::try_new(
        schema,
        vec![
            Arc::new(UInt32Array::from_iter_values(0..ids)),
            Arc::new(UInt32Array::from_iter(nodes.iter().map(|nd| nd.parent))),
            Arc::new(UInt16Array::from(level)),
            f(&|nd| nd.min[0]),
            f(&|nd| nd.min[1]),
            f(&|nd| nd.min[2]),
            f(&|nd| nd.max[0]),
            f(&|nd| nd.max[1]),
            f(&|nd| nd.max[2]),
            Arc::new(BooleanArray::from_iter(nodes.iter().map(|nd| Some(nd.leaf)))),
            Arc::new(prims),
        ],
    )
    .map_err(|e| e.to_string())
}

/// One BVH node a ray visited: (tree id, ray index, node id, whether the ray hit a triangle of
/// the node when it is a leaf; None for an inner node).
pub type Visit = (u64, u32, u32, Option<bool>);

/// The `ray_nodes` table of `visits`, sorted by ray (keeping each ray's visit order) and
/// numbered by step.
pub fn ray_nodes_batch(mut visits: Vec<Visit>) -> Result<arrow::array::RecordBatch, arrow::error::ArrowError> {
    use arrow::array::{BooleanArray, UInt32Array, UInt64Array};
    visits.sort_by_key(|v| (v.0, v.1));
    let mut steps = Vec::with_capacity(visits.len());
    let mut prev = None;
    let mut step = 0u32;
    for v in &visits {
        step = if prev == Some((v.0, v.1)) { step + 1 } else { 0 };
        prev = Some((v.0, v.1));
        steps.push(step);
    }
    arrow::array::RecordBatch::try_new(
        ray_nodes_schema(),
        vec![
            Arc::new(UInt64Array::from_iter_values(visits.iter().map(|v| v.0))),
            Arc::new(UInt32Array::from_iter_values(visits.iter().map(|v| v.1))),
            Arc::new(UInt32Array::from(steps)),
            Arc::new(UInt32Array::from_iter_values(visits.iter().map(|v| v.2))),
            Arc::new(BooleanArray::from_iter(visits.iter().map(|v| v.3))),
        ],
    )
}

/// Schema of the `ray_nodes` table: the nodes each ray visited, in order; `leaf_hit` is null for
/// inner nodes and says whether a visited leaf held the ray's hit.
pub fn ray_nodes_schema() -> SchemaRef {
    Arc::new(Schema::new(vec![
        Field::new(col::TREE_ID, DataType::UInt64, false),
        Field::new(col::RAY, DataType::UInt32, false),
        Field::new(col::STEP, DataType::UInt32, false),
        Field::new(col::NODE_ID, DataType::UInt32, false),
        Field::new(col::LEAF_HIT, DataType::Boolean, true),
    ]))
}

/// The schema a known optional table must match, or `None` for a table this build does not know.
pub fn known_table_schema(name: &str) -> Option<SchemaRef> {
    match name {
        TRIANGLES_TABLE => Some(triangles_schema()),
        LIGHTS_TABLE => Some(lights_schema()),
        SITES_TABLE => Some(sites_schema()),
        BVH_NODES_TABLE => Some(bvh_nodes_schema()),
        RAY_NODES_TABLE => Some(ray_nodes_schema()),
        _ => None,
    }
}

/// Checks that `schema` (a table as read or about to be written) has every column its known
/// schema declares, with the same type. Extra columns are allowed (a renderer may add its own).
/// Returns a message naming the first missing or mistyped column.
pub fn check_table(name: &str, schema: &Schema) -> Result<(), String> {
    let Some(expected) = known_table_schema(name) else { return Ok(()) };
    for f in expected.fields() {
        match schema.field_with_name(f.name()) {
            Err(_) => return Err(format!("column `{}` is missing: expected {}", f.name(), f.data_type())),
            Ok(found) if !types_match(f.data_type(), found.data_type()) => {
                return Err(format!(
                    "column `{}` has type {}: expected {}",
                    f.name(),
                    found.data_type(),
                    f.data_type()
                ));
            }
            Ok(_) => {}
        }
    }
    Ok(())
}

/// Types match ignoring list item names and nullability (Parquet round trips may rename them).
fn types_match(a: &DataType, b: &DataType) -> bool {
    match (a, b) {
        (DataType::List(x), DataType::List(y)) => x.data_type() == y.data_type(),
        (DataType::Utf8, DataType::Utf8 | DataType::LargeUtf8 | DataType::Utf8View) => true,
        _ => a == b,
    }
}

/// Attribute keys of the camera and the image, in the manifest's `attributes`.
pub mod attr {
    /// `x,y,z` of the eye.
    pub const CAMERA_POSITION: &str = "camera.position";
    /// `x,y,z` the camera looks at.
    pub const CAMERA_TARGET: &str = "camera.target";
    /// `x,y,z` up vector.
    pub const CAMERA_UP: &str = "camera.up";
    /// Vertical field of view, degrees.
    pub const CAMERA_FOV_Y: &str = "camera.fov_y";
    /// Image width and height in pixels.
    pub const WIDTH: &str = "width";
    pub const HEIGHT: &str = "height";
    /// The rendered image (PNG, tone mapped) and its linear EXR, relative to the dataset directory.
    pub const IMAGE_PNG: &str = "image.png";
    pub const IMAGE_EXR: &str = "image.exr";
}

/// The pinhole camera a dataset was rendered with, as the manifest's attributes record it.
///
/// Primary ray of film position (px, py) in a `width` × `height` image (y down):
/// `normalize(f + r * sx + u * sy)` with `f = normalize(target - position)`,
/// `r = normalize(f × up)`, `u = r × f`, `sx = (2 px / width - 1) tan(fov_y / 2) width / height`,
/// `sy = (1 - 2 py / height) tan(fov_y / 2)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraAttrs {
    pub position: [f32; 3],
    pub target: [f32; 3],
    pub up: [f32; 3],
    pub fov_y: f32,
    pub width: u32,
    pub height: u32,
}

fn vec3(s: &str) -> Option<[f32; 3]> {
    let v: Vec<f32> = s.split(',').map(|p| p.trim().parse::<f32>().ok()).collect::<Option<_>>()?;
    let v: [f32; 3] = v.try_into().ok()?;
    v.iter().all(|c| c.is_finite()).then_some(v)
}

fn fmt3(v: [f32; 3]) -> String {
    format!("{},{},{}", v[0], v[1], v[2])
}

impl CameraAttrs {
    /// The attributes to store (`camera.*`, `width`, `height`).
    pub fn to_attributes(&self) -> Vec<(String, String)> {
        vec![
            (attr::CAMERA_POSITION.into(), fmt3(self.position)),
            (attr::CAMERA_TARGET.into(), fmt3(self.target)),
            (attr::CAMERA_UP.into(), fmt3(self.up)),
            (attr::CAMERA_FOV_Y.into(), self.fov_y.to_string()),
            (attr::WIDTH.into(), self.width.to_string()),
            (attr::HEIGHT.into(), self.height.to_string()),
        ]
    }

    /// Reads the camera back. `Ok(None)` when the dataset has no camera attributes (recorded
    /// before they existed); `Err` names the attribute that is present but malformed.
    pub fn from_attributes(attrs: &BTreeMap<String, String>) -> Result<Option<CameraAttrs>, String> {
        if !attrs.contains_key(attr::CAMERA_POSITION) {
            return Ok(None);
        }
        let get = |k: &str| attrs.get(k).ok_or_else(|| format!("attribute `{k}` is missing"));
        let v = |k: &str| -> Result<[f32; 3], String> {
            let s = get(k)?;
            vec3(s).ok_or_else(|| format!("attribute `{k}` is {s:?}: expected three finite numbers x,y,z"))
        };
        let n = |k: &str| -> Result<u32, String> {
            let s = get(k)?;
            s.parse::<u32>()
                .ok()
                .filter(|n| *n > 0)
                .ok_or_else(|| format!("attribute `{k}` is {s:?}: expected a positive integer"))
        };
        let fov_s = get(attr::CAMERA_FOV_Y)?;
        let fov_y =
            fov_s.parse::<f32>().ok().filter(|f| f.is_finite() && *f > 0.0 && *f < 180.0).ok_or_else(|| {
                format!("attribute `{}` is {fov_s:?}: expected degrees in (0, 180)", attr::CAMERA_FOV_Y)
            })?;
        let c = CameraAttrs {
            position: v(attr::CAMERA_POSITION)?,
            target: v(attr::CAMERA_TARGET)?,
            up: v(attr::CAMERA_UP)?,
            fov_y,
            width: n(attr::WIDTH)?,
            height: n(attr::HEIGHT)?,
        };
        if c.position == c.target {
            return Err(format!("attributes `{}` and `{}` are equal", attr::CAMERA_POSITION, attr::CAMERA_TARGET));
        }
        Ok(Some(c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_round_trips_and_bad_values_are_named() {
        let c = CameraAttrs {
            position: [278.0, 273.0, -800.0],
            target: [278.0, 273.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y: 39.3077,
            width: 640,
            height: 480,
        };
        let mut m: BTreeMap<String, String> = c.to_attributes().into_iter().collect();
        assert_eq!(CameraAttrs::from_attributes(&m), Ok(Some(c)));
        assert_eq!(CameraAttrs::from_attributes(&BTreeMap::new()), Ok(None));
        m.insert(attr::CAMERA_UP.into(), "0,nan,0".into());
        let e = CameraAttrs::from_attributes(&m).unwrap_err();
        assert!(e.contains("camera.up"), "{e}");
        m.insert(attr::CAMERA_UP.into(), "0,1,0".into());
        m.insert(attr::WIDTH.into(), "0".into());
        assert!(CameraAttrs::from_attributes(&m).unwrap_err().contains("width"));
    }

    #[test]
    fn emissive_triangles_become_the_lights_table() {
        use arrow::array::AsArray;
        use arrow::datatypes::{Float32Type, UInt32Type};
        // A floor triangle (grey), a light triangle of area 2 and a dark one.
        let v = [
            0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 5.0, 0.0, 2.0, 5.0, 0.0, 0.0, 5.0, 2.0, 0.0, 1.0, 0.0,
            1.0, 1.0, 0.0, 0.0, 1.0, 1.0,
        ];
        let names = ["grey".to_string(), "lamp".to_string(), "black".to_string()];
        let colors = [0.5; 9];
        let emission = [0.0, 0.0, 0.0, 4.0, 3.0, 2.0, 0.0, 0.0, 0.0];
        let tris = triangles_from_arrays(&v, &[0, 1, 2], &colors, &emission, &names).unwrap();
        let lights = lights_from_triangles(&tris).unwrap();
        assert_eq!(check_table(LIGHTS_TABLE, &lights.schema()), Ok(()));
        assert_eq!(lights.num_rows(), 1);
        let prim = lights.column_by_name(col::PRIM).unwrap().as_primitive::<UInt32Type>();
        assert_eq!(prim.value(0), 1);
        let f = |n: &str| lights.column_by_name(n).unwrap().as_primitive::<Float32Type>().value(0);
        assert_eq!((f("emission_r"), f("emission_g"), f("emission_b")), (4.0, 3.0, 2.0));
        assert!((f(col::AREA) - 2.0).abs() < 1e-6);
        assert_eq!(f("v1_x"), 2.0);
        // Point lights follow the triangles: their position three times, no prim, no area.
        let p = PointLight { position: [1.0, 2.0, 3.0], intensity: [5.0, 5.0, 5.0] };
        let both = lights_table(Some(&tris), &[p]).unwrap();
        assert_eq!(both.num_rows(), 2);
        let prim = both.column_by_name(col::PRIM).unwrap().as_primitive::<UInt32Type>();
        assert_eq!((prim.value(0), prim.value(1)), (1, POINT_LIGHT_PRIM));
        let g = |n: &str| both.column_by_name(n).unwrap().as_primitive::<Float32Type>().value(1);
        assert_eq!([g("v0_x"), g("v1_y"), g("v2_z"), g("emission_g"), g(col::AREA)], [1.0, 2.0, 3.0, 5.0, 0.0]);
        let bad = PointLight { position: [f32::NAN, 0.0, 0.0], intensity: [1.0; 3] };
        assert!(lights_table(None, &[bad]).unwrap_err().to_string().contains("point light 0"));
        assert_eq!(lights_table(None, &[p]).unwrap().num_rows(), 1);
        // No emitter: an empty table, still of the lights schema.
        let dark = triangles_from_arrays(&v[..9], &[0], &colors[..3], &[0.0; 3], &names[..1]).unwrap();
        assert_eq!(lights_from_triangles(&dark).unwrap().num_rows(), 0);
    }

    #[test]
    fn check_table_names_missing_and_mistyped_columns() {
        let s = lights_schema();
        assert_eq!(check_table(LIGHTS_TABLE, &s), Ok(()));
        let fewer = Schema::new(s.fields().iter().filter(|f| f.name() != "v1_y").cloned().collect::<Vec<_>>());
        let e = check_table(LIGHTS_TABLE, &fewer).unwrap_err();
        assert!(e.contains("`v1_y` is missing"), "{e}");
        let retyped = Schema::new(
            s.fields()
                .iter()
                .map(|f| {
                    if f.name() == "area" { Arc::new(Field::new("area", DataType::Float64, false)) } else { f.clone() }
                })
                .collect::<Vec<_>>(),
        );
        let e = check_table(LIGHTS_TABLE, &retyped).unwrap_err();
        assert!(e.contains("`area` has type Float64"), "{e}");
        assert_eq!(check_table("my_own_table", &fewer), Ok(()));
        for t in [TRIANGLES_TABLE, BVH_NODES_TABLE, RAY_NODES_TABLE] {
            let s = known_table_schema(t).unwrap();
            assert_eq!(check_table(t, &s), Ok(()));
        }
    }
}
