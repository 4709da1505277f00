//! An entry being written: a directory under `tmp/` that a stage's streamed output tables go
//! into while the stage runs (each batch one Parquet row group, hashed as it is written), and
//! that publishing completes with the stage's other tables and the manifest. Dropped
//! unpublished (the stage failed), it is removed.

use std::{
    collections::BTreeMap,
    fs,
    path::{Path, PathBuf},
    sync::{Arc, Mutex},
};

use arrow::record_batch::RecordBatch;
use serde::{Deserialize, Serialize};
use stages::{
    stream::{Sinks, TableSink},
    StageError,
};

use super::{
    codec::{HashingFile, StoredTable, TableEncoder},
    error::StoreError,
};
use crate::error::IoContext;

/// Size and hash of one file of an entry.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FileInfo {
    pub size: u64,
    pub blake3: String,
}

/// What the sinks of one entry report: each finished table's file, or that a table was opened
/// and not finished.
type Written = Arc<Mutex<BTreeMap<String, Option<FileInfo>>>>;

pub struct PendingEntry {
    dir: PathBuf,
    written: Written,
    published: bool,
}

impl PendingEntry {
    pub(super) fn create(dir: PathBuf) -> Result<Self, StoreError> {
        fs::create_dir_all(&dir).io_context(|| format!("creating {}", dir.display()))?;
        Ok(Self {
            dir,
            written: Arc::default(),
            published: false,
        })
    }

    pub(super) fn dir(&self) -> &Path {
        &self.dir
    }

    /// Names of the tables streamed so far.
    pub fn streamed(&self) -> Vec<String> {
        self.written.lock().unwrap().keys().cloned().collect()
    }

    /// Takes the table `table` unchanged from another entry's file `from` (whose size and
    /// blake3 are `info`): a hard link where the file system has them, else a copy. Entries are
    /// never written after they are published, so sharing the file is safe.
    pub fn keep(&self, table: &str, from: &Path, info: FileInfo) -> Result<(), StoreError> {
        let mut written = self.written.lock().unwrap();
        if written.contains_key(table) {
            return Err(StoreError::Corrupt(format!(
                "output table `{table}` was written and kept from the previous run"
            )));
        }
        let to = self.dir.join(format!("{table}.parquet"));
        fs::hard_link(from, &to)
            .or_else(|_| fs::copy(from, &to).map(|_| ()))
            .io_context(|| format!("taking {} into {}", from.display(), to.display()))?;
        written.insert(table.to_string(), Some(info));
        Ok(())
    }

    /// The streamed tables' files; an error if one was opened and never finished. From here on
    /// the caller owns the directory (it is not removed on drop).
    pub(super) fn finish(mut self) -> Result<BTreeMap<String, FileInfo>, StoreError> {
        self.published = true;
        let written = std::mem::take(&mut *self.written.lock().unwrap());
        written
            .into_iter()
            .map(|(name, info)| {
                info.map(|i| (name.clone(), i)).ok_or_else(|| {
                    StoreError::Corrupt(format!("streamed table `{name}` was never finished"))
                })
            })
            .collect()
    }
}

impl Drop for PendingEntry {
    fn drop(&mut self) {
        if !self.published {
            let _ = fs::remove_dir_all(&self.dir);
        }
    }
}

impl Sinks for PendingEntry {
    fn open(&self, table: &str) -> stages::Result<Box<dyn TableSink>> {
        let mut written = self.written.lock().unwrap();
        if written.contains_key(table) {
            return Err(StageError::Failed(format!(
                "output table `{table}` was opened twice"
            )));
        }
        let schema = stages::schema::get(table).ok_or_else(|| {
            StageError::Failed(format!("no schema file data_schema/{table}.json"))
        })?;
        let path = self.dir.join(format!("{table}.parquet"));
        let file = HashingFile::create(&path)
            .map_err(|e| StageError::Failed(format!("creating {}: {e}", path.display())))?;
        let encoder = TableEncoder::new(file, schema)
            .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))?;
        written.insert(table.to_string(), None);
        Ok(Box::new(ParquetSink {
            table: table.to_string(),
            path,
            encoder: Some(encoder),
            written: self.written.clone(),
        }))
    }
}

/// One streamed output table: each batch checked against the table's schema file and appended
/// as a row group.
struct ParquetSink {
    table: String,
    path: PathBuf,
    encoder: Option<TableEncoder<HashingFile>>,
    written: Written,
}

impl ParquetSink {
    fn failed(&self, what: impl std::fmt::Display) -> StageError {
        StageError::Failed(format!("writing {}: {what}", self.path.display()))
    }
}

impl TableSink for ParquetSink {
    fn write(&mut self, batch: &RecordBatch) -> stages::Result<()> {
        stages::schema::check(&self.table, &batch.schema()).map_err(|m| {
            StageError::Failed(format!(
                "output table `{}` does not match its schema file: {m}",
                self.table
            ))
        })?;
        let enc = self
            .encoder
            .as_mut()
            .ok_or_else(|| StageError::Failed(format!("table `{}` is finished", self.table)))?;
        enc.write(batch).map_err(|e| {
            StageError::Failed(format!("writing {} (disk full?): {e}", self.path.display()))
        })
    }

    /// Copies the row's other columns as stored where `from` is a table of the cache whose
    /// row is a row group of its own; otherwise decodes the row.
    fn write_from(
        &mut self,
        from: &stages::stream::Table,
        row: usize,
        replaced: &[(&str, arrow::array::ArrayRef)],
    ) -> stages::Result<()> {
        let stored = from
            .stored_source()
            .and_then(|s| s.as_any())
            .and_then(|a| a.downcast_ref::<StoredTable>());
        if let Some((t, group)) = stored.and_then(|t| Some((t, t.group_alone(row)?))) {
            let enc = self
                .encoder
                .as_mut()
                .ok_or_else(|| StageError::Failed(format!("table `{}` is finished", self.table)))?;
            let spliced = enc.splice(t, group, replaced).map_err(|e| {
                StageError::Failed(format!("writing {} (disk full?): {e}", self.path.display()))
            })?;
            if spliced {
                return Ok(());
            }
        }
        self.write(&from.row_with(row, replaced)?)
    }

    fn finish(mut self: Box<Self>) -> stages::Result<()> {
        let enc = self
            .encoder
            .take()
            .ok_or_else(|| StageError::Failed(format!("table `{}` is finished", self.table)))?;
        let file = enc.finish().map_err(|e| self.failed(e))?;
        let (size, blake3) = file.finish().map_err(|e| self.failed(e))?;
        self.written
            .lock()
            .unwrap()
            .insert(self.table.clone(), Some(FileInfo { size, blake3 }));
        Ok(())
    }
}
