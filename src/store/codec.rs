//! The table format of cache entries: one Arrow batch per Parquet file (snappy), written
//! deterministically so equal tables give equal bytes (and equal digests).

use std::sync::Arc;

use arrow::{compute::concat_batches, error::ArrowError, record_batch::RecordBatch};
use parquet::{
    arrow::{arrow_reader::ParquetRecordBatchReaderBuilder, ArrowWriter},
    basic::Compression,
    errors::ParquetError,
    file::properties::WriterProperties,
};

/// Parquet or Arrow refused a table.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    #[error(transparent)]
    Parquet(#[from] ParquetError),
    #[error(transparent)]
    Arrow(#[from] ArrowError),
}

/// Encodes one table as Parquet (snappy), deterministically.
pub fn write_parquet(batch: &RecordBatch) -> Result<Vec<u8>, CodecError> {
    let mut props = WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .set_created_by(format!("panoptic-pipe {}", env!("CARGO_PKG_VERSION")));
    // Float columns (weights, positions, depths) barely repeat: a dictionary only costs time
    // (interning a million weights took ~0.4 s per train entry) and space.
    let parquet_schema = parquet::arrow::ArrowSchemaConverter::new().convert(&batch.schema())?;
    for col in parquet_schema.columns() {
        if matches!(
            col.physical_type(),
            parquet::basic::Type::FLOAT | parquet::basic::Type::DOUBLE
        ) {
            props = props.set_column_dictionary_enabled(col.path().clone(), false);
        }
    }
    let props = props.build();
    let mut buf = Vec::new();
    let mut w = ArrowWriter::try_new(&mut buf, batch.schema(), Some(props))?;
    w.write(batch)?;
    w.close()?;
    Ok(buf)
}

/// Decodes a Parquet file into one batch.
pub fn read_parquet(bytes: Vec<u8>) -> Result<RecordBatch, CodecError> {
    let builder = ParquetRecordBatchReaderBuilder::try_new(bytes::Bytes::from(bytes))?;
    let schema = Arc::clone(builder.schema());
    let reader = builder.with_batch_size(1 << 16).build()?;
    let batches = reader.collect::<Result<Vec<_>, _>>()?;
    Ok(concat_batches(&schema, &batches)?)
}
