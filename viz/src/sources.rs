//! What the components draw from: a dataset (its rays from the store, its scene tables, camera
//! and image, and with the `sql` feature a SQL session over it) or a scene with no dataset at all.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::RecordBatch;
#[cfg(feature = "sql")]
use arrow::array::{Array, AsArray};
use renderers::{Camera, Scene};
use store::Dataset;
use store::scene::{BVH_NODES_TABLE, CameraAttrs, RAY_NODES_TABLE, TRIANGLES_TABLE, attr};

use crate::camera::Frame;
use crate::camera::ViewCamera;
use crate::{Error, Result};

/// The path-traced picture of a dataset, tone mapped (RGBA8, rows top to bottom).
#[derive(Clone)]
pub struct Picture {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

/// Everything a pipeline can draw.
pub struct Sources {
    pub name: String,
    pub dir: Option<PathBuf>,
    /// The dataset, where this process reads it (not for a service's client).
    pub dataset: Option<Arc<Dataset>>,
    /// The SQL engine over the dataset: given (the viewer's, a service's client), or made on the
    /// first query over the same open dataset.
    sql: std::sync::OnceLock<sql::Sql>,
    /// The dataset's name in the engine (`None`: the unqualified tables).
    table_schema: Option<String>,
    /// The scene (from the `triangles` table, or built in).
    pub scene: Option<Arc<Scene>>,
    /// The camera and image size the dataset was rendered with.
    pub camera: Option<ViewCamera>,
    pub image_size: [u32; 2],
    pub picture: Option<Picture>,
    /// Scene bounds (triangles, else ray origins and hit points).
    pub bounds: Option<([f64; 3], [f64; 3])>,
    pub has_bvh_nodes: bool,
    pub has_ray_nodes: bool,
    /// What the dataset lacks, in words (`no triangles table: ...`).
    pub missing: Vec<String>,
}

/// The SQL engine over a dataset: only with the `sql` feature.
#[cfg(feature = "sql")]
mod sql {
    use std::sync::Arc;

    use arrow::array::RecordBatch;
    use futures::StreamExt;
    use store::Dataset;

    use crate::Result;

    pub struct Sql {
        pub engine: Arc<query::Engine>,
    }

    impl Sql {
        /// An in-process engine over the dataset this process has open (the same `Arc`).
        pub fn over(dataset: &Arc<Dataset>) -> Result<Sql> {
            let datasets = vec![query::Registered { name: "trace".into(), dataset: dataset.clone() }];
            let engine = query::Engine::blocking(query::Engine::with_datasets(datasets, &Default::default()))?;
            Ok(Sql { engine: Arc::new(engine) })
        }

        pub fn query_batches(&self, sql: &str, each: &mut dyn FnMut(&RecordBatch) -> Result<()>) -> Result<()> {
            self.engine.block_on(async {
                let mut stream = self.engine.stream(sql).await?;
                while let Some(b) = stream.next().await {
                    each(&b?)?;
                }
                Ok(())
            })
        }
    }
}

/// Built without the `sql` feature: no SQL engine, and every query says so.
#[cfg(not(feature = "sql"))]
mod sql {
    use std::sync::Arc;

    use arrow::array::RecordBatch;
    use store::Dataset;

    use crate::{Error, Result};

    pub struct Sql;

    impl Sql {
        pub fn over(_dataset: &Arc<Dataset>) -> Result<Sql> {
            Err(Error::NoSql)
        }

        pub fn query_batches(&self, _sql: &str, _each: &mut dyn FnMut(&RecordBatch) -> Result<()>) -> Result<()> {
            Err(Error::NoSql)
        }
    }
}

/// What a dataset holds beyond its rays, however it is read (from its directory, or through a
/// query engine).
struct Parts {
    attributes: std::collections::BTreeMap<String, String>,
    triangles: Option<RecordBatch>,
    picture: Option<Picture>,
    tables: Vec<String>,
}

fn scene_bounds(scene: &Scene) -> ([f64; 3], [f64; 3]) {
    let (lo, hi) = scene.bounds();
    (lo.to_array().map(f64::from), hi.to_array().map(f64::from))
}

/// What `missing` says of a broken `triangles` table (`store::unavailable`'s subject).
const SCENE_UNAVAILABLE: &str = "the scene's `triangles` table";

impl Sources {
    /// Opens a dataset directory. A dataset recorded before scenes and cameras were stored
    /// opens too: what it lacks is listed in `missing`.
    pub fn open(dir: &Path) -> Result<Sources> {
        Sources::of_dataset(Arc::new(Dataset::open(dir)?))
    }

    /// The sources of a dataset already open (the one `Arc` an engine registered, too).
    pub fn of_dataset(ds: Arc<Dataset>) -> Result<Sources> {
        let dir = ds.dir().to_path_buf();
        let m = ds.manifest();
        let mut missing = Vec::new();
        let picture = match m.attributes.get(attr::IMAGE_PNG) {
            Some(rel) => {
                let p = dir.join(rel);
                if p.exists() {
                    Some(load_png(&p)?)
                } else {
                    missing.push(format!("the image {} named by the manifest is missing", p.display()));
                    None
                }
            }
            None => {
                let p = dir.join("image.png");
                if p.exists() {
                    Some(load_png(&p)?)
                } else {
                    missing.push("no rendered image: the image layer needs a scene to trace".into());
                    None
                }
            }
        };
        // A broken `triangles` table costs the layers that draw the scene, named in `missing`;
        // the rays and the other layers draw.
        let triangles = ds.table(TRIANGLES_TABLE).unwrap_or_else(|e| {
            missing.push(store::unavailable(SCENE_UNAVAILABLE, e));
            None
        });
        let parts =
            Parts { attributes: m.attributes.clone(), triangles, picture, tables: m.tables.keys().cloned().collect() };
        let fallback = || {
            let st = ds.stats();
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            for b in [&st.origin_bounds, &st.hit_bounds] {
                if !b.is_empty() {
                    for k in 0..3 {
                        lo[k] = lo[k].min(f64::from(b.min[k]));
                        hi[k] = hi[k].max(f64::from(b.max[k]));
                    }
                }
            }
            Ok((lo[0] <= hi[0]).then_some((lo, hi)))
        };
        let mut s = Sources::assemble(dir.display().to_string(), parts, missing, fallback)?;
        s.dir = Some(dir);
        s.dataset = Some(ds);
        Ok(s)
    }

    /// The sources of a dataset read through a query engine: `engine`'s dataset `name` (`None`:
    /// its first, the unqualified tables). Where the engine has the dataset open in this process
    /// it is read from there (rays straight from the store); a service's client reads the
    /// scene, camera and rays through SQL (the recorded picture is not served: the image layer
    /// traces the view).
    #[cfg(feature = "sql")]
    pub fn with_engine(engine: Arc<query::Engine>, name: Option<&str>) -> Result<Sources> {
        if let Some(ds) = engine.dataset(name) {
            let mut s = Sources::of_dataset(ds)?;
            s.table_schema = name.map(String::from);
            let _ = s.sql.set(sql::Sql { engine });
            return Ok(s);
        }
        let prefix = name.map_or(String::new(), |n| format!("{n}."));
        let sql = sql::Sql { engine: engine.clone() };
        let collect = |q: &str| -> Result<Vec<RecordBatch>> {
            let mut out = Vec::new();
            sql.query_batches(q, &mut |b| {
                out.push(b.clone());
                Ok(())
            })?;
            Ok(out)
        };
        let catalog = engine.block_on(engine.catalog())?;
        let in_schema = |t: &str| match name {
            Some(n) => t.strip_prefix(&format!("{n}.")).map(String::from),
            None => (!t.contains('.')).then(|| t.to_string()),
        };
        let tables: Vec<String> = catalog.tables.iter().filter_map(|t| in_schema(t)).collect();
        if !tables.iter().any(|t| t == "rays") {
            return Err(Error::Settings(format!(
                "{} has no dataset {}: its tables are {}",
                engine.describe(),
                name.unwrap_or("(unqualified)"),
                catalog.tables.join(", ")
            )));
        }
        let mut attributes = std::collections::BTreeMap::new();
        if tables.iter().any(|t| t == query::ATTRIBUTES_TABLE) {
            for b in collect(&format!("SELECT key, value FROM {prefix}{}", query::ATTRIBUTES_TABLE))? {
                let k = arrow::compute::cast(b.column(0), &arrow::datatypes::DataType::Utf8)?;
                let v = arrow::compute::cast(b.column(1), &arrow::datatypes::DataType::Utf8)?;
                let (k, v) = (k.as_string::<i32>(), v.as_string::<i32>());
                for i in 0..b.num_rows() {
                    attributes.insert(k.value(i).to_string(), v.value(i).to_string());
                }
            }
        }
        let mut missing = vec![format!(
            "the recorded picture is not served by {}: the image layer traces the view",
            engine.describe()
        )];
        let triangles = if tables.iter().any(|t| t == TRIANGLES_TABLE) {
            match collect(&format!("SELECT * FROM {prefix}{TRIANGLES_TABLE}")) {
                Ok(batches) => {
                    let schema = batches.first().map(|b| b.schema()).unwrap_or_else(store::scene::triangles_schema);
                    Some(arrow::compute::concat_batches(&schema, &batches)?)
                }
                // A broken table on the server costs the scene's layers alone, as it does here.
                Err(e) => {
                    missing.push(store::unavailable(SCENE_UNAVAILABLE, e));
                    None
                }
            }
        } else {
            None
        };
        let parts = Parts { attributes, triangles, picture: None, tables };
        let fallback = || {
            let b = collect(&format!(
                "SELECT min(origin_x), min(origin_y), min(origin_z), max(origin_x), max(origin_y), max(origin_z) \
                 FROM {prefix}rays"
            ))?;
            let v: Vec<f64> = match b.first() {
                Some(b) if b.num_rows() == 1 => (0..6)
                    .map(|i| {
                        let c = arrow::compute::cast(b.column(i), &arrow::datatypes::DataType::Float64)?;
                        let c = c.as_primitive::<arrow::datatypes::Float64Type>();
                        Ok(if c.is_null(0) { f64::NAN } else { c.value(0) })
                    })
                    .collect::<Result<_>>()?,
                _ => return Ok(None),
            };
            Ok((v[0] <= v[3]).then_some(([v[0], v[1], v[2]], [v[3], v[4], v[5]])))
        };
        let mut s = Sources::assemble(engine.describe(), parts, missing, fallback)?;
        s.table_schema = name.map(String::from);
        let _ = s.sql.set(sql);
        Ok(s)
    }

    /// Sources from a dataset's parts; `fallback` gives the bounds when there are no triangles.
    fn assemble(
        describe: String,
        parts: Parts,
        mut missing: Vec<String>,
        fallback: impl FnOnce() -> Result<Option<([f64; 3], [f64; 3])>>,
    ) -> Result<Sources> {
        let attrs = &parts.attributes;
        let cam = CameraAttrs::from_attributes(attrs).map_err(|message| Error::File {
            what: "the dataset's camera attributes",
            path: PathBuf::from(&describe).join("manifest.json"),
            message,
        })?;
        let (camera, image_size) = match cam {
            Some(c) => (Some(ViewCamera::from_attrs(&c)), [c.width, c.height]),
            None => {
                missing.push("no camera attributes (recorded before they were stored): a camera framing the scene is used, the image cannot be registered".into());
                let w = attrs.get(attr::WIDTH).and_then(|s| s.parse().ok()).unwrap_or(512);
                let h = attrs.get(attr::HEIGHT).and_then(|s| s.parse().ok()).unwrap_or(512);
                (None, [w, h])
            }
        };
        let scene = match &parts.triangles {
            Some(t) => {
                let c = camera.as_ref().map_or(
                    Camera { position: glam::Vec3A::ZERO, target: glam::Vec3A::Z, up: glam::Vec3A::Y, fov_y: 40.0 },
                    Camera::from,
                );
                let name = attrs.get("scene").cloned().unwrap_or_else(|| "dataset".into());
                Some(Arc::new(Scene::from_triangles_table(&name, t, c)?))
            }
            // A broken table has said why in `missing` already.
            None if parts.tables.iter().any(|t| t == TRIANGLES_TABLE) => None,
            None => {
                missing.push("no triangles table: the geometry and composition layers are not available".into());
                None
            }
        };
        let bounds = match &scene {
            Some(s) => Some(scene_bounds(s)),
            None => fallback()?,
        };
        let has_bvh_nodes = parts.tables.iter().any(|t| t == BVH_NODES_TABLE);
        let has_ray_nodes = parts.tables.iter().any(|t| t == RAY_NODES_TABLE);
        if !has_ray_nodes {
            missing.push(
                "no ray_nodes table (record with --record-visits): BVH boxes cannot be limited to visited nodes".into(),
            );
        }
        Ok(Sources {
            name: attrs.get("scene").cloned().unwrap_or(describe),
            dir: None,
            dataset: None,
            sql: std::sync::OnceLock::new(),
            table_schema: None,
            scene,
            camera,
            image_size,
            picture: parts.picture,
            bounds,
            has_bvh_nodes,
            has_ray_nodes,
            missing,
        })
    }

    /// A scene with no dataset (immediate mode, tests): its camera, no rays, no image.
    pub fn from_scene(scene: Scene, width: u32, height: u32) -> Result<Sources> {
        let c = scene.camera;
        let d = |v: glam::Vec3A| v.to_array().map(f64::from);
        let camera =
            ViewCamera { position: d(c.position), target: d(c.target), up: d(c.up), fov_y: f64::from(c.fov_y) };
        Ok(Sources {
            name: scene.name.clone(),
            dir: None,
            dataset: None,
            sql: std::sync::OnceLock::new(),
            table_schema: None,
            bounds: Some(scene_bounds(&scene)),
            scene: Some(Arc::new(scene)),
            camera: Some(camera),
            image_size: [width, height],
            picture: None,
            has_bvh_nodes: false,
            has_ray_nodes: false,
            missing: vec!["no dataset: no rays, BVH or query layers".into()],
        })
    }

    /// The camera to start with: the dataset's, else one framing the bounds.
    pub fn initial_camera(&self) -> ViewCamera {
        self.camera.unwrap_or_else(|| match self.bounds {
            Some((lo, hi)) => ViewCamera::framing(lo, hi, 40.0),
            None => ViewCamera { position: [0.0, 0.0, -5.0], target: [0.0; 3], up: [0.0, 1.0, 0.0], fov_y: 40.0 },
        })
    }

    /// The frame positions are drawn in: anchored at the bounds' centre.
    pub fn frame(&self) -> Frame {
        match self.bounds {
            Some((lo, hi)) => {
                let c = [0, 1, 2].map(|k| (lo[k] + hi[k]) * 0.5);
                let r = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt() * 0.5;
                Frame { anchor: c, radius: r.max(1e-9) }
            }
            None => Frame { anchor: [0.0; 3], radius: 1.0 },
        }
    }

    /// The SQL engine over the dataset (given, or made on first use over the open dataset).
    fn sql(&self) -> Result<&sql::Sql> {
        if let Some(s) = self.sql.get() {
            return Ok(s);
        }
        let Some(ds) = &self.dataset else {
            return Err(Error::Settings("no dataset is loaded, so there is nothing to query".into()));
        };
        let s = sql::Sql::over(ds)?;
        Ok(self.sql.get_or_init(|| s))
    }

    /// The engine the SQL layers ask (made on first use over the open dataset).
    #[cfg(feature = "sql")]
    pub fn engine(&self) -> Result<Arc<query::Engine>> {
        Ok(self.sql()?.engine.clone())
    }

    /// Whether there are recorded rays to draw: a dataset open here, or one a service serves.
    pub fn has_rays(&self) -> bool {
        self.dataset.is_some() || self.sql.get().is_some()
    }

    /// Why the dataset has no scene (its `triangles` table missing, or broken and why): what the
    /// layers that draw the scene say instead of drawing.
    pub fn why_no_scene(&self) -> String {
        self.missing
            .iter()
            .find(|m| m.starts_with(SCENE_UNAVAILABLE))
            .cloned()
            .unwrap_or_else(|| "the dataset has no triangles table (recorded before scenes were stored)".into())
    }

    /// The name of one of the dataset's tables in its engine (`rays`, `NAME.rays`).
    pub fn table(&self, table: &str) -> String {
        match &self.table_schema {
            Some(n) => format!("{n}.{table}"),
            None => table.to_string(),
        }
    }

    /// Whether this build can run SQL (the `sql` feature) and there is a dataset to query.
    pub fn can_query(&self) -> Result<(), String> {
        if !cfg!(feature = "sql") {
            return Err(Error::NoSql.to_string());
        }
        if !self.has_rays() {
            return Err("no dataset".into());
        }
        Ok(())
    }

    /// Runs a read-only query and hands its record batches to `each` as they arrive (the result
    /// is never held whole).
    pub fn query_batches(&self, sql: &str, mut each: impl FnMut(&RecordBatch) -> Result<()>) -> Result<()> {
        self.sql()?.query_batches(sql, &mut each)
    }

    /// Runs a query and collects its result (small results: tables, heatmaps).
    pub fn query(&self, sql: &str) -> Result<Vec<RecordBatch>> {
        let mut out = Vec::new();
        self.query_batches(sql, |b| {
            out.push(b.clone());
            Ok(())
        })?;
        Ok(out)
    }
}

fn load_png(path: &Path) -> Result<Picture> {
    let img = image::open(path)
        .map_err(|e| Error::File { what: "the dataset's image", path: path.into(), message: e.to_string() })?
        .to_rgba8();
    Ok(Picture { width: img.width(), height: img.height(), rgba: img.into_raw() })
}
