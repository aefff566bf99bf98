#![allow(clippy::unwrap_used)]
//! `rtvtk serve` end to end through a Flight SQL client (arrow-flight's, the protocol ADBC and
//! JDBC speak): statements and prepared statements with the ray functions give the answers
//! `rtvtk sql` gives, the catalog lists the datasets' tables, and anything that would write is
//! refused with a clear status while the server keeps serving.

use std::path::Path;
use std::process::{Child, Command};

use arrow::array::{Array, RecordBatch, StringArray, UInt64Array};
use arrow::compute::concat_batches;
use arrow_flight::sql::client::FlightSqlServiceClient;
use arrow_flight::sql::{CommandGetTables, SqlInfo};
use arrow_flight::{FlightInfo, Ticket};
use futures::TryStreamExt;
use tonic::transport::Channel;

mod common;
use common::{WRONG_SHADOWS, rtvtk, scalar as sql_scalar};

const SETTINGS: [&str; 8] = ["--scene", "cornell", "--size", "32x24", "--spp", "4", "--threads", "2"];

fn record(dir: &Path, extra: &[&str]) {
    common::record(dir, &[&SETTINGS[..], extra].concat());
}

/// The server process, killed when the test ends (also when it fails).
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `rtvtk serve` on a free port; returns it and its `http://HOST:PORT` address.
fn serve(datasets: &[&str]) -> (Server, String) {
    let (child, line) = common::start_with_first_line(&[&["serve"], datasets, &["--addr", "127.0.0.1:0"]].concat());
    let server = Server(child);
    let addr = line.split("grpc://").nth(1).and_then(|s| s.split_whitespace().next());
    let addr = addr.unwrap_or_else(|| panic!("no address in {line:?}")).to_string();
    (server, format!("http://{addr}"))
}

async fn fetch(client: &mut FlightSqlServiceClient<Channel>, info: FlightInfo) -> RecordBatch {
    let schema = std::sync::Arc::new(info.clone().try_decode_schema().unwrap());
    let mut batches = vec![];
    for endpoint in info.endpoint {
        let ticket: Ticket = endpoint.ticket.unwrap();
        let stream = client.do_get(ticket).await.unwrap();
        batches.extend(stream.try_collect::<Vec<_>>().await.unwrap());
    }
    concat_batches(&schema, &batches).unwrap()
}

async fn query(client: &mut FlightSqlServiceClient<Channel>, sql: &str) -> RecordBatch {
    let info = client.execute(sql.to_string(), None).await.unwrap_or_else(|e| panic!("{sql}: {e}"));
    fetch(client, info).await
}

fn u64_at(batch: &RecordBatch, col: usize, row: usize) -> u64 {
    batch.column(col).as_any().downcast_ref::<UInt64Array>().map(|a| a.value(row)).unwrap_or_else(|| {
        let c = arrow::compute::cast(batch.column(col), &arrow::datatypes::DataType::UInt64).unwrap();
        c.as_any().downcast_ref::<UInt64Array>().unwrap().value(row)
    })
}

#[test]
fn flight_sql_clients_query_traces_read_only() {
    let tmp = tempfile::tempdir().unwrap();
    let (good, bad) = common::record_good_and_bad(tmp.path(), &SETTINGS);
    let (g, b) = (format!("good={}", good.display()), format!("bad={}", bad.display()));
    // The answers `rtvtk sql` gives, to compare with.
    let rays: u64 = sql_scalar(&[&g], "SELECT count(*) FROM rays").parse().unwrap();
    let wrong_bad: u64 = sql_scalar(&[&b], WRONG_SHADOWS).parse().unwrap();
    assert!(rays > 0 && wrong_bad > 0);
    let per_kind_q = "SELECT kind, count(*) AS n FROM rays GROUP BY kind ORDER BY kind";
    let per_kind_csv = String::from_utf8(rtvtk(&["sql", &g, per_kind_q, "--format", "csv"]).stdout).unwrap();

    let (_server, url) = serve(&[&g, &b]);
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    rt.block_on(async {
        let channel = Channel::from_shared(url.clone()).unwrap().connect().await.unwrap();
        let mut client = FlightSqlServiceClient::new(channel);

        // Statements: counts, the ray functions, the paper's bug, both datasets in one query.
        let n = query(&mut client, "SELECT count(*) FROM rays").await;
        assert_eq!(u64_at(&n, 0, 0), rays);
        let wrong = query(&mut client, &WRONG_SHADOWS.replace("FROM rays", "FROM bad.rays")).await;
        assert_eq!(u64_at(&wrong, 0, 0), wrong_bad);
        let wrong = query(&mut client, &WRONG_SHADOWS.replace("FROM rays", "FROM good.rays")).await;
        assert_eq!(u64_at(&wrong, 0, 0), 0, "a correct trace has no wrong shadow ray");
        let per_kind = query(&mut client, per_kind_q).await;
        let kinds = arrow::compute::cast(per_kind.column(0), &arrow::datatypes::DataType::Utf8).unwrap();
        let kinds = kinds.as_any().downcast_ref::<StringArray>().unwrap();
        let mut csv = String::from("kind,n\n");
        for i in 0..per_kind.num_rows() {
            csv += &format!("{},{}\n", kinds.value(i), u64_at(&per_kind, 1, i));
        }
        assert_eq!(csv, per_kind_csv);
        // A result over many batches streams whole.
        let all = query(&mut client, "SELECT tree_id, ray, octant(dir_x, dir_y, dir_z) FROM rays").await;
        assert_eq!(all.num_rows() as u64, rays);

        // Prepared statements (what ADBC and JDBC use), with a bound parameter.
        let sql = "SELECT count(*) FROM good.rays WHERE depth >= $1";
        let mut ps = client.prepare(sql.to_string(), None).await.unwrap();
        assert_eq!(ps.parameter_schema().unwrap().fields().len(), 1);
        let one: arrow::array::ArrayRef = std::sync::Arc::new(arrow::array::Int64Array::from(vec![1]));
        ps.set_parameters(RecordBatch::try_from_iter([("$1", one)]).unwrap()).unwrap();
        let info = ps.execute().await.unwrap();
        let deep = fetch(&mut client, info).await;
        let expect: u64 = sql_scalar(&[&g], "SELECT count(*) FROM rays WHERE depth >= 1").parse().unwrap();
        assert!(expect > 0 && expect < rays);
        assert_eq!(u64_at(&deep, 0, 0), expect);
        ps.close().await.unwrap();
        let mut ps = client.prepare("SELECT count(*) FROM rays".to_string(), None).await.unwrap();
        let info = ps.execute().await.unwrap();
        assert_eq!(u64_at(&fetch(&mut client, info).await, 0, 0), rays);

        // The catalog: both datasets' tables, with their schemas, whether or not a catalog is named.
        for catalog in [Some("datafusion".to_string()), None] {
            let info = client
                .get_tables(CommandGetTables {
                    catalog,
                    db_schema_filter_pattern: None,
                    table_name_filter_pattern: Some("rays".into()),
                    table_types: vec![],
                    include_schema: true,
                })
                .await
                .unwrap();
            let tables = fetch(&mut client, info).await;
            let schemas = tables.column_by_name("db_schema_name").unwrap();
            let schemas = schemas.as_any().downcast_ref::<StringArray>().unwrap();
            let mut names: Vec<&str> = (0..schemas.len()).map(|i| schemas.value(i)).collect();
            names.sort();
            assert_eq!(names, ["bad", "good", "public"]);
            assert!(tables.column_by_name("table_schema").is_some());
        }
        let catalogs = client.get_catalogs().await.unwrap();
        assert_eq!(fetch(&mut client, catalogs).await.num_rows(), 1);
        let info =
            client.get_sql_info(vec![SqlInfo::FlightSqlServerName, SqlInfo::FlightSqlServerReadOnly]).await.unwrap();
        assert_eq!(fetch(&mut client, info).await.num_rows(), 2);

        // Bad input: clear statuses, and the server keeps serving.
        let err = client.execute("SELECT nope FROM rays".to_string(), None).await.unwrap_err().to_string();
        assert!(err.contains("nope"), "{err}");
        let err = client.execute("SELEKT 1".to_string(), None).await.unwrap_err().to_string();
        assert!(err.to_lowercase().contains("sql"), "{err}");
        for write in [
            "CREATE TABLE x AS SELECT 1",
            "INSERT INTO trees SELECT * FROM trees",
            "COPY (SELECT * FROM rays) TO '/tmp/rtvtk-service-leak.parquet'",
            "DROP TABLE rays",
            "SET datafusion.execution.batch_size = 1",
        ] {
            let err = client.execute(write.to_string(), None).await.unwrap_err().to_string();
            assert!(err.contains("not supported") || err.contains("not allowed"), "{write}: {err}");
        }
        assert!(!Path::new("/tmp/rtvtk-service-leak.parquet").exists());
        let err = client.execute_update("DELETE FROM rays".to_string(), None).await.unwrap_err().to_string();
        assert!(err.contains("read-only"), "{err}");
        let n = query(&mut client, "SELECT count(*) FROM good.rays").await;
        assert_eq!(u64_at(&n, 0, 0), rays, "tables unchanged after the refused writes");
    });
    // The dataset on disk is intact.
    assert!(rtvtk(&["check", good.to_str().unwrap()]).status.success());
}

#[test]
fn serve_refuses_bad_arguments() {
    let out = rtvtk(&["serve", "/nonexistent/trace", "--addr", "127.0.0.1:0"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("/nonexistent/trace") && err.contains("not a dataset"), "{err}");
    let tmp = tempfile::tempdir().unwrap();
    record(&tmp.path().join("t"), &[]);
    let t = tmp.path().join("t");
    let out = rtvtk(&["serve", t.to_str().unwrap(), "--addr", "not-an-address"]);
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("not-an-address"), "{err}");
}

/// The ADBC Flight SQL driver (Go, used from Python through `adbc_driver_flightsql`; installed by
/// `scripts/check.sh`), as analysts would connect: statements, `?` parameters, the catalog.
#[test]
fn adbc_python_client_queries_the_service() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("bad");
    record(&bad, &["--inject-bug", "shadow-dir"]);
    let b = bad.to_str().unwrap();
    let wrong: u64 = sql_scalar(&[b], WRONG_SHADOWS).parse().unwrap();
    let deep: u64 = sql_scalar(&[b], "SELECT count(*) FROM rays WHERE depth >= 2").parse().unwrap();
    assert!(wrong > 0 && deep > 0);
    let (_server, url) = serve(&[b]);
    let script = r#"
import sys, json, warnings
warnings.simplefilter("ignore")
import adbc_driver_flightsql.dbapi as flightsql
con = flightsql.connect(sys.argv[1].replace("http://", "grpc://"))
cur = con.cursor()
out = {}
cur.execute(sys.argv[2]); out["wrong"] = cur.fetchone()[0]
cur.execute("SELECT count(*) FROM rays WHERE depth >= ?", parameters=(2,)); out["deep"] = cur.fetchone()[0]
objs = con.adbc_get_objects(depth="tables").read_all().to_pylist()
out["tables"] = sorted(t["table_name"] for c in objs for s in c["catalog_db_schemas"] if s["db_schema_name"] == "public" for t in s["db_schema_tables"])
out["vendor"] = con.adbc_get_info()["vendor_name"]
try:
    cur.execute("DROP TABLE rays"); out["drop"] = "accepted"
except Exception as e:
    out["drop"] = str(e)
print(json.dumps(out))
"#;
    let out = Command::new("python3").args(["-c", script, &url, WRONG_SHADOWS]).output().unwrap();
    assert!(out.status.success(), "python3/adbc: {}", String::from_utf8_lossy(&out.stderr));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["wrong"], wrong);
    assert_eq!(v["deep"], deep);
    assert_eq!(v["vendor"], "rtvtk");
    let tables: Vec<&str> = v["tables"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()).collect();
    assert_eq!(
        tables,
        ["attributes", "bvh_nodes", "lights", "numerics", "numerics_checks", "ray_paths", "rays", "trees", "triangles"]
    );
    let drop = v["drop"].as_str().unwrap();
    assert!(drop.contains("DDL not supported"), "{drop}");
}
