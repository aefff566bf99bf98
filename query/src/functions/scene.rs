//! What the scene-dependent functions (`aims_at_light`, `morton3`) know of a dataset's scene.

use arrow::array::{AsArray, RecordBatch};
use arrow::datatypes::Float32Type;
use store::Dataset;

use crate::Result;

/// What scene-dependent functions know about the scene.
#[derive(Clone, Debug, Default)]
pub struct SceneContext {
    /// Bounds of the finite origins and hit points, when any.
    pub bounds: Option<([f64; 3], [f64; 3])>,
    /// Emitter triangles (v0, v1, v2).
    pub lights: Vec<[[f64; 3]; 3]>,
}

impl SceneContext {
    /// The scene of a dataset: bounds from its statistics, emitters from its `lights` table
    /// (`Dataset::table` has checked it against `store::scene::lights_schema`).
    pub fn of(ds: &Dataset) -> Result<Self> {
        let lights = ds.table(store::scene::LIGHTS_TABLE)?;
        Self::from_parts(ds.stats(), lights.as_ref(), &ds.dir().display().to_string())
    }

    /// The scene from a trace's statistics and its `lights` table, if any (`place` names the
    /// trace in errors).
    pub fn from_parts(stats: &store::Stats, lights_table: Option<&RecordBatch>, place: &str) -> Result<Self> {
        let (o, h) = (&stats.origin_bounds, &stats.hit_bounds);
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for b in [o, h] {
            if !b.is_empty() {
                for k in 0..3 {
                    lo[k] = lo[k].min(f64::from(b.min[k]));
                    hi[k] = hi[k].max(f64::from(b.max[k]));
                }
            }
        }
        let bounds = (lo[0] <= hi[0]).then_some((lo, hi));
        let mut lights = Vec::new();
        if let Some(batch) = lights_table {
            let mut cols = Vec::with_capacity(9);
            for name in store::scene::col::VERTEX.iter().flatten() {
                let c = batch.column_by_name(name).and_then(|c| c.as_primitive_opt::<Float32Type>().cloned());
                cols.push(c.ok_or_else(|| store::Error::Table {
                    name: store::scene::LIGHTS_TABLE.into(),
                    path: place.into(),
                    message: format!("column `{name}` is missing or not Float32"),
                })?);
            }
            for r in 0..batch.num_rows() {
                let p = |v: usize| [0, 1, 2].map(|a| f64::from(cols[v * 3 + a].value(r)));
                lights.push([p(0), p(1), p(2)]);
            }
        }
        Ok(Self { bounds, lights })
    }
}
