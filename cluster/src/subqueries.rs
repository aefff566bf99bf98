//! Uncorrelated scalar subqueries the optimizer cannot turn into joins (one inside an aggregate's
//! argument or a `CASE`, say) are planned by DataFusion as a `ScalarSubqueryExec` whose results
//! live in one process; Ballista cannot split such a plan into stages
//! (apache/datafusion-ballista#1909) and refuses it. [`SubqueriesFirst`] wraps the client's
//! (Ballista's) query planner: it runs each such subquery on the cluster first, puts its value in
//! the plan as a literal (keeping the expression's name) and hands the rest to Ballista, so these
//! queries give the in-process answers.

use std::sync::Arc;

use datafusion::catalog::Session;
use datafusion::common::tree_node::{Transformed, TreeNode, TreeNodeRecursion};
use datafusion::common::{ScalarValue, plan_err};
use datafusion::error::Result;
use datafusion::execution::context::QueryPlanner;
use datafusion::logical_expr::expr_rewriter::NamePreserver;
use datafusion::logical_expr::{Expr, LogicalPlan, Subquery};
use datafusion::physical_plan::ExecutionPlan;

/// A query planner that evaluates uncorrelated scalar subqueries through `inner` before
/// planning the query with it.
#[derive(Debug)]
pub struct SubqueriesFirst {
    pub inner: Arc<dyn QueryPlanner + Send + Sync>,
}

/// The uncorrelated scalar subqueries of `plan`'s expressions (not those nested in them).
fn uncorrelated(plan: &LogicalPlan) -> Result<Vec<Subquery>> {
    let mut found: Vec<Subquery> = Vec::new();
    plan.apply(|node| {
        node.apply_expressions(|e| {
            e.apply(|e| {
                if let Expr::ScalarSubquery(sq) = e
                    && sq.outer_ref_columns.is_empty()
                    && !found.contains(sq)
                {
                    found.push(sq.clone());
                }
                Ok(TreeNodeRecursion::Continue)
            })
        })
    })?;
    Ok(found)
}

impl SubqueriesFirst {
    fn plan<'a>(
        &'a self,
        plan: &'a LogicalPlan,
        state: &'a dyn Session,
    ) -> futures::future::BoxFuture<'a, Result<Arc<dyn ExecutionPlan>>> {
        Box::pin(async move {
            let subqueries = uncorrelated(plan)?;
            if subqueries.is_empty() {
                return self.inner.create_physical_plan(plan, state).await;
            }
            let mut values = Vec::with_capacity(subqueries.len());
            for sq in &subqueries {
                values.push(self.value(sq, state).await?);
            }
            let replaced = plan.clone().transform_up(|node| {
                let names = NamePreserver::new(&node);
                let node = node.map_expressions(|e| {
                    let name = names.save(&e);
                    let e = e.transform_up(|e| match &e {
                        Expr::ScalarSubquery(sq) => match subqueries.iter().position(|s| s == sq) {
                            Some(i) => Ok(Transformed::yes(Expr::Literal(values[i].clone(), None))),
                            None => Ok(Transformed::no(e)),
                        },
                        _ => Ok(Transformed::no(e)),
                    })?;
                    Ok(e.update_data(|e| name.restore(e)))
                })?;
                if node.transformed { node.map_data(|n| n.recompute_schema()) } else { Ok(node) }
            })?;
            self.inner.create_physical_plan(&replaced.data, state).await
        })
    }

    /// The one value of a scalar subquery (NULL when it has no row), run on the cluster.
    async fn value(&self, sq: &Subquery, state: &dyn Session) -> Result<ScalarValue> {
        let exec = self.plan(&sq.subquery, state).await?;
        let batches = datafusion::physical_plan::collect(exec, state.task_ctx()).await?;
        let schema = sq.subquery.schema();
        if schema.fields().len() != 1 {
            return plan_err!("a scalar subquery must return one column, not {}", schema.fields().len());
        }
        let mut value = None;
        for b in &batches {
            for row in 0..b.num_rows() {
                if value.is_some() {
                    return plan_err!("a scalar subquery returned more than one row");
                }
                value = Some(ScalarValue::try_from_array(b.column(0).as_ref(), row)?);
            }
        }
        match value {
            Some(v) => Ok(v),
            None => ScalarValue::try_from(schema.field(0).data_type()),
        }
    }
}

#[async_trait::async_trait]
impl QueryPlanner for SubqueriesFirst {
    async fn create_physical_plan(
        &self,
        logical_plan: &LogicalPlan,
        session_state: &dyn Session,
    ) -> Result<Arc<dyn ExecutionPlan>> {
        self.plan(logical_plan, session_state).await
    }
}
