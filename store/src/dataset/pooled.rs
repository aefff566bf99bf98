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
//!
//! A repeated column's data pages are checked to hold the repetition levels their headers count
//! before arrow-rs decodes them: arrow-rs's record skipping (a row selection) loops forever on a
//! page whose levels end early (its record reading has that check, its skipping does not).

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

/// A page reader as arrow-rs's array readers get it: over a zstd column chunk opened as
/// uncompressed, each page decompressed here (`zstd`); in a repeated column (`rep_bits`, the width
/// of its repetition levels, 0 when not repeated), each data page's levels counted first.
struct Pages<R: PageReader> {
    inner: R,
    zstd: bool,
    rep_bits: u8,
}

impl<R: PageReader> Iterator for Pages<R> {
    type Item = Result<Page>;

    fn next(&mut self) -> Option<Self::Item> {
        self.get_next_page().transpose()
    }
}

impl<R: PageReader> PageReader for Pages<R> {
    fn get_next_page(&mut self) -> Result<Option<Page>> {
        let Some(mut page) = self.inner.get_next_page()? else {
            return Ok(None);
        };
        if self.zstd {
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
        }
        if self.rep_bits > 0 {
            check_repetition_levels(&page, self.rep_bits)?;
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

/// Fails unless data page `page` of a column whose repetition levels are `bits` wide holds as many
/// levels as its header counts values (its other pages pass).
fn check_repetition_levels(page: &Page, bits: u8) -> Result<()> {
    let (levels, num_values) = match page {
        Page::DataPage { buf, num_values, rep_level_encoding: parquet::basic::Encoding::RLE, .. } => {
            // A v1 page's levels: their byte length (4 bytes, little-endian), then the levels.
            let len = buf.get(..4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
            let levels = len.and_then(|len| buf.get(4..4usize.checked_add(len)?));
            let levels = levels.ok_or_else(|| {
                ParquetError::General(format!("data page of {} bytes: its repetition levels overrun it", buf.len()))
            })?;
            (levels, *num_values)
        }
        Page::DataPageV2 { buf, num_values, rep_levels_byte_len, .. } => {
            let levels = buf.get(..*rep_levels_byte_len as usize).ok_or_else(|| {
                ParquetError::General(format!(
                    "data page of {} bytes: its {rep_levels_byte_len} bytes of repetition levels overrun it",
                    buf.len()
                ))
            })?;
            (levels, *num_values)
        }
        // Bit-packed v1 levels are read by their count (a short page fails there); dictionaries
        // hold no levels.
        _ => return Ok(()),
    };
    let held = hybrid_levels(levels, bits, num_values as usize);
    if held < num_values as usize {
        return Err(ParquetError::General(format!("data page of {num_values} values holds {held} repetition levels")));
    }
    Ok(())
}

/// How many `bits`-wide values the RLE/bit-packed hybrid stream `data` gives arrow-rs's decoder
/// (counting stops once `enough` are found): a zero run header ends the stream, a cut bit-packed
/// run gives the whole values it holds, and a run's count is taken as arrow-rs takes it (32 bits).
fn hybrid_levels(data: &[u8], bits: u8, enough: usize) -> usize {
    let (mut at, mut held) = (0usize, 0usize);
    while held < enough && at < data.len() {
        // The run's header: an unsigned LEB128 of at most 10 bytes.
        let mut header = 0u64;
        let mut shift = 0;
        loop {
            let Some(&byte) = data.get(at) else {
                return held;
            };
            at += 1;
            header |= u64::from(byte & 0x7f) << shift;
            if byte & 0x80 == 0 {
                break;
            }
            shift += 7;
            if shift >= 64 {
                return held;
            }
        }
        if header == 0 {
            return held;
        }
        if header & 1 == 1 {
            // Bit-packed: header >> 1 groups of 8 values, `bits` bytes a group.
            let values = (header >> 1).wrapping_mul(8) as u32 as usize;
            let bytes = values / 8 * usize::from(bits);
            let left = data.len() - at;
            if bytes > left {
                return held + (left * 8 / usize::from(bits)).min(values);
            }
            held += values;
            at += bytes;
        } else {
            // A run of one value, stored in whole bytes.
            let width = usize::from(bits).div_ceil(8);
            if data.len() - at < width {
                return held;
            }
            held += (header >> 1) as u32 as usize;
            at += width;
        }
    }
    held
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
        let schema = self.meta.file_metadata().schema_descr();
        let max_rep = schema.columns().get(self.column).map_or(0, |c| c.max_rep_level());
        let rep_bits = (u16::BITS - (max_rep.max(0) as u16).leading_zeros()) as u8;
        let zstd = matches!(chunk.compression(), Compression::ZSTD(_));
        if !zstd && rep_bits == 0 {
            return Ok(Box::new(SerializedPageReader::new(self.file.clone(), chunk, rows, locations)?));
        }
        let inner = if zstd {
            let plain = chunk.clone().into_builder().set_compression(Compression::UNCOMPRESSED).build()?;
            SerializedPageReader::new(self.file.clone(), &plain, rows, locations)?
        } else {
            SerializedPageReader::new(self.file.clone(), chunk, rows, locations)?
        };
        Ok(Box::new(Pages { inner, zstd, rep_bits }))
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

    /// The level count of hand-made hybrid streams, as arrow-rs's decoder reads them.
    #[test]
    fn hybrid_streams_count_the_levels_a_decoder_gets() {
        // An RLE run of 5 ones (header 5 << 1), then a bit-packed group of 8 one-bit values.
        let stream = [10u8, 1, 3, 0b1011_0110];
        assert_eq!(hybrid_levels(&stream, 1, usize::MAX), 13);
        assert_eq!(hybrid_levels(&stream, 1, 3), 5, "counting stops once enough are found");
        // A zero header ends the stream (the levels after it are never read).
        assert_eq!(hybrid_levels(&[10, 1, 0, 10, 1], 1, usize::MAX), 5);
        // A bit-packed run cut short gives the whole values left: 2 groups of 3-bit values
        // claimed (6 bytes), 4 bytes there (10 values).
        assert_eq!(hybrid_levels(&[5, 0, 0, 0, 0], 3, usize::MAX), 10);
        // An RLE run without its value byte gives nothing; nor does an unfinished header.
        assert_eq!(hybrid_levels(&[10], 1, usize::MAX), 0);
        assert_eq!(hybrid_levels(&[0x80, 0x80], 1, usize::MAX), 0);
        // A multi-byte header: a run of 300 (600 = 0xd8 0x04), a 9-bit value in two bytes.
        assert_eq!(hybrid_levels(&[0xd8, 0x04, 0xff, 0x01], 9, usize::MAX), 300);
        // A run count past 32 bits is cut to 32 bits, as the decoder cuts it: (2^32 + 7) << 1.
        let mut huge = Vec::new();
        let mut v: u64 = ((1u64 << 32) + 7) << 1;
        while v >= 0x80 {
            huge.push((v as u8 & 0x7f) | 0x80);
            v >>= 7;
        }
        huge.extend([v as u8, 1]);
        assert_eq!(hybrid_levels(&huge, 1, usize::MAX), 7);
    }

    /// A repeated column whose page's repetition levels were damaged, read with a row selection
    /// that skips into that page: every read ends, and a page whose levels end early is an error
    /// (arrow-rs alone reads some such pages as if sound, and loops forever skipping others: the
    /// reader fuzz case in store/tests/dataset.rs).
    #[test]
    fn short_repetition_levels_fail_a_skipping_read() {
        use arrow::array::{Float32Builder, ListBuilder};
        let mut list = ListBuilder::new(Float32Builder::new());
        for i in 0..4000 {
            for k in 0..3 {
                list.values().append_value((i * 3 + k) as f32);
            }
            list.append(true);
        }
        let batch = RecordBatch::try_from_iter([("l", Arc::new(list.finish()) as ArrayRef)]).unwrap();
        let props = WriterProperties::builder()
            .set_writer_version(WriterVersion::PARQUET_1_0)
            .set_dictionary_enabled(false)
            .set_data_page_row_count_limit(1000)
            .set_write_batch_size(1000)
            .build();
        let mut bytes = Vec::new();
        let mut w = ArrowWriter::try_new(&mut bytes, batch.schema(), Some(props)).unwrap();
        w.write(&batch).unwrap();
        w.close().unwrap();
        let read = |bytes: &[u8]| -> Result<usize> {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("l.parquet");
            std::fs::write(&path, bytes).unwrap();
            let file = File::open(&path).unwrap();
            let meta = ArrowReaderMetadata::load(&file, ArrowReaderOptions::new()).unwrap();
            let selection = RowSelection::from(vec![RowSelector::skip(2500), RowSelector::select(10)]);
            let reader = reader(file, &meta, None, None, Some(selection), 1024)?;
            let mut rows = 0;
            for b in reader {
                rows += b.map_err(|e| ParquetError::General(e.to_string()))?.num_rows();
            }
            Ok(rows)
        };
        assert_eq!(read(&bytes).unwrap(), 10);
        // Zero 5 bytes at each place in the first 48 of the page the selection skips into (its
        // header and the length of its levels): each read ends, and some fail on the levels.
        let meta = ArrowReaderMetadata::load(
            &Bytes::from(bytes.clone()),
            ArrowReaderOptions::new().with_page_index_policy(PageIndexPolicy::Required),
        )
        .unwrap();
        let pages = meta.metadata().offset_index().unwrap()[0][0].page_locations();
        let page = pages.iter().rfind(|p| p.first_row_index <= 2500).unwrap();
        assert!(page.first_row_index > 0, "the selection skips whole pages and into this one");
        let mut short = 0;
        for at in page.offset as usize..page.offset as usize + 48 {
            let mut damaged = bytes.clone();
            damaged[at..at + 5].fill(0);
            let (tx, rx) = std::sync::mpsc::channel();
            // arrow-rs panics on some damaged headers (the store's `Guarded` makes those errors).
            std::thread::spawn(move || {
                let result = std::panic::catch_unwind(|| read(&damaged).map_err(|e| e.to_string()));
                tx.send(result.unwrap_or_else(|_| Err("panicked".into())))
            });
            let result = rx.recv_timeout(std::time::Duration::from_secs(30));
            let result = result.unwrap_or_else(|_| panic!("the read with 5 bytes zeroed at {at} did not end"));
            short += matches!(&result, Err(e) if e.contains("repetition levels")) as usize;
        }
        assert!(short > 0, "no damage was caught by the levels check");
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
