//! The ray files' Parquet writer: the core integer columns are encoded and compressed here, page
//! by page, instead of by arrow-rs's column writers.
//!
//! The files are the same Parquet as before (format unchanged, any reader sees the same
//! columns, encodings, statistics and page index): `BYTE_STREAM_SPLIT` integer columns,
//! `DELTA_BINARY_PACKED` tree ids, data pages v1 compressed with zstd, an offset index for
//! every column and a column index (page min/max) for the columns with statistics. Writing them
//! here costs a fraction of the generic path: arrow-rs splits byte streams one byte at a time,
//! bit-packs deltas one value at a time and allocates every page's buffers anew; here one
//! transposing loop per column, one bit-packing loop per miniblock and buffers reused across
//! pages and row groups. Payload columns (any Arrow type) still go through arrow-rs's column
//! writers, into the same row groups.

use std::io::Write;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::buffer::NullBuffer;
use arrow::datatypes::{DataType, SchemaRef, UInt8Type, UInt16Type, UInt32Type, UInt64Type};
use bytes::Bytes;
use parquet::arrow::ArrowSchemaConverter;
use parquet::arrow::add_encoded_arrow_schema_to_metadata;
use parquet::arrow::arrow_writer::{ArrowColumnWriter, ArrowRowGroupWriterFactory, compute_leaves};
use parquet::basic::{BoundaryOrder, Compression, Encoding, EncodingMask, Type as PhysicalType, ZstdLevel};
use parquet::column::page::{CompressedPage, Page, PageWriter};
use parquet::column::writer::ColumnCloseResult;
use parquet::errors::{ParquetError, Result};
use parquet::file::metadata::{ColumnChunkMetaData, ColumnIndexBuilder, KeyValue, OffsetIndexBuilder};
use parquet::file::properties::WriterProperties;
use parquet::file::statistics::{Statistics, ValueStatistics};
use parquet::file::writer::{SerializedFileWriter, SerializedPageWriter, TrackedWrite};
use parquet::schema::types::ColumnDescPtr;

/// How one top-level column of a ray file is written.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Plan {
    /// u8/u16/u32 values as INT32, `BYTE_STREAM_SPLIT`; `stats`: page min/max and chunk statistics.
    Split { stats: bool },
    /// u64 values as INT64, `DELTA_BINARY_PACKED`, with statistics.
    Delta,
    /// arrow-rs's column writer (payload columns, plain layouts).
    Arrow,
}

/// Writes a ray file row group by row group, streaming: `write` encodes and compresses every
/// full page of the core columns at once (while the batch is in cache; only compressed pages
/// wait for the row group) and hands payload columns to arrow-rs's column writers; `flush`
/// closes the row group.
pub(crate) struct RayFileWriter<W: Write + Send> {
    file: SerializedFileWriter<W>,
    arrow_schema: SchemaRef,
    /// Column writers of the payload columns (arrow-rs's).
    factory: ArrowRowGroupWriterFactory,
    row_groups: usize,
    plans: Vec<Plan>,
    /// First leaf column and number of leaves of each top-level field.
    leaves: Vec<(usize, usize)>,
    /// Per field: the paged column (None where arrow-rs writes it).
    columns: Vec<Option<PagedColumn>>,
    /// Per leaf: arrow-rs's writers for the row group in progress (empty before its first rows).
    arrow_writers: Vec<Option<ArrowColumnWriter>>,
    /// Rows of the row group in progress.
    rows: usize,
    page_rows: usize,
    level: i32,
    zstd: zstd::bulk::Compressor<'static>,
    scratch: Scratch,
}

impl<W: Write + Send> RayFileWriter<W> {
    /// `plans`: one per field of `arrow_schema` (checked against the field types: a plan that
    /// does not fit its field's type falls back to arrow-rs).
    pub fn try_new(
        sink: W,
        arrow_schema: SchemaRef,
        mut props: WriterProperties,
        plans: &[Plan],
        zstd_level: i32,
        page_rows: usize,
    ) -> Result<Self> {
        let parquet_schema =
            ArrowSchemaConverter::new().with_coerce_types(props.coerce_types()).convert(&arrow_schema)?;
        add_encoded_arrow_schema_to_metadata(&arrow_schema, &mut props);
        let file = SerializedFileWriter::new(sink, parquet_schema.root_schema_ptr(), Arc::new(props))?;
        let factory = ArrowRowGroupWriterFactory::new(&file, arrow_schema.clone());
        let fields = arrow_schema.fields();
        let mut leaves = vec![(0usize, 0usize); fields.len()];
        for leaf in 0..parquet_schema.num_columns() {
            let root = parquet_schema.get_column_root_idx(leaf);
            let entry = leaves.get_mut(root).ok_or_else(|| general("a Parquet leaf outside the Arrow schema"))?;
            if entry.1 == 0 {
                entry.0 = leaf;
            }
            entry.1 += 1;
        }
        let plans: Vec<Plan> = fields
            .iter()
            .enumerate()
            .map(|(i, f)| {
                let plan = plans.get(i).copied().unwrap_or(Plan::Arrow);
                let fits = match plan {
                    Plan::Split { .. } => {
                        matches!(f.data_type(), DataType::UInt8 | DataType::UInt16 | DataType::UInt32)
                    }
                    Plan::Delta => f.data_type() == &DataType::UInt64 && !f.is_nullable(),
                    Plan::Arrow => true,
                };
                if fits && leaves[i].1 == 1 { plan } else { Plan::Arrow }
            })
            .collect();
        let columns = plans
            .iter()
            .zip(&leaves)
            .map(|(&plan, &(leaf, _))| PagedColumn::new(parquet_schema.column(leaf), plan))
            .collect();
        let zstd = zstd::bulk::Compressor::new(zstd_level)
            .map_err(|e| ParquetError::General(format!("zstd level {zstd_level}: {e}")))?;
        Ok(Self {
            file,
            arrow_schema,
            factory,
            row_groups: 0,
            plans,
            leaves,
            columns,
            arrow_writers: Vec::new(),
            rows: 0,
            page_rows: page_rows.max(1),
            level: zstd_level,
            zstd,
            scratch: Scratch::default(),
        })
    }

    /// Rows written to the row group in progress.
    pub fn in_progress_rows(&self) -> usize {
        self.rows
    }

    /// Writes `batch` (of the writer's schema) into the row group in progress.
    pub fn write(&mut self, batch: &RecordBatch) -> Result<()> {
        if batch.schema().fields() != self.arrow_schema.fields() {
            return Err(general("record batch schema does not match the ray file schema"));
        }
        if batch.num_rows() == 0 {
            return Ok(());
        }
        if self.arrow_writers.is_empty() && self.plans.contains(&Plan::Arrow) {
            self.arrow_writers = self.factory.create_column_writers(self.row_groups)?.into_iter().map(Some).collect();
        }
        for (f, field) in self.arrow_schema.fields().iter().enumerate() {
            let array = batch.column(f);
            match self.columns.get_mut(f).and_then(Option::as_mut) {
                Some(col) => {
                    col.push(array)?;
                    while col.pending >= self.page_rows {
                        col.emit_page(self.page_rows, &mut self.zstd, &mut self.scratch)?;
                    }
                }
                None => {
                    let first_leaf = self.leaves[f].0;
                    for (k, leaf) in compute_leaves(field, array)?.iter().enumerate() {
                        let w = self
                            .arrow_writers
                            .get_mut(first_leaf + k)
                            .and_then(Option::as_mut)
                            .ok_or_else(|| general("no column writer for a payload leaf"))?;
                        w.write(leaf)?;
                    }
                }
            }
        }
        self.rows += batch.num_rows();
        Ok(())
    }

    /// Closes the row group in progress (nothing when it has no rows).
    pub fn flush(&mut self) -> Result<()> {
        if self.rows == 0 {
            return Ok(());
        }
        let rows = std::mem::take(&mut self.rows);
        let mut chunks = Vec::with_capacity(self.columns.len());
        for col in self.columns.iter_mut().flatten() {
            if col.pending > 0 {
                let n = col.pending;
                col.emit_page(n, &mut self.zstd, &mut self.scratch)?;
            }
            chunks.push(col.close(rows, self.level)?);
        }
        let mut chunks = chunks.into_iter();
        let mut arrow_writers = std::mem::take(&mut self.arrow_writers);
        let mut rg = self.file.next_row_group()?;
        for (f, plan) in self.plans.iter().enumerate() {
            if *plan == Plan::Arrow {
                let (first_leaf, n_leaves) = self.leaves[f];
                for k in 0..n_leaves {
                    let w = arrow_writers
                        .get_mut(first_leaf + k)
                        .and_then(Option::take)
                        .ok_or_else(|| general("no column writer for a payload leaf"))?;
                    w.close()?.append_to_row_group(&mut rg)?;
                }
            } else {
                let (bytes, close) = chunks.next().ok_or_else(|| general("a paged column went missing"))?;
                rg.append_column(&bytes, close)?;
            }
        }
        rg.close()?;
        self.row_groups += 1;
        Ok(())
    }

    pub fn append_key_value_metadata(&mut self, kv: KeyValue) {
        self.file.append_key_value_metadata(kv);
    }

    /// Writes the last row group and the footer; returns the sink.
    pub fn into_inner(mut self) -> Result<W> {
        self.flush()?;
        self.file.into_inner()
    }
}

fn general(message: &str) -> ParquetError {
    ParquetError::General(message.to_string())
}

/// Buffers shared by the paged columns: one page uncompressed and compressed, the deltas.
#[derive(Default)]
struct Scratch {
    page: Vec<u8>,
    compressed: Vec<u8>,
    deltas: Vec<i64>,
}

/// One column written here: the values of the page in progress and the pages of the row group
/// in progress (compressed, in memory until the row group closes).
struct PagedColumn {
    descr: ColumnDescPtr,
    encoding: Encoding,
    physical: PhysicalType,
    stats: bool,
    nullable: bool,
    /// Rows, non-null values (widened) and validity of the page in progress.
    pending: usize,
    values32: Vec<u32>,
    values64: Vec<u64>,
    valid: Vec<bool>,
    sink: TrackedWrite<Vec<u8>>,
    offsets: OffsetIndexBuilder,
    index: ColumnIndexBuilder,
    uncompressed: i64,
    nulls: u64,
    min: u64,
    max: u64,
    ascending: bool,
    descending: bool,
    last: Option<(u64, u64)>,
}

impl PagedColumn {
    fn new(descr: ColumnDescPtr, plan: Plan) -> Option<Self> {
        let (encoding, physical, stats) = match plan {
            Plan::Split { stats } => (Encoding::BYTE_STREAM_SPLIT, PhysicalType::INT32, stats),
            Plan::Delta => (Encoding::DELTA_BINARY_PACKED, PhysicalType::INT64, true),
            Plan::Arrow => return None,
        };
        if descr.physical_type() != physical || descr.max_rep_level() > 0 {
            return None;
        }
        Some(Self {
            nullable: descr.max_def_level() > 0,
            descr,
            encoding,
            physical,
            stats,
            pending: 0,
            values32: Vec::new(),
            values64: Vec::new(),
            valid: Vec::new(),
            sink: TrackedWrite::new(Vec::new()),
            offsets: OffsetIndexBuilder::new(),
            index: ColumnIndexBuilder::new(physical),
            uncompressed: 0,
            nulls: 0,
            min: u64::MAX,
            max: 0,
            ascending: true,
            descending: true,
            last: None,
        })
    }

    /// Appends an array's values to the page in progress.
    fn push(&mut self, a: &ArrayRef) -> Result<()> {
        if self.nullable {
            match a.nulls() {
                Some(n) => self.valid.extend(n.iter()),
                None => self.valid.extend(std::iter::repeat_n(true, a.len())),
            }
        } else if a.null_count() > 0 {
            return Err(ParquetError::General(format!("column {} is required but holds nulls", self.descr.name())));
        }
        let nulls = a.nulls().filter(|n| n.null_count() > 0);
        match a.data_type() {
            DataType::UInt8 => push_valid(&mut self.values32, a.as_primitive::<UInt8Type>().values(), nulls, u32::from),
            DataType::UInt16 => {
                push_valid(&mut self.values32, a.as_primitive::<UInt16Type>().values(), nulls, u32::from)
            }
            DataType::UInt32 => push_valid(&mut self.values32, a.as_primitive::<UInt32Type>().values(), nulls, |v| v),
            DataType::UInt64 => push_valid(&mut self.values64, a.as_primitive::<UInt64Type>().values(), nulls, |v| v),
            other => {
                return Err(ParquetError::General(format!("column {}: cannot page {other}", self.descr.name())));
            }
        }
        self.pending += a.len();
        Ok(())
    }

    /// Encodes, compresses and writes the first `n` pending rows as one data page.
    fn emit_page(&mut self, n: usize, zstd: &mut zstd::bulk::Compressor<'static>, s: &mut Scratch) -> Result<()> {
        s.page.clear();
        let present = if self.nullable {
            let valid = &self.valid[..n];
            let present = valid.iter().filter(|&&v| v).count();
            def_levels(valid, present == n, &mut s.page);
            present
        } else {
            n
        };
        // Min/max only where the column keeps statistics (not for the residual columns).
        let (lo, hi) = if self.physical == PhysicalType::INT32 {
            let v = &self.values32[..present];
            split_u32(v, &mut s.page);
            if self.stats { min_max(v.iter().map(|&x| u64::from(x))) } else { (0, 0) }
        } else {
            let v = &self.values64[..present];
            delta_encode(v, &mut s.deltas, &mut s.page);
            if self.stats { min_max(v.iter().copied()) } else { (0, 0) }
        };
        let page_nulls = (n - present) as u64;
        self.nulls += page_nulls;
        if self.stats {
            if present == 0 {
                self.index.append(true, Vec::new(), Vec::new(), page_nulls as i64);
            } else {
                let bytes = |x: u64| {
                    if self.physical == PhysicalType::INT32 {
                        (x as u32).to_le_bytes().to_vec()
                    } else {
                        x.to_le_bytes().to_vec()
                    }
                };
                self.index.append(false, bytes(lo), bytes(hi), page_nulls as i64);
                self.min = self.min.min(lo);
                self.max = self.max.max(hi);
                if let Some((plo, phi)) = self.last {
                    self.ascending &= plo <= lo && phi <= hi;
                    self.descending &= plo >= lo && phi >= hi;
                }
                self.last = Some((lo, hi));
            }
        }
        s.compressed.clear();
        s.compressed.reserve(zstd::zstd_safe::compress_bound(s.page.len()));
        zstd.compress_to_buffer(&s.page, &mut s.compressed).map_err(|e| ParquetError::General(format!("zstd: {e}")))?;
        let page = Page::DataPage {
            buf: Bytes::copy_from_slice(&s.compressed),
            num_values: n as u32,
            encoding: self.encoding,
            def_level_encoding: Encoding::RLE,
            rep_level_encoding: Encoding::RLE,
            statistics: None,
        };
        let spec = SerializedPageWriter::new(&mut self.sink).write_page(CompressedPage::new(page, s.page.len()))?;
        self.uncompressed += spec.uncompressed_size as i64;
        self.offsets.append_row_count(n as i64);
        self.offsets.append_offset_and_size(spec.offset as i64, spec.compressed_size as i32);
        // What is left starts the next page.
        if self.nullable {
            self.valid.drain(..n);
        }
        if self.physical == PhysicalType::INT32 {
            self.values32.drain(..present);
        } else {
            self.values64.drain(..present);
        }
        self.pending -= n;
        Ok(())
    }

    /// The row group's column chunk (`rows` rows, every page emitted): its bytes and what
    /// `append_column` takes (offsets relative to the bytes). Starts the next chunk.
    fn close(&mut self, rows: usize, level: i32) -> Result<(Bytes, ColumnCloseResult)> {
        let sink = std::mem::replace(&mut self.sink, TrackedWrite::new(Vec::new()));
        let offsets = std::mem::take(&mut self.offsets);
        let index = std::mem::replace(&mut self.index, ColumnIndexBuilder::new(self.physical));
        let (uncompressed, nulls) = (std::mem::take(&mut self.uncompressed), std::mem::take(&mut self.nulls));
        let (min, max) = (std::mem::replace(&mut self.min, u64::MAX), std::mem::take(&mut self.max));
        let (ascending, descending) =
            (std::mem::replace(&mut self.ascending, true), std::mem::replace(&mut self.descending, true));
        self.last = None;
        let bytes = Bytes::from(sink.into_inner()?);
        let mut meta = ColumnChunkMetaData::builder(self.descr.clone())
            .set_compression(Compression::ZSTD(ZstdLevel::try_new(level)?))
            .set_encodings_mask(EncodingMask::new_from_encodings([Encoding::RLE, self.encoding].iter()))
            .set_total_compressed_size(bytes.len() as i64)
            .set_total_uncompressed_size(uncompressed)
            .set_num_values(rows as i64)
            .set_data_page_offset(0);
        let mut column_index = None;
        if self.stats {
            let present = (rows as u64) > nulls;
            let (lo, hi) = (present.then_some(min), present.then_some(max));
            let s = if self.physical == PhysicalType::INT32 {
                Statistics::Int32(
                    ValueStatistics::new(
                        lo.map(|x| x as u32 as i32),
                        hi.map(|x| x as u32 as i32),
                        None,
                        Some(nulls),
                        false,
                    )
                    .with_backwards_compatible_min_max(false),
                )
            } else {
                Statistics::Int64(
                    ValueStatistics::new(lo.map(|x| x as i64), hi.map(|x| x as i64), None, Some(nulls), false)
                        .with_backwards_compatible_min_max(false),
                )
            };
            meta = meta.set_statistics(s);
            let mut index = index;
            index.set_boundary_order(match (ascending, descending) {
                (true, _) => BoundaryOrder::ASCENDING,
                (false, true) => BoundaryOrder::DESCENDING,
                (false, false) => BoundaryOrder::UNORDERED,
            });
            column_index = Some(index.build()?);
        }
        let close = ColumnCloseResult {
            bytes_written: bytes.len() as u64,
            rows_written: rows as u64,
            metadata: meta.build()?,
            bloom_filter: None,
            column_index,
            offset_index: Some(offsets.build()),
        };
        Ok((bytes, close))
    }
}

/// Appends the non-null values of `values` (all of them when there are no nulls), widened.
#[inline]
fn push_valid<T: Copy, U>(out: &mut Vec<U>, values: &[T], nulls: Option<&NullBuffer>, widen: impl Fn(T) -> U) {
    match nulls {
        Some(n) => out.extend(values.iter().zip(n.iter()).filter(|&(_, ok)| ok).map(|(&v, _)| widen(v))),
        None => out.extend(values.iter().map(|&v| widen(v))),
    }
}

fn min_max(values: impl Iterator<Item = u64>) -> (u64, u64) {
    values.fold((u64::MAX, 0), |(lo, hi), v| (lo.min(v), hi.max(v)))
}

/// `BYTE_STREAM_SPLIT` of 4-byte values: byte k of every value, for k = 0..4, one plane after
/// another.
fn split_u32(values: &[u32], out: &mut Vec<u8>) {
    let n = values.len();
    let start = out.len();
    out.resize(start + 4 * n, 0);
    let (p0, rest) = out[start..].split_at_mut(n);
    let (p1, rest) = rest.split_at_mut(n);
    let (p2, p3) = rest.split_at_mut(n);
    for ((((v, a), b), c), d) in values.iter().zip(p0).zip(p1).zip(p2).zip(p3) {
        let [x0, x1, x2, x3] = v.to_le_bytes();
        (*a, *b, *c, *d) = (x0, x1, x2, x3);
    }
}

fn uleb(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn zigzag(v: i64) -> u64 {
    ((v << 1) ^ (v >> 63)) as u64
}

/// Definition levels of a v1 data page (bit width 1): a 4-byte length, then the RLE/bit-packed
/// hybrid: one run when every value is present, else bit-packed runs of up to 504 values.
fn def_levels(valid: &[bool], all: bool, out: &mut Vec<u8>) {
    let at = out.len();
    out.extend_from_slice(&[0; 4]);
    if all {
        uleb(out, (valid.len() as u64) << 1);
        out.push(1);
    } else {
        for run in valid.chunks(504) {
            let groups = run.len().div_ceil(8);
            uleb(out, ((groups as u64) << 1) | 1);
            for group in run.chunks(8) {
                out.push(group.iter().enumerate().fold(0u8, |b, (i, &v)| b | (u8::from(v) << i)));
            }
        }
    }
    let len = (out.len() - at - 4) as u32;
    out[at..at + 4].copy_from_slice(&len.to_le_bytes());
}

/// Values per `DELTA_BINARY_PACKED` block and miniblock.
const DELTA_BLOCK: usize = 128;
const DELTA_MINIBLOCK: usize = 32;

/// `DELTA_BINARY_PACKED` of 8-byte values (as two's complement i64, as Parquet stores UINT_64).
fn delta_encode(values: &[u64], deltas: &mut Vec<i64>, out: &mut Vec<u8>) {
    uleb(out, DELTA_BLOCK as u64);
    uleb(out, (DELTA_BLOCK / DELTA_MINIBLOCK) as u64);
    uleb(out, values.len() as u64);
    let Some(&first) = values.first() else {
        uleb(out, 0);
        return;
    };
    uleb(out, zigzag(first as i64));
    deltas.clear();
    deltas.extend(values.windows(2).map(|w| (w[1] as i64).wrapping_sub(w[0] as i64)));
    for block in deltas.chunks(DELTA_BLOCK) {
        let min = block.iter().copied().min().unwrap_or(0);
        uleb(out, zigzag(min));
        let widths_at = out.len();
        out.extend_from_slice(&[0; DELTA_BLOCK / DELTA_MINIBLOCK]);
        for (m, mini) in block.chunks(DELTA_MINIBLOCK).enumerate() {
            let max = mini.iter().map(|&d| d.wrapping_sub(min) as u64).max().unwrap_or(0);
            let width = 64 - max.leading_zeros();
            out[widths_at + m] = width as u8;
            if width == 0 {
                continue;
            }
            // Bit-pack 32 values (padded with zeros), least significant bit first.
            let (mut acc, mut bits) = (0u128, 0u32);
            for k in 0..DELTA_MINIBLOCK {
                let v = mini.get(k).map_or(0, |&d| d.wrapping_sub(min) as u64);
                acc |= u128::from(v) << bits;
                bits += width;
                while bits >= 8 {
                    out.push(acc as u8);
                    acc >>= 8;
                    bits -= 8;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use arrow::array::{UInt8Array, UInt16Array, UInt32Array, UInt64Array};
    use arrow::datatypes::{Field, Schema};
    use parquet::arrow::arrow_reader::{ArrowReaderOptions, ParquetRecordBatchReaderBuilder};
    use parquet::file::metadata::PageIndexPolicy;
    use parquet::file::page_index::column_index::ColumnIndexMetaData;

    fn schema() -> SchemaRef {
        Arc::new(Schema::new(vec![
            Field::new("id", DataType::UInt64, false),
            Field::new("a", DataType::UInt32, false),
            Field::new("b", DataType::UInt32, true),
            Field::new("c", DataType::UInt8, false),
            Field::new("d", DataType::UInt16, true),
            Field::new("payload", DataType::Float32, true),
        ]))
    }

    fn batch(start: u64, n: usize) -> RecordBatch {
        let mut s = start.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        // Ids: runs and jumps, including huge ones (wrapping deltas) and the extremes.
        let ids: Vec<u64> = (0..n as u64)
            .map(|i| match i % 97 {
                0 => u64::MAX,
                1 => 0,
                2 => next(),
                _ => start + i / 3,
            })
            .collect();
        let a: Vec<u32> = (0..n).map(|_| next() as u32).collect();
        let b: Vec<Option<u32>> = (0..n).map(|i| (i % 5 != 0).then(|| next() as u32 >> (i % 32))).collect();
        let c: Vec<u8> = (0..n).map(|i| (i % 7) as u8).collect();
        // A whole stretch of nulls: null pages in the column index.
        let d: Vec<Option<u16>> = (0..n).map(|i| (i < n / 2).then_some(i as u16)).collect();
        let p: Vec<Option<f32>> = (0..n).map(|i| (i % 3 != 0).then_some(i as f32 * 0.5)).collect();
        RecordBatch::try_new(
            schema(),
            vec![
                Arc::new(UInt64Array::from(ids)),
                Arc::new(UInt32Array::from(a)),
                Arc::new(UInt32Array::from(b)),
                Arc::new(UInt8Array::from(c)),
                Arc::new(UInt16Array::from(d)),
                Arc::new(arrow::array::Float32Array::from(p)),
            ],
        )
        .unwrap()
    }

    #[test]
    fn columns_written_here_read_back_exactly_with_their_page_index() {
        let plans = [
            Plan::Delta,
            Plan::Split { stats: false },
            Plan::Split { stats: true },
            Plan::Split { stats: true },
            Plan::Split { stats: true },
            Plan::Arrow,
        ];
        let mut w =
            RayFileWriter::try_new(Vec::new(), schema(), WriterProperties::builder().build(), &plans, 1, 1000).unwrap();
        assert_eq!(w.plans, plans);
        let batches = [batch(5, 2500), batch(90_000, 777), batch(1 << 40, 3001), batch(7, 1)];
        // Row groups of 3277 rows (two batches, pages cut across them) and 3002.
        w.write(&batches[0]).unwrap();
        w.write(&batches[1]).unwrap();
        w.flush().unwrap();
        w.write(&batches[2]).unwrap();
        w.write(&batches[3]).unwrap();
        w.append_key_value_metadata(KeyValue::new("k".to_string(), "v".to_string()));
        let bytes = Bytes::from(w.into_inner().unwrap());

        let options = ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Required);
        let reader = ParquetRecordBatchReaderBuilder::try_new_with_options(bytes.clone(), options).unwrap();
        let md = reader.metadata().clone();
        assert_eq!(reader.schema().fields(), schema().fields(), "the Arrow schema is stored");
        let got: Vec<RecordBatch> = reader.build().unwrap().map(|b| b.unwrap()).collect();
        let got = arrow::compute::concat_batches(&schema(), &got).unwrap();
        let want = arrow::compute::concat_batches(&schema(), &batches).unwrap();
        assert_eq!(got, want);

        assert_eq!(md.num_row_groups(), 2);
        assert_eq!(md.file_metadata().key_value_metadata().unwrap().iter().filter(|kv| kv.key == "k").count(), 1);
        let rg = md.row_group(0);
        assert_eq!(rg.num_rows(), 3277);
        assert_eq!(rg.column(0).encodings().collect::<Vec<_>>(), vec![Encoding::RLE, Encoding::DELTA_BINARY_PACKED]);
        assert!(rg.column(2).encodings().any(|e| e == Encoding::BYTE_STREAM_SPLIT));
        // Pages of 1000 rows across the batch boundary; every column has its offset index.
        let offsets = &md.offset_index().unwrap()[0];
        let firsts: Vec<i64> = offsets[1].page_locations().iter().map(|l| l.first_row_index).collect();
        assert_eq!(firsts, vec![0, 1000, 2000, 3000]);
        assert!(offsets[..5].iter().all(|o| o.page_locations().len() == 4));
        assert!(!offsets[5].page_locations().is_empty(), "the payload column (arrow-rs) has its offset index too");
        // Statistics: none for the split column without them, unsigned min/max for the others.
        assert!(rg.column(1).statistics().is_none());
        let Some(Statistics::Int64(s)) = rg.column(0).statistics() else { panic!("tree id statistics") };
        assert_eq!((*s.min_opt().unwrap() as u64, *s.max_opt().unwrap() as u64), (0, u64::MAX));
        let index = &md.column_index().unwrap()[0];
        assert!(matches!(index[1], ColumnIndexMetaData::NONE));
        let ColumnIndexMetaData::INT32(c) = &index[3] else { panic!("u8 column index") };
        assert_eq!((c.min_value(0), c.max_value(0)), (Some(&0), Some(&6)));
        let ColumnIndexMetaData::INT32(d) = &index[4] else { panic!("u16 column index") };
        // Rows 1638.. of the first group are null: the third and fourth pages hold no value.
        assert_eq!(d.null_count(3), Some(277));
        assert!(d.min_value(3).is_none());
        assert_eq!(d.max_value(1), Some(&1249));
        let ColumnIndexMetaData::INT32(b) = &index[2] else { panic!("u32 column index") };
        let b_col = want.column(2).as_primitive::<UInt32Type>();
        let want_max = b_col.iter().take(1000).flatten().max().unwrap();
        assert_eq!(b.max_value(0).map(|&v| v as u32), Some(want_max), "unsigned order");
    }

    #[test]
    fn delta_handles_empty_single_and_wrapping_runs() {
        for values in [vec![], vec![42u64], vec![u64::MAX, 0, u64::MAX, 1, 1, 1], (0..1000u64).map(|i| i * i).collect()]
        {
            let n = values.len();
            let schema = Arc::new(Schema::new(vec![Field::new("id", DataType::UInt64, false)]));
            let b = RecordBatch::try_new(schema.clone(), vec![Arc::new(UInt64Array::from(values.clone()))]).unwrap();
            let mut w =
                RayFileWriter::try_new(Vec::new(), schema, WriterProperties::builder().build(), &[Plan::Delta], 3, 300)
                    .unwrap();
            w.write(&b).unwrap();
            let bytes = Bytes::from(w.into_inner().unwrap());
            let r = ParquetRecordBatchReaderBuilder::try_new(bytes).unwrap().build().unwrap();
            let got: Vec<u64> =
                r.flat_map(|b| b.unwrap().column(0).as_primitive::<UInt64Type>().values().to_vec()).collect();
            assert_eq!(got, values, "{n} values");
        }
    }
}
