//! Ballista's executors serve shuffle data over Arrow Flight with the encoder's default
//! dictionary handling, which hydrates dictionary columns into their value type; the reading
//! stage was planned for the dictionary (`rays.kind` is `Dictionary(UInt8, Utf8)`), and its
//! operators refuse the plain strings ("RowConverter column schema mismatch"). This rule, the last
//! of the scheduler's physical rules, makes every stage boundary (`RepartitionExec`,
//! `CoalescePartitionsExec`, `SortPreservingMergeExec`, where Ballista cuts stages) carry the
//! value type instead: a cast to it below the boundary and back to the dictionary above it, so
//! the operators on either side see the schema they were planned with. [`CastBackExec`] crosses
//! the wire through [`ClusterCodec`].

use std::sync::Arc;

use std::fmt;

use datafusion::arrow::array::RecordBatch;
use datafusion::arrow::compute::cast;
use datafusion::arrow::datatypes::{DataType, Schema, SchemaRef};
use datafusion::common::config::ConfigOptions;
use datafusion::common::internal_err;
use datafusion::common::tree_node::{Transformed, TreeNode, TreeNodeRecursion};
use datafusion::error::DataFusionError;
use datafusion::error::Result;
use datafusion::execution::TaskContext;
use datafusion::logical_expr::{AggregateUDF, ScalarUDF};
use datafusion::physical_expr::EquivalenceProperties;
use datafusion::physical_expr::PhysicalExpr;
use datafusion::physical_expr::expressions::{CastExpr, Column};
use datafusion::physical_optimizer::PhysicalOptimizerRule;
use datafusion::physical_plan::ExecutionPlan;
use datafusion::physical_plan::coalesce_partitions::CoalescePartitionsExec;
use datafusion::physical_plan::execution_plan::{ChildrenPropertiesMode, ReplaceChildrenOptions};
use datafusion::physical_plan::projection::ProjectionExec;
use datafusion::physical_plan::repartition::RepartitionExec;
use datafusion::physical_plan::sorts::sort_preserving_merge::SortPreservingMergeExec;
use datafusion::physical_plan::stream::RecordBatchStreamAdapter;
use datafusion::physical_plan::{
    DisplayAs, DisplayFormatType, ExecutionPlanProperties, PlanProperties, SendableRecordBatchStream,
};
use datafusion_proto::physical_plan::{PhysicalExtensionCodec, PhysicalProtoConverterExtension};
use futures::StreamExt;
use prost::Message;

#[derive(Debug, Default)]
pub struct PlainAcrossStages;

/// A projection of `input` with its dictionary columns cast to their value types; None when it
/// has none.
fn dictionaries_as_values(input: &Arc<dyn ExecutionPlan>) -> Result<Option<Arc<dyn ExecutionPlan>>> {
    let schema = input.schema();
    if !schema.fields().iter().any(|f| matches!(f.data_type(), DataType::Dictionary(..))) {
        return Ok(None);
    }
    let exprs: Vec<(Arc<dyn PhysicalExpr>, String)> = schema
        .fields()
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let col: Arc<dyn PhysicalExpr> = Arc::new(Column::new(f.name(), i));
            let expr: Arc<dyn PhysicalExpr> = match f.data_type() {
                DataType::Dictionary(_, v) => Arc::new(CastExpr::new(col, v.as_ref().clone(), None)),
                _ => col,
            };
            (expr, f.name().clone())
        })
        .collect();
    Ok(Some(Arc::new(ProjectionExec::try_new(exprs, input.clone())?)))
}

impl PhysicalOptimizerRule for PlainAcrossStages {
    fn optimize(&self, plan: Arc<dyn ExecutionPlan>, _config: &ConfigOptions) -> Result<Arc<dyn ExecutionPlan>> {
        plan.transform_up(|node| {
            let boundary = node.downcast_ref::<RepartitionExec>().is_some()
                || node.downcast_ref::<CoalescePartitionsExec>().is_some()
                || node.downcast_ref::<SortPreservingMergeExec>().is_some();
            if !boundary {
                return Ok(Transformed::no(node));
            }
            let [input] = node.children()[..] else { return Ok(Transformed::no(node)) };
            let Some(plain) = dictionaries_as_values(input)? else { return Ok(Transformed::no(node)) };
            let crossed = node
                .clone()
                .replace_children(vec![plain], ReplaceChildrenOptions::new(ChildrenPropertiesMode::Recompute))?;
            // Back to the dictionary types the operators above were planned with, keeping the
            // boundary's partitioning and ordering (a projection of casts would hide them, and a
            // join above needs its inputs co-partitioned).
            Ok(Transformed::yes(Arc::new(CastBackExec::new(crossed, node.schema())?) as Arc<dyn ExecutionPlan>))
        })
        .map(|t| t.data)
    }

    fn name(&self) -> &str {
        "PlainAcrossStages"
    }

    fn schema_check(&self) -> bool {
        true
    }
}

/// Casts its input's columns to `schema`'s types (dictionaries back from their values), with the
/// input's partitioning and ordering.
#[derive(Debug)]
pub struct CastBackExec {
    input: Arc<dyn ExecutionPlan>,
    schema: SchemaRef,
    properties: Arc<PlanProperties>,
}

impl CastBackExec {
    pub fn new(input: Arc<dyn ExecutionPlan>, schema: SchemaRef) -> Result<Self> {
        let from = input.schema();
        if from.fields().len() != schema.fields().len() {
            return internal_err!("CastBackExec: {} columns in, {} out", from.fields().len(), schema.fields().len());
        }
        let orderings = input.output_ordering().map(|o| o.iter().cloned().collect::<Vec<_>>());
        let eq = EquivalenceProperties::new_with_orderings(schema.clone(), orderings);
        let p = input.properties();
        let properties = Arc::new(PlanProperties::new(eq, p.partitioning.clone(), p.emission_type, p.boundedness));
        Ok(Self { input, schema, properties })
    }
}

impl DisplayAs for CastBackExec {
    fn fmt_as(&self, _t: DisplayFormatType, f: &mut fmt::Formatter) -> fmt::Result {
        let from = self.input.schema();
        let cast: Vec<String> = self
            .schema
            .fields()
            .iter()
            .zip(from.fields())
            .filter(|(to, from)| to.data_type() != from.data_type())
            .map(|(to, _)| format!("{} AS {}", to.name(), to.data_type()))
            .collect();
        write!(f, "CastBackExec: [{}]", cast.join(", "))
    }
}

impl ExecutionPlan for CastBackExec {
    fn name(&self) -> &str {
        "CastBackExec"
    }

    fn properties(&self) -> &Arc<PlanProperties> {
        &self.properties
    }

    fn children(&self) -> Vec<&Arc<dyn ExecutionPlan>> {
        vec![&self.input]
    }

    fn apply_expressions(
        &self,
        _f: &mut dyn FnMut(&Arc<dyn PhysicalExpr>) -> Result<TreeNodeRecursion>,
    ) -> Result<TreeNodeRecursion> {
        Ok(TreeNodeRecursion::Continue)
    }

    fn maintains_input_order(&self) -> Vec<bool> {
        vec![true]
    }

    fn with_new_children(self: Arc<Self>, children: Vec<Arc<dyn ExecutionPlan>>) -> Result<Arc<dyn ExecutionPlan>> {
        let [input] = <[_; 1]>::try_from(children)
            .map_err(|c| DataFusionError::Internal(format!("CastBackExec has one child, not {}", c.len())))?;
        Ok(Arc::new(Self::new(input, self.schema.clone())?))
    }

    fn execute(&self, partition: usize, context: Arc<TaskContext>) -> Result<SendableRecordBatchStream> {
        let schema = self.schema.clone();
        let stream = self.input.execute(partition, context)?;
        let out = schema.clone();
        let cast = stream.map(move |batch| {
            let batch = batch?;
            let columns = batch
                .columns()
                .iter()
                .zip(out.fields())
                .map(|(c, f)| if c.data_type() == f.data_type() { Ok(c.clone()) } else { cast(c, f.data_type()) })
                .collect::<std::result::Result<Vec<_>, _>>()?;
            Ok(RecordBatch::try_new(out.clone(), columns)?)
        });
        Ok(Box::pin(RecordBatchStreamAdapter::new(schema, cast)))
    }
}

const MAGIC: &[u8] = b"\0rtvtk-cluster1";

/// The cluster's codec: [`CastBackExec`] (its target schema), everything else through `inner`
/// (rtvtk's codec over Ballista's).
#[derive(Debug)]
pub struct ClusterCodec {
    pub inner: Arc<dyn PhysicalExtensionCodec>,
}

impl PhysicalExtensionCodec for ClusterCodec {
    fn try_decode(
        &self,
        buf: &[u8],
        inputs: &[Arc<dyn ExecutionPlan>],
        ctx: &TaskContext,
        proto_converter: &dyn PhysicalProtoConverterExtension,
    ) -> Result<Arc<dyn ExecutionPlan>> {
        let Some(body) = buf.strip_prefix(MAGIC) else {
            return self.inner.try_decode(buf, inputs, ctx, proto_converter);
        };
        let proto = datafusion_proto::protobuf::Schema::decode(body)
            .map_err(|e| DataFusionError::Internal(format!("CastBackExec: cannot decode its schema: {e}")))?;
        let schema = Schema::try_from(&proto)
            .map_err(|e| DataFusionError::Internal(format!("CastBackExec: cannot decode its schema: {e}")))?;
        let [input] = inputs else { return internal_err!("CastBackExec: {} inputs, not one", inputs.len()) };
        Ok(Arc::new(CastBackExec::new(input.clone(), Arc::new(schema))?))
    }

    fn try_encode(
        &self,
        node: Arc<dyn ExecutionPlan>,
        buf: &mut Vec<u8>,
        proto_converter: &dyn PhysicalProtoConverterExtension,
    ) -> Result<()> {
        let Some(exec) = node.downcast_ref::<CastBackExec>() else {
            return self.inner.try_encode(node, buf, proto_converter);
        };
        let proto = datafusion_proto::protobuf::Schema::try_from(exec.schema.as_ref())
            .map_err(|e| DataFusionError::Internal(format!("CastBackExec: cannot encode its schema: {e}")))?;
        buf.extend_from_slice(MAGIC);
        proto.encode(buf).map_err(|e| DataFusionError::Internal(format!("CastBackExec: {e}")))?;
        Ok(())
    }

    fn try_decode_udf(&self, name: &str, buf: &[u8]) -> Result<Arc<ScalarUDF>> {
        self.inner.try_decode_udf(name, buf)
    }

    fn try_encode_udf(&self, node: &ScalarUDF, buf: &mut Vec<u8>) -> Result<()> {
        self.inner.try_encode_udf(node, buf)
    }

    fn try_decode_udaf(&self, name: &str, buf: &[u8]) -> Result<Arc<AggregateUDF>> {
        self.inner.try_decode_udaf(name, buf)
    }

    fn try_encode_udaf(&self, node: &AggregateUDF, buf: &mut Vec<u8>) -> Result<()> {
        self.inner.try_encode_udaf(node, buf)
    }
}
