//! What rtvtk's own physical operators share: replacing plan nodes from an optimizer rule.

use std::sync::Arc;

use datafusion::common::tree_node::{Transformed, TreeNode};
use datafusion::error::Result;
use datafusion::physical_plan::ExecutionPlan;

/// Which way [`replace_nodes`] walks the plan.
pub(crate) enum Walk {
    /// Parents first (a replacement takes its whole subtree's shape into account).
    Down,
    /// Children first.
    Up,
}

/// `plan` with every node that `replacing` has a replacement for replaced by it.
pub(crate) fn replace_nodes<E: ExecutionPlan + 'static>(
    plan: Arc<dyn ExecutionPlan>,
    walk: Walk,
    replacing: fn(&Arc<dyn ExecutionPlan>) -> Result<Option<E>>,
) -> Result<Arc<dyn ExecutionPlan>> {
    let f = |node: Arc<dyn ExecutionPlan>| match replacing(&node)? {
        Some(exec) => Ok(Transformed::yes(Arc::new(exec) as Arc<dyn ExecutionPlan>)),
        None => Ok(Transformed::no(node)),
    };
    match walk {
        Walk::Down => plan.transform_down(f),
        Walk::Up => plan.transform_up(f),
    }
    .map(|t| t.data)
}

/// The metrics of the first node of type `E` in `plan` (tests read an operator's counters).
#[cfg(test)]
pub(crate) fn metrics_of<E: ExecutionPlan + 'static>(
    plan: &Arc<dyn ExecutionPlan>,
) -> Option<datafusion::physical_plan::metrics::MetricsSet> {
    use datafusion::common::tree_node::TreeNodeRecursion;
    let mut found = None;
    plan.apply(|n| {
        if n.downcast_ref::<E>().is_some() {
            found = n.metrics();
            return Ok(TreeNodeRecursion::Stop);
        }
        Ok(TreeNodeRecursion::Continue)
    })
    .ok()?;
    found
}
