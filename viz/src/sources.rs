//! What the components draw from: a dataset (its rays from the store, its scene tables, camera
//! and image, and with the `sql` feature a SQL session over it) or a scene with no dataset at all.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use arrow::array::RecordBatch;
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
    pub dataset: Option<Arc<Dataset>>,
    /// The SQL session over the dataset, made on the first query.
    sql: std::sync::OnceLock<sql::Sql>,
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

/// The SQL session (DataFusion) over a dataset: only with the `sql` feature.
#[cfg(feature = "sql")]
mod sql {
    use std::path::Path;

    use arrow::array::RecordBatch;
    use datafusion::prelude::SessionContext;
    use futures::StreamExt;

    use crate::{Error, Result};

    pub struct Sql {
        pub ctx: SessionContext,
        runtime: tokio::runtime::Runtime,
    }

    impl Sql {
        pub fn open(dir: &Path) -> Result<Sql> {
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .worker_threads(std::thread::available_parallelism().map_or(2, |n| n.get()).min(8))
                .enable_all()
                .build()
                .map_err(|e| Error::Settings(format!("cannot start the query runtime: {e}")))?;
            let src = query::TraceSource { name: "trace".into(), path: dir.to_path_buf() };
            let ctx = runtime.block_on(query::session(&[src]))?;
            Ok(Sql { ctx, runtime })
        }

        pub fn query_batches(&self, sql: &str, each: &mut dyn FnMut(&RecordBatch) -> Result<()>) -> Result<()> {
            let opts = datafusion::execution::context::SQLOptions::new()
                .with_allow_ddl(false)
                .with_allow_dml(false)
                .with_allow_statements(false);
            self.runtime.block_on(async {
                let df = self.ctx.sql_with_options(sql, opts).await?;
                let mut stream = df.execute_stream().await?;
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
    use std::path::Path;

    use arrow::array::RecordBatch;

    use crate::{Error, Result};

    pub struct Sql;

    impl Sql {
        pub fn open(_dir: &Path) -> Result<Sql> {
            Err(Error::NoSql)
        }

        pub fn query_batches(&self, _sql: &str, _each: &mut dyn FnMut(&RecordBatch) -> Result<()>) -> Result<()> {
            Err(Error::NoSql)
        }
    }
}

fn scene_bounds(scene: &Scene) -> ([f64; 3], [f64; 3]) {
    let (lo, hi) = scene.bounds();
    (lo.to_array().map(f64::from), hi.to_array().map(f64::from))
}

impl Sources {
    /// Opens a dataset directory. A dataset recorded before scenes and cameras were stored
    /// opens too: what it lacks is listed in `missing`.
    pub fn open(dir: &Path) -> Result<Sources> {
        let ds = Arc::new(Dataset::open(dir)?);
        let m = ds.manifest();
        let mut missing = Vec::new();
        let cam = CameraAttrs::from_attributes(&m.attributes).map_err(|message| Error::File {
            what: "the dataset's camera attributes",
            path: dir.join("manifest.json"),
            message,
        })?;
        let (camera, image_size) = match cam {
            Some(c) => (Some(ViewCamera::from_attrs(&c)), [c.width, c.height]),
            None => {
                missing.push("no camera attributes (recorded before they were stored): a camera framing the scene is used, the image cannot be registered".into());
                let w = m.attributes.get(attr::WIDTH).and_then(|s| s.parse().ok()).unwrap_or(512);
                let h = m.attributes.get(attr::HEIGHT).and_then(|s| s.parse().ok()).unwrap_or(512);
                (None, [w, h])
            }
        };
        let scene = match ds.table(TRIANGLES_TABLE)? {
            Some(t) => {
                let c = camera.map_or(
                    Camera { position: glam::Vec3A::ZERO, target: glam::Vec3A::Z, up: glam::Vec3A::Y, fov_y: 40.0 },
                    |c| Camera {
                        position: glam::DVec3::from_array(c.position).as_vec3a(),
                        target: glam::DVec3::from_array(c.target).as_vec3a(),
                        up: glam::DVec3::from_array(c.up).as_vec3a(),
                        fov_y: c.fov_y as f32,
                    },
                );
                let name = m.attributes.get("scene").cloned().unwrap_or_else(|| "dataset".into());
                Some(Arc::new(Scene::from_triangles_table(&name, &t, c)?))
            }
            None => {
                missing.push("no triangles table: the geometry and composition layers are not available".into());
                None
            }
        };
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
        let bounds = match &scene {
            Some(s) => Some(scene_bounds(s)),
            None => {
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
                (lo[0] <= hi[0]).then_some((lo, hi))
            }
        };
        let has_bvh_nodes = m.tables.contains_key(BVH_NODES_TABLE);
        let has_ray_nodes = m.tables.contains_key(RAY_NODES_TABLE);
        if !has_ray_nodes {
            missing.push(
                "no ray_nodes table (record with --record-visits): BVH boxes cannot be limited to visited nodes".into(),
            );
        }
        let name = m.attributes.get("scene").cloned().unwrap_or_else(|| dir.display().to_string());
        Ok(Sources {
            name,
            dir: Some(dir.to_path_buf()),
            dataset: Some(ds.clone()),
            sql: std::sync::OnceLock::new(),
            scene,
            camera,
            image_size,
            picture,
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

    /// The SQL session over the dataset (made on first use).
    fn sql(&self) -> Result<&sql::Sql> {
        let Some(dir) = &self.dir else {
            return Err(Error::Settings("no dataset is loaded, so there is nothing to query".into()));
        };
        if let Some(s) = self.sql.get() {
            return Ok(s);
        }
        let s = sql::Sql::open(dir)?;
        Ok(self.sql.get_or_init(|| s))
    }

    /// The SQL session over the dataset (tables `rays`, `trees`, `bvh_nodes`, ...).
    #[cfg(feature = "sql")]
    pub fn session(&self) -> Result<&datafusion::prelude::SessionContext> {
        Ok(&self.sql()?.ctx)
    }

    /// Whether this build can run SQL (the `sql` feature) and there is a dataset to query.
    pub fn can_query(&self) -> Result<(), String> {
        if !cfg!(feature = "sql") {
            return Err(Error::NoSql.to_string());
        }
        if self.dataset.is_none() {
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
