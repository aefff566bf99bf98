#![cfg(feature = "cluster")]
#![allow(clippy::unwrap_used)]
//! rtvtk on a Ballista cluster: a scheduler and two executors as `rtvtk cluster` processes on
//! loopback (free ports, all stopped by the test). The `.slt` suite and the canned analyses run
//! against it with the in-process answers; a query's plan survives the codec; an executor killed
//! during a long query gives a clear error or a retried answer, and the cluster keeps serving.

use std::process::Child;
use std::sync::Arc;
use std::time::{Duration, Instant};

use datafusion::error::DataFusionError;

mod common;
mod slt_db;

/// Child processes, killed when dropped (also when the test fails).
struct Procs(Vec<Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for c in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

fn start(args: &[&str]) -> (Child, String) {
    // Their log lines (Ballista's warnings) show with a failing test's output.
    common::start_with_first_line(args)
}

fn executor(scheduler: &str) -> Child {
    let (child, line) = start(&["cluster", "executor", "--scheduler", scheduler, "--cores", "2"]);
    assert!(line.starts_with("executor on 127.0.0.1:"), "{line}");
    child
}

async fn cluster_session(url: &str, sources: &[query::TraceSource]) -> datafusion::prelude::SessionContext {
    cluster::connect(url, sources).await.unwrap().session().unwrap().clone()
}

async fn rows(ctx: &datafusion::prelude::SessionContext, sql: &str) -> Result<String, DataFusionError> {
    let batches = ctx.sql_with_options(sql, query::service::read_only_sql_options()).await?.collect().await?;
    Ok(arrow::util::pretty::pretty_format_batches(&batches)?.to_string())
}

/// `plan` encoded and decoded with the cluster's codec, as a task's plan travels.
fn through_codec(
    plan: Arc<dyn datafusion::physical_plan::ExecutionPlan>,
    ctx: &datafusion::prelude::SessionContext,
) -> Arc<dyn datafusion::physical_plan::ExecutionPlan> {
    let codec = cluster::physical_codec();
    let bytes = datafusion_proto::bytes::physical_plan_to_bytes_with_extension_codec(plan, codec.as_ref()).unwrap();
    datafusion_proto::bytes::physical_plan_from_bytes_with_extension_codec(&bytes, &ctx.task_ctx(), codec.as_ref())
        .unwrap()
}

/// Records a trace of several segments (about 60K rays in chunks of at most 1,000-ray segments'
/// worth) into `dir` and returns how many segments it has.
fn record_many(dir: &std::path::Path) -> usize {
    common::record(
        dir,
        &[
            "--scene",
            "cornell",
            "--size",
            "64x64",
            "--spp",
            "4",
            "--seed",
            "3",
            "--threads",
            "1",
            "--segment-rays",
            "1000",
            "--record-visits",
        ],
    );
    let info = common::ok(&["info", dir.to_str().unwrap()]);
    let segments: usize = info
        .lines()
        .find_map(|l| l.strip_prefix("segments"))
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or_else(|| panic!("no segment count in {info}"));
    assert!(segments > 2, "the test needs a dataset of several segments: {info}");
    segments
}

/// Queries over the many-segment dataset whose cluster answers must equal the in-process ones:
/// whole scans, pushed-down pixel and tree filters (row ranges within segments), the counts
/// answered from segment statistics, a ray function, a self-join, `ray_paths`, a limit.
const MANY_SEGMENT_QUERIES: [&str; 9] = [
    "SELECT count(*) AS n, sum(nodes_visited) AS v, min(tree_id) AS lo, max(tree_id) AS hi FROM rays",
    "SELECT kind, depth, count(*) AS n FROM rays GROUP BY kind, depth ORDER BY kind, depth",
    "SELECT count(*) AS n, sum(pixel_x + pixel_y) AS p FROM rays WHERE pixel_y BETWEEN 20 AND 40 AND depth >= 1",
    "SELECT tree_id, depth, count(*) AS n FROM rays WHERE tree_id IN (3, 5000, 9000, 15000) GROUP BY tree_id, depth ORDER BY tree_id, depth",
    "SELECT count(DISTINCT morton3(origin_x, origin_y, origin_z, 5)) AS cells, round(dir_coherence(dir_x, dir_y, dir_z), 6) AS c FROM rays",
    "SELECT count(*) AS n FROM rays a JOIN rays b ON a.tree_id = b.tree_id AND b.depth = a.depth + 1",
    "SELECT path, count(*) AS n FROM ray_paths GROUP BY path ORDER BY n DESC, path LIMIT 10",
    "SELECT count(*) AS n FROM (SELECT tree_id FROM rays LIMIT 100)",
    "SELECT pixel_x % 4 AS px, count(*) AS n FROM rays WHERE kind = 'shadow' GROUP BY px ORDER BY px",
];

#[test]
fn each_task_of_a_scan_stage_reads_only_its_segments() {
    // What the scheduler does to a scan stage: `SliceableScans` plans the scans as file scans of
    // one group per segment, Ballista's task builder cuts a task's plan down to its partitions,
    // and the plan crosses the codec. Each task must then read its own segments only: the tasks'
    // rows add up to the table's, whatever the pruning kept.
    use datafusion::physical_optimizer::PhysicalOptimizerRule;
    let tmp = tempfile::tempdir().unwrap();
    let many = tmp.path().join("many");
    let segments = record_many(&many);
    let sources = vec![query::TraceSource { name: "many".into(), path: many.clone() }];
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let direct = rt.block_on(query::session(&sources)).unwrap();
    let count = |sql: &str| -> usize {
        let b = rt.block_on(async { direct.sql(sql).await.unwrap().collect().await.unwrap() });
        b.iter().map(|b| b.num_rows()).sum()
    };
    // The scan leaf of a query's plan (these plans are chains).
    let leaf_of = |sql: &str| {
        let mut plan = rt.block_on(async { direct.sql(sql).await.unwrap().create_physical_plan().await.unwrap() });
        while let Some(child) = plan.children().first().map(|c| (*c).clone()) {
            plan = child;
        }
        plan
    };
    let rows_of = |plan: Arc<dyn datafusion::physical_plan::ExecutionPlan>| -> usize {
        let b = rt.block_on(datafusion::physical_plan::collect(plan, direct.task_ctx())).unwrap();
        b.iter().map(|b| b.num_rows()).sum()
    };
    let total: usize = count("SELECT tree_id FROM rays");
    for (sql, kept) in [
        ("SELECT tree_id, depth FROM rays", segments),
        ("SELECT pixel_x, t FROM rays WHERE depth >= 1", segments),
        ("SELECT tree_id FROM rays WHERE tree_id < 2000", 0),
        ("SELECT path FROM ray_paths", segments),
    ] {
        let scan = leaf_of(sql);
        let sliceable = query::SliceableScans.optimize(scan.clone(), direct.state().config_options()).unwrap();
        let partitions = sliceable.properties().output_partitioning().partition_count();
        if kept > 0 {
            assert_eq!(partitions, kept, "{sql}: one partition per segment");
        } else {
            assert!(partitions >= 1 && partitions < segments, "{sql}: pruned to {partitions} of {segments}");
        }
        let mut rows = 0;
        for p in 0..partitions {
            let task = cluster::restrict_plan_to_partitions(sliceable.clone(), &[p]).unwrap();
            let task = through_codec(task, &direct);
            let shown = datafusion::physical_plan::displayable(task.as_ref()).indent(false).to_string();
            assert!(
                shown.contains("file_type=rtvtk_segments") && shown.contains("{1 group: "),
                "{sql}, task {p}: {shown}"
            );
            assert_eq!(task.properties().output_partitioning().partition_count(), 1, "{sql}, task {p}: {shown}");
            rows += rows_of(task);
        }
        // Every task read its own segments: together, what the whole scan reads in-process.
        assert_eq!(rows, rows_of(scan), "{sql}: the tasks' rows add up to the scan's");
        if !sql.contains("WHERE") {
            assert_eq!(rows, total, "{sql}: every ray once");
        }
    }
}

#[test]
fn queries_run_on_a_cluster_with_the_in_process_answers() {
    let tmp = tempfile::tempdir().unwrap();
    let sources = slt_db::sources(tmp.path());
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();

    let (scheduler, line) = start(&["cluster", "scheduler", "--addr", "127.0.0.1:0", "--executor-timeout", "10"]);
    let mut procs = Procs(vec![scheduler]);
    let addr = line.strip_prefix("scheduler listening on ").unwrap().split_whitespace().next().unwrap().to_string();
    let url = format!("df://{addr}");
    procs.0.push(executor(&addr));
    procs.0.push(executor(&addr));

    // The executors register on their first poll: wait until a query runs.
    let ctx = rt.block_on(cluster_session(&url, &sources));
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let r = rt.block_on(async {
            tokio::time::timeout(Duration::from_secs(10), rows(&ctx, "SELECT count(*) FROM rays")).await
        });
        match r {
            Ok(Ok(_)) => break,
            other => assert!(Instant::now() < deadline, "the cluster never answered: {other:?}"),
        }
    }

    // The plan of a query with the ray functions, the scan and a scene payload crosses the codec
    // and runs with the same answer.
    let direct = rt.block_on(query::session(&sources)).unwrap();
    let check = "SELECT kind, count(*) AS n, sum(CASE WHEN aims_at_light(origin_x, origin_y, origin_z, dir_x, dir_y, dir_z) THEN 1 ELSE 0 END) AS lit, \
                 count(DISTINCT morton3(origin_x, origin_y, origin_z, 4)) AS cells, round(dir_coherence(dir_x, dir_y, dir_z), 6) AS c \
                 FROM rays WHERE depth >= 1 GROUP BY kind ORDER BY kind";
    let small = "SELECT kind, depth, count(*) AS n, avg(nodes_visited) AS nodes FROM rays GROUP BY kind, depth ORDER BY kind, depth";
    for (sql, operator) in [(check, "RaysScanExec"), (small, "SmallGroupsExec")] {
        let plan = rt.block_on(async { direct.sql(sql).await.unwrap().create_physical_plan().await.unwrap() });
        let shown = datafusion::physical_plan::displayable(plan.as_ref()).indent(false).to_string();
        assert!(shown.contains(operator), "{sql}: {shown}");
        let back = through_codec(plan, &direct);
        let back_shown = datafusion::physical_plan::displayable(back.as_ref()).indent(false).to_string();
        assert!(back_shown.contains(operator), "{sql} decoded: {back_shown}");
        let decoded = rt.block_on(datafusion::physical_plan::collect(back, direct.task_ctx())).unwrap();
        let want = rt.block_on(rows(&direct, sql)).unwrap();
        assert_eq!(arrow::util::pretty::pretty_format_batches(&decoded).unwrap().to_string(), want);
        assert_eq!(rt.block_on(rows(&ctx, sql)).unwrap(), want, "{sql} on the cluster");
    }

    // The whole .slt suite, with the answers the in-process sessions give.
    let (u, s) = (url.clone(), sources.clone());
    let factory: slt_db::Factory = Arc::new(move || {
        let (u, s) = (u.clone(), s.clone());
        Box::pin(async move {
            let engine = cluster::connect(&u, &s).await.map_err(|e| DataFusionError::External(Box::new(e)))?;
            Ok(engine.session().cloned().unwrap_or_default())
        })
    });
    let failures = slt_db::run_all(&rt, factory, false);
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));

    // The canned analyses: the same reports.
    let good = sources[0].path.to_str().unwrap().to_string();
    let bad = sources[1].path.to_str().unwrap().to_string();
    for args in [
        vec!["analyze", "coherence", good.as_str()],
        vec!["analyze", "bvh", good.as_str()],
        vec!["analyze", "bugs", bad.as_str()],
        vec!["analyze", "diff", good.as_str(), bad.as_str()],
    ] {
        let here = common::ok(&args);
        let there = common::ok(&[args.as_slice(), &["--cluster", url.as_str()]].concat());
        assert_eq!(here, there, "{args:?}");
    }

    // A dataset of several segments: every task of a scan stage reads its own segments, so the
    // answers are the in-process ones.
    let many = tmp.path().join("many");
    record_many(&many);
    let many_sources = vec![query::TraceSource { name: "many".into(), path: many.clone() }];
    let many_ctx = rt.block_on(cluster_session(&url, &many_sources));
    let many_direct = rt.block_on(query::session(&many_sources)).unwrap();
    for sql in MANY_SEGMENT_QUERIES {
        let want = rt.block_on(rows(&many_direct, sql)).unwrap();
        assert_eq!(rt.block_on(rows(&many_ctx, sql)).unwrap(), want, "{sql} on the cluster");
    }
    let many_path = many.to_str().unwrap();
    for args in [vec!["analyze", "coherence", many_path], vec!["analyze", "bvh", many_path]] {
        let here = common::ok(&args);
        let there = common::ok(&[args.as_slice(), &["--cluster", url.as_str()]].concat());
        assert_eq!(here, there, "{args:?}");
    }

    // Read-only, as `rtvtk serve`; bad SQL gets DataFusion's error.
    for (sql, says) in [
        ("CREATE TABLE t AS SELECT 1", "not supported"),
        ("SET datafusion.execution.batch_size = 1", "not supported"),
        ("SELECT no_such_column FROM rays", "no_such_column"),
    ] {
        let e = rt.block_on(rows(&ctx, sql)).unwrap_err().to_string();
        assert!(e.contains(says), "{sql}: {e}");
    }
    // A path that is no dataset: the CLI names it once (no cause repeated in the chain).
    let none = many.with_file_name("no-such-dataset");
    let out = common::rtvtk(&["sql", none.to_str().unwrap(), "SELECT 1", "--cluster", url.as_str()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert_eq!(err.matches("expected a dataset directory").count(), 1, "{err}");
    assert!(err.contains("no-such-dataset"), "{err}");

    // An executor dies during a long query: the query fails with an error that says so, or is
    // retried on the other one; either way the next query runs. The query (a three-way join on
    // `kind`: the sum of n^3 over the kinds' ray counts) must still run when the executor dies.
    let long =
        "SELECT count(*) FROM good.rays a JOIN good.rays b ON a.kind = b.kind JOIN good.rays c ON b.kind = c.kind";
    let cube = "SELECT sum(n * n * n) FROM (SELECT kind, count(*) AS n FROM good.rays GROUP BY kind)";
    let value =
        |table: &str| table.lines().nth(3).and_then(|l| l.split('|').nth(1)).unwrap_or_default().trim().to_string();
    let expected = value(&rt.block_on(rows(&direct, cube)).unwrap());
    let ctx2 = ctx.clone();
    let started = Instant::now();
    let handle = rt.spawn(async move { rows(&ctx2, long).await });
    std::thread::sleep(Duration::from_millis(1500));
    assert!(!handle.is_finished(), "the long query ended within 1.5 s: the kill would test nothing");
    let mut victim = procs.0.remove(1);
    victim.kill().unwrap();
    victim.wait().unwrap();
    let outcome = rt.block_on(async { tokio::time::timeout(Duration::from_secs(240), handle).await });
    match outcome {
        Ok(Ok(Ok(answer))) => {
            assert_eq!(value(&answer), expected, "a retried query's answer");
            eprintln!(
                "the query with a killed executor answered (retried) after {:.1} s",
                started.elapsed().as_secs_f64()
            );
        }
        Ok(Ok(Err(e))) => {
            let text = e.to_string();
            assert!(!text.is_empty(), "an error that says what failed");
            eprintln!("the query with a killed executor failed after {:.1} s: {text}", started.elapsed().as_secs_f64());
        }
        other => panic!("the query with a killed executor neither answered nor failed: {other:?}"),
    }
    let after = rt.block_on(async {
        tokio::time::timeout(
            Duration::from_secs(60),
            rows(&ctx, "SELECT kind, count(*) FROM rays GROUP BY kind ORDER BY kind"),
        )
        .await
    });
    let want = rt.block_on(rows(&direct, "SELECT kind, count(*) FROM rays GROUP BY kind ORDER BY kind")).unwrap();
    assert_eq!(after.expect("the cluster answers after losing an executor").unwrap(), want);
    drop(procs);
}

#[test]
fn a_cluster_nobody_runs_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let ds = tmp.path().join("t");
    common::record(&ds, &["--scene", "cornell", "--size", "4x4", "--spp", "1"]);
    let out = common::rtvtk(&["sql", ds.to_str().unwrap(), "SELECT 1", "--cluster", "df://127.0.0.1:1"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot reach the scheduler at 127.0.0.1:1"), "{err}");
    assert_eq!(err.matches("os error").count(), 1, "the cause once: {err}");
    // A timeout a busy executor cannot meet is refused, naming the flag and the floor.
    let out = common::rtvtk(&["cluster", "scheduler", "--addr", "127.0.0.1:0", "--executor-timeout", "4"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--executor-timeout") && err.contains("at least 10 s"), "{err}");
    let out = common::rtvtk(&["sql", ds.to_str().unwrap(), "SELECT 1", "--cluster", "http://x:1"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("expected df://HOST:PORT"));
    let out = common::rtvtk(&["cluster", "executor", "--scheduler", "nowhere"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("HOST:PORT"));
}
