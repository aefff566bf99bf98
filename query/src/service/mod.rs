//! The read-only query service: Arrow Flight SQL over a session of trace datasets.
//!
//! Any Flight SQL client (the ADBC Flight SQL driver from Python/R/Go/Java, the JDBC driver,
//! `arrow_flight::sql::client::FlightSqlServiceClient`) can list catalogs, schemas, tables (with
//! their Arrow schemas) and table types, ask `GetSqlInfo`, run statements and prepared statements
//! (with `$1`-style parameters bound by the client) using every table and ray function of the
//! session, and stream the results as Arrow record batches.
//!
//! The service is stateless: a statement's ticket and a prepared statement's handle carry the SQL
//! (and the bound parameters), so any number of clients can use it concurrently and a restart
//! loses nothing. Every statement is planned with [`read_only_sql_options`]: DDL (`CREATE`,
//! `DROP`), DML (`INSERT`, `COPY ... TO`) and `SET` are refused with `InvalidArgument`, as are
//! updates, ingestion, Substrait plans and transactions.
//!
//! [`ServiceOptions`] make it shareable: a bearer token ([`guard::authorized`]), a bound on
//! queries running and queued, per-query time and memory limits, cancellation
//! (`CancelFlightInfo`, `CancelQuery`, or the client dropping its stream), a drain period on
//! shutdown and a log line per query.

mod guard;
pub use guard::{LogFormat, MAX_SQL_BYTES, QueryPool, ServiceOptions, authorized};

use std::net::{SocketAddr, TcpListener};
use std::sync::Arc;

use guard::{Admission, Guarded, QueryLog, Running};

use arrow::array::{ArrayRef, RecordBatch, StringArray};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use arrow::ipc::reader::StreamReader;
use arrow::ipc::writer::{IpcWriteOptions, StreamWriter};
use arrow_flight::decode::FlightRecordBatchStream;
use arrow_flight::encode::{DictionaryHandling, FlightDataEncoderBuilder};
use arrow_flight::error::FlightError;
use arrow_flight::flight_service_server::{FlightService, FlightServiceServer};
use arrow_flight::sql::metadata::{SqlInfoData, SqlInfoDataBuilder};
use arrow_flight::sql::server::{FlightSqlService, PeekableFlightDataStream};
use arrow_flight::sql::{
    ActionBeginSavepointRequest, ActionBeginSavepointResult, ActionBeginTransactionRequest,
    ActionBeginTransactionResult, ActionClosePreparedStatementRequest, ActionCreatePreparedStatementRequest,
    ActionCreatePreparedStatementResult, ActionCreatePreparedSubstraitPlanRequest, CommandGetCatalogs,
    CommandGetDbSchemas, CommandGetSqlInfo, CommandGetTableTypes, CommandGetTables, CommandPreparedStatementQuery,
    CommandPreparedStatementUpdate, CommandStatementIngest, CommandStatementQuery, CommandStatementSubstraitPlan,
    CommandStatementUpdate, DoPutPreparedStatementResult, ProstMessageExt, SqlInfo, TicketStatementQuery,
};
use arrow_flight::{FlightDescriptor, FlightEndpoint, FlightInfo, IpcMessage, SchemaAsIpc, Ticket};
use bytes::Bytes;
use datafusion::common::ParamValues;
use datafusion::error::DataFusionError;
use datafusion::execution::context::SQLOptions;
use datafusion::logical_expr::LogicalPlan;
use datafusion::prelude::SessionContext;
use datafusion::scalar::ScalarValue;
use futures::TryStreamExt;
use prost::Message;
use tonic::{Request, Response, Status};

use crate::{Error, Result};

/// What a read-only session accepts: queries, `EXPLAIN` and `SHOW`-style reads; no DDL
/// (`CREATE`, `DROP`), no DML (`INSERT`, `COPY ... TO`) and no `SET`.
pub fn read_only_sql_options() -> SQLOptions {
    SQLOptions::new().with_allow_ddl(false).with_allow_dml(false).with_allow_statements(false)
}

/// Binds `addr` (for example `127.0.0.1:50051`; port 0 picks a free one) for [`serve`].
pub fn bind(addr: &str) -> Result<TcpListener> {
    let listener = TcpListener::bind(addr)
        .map_err(|e| Error::Service(format!("cannot listen on {addr:?}: {e} (expected a free HOST:PORT)")))?;
    listener
        .set_nonblocking(true)
        .map_err(|e| Error::Service(format!("cannot set up the listener on {addr:?}: {e}")))?;
    Ok(listener)
}

/// The address a listener from [`bind`] accepts on.
pub fn local_addr(listener: &TcpListener) -> Result<SocketAddr> {
    listener.local_addr().map_err(|e| Error::Service(format!("listener address: {e}")))
}

/// Serves `ctx` read-only over Flight SQL on `listener` until `shutdown` completes (pass
/// `std::future::pending()` to serve until the process ends), with the default options (no
/// token, no limits). Must run inside a Tokio runtime with I/O and timers enabled.
pub async fn serve(
    ctx: &SessionContext,
    listener: TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<()> {
    serve_with(TraceService::with_options(ctx.clone(), ServiceOptions::default())?, listener, shutdown).await
}

/// Serves `service` on `listener` until `shutdown` completes: then no new connection is
/// accepted, running queries may finish for the drain timeout, the rest are cancelled, and it
/// returns once they are gone.
pub async fn serve_with(
    service: TraceService,
    listener: TcpListener,
    shutdown: impl std::future::Future<Output = ()> + Send,
) -> Result<()> {
    let listener = tokio::net::TcpListener::from_std(listener)
        .map_err(|e| Error::Service(format!("cannot use the listener: {e}")))?;
    let incoming = tonic::transport::server::TcpIncoming::from(listener).with_nodelay(Some(true));
    let token = service.options.token.clone();
    let (running, drain, log) = (service.running.clone(), service.options.drain_timeout, service.options.log);
    let stopping = Arc::new(tokio::sync::Notify::new());
    let stopped = stopping.clone();
    let signal = async move {
        shutdown.await;
        if log != LogFormat::Quiet {
            eprintln!(
                "rtvtk serve: shutting down: no new queries; {} running may finish within {:.1} s",
                running.count(),
                drain.as_secs_f64()
            );
        }
        stopped.notify_one();
        let r = running.clone();
        tokio::spawn(async move {
            tokio::time::sleep(drain).await;
            let n = r.cancel_all("the server is shutting down (--drain-timeout passed)");
            if n > 0 && log != LogFormat::Quiet {
                eprintln!("rtvtk serve: cancelled {n} queries still running after the drain timeout");
            }
        });
    };
    let check = move |request: Request<()>| match &token {
        Some(t) => authorized(t, &request).map(|_| request),
        None => Ok(request),
    };
    let mut builder = tonic::transport::Server::builder();
    if let Some((cert, key)) = &service.options.tls {
        let identity = tonic::transport::Identity::from_pem(cert, key);
        builder = builder
            .tls_config(tonic::transport::ServerTlsConfig::new().identity(identity))
            .map_err(|e| Error::Service(format!("TLS: the certificate or key is not usable: {e}")))?;
    }
    let server = builder
        .add_service(FlightServiceServer::with_interceptor(service, check))
        .serve_with_incoming_shutdown(incoming, signal);
    // Connections that outlive the drain (a client holding an idle stream open) do not keep
    // the process: a few seconds after the drain timeout it returns anyway.
    let deadline = async move {
        stopping.notified().await;
        tokio::time::sleep(drain + std::time::Duration::from_secs(5)).await;
    };
    futures::pin_mut!(server, deadline);
    match futures::future::select(server, deadline).await {
        futures::future::Either::Left((r, _)) => {
            r.map_err(|e| Error::Service(format!("Flight SQL server stopped: {e}")))
        }
        futures::future::Either::Right(_) => Ok(()),
    }
}

/// The Flight SQL service over a session (see the module documentation).
pub struct TraceService {
    ctx: SessionContext,
    sql_info: SqlInfoData,
    options: ServiceOptions,
    admission: Arc<Admission>,
    running: Arc<Running>,
}

/// A ticket of this server: `rtvtk1`, the query id (u64 LE), `S` + SQL or `P` + a prepared
/// statement's handle.
const TICKET_MAGIC: &[u8] = b"rtvtk1";

enum TicketBody {
    Sql(String),
    Prepared(Handle),
}

fn encode_ticket(id: u64, body: &TicketBody) -> Result<Bytes, Status> {
    let mut out = TICKET_MAGIC.to_vec();
    out.extend_from_slice(&id.to_le_bytes());
    match body {
        TicketBody::Sql(sql) => {
            out.push(b'S');
            out.extend_from_slice(sql.as_bytes());
        }
        TicketBody::Prepared(h) => {
            out.push(b'P');
            out.extend_from_slice(&h.encode()?);
        }
    }
    Ok(out.into())
}

/// The query id and body of a ticket (a bare SQL ticket of an older server: id `None`).
fn decode_ticket(bytes: &[u8]) -> Result<(Option<u64>, TicketBody), Status> {
    let bad = || Status::invalid_argument("not a statement ticket of this server");
    let Some(rest) = bytes.strip_prefix(TICKET_MAGIC) else {
        let sql = std::str::from_utf8(bytes).map_err(|_| bad())?;
        return Ok((None, TicketBody::Sql(sql.to_string())));
    };
    let id = u64::from_le_bytes(rest.get(..8).ok_or_else(bad)?.try_into().map_err(|_| bad())?);
    let body = match rest.get(8) {
        Some(b'S') => TicketBody::Sql(std::str::from_utf8(&rest[9..]).map_err(|_| bad())?.to_string()),
        Some(b'P') => TicketBody::Prepared(Handle::decode(&rest[9..])?),
        _ => return Err(bad()),
    };
    Ok((Some(id), body))
}

type DoGetStream = <TraceService as FlightService>::DoGetStream;

impl TraceService {
    /// The service with the default options (no token, no limits).
    pub fn new(ctx: SessionContext) -> Result<Self> {
        Self::with_options(ctx, ServiceOptions::default())
    }

    /// The service under `options`.
    pub fn with_options(ctx: SessionContext, options: ServiceOptions) -> Result<Self> {
        let mut b = SqlInfoDataBuilder::new();
        b.append(SqlInfo::FlightSqlServerName, "rtvtk");
        b.append(SqlInfo::FlightSqlServerVersion, env!("CARGO_PKG_VERSION"));
        b.append(SqlInfo::FlightSqlServerArrowVersion, "1.3");
        b.append(SqlInfo::FlightSqlServerReadOnly, true);
        b.append(SqlInfo::FlightSqlServerSql, true);
        b.append(SqlInfo::FlightSqlServerSubstrait, false);
        b.append(SqlInfo::FlightSqlServerTransaction, 0i32); // SQL_SUPPORTED_TRANSACTION_NONE
        b.append(SqlInfo::FlightSqlServerCancel, true);
        b.append(SqlInfo::SqlIdentifierQuoteChar, "\"");
        let sql_info = b.build().map_err(|e| Error::Service(format!("server information: {e}")))?;
        let admission = Arc::new(Admission::new(options.max_concurrent, options.max_queued));
        Ok(Self { ctx, sql_info, options, admission, running: Arc::default() })
    }

    /// Bytes the session's memory pool holds now, over all queries (0 when none runs).
    pub fn memory_reserved(&self) -> usize {
        self.ctx.runtime_env().memory_pool.reserved()
    }

    /// Queries executing or streaming now.
    pub fn running_queries(&self) -> usize {
        self.running.count()
    }

    /// Plans `sql` read-only, with `params` bound when given.
    async fn plan(&self, sql: &str, params: Option<ParamValues>) -> Result<LogicalPlan, Status> {
        if sql.len() > MAX_SQL_BYTES {
            return Err(Status::invalid_argument(format!(
                "the statement is {} bytes long; the server takes at most {MAX_SQL_BYTES}",
                sql.len()
            )));
        }
        let sql = number_placeholders(sql);
        let plan = self.ctx.state().create_logical_plan(&sql).await.map_err(plan_status)?;
        read_only_sql_options().verify_plan(&plan).map_err(plan_status)?;
        match params {
            Some(ParamValues::List(values)) => {
                let types = plan.get_parameter_types().map_err(plan_status)?;
                let expected = types.len();
                if values.len() != expected {
                    return Err(Status::invalid_argument(format!(
                        "parameters: the statement takes {expected} ($1 … ${expected}), {} values were bound",
                        values.len()
                    )));
                }
                // Each value as its placeholder's type (a value that does not convert is an error
                // naming the parameter, not a comparison of mismatched types).
                let mut cast = Vec::with_capacity(values.len());
                for (i, v) in values.into_iter().enumerate() {
                    let want = types.get(&format!("${}", i + 1)).cloned().flatten();
                    let v = match want {
                        Some(t) if v.value.data_type() != t && !v.value.is_null() => {
                            let converted = v.value.cast_to(&t).ok().filter(|c| !c.is_null());
                            let c = converted.ok_or_else(|| {
                                Status::invalid_argument(format!(
                                    "parameter ${}: expected {t}, got {} {}",
                                    i + 1,
                                    v.value.data_type(),
                                    v.value
                                ))
                            })?;
                            datafusion::common::metadata::ScalarAndMetadata::new(c, v.metadata)
                        }
                        _ => v,
                    };
                    cast.push(v);
                }
                plan.with_param_values(ParamValues::List(cast)).map_err(plan_status)
            }
            Some(p) => plan.with_param_values(p).map_err(plan_status),
            None => Ok(plan),
        }
    }

    /// Runs a planned statement once admitted and streams its batches under the time limit
    /// and cancellation, announced with the plan's schema (the one `FlightInfo` advertised;
    /// strict clients compare them).
    async fn execute(&self, plan: LogicalPlan, log: QueryLog) -> Result<Response<DoGetStream>, Status> {
        let permit = match self.admission.admit().await {
            Ok(p) => p,
            Err(e) => {
                log.write(&format!("refused: {}", e.message()), 0, 0);
                return Err(e);
            }
        };
        let schema: SchemaRef = Arc::new(plan.schema().as_arrow().clone());
        let state = self.ctx.state();
        let state = match self.options.query_memory {
            None => state,
            Some(limit) => {
                // The query's own pool inside the session's: its limit, the shared total.
                let rt = state.runtime_env().clone();
                let env = datafusion::execution::runtime_env::RuntimeEnv {
                    memory_pool: Arc::new(QueryPool::new(rt.memory_pool.clone(), limit)),
                    disk_manager: rt.disk_manager.clone(),
                    cache_manager: rt.cache_manager.clone(),
                    object_store_registry: rt.object_store_registry.clone(),
                };
                let mut state = datafusion::execution::SessionStateBuilder::new_from_existing(state)
                    .with_runtime_env(Arc::new(env))
                    .build();
                // A sort reserves this much up front for merging its spills (10 MiB by default):
                // within a small limit, a fraction of it, so that small sorts still run.
                let spill = &mut state.config_mut().options_mut().execution.sort_spill_reservation_bytes;
                *spill = (*spill).min(limit / 8);
                state
            }
        };
        let df = datafusion::dataframe::DataFrame::new(state, plan);
        let stream = match df.execute_stream().await {
            Ok(s) => s,
            Err(e) => {
                log.write(&format!("failed: {e}"), 0, 0);
                return Err(exec_status(e));
            }
        };
        let guarded = Guarded::new(stream, permit, self.options.query_timeout, self.running.clone(), log);
        Ok(encoded(schema, guarded))
    }

    fn log(&self, id: u64, sql: &str, remote: Option<SocketAddr>) -> QueryLog {
        let peer = remote.map_or_else(|| "?".to_string(), |a| a.to_string());
        QueryLog::new(id, sql, peer, self.options.log)
    }

    /// Cancels the queries the tickets of `info` started; whether any was running.
    fn cancel_info(&self, info: &FlightInfo) -> bool {
        let mut any = false;
        for e in &info.endpoint {
            if let Some(t) = &e.ticket
                && let Ok(any_msg) = arrow_flight::sql::Any::decode(&*t.ticket)
                && let Ok(Some(tq)) = any_msg.unpack::<TicketStatementQuery>()
                && let Ok((Some(id), _)) = decode_ticket(&tq.statement_handle)
            {
                any |= self.running.cancel(id, "the client asked to cancel it");
            }
        }
        any
    }

    /// The answer to `request`: a `FlightInfo` announcing `schema`, fetched with `ticket`.
    fn info(
        schema: &Schema,
        ticket: &impl ProstMessageExt,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let ticket = Ticket { ticket: ticket.as_any().encode_to_vec().into() };
        let info = FlightInfo::new()
            .try_with_schema(schema)
            .map_err(|e| Status::internal(format!("encoding the result schema: {e}")))?
            .with_endpoint(FlightEndpoint::new().with_ticket(ticket))
            .with_descriptor(request.into_inner());
        Ok(Response::new(info))
    }

    /// A one-batch stream (catalog answers).
    fn one_batch<E: std::fmt::Display>(batch: Result<RecordBatch, E>) -> Result<Response<DoGetStream>, Status> {
        let batch = batch.map_err(|e| Status::internal(format!("building the answer: {e}")))?;
        Ok(encoded(batch.schema(), futures::stream::once(async { Ok(batch) })))
    }
}

/// `batches` as Flight data announced with `schema`; dictionary columns (`kind`) stay
/// dictionaries, as the schema says.
fn encoded(
    schema: SchemaRef,
    batches: impl futures::Stream<Item = Result<RecordBatch, FlightError>> + Send + 'static,
) -> Response<DoGetStream> {
    let data = FlightDataEncoderBuilder::new()
        .with_schema(schema)
        .with_dictionary_handling(DictionaryHandling::Resend)
        .build(batches)
        .map_err(flight_status);
    Response::new(Box::pin(data))
}

/// JDBC/ODBC-style `?` parameters become `$1`, `$2`, ... (DataFusion's positional form), outside
/// string literals and identifiers; statements without them are returned unchanged.
fn number_placeholders(sql: &str) -> std::borrow::Cow<'_, str> {
    use datafusion::sql::sqlparser::dialect::GenericDialect;
    use datafusion::sql::sqlparser::tokenizer::{Token, Tokenizer};
    if !sql.contains('?') {
        return sql.into();
    }
    let Ok(tokens) = Tokenizer::new(&GenericDialect {}, sql).tokenize_with_location() else {
        return sql.into(); // the planner reports the error
    };
    // Byte offset of each `?` token, from its line and (character) column.
    let line_starts: Vec<usize> = std::iter::once(0).chain(sql.match_indices('\n').map(|(i, _)| i + 1)).collect();
    let offsets: Vec<usize> = tokens
        .iter()
        .filter(|t| matches!(&t.token, Token::Placeholder(p) if p == "?"))
        .filter_map(|t| {
            let start = *line_starts.get(usize::try_from(t.span.start.line).ok()?.checked_sub(1)?)?;
            let column = usize::try_from(t.span.start.column).ok()?.checked_sub(1)?;
            let (offset, c) = sql[start..].char_indices().nth(column)?;
            (c == '?').then_some(start + offset)
        })
        .collect();
    if offsets.is_empty() {
        return sql.into();
    }
    let mut out = String::with_capacity(sql.len() + 2 * offsets.len());
    let mut last = 0;
    for (i, at) in offsets.iter().enumerate() {
        out.push_str(&sql[last..*at]);
        out.push_str(&format!("${}", i + 1));
        last = at + 1;
    }
    out.push_str(&sql[last..]);
    out.into()
}

/// Errors found while planning: the client's statement is at fault.
fn plan_status(e: DataFusionError) -> Status {
    match e {
        DataFusionError::ResourcesExhausted(m) => Status::resource_exhausted(m),
        e => Status::invalid_argument(e.to_string()),
    }
}

/// Errors found while running.
fn exec_status(e: DataFusionError) -> Status {
    match e {
        DataFusionError::ResourcesExhausted(m) => Status::resource_exhausted(m),
        e => Status::internal(e.to_string()),
    }
}

fn flight_status(e: FlightError) -> Status {
    match e {
        FlightError::Tonic(s) => *s,
        FlightError::ExternalError(e) => match e.downcast::<DataFusionError>() {
            Ok(df) => exec_status(*df),
            Err(e) => Status::internal(e.to_string()),
        },
        e => Status::internal(e.to_string()),
    }
}

fn read_only(what: &str) -> Status {
    Status::invalid_argument(format!("rtvtk serve is read-only: {what} is not allowed (send a query)"))
}

/// A prepared statement's handle: the SQL and, once bound, its parameters as an Arrow IPC stream
/// of one row. Layout: `u32` little-endian SQL length, the SQL (UTF-8), the IPC bytes.
struct Handle {
    sql: String,
    params: Option<RecordBatch>,
}

impl Handle {
    fn encode(&self) -> Result<Bytes, Status> {
        let len = u32::try_from(self.sql.len()).map_err(|_| Status::invalid_argument("statement too long"))?;
        let mut out = len.to_le_bytes().to_vec();
        out.extend_from_slice(self.sql.as_bytes());
        if let Some(batch) = &self.params {
            let mut w = StreamWriter::try_new(&mut out, &batch.schema())
                .map_err(|e| Status::internal(format!("encoding parameters: {e}")))?;
            w.write(batch).map_err(|e| Status::internal(format!("encoding parameters: {e}")))?;
            w.finish().map_err(|e| Status::internal(format!("encoding parameters: {e}")))?;
        }
        Ok(out.into())
    }

    fn decode(bytes: &[u8]) -> Result<Self, Status> {
        let bad = || Status::invalid_argument("not a prepared statement handle of this server");
        let len = bytes.get(..4).ok_or_else(bad)?;
        let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
        let sql = bytes.get(4..4 + len).ok_or_else(bad)?;
        let sql = std::str::from_utf8(sql).map_err(|_| bad())?.to_string();
        let rest = &bytes[4 + len..];
        let params = if rest.is_empty() {
            None
        } else {
            let mut r = StreamReader::try_new(rest, None).map_err(|_| bad())?;
            r.next().transpose().map_err(|_| bad())?
        };
        Ok(Self { sql, params })
    }

    /// The bound parameters as positional values (`$1`, `$2`, ... in column order).
    fn param_values(&self) -> Result<Option<ParamValues>, Status> {
        let Some(batch) = &self.params else { return Ok(None) };
        if batch.num_rows() != 1 {
            return Err(Status::invalid_argument(format!(
                "parameters: expected one row of values, got {} (execute once per row)",
                batch.num_rows()
            )));
        }
        let values = batch
            .columns()
            .iter()
            .map(|c| ScalarValue::try_from_array(c, 0))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| Status::invalid_argument(format!("parameters: {e}")))?;
        Ok(Some(ParamValues::from(values)))
    }
}

fn schema_bytes(schema: &Schema) -> Result<Bytes, Status> {
    let IpcMessage(bytes) = SchemaAsIpc::new(schema, &IpcWriteOptions::default())
        .try_into()
        .map_err(|e: arrow::error::ArrowError| Status::internal(format!("encoding a schema: {e}")))?;
    Ok(bytes)
}

#[tonic::async_trait]
impl FlightSqlService for TraceService {
    type FlightService = TraceService;

    async fn get_flight_info_statement(
        &self,
        query: CommandStatementQuery,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let plan = self.plan(&query.query, None).await?;
        let id = self.running.new_id();
        let ticket = TicketStatementQuery { statement_handle: encode_ticket(id, &TicketBody::Sql(query.query))? };
        Self::info(plan.schema().as_arrow(), &ticket, request)
    }

    async fn do_get_statement(
        &self,
        ticket: TicketStatementQuery,
        request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        let (id, body) = decode_ticket(&ticket.statement_handle)?;
        let id = id.unwrap_or_else(|| self.running.new_id());
        let (sql, params) = match body {
            TicketBody::Sql(sql) => (sql, None),
            TicketBody::Prepared(h) => {
                let p = h.param_values()?;
                (h.sql, p)
            }
        };
        let log = self.log(id, &sql, request.remote_addr());
        let plan = match self.plan(&sql, params).await {
            Ok(p) => p,
            Err(e) => {
                log.write(&format!("refused: {}", e.message()), 0, 0);
                return Err(e);
            }
        };
        self.execute(plan, log).await
    }

    async fn do_action_create_prepared_statement(
        &self,
        query: ActionCreatePreparedStatementRequest,
        _request: Request<arrow_flight::Action>,
    ) -> Result<ActionCreatePreparedStatementResult, Status> {
        let plan = self.plan(&query.query, None).await?;
        let mut params: Vec<(String, DataType)> = plan
            .get_parameter_types()
            .map_err(plan_status)?
            .into_iter()
            .map(|(name, t)| (name, t.unwrap_or(DataType::Null)))
            .collect();
        // `$1`, `$2`, ... in number order.
        params.sort_by_key(|(name, _)| name.trim_start_matches('$').parse::<u64>().unwrap_or(u64::MAX));
        let param_schema = Schema::new(params.into_iter().map(|(n, t)| Field::new(n, t, true)).collect::<Vec<_>>());
        Ok(ActionCreatePreparedStatementResult {
            prepared_statement_handle: Handle { sql: query.query, params: None }.encode()?,
            dataset_schema: schema_bytes(plan.schema().as_arrow())?,
            parameter_schema: schema_bytes(&param_schema)?,
        })
    }

    async fn do_put_prepared_statement_query(
        &self,
        query: CommandPreparedStatementQuery,
        request: Request<PeekableFlightDataStream>,
    ) -> Result<DoPutPreparedStatementResult, Status> {
        let mut handle = Handle::decode(&query.prepared_statement_handle)?;
        let stream = FlightRecordBatchStream::new_from_flight_data(request.into_inner().map_err(FlightError::from));
        let batches: Vec<RecordBatch> =
            stream.try_collect().await.map_err(|e| Status::invalid_argument(format!("reading parameters: {e}")))?;
        let Some(first) = batches.first() else {
            return Err(Status::invalid_argument("parameters: no values were sent"));
        };
        let batch = arrow::compute::concat_batches(&first.schema(), &batches)
            .map_err(|e| Status::invalid_argument(format!("parameters: {e}")))?;
        handle.params = Some(batch);
        // Checked now, so a bad binding fails here rather than at execution.
        self.plan(&handle.sql, handle.param_values()?).await?;
        Ok(DoPutPreparedStatementResult { prepared_statement_handle: Some(handle.encode()?) })
    }

    async fn get_flight_info_prepared_statement(
        &self,
        cmd: CommandPreparedStatementQuery,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let handle = Handle::decode(&cmd.prepared_statement_handle)?;
        let plan = self.plan(&handle.sql, handle.param_values()?).await?;
        // A ticket of its own (a query id for cancelling it), carrying the handle.
        let id = self.running.new_id();
        let ticket = TicketStatementQuery { statement_handle: encode_ticket(id, &TicketBody::Prepared(handle))? };
        Self::info(plan.schema().as_arrow(), &ticket, request)
    }

    async fn do_get_prepared_statement(
        &self,
        cmd: CommandPreparedStatementQuery,
        request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        let handle = Handle::decode(&cmd.prepared_statement_handle)?;
        let log = self.log(self.running.new_id(), &handle.sql, request.remote_addr());
        let plan = self.plan(&handle.sql, handle.param_values()?).await?;
        self.execute(plan, log).await
    }

    async fn do_action_close_prepared_statement(
        &self,
        _query: ActionClosePreparedStatementRequest,
        _request: Request<arrow_flight::Action>,
    ) -> Result<(), Status> {
        Ok(()) // Stateless: the handle holds everything.
    }

    async fn get_flight_info_catalogs(
        &self,
        query: CommandGetCatalogs,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let schema = query.into_builder().schema();
        Self::info(&schema, &query, request)
    }

    async fn do_get_catalogs(
        &self,
        query: CommandGetCatalogs,
        _request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        let mut b = query.into_builder();
        for name in self.ctx.catalog_names() {
            b.append(name);
        }
        Self::one_batch(b.build())
    }

    async fn get_flight_info_schemas(
        &self,
        query: CommandGetDbSchemas,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let schema = query.clone().into_builder().schema();
        Self::info(&schema, &query, request)
    }

    async fn do_get_schemas(
        &self,
        query: CommandGetDbSchemas,
        _request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        let mut b = query.into_builder();
        for catalog_name in self.ctx.catalog_names() {
            if let Some(catalog) = self.ctx.catalog(&catalog_name) {
                for schema_name in catalog.schema_names() {
                    b.append(&catalog_name, schema_name); // the builder applies the filters
                }
            }
        }
        Self::one_batch(b.build())
    }

    async fn get_flight_info_tables(
        &self,
        query: CommandGetTables,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let schema = query.clone().into_builder().schema();
        Self::info(&schema, &query, request)
    }

    async fn do_get_tables(
        &self,
        query: CommandGetTables,
        _request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        let wanted_catalog = query.catalog.clone();
        let mut b = query.into_builder();
        for catalog_name in self.ctx.catalog_names() {
            if wanted_catalog.as_ref().is_some_and(|c| c != &catalog_name) {
                continue;
            }
            let Some(catalog) = self.ctx.catalog(&catalog_name) else { continue };
            for schema_name in catalog.schema_names() {
                let Some(schema) = catalog.schema(&schema_name) else { continue };
                for table_name in schema.table_names() {
                    let table = schema.table(&table_name).await.map_err(exec_status)?;
                    if let Some(table) = table {
                        b.append(
                            &catalog_name,
                            &schema_name,
                            &table_name,
                            table.table_type().to_string(),
                            &table.schema(),
                        )
                        .map_err(|e| Status::internal(format!("listing tables: {e}")))?;
                    }
                }
            }
        }
        Self::one_batch(b.build())
    }

    async fn get_flight_info_table_types(
        &self,
        query: CommandGetTableTypes,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        Self::info(&table_types_schema(), &query, request)
    }

    async fn do_get_table_types(
        &self,
        _query: CommandGetTableTypes,
        _request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        use datafusion::datasource::TableType;
        let types: Vec<String> =
            [TableType::Base, TableType::View, TableType::Temporary].iter().map(|t| t.to_string()).collect();
        let column: ArrayRef = Arc::new(StringArray::from(types));
        Self::one_batch(RecordBatch::try_new(Arc::new(table_types_schema()), vec![column]))
    }

    async fn get_flight_info_sql_info(
        &self,
        query: CommandGetSqlInfo,
        request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        let schema = query.clone().into_builder(&self.sql_info).schema();
        Self::info(&schema, &query, request)
    }

    async fn do_get_sql_info(
        &self,
        query: CommandGetSqlInfo,
        _request: Request<Ticket>,
    ) -> Result<Response<DoGetStream>, Status> {
        Self::one_batch(query.into_builder(&self.sql_info).build())
    }

    async fn do_put_statement_update(
        &self,
        _ticket: CommandStatementUpdate,
        _request: Request<PeekableFlightDataStream>,
    ) -> Result<i64, Status> {
        Err(read_only("an update statement"))
    }

    async fn do_put_statement_ingest(
        &self,
        _ticket: CommandStatementIngest,
        _request: Request<PeekableFlightDataStream>,
    ) -> Result<i64, Status> {
        Err(read_only("ingesting data"))
    }

    async fn do_put_prepared_statement_update(
        &self,
        _query: CommandPreparedStatementUpdate,
        _request: Request<PeekableFlightDataStream>,
    ) -> Result<i64, Status> {
        Err(read_only("an update statement"))
    }

    async fn get_flight_info_substrait_plan(
        &self,
        _query: CommandStatementSubstraitPlan,
        _request: Request<FlightDescriptor>,
    ) -> Result<Response<FlightInfo>, Status> {
        Err(Status::unimplemented("Substrait plans are not accepted: send SQL"))
    }

    async fn do_action_create_prepared_substrait_plan(
        &self,
        _query: ActionCreatePreparedSubstraitPlanRequest,
        _request: Request<arrow_flight::Action>,
    ) -> Result<ActionCreatePreparedStatementResult, Status> {
        Err(Status::unimplemented("Substrait plans are not accepted: send SQL"))
    }

    async fn do_action_begin_transaction(
        &self,
        _query: ActionBeginTransactionRequest,
        _request: Request<arrow_flight::Action>,
    ) -> Result<ActionBeginTransactionResult, Status> {
        Err(read_only("a transaction"))
    }

    async fn do_action_begin_savepoint(
        &self,
        _query: ActionBeginSavepointRequest,
        _request: Request<arrow_flight::Action>,
    ) -> Result<ActionBeginSavepointResult, Status> {
        Err(read_only("a savepoint"))
    }

    async fn do_action_cancel_query(
        &self,
        query: arrow_flight::sql::ActionCancelQueryRequest,
        _request: Request<arrow_flight::Action>,
    ) -> Result<arrow_flight::sql::ActionCancelQueryResult, Status> {
        // ActionCancelQueryResult.CancelResult: CANCELLED = 1, NOT_CANCELLABLE = 3 (the nested
        // enum is not re-exported by arrow-flight).
        let info = FlightInfo::decode(&*query.info)
            .map_err(|e| Status::invalid_argument(format!("CancelQuery: not a FlightInfo: {e}")))?;
        let result = if self.cancel_info(&info) { 1 } else { 3 };
        Ok(arrow_flight::sql::ActionCancelQueryResult { result })
    }

    async fn do_action_fallback(
        &self,
        request: Request<arrow_flight::Action>,
    ) -> Result<Response<<Self as FlightService>::DoActionStream>, Status> {
        let action = request.into_inner();
        if action.r#type != "CancelFlightInfo" {
            return Err(Status::invalid_argument(format!(
                "unknown action {:?}: this server takes CancelFlightInfo, CancelQuery and the prepared-statement actions",
                action.r#type
            )));
        }
        let req = arrow_flight::CancelFlightInfoRequest::decode(&*action.body)
            .map_err(|e| Status::invalid_argument(format!("CancelFlightInfo: not a CancelFlightInfoRequest: {e}")))?;
        let info = req.info.ok_or_else(|| Status::invalid_argument("CancelFlightInfo: no FlightInfo given"))?;
        let status = if self.cancel_info(&info) {
            arrow_flight::CancelStatus::Cancelled
        } else {
            arrow_flight::CancelStatus::NotCancellable
        };
        let body = arrow_flight::CancelFlightInfoResult { status: status as i32 }.encode_to_vec();
        let out = arrow_flight::Result { body: body.into() };
        Ok(Response::new(Box::pin(futures::stream::iter([Ok(out)]))))
    }

    async fn do_handshake(
        &self,
        _request: Request<tonic::Streaming<arrow_flight::HandshakeRequest>>,
    ) -> Result<
        Response<
            std::pin::Pin<Box<dyn futures::Stream<Item = Result<arrow_flight::HandshakeResponse, Status>> + Send>>,
        >,
        Status,
    > {
        // Reached only with valid credentials (the interceptor checks them): answer with the
        // bearer token to send from now on, in the payload and the `authorization` header.
        let token = self.options.token.clone().unwrap_or_default();
        let reply = arrow_flight::HandshakeResponse { protocol_version: 0, payload: token.clone().into_bytes().into() };
        let mut response: Response<
            std::pin::Pin<Box<dyn futures::Stream<Item = Result<arrow_flight::HandshakeResponse, Status>> + Send>>,
        > = Response::new(Box::pin(futures::stream::iter([Ok(reply)])));
        if !token.is_empty() {
            let value = format!("Bearer {token}")
                .parse()
                .map_err(|_| Status::internal("the token is not a valid header value"))?;
            response.metadata_mut().insert("authorization", value);
        }
        Ok(response)
    }

    async fn register_sql_info(&self, _id: i32, _result: &SqlInfo) {}
}

fn table_types_schema() -> Schema {
    Schema::new(vec![Field::new("table_type", DataType::Utf8, false)])
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn question_marks_become_numbered_placeholders() {
        assert_eq!(number_placeholders("SELECT 1"), "SELECT 1");
        assert_eq!(
            number_placeholders("SELECT * FROM rays WHERE depth >= ? AND kind = ?"),
            "SELECT * FROM rays WHERE depth >= $1 AND kind = $2"
        );
        // Not inside literals or quoted identifiers.
        assert_eq!(
            number_placeholders("SELECT '?', \"a?\" FROM t WHERE x = ?"),
            "SELECT '?', \"a?\" FROM t WHERE x = $1"
        );
        assert_eq!(number_placeholders("SELECT 'it''s ?' WHERE x = ?"), "SELECT 'it''s ?' WHERE x = $1");
        assert_eq!(number_placeholders("SELECT 'é?'\n -- ?\n , ? FROM t"), "SELECT 'é?'\n -- ?\n , $1 FROM t");
    }

    #[test]
    fn handles_round_trip_and_reject_garbage() {
        let h = Handle { sql: "SELECT $1".into(), params: None }.encode().unwrap();
        let d = Handle::decode(&h).unwrap();
        assert_eq!(d.sql, "SELECT $1");
        assert!(d.params.is_none());
        let col: ArrayRef = Arc::new(arrow::array::Int64Array::from(vec![7]));
        let batch = RecordBatch::try_from_iter([("$1", col)]).unwrap();
        let h = Handle { sql: "SELECT $1".into(), params: Some(batch) }.encode().unwrap();
        let d = Handle::decode(&h).unwrap();
        let p = d.param_values().unwrap().unwrap();
        assert!(matches!(p, ParamValues::List(v) if v.len() == 1));
        for garbage in [&b""[..], b"\xff\xff\xff\xff", b"\x02\x00\x00\x00\xff\xfe", b"\x01\x00\x00\x00Xjunk"] {
            assert!(Handle::decode(garbage).is_err(), "{garbage:?}");
        }
    }
}
