//! `rtvtk serve`: the read-only Arrow Flight SQL query service over one or more datasets.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LogFormatArg {
    /// One readable line per query on stderr.
    Text,
    /// One JSON object per query on stderr.
    Json,
}

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// Datasets (`PATH` or `NAME=PATH`; the first one's tables are also unqualified, as in
    /// `rtvtk sql`).
    #[arg(required = true, num_args = 1..)]
    datasets: Vec<String>,
    /// Where to listen, HOST:PORT (port 0 picks a free one; the address is printed at start).
    /// Off loopback (0.0.0.0:PORT to accept other machines) a token is required.
    #[arg(long, default_value = "127.0.0.1:50051")]
    addr: String,
    /// A file holding the bearer token clients must send (`authorization: Bearer TOKEN`);
    /// the environment variable RTVTK_TOKEN is the alternative.
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Memory all queries together may hold, e.g. `8GiB` (default: 80% of this machine's memory).
    #[arg(long, value_parser = crate::sql::parse_bytes)]
    memory_limit: Option<usize>,
    /// Memory one query may hold, e.g. `1GiB` (within --memory-limit).
    #[arg(long, value_parser = crate::sql::parse_bytes)]
    query_memory: Option<usize>,
    /// A query running longer fails alone (`30s`, `500ms`, `5m`; unlimited by default).
    #[arg(long, value_parser = parse_duration)]
    query_timeout: Option<Duration>,
    /// Queries executing at once (default: the cores); more wait in a queue.
    #[arg(long)]
    max_concurrent: Option<usize>,
    /// Queries waiting at most; more are refused with ResourceExhausted.
    #[arg(long, default_value_t = 64)]
    max_queued: usize,
    /// On SIGINT/SIGTERM running queries may finish for this long, then are cancelled.
    #[arg(long, default_value = "30s", value_parser = parse_duration)]
    drain_timeout: Duration,
    /// The per-query log line's format.
    #[arg(long, value_enum, default_value = "text")]
    log_format: LogFormatArg,
    /// No per-query log lines.
    #[arg(long)]
    quiet: bool,
    /// TLS: the server's certificate chain (PEM); with --tls-key.
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// TLS: the certificate's private key (PEM); with --tls-cert.
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
}

/// `30s`, `500ms`, `5m`, `1h` or plain seconds (`2.5`).
pub fn parse_duration(s: &str) -> Result<Duration, String> {
    let t = s.trim();
    let (num, scale) = if let Some(v) = t.strip_suffix("ms") {
        (v, 1e-3)
    } else if let Some(v) = t.strip_suffix('s') {
        (v, 1.0)
    } else if let Some(v) = t.strip_suffix('m') {
        (v, 60.0)
    } else if let Some(v) = t.strip_suffix('h') {
        (v, 3600.0)
    } else {
        (t, 1.0)
    };
    let v: f64 = num.trim().parse().map_err(|_| format!("bad duration {s:?}: expected e.g. 30s, 500ms, 5m"))?;
    if !(v.is_finite() && v >= 0.0) {
        return Err(format!("bad duration {s:?}: expected a non-negative time"));
    }
    Duration::try_from_secs_f64(v * scale).map_err(|e| format!("bad duration {s:?}: {e}"))
}

/// The token from `--token-file` or `RTVTK_TOKEN`, never empty.
fn token(a: &ServeArgs) -> Result<Option<String>> {
    let raw = match &a.token_file {
        Some(p) => {
            Some(std::fs::read_to_string(p).with_context(|| format!("cannot read the token file {}", p.display()))?)
        }
        None => std::env::var("RTVTK_TOKEN").ok(),
    };
    match raw.map(|t| t.trim().to_string()) {
        Some(t) if t.is_empty() => bail!("the token (--token-file or RTVTK_TOKEN) is empty"),
        Some(t) if t.chars().any(|c| !c.is_ascii_graphic()) => {
            bail!("the token must be printable ASCII without spaces (it travels in an HTTP header)")
        }
        t => Ok(t),
    }
}

pub fn run(a: &ServeArgs) -> Result<()> {
    if let Some(d) = a.datasets.iter().find(|d| !crate::sql::is_dataset(d)) {
        bail!("{d}: not a dataset directory (expected {})", store::MANIFEST_FILE);
    }
    let token = token(a)?;
    let tls = match (&a.tls_cert, &a.tls_key) {
        (Some(c), Some(k)) => {
            let read = |p: &PathBuf, what: &str| {
                std::fs::read(p).with_context(|| format!("cannot read the TLS {what} {}", p.display()))
            };
            let (cert, key) = (read(c, "certificate")?, read(k, "key")?);
            if !String::from_utf8_lossy(&cert).contains("-----BEGIN CERTIFICATE-----") {
                bail!("{}: not a PEM certificate (expected -----BEGIN CERTIFICATE-----)", c.display());
            }
            if !String::from_utf8_lossy(&key).contains("PRIVATE KEY-----") {
                bail!("{}: not a PEM private key (expected -----BEGIN ... PRIVATE KEY-----)", k.display());
            }
            Some((cert, key))
        }
        _ => None,
    };
    let sources: Vec<query::TraceSource> = a.datasets.iter().map(|d| query::TraceSource::parse(d)).collect();
    let rt = crate::runtime()?;
    let served = rt.block_on(async {
        let listener = query::service::bind(&a.addr)?;
        let addr = query::service::local_addr(&listener)?;
        if !addr.ip().is_loopback() && token.is_none() {
            bail!(
                "refusing to serve every trace to anyone who can reach {addr}: off loopback a token is required \
                 (--token-file PATH or the environment variable RTVTK_TOKEN; clients send `authorization: Bearer TOKEN`)"
            );
        }
        let session = query::SessionOptions { memory_limit: a.memory_limit, ..Default::default() };
        let engine = query::Engine::open(&sources, &session).await?;
        let ctx = engine.session().context("an in-process session")?.clone();
        let mut options = query::service::ServiceOptions {
            token: token.clone(),
            query_timeout: a.query_timeout,
            max_queued: a.max_queued,
            query_memory: a.query_memory,
            drain_timeout: a.drain_timeout,
            tls: tls.clone(),
            log: match (a.quiet, a.log_format) {
                (true, _) => query::service::LogFormat::Quiet,
                (false, LogFormatArg::Text) => query::service::LogFormat::Text,
                (false, LogFormatArg::Json) => query::service::LogFormat::Json,
            },
            ..Default::default()
        };
        if let Some(n) = a.max_concurrent {
            options.max_concurrent = n.max(1);
        }
        let service = query::service::TraceService::with_options(ctx, options)?;
        let names: Vec<&str> = sources.iter().map(|s| s.name.as_str()).collect();
        // One line on stdout, flushed, so scripts and tests can read the address.
        use std::io::Write as _;
        let mut out = std::io::stdout();
        writeln!(
            out,
            "rtvtk serve: Arrow Flight SQL on {}://{addr} (read-only; {}; datasets: {})",
            if tls.is_some() { "grpc+tls" } else { "grpc" },
            if token.is_some() { "bearer token required" } else { "no token: loopback only" },
            names.join(", ")
        )
        .and_then(|_| out.flush())
        .context("writing the address")?;
        query::service::serve_with(service, listener, shutdown_signal()).await?;
        Ok(())
    });
    // A query cancelled in the middle of a long step of its execution finishes that step on a
    // worker thread: do not wait for it.
    rt.shutdown_timeout(Duration::from_millis(500));
    served
}

/// Set by the SIGINT/SIGTERM handler.
static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

#[cfg(unix)]
extern "C" fn on_stop_signal(_: libc::c_int) {
    // Async-signal-safe: one atomic store.
    STOP.store(true, std::sync::atomic::Ordering::SeqCst);
}

/// Completes on SIGINT or SIGTERM (checked every 50 ms).
async fn shutdown_signal() {
    #[cfg(unix)]
    // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, on_stop_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_stop_signal as *const () as libc::sighandler_t);
    }
    while !STOP.load(std::sync::atomic::Ordering::SeqCst) {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}
