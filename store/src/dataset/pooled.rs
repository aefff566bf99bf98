//! The one way this store builds a Parquet reader over a range of a file's rows: arrow-rs's page
//! and array readers, with the zstd pages decompressed by contexts kept in a pool.
//!
//! arrow-rs's page reader makes a codec for every column chunk it opens, and its zstd codec makes
//! a compression and a decompression context each time. Making a context asks the CPU for BMI2
//! (`cpuid`), which a virtual machine traps: on the 2-core VM the four `cpuid`s of one codec cost
//! about 12 µs, a fifth of a one-tree fetch (26 columns). Here a column chunk compressed with zstd
//! is read as if uncompressed (the pages' bytes pass through untouched, their CRCs still checked
//! by arrow-rs) and each page is decompressed with a context taken from the pool; every other
//! codec goes through arrow-rs unchanged.

use std::fs::File;
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use parquet::arrow::ProjectionMask;
use parquet::arrow::arrow_reader::{ArrowReaderMetadata, ParquetRecordBatchReader, RowGroups, RowSelection};
use parquet::arrow::parquet_to_arrow_field_levels;
use parquet::basic::Compression;
use parquet::column::page::{Page, PageIterator, PageMetadata, PageReader};
use parquet::errors::{ParquetError, Result};
use parquet::file::metadata::{ParquetMetaData, RowGroupMetaData};
use parquet::file::serialized_reader::SerializedPageReader;

/// A decompressed page may claim at most this many bytes (a damaged frame header must not make
/// the reader allocate gigabytes).
const MAX_PAGE_BYTES: u64 = 1 << 30;

/// Decompression contexts not in use, shared by every reader of the process.
static CONTEXTS: Mutex<Vec<zstd::bulk::Decompressor<'static>>> = Mutex::new(Vec::new());

/// Decompresses one zstd frame (a page's bytes after `keep` uncompressed ones, which are copied
/// first: the levels of a v2 page) with a pooled context.
fn decompress(buf: &Bytes, keep: usize) -> Result<Bytes> {
    let (head, frame) = buf
        .split_at_checked(keep)
        .ok_or_else(|| ParquetError::General(format!("page of {} bytes has {keep} bytes of levels", buf.len())))?;
    let size = match zstd::zstd_safe::get_frame_content_size(frame) {
        Ok(Some(n)) if n <= MAX_PAGE_BYTES => n as usize,
        Ok(Some(n)) => return Err(ParquetError::General(format!("zstd page claims {n} bytes decompressed"))),
        // A frame without its size: decoded by the streaming decoder instead.
        Ok(None) => {
            let mut out = head.to_vec();
            out.extend(zstd::stream::decode_all(frame).map_err(|e| ParquetError::General(format!("zstd page: {e}")))?);
            return Ok(out.into());
        }
        Err(e) => return Err(ParquetError::General(format!("zstd page header: {e:?}"))),
    };
    let taken = CONTEXTS.lock().map(|mut pool| pool.pop()).unwrap_or(None);
    let mut ctx = match taken {
        Some(c) => c,
        None => zstd::bulk::Decompressor::new().map_err(|e| ParquetError::General(format!("zstd context: {e}")))?,
    };
    let mut out = Vec::with_capacity(keep + size);
    out.extend_from_slice(head);
    let mut cursor = std::io::Cursor::new(&mut out);
    cursor.set_position(keep as u64);
    let result = ctx.decompress_to_buffer(frame, &mut cursor);
    if let Ok(mut pool) = CONTEXTS.lock() {
        pool.push(ctx);
    }
    let n = result.map_err(|e| ParquetError::General(format!("zstd page: {e}")))?;
    if n != size {
        return Err(ParquetError::General(format!("zstd page decompressed to {n} bytes, its frame says {size}")));
    }
    Ok(out.into())
}

/// A page reader over a zstd column chunk opened as uncompressed: each page decompressed here.
struct Decompressing<R: PageReader> {
    inner: R,
}

impl<R: PageReader> Iterator for Decompressing<R> {
    type Item = Result<Page>;

    fn next(&mut self) -> Option<Self::Item> {
        self.get_next_page().transpose()
    }
}

impl<R: PageReader> PageReader for Decompressing<R> {
    fn get_next_page(&mut self) -> Result<Option<Page>> {
        let Some(mut page) = self.inner.get_next_page()? else {
            return Ok(None);
        };
        match &mut page {
            Page::DataPage { buf, .. } | Page::DictionaryPage { buf, .. } => *buf = decompress(buf, 0)?,
            Page::DataPageV2 { buf, def_levels_byte_len, rep_levels_byte_len, is_compressed, .. } => {
                if *is_compressed {
                    let keep = *def_levels_byte_len as usize + *rep_levels_byte_len as usize;
                    *buf = decompress(buf, keep)?;
                    *is_compressed = false;
                }
            }
        }
        Ok(Some(page))
    }

    fn peek_next_page(&mut self) -> Result<Option<PageMetadata>> {
        self.inner.peek_next_page()
    }

    fn skip_next_page(&mut self) -> Result<()> {
        self.inner.skip_next_page()
    }

    fn at_record_boundary(&mut self) -> Result<bool> {
        self.inner.at_record_boundary()
    }
}

/// The row groups `groups` of one open file, as arrow-rs's array readers ask for them.
struct Groups {
    file: Arc<File>,
    meta: Arc<ParquetMetaData>,
    groups: Vec<usize>,
}

/// The pages of one column across the chosen row groups.
struct ColumnPages {
    file: Arc<File>,
    meta: Arc<ParquetMetaData>,
    column: usize,
    groups: std::vec::IntoIter<usize>,
}

impl ColumnPages {
    fn open(&self, g: usize) -> Result<Box<dyn PageReader>> {
        let rg = self.meta.row_group(g);
        let chunk = rg.columns().get(self.column).ok_or_else(|| {
            ParquetError::General(format!("row group {g} has no column {} of the schema", self.column))
        })?;
        let locations = self
            .meta
            .offset_index()
            .and_then(|ix| ix.get(g))
            .and_then(|cols| cols.get(self.column))
            .map(|c| c.page_locations.clone());
        let rows = usize::try_from(rg.num_rows()).map_err(|_| ParquetError::General("negative row count".into()))?;
        Ok(match chunk.compression() {
            Compression::ZSTD(_) => {
                let plain = chunk.clone().into_builder().set_compression(Compression::UNCOMPRESSED).build()?;
                Box::new(Decompressing {
                    inner: SerializedPageReader::new(self.file.clone(), &plain, rows, locations)?,
                })
            }
            _ => Box::new(SerializedPageReader::new(self.file.clone(), chunk, rows, locations)?),
        })
    }
}

impl Iterator for ColumnPages {
    type Item = Result<Box<dyn PageReader>>;

    fn next(&mut self) -> Option<Self::Item> {
        let g = self.groups.next()?;
        Some(self.open(g))
    }
}

impl PageIterator for ColumnPages {}

impl RowGroups for Groups {
    fn num_rows(&self) -> usize {
        self.groups.iter().map(|&g| self.meta.row_group(g).num_rows().max(0) as usize).sum()
    }

    fn column_chunks(&self, i: usize) -> Result<Box<dyn PageIterator>> {
        Ok(Box::new(ColumnPages {
            file: self.file.clone(),
            meta: self.meta.clone(),
            column: i,
            groups: self.groups.clone().into_iter(),
        }))
    }

    fn row_groups(&self) -> Box<dyn Iterator<Item = &RowGroupMetaData> + '_> {
        Box::new(self.groups.iter().map(|&g| self.meta.row_group(g)))
    }

    fn metadata(&self) -> &ParquetMetaData {
        &self.meta
    }
}

/// A reader of `file` (whose footer is `meta`): the columns of `projection` (every column when
/// None), the row groups `groups` (all when None) and within them the rows `selection`, in
/// batches of at most `batch_size` rows.
pub(crate) fn reader(
    file: File,
    meta: &ArrowReaderMetadata,
    projection: Option<ProjectionMask>,
    groups: Option<Vec<usize>>,
    selection: Option<RowSelection>,
    batch_size: usize,
) -> Result<ParquetRecordBatchReader> {
    let parquet = meta.metadata().clone();
    let mask = projection.unwrap_or_else(ProjectionMask::all);
    let levels =
        parquet_to_arrow_field_levels(parquet.file_metadata().schema_descr(), mask, Some(meta.schema().fields()))?;
    let groups = groups.unwrap_or_else(|| (0..parquet.num_row_groups()).collect());
    let groups = Groups { file: Arc::new(file), meta: parquet, groups };
    let rows = groups.num_rows().max(1);
    ParquetRecordBatchReader::try_new_with_row_groups(&levels, &groups, batch_size.min(rows), selection)
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::array::{ArrayRef, Float32Array, RecordBatch, StringArray, UInt32Array};
    use parquet::arrow::ArrowWriter;
    use parquet::arrow::arrow_reader::{ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelector};
    use parquet::basic::ZstdLevel;
    use parquet::file::metadata::PageIndexPolicy;
    use parquet::file::properties::{WriterProperties, WriterVersion};
    use parquet::schema::types::ColumnPath;

    /// A file of zstd (v1 or v2 pages, plain and dictionary) and uncompressed columns, read
    /// through the pool with page-skipping selections, equals arrow-rs's own reader.
    #[test]
    fn pooled_pages_read_as_arrow_rs_reads_them() {
        let dir = tempfile::tempdir().unwrap();
        let n = 50_000u32;
        let ids: ArrayRef = Arc::new(UInt32Array::from_iter_values(0..n));
        let x: ArrayRef = Arc::new(Float32Array::from_iter((0..n).map(|i| (i % 7 != 0).then_some(i as f32 * 0.5))));
        let names: ArrayRef = Arc::new(StringArray::from_iter_values((0..n).map(|i| format!("kind{}", i % 5))));
        let batch = RecordBatch::try_from_iter([("id", ids), ("x", x), ("name", names)]).unwrap();
        for version in [WriterVersion::PARQUET_1_0, WriterVersion::PARQUET_2_0] {
            let path = dir.path().join(format!("{version:?}.parquet"));
            let props = WriterProperties::builder()
                .set_writer_version(version)
                .set_compression(Compression::ZSTD(ZstdLevel::try_new(3).unwrap()))
                .set_column_compression(ColumnPath::from("x"), Compression::UNCOMPRESSED)
                .set_data_page_row_count_limit(1000)
                .set_write_batch_size(1000)
                .set_max_row_group_row_count(Some(20_000))
                .build();
            let mut w = ArrowWriter::try_new(File::create(&path).unwrap(), batch.schema(), Some(props)).unwrap();
            w.write(&batch).unwrap();
            w.close().unwrap();
            let options = ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Optional);
            let meta = ArrowReaderMetadata::load(&File::open(&path).unwrap(), options).unwrap();
            let selection = RowSelection::from(vec![
                RowSelector::skip(3_000),
                RowSelector::select(17),
                RowSelector::skip(20_000),
                RowSelector::select(2_500),
                RowSelector::skip(100),
            ]);
            let ours: Vec<RecordBatch> =
                reader(File::open(&path).unwrap(), &meta, None, Some(vec![0, 1, 2]), Some(selection.clone()), 777)
                    .unwrap()
                    .collect::<std::result::Result<_, _>>()
                    .unwrap();
            let theirs: Vec<RecordBatch> =
                ParquetRecordBatchReaderBuilder::new_with_metadata(File::open(&path).unwrap(), meta.clone())
                    .with_row_groups(vec![0, 1, 2])
                    .with_row_selection(selection)
                    .with_batch_size(777)
                    .build()
                    .unwrap()
                    .collect::<std::result::Result<_, _>>()
                    .unwrap();
            let cat = |b: &[RecordBatch]| arrow::compute::concat_batches(&batch.schema(), b).unwrap();
            assert_eq!(cat(&ours).num_rows(), 2_517, "{version:?}");
            assert_eq!(cat(&ours), cat(&theirs), "{version:?}");
            // A projection of one zstd column, every row.
            let mask = ProjectionMask::roots(meta.metadata().file_metadata().schema_descr(), [2]);
            let all: usize = reader(File::open(&path).unwrap(), &meta, Some(mask), None, None, 4096)
                .unwrap()
                .map(|b| b.unwrap().num_rows())
                .sum();
            assert_eq!(all, n as usize);
        }
    }

    /// Two threads reading a few trees split the columns where the bytes balance, not at the
    /// middle column.
    #[test]
    fn columns_split_where_their_bytes_balance() {
        let dir = tempfile::tempdir().unwrap();
        let n = 20_000u32;
        let noise = |seed: u32| -> ArrayRef {
            Arc::new(UInt32Array::from_iter_values((0..n).map(move |i| (i ^ seed).wrapping_mul(2_654_435_761))))
        };
        let small = || -> ArrayRef { Arc::new(UInt32Array::from_iter_values((0..n).map(|i| i / 1000))) };
        let split = |cols: Vec<(&str, ArrayRef)>| {
            let batch = RecordBatch::try_from_iter(cols).unwrap();
            let path = dir.path().join("split.parquet");
            let mut w = ArrowWriter::try_new(File::create(&path).unwrap(), batch.schema(), None).unwrap();
            w.write(&batch).unwrap();
            w.close().unwrap();
            let meta = ArrowReaderMetadata::load(&File::open(&path).unwrap(), ArrowReaderOptions::new()).unwrap();
            super::super::balanced_split(&meta)
        };
        assert_eq!(split(vec![("a", noise(1)), ("b", noise(2)), ("c", small()), ("d", small())]), 1);
        assert_eq!(split(vec![("a", small()), ("b", small()), ("c", small()), ("d", noise(3))]), 3);
        assert_eq!(split(vec![("a", small()), ("b", small())]), 1);
        assert_eq!(split(vec![("a", noise(4))]), 0, "one column: nothing to split");
    }

    #[test]
    fn damaged_frames_are_errors() {
        let good = zstd::bulk::compress(&[7u8; 4096], 3).unwrap();
        assert_eq!(decompress(&Bytes::from(good.clone()), 0).unwrap().len(), 4096);
        let mut bad = good.clone();
        let last = bad.len() - 3;
        bad[last] ^= 0xff;
        bad.truncate(bad.len() - 1);
        assert!(decompress(&Bytes::from(bad), 0).is_err());
        assert!(decompress(&Bytes::from(vec![1u8, 2, 3]), 0).is_err());
        assert!(decompress(&Bytes::from(good), 100_000).is_err(), "more levels than bytes");
    }
}
