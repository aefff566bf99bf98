//! The ray files' Parquet writer: the core integer columns and the numeric payload columns are
//! encoded and compressed here, page by page, instead of by arrow-rs's column writers.
//!
//! The files are the same Parquet as before (format unchanged, any reader sees the same
//! columns, encodings, statistics and page index): `BYTE_STREAM_SPLIT` integer columns,
//! `DELTA_BINARY_PACKED` tree ids, `PLAIN` float payloads (fixed-size lists with their
//! repetition and definition levels), data pages v1 compressed with zstd, an offset index for
//! every column and a column index (page min/max; floats ignoring NaN, zero minima as -0.0) for
//! the columns with statistics. Writing them here costs a fraction of the generic path: arrow-rs
//! splits byte streams one byte at a time, bit-packs deltas and levels one value at a time and
//! allocates every page's buffers anew; here one transposing loop per column, one bit-packing
//! loop per miniblock and buffers reused across pages and row groups. Payload columns of other
//! types still go through arrow-rs's column writers, into the same row groups.

use std::io::Write;
use std::sync::Arc;

use arrow::array::{Array, ArrayRef, AsArray, RecordBatch};
use arrow::buffer::{BooleanBuffer, NullBuffer};
use arrow::datatypes::{DataType, Float32Type, SchemaRef, UInt8Type, UInt16Type, UInt32Type, UInt64Type};
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
    /// u8/u16/u32 values as INT32 or f32 values as FLOAT (flat or fixed-size lists of them),
    /// `BYTE_STREAM_SPLIT`; `stats`: page min/max and chunk statistics.
    Split { stats: bool },
    /// The same values and lists, `PLAIN` (for floats that repeat whole: byte-splitting them
    /// hides the repeats from zstd).
    Plain { stats: bool },
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
        // A field whose type or Parquet leaf does not fit its plan (None) goes to arrow-rs.
        let columns: Vec<Option<PagedColumn>> = fields
            .iter()
            .zip(&leaves)
            .enumerate()
            .map(|(i, (field, &(leaf, _)))| {
                let plan = plans.get(i).copied().unwrap_or(Plan::Arrow);
                PagedColumn::new(parquet_schema.column(leaf), field, plan)
            })
            .collect();
        let zstd = zstd::bulk::Compressor::new(zstd_level)
            .map_err(|e| ParquetError::General(format!("zstd level {zstd_level}: {e}")))?;
        Ok(Self {
            file,
            arrow_schema,
            factory,
            row_groups: 0,
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

    /// How each field is written (`Plan::Arrow` where arrow-rs writes it).
    #[cfg(test)]
    fn plans(&self) -> Vec<Plan> {
        let plan = |c: &PagedColumn| match c.encoding {
            Encoding::DELTA_BINARY_PACKED => Plan::Delta,
            Encoding::PLAIN => Plan::Plain { stats: c.stats },
            _ => Plan::Split { stats: c.stats },
        };
        self.columns.iter().map(|c| c.as_ref().map_or(Plan::Arrow, plan)).collect()
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
        if self.arrow_writers.is_empty() && self.columns.iter().any(Option::is_none) {
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
        let mut arrow_writers = std::mem::take(&mut self.arrow_writers);
        let mut rg = self.file.next_row_group()?;
        for (f, column) in self.columns.iter_mut().enumerate() {
            match column {
                Some(col) => {
                    if col.pending > 0 {
                        let n = col.pending;
                        col.emit_page(n, &mut self.zstd, &mut self.scratch)?;
                    }
                    let (bytes, close) = col.close(rows, self.level)?;
                    rg.append_column(&bytes, close)?;
                }
                None => {
                    let (first_leaf, n_leaves) = self.leaves[f];
                    for k in 0..n_leaves {
                        let w = arrow_writers
                            .get_mut(first_leaf + k)
                            .and_then(Option::take)
                            .ok_or_else(|| general("no column writer for a payload leaf"))?;
                        w.close()?.append_to_row_group(&mut rg)?;
                    }
                }
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
    levels: Vec<u8>,
}

/// Rows, levels and values of a paged column: flat (`list` None; definition level 0 for a null
/// row when nullable) or a fixed-size list of `n` values per row (repetition level 1: the first
/// value of a row 0, the others 1; definition levels 0 for a null list, `max_def - 1` for a null
/// value, `max_def` for a value).
#[derive(Clone, Copy, Debug)]
struct Shape {
    list: Option<usize>,
    nullable: bool,
    item_nullable: bool,
    max_def: i16,
}

/// How a 4-byte column's values order for statistics.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Order {
    Unsigned,
    /// IEEE floats: NaN ignored, -0.0 below +0.0.
    Float,
}

/// One column written here: the values of the page in progress and the pages of the row group
/// in progress (compressed, in memory until the row group closes).
struct PagedColumn {
    descr: ColumnDescPtr,
    encoding: Encoding,
    physical: PhysicalType,
    order: Order,
    stats: bool,
    shape: Shape,
    /// Rows, non-null values (widened; floats as their bits), row validity and (lists whose
    /// values may be null) the validity of each value of the valid rows, of the page in progress.
    pending: usize,
    values32: Vec<u32>,
    values64: Vec<u64>,
    valid: Vec<bool>,
    item_valid: Vec<bool>,
    sink: TrackedWrite<Vec<u8>>,
    offsets: OffsetIndexBuilder,
    index: ColumnIndexBuilder,
    uncompressed: i64,
    /// Level entries (values and nulls) and nulls of the column chunk in progress.
    levels: u64,
    nulls: u64,
    /// Smallest and largest value of the chunk, as order keys ([`order_key`]).
    range: Option<(u64, u64)>,
    ascending: bool,
    descending: bool,
    last: Option<(u64, u64)>,
}

/// Whether a leaf type is paged as 4-byte values with `BYTE_STREAM_SPLIT`.
fn splits(t: &DataType) -> bool {
    matches!(t, DataType::UInt8 | DataType::UInt16 | DataType::UInt32 | DataType::Float32)
}

/// A value's key in its column's order (floats: a total order over the non-NaN values).
#[inline]
fn order_key(order: Order, v: u32) -> u64 {
    match order {
        Order::Unsigned => u64::from(v),
        Order::Float if v & 0x8000_0000 != 0 => u64::from(!v),
        Order::Float => u64::from(v | 0x8000_0000),
    }
}

/// The value of an order key, as the little-endian bytes statistics hold. Float minima of zero
/// are written as -0.0 and maxima as +0.0, as the Parquet format asks.
fn key_value(order: Order, key: u64, is_min: bool) -> u32 {
    match order {
        Order::Unsigned => key as u32,
        Order::Float => {
            let k = key as u32;
            let bits = if k & 0x8000_0000 != 0 { k & 0x7FFF_FFFF } else { !k };
            match (f32::from_bits(bits) == 0.0, is_min) {
                (true, true) => (-0.0f32).to_bits(),
                (true, false) => 0.0f32.to_bits(),
                _ => bits,
            }
        }
    }
}

impl PagedColumn {
    fn new(descr: ColumnDescPtr, field: &arrow::datatypes::Field, plan: Plan) -> Option<Self> {
        let (encoding, stats) = match plan {
            Plan::Split { stats } => (Encoding::BYTE_STREAM_SPLIT, stats),
            Plan::Plain { stats } => (Encoding::PLAIN, stats),
            Plan::Delta => (Encoding::DELTA_BINARY_PACKED, true),
            Plan::Arrow => return None,
        };
        let (list, leaf, item_nullable) = match field.data_type() {
            DataType::FixedSizeList(item, n) => (Some(usize::try_from(*n).ok()?), item.data_type(), item.is_nullable()),
            t => (None, t, false),
        };
        let (physical, order) = match leaf {
            DataType::UInt64 if plan == Plan::Delta && list.is_none() && !field.is_nullable() => {
                (PhysicalType::INT64, Order::Unsigned)
            }
            DataType::Float32 if plan != Plan::Delta => (PhysicalType::FLOAT, Order::Float),
            t if plan != Plan::Delta && splits(t) => (PhysicalType::INT32, Order::Unsigned),
            _ => return None,
        };
        let nullable = field.is_nullable();
        let (max_rep, max_def) = match list {
            None => (0, i16::from(nullable)),
            Some(_) => (1, i16::from(nullable) + 1 + i16::from(item_nullable)),
        };
        if descr.physical_type() != physical
            || descr.max_rep_level() != max_rep
            || descr.max_def_level() != max_def
            || list == Some(0)
        {
            return None;
        }
        Some(Self {
            descr,
            encoding,
            physical,
            order,
            stats,
            shape: Shape { list, nullable, item_nullable, max_def },
            pending: 0,
            values32: Vec::new(),
            values64: Vec::new(),
            valid: Vec::new(),
            item_valid: Vec::new(),
            sink: TrackedWrite::new(Vec::new()),
            offsets: OffsetIndexBuilder::new(),
            index: ColumnIndexBuilder::new(physical),
            uncompressed: 0,
            levels: 0,
            nulls: 0,
            range: None,
            ascending: true,
            descending: true,
            last: None,
        })
    }

    /// Appends an array's rows to the page in progress.
    fn push(&mut self, a: &ArrayRef) -> Result<()> {
        let name = || self.descr.name().to_string();
        let row_nulls = a.nulls().filter(|n| n.null_count() > 0);
        if self.shape.nullable {
            match row_nulls {
                Some(n) => self.valid.extend(n.iter()),
                None => self.valid.extend(std::iter::repeat_n(true, a.len())),
            }
        } else if row_nulls.is_some() {
            return Err(ParquetError::General(format!("column {} is required but holds nulls", name())));
        }
        match self.shape.list {
            None => push_leaf(&mut self.values32, &mut self.values64, a.as_ref(), row_nulls)
                .map_err(|t| ParquetError::General(format!("column {}: cannot page {t}", name())))?,
            Some(n) => {
                let list = a
                    .as_fixed_size_list_opt()
                    .filter(|l| l.value_length() as usize == n && l.values().len() == l.len() * n)
                    .ok_or_else(|| ParquetError::General(format!("column {}: expected lists of {n} values", name())))?;
                let values = list.values();
                let item_nulls = values.nulls().filter(|m| m.null_count() > 0);
                if item_nulls.is_some() && !self.shape.item_nullable {
                    return Err(ParquetError::General(format!("column {}: list values are required", name())));
                }
                if self.shape.item_nullable {
                    for row in 0..list.len() {
                        if row_nulls.is_none_or(|r| r.is_valid(row)) {
                            let slots = row * n..(row + 1) * n;
                            self.item_valid.extend(slots.map(|k| item_nulls.is_none_or(|m| m.is_valid(k))));
                        }
                    }
                }
                // The values to keep: those of valid rows that are not null themselves.
                let keep = match (row_nulls, item_nulls) {
                    (None, None) => None,
                    (rows, items) => Some(NullBuffer::new(BooleanBuffer::collect_bool(values.len(), |k| {
                        rows.is_none_or(|r| r.is_valid(k / n)) && items.is_none_or(|m| m.is_valid(k))
                    }))),
                };
                push_leaf(&mut self.values32, &mut self.values64, values.as_ref(), keep.as_ref())
                    .map_err(|t| ParquetError::General(format!("column {}: cannot page {t}", name())))?;
            }
        }
        self.pending += a.len();
        Ok(())
    }

    /// Writes the repetition and definition levels of the first `n` pending rows, which hold
    /// `rows_valid` valid rows and `slots` list slots (their values, null or not). Returns the
    /// number of level entries.
    fn write_levels(&self, n: usize, rows_valid: usize, slots: usize, present: usize, s: &mut Scratch) -> usize {
        let shape = self.shape;
        let Some(len) = shape.list else {
            if shape.nullable {
                def_levels(&self.valid[..n], rows_valid == n, &mut s.page);
            }
            return n;
        };
        let entries = (n - rows_valid) + slots;
        let def_width = 16 - (shape.max_def as u16).leading_zeros();
        // Repetition levels: 0 for each row's first entry, 1 for the others.
        s.levels.clear();
        for row in 0..n {
            if shape.nullable && !self.valid[row] {
                s.levels.push(0);
            } else {
                s.levels.push(0);
                s.levels.extend(std::iter::repeat_n(1, len - 1));
            }
        }
        hybrid_levels(&s.levels, 1, &mut s.page);
        if present == entries {
            rle_levels(entries, shape.max_def as u8, def_width, &mut s.page);
        } else {
            s.levels.clear();
            let mut slot = 0;
            for row in 0..n {
                if shape.nullable && !self.valid[row] {
                    s.levels.push(0);
                    continue;
                }
                for _ in 0..len {
                    let ok = !shape.item_nullable || self.item_valid[slot];
                    s.levels.push(if ok { shape.max_def as u8 } else { shape.max_def as u8 - 1 });
                    slot += 1;
                }
            }
            hybrid_levels(&s.levels, def_width, &mut s.page);
        }
        entries
    }

    /// Encodes, compresses and writes the first `n` pending rows as one data page.
    fn emit_page(&mut self, n: usize, zstd: &mut zstd::bulk::Compressor<'static>, s: &mut Scratch) -> Result<()> {
        s.page.clear();
        let rows_valid = if self.shape.nullable { self.valid[..n].iter().filter(|&&v| v).count() } else { n };
        let slots = rows_valid * self.shape.list.unwrap_or(1);
        let present =
            if self.shape.item_nullable { self.item_valid[..slots].iter().filter(|&&v| v).count() } else { slots };
        let entries = self.write_levels(n, rows_valid, slots, present, s);
        // Min/max only where the column keeps statistics (not for the residual columns).
        let range = if self.physical == PhysicalType::INT64 {
            let v = &self.values64[..present];
            delta_encode(v, &mut s.deltas, &mut s.page);
            if self.stats { min_max(v.iter().copied()) } else { None }
        } else {
            let v = &self.values32[..present];
            if self.encoding == Encoding::PLAIN {
                s.page.extend(v.iter().flat_map(|x| x.to_le_bytes()));
            } else {
                split_u32(v, &mut s.page);
            }
            match (self.stats, self.order) {
                (false, _) => None,
                (true, Order::Unsigned) => min_max(v.iter().map(|&x| u64::from(x))),
                (true, Order::Float) => {
                    min_max(v.iter().filter(|&&x| x & 0x7FFF_FFFF <= 0x7F80_0000).map(|&x| order_key(Order::Float, x)))
                }
            }
        };
        let page_nulls = (entries - present) as u64;
        self.nulls += page_nulls;
        self.levels += entries as u64;
        if self.stats {
            match range {
                _ if present == 0 => self.index.append(true, Vec::new(), Vec::new(), page_nulls as i64),
                // Only NaNs: no page min/max, so no column index (as arrow-rs does).
                None => self.index.to_invalid(),
                Some((lo, hi)) => {
                    let bytes = |key: u64, is_min: bool| {
                        if self.physical == PhysicalType::INT64 {
                            key.to_le_bytes().to_vec()
                        } else {
                            key_value(self.order, key, is_min).to_le_bytes().to_vec()
                        }
                    };
                    self.index.append(false, bytes(lo, true), bytes(hi, false), page_nulls as i64);
                    self.range = Some(self.range.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
                    if let Some((plo, phi)) = self.last {
                        self.ascending &= plo <= lo && phi <= hi;
                        self.descending &= plo >= lo && phi >= hi;
                    }
                    self.last = Some((lo, hi));
                }
            }
        }
        s.compressed.clear();
        s.compressed.reserve(zstd::zstd_safe::compress_bound(s.page.len()));
        zstd.compress_to_buffer(&s.page, &mut s.compressed).map_err(|e| ParquetError::General(format!("zstd: {e}")))?;
        let page = Page::DataPage {
            buf: Bytes::copy_from_slice(&s.compressed),
            num_values: entries as u32,
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
        if self.shape.nullable {
            self.valid.drain(..n);
        }
        if self.shape.item_nullable {
            self.item_valid.drain(..slots);
        }
        if self.physical == PhysicalType::INT64 {
            self.values64.drain(..present);
        } else {
            self.values32.drain(..present);
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
        let levels = std::mem::take(&mut self.levels);
        let range = self.range.take();
        let (ascending, descending) =
            (std::mem::replace(&mut self.ascending, true), std::mem::replace(&mut self.descending, true));
        self.last = None;
        let bytes = Bytes::from(sink.into_inner()?);
        let mut meta = ColumnChunkMetaData::builder(self.descr.clone())
            .set_compression(Compression::ZSTD(ZstdLevel::try_new(level)?))
            .set_encodings_mask(EncodingMask::new_from_encodings([Encoding::RLE, self.encoding].iter()))
            .set_total_compressed_size(bytes.len() as i64)
            .set_total_uncompressed_size(uncompressed)
            .set_num_values(levels as i64)
            .set_data_page_offset(0);
        let mut column_index = None;
        if self.stats {
            let (lo, hi) = (range.map(|r| r.0), range.map(|r| r.1));
            let value = |key: Option<u64>, is_min: bool| key.map(|k| key_value(self.order, k, is_min));
            let s = match self.physical {
                PhysicalType::INT64 => Statistics::Int64(
                    ValueStatistics::new(lo.map(|x| x as i64), hi.map(|x| x as i64), None, Some(nulls), false)
                        .with_backwards_compatible_min_max(false),
                ),
                PhysicalType::FLOAT => Statistics::Float(
                    ValueStatistics::new(
                        value(lo, true).map(f32::from_bits),
                        value(hi, false).map(f32::from_bits),
                        None,
                        Some(nulls),
                        false,
                    )
                    .with_backwards_compatible_min_max(false),
                ),
                _ => Statistics::Int32(
                    ValueStatistics::new(
                        value(lo, true).map(|x| x as i32),
                        value(hi, false).map(|x| x as i32),
                        None,
                        Some(nulls),
                        false,
                    )
                    .with_backwards_compatible_min_max(false),
                ),
            };
            meta = meta.set_statistics(s);
            if index.valid() {
                let mut index = index;
                index.set_boundary_order(match (ascending, descending) {
                    (true, _) => BoundaryOrder::ASCENDING,
                    (false, true) => BoundaryOrder::DESCENDING,
                    (false, false) => BoundaryOrder::UNORDERED,
                });
                column_index = Some(index.build()?);
            }
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

/// Appends the values of a leaf array that `keep` keeps (all when None): 1-, 2- and 4-byte
/// unsigned integers widened to u32, floats as their bits, u64 as they are. Returns the type of
/// an array it cannot page.
fn push_leaf(
    out32: &mut Vec<u32>,
    out64: &mut Vec<u64>,
    a: &dyn Array,
    keep: Option<&NullBuffer>,
) -> std::result::Result<(), DataType> {
    match a.data_type() {
        DataType::UInt8 => push_valid(out32, a.as_primitive::<UInt8Type>().values(), keep, u32::from),
        DataType::UInt16 => push_valid(out32, a.as_primitive::<UInt16Type>().values(), keep, u32::from),
        DataType::UInt32 => push_valid(out32, a.as_primitive::<UInt32Type>().values(), keep, |v| v),
        DataType::Float32 => push_valid(out32, a.as_primitive::<Float32Type>().values(), keep, f32::to_bits),
        DataType::UInt64 => push_valid(out64, a.as_primitive::<UInt64Type>().values(), keep, |v| v),
        other => return Err(other.clone()),
    }
    Ok(())
}

/// Appends the non-null values of `values` (all of them when there are no nulls), widened.
#[inline]
fn push_valid<T: Copy, U>(out: &mut Vec<U>, values: &[T], nulls: Option<&NullBuffer>, widen: impl Fn(T) -> U) {
    match nulls {
        Some(n) => out.extend(values.iter().zip(n.iter()).filter(|&(_, ok)| ok).map(|(&v, _)| widen(v))),
        None => out.extend(values.iter().map(|&v| widen(v))),
    }
}

/// Smallest and largest of the values (None when there are none).
fn min_max(values: impl Iterator<Item = u64>) -> Option<(u64, u64)> {
    values.fold(None, |r, v| Some(r.map_or((v, v), |(lo, hi): (u64, u64)| (lo.min(v), hi.max(v)))))
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

/// Levels of a v1 data page as one RLE run of `count` times `level`: a 4-byte length, then the run.
fn rle_levels(count: usize, level: u8, bit_width: u32, out: &mut Vec<u8>) {
    let at = out.len();
    out.extend_from_slice(&[0; 4]);
    uleb(out, (count as u64) << 1);
    if bit_width > 0 {
        out.push(level);
    }
    let len = (out.len() - at - 4) as u32;
    out[at..at + 4].copy_from_slice(&len.to_le_bytes());
}

/// Levels of a v1 data page (each below `1 << bit_width`, at most 8 bits wide): a 4-byte length,
/// then the RLE/bit-packed hybrid: one run when all are equal, else bit-packed runs of up to 504
/// levels (8 levels to `bit_width` bytes, least significant bits first).
fn hybrid_levels(levels: &[u8], bit_width: u32, out: &mut Vec<u8>) {
    if let Some(&first) = levels.first()
        && levels.iter().all(|&l| l == first)
    {
        return rle_levels(levels.len(), first, bit_width, out);
    }
    let at = out.len();
    out.extend_from_slice(&[0; 4]);
    for run in levels.chunks(504) {
        uleb(out, ((run.len().div_ceil(8) as u64) << 1) | 1);
        for group in run.chunks(8) {
            let packed =
                group.iter().enumerate().fold(0u64, |acc, (i, &l)| acc | (u64::from(l) << (i as u32 * bit_width)));
            out.extend_from_slice(&packed.to_le_bytes()[..bit_width as usize]);
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
        assert_eq!(w.plans(), plans);
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
    #[test]
    fn float_and_fixed_size_list_columns_read_back_with_levels_nulls_and_float_statistics() {
        use arrow::array::{FixedSizeListArray, Float32Array};
        let tp_item = Arc::new(Field::new("item", DataType::Float32, false));
        let tq_item = Arc::new(Field::new("item", DataType::UInt16, true));
        let schema = Arc::new(Schema::new(vec![
            Field::new("tp", DataType::FixedSizeList(tp_item.clone(), 3), true),
            Field::new("tq", DataType::FixedSizeList(tq_item.clone(), 2), false),
            Field::new("f", DataType::Float32, true),
            Field::new("nan", DataType::Float32, false),
            Field::new("all_valid", DataType::FixedSizeList(tp_item.clone(), 3), true),
        ]));
        let batch = |start: usize, n: usize| {
            let tp_values: Vec<f32> = (0..n * 3).map(|k| (start * 3 + k) as f32 * 0.25 - 100.0).collect();
            let tp_valid: Vec<bool> = (0..n).map(|i| (start + i) % 4 != 1).collect();
            let tp = FixedSizeListArray::try_new(
                tp_item.clone(),
                3,
                Arc::new(Float32Array::from(tp_values.clone())),
                Some(NullBuffer::from(tp_valid)),
            )
            .unwrap();
            let tq_values: Vec<Option<u16>> =
                (0..n * 2).map(|k| (!(start * 2 + k).is_multiple_of(3)).then_some((start * 2 + k) as u16)).collect();
            let tq =
                FixedSizeListArray::try_new(tq_item.clone(), 2, Arc::new(UInt16Array::from(tq_values)), None).unwrap();
            let specials = [f32::NAN, -0.0, 0.0, f32::INFINITY, f32::NEG_INFINITY, 1e-38, -3.3e38];
            let f: Vec<Option<f32>> = (0..n)
                .map(|i| match (start + i) % 9 {
                    0 => None,
                    k => Some(specials[k % specials.len()] * if (start + i).is_multiple_of(2) { 1.0 } else { -1.0 }),
                })
                .collect();
            let all =
                FixedSizeListArray::try_new(tp_item.clone(), 3, Arc::new(Float32Array::from(tp_values)), None).unwrap();
            RecordBatch::try_new(
                schema.clone(),
                vec![
                    Arc::new(tp),
                    Arc::new(tq),
                    Arc::new(Float32Array::from(f)),
                    Arc::new(Float32Array::from(vec![f32::NAN; n])),
                    Arc::new(all),
                ],
            )
            .unwrap()
        };
        let plans = [Plan::Split { stats: true }; 5];
        let mut w =
            RayFileWriter::try_new(Vec::new(), schema.clone(), WriterProperties::builder().build(), &plans, 1, 500)
                .unwrap();
        assert_eq!(w.plans(), plans, "every column is paged here");
        let batches = [batch(0, 1234), batch(1234, 1), batch(1235, 800)];
        w.write(&batches[0]).unwrap();
        w.write(&batches[1].slice(0, 1)).unwrap();
        w.flush().unwrap();
        // A sliced batch: list values must follow the slice.
        let big = batch(1235, 900);
        w.write(&big.slice(100, 800)).unwrap();
        let bytes = Bytes::from(w.into_inner().unwrap());

        let options = ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Required);
        let reader = ParquetRecordBatchReaderBuilder::try_new_with_options(bytes, options).unwrap();
        let md = reader.metadata().clone();
        let got: Vec<RecordBatch> = reader.build().unwrap().map(|b| b.unwrap()).collect();
        let got = arrow::compute::concat_batches(&schema, &got).unwrap();
        let want =
            arrow::compute::concat_batches(&schema, &[batches[0].clone(), batches[1].clone(), big.slice(100, 800)])
                .unwrap();
        assert_eq!(got.num_rows(), want.num_rows());
        for c in [0, 1, 4] {
            assert_eq!(got.column(c).as_ref(), want.column(c).as_ref(), "column {c}");
        }
        // Floats compared by bits (NaN != NaN).
        for c in [2, 3] {
            let (g, w) = (got.column(c).as_primitive::<Float32Type>(), want.column(c).as_primitive::<Float32Type>());
            assert_eq!(g.nulls(), w.nulls());
            let bits = |a: &arrow::array::Float32Array| a.iter().map(|v| v.map(f32::to_bits)).collect::<Vec<_>>();
            assert!(bits(g) == bits(w), "column {c}");
        }
        for rg in md.row_groups() {
            for c in rg.columns() {
                assert!(c.encodings().any(|e| e == Encoding::BYTE_STREAM_SPLIT), "{}", c.column_path());
            }
        }
        let rg = md.row_group(0);
        // Nulls count leaf entries: a null list is one.
        let Some(Statistics::Float(tp)) = rg.column(0).statistics() else { panic!("tp statistics") };
        let tp_nulls = (0..1235).filter(|i| i % 4 == 1).count() as u64;
        assert_eq!(tp.null_count_opt(), Some(tp_nulls));
        assert_eq!(rg.column(0).num_values(), (1235 - tp_nulls as i64) * 3 + tp_nulls as i64);
        let valid_tp: Vec<f32> = (0..1235usize)
            .filter(|i| i % 4 != 1)
            .flat_map(|i| (0..3).map(move |k| (i * 3 + k) as f32 * 0.25 - 100.0))
            .collect();
        assert_eq!(tp.min_opt(), valid_tp.iter().copied().reduce(f32::min).as_ref());
        assert_eq!(tp.max_opt(), valid_tp.iter().copied().reduce(f32::max).as_ref());
        // NaN ignored, infinities kept, zero minima/maxima signed as the format asks.
        let Some(Statistics::Float(f)) = rg.column(2).statistics() else { panic!("f statistics") };
        assert_eq!((f.min_opt(), f.max_opt()), (Some(&f32::NEG_INFINITY), Some(&f32::INFINITY)));
        let Some(Statistics::Float(nan)) = rg.column(3).statistics() else { panic!("nan statistics") };
        assert_eq!((nan.min_opt(), nan.max_opt()), (None, None));
        let index = &md.column_index().unwrap()[0];
        assert!(matches!(index[3], ColumnIndexMetaData::NONE), "pages of only NaN: no column index");
        let ColumnIndexMetaData::FLOAT(tpi) = &index[0] else { panic!("tp column index") };
        assert_eq!(tpi.min_value(0), Some(&-100.0));
        assert_eq!(tpi.null_count(0), Some(125));
        let ColumnIndexMetaData::INT32(tqi) = &index[1] else { panic!("tq column index") };
        assert_eq!(tqi.max_value(0).map(|&v| v as u16), Some(998), "999 is null");
        let offsets = &md.offset_index().unwrap()[0];
        let firsts: Vec<i64> = offsets[0].page_locations().iter().map(|l| l.first_row_index).collect();
        assert_eq!(firsts, vec![0, 500, 1000], "pages hold rows, not values");
    }

    #[test]
    fn zero_minima_and_maxima_are_signed() {
        let schema = Arc::new(Schema::new(vec![Field::new("z", DataType::Float32, false)]));
        let b = RecordBatch::try_new(
            schema.clone(),
            vec![Arc::new(arrow::array::Float32Array::from(vec![0.0, -0.0, 0.0]))],
        )
        .unwrap();
        let mut w = RayFileWriter::try_new(
            Vec::new(),
            schema,
            WriterProperties::builder().build(),
            &[Plan::Split { stats: true }],
            1,
            10,
        )
        .unwrap();
        w.write(&b).unwrap();
        let bytes = Bytes::from(w.into_inner().unwrap());
        let r = ParquetRecordBatchReaderBuilder::try_new(bytes).unwrap();
        let Some(Statistics::Float(s)) = r.metadata().row_group(0).column(0).statistics() else { panic!("statistics") };
        assert_eq!(s.min_opt().map(|v| v.to_bits()), Some((-0.0f32).to_bits()));
        assert_eq!(s.max_opt().map(|v| v.to_bits()), Some(0.0f32.to_bits()));
    }
}
