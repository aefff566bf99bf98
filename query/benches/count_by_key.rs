//! `CountByKeyExec` beside DataFusion's own two-phase hash aggregation, in the same run, on the
//! same in-memory table: `SELECT k, count(*) FROM t GROUP BY k` over 4M rows of 32-bit keys with
//! 16K, 256K and 2M distinct values (uniform random). Run with
//! `cargo bench -p rtvtk-query --bench count_by_key`; throughput is in rows.
#![allow(clippy::unwrap_used)]

use std::sync::Arc;

use arrow::array::{RecordBatch, UInt32Array};
use arrow::datatypes::{DataType, Field, Schema};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use datafusion::datasource::MemTable;
use datafusion::execution::session_state::SessionStateBuilder;
use datafusion::physical_plan::displayable;
use datafusion::prelude::{SessionConfig, SessionContext};

const ROWS: usize = 4 << 20;

fn table(distinct: u32) -> Arc<MemTable> {
    let schema = Arc::new(Schema::new(vec![Field::new("k", DataType::UInt32, false)]));
    let mut s = 0x9E37_79B9_7F4A_7C15u64;
    let mut partitions = vec![Vec::new(), Vec::new()];
    for (i, chunk) in (0..ROWS).collect::<Vec<_>>().chunks(8192).enumerate() {
        let keys: UInt32Array = chunk
            .iter()
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s % u64::from(distinct)) as u32
            })
            .collect();
        partitions[i % 2].push(RecordBatch::try_new(schema.clone(), vec![Arc::new(keys)]).unwrap());
    }
    Arc::new(MemTable::try_new(schema, partitions).unwrap())
}

fn session(ours: bool, t: Arc<MemTable>) -> SessionContext {
    let config = SessionConfig::new().with_target_partitions(2);
    let mut b = SessionStateBuilder::new().with_config(config).with_default_features();
    if ours {
        b = b.with_physical_optimizer_rules(query::physical_optimizer_rules());
    }
    let ctx = SessionContext::new_with_state(b.build());
    ctx.register_table("t", t).unwrap();
    ctx
}

fn bench(c: &mut Criterion) {
    let rt = tokio::runtime::Runtime::new().unwrap();
    for distinct in [16 << 10, 256 << 10, 2 << 20] {
        let t = table(distinct);
        let mut g = c.benchmark_group(format!("count_by_key/{distinct}_keys"));
        g.throughput(Throughput::Elements(ROWS as u64)).sample_size(10);
        for (name, ours) in [("datafusion_hash_aggregate", false), ("count_by_key", true)] {
            let ctx = session(ours, t.clone());
            let sql = "SELECT k, count(*) FROM t GROUP BY k";
            let plan = rt.block_on(async { ctx.sql(sql).await?.create_physical_plan().await }).unwrap();
            let shown = displayable(plan.as_ref()).indent(true).to_string();
            assert_eq!(shown.contains("CountByKeyExec"), ours, "{shown}");
            let groups: usize =
                rt.block_on(async { ctx.sql(sql).await?.collect().await }).unwrap().iter().map(|b| b.num_rows()).sum();
            assert!(groups as u32 <= distinct && groups as u32 > distinct / 2, "{groups} groups");
            g.bench_function(name, |b| b.iter(|| rt.block_on(async { ctx.sql(sql).await?.collect().await }).unwrap()));
        }
        g.finish();
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
