//! A scene as the dataset's `triangles` and `lights` tables and camera attributes (schemas in
//! `store::scene`), and back: a viewer can rebuild the scene a dataset was rendered from.

use std::path::Path;

use arrow::array::{Array, AsArray, Float32Array, RecordBatch, StringArray, UInt32Array};
use arrow::datatypes::{Float32Type, UInt32Type};
use glam::Vec3A;
use store::scene::{CameraAttrs, TriangleRow, col, triangles_batch};

use crate::scene::{BuiltinScene, Camera, Material, MaterialKind, Scene, load_obj};
use crate::{Error, Result};

fn kind_name(k: MaterialKind) -> &'static str {
    match k {
        MaterialKind::Diffuse => "diffuse",
        MaterialKind::Glossy => "glossy",
        MaterialKind::Mirror => "mirror",
        MaterialKind::Dielectric => "dielectric",
    }
}

fn kind_from_name(s: &str) -> Option<MaterialKind> {
    Some(match s {
        "diffuse" => MaterialKind::Diffuse,
        "glossy" => MaterialKind::Glossy,
        "mirror" => MaterialKind::Mirror,
        "dielectric" => MaterialKind::Dielectric,
        _ => return None,
    })
}

impl Scene {
    /// The `triangles` table: every triangle with its vertices and its material.
    pub fn triangles_table(&self) -> std::result::Result<RecordBatch, arrow::error::ArrowError> {
        let rows: Vec<TriangleRow> = (0..self.tris.len())
            .map(|i| {
                let m = self.material_of(i as u32);
                TriangleRow {
                    vertices: self.tris[i].map(|v| v.to_array()),
                    material: self.tri_material[i],
                    material_name: &m.name,
                    material_kind: kind_name(m.kind),
                    diffuse: m.diffuse.to_array(),
                    specular: m.specular.to_array(),
                    exponent: m.exponent,
                    ior: m.ior,
                    emission: m.emission.to_array(),
                }
            })
            .collect();
        triangles_batch(&rows)
    }

    /// The `lights` table: every emissive triangle with its vertices, emission and area.
    pub fn lights_table(&self) -> std::result::Result<RecordBatch, arrow::error::ArrowError> {
        // One derivation for every recorder (this crate's tracers, `rlSetTriangles`, Python).
        store::scene::lights_from_triangles(&self.triangles_table()?)
    }

    /// The scene's camera as dataset attributes, for a `width` × `height` image.
    pub fn camera_attrs(&self, width: u32, height: u32) -> CameraAttrs {
        let c = self.camera;
        CameraAttrs {
            position: c.position.to_array(),
            target: c.target.to_array(),
            up: c.up.to_array(),
            fov_y: c.fov_y,
            width,
            height,
        }
    }

    /// Rebuilds a scene from a `triangles` table (as `store::Dataset::table` returns it, already
    /// checked against its schema). Materials are shared by index; a row whose material index
    /// disagrees with an earlier row's material is an error naming the row.
    pub fn from_triangles_table(name: &str, batch: &RecordBatch, camera: Camera) -> Result<Scene> {
        let bad = |m: String| Error::Scene(format!("table `triangles`: {m}"));
        let f32c = |n: &str| -> Result<&Float32Array> {
            batch
                .column_by_name(n)
                .and_then(|c| c.as_primitive_opt::<Float32Type>())
                .ok_or_else(|| bad(format!("column `{n}` missing or not Float32")))
        };
        let u32c = |n: &str| -> Result<&UInt32Array> {
            batch
                .column_by_name(n)
                .and_then(|c| c.as_primitive_opt::<UInt32Type>())
                .ok_or_else(|| bad(format!("column `{n}` missing or not UInt32")))
        };
        let strc = |n: &str| -> Result<StringArray> {
            let c = batch.column_by_name(n).ok_or_else(|| bad(format!("column `{n}` missing")))?;
            let c = arrow::compute::cast(c, &arrow::datatypes::DataType::Utf8)
                .map_err(|e| bad(format!("column `{n}`: {e}")))?;
            Ok(c.as_string::<i32>().clone())
        };
        let verts: Vec<Vec<&Float32Array>> =
            col::VERTEX.iter().map(|v| v.iter().map(|a| f32c(a)).collect::<Result<Vec<_>>>()).collect::<Result<_>>()?;
        let mat = u32c(col::MATERIAL)?;
        let (names, kinds) = (strc(col::MATERIAL_NAME)?, strc(col::MATERIAL_KIND)?);
        let rgb = |names: &[&str; 3]| -> Result<[&Float32Array; 3]> {
            Ok([f32c(names[0])?, f32c(names[1])?, f32c(names[2])?])
        };
        let (dif, spec, emi) = (rgb(&col::DIFFUSE)?, rgb(&col::SPECULAR)?, rgb(&col::EMISSION)?);
        let (exp, ior) = (f32c(col::EXPONENT)?, f32c(col::IOR)?);
        let v3 = |c: &[&Float32Array; 3], r: usize| Vec3A::new(c[0].value(r), c[1].value(r), c[2].value(r));
        let mut materials: Vec<Option<Material>> = Vec::new();
        let mut tris = Vec::with_capacity(batch.num_rows());
        let mut tri_material = Vec::with_capacity(batch.num_rows());
        for r in 0..batch.num_rows() {
            if mat.is_null(r) || names.is_null(r) || kinds.is_null(r) {
                return Err(bad(format!("row {r}: material is null")));
            }
            let kind = kind_from_name(kinds.value(r)).ok_or_else(|| {
                bad(format!(
                    "row {r}: material_kind {:?}: expected diffuse, glossy, mirror or dielectric",
                    kinds.value(r)
                ))
            })?;
            let m = Material {
                name: names.value(r).to_string(),
                kind,
                diffuse: v3(&dif, r),
                specular: v3(&spec, r),
                exponent: exp.value(r),
                ior: ior.value(r),
                emission: v3(&emi, r),
            };
            let i = mat.value(r) as usize;
            if i > 1 << 20 {
                return Err(bad(format!("row {r}: material index {i} is implausibly large")));
            }
            if materials.len() <= i {
                materials.resize(i + 1, None);
            }
            match &materials[i] {
                Some(prev) if *prev != m => {
                    return Err(bad(format!("row {r}: material {i} differs from an earlier row's material {i}")));
                }
                Some(_) => {}
                None => materials[i] = Some(m),
            }
            let p = |v: usize| Vec3A::new(verts[v][0].value(r), verts[v][1].value(r), verts[v][2].value(r));
            let t = [p(0), p(1), p(2)];
            if t.iter().any(|v| !v.is_finite()) {
                return Err(bad(format!("row {r}: a vertex is NaN or infinite")));
            }
            tris.push(t);
            tri_material.push(i as u32);
        }
        let materials: Vec<Material> =
            materials.into_iter().map(|m| m.unwrap_or_else(|| Material::diffuse("unused", [0.5; 3]))).collect();
        Scene::new(name, tris, tri_material, materials, camera)
    }
}

impl Camera {
    /// The camera of dataset attributes.
    pub fn from_attrs(c: &CameraAttrs) -> Camera {
        Camera {
            position: Vec3A::from_array(c.position),
            target: Vec3A::from_array(c.target),
            up: Vec3A::from_array(c.up),
            fov_y: c.fov_y,
        }
    }
}

/// A built-in scene by name (`cornell`, `cornell-glass`, `glossy`) or an OBJ file, with its
/// quads split `subdivide` × `subdivide` (built-in scenes only) and `camera` replacing the
/// scene's own when given.
pub fn load_scene(name: &str, camera: Option<Camera>, subdivide: u32) -> Result<Scene> {
    let mut scene = match BuiltinScene::parse(name) {
        Some(b) => b.build(subdivide)?,
        None => {
            let p = Path::new(name);
            if p.extension().is_none_or(|e| !e.eq_ignore_ascii_case("obj")) && !p.exists() {
                return Err(Error::Scene(format!(
                    "unknown scene {name:?}: expected cornell, cornell-glass, glossy or an .obj file"
                )));
            }
            load_obj(p, camera)?
        }
    };
    if let Some(c) = camera {
        scene.camera = c;
    }
    Ok(scene)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn triangles_table_round_trips_every_builtin_scene() {
        for b in [BuiltinScene::Cornell, BuiltinScene::CornellGlass, BuiltinScene::Glossy] {
            let s = b.build(1).unwrap();
            let t = s.triangles_table().unwrap();
            assert_eq!(store::scene::check_table("triangles", &t.schema()), Ok(()));
            let back = Scene::from_triangles_table(&s.name, &t, s.camera).unwrap();
            assert_eq!(back.tris, s.tris);
            assert_eq!(back.lights, s.lights);
            for p in 0..s.tris.len() as u32 {
                assert_eq!(back.material_of(p), s.material_of(p));
            }
            let lights = s.lights_table().unwrap();
            assert_eq!(store::scene::check_table("lights", &lights.schema()), Ok(()));
            // The emitters the tracers sample, in order, with the areas they weigh them by.
            assert_eq!(lights.num_rows(), s.lights.len());
            let prim = lights.column_by_name(col::PRIM).unwrap().as_primitive::<arrow::datatypes::UInt32Type>();
            let area = lights.column_by_name(col::AREA).unwrap().as_primitive::<arrow::datatypes::Float32Type>();
            for (i, &l) in s.lights.iter().enumerate() {
                assert_eq!(prim.value(i), l);
                assert!((area.value(i) - s.emitter_area(i)).abs() <= 1e-6 * s.emitter_area(i).max(1.0));
            }
        }
    }

    #[test]
    fn bad_triangles_rows_are_named() {
        let s = BuiltinScene::Cornell.build(1).unwrap();
        let t = s.triangles_table().unwrap();
        let mut cols = t.columns().to_vec();
        let k = t.schema().index_of(col::MATERIAL_KIND).unwrap();
        let mut kinds: Vec<String> = (0..t.num_rows()).map(|_| "diffuse".to_string()).collect();
        kinds[3] = "plasma".into();
        cols[k] = Arc::new(StringArray::from(kinds));
        let bad = RecordBatch::try_new(t.schema(), cols).unwrap();
        let e = Scene::from_triangles_table("x", &bad, s.camera).unwrap_err().to_string();
        assert!(e.contains("row 3") && e.contains("plasma"), "{e}");
        assert!(load_scene("nope", None, 1).unwrap_err().to_string().contains("unknown scene"));
    }
}
