#![allow(clippy::unwrap_used)]
//! `rtvtk serve` as a shared service: bearer-token access, what statements can reach, limits on
//! running/queued queries and on a query's time and memory, cancellation, per-query log lines
//! and a graceful shutdown.

use std::io::{BufRead, BufReader, Read};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use arrow_flight::sql::client::FlightSqlServiceClient;
use arrow_flight::{FlightInfo, Ticket};
use futures::{StreamExt, TryStreamExt};
use tonic::transport::Channel;

mod common;
use common::{record, rtvtk};

/// A slow query: the rays crossed with themselves (~10⁹ rows at this size), streamed batch by
/// batch (so each step of its execution is short and stops soon after it is cancelled).
const SLOW: &str = "SELECT a.tree_id, b.ray FROM rays a, rays b";

/// The server process (killed when dropped) and what it wrote to stderr.
struct Server {
    child: Child,
    stderr: Arc<Mutex<String>>,
    url: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Server {
    fn log(&self) -> String {
        self.stderr.lock().unwrap().clone()
    }
}

fn serve(dataset: &Path, args: &[&str], env: &[(&str, &str)]) -> Server {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_rtvtk"));
    cmd.args([&["serve", dataset.to_str().unwrap(), "--addr", "127.0.0.1:0"], args].concat())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .env_remove("RTVTK_TOKEN");
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd.spawn().unwrap();
    let stderr = Arc::new(Mutex::new(String::new()));
    let sink = stderr.clone();
    let mut err = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        let mut buf = [0u8; 4096];
        while let Ok(n) = err.read(&mut buf) {
            if n == 0 {
                break;
            }
            sink.lock().unwrap().push_str(&String::from_utf8_lossy(&buf[..n]));
        }
    });
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
    let addr = line.split("://").nth(1).and_then(|s| s.split_whitespace().next());
    let addr = addr.unwrap_or_else(|| panic!("no address in {line:?}; stderr: {}", stderr.lock().unwrap())).to_string();
    Server { child, stderr, url: format!("http://{addr}") }
}

fn trace(dir: &Path) -> std::path::PathBuf {
    let t = dir.join("t");
    record(&t, &["--scene", "cornell", "--size", "48x32", "--spp", "4", "--threads", "2"]);
    t
}

async fn client(url: &str) -> FlightSqlServiceClient<Channel> {
    FlightSqlServiceClient::new(Channel::from_shared(url.to_string()).unwrap().connect().await.unwrap())
}

async fn rows(c: &mut FlightSqlServiceClient<Channel>, info: FlightInfo) -> Result<usize, tonic::Status> {
    let mut n = 0;
    for e in info.endpoint {
        let ticket: Ticket = e.ticket.unwrap();
        let mut s = c.do_get(ticket).await.map_err(status)?;
        while let Some(b) = s.next().await {
            n += b.map_err(status)?.num_rows();
        }
    }
    Ok(n)
}

fn status(e: impl std::fmt::Display) -> tonic::Status {
    // The client wraps the server's status in its own error: keep its text, code by the text.
    let text = e.to_string();
    let code = [
        tonic::Code::Unauthenticated,
        tonic::Code::ResourceExhausted,
        tonic::Code::DeadlineExceeded,
        tonic::Code::Cancelled,
        tonic::Code::InvalidArgument,
    ]
    .map(|c| (c.description(), c))
    .iter()
    .find(|(k, _)| text.contains(k))
    .map_or(tonic::Code::Unknown, |(_, c)| *c);
    tonic::Status::new(code, text)
}

async fn run_sql(c: &mut FlightSqlServiceClient<Channel>, sql: &str) -> Result<usize, tonic::Status> {
    let info = c.execute(sql.to_string(), None).await.map_err(status)?;
    rows(c, info).await
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap()
}

#[test]
fn off_loopback_a_token_is_required_and_checked() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let out = rtvtk(&["serve", t.to_str().unwrap(), "--addr", "0.0.0.0:0"]);
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("a token is required") && e.contains("--token-file") && e.contains("RTVTK_TOKEN"), "{e}");
    let token_file = tmp.path().join("token");
    std::fs::write(&token_file, "s3cret-T0ken\n").unwrap();
    let s = serve(&t, &["--token-file", token_file.to_str().unwrap()], &[]);
    rt().block_on(async {
        let mut anon = client(&s.url).await;
        let e = run_sql(&mut anon, "SELECT 1").await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::Unauthenticated, "{e}");
        let mut wrong = client(&s.url).await;
        wrong.set_token("s3cret-T0kem".into());
        assert_eq!(run_sql(&mut wrong, "SELECT 1").await.unwrap_err().code(), tonic::Code::Unauthenticated);
        let mut bearer = client(&s.url).await;
        bearer.set_token("s3cret-T0ken".into());
        assert_eq!(run_sql(&mut bearer, "SELECT count(*) FROM rays").await.unwrap(), 1);
        // The Flight handshake: basic auth with the token as password answers a bearer token.
        let mut shake = client(&s.url).await;
        shake.handshake("analyst", "s3cret-T0ken").await.unwrap();
        assert_eq!(run_sql(&mut shake, "SELECT 1").await.unwrap(), 1);
        let mut bad_shake = client(&s.url).await;
        assert!(bad_shake.handshake("analyst", "guess").await.is_err());
    });
    std::thread::sleep(Duration::from_millis(200));
    assert!(!s.log().contains("s3cret"), "the token is never logged: {}", s.log());
    // The environment variable works too.
    let s = serve(&t, &[], &[("RTVTK_TOKEN", "env-token")]);
    rt().block_on(async {
        let mut c = client(&s.url).await;
        assert_eq!(run_sql(&mut c, "SELECT 1").await.unwrap_err().code(), tonic::Code::Unauthenticated);
        c.set_token("env-token".into());
        assert_eq!(run_sql(&mut c, "SELECT 1").await.unwrap(), 1);
    });
}

#[test]
fn statements_reach_nothing_but_the_served_datasets() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let s = serve(&t, &["--quiet"], &[]);
    rt().block_on(async {
        let mut c = client(&s.url).await;
        for sql in [
            "SELECT * FROM '/etc/passwd'",
            "SELECT * FROM 'file:///etc/passwd'",
            "SELECT * FROM read_csv('/etc/passwd')",
            "SELECT * FROM parquet_metadata('/etc/passwd')",
            "CREATE EXTERNAL TABLE p STORED AS CSV LOCATION '/etc/passwd'",
            "COPY (SELECT 1) TO '/tmp/rtvtk-ops-leak.csv'",
            "EXPLAIN ANALYZE COPY (SELECT 1) TO '/tmp/rtvtk-ops-leak.csv'",
            "EXPLAIN ANALYZE SELECT * FROM '/etc/passwd'",
        ] {
            let e = run_sql(&mut c, sql).await.unwrap_err();
            let m = e.message().to_string();
            assert!(!m.contains("root:"), "{sql}: the file's content leaked: {m}");
            assert_ne!(e.code(), tonic::Code::Ok, "{sql}");
        }
        assert!(!Path::new("/tmp/rtvtk-ops-leak.csv").exists());
        // Very long and very deeply nested statements: clear errors, no crash.
        let long = format!("SELECT {} 1", "1 + ".repeat(300_000));
        let e = run_sql(&mut c, &long).await.unwrap_err();
        assert!(e.message().contains("at most"), "{}", e.message());
        let nested = format!("SELECT {}1{}", "(".repeat(5000), ")".repeat(5000));
        let e = run_sql(&mut c, &nested).await.unwrap_err();
        assert!(e.message().to_lowercase().contains("recursion") || e.message().contains("nested"), "{}", e.message());
        let subqueries = format!("SELECT * FROM {}(SELECT 1){}", "(SELECT * FROM ".repeat(2000), ") x".repeat(2000));
        assert!(run_sql(&mut c, &subqueries).await.is_err());
        assert_eq!(run_sql(&mut c, "SELECT count(*) FROM rays").await.unwrap(), 1, "still serving");
    });
}

#[test]
fn limits_and_cancellation_stop_one_query_and_spare_the_rest() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let s = serve(
        &t,
        &["--max-concurrent", "1", "--max-queued", "1", "--query-timeout", "1500ms", "--log-format", "json"],
        &[],
    );
    rt().block_on(async {
        // One slow query runs; of three quick ones sent together one waits and one is refused,
        // naming the limits (sent again until that happens: on a loaded machine the slow one
        // takes a while to start).
        let url = s.url.clone();
        let slow = tokio::spawn(async move { run_sql(&mut client(&url).await, SLOW).await });
        let t0 = Instant::now();
        let (refused, waited) = loop {
            let probes: Vec<_> = (0..3)
                .map(|_| {
                    let url = s.url.clone();
                    tokio::spawn(async move { run_sql(&mut client(&url).await, "SELECT 2").await })
                })
                .collect();
            let mut outcomes = Vec::new();
            for p in probes {
                outcomes.push(p.await.unwrap());
            }
            let refused = outcomes
                .iter()
                .find_map(|o| o.as_ref().err().filter(|e| e.code() == tonic::Code::ResourceExhausted).cloned());
            if let Some(e) = refused {
                break (e, outcomes.iter().filter(|o| o.is_ok()).count());
            }
            assert!(t0.elapsed() < Duration::from_secs(10), "never refused: {outcomes:?}; {}", s.log());
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        assert!(
            refused.message().contains("--max-concurrent 1") && refused.message().contains("--max-queued 1"),
            "{refused}"
        );
        assert!(waited >= 1, "the queued quick query ran once there was room");
        // The slow one hits the time limit alone (or, when the probes came first, was the one
        // refused: then a slow query alone shows the limit).
        let e = slow.await.unwrap().unwrap_err();
        let e = match e.code() {
            tonic::Code::ResourceExhausted => run_sql(&mut client(&s.url).await, SLOW).await.unwrap_err(),
            _ => e,
        };
        assert_eq!(e.code(), tonic::Code::DeadlineExceeded, "{e}");
        assert!(e.message().contains("--query-timeout"), "{e}");
        assert!(t0.elapsed() < Duration::from_secs(15));
        // CancelFlightInfo stops a running query.
        let mut c = client(&s.url).await;
        let info = c.execute(SLOW.to_string(), None).await.unwrap();
        let ticket = info.endpoint[0].ticket.clone().unwrap();
        let mut c2 = client(&s.url).await;
        let stream = tokio::spawn(async move {
            let r = c2.do_get(ticket).await.map_err(status)?;
            r.try_collect::<Vec<_>>().await.map_err(status)
        });
        tokio::time::sleep(Duration::from_millis(300)).await;
        let mut flight =
            arrow_flight::FlightClient::new(Channel::from_shared(s.url.clone()).unwrap().connect().await.unwrap());
        // Cancelled once it runs (NotCancellable before its stream started).
        let t0 = Instant::now();
        loop {
            let r = flight.cancel_flight_info(arrow_flight::CancelFlightInfoRequest::new(info.clone())).await.unwrap();
            if r.status == arrow_flight::CancelStatus::Cancelled as i32 {
                break;
            }
            assert_eq!(r.status, arrow_flight::CancelStatus::NotCancellable as i32);
            assert!(t0.elapsed() < Duration::from_secs(10), "the query never ran: {}", s.log());
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let e = stream.await.unwrap().unwrap_err();
        assert_eq!(e.code(), tonic::Code::Cancelled, "{e}");
        assert_eq!(run_sql(&mut c, "SELECT count(*) FROM rays").await.unwrap(), 1, "still serving");
    });
    std::thread::sleep(Duration::from_millis(300));
    // One JSON line per query, with its outcome.
    let log = s.log();
    let lines: Vec<serde_json::Value> =
        log.lines().filter(|l| l.starts_with('{')).map(|l| serde_json::from_str(l).unwrap()).collect();
    let outcomes: Vec<&str> = lines.iter().map(|l| l["outcome"].as_str().unwrap()).collect();
    assert!(
        outcomes.contains(&"timed out") && outcomes.contains(&"cancelled") && outcomes.contains(&"finished"),
        "{log}"
    );
    assert!(outcomes.iter().any(|o| o.starts_with("refused: the server is busy")), "{log}");
    for l in &lines {
        assert!(
            l["secs"].is_number() && l["rows"].is_number() && l["bytes"].is_number() && l["sql"].is_string(),
            "{l}"
        );
    }
}

#[test]
fn a_query_over_its_memory_limit_fails_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let s = serve(&t, &["--query-memory", "64KiB", "--quiet"], &[]);
    rt().block_on(async {
        let mut c = client(&s.url).await;
        let e = run_sql(&mut c, "SELECT tree_id, ray, t FROM rays ORDER BY t, tree_id, ray").await;
        let e = e.unwrap_err();
        assert!(e.message().contains("memory limit of 65536 bytes (--query-memory"), "{e}");
        assert_eq!(run_sql(&mut c, "SELECT count(*) FROM rays").await.unwrap(), 1, "still serving");
    });
}

#[test]
fn sigterm_drains_then_cancels_and_exits_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let mut s = serve(&t, &["--drain-timeout", "1s"], &[]);
    let url = s.url.clone();
    let rt = rt();
    let slow = rt.spawn(async move { run_sql(&mut client(&url).await, SLOW).await });
    std::thread::sleep(Duration::from_millis(400));
    // SAFETY: signalling our own child process.
    unsafe { libc::kill(s.child.id() as libc::pid_t, libc::SIGTERM) };
    let t0 = Instant::now();
    let code = loop {
        if let Some(c) = s.child.try_wait().unwrap() {
            break c;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "the server did not stop: {}", s.log());
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(code.success(), "exit status {code:?}: {}", s.log());
    // The client's stream ends in an error: the cancellation's status, or (when the process has
    // exited before the client read the trailers) the connection's end.
    let e = rt.block_on(slow).unwrap().unwrap_err();
    let m = e.message();
    assert!(
        m.contains("shutting down") || e.code() == tonic::Code::Cancelled || m.contains("error reading a body"),
        "{e}"
    );
    let log = s.log();
    assert!(log.contains("shutting down") && log.contains("cancelled"), "{log}");
}

/// Peak resident memory of a process (Linux), bytes.
fn peak_rss(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: u64 =
        s.lines().find(|l| l.starts_with("VmHWM:")).unwrap().split_whitespace().nth(1).unwrap().parse().unwrap();
    kb * 1024
}

/// The load test: 32 clients for 4 s mixing canned-analysis queries, one-tree lookups and a
/// query over its memory limit; every answer is checked against the in-process session's by
/// `rtvtk bench serve`, none is lost, the over-limit one fails alone, and the server stays
/// within its total memory limit plus the process's own overhead.
#[test]
fn thirty_two_clients_get_right_answers_within_the_memory_limit() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path().join("t");
    record(&t, &["--scene", "cornell", "--size", "96x64", "--spp", "8", "--threads", "2"]);
    let s = serve(&t, &["--memory-limit", "256MiB", "--query-memory", "4MiB", "--max-queued", "64", "--quiet"], &[]);
    let before = peak_rss(s.child.id());
    let out = rtvtk(&[
        "bench",
        "serve",
        t.to_str().unwrap(),
        "--connect",
        &s.url,
        "--clients",
        "32",
        "--seconds",
        "4",
        "--over-limit",
    ]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("0 wrong answers, 0 errors"), "{text}");
    for kind in ["one tree", "coherence by kind and depth", "over its memory limit", "rays by kind"] {
        assert!(text.contains(&format!("| {kind} |")), "{kind} ran: {text}");
    }
    let peak = peak_rss(s.child.id());
    eprintln!("{text}server peak RSS {} MiB (idle {} MiB)", peak >> 20, before >> 20);
    // The total pool bounds what queries hold; the process itself (code, tokio, tonic buffers,
    // decoded pages the scans hold outside the pool) is the overhead: 192 MiB stated.
    assert!(peak < (256 << 20) + (192 << 20), "peak RSS {} MiB", peak >> 20);
    rt().block_on(async { assert_eq!(run_sql(&mut client(&s.url).await, "SELECT 1").await.unwrap(), 1) });
}

#[test]
fn bad_input_gets_a_clear_status_and_nothing_else() {
    use std::io::Write;
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let mut s = serve(&t, &[], &[]);
    // Garbage bytes on the port, and a connection closed mid-frame.
    let addr = s.url.trim_start_matches("http://").to_string();
    for junk in
        [&b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"[..], &[0xffu8; 4096][..], b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n\x00\x00"]
    {
        let mut tcp = std::net::TcpStream::connect(&addr).unwrap();
        let _ = tcp.write_all(junk);
        drop(tcp);
    }
    rt().block_on(async {
        // The server still accepts (a connection refused or reset in the moment the junk is
        // dropped is retried, for up to 5 s).
        let t0 = Instant::now();
        let mut c = loop {
            match Channel::from_shared(s.url.clone()).unwrap().connect().await {
                Ok(ch) => break FlightSqlServiceClient::new(ch),
                Err(e) => assert!(t0.elapsed() < Duration::from_secs(5), "the server stopped accepting: {e}"),
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        // An oversized message (over tonic's 4 MiB decoding limit).
        let huge = format!("SELECT '{}'", "x".repeat(5 << 20));
        let e = run_sql(&mut c, &huge).await.unwrap_err();
        assert!(e.message().contains("message") || e.message().contains("at most"), "{e}");
        // An unknown action.
        let ch = Channel::from_shared(s.url.clone()).unwrap().connect().await;
        let mut flight = arrow_flight::FlightClient::new(
            ch.unwrap_or_else(|e| panic!("{e}: server {:?}, log: {}", s.child.try_wait(), s.log())),
        );
        let e = flight.do_action(arrow_flight::Action::new("DropEverything", "")).await.err().unwrap().to_string();
        assert!(e.contains("unknown action") && e.contains("DropEverything"), "{e}");
        // A ticket that is not ours.
        let e = flight.do_get(Ticket::new("not a ticket")).await.err().unwrap().to_string();
        assert!(!e.is_empty());
        // A prepared statement bound with the wrong number and type of parameters.
        let mut ps = c.prepare("SELECT count(*) FROM rays WHERE depth >= $1".to_string(), None).await.unwrap();
        let two = arrow::array::RecordBatch::try_from_iter([
            ("$1", std::sync::Arc::new(arrow::array::Int64Array::from(vec![1])) as arrow::array::ArrayRef),
            ("$2", std::sync::Arc::new(arrow::array::Int64Array::from(vec![2])) as arrow::array::ArrayRef),
        ])
        .unwrap();
        ps.set_parameters(two).unwrap();
        let e = ps.execute().await.err().map(|e| e.to_string());
        assert!(
            e.as_ref().is_some_and(|e| e.contains("takes 1") && e.contains("2 values")),
            "two values for one parameter: {e:?}"
        );
        let text = arrow::array::RecordBatch::try_from_iter([(
            "$1",
            std::sync::Arc::new(arrow::array::StringArray::from(vec!["deep"])) as arrow::array::ArrayRef,
        )])
        .unwrap();
        let mut ps = c.prepare("SELECT count(*) FROM rays WHERE depth >= $1".to_string(), None).await.unwrap();
        ps.set_parameters(text).unwrap();
        assert!(ps.execute().await.is_err(), "a string for a number");
        assert_eq!(run_sql(&mut c, "SELECT count(*) FROM rays").await.unwrap(), 1, "still serving");
    });
}

/// A client dropping its stream stops the query: the session's memory reservation falls back
/// to zero (in-process, to watch the pool).
#[test]
fn a_dropped_stream_releases_the_query_memory() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    rt().block_on(async {
        let sources = vec![query::TraceSource::parse(t.to_str().unwrap())];
        let ctx = query::session(&sources).await.unwrap();
        let pool = ctx.runtime_env().memory_pool.clone();
        let service =
            query::service::TraceService::with_options(ctx, query::service::ServiceOptions::default()).unwrap();
        let listener = query::service::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", query::service::local_addr(&listener).unwrap());
        tokio::spawn(query::service::serve_with(service, listener, std::future::pending()));
        let mut c = client(&url).await;
        // A hash join holds its build side while the (large) join streams out.
        let sql = "SELECT a.tree_id, b.ray FROM rays a JOIN rays b ON a.prim = b.prim";
        let info = c.execute(sql.to_string(), None).await.unwrap();
        let mut stream = c.do_get(info.endpoint[0].ticket.clone().unwrap()).await.unwrap();
        let first = stream.next().await.unwrap().unwrap();
        assert!(first.num_rows() > 0);
        let held = pool.reserved();
        assert!(held > 0, "the join holds memory while streaming");
        drop(stream);
        let t0 = Instant::now();
        while pool.reserved() > 0 {
            assert!(t0.elapsed() < Duration::from_secs(10), "still {} bytes reserved", pool.reserved());
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        eprintln!("{held} bytes reserved while streaming, 0 after the client dropped the stream");
    });
}

/// The ADBC Flight SQL driver (from PyPI) with a token: refused without it, answered with it.
#[test]
fn adbc_python_client_sends_the_token() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let s = serve(&t, &["--quiet"], &[("RTVTK_TOKEN", "adbc-T0ken")]);
    let script = r#"
import sys, json, warnings
warnings.simplefilter("ignore")
import adbc_driver_flightsql.dbapi as flightsql
import adbc_driver_flightsql as fs
url = sys.argv[1].replace("http://", "grpc://")
out = {}
try:
    con = flightsql.connect(url)
    cur = con.cursor(); cur.execute("SELECT 1"); out["anon"] = "accepted"
except Exception as e:
    out["anon"] = str(e)
con = flightsql.connect(url, db_kwargs={fs.DatabaseOptions.AUTHORIZATION_HEADER.value: "Bearer adbc-T0ken"})
cur = con.cursor(); cur.execute("SELECT count(*) FROM rays"); out["rays"] = cur.fetchone()[0]
print(json.dumps(out))
"#;
    let out = Command::new("python3").args(["-c", script, &s.url]).output().unwrap();
    assert!(out.status.success(), "python3/adbc: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["anon"].as_str().unwrap().to_lowercase().contains("unauthenticated"), "{v}");
    assert!(v["rays"].as_u64().unwrap() > 0, "{v}");
}

/// TLS with a self-signed certificate made here (openssl): a client trusting it gets answers, a
/// plain-text client does not; a file that is not a certificate is refused at start.
#[test]
fn tls_serves_clients_that_trust_the_certificate() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let p = |n: &str| tmp.path().join(n);
    let (cert, key, ca) = (p("cert.pem"), p("key.pem"), p("ca.pem"));
    std::fs::write(p("ext.cnf"), "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n").unwrap();
    let openssl = |args: &[&str]| {
        let o = Command::new("openssl")
            .current_dir(tmp.path())
            .args(args)
            .output()
            .expect("openssl (apt-get install openssl)");
        assert!(o.status.success(), "openssl {args:?}: {}", String::from_utf8_lossy(&o.stderr));
    };
    // A test CA, and the server's certificate signed by it.
    openssl(&[
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "1",
        "-subj",
        "/CN=rtvtk test CA",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
    ]);
    openssl(&[
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-subj",
        "/CN=localhost",
        "-keyout",
        "key.pem",
        "-out",
        "srv.csr",
    ]);
    openssl(&[
        "x509",
        "-req",
        "-in",
        "srv.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca.key",
        "-CAcreateserial",
        "-days",
        "1",
        "-out",
        "cert.pem",
        "-extfile",
        "ext.cnf",
    ]);
    let bad = rtvtk(&[
        "serve",
        t.to_str().unwrap(),
        "--addr",
        "127.0.0.1:0",
        "--tls-cert",
        key.to_str().unwrap(),
        "--tls-key",
        key.to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&bad.stderr).contains("not a PEM certificate"));
    let s = serve(&t, &["--tls-cert", cert.to_str().unwrap(), "--tls-key", key.to_str().unwrap(), "--quiet"], &[]);
    let url = s.url.replace("http://", "https://");
    let pem = std::fs::read(&ca).unwrap();
    rt().block_on(async {
        let tls = tonic::transport::ClientTlsConfig::new()
            .ca_certificate(tonic::transport::Certificate::from_pem(&pem))
            .domain_name("localhost");
        let channel = Channel::from_shared(url.clone()).unwrap().tls_config(tls).unwrap().connect().await.unwrap();
        let mut c = FlightSqlServiceClient::new(channel);
        assert_eq!(run_sql(&mut c, "SELECT count(*) FROM rays").await.unwrap(), 1);
        // Plain text to a TLS port: no answer.
        let plain = Channel::from_shared(s.url.clone()).unwrap().connect().await;
        if let Ok(ch) = plain {
            assert!(run_sql(&mut FlightSqlServiceClient::new(ch), "SELECT 1").await.is_err());
        }
    });
}

/// `render --connect` draws a dataset the client is never told the path of, from the service's
/// second dataset (`--dataset`): scene, camera and rays through SQL; the picture is the local
/// render's.
#[test]
fn render_connect_draws_the_served_dataset_as_a_local_render_does() {
    let tmp = tempfile::tempdir().unwrap();
    let t = trace(tmp.path());
    let other = tmp.path().join("other");
    record(&other, &["--scene", "cornell-glass", "--size", "32x24", "--spp", "1", "--threads", "2"]);
    let named = format!("t={}", t.display());
    let s = serve(&other, &[&named], &[]);
    let layers = ["--layers", "geometry,composition,rays", "--pixel", "24,16", "--size", "192x128"];
    let local = tmp.path().join("local.png");
    let out = rtvtk(&[&["render", t.to_str().unwrap(), "--out", local.to_str().unwrap()][..], &layers[..]].concat());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let remote = tmp.path().join("remote.png");
    let url = s.url.replace("http://", "grpc://");
    let out = rtvtk(
        &[&["render", "--connect", &url, "--dataset", "t", "--out", remote.to_str().unwrap()][..], &layers[..]]
            .concat(),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}\nserver: {}", s.log());
    let (a, b) = (image::open(&local).unwrap().to_rgba8(), image::open(&remote).unwrap().to_rgba8());
    assert_eq!(a.dimensions(), b.dimensions());
    let differ =
        a.pixels().zip(b.pixels()).filter(|(p, q)| p.0.iter().zip(q.0).any(|(x, y)| x.abs_diff(y) > 2)).count();
    eprintln!("{differ} of {} pixels differ; remote's report:\n{err}", a.len() / 4);
    assert_eq!(differ, 0, "the served dataset draws as the local one");
    // A dataset the service does not serve is named with what it does serve.
    let out = rtvtk(&["render", "--connect", &url, "--dataset", "nope", "--out", remote.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("nope") && err.contains("t.rays"), "{err}");
}
