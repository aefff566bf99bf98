//! `rtvtk bench query`: a fixed suite of queries on a trace, timed in rtvtk (DataFusion through
//! the store) and in DuckDB on the same Parquet files in the same run, with peak memory.
//!
//! Each query runs in its own process (`rtvtk sql --timing` / `python3 -c` with duckdb), warm
//! (once untimed, then `runs` times); the time is the median of the query alone, as each engine
//! reports it, and the memory the process's peak resident set (Linux `VmHWM`, reported by the
//! child itself; `wait4` elsewhere), so both include their runtime (DuckDB's includes the
//! Python interpreter, ~30 MB). Both engines read the plain export
//! (same files, same columns); rtvtk also reads the encoded dataset when given one. The row
//! counts of the two engines' answers are compared: a query whose answers differ is reported.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

/// One query of the suite: rtvtk's form and DuckDB's (which lacks the ray functions: octants
/// and Morton codes by SQL arithmetic).
#[derive(Clone)]
struct Case {
    name: &'static str,
    ours: String,
    duckdb: String,
    /// Answers compared by row count only (whole rays: rtvtk adds the pixel columns and prints
    /// payload lists as JSON, since CSV cannot hold them).
    counts_only: bool,
    /// DuckDB reads a copy of the plain files written without Parquet statistics (the anchors'
    /// "same file without statistics"); rtvtk finds a tree's rows through its tree table, which
    /// statistics do not change, so it reads the dataset as usual.
    duckdb_without_statistics: bool,
    /// Extra arguments of `rtvtk sql` (a baseline inside rtvtk, such as `--stock-aggregation`).
    ours_args: &'static [&'static str],
}

impl Case {
    fn new(name: &'static str, ours: impl Into<String>, duckdb: impl Into<String>) -> Self {
        Self {
            name,
            ours: ours.into(),
            duckdb: duckdb.into(),
            counts_only: false,
            duckdb_without_statistics: false,
            ours_args: &[],
        }
    }

    fn agree(&self, a: &Measured, b: &Measured) -> bool {
        if self.counts_only { a.rows.len() == b.rows.len() } else { same_answer(&a.rows, &b.rows) }
    }
}

/// Morton code of a point's 10-bit cells over [lo, hi], by SQL arithmetic (what a DuckDB user writes).
fn duckdb_morton(lo: [f64; 3], hi: [f64; 3]) -> String {
    let axes = ["origin_x", "origin_y", "origin_z"];
    let q: Vec<String> = (0..3)
        .map(|k| {
            let ext = (hi[k] - lo[k]).max(f64::MIN_POSITIVE);
            format!("CAST(round(least(greatest(({} - ({})) / ({ext}), 0), 1) * 1023) AS BIGINT)", axes[k], lo[k])
        })
        .collect();
    let mut terms = Vec::new();
    for bit in 0..10 {
        for (k, qk) in q.iter().enumerate() {
            terms.push(format!("(((({qk}) >> {bit}) & 1) << {})", 3 * bit + k));
        }
    }
    terms.join(" | ")
}

fn suite(tree: u64, lo: [f64; 3], hi: [f64; 3]) -> Vec<Case> {
    let same = |name, q: &str| Case::new(name, q, q);
    let coherence_duckdb = "SELECT kind, depth, sqrt(power(sum(dir_x / l), 2) + power(sum(dir_y / l), 2) + \
        power(sum(dir_z / l), 2)) / count(*) AS c FROM (SELECT kind, depth, dir_x, dir_y, dir_z, \
        sqrt(dir_x * dir_x + dir_y * dir_y + dir_z * dir_z) AS l FROM rays) WHERE l > 0 GROUP BY kind, depth";
    let morton = Case::new(
        "30-bit Morton cell of origin, top 20",
        "SELECT morton3(origin_x, origin_y, origin_z, 10) AS m, count(*) AS n FROM rays \
               GROUP BY m ORDER BY n DESC, m LIMIT 20",
        format!(
            "SELECT {} AS m, count(*) AS n FROM rays GROUP BY m ORDER BY n DESC, m LIMIT 20",
            duckdb_morton(lo, hi)
        ),
    );
    vec![
        same("count shadow rays with depth >= 2", "SELECT count(*) FROM rays WHERE kind = 'shadow' AND depth >= 2"),
        Case::new(
            "group by direction octant",
            "SELECT octant(dir_x, dir_y, dir_z) AS o, count(*) FROM rays GROUP BY o",
            "SELECT (CASE WHEN dir_x < 0 THEN 1 ELSE 0 END) + (CASE WHEN dir_y < 0 THEN 2 ELSE 0 END) + \
                     (CASE WHEN dir_z < 0 THEN 4 ELSE 0 END) AS o, count(*) FROM rays GROUP BY o",
        ),
        morton.clone(),
        Case {
            name: "the same, DataFusion's own aggregation (baseline)",
            ours_args: &["--stock-aggregation"],
            ..morton
        },
        Case {
            counts_only: true,
            ..same("all rays of one tree", &format!("SELECT * FROM rays WHERE tree_id = {tree}"))
        },
        Case {
            counts_only: true,
            duckdb_without_statistics: true,
            ..same("one tree, DuckDB's files without statistics", &format!("SELECT * FROM rays WHERE tree_id = {tree}"))
        },
        Case::new(
            "average depth per pixel",
            "SELECT pixel_x, pixel_y, avg(depth) FROM rays GROUP BY pixel_x, pixel_y",
            "SELECT t.pixel_x, t.pixel_y, avg(r.depth) FROM rays r JOIN trees t USING (tree_id) \
                     GROUP BY t.pixel_x, t.pixel_y",
        ),
        Case::new(
            "direction coherence by kind and depth",
            "SELECT kind, depth, dir_coherence(dir_x, dir_y, dir_z) FROM rays GROUP BY kind, depth",
            coherence_duckdb,
        ),
        same(
            "BVH cost by kind and depth",
            "SELECT kind, depth, avg(nodes_visited), avg(box_tests), avg(tri_tests) FROM rays GROUP BY kind, depth",
        ),
    ]
}

/// Median seconds and peak RSS (bytes) of a command that prints `query seconds: S` per run on
/// stderr, and its last answer (rows of cells as text).
struct Measured {
    secs: f64,
    rss: u64,
    rows: Vec<Vec<String>>,
}

/// Whether two answers agree: the same rows in some order, numbers within a relative 1e-6.
pub fn same_answer(a: &[Vec<String>], b: &[Vec<String>]) -> bool {
    let key = |r: &Vec<String>| -> Vec<String> {
        r.iter()
            .map(|c| match c.trim().parse::<f64>() {
                Ok(v) if v.is_finite() && v != 0.0 => format!("{:.3e}", v),
                Ok(v) => format!("{v}"),
                Err(_) => c.trim().to_string(),
            })
            .collect()
    };
    fn sorted<'a>(x: &'a [Vec<String>], key: &impl Fn(&Vec<String>) -> Vec<String>) -> Vec<&'a Vec<String>> {
        let mut v: Vec<&Vec<String>> = x.iter().collect();
        v.sort_by_key(|r| key(r));
        v
    }
    let (sa, sb) = (sorted(a, &key), sorted(b, &key));
    sa.len() == sb.len()
        && sa.iter().zip(&sb).all(|(x, y)| {
            x.len() == y.len()
                && x.iter().zip(y.iter()).all(|(u, v)| match (u.trim().parse::<f64>(), v.trim().parse::<f64>()) {
                    (Ok(p), Ok(q)) => p == q || (p - q).abs() <= 1e-6 * p.abs().max(q.abs()),
                    _ => u.trim() == v.trim(),
                })
        })
}

/// Runs `cmd`, returning its output and peak resident set size.
#[cfg(unix)]
pub(crate) fn run_measured(cmd: &mut Command) -> Result<(std::process::Output, u64)> {
    use std::os::unix::process::ExitStatusExt;
    let mut child = cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped()).spawn()?;
    let pid = child.id() as libc::pid_t;
    // Read the pipes on threads while waiting with wait4 (for the child's rusage).
    fn drain(pipe: Option<impl std::io::Read + Send + 'static>) -> std::thread::JoinHandle<Vec<u8>> {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            if let Some(mut p) = pipe {
                let _ = p.read_to_end(&mut v);
            }
            v
        })
    }
    let (t1, t2) = (drain(child.stdout.take()), drain(child.stderr.take()));
    let mut status = 0;
    // SAFETY: an all-zero rusage is a valid value, and wait4 writes it for our own child.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: pid is our child's; status and usage are valid for writes.
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
    if r < 0 {
        bail!("wait4 failed: {}", std::io::Error::last_os_error());
    }
    let stdout = t1.join().unwrap_or_default();
    let stderr = t2.join().unwrap_or_default();
    let status = std::process::ExitStatus::from_raw(status);
    Ok((std::process::Output { status, stdout, stderr }, usage.ru_maxrss as u64 * 1024))
}

#[cfg(not(unix))]
pub(crate) fn run_measured(cmd: &mut Command) -> Result<(std::process::Output, u64)> {
    Ok((cmd.output()?, 0))
}

/// The peak resident set a child reported (`peak rss bytes: N` on stderr, from Linux `VmHWM`).
/// Preferred to `wait4`'s `ru_maxrss`, which starts from this (parent) process's own peak:
/// Linux carries the pre-`exec` image's high-water mark over into the child's.
fn reported_peak(stderr: &str) -> Option<u64> {
    stderr.lines().find_map(|l| l.strip_prefix("peak rss bytes: ")).and_then(|v| v.trim().parse().ok())
}

/// The median (the mean of the middle two for an even count); NaN for none.
pub(crate) fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// rtvtk's answer as CSV rows, or with `json` as JSON lines (for nested payload columns).
fn ours(dataset: &Path, case: &Case, runs: usize, memory_limit: Option<&str>) -> Result<Measured> {
    ours_on(dataset, case, runs, memory_limit, None)
}

fn ours_on(
    dataset: &Path,
    case: &Case,
    runs: usize,
    memory_limit: Option<&str>,
    cluster: Option<&str>,
) -> Result<Measured> {
    let (query, json) = (case.ours.as_str(), case.counts_only);
    let exe = std::env::current_exe().context("finding the rtvtk executable")?;
    let mut times = Vec::new();
    let mut rss = 0;
    let mut rows = Vec::new();
    for i in 0..=runs {
        let mut cmd = Command::new(&exe);
        cmd.args(["sql"]).arg(dataset).args([query, "--format", if json { "json" } else { "csv" }, "--timing"]);
        cmd.args(case.ours_args);
        if let Some(m) = memory_limit {
            cmd.args(["--memory-limit", m]);
        }
        if let Some(url) = cluster {
            // Ballista's own aggregation on the cluster: compare with the same in-process.
            cmd.args(["--cluster", url]);
        }
        let (out, peak) = run_measured(&mut cmd)?;
        if !out.status.success() {
            bail!("rtvtk sql failed on {query:?}: {}", String::from_utf8_lossy(&out.stderr));
        }
        let err = String::from_utf8_lossy(&out.stderr);
        let secs: f64 = err
            .lines()
            .find_map(|l| l.strip_prefix("query seconds: "))
            .and_then(|s| s.trim().parse().ok())
            .context("no timing from rtvtk sql")?;
        if i > 0 {
            times.push(secs);
            rss = rss.max(reported_peak(&err).unwrap_or(peak));
        }
        rows = String::from_utf8_lossy(&out.stdout)
            .lines()
            .skip(usize::from(!json))
            .filter(|l| !l.trim().is_empty())
            .map(|l| l.split(',').map(str::to_string).collect())
            .collect();
    }
    Ok(Measured { secs: median(&times), rss, rows })
}

/// Rewrites the plain export's ray files under `out/segments` with no Parquet statistics (no
/// row-group or page min/max), same row groups and zstd-1; the tree files are copied.
fn copy_without_statistics(plain: &Path, out: &Path) -> Result<()> {
    use arrow::array::RecordBatchReader as _;
    use parquet::arrow::ArrowWriter;
    use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
    use parquet::basic::{Compression, ZstdLevel};
    use parquet::file::properties::{EnabledStatistics, WriterProperties};
    let segments = plain.join("segments");
    std::fs::create_dir_all(out.join("segments")).with_context(|| format!("creating {}", out.display()))?;
    let entries = std::fs::read_dir(&segments).with_context(|| format!("listing {}", segments.display()))?;
    for entry in entries {
        let path = entry.with_context(|| format!("listing {}", segments.display()))?.path();
        let Some(name) = path.file_name().map(|n| n.to_string_lossy().to_string()) else { continue };
        let target = out.join("segments").join(&name);
        if name.ends_with(".trees.parquet") {
            std::fs::copy(&path, &target).with_context(|| format!("copying {}", path.display()))?;
        } else if name.ends_with(".rays.parquet") {
            let file = std::fs::File::open(&path).with_context(|| format!("opening {}", path.display()))?;
            let builder = ParquetRecordBatchReaderBuilder::try_new(file)
                .with_context(|| format!("reading {}", path.display()))?;
            let group_rows = builder.metadata().row_groups().first().map_or(1 << 20, |g| g.num_rows().max(1) as usize);
            let reader = builder.with_batch_size(64 * 1024).build()?;
            let props = WriterProperties::builder()
                .set_statistics_enabled(EnabledStatistics::None)
                .set_compression(Compression::ZSTD(ZstdLevel::try_new(1)?))
                .set_max_row_group_row_count(Some(group_rows))
                .build();
            let sink = std::fs::File::create(&target).with_context(|| format!("creating {}", target.display()))?;
            let mut writer = ArrowWriter::try_new(sink, reader.schema(), Some(props))?;
            for batch in reader {
                writer.write(&batch.with_context(|| format!("reading {}", path.display()))?)?;
            }
            writer.close().with_context(|| format!("writing {}", target.display()))?;
        }
    }
    Ok(())
}

fn duckdb(plain: &Path, query: &str, runs: usize) -> Result<Measured> {
    let script = r#"
import sys, time
import duckdb
d, q, runs = sys.argv[1], sys.argv[2], int(sys.argv[3])
con = duckdb.connect()
con.execute("SET enable_progress_bar = false")
con.execute(f"CREATE VIEW rays AS SELECT * FROM read_parquet('{d}/segments/*.rays.parquet')")
con.execute(f"CREATE VIEW trees AS SELECT * FROM read_parquet('{d}/segments/*.trees.parquet')")
rows = con.execute(q).fetchall()
times = []
for _ in range(runs):
    t = time.perf_counter(); rows = con.execute(q).fetchall(); times.append(time.perf_counter() - t)
times.sort()
print(times[len(times) // 2])
try:
    hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM:")][0].split()[1]
    print(f"peak rss bytes: {int(hwm) * 1024}", file=sys.stderr)
except (OSError, IndexError, ValueError):
    pass
for r in rows:
    print(",".join("" if v is None else str(v) for v in r))
"#;
    let mut cmd = Command::new("python3");
    cmd.arg("-c").arg(script).arg(plain).arg(query).arg(runs.to_string());
    let (out, rss) = run_measured(&mut cmd)?;
    let rss = reported_peak(&String::from_utf8_lossy(&out.stderr)).unwrap_or(rss);
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        bail!("python3/duckdb failed on {query:?}: {}", err.lines().last().unwrap_or(""));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let mut lines = text.lines();
    let secs: f64 = lines
        .next()
        .and_then(|l| l.trim().parse().ok())
        .with_context(|| format!("unexpected output from the DuckDB script: {text}"))?;
    let rows = lines.filter(|l| !l.trim().is_empty()).map(|l| l.split(',').map(str::to_string).collect()).collect();
    Ok(Measured { secs, rss, rows })
}

pub fn run(
    dataset: &Path,
    plain: Option<PathBuf>,
    runs: usize,
    memory_limit: Option<&str>,
    with_duckdb: bool,
) -> Result<()> {
    let ds = store::Dataset::open(dataset).with_context(|| format!("opening {}", dataset.display()))?;
    let (plain, _tmp) = match (plain, ds.encoding()) {
        (Some(p), _) => (p, None),
        (None, store::Encoding::Plain) => (dataset.to_path_buf(), None),
        (None, _) => {
            let tmp =
                tempfile::tempdir_in(dataset.parent().unwrap_or(Path::new("."))).context("temporary directory")?;
            let p = tmp.path().join("plain");
            eprintln!("exporting a plain copy for DuckDB to {} ...", p.display());
            store::export_plain(&ds, &p).with_context(|| format!("exporting {}", dataset.display()))?;
            (p, Some(tmp))
        }
    };
    let no_stats = if with_duckdb {
        let dir = tempfile::tempdir_in(plain.parent().unwrap_or(Path::new("."))).context("temporary directory")?;
        eprintln!("writing a copy without Parquet statistics for DuckDB to {} ...", dir.path().display());
        copy_without_statistics(&plain, dir.path())?;
        Some(dir)
    } else {
        None
    };
    // The bounds `morton3` uses, so DuckDB's arithmetic quantizes the same way.
    let (lo, hi) = query::SceneContext::of(&ds).bounds.unwrap_or(([0.0; 3], [1.0; 3]));
    let tree = ds.tree_entry_at(ds.tree_count() as usize / 2)?.map_or(0, |e| e.info.id.0);
    let encoded = ds.encoding() != store::Encoding::Plain && plain != dataset;
    println!(
        "query suite on {} ({} rays, {} trees, {} encoding); median of {runs} warm runs; peak RSS per process{}",
        dataset.display(),
        ds.ray_count(),
        ds.tree_count(),
        ds.encoding().name(),
        memory_limit.map(|m| format!("; rtvtk memory limit {m}")).unwrap_or_default()
    );
    println!(
        "\n| query | rtvtk s | rtvtk MB |{} DuckDB s | DuckDB MB | time ratio (rtvtk/DuckDB) | memory ratio |{}",
        if encoded { " rtvtk lossless s | lossless MB |" } else { "" },
        if encoded { " lossless time ratio (lossless/DuckDB) |" } else { "" }
    );
    println!(
        "|---|---|---|{}---|---|---|---|{}",
        if encoded { "---|---|" } else { "" },
        if encoded { "---|" } else { "" }
    );
    let mut disagreements = Vec::new();
    for case in suite(tree, lo, hi) {
        let a = ours(&plain, &case, runs, memory_limit)?;
        let enc = if encoded { Some(ours(dataset, &case, runs, memory_limit)?) } else { None };
        let duck_dir = match &no_stats {
            Some(dir) if case.duckdb_without_statistics => dir.path(),
            _ => plain.as_path(),
        };
        let d = if with_duckdb { Some(duckdb(duck_dir, &case.duckdb, runs)?) } else { None };
        let mb = |b: u64| b as f64 / (1 << 20) as f64;
        let enc_cols = enc.as_ref().map(|e| format!(" {:.3} | {:.0} |", e.secs, mb(e.rss))).unwrap_or_default();
        let (ds_, dm, tr, mr) = match &d {
            Some(d) => (
                format!("{:.3}", d.secs),
                format!("{:.0}", mb(d.rss)),
                format!("{:.2}x", a.secs / d.secs),
                format!("{:.2}x", a.rss as f64 / d.rss as f64),
            ),
            None => ("—".into(), "—".into(), "—".into(), "—".into()),
        };
        // The encoded dataset's own ratio: what issue 45 asks to keep at or below 1.
        let enc_ratio = match (&enc, &d) {
            (Some(e), Some(d)) => format!(" {:.2}x |", e.secs / d.secs),
            (Some(_), None) => " — |".into(),
            _ => String::new(),
        };
        println!(
            "| {} | {:.3} | {:.0} |{enc_cols} {ds_} | {dm} | {tr} | {mr} |{enc_ratio}",
            case.name,
            a.secs,
            mb(a.rss)
        );
        if let Some(e) = &enc
            && !case.agree(e, &a)
        {
            disagreements.push(case.name);
            println!("|   ↳ the encoded dataset and its plain export answer differently | | | | | | |");
        }
        if let Some(d) = &d {
            let agree = case.agree(&a, d);
            if !agree {
                disagreements.push(case.name);
                println!(
                    "|   ↳ answers differ: rtvtk {} rows vs DuckDB {} rows | | | | | | |",
                    a.rows.len(),
                    d.rows.len()
                );
            }
        }
    }
    if !disagreements.is_empty() {
        bail!("answers disagree on: {}", disagreements.join(", "));
    }
    if with_duckdb {
        println!("\nrtvtk (plain and encoded) and DuckDB gave the same answers to every query.");
    }
    Ok(())
}

/// A scheduler and executors started by `run_cluster`, stopped when dropped.
#[cfg(feature = "cluster")]
struct LocalCluster(Vec<std::process::Child>);

#[cfg(feature = "cluster")]
impl Drop for LocalCluster {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

#[cfg(feature = "cluster")]
impl LocalCluster {
    /// `executors` executors of `cores` slots and a scheduler on free loopback ports; the address.
    fn start(executors: usize, cores: usize) -> Result<(Self, String)> {
        use std::io::BufRead;
        let exe = std::env::current_exe().context("finding the rtvtk executable")?;
        let spawn = |args: &[&str]| -> Result<(std::process::Child, String)> {
            let mut c = Command::new(&exe)
                .args(args)
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::null())
                .spawn()
                .context("starting rtvtk cluster")?;
            let mut line = String::new();
            let out = c.stdout.take().context("no stdout")?;
            std::io::BufReader::new(out).read_line(&mut line)?;
            Ok((c, line))
        };
        let (s, line) = spawn(&["cluster", "scheduler", "--addr", "127.0.0.1:0"])?;
        let mut me = Self(vec![s]);
        let addr = line
            .strip_prefix("scheduler listening on ")
            .and_then(|l| l.split_whitespace().next())
            .with_context(|| format!("scheduler said {line:?}"))?
            .to_string();
        let cores = cores.to_string();
        for _ in 0..executors {
            me.0.push(spawn(&["cluster", "executor", "--scheduler", &addr, "--cores", &cores])?.0);
        }
        Ok((me, format!("df://{addr}")))
    }
}

/// The suite in-process and on local clusters of `counts` executors: time ratios against the
/// in-process session in the same run (answers checked).
#[cfg(feature = "cluster")]
pub fn run_cluster(dataset: &Path, counts: &[usize], cores: usize, runs: usize) -> Result<()> {
    let ds = store::Dataset::open(dataset).with_context(|| format!("opening {}", dataset.display()))?;
    let (lo, hi) = query::SceneContext::of(&ds).bounds.unwrap_or(([0.0; 3], [1.0; 3]));
    let tree = ds.tree_entry_at(ds.tree_count() as usize / 2)?.map_or(0, |e| e.info.id.0);
    let dataset = std::path::absolute(dataset)?;
    println!(
        "query suite on {} ({} rays, {} segments): in-process (rtvtk's operators) vs Ballista clusters of {:?} executors x {cores} slots on this machine; median of {runs} warm runs",
        dataset.display(),
        ds.ray_count(),
        ds.manifest().segments.len(),
        counts
    );
    let cases = suite(tree, lo, hi);
    let mut base = Vec::new();
    for case in &cases {
        base.push(ours_on(&dataset, case, runs, None, None)?);
    }
    let mut columns = Vec::new();
    for &n in counts {
        let (cluster, url) = LocalCluster::start(n, cores)?;
        // Executors register on their first poll: wait for a first answer.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
        loop {
            let out = Command::new(std::env::current_exe()?)
                .arg("sql")
                .arg(&dataset)
                .args(["SELECT count(*) FROM rays", "--cluster", &url])
                .output()?;
            if out.status.success() {
                break;
            }
            if std::time::Instant::now() > deadline {
                bail!("the cluster of {n} executors never answered: {}", String::from_utf8_lossy(&out.stderr));
            }
            std::thread::sleep(std::time::Duration::from_millis(500));
        }
        let mut col = Vec::new();
        for (case, b) in cases.iter().zip(&base) {
            let m = ours_on(&dataset, case, runs, None, Some(&url))?;
            if !case.agree(&m, b) {
                bail!("{}: the cluster of {n} answers differently from the in-process session", case.name);
            }
            col.push(m.secs);
        }
        drop(cluster);
        columns.push(col);
    }
    let heads: Vec<String> = counts.iter().map(|n| format!(" {n} exec s | ratio |")).collect();
    println!("\n| query | in-process s |{}", heads.concat());
    println!("|---|---|{}", "---|---|".repeat(counts.len()));
    for (i, (case, b)) in cases.iter().zip(&base).enumerate() {
        let cells: Vec<String> =
            columns.iter().map(|c| format!(" {:.3} | {:.2}x |", c[i], c[i] / b.secs.max(1e-9))).collect();
        println!("| {} | {:.3} |{}", case.name, b.secs, cells.concat());
    }
    println!("\nratio: cluster time / in-process time (below 1: the cluster is faster). Every answer matched.");
    Ok(())
}

#[cfg(not(feature = "cluster"))]
pub fn run_cluster(_: &Path, _: &[usize], _: usize, _: usize) -> Result<()> {
    bail!("--cluster: this rtvtk was built without the `cluster` feature")
}

#[cfg(test)]
mod tests {
    use super::same_answer;

    fn rows(v: &[&[&str]]) -> Vec<Vec<String>> {
        v.iter().map(|r| r.iter().map(|c| c.to_string()).collect()).collect()
    }

    #[test]
    fn answers_compare_as_sets_with_a_float_tolerance() {
        let a = rows(&[&["shadow", "2", "0.5"], &["camera", "0", "0.1234567"]]);
        let b = rows(&[&["camera", "0", "0.12345670000001"], &["shadow", "2.0", "0.5"]]);
        assert!(same_answer(&a, &b));
        assert!(!same_answer(&a, &rows(&[&["camera", "0", "0.1234567"], &["shadow", "2", "0.51"]])));
        assert!(!same_answer(&a, &rows(&[&["camera", "0", "0.1234567"]])));
        assert!(!same_answer(&a, &rows(&[&["camera", "0", "0.1234567"], &["diffuse", "2", "0.5"]])));
    }
}
