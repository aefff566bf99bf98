//! A table that cannot be read, registered so that its queries fail naming it and why while the
//! rest of the session answers (a leaf: `tables` and `numerics` both register such tables).

use std::sync::Arc;

use arrow::datatypes::SchemaRef;
use datafusion::datasource::TableProvider;
use datafusion::physical_plan::ExecutionPlan;

/// A table of the dataset that cannot be read (a known table whose file is missing, truncated,
/// corrupted or has a missing or mistyped column), or one made from such a table (`ray_paths`
/// from `lights`, the `numerics` view): registered so that a query of it fails naming the table
/// and the reason, while every other table stays queryable.
#[derive(Debug)]
pub(crate) struct Unavailable {
    name: String,
    schema: SchemaRef,
    message: String,
}

impl Unavailable {
    /// Table `name`, with the schema it would have, unavailable for `message`.
    pub(crate) fn new(name: &str, schema: SchemaRef, message: String) -> Self {
        Self { name: name.to_string(), schema, message }
    }

    fn error(&self) -> datafusion::error::DataFusionError {
        datafusion::error::DataFusionError::Plan(store::unavailable(&format!("table `{}`", self.name), &self.message))
    }
}

#[async_trait::async_trait]
impl TableProvider for Unavailable {
    fn schema(&self) -> SchemaRef {
        self.schema.clone()
    }

    fn table_type(&self) -> datafusion::datasource::TableType {
        datafusion::datasource::TableType::Base
    }

    async fn scan(
        &self,
        _state: &dyn datafusion::catalog::Session,
        _projection: Option<&Vec<usize>>,
        _filters: &[datafusion::logical_expr::Expr],
        _limit: Option<usize>,
    ) -> datafusion::error::Result<Arc<dyn ExecutionPlan>> {
        Err(self.error())
    }
}
