//! What Python's keyword arguments say, checked before anything runs: an analysis and its
//! options, a render request, a payload column's type (`f32`, `u32x4`, ...).

use arrow::datatypes::DataType;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use query::Engine;
use rl::PayloadField;

use crate::work::{QueryError, RenderError, record_err};

/// An analysis and its options, checked before it runs.
pub(crate) enum Analysis {
    Coherence(query::analyze::CoherenceOptions),
    Bvh(u16),
    Numerics,
    Diff { a: String, b: String, tile: usize },
}

impl Analysis {
    pub(crate) fn parse(name: &str, o: &Bound<'_, PyDict>, engine: &Engine) -> PyResult<Analysis> {
        let get = |key: &str| o.get_item(key).ok().flatten().filter(|v| !v.is_none());
        let a = match name {
            "coherence" => {
                let mut c = query::analyze::CoherenceOptions::default();
                if let Some(w) = get("width") {
                    c.width = w.extract()?;
                    if !(1..=1024).contains(&c.width) {
                        return Err(QueryError::new_err(format!("coherence: width {} is not in 1..=1024", c.width)));
                    }
                }
                if let Some(v) = get("orders") {
                    c.orders = v.extract()?;
                }
                if let Some(v) = get("kind") {
                    c.kind = Some(v.extract()?);
                }
                Analysis::Coherence(c)
            }
            "bvh" => Analysis::Bvh(get("level").map(|v| v.extract()).transpose()?.unwrap_or(3)),
            "numerics" | "bugs" => Analysis::Numerics,
            "diff" => {
                let names: Vec<String> = engine.datasets().iter().map(|d| d.name.clone()).collect();
                let pick = |v: Option<Bound<'_, PyAny>>, i: usize| -> PyResult<String> {
                    match v {
                        Some(v) => v.extract(),
                        None => names.get(i).cloned().ok_or_else(|| {
                            QueryError::new_err(
                                "diff compares two datasets: open two (rtvtk.open([a, b])) or name them with a=, b=",
                            )
                        }),
                    }
                };
                let a = pick(get("a"), 0)?;
                let b = pick(get("b"), 1)?;
                let tile = get("tile").map(|v| v.extract()).transpose()?.unwrap_or(16usize).max(1);
                Analysis::Diff { a, b, tile }
            }
            other => {
                return Err(QueryError::new_err(format!(
                    "unknown analysis {other:?}: expected coherence, bvh, numerics (or bugs) or diff"
                )));
            }
        };
        let known: &[&str] = match name {
            "coherence" => &["width", "orders", "kind"],
            "bvh" => &["level"],
            "diff" => &["a", "b", "tile"],
            _ => &[],
        };
        for k in o.keys() {
            let k: String = k.extract()?;
            if !known.contains(&k.as_str()) {
                return Err(QueryError::new_err(format!("analyze {name}: unknown option {k:?} (it takes {known:?})")));
            }
        }
        Ok(a)
    }

    pub(crate) async fn run(&self, engine: &Engine) -> query::Result<query::analyze::Report> {
        use query::analyze;
        match self {
            Analysis::Coherence(o) => analyze::coherence(engine, o).await,
            Analysis::Bvh(level) => analyze::bvh(engine, *level).await,
            Analysis::Numerics => analyze::numerics(engine).await,
            Analysis::Diff { a, b, tile } => analyze::diff(engine, a, b, *tile).await,
        }
    }
}

/// `camera=((x, y, z), (x, y, z), fov_y)`: position, target, vertical field of view in degrees.
pub(crate) type CameraArg = ((f64, f64, f64), (f64, f64, f64), f64);

/// A render request from Python keyword arguments (unknown names are refused, naming them).
pub(crate) fn render_request(o: &Bound<'_, PyDict>) -> PyResult<rtvtk_viz::headless::RenderRequest> {
    let mut r = rtvtk_viz::headless::RenderRequest::default();
    for (k, v) in o.iter() {
        let key: String = k.extract()?;
        match key.as_str() {
            "layers" => r.layers = v.extract()?,
            "sql" => r.sql = v.extract()?,
            "colour_by" | "color_by" => r.colour_by = v.extract()?,
            "tree" => r.tree = v.extract()?,
            "pixel" => r.pixel = v.extract::<Option<(u32, u32)>>()?.map(|(x, y)| [x, y]),
            "sample" => r.sample = v.extract()?,
            "kinds" => r.kinds = v.extract()?,
            "depth" => r.depth = v.extract::<Option<(u32, u32)>>()?.map(|(a, b)| [a, b]),
            "max_rays" => r.max_rays = v.extract()?,
            "bvh_levels" => r.bvh_levels = v.extract::<Option<(u32, u32)>>()?.map(|(a, b)| [a, b]),
            "bvh_visited" => r.bvh_visited = v.extract()?,
            "geometry" => r.geometry = v.extract()?,
            "size" => r.size = v.extract::<Option<(u32, u32)>>()?.map(|(w, h)| [w, h]),
            "line_width" => r.line_width = v.extract()?,
            "image_source" => r.image_source = v.extract()?,
            "image_spp" => r.image_spp = v.extract()?,
            "legend" => r.legend = v.extract()?,
            "style" => {
                let name: String = v.extract()?;
                r.style = name.parse().map_err(RenderError::new_err)?;
            }
            "opacity" => r.opacity = v.extract()?,
            "density_scale" => {
                let name: String = v.extract()?;
                r.density_scale = name.parse().map_err(RenderError::new_err)?;
            }
            "density_map" => r.density_map = v.extract()?,
            "map" | "colour_map" | "color_map" => r.map = v.extract()?,
            "camera" => {
                let c: Option<CameraArg> = v.extract()?;
                r.camera = match c {
                    Some((p, t, fov)) => {
                        let c = rtvtk_viz::ViewCamera {
                            position: [p.0, p.1, p.2],
                            target: [t.0, t.1, t.2],
                            up: [0.0, 1.0, 0.0],
                            fov_y: fov,
                        };
                        c.validate().map_err(|e| RenderError::new_err(e.to_string()))?;
                        Some(c)
                    }
                    None => None,
                };
            }
            other => return Err(RenderError::new_err(format!("render: unknown option {other:?}"))),
        }
    }
    Ok(r)
}

/// `f32`, `u32x4`, ...: a payload column's declaration.
pub(crate) fn describe_field(f: &PayloadField) -> String {
    let t = match f.element {
        DataType::Boolean => "bool",
        DataType::Int8 => "i8",
        DataType::Int16 => "i16",
        DataType::Int32 => "i32",
        DataType::Int64 => "i64",
        DataType::UInt8 => "u8",
        DataType::UInt16 => "u16",
        DataType::UInt32 => "u32",
        DataType::UInt64 => "u64",
        DataType::Float32 => "f32",
        DataType::Float64 => "f64",
        _ => "?",
    };
    match f.list_len {
        Some(n) => format!("{t}x{n}"),
        None => t.to_string(),
    }
}

/// The payload column `name` declared as `spec` (`f32`, `f32x3`, `u32`, `i64`, `f64x4`, ...).
pub(crate) fn parse_field(name: &str, spec: &str) -> PyResult<PayloadField> {
    let (t, n) = match spec.split_once('x') {
        Some((t, n)) => {
            let n: usize = n.parse().ok().filter(|n| *n >= 1).ok_or_else(|| {
                record_err(format!("payload {name:?}: {spec:?}: expected TYPE or TYPExN with N >= 1 (f32x3)"))
            })?;
            (t, Some(n))
        }
        None => (spec, None),
    };
    let element = match t {
        "f32" => DataType::Float32,
        "f64" => DataType::Float64,
        "i32" => DataType::Int32,
        "i64" => DataType::Int64,
        "u8" => DataType::UInt8,
        "u16" => DataType::UInt16,
        "u32" => DataType::UInt32,
        "u64" => DataType::UInt64,
        _ => {
            return Err(record_err(format!(
                "payload {name:?}: type {t:?} is not one of f32, f64, i32, i64, u8, u16, u32, u64 (with xN for N per ray)"
            )));
        }
    };
    Ok(PayloadField { name: name.to_string(), element, list_len: n })
}
