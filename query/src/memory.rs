//! The memory pool of rtvtk's sessions: DataFusion's greedy pool under the session's limit, with
//! one exception that keeps queries from hanging.
//!
//! DataFusion 55.2 (the newest release) lets a `RepartitionExec` that cannot reserve memory for a
//! batch write it to a spill pool shared by all its inputs. When two inputs spill at once the pool
//! holds two open files, its reader waits on the older one while the batch it needs is in the
//! newer one, and every worker parks: the query neither returns nor fails (apache/datafusion
//! issue 24883, fixed after 55.2). Here a per-pixel style group-by of 100M rays under
//! `--memory-limit 300MiB` hung in half of its runs. So a repartition's reservations are granted
//! without being refused ([`granted_always`]): it keeps its batches in memory, as DataFusion did
//! before it could spill, and those bytes still count against the limit, so the operators that
//! can spill (aggregations, sorts, joins) spill sooner instead.

use std::sync::Arc;

use datafusion::error::Result;
use datafusion::execution::memory_pool::{
    GreedyMemoryPool, MemoryConsumer, MemoryLimit, MemoryPool, MemoryReservation, TrackConsumersPool,
};

/// Whether `consumer`'s reservations are granted without being refused: a repartition's queues
/// (see the module's text).
pub fn granted_always(consumer: &MemoryConsumer) -> bool {
    consumer.name().starts_with("RepartitionExec[")
}

/// The pool of a session limited to `limit` bytes: DataFusion's (greedy, naming its five biggest
/// consumers when it refuses), with [`granted_always`]'s exception.
pub fn session_pool(limit: usize) -> Arc<dyn MemoryPool> {
    let tracked = TrackConsumersPool::new(GreedyMemoryPool::new(limit), std::num::NonZeroUsize::MIN.saturating_add(4));
    Arc::new(SessionPool { inner: tracked })
}

#[derive(Debug)]
struct SessionPool {
    inner: TrackConsumersPool<GreedyMemoryPool>,
}

impl std::fmt::Display for SessionPool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "rtvtk session pool ({})", self.inner)
    }
}

impl MemoryPool for SessionPool {
    fn name(&self) -> &str {
        "rtvtk session pool"
    }
    fn register(&self, consumer: &MemoryConsumer) {
        self.inner.register(consumer);
    }
    fn unregister(&self, consumer: &MemoryConsumer) {
        self.inner.unregister(consumer);
    }
    fn grow(&self, reservation: &MemoryReservation, additional: usize) {
        self.inner.grow(reservation, additional);
    }
    fn shrink(&self, reservation: &MemoryReservation, shrink: usize) {
        self.inner.shrink(reservation, shrink);
    }
    fn try_grow(&self, reservation: &MemoryReservation, additional: usize) -> Result<()> {
        if granted_always(reservation.consumer()) {
            self.inner.grow(reservation, additional);
            return Ok(());
        }
        self.inner.try_grow(reservation, additional)
    }
    fn reserved(&self) -> usize {
        self.inner.reserved()
    }
    fn memory_limit(&self) -> MemoryLimit {
        self.inner.memory_limit()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repartitions_are_granted_others_refused_and_both_counted() {
        let pool = session_pool(1000);
        let rep = MemoryConsumer::new("RepartitionExec[1]").with_can_spill(true).register(&pool);
        let agg = MemoryConsumer::new("GroupedHashAggregateStream[0]").with_can_spill(true).register(&pool);
        rep.try_grow(900).expect("a repartition is granted");
        rep.try_grow(900).expect("even past the limit");
        assert_eq!(pool.reserved(), 1800);
        let e = agg.try_grow(10).expect_err("an aggregation is refused past the limit");
        assert!(e.to_string().contains("Resources exhausted"), "{e}");
        drop(rep);
        assert_eq!(pool.reserved(), 0);
        agg.try_grow(900).expect("room again once the repartition's batches are gone");
        drop(agg);
        // A query's own limit in the service makes the same exception.
        let query = crate::service::QueryPool::new(session_pool(1 << 20), 1000);
        let query: Arc<dyn MemoryPool> = Arc::new(query);
        let rep = MemoryConsumer::new("RepartitionExec[0]").register(&query);
        let agg = MemoryConsumer::new("GroupedHashAggregateStream[0]").register(&query);
        rep.try_grow(1500).expect("a repartition is granted past the query's limit");
        assert!(agg.try_grow(10).is_err(), "the query's other operators are refused");
        // Sessions get this pool when a limit is set.
        let options = crate::SessionOptions { memory_limit: Some(1000), ..Default::default() };
        let state = crate::session_state(&options).expect("a session");
        assert_eq!(state.runtime_env().memory_pool.name(), "rtvtk session pool");
    }

    /// The exception keys on the name DataFusion gives a repartition's reservations: under a
    /// limit of one byte a repartition of 40 batches would spill every one of them, and with the
    /// session's pool it spills none (a renamed consumer would make this fail).
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_repartition_under_a_tiny_limit_keeps_its_batches() {
        use arrow::array::{RecordBatch, UInt64Array};
        use arrow::datatypes::{DataType, Field, Schema};
        let options = crate::SessionOptions { memory_limit: Some(1), stock_aggregation: true };
        let ctx = datafusion::prelude::SessionContext::new_with_state(crate::session_state(&options).unwrap());
        for set in [
            "SET datafusion.execution.target_partitions = 2",
            "SET datafusion.optimizer.repartition_file_scans = false",
        ] {
            ctx.sql(set).await.unwrap().collect().await.unwrap();
        }
        let schema = Arc::new(Schema::new(vec![Field::new("k", DataType::UInt64, false)]));
        let batches: Vec<RecordBatch> = (0..40u64)
            .map(|b| {
                let k = UInt64Array::from_iter_values(b * 1000..(b + 1) * 1000);
                RecordBatch::try_new(schema.clone(), vec![Arc::new(k)]).unwrap()
            })
            .collect();
        let table = datafusion::datasource::MemTable::try_new(schema, vec![batches]).unwrap();
        ctx.register_table("t", Arc::new(table)).unwrap();
        let plan = ctx.sql("EXPLAIN ANALYZE SELECT k FROM t WHERE k % 3 = 0").await.unwrap().collect().await.unwrap();
        let text = arrow::util::pretty::pretty_format_batches(&plan).unwrap().to_string();
        let line =
            text.lines().find(|l| l.contains("RepartitionExec")).unwrap_or_else(|| panic!("no repartition: {text}"));
        assert!(line.contains("spill_count=0"), "the repartition spilled: {line}");
    }
}
