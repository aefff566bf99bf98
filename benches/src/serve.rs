//! `rtvtk bench serve`: many Flight SQL clients at once against the query service (queries per
//! second, p50/p99 latency per query type), every answer checked against the in-process
//! session's; the same queries one at a time in-process are the baseline (the ratio is the
//! service's overhead). Also the load test of issue 27 (`tests/service_ops.rs`).

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use arrow::array::RecordBatch;
use arrow::util::display::{ArrayFormatter, FormatOptions};
use arrow_flight::sql::client::FlightSqlServiceClient;
use datafusion::prelude::SessionContext;
use futures::TryStreamExt;
use tonic::transport::Channel;

use crate::query::{median, same_answer};

/// What `rtvtk bench serve` does.
pub struct ServeBench {
    /// Run against this service (`http://HOST:PORT`) instead of one started in-process.
    pub connect: Option<String>,
    pub token: Option<String>,
    pub clients: usize,
    pub seconds: f64,
    /// Mix in a query over the server's per-query memory limit (expected to fail alone).
    pub over_limit: bool,
}

struct Case {
    kind: &'static str,
    sql: String,
    expected: Option<Vec<Vec<String>>>,
}

/// The over-limit query: every ray's origin and direction in one list each (an aggregate that
/// cannot spill; over 4 MiB from about 180K rays on).
const OVER_LIMIT: &str = "SELECT array_agg(origin_x), array_agg(origin_y), array_agg(origin_z), array_agg(dir_x), \
     array_agg(dir_y), array_agg(dir_z) FROM rays";

/// The in-process service's per-query memory with `--over-limit`.
const OVER_LIMIT_MEMORY: usize = 4 << 20;

fn rows_of(batches: &[RecordBatch]) -> Result<Vec<Vec<String>>> {
    let opts = FormatOptions::default().with_null("NULL");
    let mut out = Vec::new();
    for b in batches {
        let f: Vec<ArrayFormatter> =
            b.columns().iter().map(|c| ArrayFormatter::try_new(c.as_ref(), &opts)).collect::<Result<_, _>>()?;
        for r in 0..b.num_rows() {
            out.push(f.iter().map(|f| f.value(r).to_string()).collect());
        }
    }
    Ok(out)
}

async fn local(ctx: &SessionContext, sql: &str) -> Result<Vec<Vec<String>>> {
    rows_of(&ctx.sql(sql).await?.collect().await?)
}

async fn remote(c: &mut FlightSqlServiceClient<Channel>, sql: &str) -> Result<Vec<Vec<String>>> {
    let info = c.execute(sql.to_string(), None).await?;
    let mut batches = Vec::new();
    for e in info.endpoint {
        let ticket = e.ticket.context("an endpoint without a ticket")?;
        batches.extend(c.do_get(ticket).await?.try_collect::<Vec<_>>().await?);
    }
    rows_of(&batches)
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

pub fn run(dataset: &Path, o: &ServeBench) -> Result<()> {
    if !dataset.join(store::MANIFEST_FILE).is_file() {
        bail!("{}: not a dataset directory (expected {})", dataset.display(), store::MANIFEST_FILE);
    }
    if o.clients == 0 || o.seconds.is_nan() || o.seconds <= 0.0 {
        bail!("--clients and --seconds must be positive");
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async {
        let sources = vec![query::TraceSource::parse(&dataset.to_string_lossy())];
        let ctx = query::session(&sources).await?;
        // The mix: canned-analysis aggregations and point lookups of single trees.
        let ids = local(&ctx, "SELECT tree_id FROM trees ORDER BY tree_id").await?;
        let step = (ids.len() / 16).max(1);
        let wrong = format!("SELECT count(*) FROM rays WHERE {}", query::analyze::WRONG_SHADOW);
        let mut cases: Vec<Case> = [
            ("rays by kind", "SELECT kind, count(*) FROM rays GROUP BY kind ORDER BY kind"),
            (
                "coherence by kind and depth",
                "SELECT kind, depth, dir_coherence(dir_x, dir_y, dir_z), origin_spread(origin_x, origin_y, origin_z), count(*) FROM rays GROUP BY kind, depth",
            ),
            (
                "BVH cost by kind and depth",
                "SELECT kind, depth, avg(nodes_visited), avg(box_tests), avg(tri_tests) FROM rays GROUP BY kind, depth",
            ),
            ("the paper's wrong shadow rays", wrong.as_str()),
        ]
        .into_iter()
        .map(|(kind, sql)| Case { kind, sql: sql.to_string(), expected: None })
        .collect();
        for id in ids.iter().step_by(step).take(16) {
            let sql = format!("SELECT * FROM rays WHERE tree_id = {} ORDER BY ray", id[0]);
            cases.push(Case { kind: "one tree", sql, expected: None });
        }
        // Expected answers, and the baseline: each query alone, in-process, median of 3.
        let mut baseline: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
        for c in &mut cases {
            let mut secs = Vec::new();
            for _ in 0..3 {
                let t = Instant::now();
                c.expected = Some(local(&ctx, &c.sql).await?);
                secs.push(t.elapsed().as_secs_f64());
            }
            baseline.entry(c.kind).or_default().push(median(&secs));
        }
        if o.over_limit {
            cases.push(Case { kind: "over its memory limit", sql: OVER_LIMIT.to_string(), expected: None });
        }
        // The service: given, or started here on a free port.
        let (url, _server) = match &o.connect {
            Some(u) => (u.clone(), None),
            None => {
                let listener = query::service::bind("127.0.0.1:0")?;
                let addr = query::service::local_addr(&listener)?;
                let mut options = query::service::ServiceOptions { token: o.token.clone(), ..Default::default() };
                if o.over_limit {
                    options.query_memory = Some(OVER_LIMIT_MEMORY);
                }
                let service = query::service::TraceService::with_options(ctx.clone(), options)?;
                let h = tokio::spawn(query::service::serve_with(service, listener, std::future::pending()));
                (format!("http://{addr}"), Some(h))
            }
        };
        let cases = Arc::new(cases);
        let deadline = Instant::now() + Duration::from_secs_f64(o.seconds);
        let started = Instant::now();
        let mut tasks = Vec::new();
        for client in 0..o.clients {
            let (cases, url, token) = (cases.clone(), url.clone(), o.token.clone());
            tasks.push(tokio::spawn(async move {
                let channel = Channel::from_shared(url)?.connect().await?;
                let mut c = FlightSqlServiceClient::new(channel);
                if let Some(t) = token {
                    c.set_token(t);
                }
                // (kind, seconds, outcome: "ok" | "mismatch" | "error: ...")
                let mut done: Vec<(&'static str, f64, String)> = Vec::new();
                let mut i = client;
                while Instant::now() < deadline {
                    let case = &cases[i % cases.len()];
                    i += 1;
                    let t = Instant::now();
                    let answer = remote(&mut c, &case.sql).await;
                    let secs = t.elapsed().as_secs_f64();
                    let outcome = match (&case.expected, answer) {
                        (Some(e), Ok(a)) if same_answer(e, &a) => "ok".to_string(),
                        (Some(_), Ok(_)) => "mismatch".to_string(),
                        (None, Err(e)) if e.to_string().contains("memory limit") => "ok".to_string(),
                        (None, Ok(_)) => "error: the over-limit query succeeded".to_string(),
                        (_, Err(e)) => format!("error: {e}"),
                    };
                    done.push((case.kind, secs, outcome));
                }
                anyhow::Ok(done)
            }));
        }
        let mut all = Vec::new();
        for t in tasks {
            all.extend(t.await.context("a client task")??);
        }
        let wall = started.elapsed().as_secs_f64();
        let mut by_kind: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
        let (mut bad, mut errors) = (0usize, Vec::new());
        for (kind, secs, outcome) in &all {
            by_kind.entry(kind).or_default().push(*secs);
            if outcome == "mismatch" {
                bad += 1;
            } else if outcome != "ok" {
                errors.push(outcome.clone());
            }
        }
        println!(
            "{} clients for {wall:.1} s against {url}: {} queries, {:.1} queries/s; {bad} wrong answers, {} errors",
            o.clients,
            all.len(),
            all.len() as f64 / wall,
            errors.len()
        );
        println!(
            "| query | count | queries/s | p50 ms | p99 ms | alone in-process ms (baseline) | p50 / baseline |"
        );
        println!("|---|---|---|---|---|---|---|");
        for (kind, v) in &mut by_kind {
            v.sort_by(f64::total_cmp);
            let base = baseline.get(kind).map(|b| median(b));
            let (p50, p99) = (percentile(v, 0.5), percentile(v, 0.99));
            println!(
                "| {kind} | {} | {:.1} | {:.1} | {:.1} | {} | {} |",
                v.len(),
                v.len() as f64 / wall,
                p50 * 1e3,
                p99 * 1e3,
                base.map_or("-".into(), |b| format!("{:.1}", b * 1e3)),
                base.map_or("-".into(), |b| format!("{:.2}x", p50 / b))
            );
        }
        // Throughput against the same mix one query at a time in-process.
        let alone: f64 = cases.iter().filter_map(|c| baseline.get(c.kind).map(|b| median(b))).sum();
        let served = cases.iter().filter(|c| c.expected.is_some()).count();
        let (qps, base_qps) = (all.len() as f64 / wall, served as f64 / alone);
        println!(
            "throughput: {qps:.1} queries/s served to {} clients; {base_qps:.1} queries/s for the same mix one at a time in-process: {:.2}x",
            o.clients,
            qps / base_qps
        );
        if bad > 0 || !errors.is_empty() {
            errors.sort();
            errors.dedup();
            bail!("{bad} answers differ from the in-process session's; errors: {errors:?}");
        }
        Ok(())
    })
}
