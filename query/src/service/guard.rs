//! What makes the query service shareable: bearer-token access, admission (a bound on running
//! and queued queries), per-query time and memory limits, cancellation, and one log line per
//! query.

use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant, SystemTime};

use arrow::array::RecordBatch;
use arrow_flight::error::FlightError;
use datafusion::error::DataFusionError;
use datafusion::execution::memory_pool::{MemoryConsumer, MemoryLimit, MemoryPool, MemoryReservation};
use datafusion::physical_plan::SendableRecordBatchStream;
use futures::{Future, Stream};
use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};
use tonic::{Request, Status};

/// How the service logs its queries (stderr).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LogFormat {
    /// Nothing.
    #[default]
    Quiet,
    /// One readable line per query.
    Text,
    /// One JSON object per line.
    Json,
}

/// The service's limits and access rules.
#[derive(Clone, Debug)]
pub struct ServiceOptions {
    /// The bearer token clients must send (`authorization: Bearer TOKEN`, or a Flight handshake
    /// with basic auth whose password is the token); `None`: no access control.
    pub token: Option<String>,
    /// A query running longer fails with `DeadlineExceeded`.
    pub query_timeout: Option<Duration>,
    /// Queries executing at once; more wait in a queue.
    pub max_concurrent: usize,
    /// Queries waiting at most; more are refused with `ResourceExhausted`.
    pub max_queued: usize,
    /// Memory one query's operators may hold (within the session's total pool).
    pub query_memory: Option<usize>,
    /// After the shutdown signal, running queries may finish for this long, then are cancelled.
    pub drain_timeout: Duration,
    pub log: LogFormat,
    /// TLS: the server's certificate chain and private key (PEM).
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
}

impl Default for ServiceOptions {
    fn default() -> Self {
        ServiceOptions {
            token: None,
            query_timeout: None,
            max_concurrent: std::thread::available_parallelism().map_or(4, |n| n.get()),
            max_queued: 64,
            query_memory: None,
            drain_timeout: Duration::from_secs(30),
            log: LogFormat::Quiet,
            tls: None,
        }
    }
}

/// Statements longer than this are refused before parsing.
pub const MAX_SQL_BYTES: usize = 1 << 20;

/// Equal in time independent of where the first difference is (the length is not secret).
fn same_secret(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    let diff = a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y));
    std::hint::black_box(diff) == 0
}

/// Whether `request` carries `token`: `authorization: Bearer TOKEN`, or `Basic` credentials
/// whose password is the token (what Flight handshakes with a user name and password send).
pub fn authorized(token: &str, request: &Request<()>) -> Result<(), Status> {
    use base64::Engine as _;
    let refuse = || {
        Status::unauthenticated(
            "missing or wrong bearer token: send the header `authorization: Bearer TOKEN` (the token the server was started with)",
        )
    };
    let value = request.metadata().get("authorization").and_then(|v| v.to_str().ok()).ok_or_else(refuse)?;
    let (scheme, rest) = value.trim().split_once(' ').ok_or_else(refuse)?;
    let ok = if scheme.eq_ignore_ascii_case("bearer") {
        same_secret(rest.trim().as_bytes(), token.as_bytes())
    } else if scheme.eq_ignore_ascii_case("basic") {
        let decoded = base64::engine::general_purpose::STANDARD.decode(rest.trim()).map_err(|_| refuse())?;
        let password = decoded.iter().position(|&c| c == b':').map_or(&decoded[..0], |i| &decoded[i + 1..]);
        same_secret(password, token.as_bytes())
    } else {
        false
    };
    if ok { Ok(()) } else { Err(refuse()) }
}

/// A running query's cancellation.
#[derive(Default)]
struct Cancel {
    flag: AtomicBool,
    why: Mutex<String>,
    notify: Notify,
}

impl Cancel {
    fn cancel(&self, why: &str) {
        *self.why.lock().unwrap_or_else(|p| p.into_inner()) = why.to_string();
        self.flag.store(true, Ordering::SeqCst);
        self.notify.notify_one();
    }
}

/// The queries running now, by the id their ticket carries.
#[derive(Default)]
pub struct Running {
    next: AtomicU64,
    queries: Mutex<HashMap<u64, Arc<Cancel>>>,
}

impl Running {
    /// A fresh query id for a ticket.
    pub fn new_id(&self) -> u64 {
        self.next.fetch_add(1, Ordering::Relaxed) + 1
    }

    /// Cancels the running query `id`; whether it was running.
    pub fn cancel(&self, id: u64, why: &str) -> bool {
        let q = self.queries.lock().unwrap_or_else(|p| p.into_inner()).get(&id).cloned();
        q.map(|c| c.cancel(why)).is_some()
    }

    /// Cancels every running query.
    pub fn cancel_all(&self, why: &str) -> usize {
        let all: Vec<Arc<Cancel>> = self.queries.lock().unwrap_or_else(|p| p.into_inner()).values().cloned().collect();
        all.iter().for_each(|c| c.cancel(why));
        all.len()
    }

    /// How many queries are executing or streaming.
    pub fn count(&self) -> usize {
        self.queries.lock().unwrap_or_else(|p| p.into_inner()).len()
    }

    fn register(&self, id: u64) -> Arc<Cancel> {
        let c = Arc::new(Cancel::default());
        self.queries.lock().unwrap_or_else(|p| p.into_inner()).insert(id, c.clone());
        c
    }

    fn remove(&self, id: u64) {
        self.queries.lock().unwrap_or_else(|p| p.into_inner()).remove(&id);
    }
}

/// The bound on queries executing at once and waiting.
pub struct Admission {
    running: Arc<Semaphore>,
    waiting: AtomicUsize,
    max_concurrent: usize,
    max_queued: usize,
}

impl Admission {
    pub fn new(max_concurrent: usize, max_queued: usize) -> Self {
        let max_concurrent = max_concurrent.max(1);
        Admission {
            running: Arc::new(Semaphore::new(max_concurrent)),
            waiting: AtomicUsize::new(0),
            max_concurrent,
            max_queued,
        }
    }

    /// A place to run: at once, after waiting in the queue, or `ResourceExhausted` when the
    /// queue is full.
    pub async fn admit(&self) -> Result<OwnedSemaphorePermit, Status> {
        if let Ok(p) = self.running.clone().try_acquire_owned() {
            return Ok(p);
        }
        let waiting = self.waiting.fetch_add(1, Ordering::SeqCst);
        if waiting >= self.max_queued {
            self.waiting.fetch_sub(1, Ordering::SeqCst);
            return Err(Status::resource_exhausted(format!(
                "the server is busy: {} queries are running and {waiting} waiting (--max-concurrent {}, --max-queued {}); try again later",
                self.max_concurrent, self.max_concurrent, self.max_queued
            )));
        }
        let p = self.running.clone().acquire_owned().await;
        self.waiting.fetch_sub(1, Ordering::SeqCst);
        p.map_err(|_| Status::unavailable("the server is shutting down"))
    }
}

/// One query's memory within the session's pool: refuses growth beyond `limit` with a clear
/// `ResourcesExhausted` (except where [`crate::memory::granted_always`]: a repartition's queues,
/// counted but never refused), and passes everything on to the shared pool (the process total).
#[derive(Debug)]
pub struct QueryPool {
    shared: Arc<dyn MemoryPool>,
    limit: usize,
    used: AtomicUsize,
}

impl QueryPool {
    pub fn new(shared: Arc<dyn MemoryPool>, limit: usize) -> Self {
        QueryPool { shared, limit, used: AtomicUsize::new(0) }
    }
}

impl std::fmt::Display for QueryPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "QueryPool(limit {} bytes)", self.limit)
    }
}

impl MemoryPool for QueryPool {
    fn name(&self) -> &str {
        "rtvtk query pool"
    }
    fn register(&self, consumer: &MemoryConsumer) {
        self.shared.register(consumer);
    }
    fn unregister(&self, consumer: &MemoryConsumer) {
        self.shared.unregister(consumer);
    }
    fn grow(&self, reservation: &MemoryReservation, additional: usize) {
        self.used.fetch_add(additional, Ordering::SeqCst);
        self.shared.grow(reservation, additional);
    }
    fn shrink(&self, reservation: &MemoryReservation, shrink: usize) {
        self.used.fetch_sub(shrink.min(self.used.load(Ordering::SeqCst)), Ordering::SeqCst);
        self.shared.shrink(reservation, shrink);
    }
    fn try_grow(&self, reservation: &MemoryReservation, additional: usize) -> datafusion::error::Result<()> {
        if crate::memory::granted_always(reservation.consumer()) {
            self.grow(reservation, additional);
            return Ok(());
        }
        let before = self.used.fetch_add(additional, Ordering::SeqCst);
        if before + additional > self.limit {
            self.used.fetch_sub(additional, Ordering::SeqCst);
            return Err(DataFusionError::ResourcesExhausted(format!(
                "the query needs more than its memory limit of {} bytes (--query-memory; {} held, {additional} more asked by {})",
                self.limit,
                before,
                reservation.consumer().name()
            )));
        }
        if let Err(e) = self.shared.try_grow(reservation, additional) {
            self.used.fetch_sub(additional, Ordering::SeqCst);
            return Err(e);
        }
        Ok(())
    }
    fn reserved(&self) -> usize {
        self.used.load(Ordering::SeqCst)
    }
    fn memory_limit(&self) -> MemoryLimit {
        MemoryLimit::Finite(self.limit)
    }
}

/// What the log line says of a query.
pub struct QueryLog {
    pub id: u64,
    pub sql: String,
    pub peer: String,
    pub format: LogFormat,
    started: SystemTime,
    clock: Instant,
}

impl QueryLog {
    pub fn new(id: u64, sql: &str, peer: String, format: LogFormat) -> Self {
        QueryLog { id, sql: truncate(sql, 200), peer, format, started: SystemTime::now(), clock: Instant::now() }
    }

    /// Writes the query's line (nothing when quiet).
    pub fn write(&self, outcome: &str, rows: u64, bytes: u64) {
        let secs = self.clock.elapsed().as_secs_f64();
        let start = self.started.duration_since(SystemTime::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64());
        match self.format {
            LogFormat::Quiet => {}
            LogFormat::Text => eprintln!(
                "rtvtk serve: query {} from {}: {outcome}, {rows} rows, {bytes} bytes, {secs:.3} s: {}",
                self.id, self.peer, self.sql
            ),
            LogFormat::Json => eprintln!(
                "{{\"query\":{},\"peer\":{},\"start\":{start:.3},\"outcome\":{},\"rows\":{rows},\"bytes\":{bytes},\"secs\":{secs:.6},\"sql\":{}}}",
                self.id,
                json_string(&self.peer),
                json_string(outcome),
                json_string(&self.sql)
            ),
        }
    }
}

/// At most `max` characters of `s` on one line, with an ellipsis when cut.
fn truncate(s: &str, max: usize) -> String {
    let one_line: String = s.split_whitespace().collect::<Vec<_>>().join(" ");
    match one_line.char_indices().nth(max) {
        Some((i, _)) => format!("{}…", &one_line[..i]),
        None => one_line,
    }
}

fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            c if (c as u32) < 0x20 => out.push_str(&format!("\\u{:04x}", c as u32)),
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// A query's result stream under the service's rules: holds its admission permit, ends with
/// `DeadlineExceeded` past the time limit and with `Cancelled` when cancelled (dropping the
/// execution, which releases its memory), unregisters and logs itself when done or dropped.
pub struct Guarded {
    inner: Option<SendableRecordBatchStream>,
    _permit: OwnedSemaphorePermit,
    deadline: Option<(Duration, Pin<Box<tokio::time::Sleep>>)>,
    cancel: Arc<Cancel>,
    cancelled: Pin<Box<dyn Future<Output = ()> + Send>>,
    running: Arc<Running>,
    log: QueryLog,
    rows: u64,
    bytes: u64,
    done: bool,
}

impl Guarded {
    pub fn new(
        inner: SendableRecordBatchStream,
        permit: OwnedSemaphorePermit,
        timeout: Option<Duration>,
        running: Arc<Running>,
        log: QueryLog,
    ) -> Self {
        let cancel = running.register(log.id);
        let c = cancel.clone();
        Guarded {
            inner: Some(inner),
            _permit: permit,
            deadline: timeout.map(|t| (t, Box::pin(tokio::time::sleep(t)))),
            cancel,
            cancelled: Box::pin(async move { c.notify.notified().await }),
            running,
            log,
            rows: 0,
            bytes: 0,
            done: false,
        }
    }

    fn finish(&mut self, outcome: &str) {
        self.done = true;
        self.inner = None;
        self.running.remove(self.log.id);
        self.log.write(outcome, self.rows, self.bytes);
    }
}

impl Stream for Guarded {
    type Item = Result<RecordBatch, FlightError>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let me = &mut *self;
        if me.done {
            return Poll::Ready(None);
        }
        let _ = me.cancelled.as_mut().poll(cx);
        if me.cancel.flag.load(Ordering::SeqCst) {
            let why = me.cancel.why.lock().unwrap_or_else(|p| p.into_inner()).clone();
            me.finish("cancelled");
            return Poll::Ready(Some(Err(FlightError::Tonic(Box::new(Status::cancelled(format!(
                "query {} cancelled: {why}",
                me.log.id
            )))))));
        }
        if let Some((limit, sleep)) = me.deadline.as_mut()
            && sleep.as_mut().poll(cx).is_ready()
        {
            let limit = *limit;
            me.finish("timed out");
            return Poll::Ready(Some(Err(FlightError::Tonic(Box::new(Status::deadline_exceeded(format!(
                "query {} ran past the server's time limit of {:.1} s (--query-timeout)",
                me.log.id,
                limit.as_secs_f64()
            )))))));
        }
        let Some(inner) = me.inner.as_mut() else { return Poll::Ready(None) };
        match inner.as_mut().poll_next(cx) {
            Poll::Pending => Poll::Pending,
            Poll::Ready(Some(Ok(batch))) => {
                me.rows += batch.num_rows() as u64;
                me.bytes += batch.get_array_memory_size() as u64;
                Poll::Ready(Some(Ok(batch)))
            }
            Poll::Ready(Some(Err(e))) => {
                me.finish(&format!("failed: {}", truncate(&e.to_string(), 200)));
                Poll::Ready(Some(Err(FlightError::ExternalError(Box::new(e)))))
            }
            Poll::Ready(None) => {
                me.finish("finished");
                Poll::Ready(None)
            }
        }
    }
}

impl Drop for Guarded {
    fn drop(&mut self) {
        if !self.done {
            self.finish("stopped: the client went away");
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn tokens_are_checked_as_bearer_or_basic_password() {
        use base64::Engine as _;
        let with = |v: &str| {
            let mut r = Request::new(());
            r.metadata_mut().insert("authorization", v.parse().unwrap());
            r
        };
        assert!(authorized("s3cret", &with("Bearer s3cret")).is_ok());
        assert!(authorized("s3cret", &with("bearer  s3cret ")).is_ok());
        let basic = base64::engine::general_purpose::STANDARD.encode("alice:s3cret");
        assert!(authorized("s3cret", &with(&format!("Basic {basic}"))).is_ok());
        for bad in ["Bearer s3cre", "Bearer s3cret2", "s3cret", "Basic !!!", "Token s3cret"] {
            let e = authorized("s3cret", &with(bad)).unwrap_err();
            assert_eq!(e.code(), tonic::Code::Unauthenticated, "{bad}");
            assert!(!e.message().contains("s3cret"), "the token is never echoed");
        }
        assert!(authorized("s3cret", &Request::new(())).is_err());
        assert!(same_secret(b"abc", b"abc") && !same_secret(b"abc", b"abd") && !same_secret(b"abc", b"ab"));
    }

    #[test]
    fn log_lines_are_one_line_and_valid_json_strings() {
        assert_eq!(truncate("SELECT\n  1,\t2", 100), "SELECT 1, 2");
        assert_eq!(truncate(&"x".repeat(300), 200).chars().count(), 201);
        assert_eq!(json_string("a\"b\\c\nd"), "\"a\\\"b\\\\c\\u000ad\"");
    }

    #[tokio::test]
    async fn admission_queues_then_refuses() {
        let a = Arc::new(Admission::new(1, 1));
        let first = a.admit().await.unwrap();
        let b = a.clone();
        let queued = tokio::spawn(async move { b.admit().await.map(|_| ()) });
        tokio::time::sleep(Duration::from_millis(50)).await;
        let e = a.admit().await.unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        assert!(e.message().contains("--max-concurrent 1") && e.message().contains("--max-queued 1"), "{e}");
        drop(first);
        queued.await.unwrap().unwrap();
    }
}
