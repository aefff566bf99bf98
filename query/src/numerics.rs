//! The numerical health checks of a trace as one SQL view, `numerics`: a row per offending ray
//! and check (`problem`), with the ray's tree, pixel, depth, kind, origin, direction and `t`, so
//! the viewer's query layer draws them in scene space and a notebook filters them like any table
//! (`SELECT * FROM numerics WHERE problem = 'self_hit'`). `analyze numerics` reports on it.
//!
//! The definitions, their tolerances and the float-error reasoning are in `query/README.md`
//! ("Numerical health"); [`CHECKS`] is the list the report and that section follow.

use arrow::datatypes::{DataType, Schema};
use datafusion::prelude::SessionContext;

use crate::Result;

/// One check of the `numerics` view.
#[derive(Clone, Copy, Debug)]
pub struct Check {
    /// The `problem` value of its rows.
    pub name: &'static str,
    /// What it finds, in a line.
    pub title: &'static str,
    /// Whether a finding is a bug (fireflies are the estimator's variance, reported apart).
    pub bug: bool,
}

/// Every check, in report order.
pub const CHECKS: [Check; 8] = [
    Check { name: "non_finite", title: "NaN or infinite origin, direction, t or float payload", bug: true },
    Check { name: "bad_direction", title: "zero or non-unit direction", bug: true },
    Check {
        name: "self_hit",
        title: "hits the primitive its parent hit, closer than the float error bound",
        bug: true,
    },
    Check {
        name: "detached_origin",
        title: "starts off its parent's hit point by more than the float error bound",
        bug: true,
    },
    Check {
        name: "leak",
        title: "starts behind a surface, or passes through one before its recorded hit (replayed)",
        bug: true,
    },
    Check { name: "energy", title: "throughput grows across a bounce beyond the BSDF's bound", bug: true },
    Check { name: "wrong_shadow", title: "shadow ray aiming at no emitter (the paper's Figure 1 bug)", bug: true },
    Check { name: "firefly", title: "a sample above 10x its pixel's median and the image mean (variance)", bug: false },
];

/// The relative float error bound the checks allow: 2^-12 of a point's largest coordinate
/// (about 2,000 ULPs of f32).
pub const REL_BOUND: f64 = 1.0 / 4096.0;
/// The coordinate magnitude below which the bound stops shrinking: within 1/32 of the origin
/// Wächter and Binder's offset (and `offset_point`) moves by an absolute 2^-16 per coordinate,
/// so the bound's floor, 2^-12 · 2^-2 = 2^-14, is four times that step.
pub const NEAR_ORIGIN: f64 = 0.25;
/// How far a direction's length may be from 1.
pub const UNIT_TOLERANCE: f64 = 1e-3;
/// Throughput may exceed its parent's (or 1, after Russian roulette) by this factor.
pub const ENERGY_SLACK: f64 = 1.1;
/// The radiance scaling a transmission may add: (eta_t / eta_i)^2 up to an index ratio of 2.
pub const TRANSMISSION_BOUND: f64 = 4.0;
/// A firefly is above this many times its pixel's median and the image's mean.
pub const FIREFLY_K: f64 = 10.0;

/// Whether a dataset has a table the checks read, and whether it can be read.
#[derive(Clone, Debug, PartialEq)]
pub enum Presence {
    /// The recording wrote no such table.
    Absent,
    /// It is there but cannot be read (the reason, naming the table).
    Broken(String),
    /// It is there and sound.
    Present,
}

impl Presence {
    /// The presence of `table` in `ds` (its schema read and its file checked whole, once per
    /// process: a table a check reads is a table whose checksum is verified).
    pub fn of(ds: &store::Dataset, table: &str) -> Self {
        match ds.verify_table(table) {
            Ok(false) => Self::Absent,
            Ok(true) => Self::Present,
            Err(e) => Self::Broken(e.to_string()),
        }
    }

    /// Why a check that needs this table cannot run (None when it can).
    fn missing(&self, table: &str) -> Option<String> {
        match self {
            Self::Absent => Some(format!("the trace has no `{table}` table")),
            Self::Broken(why) => Some(store::unavailable(&format!("the `{table}` table"), why)),
            Self::Present => None,
        }
    }
}

/// What the view of one dataset can check.
#[derive(Clone, Debug)]
pub struct Scope {
    /// The session's scene functions (`aims_at_light`, `scene_hit`) are this dataset's.
    pub scene: bool,
    /// Its `lights` table.
    pub lights: Presence,
    /// Its `triangles` table.
    pub triangles: Presence,
}

/// The checks a dataset with `rays` schema `schema` and `scope` can run, and for the others why
/// not.
pub fn available(schema: &Schema, scope: &Scope) -> Vec<(Check, Option<String>)> {
    let has = |c: &str| schema.column_with_name(c).is_some();
    let scene = |p: &Presence, table: &str| match p.missing(table) {
        Some(why) => Some(why),
        None if !scope.scene => Some("the session's scene functions are another dataset's".to_string()),
        None => None,
    };
    CHECKS
        .iter()
        .map(|c| {
            let missing = match c.name {
                "self_hit" | "detached_origin" if !has("prim") => Some("the rays record no `prim`".to_string()),
                "leak" => scene(&scope.triangles, store::scene::TRIANGLES_TABLE),
                "energy" if float_parts(schema, "throughput").is_empty() => {
                    Some("the rays record no `throughput`".to_string())
                }
                "wrong_shadow" => scene(&scope.lights, store::scene::LIGHTS_TABLE),
                "firefly" if float_parts(schema, "radiance").is_empty() => {
                    Some("the rays record no `radiance`".to_string())
                }
                _ => None,
            };
            (*c, missing)
        })
        .collect()
}

/// The SQL expressions of a float column's values: the column, or its list elements.
fn float_parts(schema: &Schema, name: &str) -> Vec<String> {
    let Some((_, f)) = schema.column_with_name(name) else { return Vec::new() };
    let float = |t: &DataType| matches!(t, DataType::Float16 | DataType::Float32 | DataType::Float64);
    match f.data_type() {
        t if float(t) => vec![name.to_string()],
        DataType::FixedSizeList(item, n) if float(item.data_type()) => {
            (1..=*n).map(|i| format!("{name}[{i}]")).collect()
        }
        _ => Vec::new(),
    }
}

/// `e` (a SQL float expression) is NaN or infinite.
fn non_finite(e: &str) -> String {
    format!("(isnan({e}) OR abs({e}) = CAST('inf' AS DOUBLE))")
}

/// The largest absolute coordinate of `a`'s `which` (origin or dir) as a double.
fn max_abs(a: &str, which: &str) -> String {
    format!(
        "greatest(abs(CAST({a}.{which}_x AS DOUBLE)), abs(CAST({a}.{which}_y AS DOUBLE)), abs(CAST({a}.{which}_z AS DOUBLE)))"
    )
}

/// The select list of a view row for ray `r`.
fn row(problem: &str, value: &str, detail: &str) -> String {
    format!(
        "'{problem}' AS problem, r.tree_id, r.ray, r.parent, r.pixel_x, r.pixel_y, r.sample, r.depth, r.kind, \
         r.origin_x, r.origin_y, r.origin_z, r.dir_x, r.dir_y, r.dir_z, r.t, \
         CAST({value} AS DOUBLE) AS value, CAST({detail} AS VARCHAR) AS detail"
    )
}

/// The `numerics` view's SQL over `rays` (a table name, qualified or not).
pub fn view_sql(schema: &Schema, rays: &str, scope: &Scope) -> String {
    let mut parts = Vec::new();
    let join = format!("FROM {rays} r JOIN {rays} p ON r.tree_id = p.tree_id AND r.parent = p.ray");
    // The parent's hit point, in doubles.
    let hit = |a: &str| format!("(CAST(p.origin_{a} AS DOUBLE) + CAST(p.t AS DOUBLE) * CAST(p.dir_{a} AS DOUBLE))");
    let eps_o = format!("({REL_BOUND} * greatest({}, {NEAR_ORIGIN}))", max_abs("r", "origin"));
    let hit_bound = format!("({REL_BOUND} * ({} + abs(CAST(p.t AS DOUBLE)) + {NEAR_ORIGIN}))", max_abs("p", "origin"));
    let off = format!(
        "greatest(abs(CAST(r.origin_x AS DOUBLE) - {}), abs(CAST(r.origin_y AS DOUBLE) - {}), abs(CAST(r.origin_z AS DOUBLE) - {}))",
        hit("x"),
        hit("y"),
        hit("z")
    );
    for (check, missing) in available(schema, scope) {
        if missing.is_some() {
            continue;
        }
        match check.name {
            "non_finite" => {
                let mut cols: Vec<String> = ["origin_x", "origin_y", "origin_z", "dir_x", "dir_y", "dir_z", "t"]
                    .iter()
                    .map(|c| c.to_string())
                    .collect();
                // Payload columns named as plain SQL identifiers (a C renderer's other names are
                // left out rather than quoted into the view's text).
                let plain = |n: &str| n.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_');
                for f in schema.fields() {
                    if !store::CORE_RAY_COLUMNS.contains(&f.name().as_str()) && plain(f.name()) {
                        cols.extend(float_parts(schema, f.name()));
                    }
                }
                let any = cols.iter().map(|c| non_finite(&format!("r.{c}"))).collect::<Vec<_>>().join(" OR ");
                let which = cols
                    .iter()
                    .map(|c| format!("WHEN {} THEN '{c}'", non_finite(&format!("r.{c}"))))
                    .collect::<Vec<_>>()
                    .join(" ");
                parts.push(format!("SELECT {} FROM {rays} r WHERE {any}", row("non_finite", "NULL", &format!("CASE {which} END"))));
            }
            "bad_direction" => {
                let len = "sqrt(CAST(r.dir_x AS DOUBLE) * CAST(r.dir_x AS DOUBLE) + CAST(r.dir_y AS DOUBLE) * CAST(r.dir_y AS DOUBLE) + CAST(r.dir_z AS DOUBLE) * CAST(r.dir_z AS DOUBLE))";
                let finite = ["r.dir_x", "r.dir_y", "r.dir_z"].map(non_finite).join(" OR ");
                parts.push(format!(
                    "SELECT {} FROM {rays} r WHERE NOT ({finite}) AND ({len} < 1e-30 OR abs({len} - 1) > {UNIT_TOLERANCE})",
                    row("bad_direction", len, &format!("CASE WHEN {len} < 1e-30 THEN 'zero' ELSE 'not unit' END"))
                ));
            }
            "self_hit" => parts.push(format!(
                "SELECT {} {join} WHERE r.prim = p.prim AND r.t IS NOT NULL AND CAST(r.t AS DOUBLE) < {eps_o}",
                row("self_hit", "r.t", &format!("concat('prim ', CAST(r.prim AS VARCHAR), ', t below ', CAST({eps_o} AS VARCHAR))"))
            )),
            "detached_origin" => parts.push(format!(
                "SELECT {} {join} WHERE p.t IS NOT NULL AND {off} > {hit_bound}",
                row("detached_origin", &off, &format!("concat('bound ', CAST({hit_bound} AS VARCHAR))"))
            )),
            "leak" => {
                // (a) The segment from the parent's hit point to the ray's origin crosses a surface.
                let (hx, hy, hz) = (hit("x"), hit("y"), hit("z"));
                let seg = format!(
                    "SELECT r.*, {hx} AS hx, {hy} AS hy, {hz} AS hz, \
                     sqrt(power(CAST(r.origin_x AS DOUBLE) - {hx}, 2) + power(CAST(r.origin_y AS DOUBLE) - {hy}, 2) + power(CAST(r.origin_z AS DOUBLE) - {hz}, 2)) AS seg_len, \
                     {hit_bound} AS seg_eps {join} WHERE p.t IS NOT NULL AND {off} > {hit_bound}"
                );
                let crossed = "scene_hit(r.hx, r.hy, r.hz, (CAST(r.origin_x AS DOUBLE) - r.hx) / r.seg_len, \
                     (CAST(r.origin_y AS DOUBLE) - r.hy) / r.seg_len, (CAST(r.origin_z AS DOUBLE) - r.hz) / r.seg_len, \
                     r.seg_eps, r.seg_len - r.seg_eps)";
                parts.push(format!(
                    "SELECT {} FROM ({seg}) r WHERE r.seg_len > 2 * r.seg_eps AND {crossed} IS NOT NULL",
                    row("leak", crossed, "'starts behind a surface'")
                ));
                // (b) Replayed, the ray meets a surface before its recorded hit (shadow rays stop
                // at any occluder, not the closest, so they are left out).
                let tol = format!(
                    "({REL_BOUND} * ({} + coalesce(abs(CAST(r.t AS DOUBLE)), 0) + {NEAR_ORIGIN}))",
                    max_abs("r", "origin")
                );
                let replay = format!(
                    "scene_hit(CAST(r.origin_x AS DOUBLE), CAST(r.origin_y AS DOUBLE), CAST(r.origin_z AS DOUBLE), \
                     CAST(r.dir_x AS DOUBLE), CAST(r.dir_y AS DOUBLE), CAST(r.dir_z AS DOUBLE), {eps_o}, \
                     coalesce(CAST(r.t AS DOUBLE), 1e30) - {tol})"
                );
                parts.push(format!(
                    "SELECT {} FROM {rays} r WHERE r.kind <> 'shadow' AND {replay} IS NOT NULL",
                    row("leak", &replay, "'passes a surface before its hit'")
                ));
            }
            "energy" => {
                let mx = |a: &str| {
                    let p = float_parts(schema, "throughput");
                    let p: Vec<String> = p.iter().map(|e| format!("CAST({a}.{e} AS DOUBLE)")).collect();
                    if p.len() == 1 { p[0].clone() } else { format!("greatest({})", p.join(", ")) }
                };
                let bound = format!(
                    "({ENERGY_SLACK} * CASE WHEN r.kind = 'transmission' THEN {TRANSMISSION_BOUND} ELSE 1.0 END * greatest({}, 1.0))",
                    mx("p")
                );
                parts.push(format!(
                    "SELECT {} {join} WHERE r.kind <> 'shadow' AND {} > {bound}",
                    row("energy", &mx("r"), &format!("concat('bound ', CAST({bound} AS VARCHAR))")),
                    mx("r")
                ));
            }
            "wrong_shadow" => parts.push(format!(
                "SELECT {} FROM {rays} r WHERE r.kind = 'shadow' AND NOT aims_at_light(r.origin_x, r.origin_y, r.origin_z, r.dir_x, r.dir_y, r.dir_z)",
                row("wrong_shadow", "NULL", "'aims at no emitter'")
            )),
            "firefly" => {
                let p = float_parts(schema, "radiance");
                let l = if p.len() == 1 {
                    format!("CAST({} AS DOUBLE)", p[0])
                } else {
                    format!("greatest({})", p.iter().map(|e| format!("CAST({e} AS DOUBLE)")).collect::<Vec<_>>().join(", "))
                };
                let samples = format!(
                    "SELECT *, {l} AS contribution, median({l}) OVER (PARTITION BY pixel_x, pixel_y) AS pixel_median \
                     FROM {rays} WHERE parent IS NULL"
                );
                let mean = format!("(SELECT avg({l}) FROM {rays} WHERE parent IS NULL AND NOT isnan({l}))");
                parts.push(format!(
                    "SELECT {} FROM ({samples}) r WHERE r.contribution > {FIREFLY_K} * r.pixel_median \
                     AND r.contribution > {FIREFLY_K} * {mean}",
                    row("firefly", "r.contribution", "concat('pixel median ', CAST(r.pixel_median AS VARCHAR))")
                ));
            }
            _ => {}
        }
    }
    parts.join(" UNION ALL ")
}

/// The name of the view.
pub const VIEW: &str = "numerics";

/// Registers the `numerics` view of dataset `ds` under `name` (as `NAME.numerics`, and as
/// `numerics` with `unqualified`) and its `numerics_checks` table; the ray functions must be
/// registered already. A broken table the checks read leaves out the checks that need it (named
/// in `numerics_checks` with the reason); a view that cannot be planned at all is registered as
/// unavailable, naming why, so the session opens whatever the dataset's state.
pub async fn register_view(
    ctx: &SessionContext,
    name: &str,
    ds: &store::Dataset,
    scope_scene: bool,
    unqualified: bool,
) -> Result<()> {
    let scope = Scope {
        scene: scope_scene,
        lights: Presence::of(ds, store::scene::LIGHTS_TABLE),
        triangles: Presence::of(ds, store::scene::TRIANGLES_TABLE),
    };
    let rays = format!("{name}.rays");
    let schema = ctx.table(rays.as_str()).await?.schema().as_arrow().clone();
    let checks = available(&schema, &scope);
    let view: std::sync::Arc<dyn datafusion::catalog::TableProvider> =
        match ctx.sql(&view_sql(&schema, &rays, &scope)).await {
            Ok(df) => df.into_view(),
            Err(e) => std::sync::Arc::new(crate::unavailable::Unavailable::new(
                VIEW,
                std::sync::Arc::new(Schema::empty()),
                format!("the view could not be planned: {e}"),
            )),
        };
    let checks = checks_table(&checks)?;
    for (table, provider) in [(VIEW, view), (CHECKS_TABLE, checks)] {
        ctx.register_table(datafusion::common::TableReference::partial(name, table), provider.clone())?;
        if unqualified {
            ctx.register_table(table, provider)?;
        }
    }
    Ok(())
}

/// The table naming each check, whether the view has it and why not:
/// `numerics_checks(problem, title, bug, missing)`.
pub const CHECKS_TABLE: &str = "numerics_checks";

fn checks_table(checks: &[(Check, Option<String>)]) -> Result<std::sync::Arc<dyn datafusion::catalog::TableProvider>> {
    use arrow::array::{BooleanArray, RecordBatch, StringArray};
    use arrow::datatypes::Field;
    use std::sync::Arc;
    let schema = Arc::new(Schema::new(vec![
        Field::new("problem", DataType::Utf8, false),
        Field::new("title", DataType::Utf8, false),
        Field::new("bug", DataType::Boolean, false),
        Field::new("missing", DataType::Utf8, true),
    ]));
    let batch = RecordBatch::try_new(
        schema.clone(),
        vec![
            Arc::new(StringArray::from_iter_values(checks.iter().map(|(c, _)| c.name))),
            Arc::new(StringArray::from_iter_values(checks.iter().map(|(c, _)| c.title))),
            Arc::new(BooleanArray::from_iter(checks.iter().map(|(c, _)| Some(c.bug)))),
            Arc::new(StringArray::from_iter(checks.iter().map(|(_, m)| m.as_deref()))),
        ],
    )
    .map_err(|e| crate::Error::DataFusion(e.into()))?;
    Ok(Arc::new(datafusion::datasource::MemTable::try_new(schema, vec![vec![batch]])?))
}
