#![allow(clippy::unwrap_used)]
//! Differential SQL fuzzing, as SQLancer does for databases: random predicates and projections
//! over `rays`, `trees` and `numerics`, generated from the tables' columns, asked of one trace
//! in its lossless encoding and in its plain export (the same answers, to the bit), and of DuckDB
//! over the plain export's Parquet files (the same answers for `rays` and `trees`).
//!
//! `RTVTK_SQL_FUZZ_CASES` (default 300, what CI runs) sets the number of queries and
//! `RTVTK_SQL_FUZZ_SEED` (default 1) the first seed: case `i` is generated from seed + i, so a
//! disagreement is reproduced by its seed, and once fixed its query goes in [`REGRESSIONS`].

mod common;

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Command, Stdio};

/// Queries that once disagreed, replayed first on every run.
const REGRESSIONS: &[&str] = &[];

/// A small deterministic generator (xorshift64*): a case is its seed.
struct Gen(u64);

impl Gen {
    fn new(seed: u64) -> Self {
        Self(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1)
    }
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
    fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.below(xs.len())]
    }
    fn chance(&mut self, percent: u64) -> bool {
        self.next() % 100 < percent
    }
}

#[derive(Clone, Copy, PartialEq)]
enum Ty {
    Int,
    Float,
    Kind,
}

/// The columns of a table the generator draws from, with their types.
fn columns(table: &str) -> &'static [(&'static str, Ty)] {
    match table {
        "rays" => &[
            ("tree_id", Ty::Int),
            ("ray", Ty::Int),
            ("parent", Ty::Int),
            ("depth", Ty::Int),
            ("kind", Ty::Kind),
            ("prim", Ty::Int),
            ("pixel_x", Ty::Int),
            ("pixel_y", Ty::Int),
            ("sample", Ty::Int),
            ("origin_x", Ty::Float),
            ("origin_y", Ty::Float),
            ("origin_z", Ty::Float),
            ("dir_x", Ty::Float),
            ("dir_y", Ty::Float),
            ("dir_z", Ty::Float),
            ("t", Ty::Float),
        ],
        "trees" => &[
            ("tree_id", Ty::Int),
            ("pixel_x", Ty::Int),
            ("pixel_y", Ty::Int),
            ("sample", Ty::Int),
            ("ray_count", Ty::Int),
            ("max_depth", Ty::Int),
        ],
        _ => &[
            ("tree_id", Ty::Int),
            ("ray", Ty::Int),
            ("depth", Ty::Int),
            ("pixel_x", Ty::Int),
            ("pixel_y", Ty::Int),
            ("origin_x", Ty::Float),
            ("dir_y", Ty::Float),
            ("t", Ty::Float),
            ("value", Ty::Float),
        ],
    }
}

/// A literal of type `ty` near the values the trace holds.
fn literal(g: &mut Gen, col: &str, ty: Ty) -> String {
    match ty {
        Ty::Kind => format!("'{}'", g.pick(&["camera", "shadow", "diffuse", "specular", "transmission", "none"])),
        Ty::Int => {
            let range: i64 = match col {
                "depth" | "max_depth" => 6,
                "pixel_x" => 18,
                "pixel_y" => 14,
                "sample" => 3,
                "ray" | "parent" | "ray_count" => 40,
                "prim" => 40,
                _ => 700,
            };
            (g.below(range as usize + 2) as i64 - 1).to_string()
        }
        Ty::Float => {
            let v = match g.below(5) {
                0 => 0.0,
                1 => (g.below(2001) as f64 - 1000.0) / 1000.0,
                2 => (g.below(601) as f64) - 50.0,
                3 => (g.below(21) as f64 - 10.0) / 10.0,
                _ => 1.0e-3 * (g.below(2001) as f64 - 1000.0),
            };
            format!("{v:?}")
        }
    }
}

/// A random predicate over `cols`, `depth` levels of AND/OR/NOT deep.
fn predicate(g: &mut Gen, cols: &[(&str, Ty)], depth: u32) -> String {
    if depth > 0 && g.chance(45) {
        let (a, b) = (predicate(g, cols, depth - 1), predicate(g, cols, depth - 1));
        return match g.below(3) {
            0 => format!("({a} AND {b})"),
            1 => format!("({a} OR {b})"),
            _ => format!("(NOT {a})"),
        };
    }
    let &(c, ty) = g.pick(cols);
    match (ty, g.below(6)) {
        (_, 0) => format!("{c} IS {}NULL", if g.chance(50) { "NOT " } else { "" }),
        (Ty::Kind, 1 | 2) => {
            let n = 1 + g.below(3);
            let items: Vec<String> = (0..n).map(|_| literal(g, c, ty)).collect();
            format!("{c} {}IN ({})", if g.chance(30) { "NOT " } else { "" }, items.join(", "))
        }
        (Ty::Kind, _) => format!("{c} {} {}", g.pick(&["=", "<>"]), literal(g, c, ty)),
        (_, 1) => {
            let (a, b) = (literal(g, c, ty), literal(g, c, ty));
            format!("{c} BETWEEN {a} AND {b}")
        }
        (Ty::Float, 2) => {
            let other = cols.iter().filter(|x| x.1 == Ty::Float).map(|x| x.0).collect::<Vec<_>>();
            let o = g.pick(&other);
            format!("CAST({c} AS DOUBLE) {} CAST({o} AS DOUBLE) * {}", g.pick(&["<", ">", "<="]), literal(g, o, ty))
        }
        _ => format!("{c} {} {}", g.pick(&["=", "<>", "<", "<=", ">", ">="]), literal(g, c, ty)),
    }
}

/// A whole query of `table`: aggregates of a filtered set, or its first rows in a fixed order.
fn query(g: &mut Gen, table: &str) -> String {
    let cols = columns(table);
    let pred = predicate(g, cols, 3);
    let keys = match table {
        "rays" => "tree_id, ray",
        "trees" => "tree_id",
        _ => "problem, tree_id, ray",
    };
    if g.chance(50) {
        let mut sel = vec!["count(*)".to_string()];
        for _ in 0..3 {
            let &(c, ty) = g.pick(cols);
            sel.push(match ty {
                Ty::Int => format!("{}(CAST({c} AS BIGINT))", g.pick(&["min", "max", "sum", "count"])),
                Ty::Float => format!("{}(CAST({c} AS DOUBLE))", g.pick(&["min", "max", "count"])),
                Ty::Kind => format!("count(DISTINCT CAST({c} AS VARCHAR))"),
            });
        }
        let sel: Vec<String> = sel.iter().enumerate().map(|(i, e)| format!("{e} AS a{i}")).collect();
        if g.chance(40) {
            let &(gc, gty) = g.pick(&cols.iter().filter(|c| c.1 != Ty::Float).copied().collect::<Vec<_>>());
            let key = if gty == Ty::Kind { format!("CAST({gc} AS VARCHAR)") } else { format!("CAST({gc} AS BIGINT)") };
            return format!(
                "SELECT {key} AS k, {} FROM {table} WHERE {pred} GROUP BY {key} ORDER BY k NULLS FIRST",
                sel.join(", ")
            );
        }
        format!("SELECT {} FROM {table} WHERE {pred}", sel.join(", "))
    } else {
        let mut sel: Vec<String> = keys.split(", ").map(|k| format!("CAST({k} AS VARCHAR)")).collect();
        for _ in 0..2 {
            let &(c, ty) = g.pick(cols);
            sel.push(match ty {
                Ty::Int => format!("CAST({c} AS BIGINT)"),
                Ty::Float => format!("CAST({c} AS DOUBLE)"),
                Ty::Kind => format!("CAST({c} AS VARCHAR)"),
            });
        }
        let sel: Vec<String> = sel.iter().enumerate().map(|(i, e)| format!("{e} AS c{i}")).collect();
        format!("SELECT {} FROM {table} WHERE {pred} ORDER BY {keys} LIMIT {}", sel.join(", "), 1 + g.below(12))
    }
}

/// A result as lines of values, floats written so both engines' texts compare.
fn rows_of(batches: &[arrow::array::RecordBatch]) -> Vec<String> {
    use arrow::array::Array;
    let mut out = Vec::new();
    for b in batches {
        let cols: Vec<_> =
            b.columns().iter().map(|c| arrow::compute::cast(c, &arrow::datatypes::DataType::Utf8).unwrap()).collect();
        for r in 0..b.num_rows() {
            let vals: Vec<String> = cols
                .iter()
                .map(|c| {
                    let s = c.as_any().downcast_ref::<arrow::array::StringArray>().unwrap();
                    if s.is_null(r) { String::new() } else { normalize(s.value(r)) }
                })
                .collect();
            out.push(vals.join(","));
        }
    }
    out
}

/// A value's text in one form: numbers as the f64 they denote.
fn normalize(v: &str) -> String {
    match v.parse::<f64>() {
        Ok(x) if v.contains('.') || v.contains('e') || v.contains("inf") || v.contains("NaN") => format!("{x:?}"),
        _ => v.to_string(),
    }
}

/// DuckDB over the plain export, one long-lived process answering a query per line.
struct Duck {
    child: std::process::Child,
    out: BufReader<std::process::ChildStdout>,
}

impl Duck {
    fn start(plain: &Path) -> Self {
        let script = r#"
import sys, json, math
import duckdb
con = duckdb.connect()
d = sys.argv[1]
con.execute(f"CREATE VIEW trees AS SELECT * FROM read_parquet('{d}/segments/*.trees.parquet')")
cols = [r[0] for r in con.execute(f"DESCRIBE SELECT * FROM read_parquet('{d}/segments/*.rays.parquet')").fetchall()]
if 'pixel_x' in cols:
    con.execute(f"CREATE VIEW rays AS SELECT * FROM read_parquet('{d}/segments/*.rays.parquet')")
else:
    con.execute(f"CREATE VIEW rays AS SELECT r.*, t.pixel_x, t.pixel_y, t.sample FROM read_parquet('{d}/segments/*.rays.parquet') r JOIN trees t USING (tree_id)")
def text(v):
    if v is None: return ""
    if isinstance(v, float): return repr(v)
    return str(v)
for line in sys.stdin:
    q = json.loads(line)
    try:
        rows = con.execute(q).fetchall()
        print(json.dumps({"rows": [",".join(text(v) for v in r) for r in rows]}), flush=True)
    except Exception as e:
        print(json.dumps({"error": str(e)}), flush=True)
"#;
        let mut child = Command::new("python3")
            .arg("-c")
            .arg(script)
            .arg(plain)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("python3 with duckdb (scripts/check.sh installs it)");
        let out = BufReader::new(child.stdout.take().unwrap());
        Self { child, out }
    }

    fn ask(&mut self, q: &str) -> Result<Vec<String>, String> {
        let stdin = self.child.stdin.as_mut().unwrap();
        writeln!(stdin, "{}", serde_json::to_string(q).unwrap()).unwrap();
        let mut line = String::new();
        self.out.read_line(&mut line).unwrap();
        let v: serde_json::Value = serde_json::from_str(&line).unwrap_or_else(|e| panic!("duckdb said {line:?}: {e}"));
        match v.get("rows") {
            Some(rows) => Ok(rows
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r.as_str().unwrap().split(',').map(normalize).collect::<Vec<_>>().join(","))
                .collect()),
            None => Err(v["error"].as_str().unwrap_or_default().to_string()),
        }
    }
}

impl Drop for Duck {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn engine(dir: &Path) -> query::Engine {
    let sources = [query::TraceSource { name: "t".into(), path: dir.to_path_buf() }];
    query::Engine::blocking(query::Engine::open(&sources, &Default::default())).unwrap()
}

fn ask(e: &query::Engine, q: &str) -> Result<Vec<String>, String> {
    e.block_on(e.collect(q)).map(|b| rows_of(&b)).map_err(|e| e.to_string())
}

#[test]
fn lossless_plain_and_duckdb_give_the_same_answers() {
    let tmp = tempfile::tempdir().unwrap();
    let (lossless, plain) = (tmp.path().join("lossless"), tmp.path().join("plain"));
    common::record(&lossless, &["--size", "16x12", "--spp", "2", "--threads", "1", "--seed", "7"]);
    common::ok(&["export", lossless.to_str().unwrap(), plain.to_str().unwrap()]);
    let (a, b) = (engine(&lossless), engine(&plain));
    let mut duck = Duck::start(&plain);
    let cases: u64 = std::env::var("RTVTK_SQL_FUZZ_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(300);
    let seed: u64 = std::env::var("RTVTK_SQL_FUZZ_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(1);
    let (mut answered, mut refused, mut with_duck) = (0u64, 0u64, 0u64);
    let t0 = std::time::Instant::now();
    let generated = (seed..seed + cases).map(|s| {
        let mut g = Gen::new(s);
        let table = *g.pick(&["rays", "rays", "rays", "trees", "numerics"]);
        (format!("seed {s}"), table, query(&mut g, table))
    });
    let replayed = REGRESSIONS
        .iter()
        .map(|q| ("regression".to_string(), if q.contains("FROM trees") { "trees" } else { "rays" }, q.to_string()));
    for (case, table, q) in replayed.chain(generated) {
        let (x, y) = (ask(&a, &q), ask(&b, &q));
        match (&x, &y) {
            (Ok(x), Ok(y)) => assert_eq!(x, y, "{case}: lossless and plain differ on\n{q}"),
            (Err(_), Err(_)) => {}
            _ => panic!("{case}: one encoding refused\n{q}\nlossless: {x:?}\nplain: {y:?}"),
        }
        let Ok(ours) = x else {
            if refused < 5 {
                eprintln!("{case}: refused by both: {q}\n  {}", x.unwrap_err());
            }
            refused += 1;
            continue;
        };
        answered += 1;
        if table != "numerics" {
            let theirs =
                duck.ask(&q).unwrap_or_else(|e| panic!("{case}: DuckDB refused what rtvtk answered\n{q}\n{e}"));
            assert_eq!(ours, theirs, "{case}: rtvtk and DuckDB differ on\n{q}");
            with_duck += 1;
        }
    }
    eprintln!(
        "{answered} queries answered alike ({with_duck} also by DuckDB), {refused} refused by both, seeds {seed}..{}, {:.1} queries/s",
        seed + cases,
        (answered + refused) as f64 / t0.elapsed().as_secs_f64()
    );
    assert!(answered > cases / 2, "most generated queries are valid: {answered} of {cases}");
}
