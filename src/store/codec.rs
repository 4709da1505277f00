//! The table format of cache entries: Parquet (snappy), written deterministically so equal
//! tables give equal bytes (and equal digests), straight to the entry's file through a hashing
//! writer (a table is never encoded into memory first), in row groups a reader can take one at
//! a time: a streamed table one per batch the stage wrote (one image), a table written whole in
//! groups of at most [`ROW_GROUP_BYTES`], or one row each where rows are images.

use std::{
    fs::File,
    io::{BufWriter, Write},
    ops::Range,
    path::{Path, PathBuf},
    sync::Arc,
};

use arrow::{
    array::{Array, UInt32Array},
    compute::{concat_batches, take_record_batch},
    datatypes::SchemaRef,
    error::ArrowError,
    record_batch::RecordBatch,
};
use parquet::{
    arrow::{
        arrow_reader::{ArrowReaderMetadata, ParquetRecordBatchReaderBuilder},
        arrow_writer::{compute_leaves, ArrowRowGroupWriterFactory},
        ArrowWriter, ProjectionMask,
    },
    basic::Compression,
    errors::ParquetError,
    file::{properties::WriterProperties, writer::SerializedFileWriter},
};
use stages::stream::RowSource;

/// Parquet or Arrow refused a table.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    #[error(transparent)]
    Parquet(#[from] ParquetError),
    #[error(transparent)]
    Arrow(#[from] ArrowError),
}

/// A table written whole is split into row groups of about this many bytes of values, so a
/// reader of a few rows (one image) decodes little more than those rows.
pub const ROW_GROUP_BYTES: usize = 64 << 20;

/// Rows of at least this many bytes on average (images, label maps, depth maps) get a row group
/// each: a reader of one image then decodes that image alone.
pub const ROW_ALONE_BYTES: usize = 256 << 10;

/// Rows per row group of Parquet's own default (kept for tables of small rows).
const MAX_GROUP_ROWS: usize = 1 << 20;

/// The writer settings of every table: snappy, no dictionary for float columns.
fn properties(schema: &SchemaRef) -> Result<WriterProperties, CodecError> {
    let mut props = WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_max_row_group_row_count(Some(MAX_GROUP_ROWS))
        .set_created_by(format!("panoptic-pipe {}", env!("CARGO_PKG_VERSION")));
    // Float columns (weights, positions, depths) barely repeat: a dictionary only costs time
    // (interning a million weights took ~0.4 s per train entry) and space.
    let parquet_schema = parquet::arrow::ArrowSchemaConverter::new().convert(schema)?;
    for col in parquet_schema.columns() {
        if matches!(
            col.physical_type(),
            parquet::basic::Type::FLOAT | parquet::basic::Type::DOUBLE
        ) {
            props = props.set_column_dictionary_enabled(col.path().clone(), false);
        }
    }
    Ok(props.build())
}

/// Rows per row group for `batch`: about [`ROW_GROUP_BYTES`] of values each, or one where rows
/// are large ([`ROW_ALONE_BYTES`]). Computed from the values, not from buffer capacities, so
/// equal tables are split equally.
fn rows_per_group(batch: &RecordBatch) -> usize {
    let bytes: usize = batch
        .columns()
        .iter()
        .map(|c| c.to_data().get_slice_memory_size().unwrap_or(0))
        .sum();
    let n = batch.num_rows().max(1);
    if bytes / n >= ROW_ALONE_BYTES {
        return 1;
    }
    if bytes <= ROW_GROUP_BYTES {
        return n;
    }
    ((ROW_GROUP_BYTES as u128 * n as u128 / bytes as u128) as usize).clamp(1, n)
}

/// A Parquet writer of one table into `out`, a row group per [`TableEncoder::write`] call.
/// It encodes as parquet's `ArrowWriter` does, a row group at a time, through the writer's
/// lower level, so that a row group can also be copied from another file as it is stored
/// ([`TableEncoder::splice`]).
pub struct TableEncoder<W: Write + Send> {
    pub(super) writer: SerializedFileWriter<W>,
    pub(super) factory: ArrowRowGroupWriterFactory,
    pub(super) schema: SchemaRef,
}

impl<W: Write + Send> TableEncoder<W> {
    pub fn new(out: W, schema: SchemaRef) -> Result<Self, CodecError> {
        let props = properties(&schema)?;
        let (writer, factory) =
            ArrowWriter::try_new(out, schema.clone(), Some(props))?.into_serialized_writer()?;
        Ok(Self {
            writer,
            factory,
            schema,
        })
    }

    /// Appends `batch` as one row group (or more, for batches over a million rows).
    pub fn write(&mut self, batch: &RecordBatch) -> Result<(), CodecError> {
        let mut start = 0;
        while start < batch.num_rows() {
            let len = MAX_GROUP_ROWS.min(batch.num_rows() - start);
            self.write_group(&batch.slice(start, len))?;
            start += len;
        }
        Ok(())
    }

    /// One row group, encoded as `ArrowWriter` encodes it.
    fn write_group(&mut self, batch: &RecordBatch) -> Result<(), CodecError> {
        let group = self.writer.flushed_row_groups().len();
        let mut writers = self.factory.create_column_writers(group)?;
        let mut next = writers.iter_mut();
        for (field, column) in self.schema.fields().iter().zip(batch.columns()) {
            for leaf in compute_leaves(field, column)? {
                next.next()
                    .ok_or_else(|| ParquetError::General("more leaves than columns".into()))?
                    .write(&leaf)?;
            }
        }
        let mut out = self.writer.next_row_group()?;
        for w in writers {
            w.close()?.append_to_row_group(&mut out)?;
        }
        out.close()?;
        Ok(())
    }

    /// Appends `batch` in row groups of [`rows_per_group`] rows.
    pub fn write_whole(&mut self, batch: &RecordBatch) -> Result<(), CodecError> {
        let step = rows_per_group(batch);
        if step >= batch.num_rows() {
            return self.write(batch);
        }
        let mut start = 0;
        while start < batch.num_rows() {
            let len = step.min(batch.num_rows() - start);
            // A copy of the rows, not a slice: the Parquet writer walks a sliced list column's
            // whole value buffer, so writing a table of 256 images an image at a time took ten
            // times as long as the table's encoding.
            let rows = UInt32Array::from_iter_values(start as u32..(start + len) as u32);
            self.write(&take_record_batch(batch, &rows)?)?;
            start += len;
        }
        Ok(())
    }

    /// Writes the footer; returns the output.
    pub fn finish(self) -> Result<W, CodecError> {
        Ok(self.writer.into_inner()?)
    }
}

/// Encodes one table as Parquet, deterministically (tests, small tables).
pub fn write_parquet(batch: &RecordBatch) -> Result<Vec<u8>, CodecError> {
    let mut enc = TableEncoder::new(Vec::new(), batch.schema())?;
    enc.write_whole(batch)?;
    enc.finish()
}

/// Decodes a Parquet file into one batch.
pub fn read_parquet(bytes: Vec<u8>) -> Result<RecordBatch, CodecError> {
    let builder = ParquetRecordBatchReaderBuilder::try_new(bytes::Bytes::from(bytes))?;
    let schema = Arc::clone(builder.schema());
    let reader = builder.with_batch_size(1 << 16).build()?;
    let batches = reader.collect::<Result<Vec<_>, _>>()?;
    Ok(concat_batches(&schema, &batches)?)
}

/// A file writer that hashes (blake3) and counts what it writes.
pub struct HashingFile {
    file: BufWriter<File>,
    hasher: blake3::Hasher,
    size: u64,
}

impl HashingFile {
    pub fn create(path: &Path) -> std::io::Result<Self> {
        Ok(Self {
            file: BufWriter::with_capacity(1 << 20, File::create(path)?),
            hasher: blake3::Hasher::new(),
            size: 0,
        })
    }

    /// Flushes and fsyncs; returns (size, blake3 hex).
    pub fn finish(self) -> std::io::Result<(u64, String)> {
        let file = self.file.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        Ok((self.size, self.hasher.finalize().to_hex().to_string()))
    }
}

impl Write for HashingFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.file.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.size += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()
    }
}

/// A table stored in the cache, read a range of rows (and a set of columns) at a time: only
/// the row groups that hold the rows are decoded.
pub struct StoredTable {
    path: PathBuf,
    pub(super) file: Arc<File>,
    pub(super) len: u64,
    pub(super) meta: ArrowReaderMetadata,
    /// First row of each row group, and the row count at the end.
    pub(super) starts: Vec<usize>,
    /// The file's metadata with its page indexes, once a row group is copied from it.
    pub(super) indexed: std::sync::OnceLock<Option<Arc<parquet::file::metadata::ParquetMetaData>>>,
}

impl StoredTable {
    pub fn open(path: &Path) -> Result<Self, CodecError> {
        let file = File::open(path).map_err(ParquetError::from)?;
        let len = file.metadata().map_err(ParquetError::from)?.len();
        let meta = ArrowReaderMetadata::load(&file, Default::default())?;
        let mut starts = vec![0usize];
        for g in meta.metadata().row_groups() {
            starts.push(starts.last().unwrap() + g.num_rows() as usize);
        }
        Ok(Self {
            path: path.to_path_buf(),
            file: Arc::new(file),
            len,
            meta,
            starts,
            indexed: Default::default(),
        })
    }

    fn read_rows(
        &self,
        range: Range<usize>,
        columns: Option<&[&str]>,
    ) -> Result<RecordBatch, CodecError> {
        let schema = self.meta.schema().clone();
        let groups: Vec<usize> = (0..self.starts.len() - 1)
            .filter(|&g| self.starts[g] < range.end && self.starts[g + 1] > range.start)
            .collect();
        let mut builder = ParquetRecordBatchReaderBuilder::new_with_metadata(
            Positional(self.file.clone(), self.len),
            self.meta.clone(),
        )
        .with_row_groups(groups.clone())
        .with_batch_size(1 << 16);
        let out_schema = match columns {
            Some(cols) => {
                let idx = cols
                    .iter()
                    .map(|c| schema.index_of(c))
                    .collect::<Result<Vec<_>, _>>()?;
                let mask = ProjectionMask::roots(builder.parquet_schema(), idx.iter().copied());
                builder = builder.with_projection(mask);
                // The reader returns the columns in file order; give them in the order asked.
                Arc::new(schema.project(&idx)?)
            }
            None => schema,
        };
        let batches = builder.build()?.collect::<Result<Vec<_>, _>>()?;
        let read_schema = batches
            .first()
            .map_or_else(|| out_schema.clone(), |b| b.schema());
        let all = concat_batches(&read_schema, &batches)?;
        let first = groups.first().map_or(range.start, |&g| self.starts[g]);
        let part = all.slice(range.start - first, range.len());
        // Projection keeps file order: reorder to the order asked.
        let cols = out_schema
            .fields()
            .iter()
            .map(|f| {
                part.schema()
                    .index_of(f.name())
                    .map(|i| part.column(i).clone())
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(RecordBatch::try_new(out_schema, cols)?)
    }
}

/// A file read by position (`pread`), never by seeking: parquet's reader for `File` seeks a
/// cloned handle, and clones share one offset, so readers of one table on several threads
/// would read each other's bytes.
/// The file and its length, taken when the table was opened.
pub(super) struct Positional(pub(super) Arc<File>, pub(super) u64);

impl parquet::file::reader::Length for Positional {
    fn len(&self) -> u64 {
        self.1
    }
}

/// A [`std::io::Read`] at a position of a [`Positional`] file.
pub(super) struct PositionalRead {
    file: Arc<File>,
    at: u64,
}

impl std::io::Read for PositionalRead {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        use std::os::unix::fs::FileExt;
        let n = self.file.read_at(buf, self.at)?;
        self.at += n as u64;
        Ok(n)
    }
}

impl parquet::file::reader::ChunkReader for Positional {
    type T = std::io::BufReader<PositionalRead>;

    fn get_read(&self, start: u64) -> parquet::errors::Result<Self::T> {
        Ok(std::io::BufReader::new(PositionalRead {
            file: self.0.clone(),
            at: start,
        }))
    }

    fn get_bytes(&self, start: u64, length: usize) -> parquet::errors::Result<bytes::Bytes> {
        use std::os::unix::fs::FileExt;
        let mut buf = vec![0u8; length];
        self.0.read_exact_at(&mut buf, start)?;
        Ok(buf.into())
    }
}

impl RowSource for StoredTable {
    fn schema(&self) -> SchemaRef {
        self.meta.schema().clone()
    }

    fn num_rows(&self) -> usize {
        *self.starts.last().unwrap()
    }

    fn read(&self, range: Range<usize>, columns: Option<&[&str]>) -> stages::Result<RecordBatch> {
        self.read_rows(range.clone(), columns).map_err(|e| {
            stages::StageError::Input(format!(
                "reading rows {range:?} of {}: {e}",
                self.path.display()
            ))
        })
    }

    fn as_any(&self) -> Option<&dyn std::any::Any> {
        Some(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::{
        array::{BinaryArray, UInt32Array},
        datatypes::{DataType, Field, Schema},
    };

    fn images(n: u32, bytes: usize) -> RecordBatch {
        let schema = Arc::new(Schema::new(vec![
            Field::new("frame", DataType::UInt32, false),
            Field::new("rgb", DataType::Binary, false),
        ]));
        let rgb: Vec<Vec<u8>> = (0..n).map(|i| vec![i as u8; bytes]).collect();
        RecordBatch::try_new(
            schema,
            vec![
                Arc::new(UInt32Array::from_iter_values(0..n)),
                Arc::new(BinaryArray::from_iter_values(rgb)),
            ],
        )
        .unwrap()
    }

    #[test]
    fn large_tables_are_split_into_row_groups_and_read_back_in_parts() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.parquet");
        // 40 rows of 4 MiB (and a little): images, one row group each.
        let b = images(40, 4 << 20);
        assert_eq!(rows_per_group(&b), 1);
        let mut enc = TableEncoder::new(HashingFile::create(&path).unwrap(), b.schema()).unwrap();
        enc.write_whole(&b).unwrap();
        let (size, hash) = enc.finish().unwrap().finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(size, bytes.len() as u64);
        assert_eq!(hash, blake3::hash(&bytes).to_hex().to_string());
        assert_eq!(
            write_parquet(&b).unwrap(),
            bytes,
            "one encoding, whatever the output"
        );
        let t = StoredTable::open(&path).unwrap();
        assert_eq!(t.num_rows(), 40);
        assert_eq!(t.starts, (0..=40).collect::<Vec<_>>());
        // Rows across a group boundary, columns in the order asked.
        let part = t.read(14..18, Some(&["rgb", "frame"])).unwrap();
        assert_eq!(part.num_rows(), 4);
        assert_eq!(part.schema().field(0).name(), "rgb");
        let frames = part
            .column(1)
            .as_any()
            .downcast_ref::<UInt32Array>()
            .unwrap();
        assert_eq!(frames.values().to_vec(), vec![14, 15, 16, 17]);
        assert_eq!(t.read(0..40, None).unwrap(), b);
        assert_eq!(t.read(40..40, None).unwrap().num_rows(), 0);
    }

    /// Rows read on several threads at once are the rows read one at a time (a reader that
    /// seeks a shared handle reads another thread's bytes: "Required field type_ is missing").
    #[test]
    fn rows_read_on_many_threads_at_once_are_the_same_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.parquet");
        let b = images(24, 4 << 20);
        let mut enc = TableEncoder::new(HashingFile::create(&path).unwrap(), b.schema()).unwrap();
        enc.write_whole(&b).unwrap();
        enc.finish().unwrap().finish().unwrap();
        let t = StoredTable::open(&path).unwrap();
        std::thread::scope(|s| {
            for k in 0..6 {
                let t = &t;
                let b = &b;
                s.spawn(move || {
                    for round in 0..8 {
                        let r = (k * 7 + round * 5) % 24;
                        assert_eq!(t.read(r..r + 1, None).unwrap(), b.slice(r, 1), "row {r}");
                    }
                });
            }
        });
    }

    #[test]
    fn tables_of_smaller_rows_are_split_by_bytes() {
        // 400 rows of 200 KiB: 81_923_204 bytes of values (frames, offsets, bytes), so groups
        // of 64 MiB * 400 / 81_923_204 = 327.7 rows.
        let b = images(400, 200 << 10);
        assert_eq!(rows_per_group(&b), 327);
        let b = images(400, ROW_ALONE_BYTES);
        assert_eq!(rows_per_group(&b), 1);
    }

    #[test]
    fn small_tables_stay_one_row_group() {
        let b = images(3, 10);
        assert_eq!(rows_per_group(&b), 3);
        let bytes = write_parquet(&b).unwrap();
        let meta = parquet::file::serialized_reader::SerializedFileReader::new(bytes::Bytes::from(
            bytes.clone(),
        ))
        .map(|r| parquet::file::reader::FileReader::metadata(&r).num_row_groups())
        .unwrap();
        assert_eq!(meta, 1);
        assert_eq!(read_parquet(bytes).unwrap(), b);
    }

    /// The encoder's own row groups are the bytes parquet's `ArrowWriter` writes (a row group
    /// per batch): entries written before it took the lower level stay valid.
    #[test]
    fn the_encoder_writes_the_bytes_arrow_writer_writes() {
        use arrow::array::{Float32Array, ListArray};
        use arrow::datatypes::{Float32Type, UInt8Type};
        let lists =
            |n: usize, seed: u32| {
                ListArray::from_iter_primitive::<UInt8Type, _, _>((0..n).map(|i| {
                    Some((0..(i + seed as usize) % 5).map(move |j| Some((i * 7 + j) as u8)))
                }))
            };
        let floats = |n: usize, seed: u32| {
            ListArray::from_iter_primitive::<Float32Type, _, _>((0..n).map(|i| {
                Some((0..i % 3).map(move |j| Some(i as f32 * 0.5 - j as f32 + seed as f32)))
            }))
        };
        let schema = Arc::new(Schema::new(vec![
            Field::new("n", DataType::UInt32, false),
            Field::new("x", DataType::Float32, false),
            Field::new("l", lists(1, 0).data_type().clone(), false),
            Field::new("f", floats(1, 0).data_type().clone(), false),
            Field::new("b", DataType::Binary, false),
        ]));
        let batch = |n: usize, seed: u32| {
            RecordBatch::try_new(
                schema.clone(),
                vec![
                    Arc::new(UInt32Array::from_iter_values(
                        (0..n as u32).map(|i| i * seed),
                    )),
                    Arc::new(Float32Array::from_iter_values(
                        (0..n).map(|i| i as f32 / 3.0),
                    )),
                    Arc::new(lists(n, seed)),
                    Arc::new(floats(n, seed)),
                    Arc::new(BinaryArray::from_iter_values(
                        (0..n).map(|i| vec![i as u8; i % 9]),
                    )),
                ],
            )
            .unwrap()
        };
        let batches = [batch(1000, 1), batch(1, 2), batch(0, 3), batch(5000, 4)];
        let mut ours = TableEncoder::new(Vec::new(), schema.clone()).unwrap();
        let mut theirs = ArrowWriter::try_new(
            Vec::new(),
            schema.clone(),
            Some(properties(&schema).unwrap()),
        )
        .unwrap();
        for b in &batches {
            ours.write(b).unwrap();
            theirs.write(b).unwrap();
            theirs.flush().unwrap();
        }
        assert!(ours.finish().unwrap() == theirs.into_inner().unwrap());
    }
}
