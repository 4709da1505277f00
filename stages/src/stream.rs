//! Tables read and written a piece at a time, so a stage's memory does not grow with the size
//! of a scene: a [`Table`] an input slot hands over is either in memory or stored (the runner
//! reads the rows a stage asks for from the cache, only the columns it names), and a
//! [`TableWriter`] takes an output table one batch (one image) at a time (the runner writes
//! each batch to the cache as it comes; without a runner, e.g. in tests, the batches are
//! gathered into one table the stage returns).

use std::{collections::BTreeMap, ops::Range, sync::OnceLock};

use arrow::{
    array::ArrayRef, compute::concat_batches, datatypes::SchemaRef, record_batch::RecordBatch,
};

use crate::error::{Result, StageError};

/// Named tables: what a stage writes, and what an upstream stage hands to a downstream one.
pub type Tables = BTreeMap<String, RecordBatch>;

/// Rows of a stored table, read on demand (the runner implements it over Parquet row groups).
pub trait RowSource: Send + Sync {
    fn schema(&self) -> SchemaRef;
    fn num_rows(&self) -> usize;
    /// Rows `range` with only the named `columns` (every column when `None`), as one batch.
    fn read(&self, range: Range<usize>, columns: Option<&[&str]>) -> Result<RecordBatch>;
    /// The source itself, for a sink that copies its rows without decoding them (see
    /// [`TableSink::write_from`]).
    fn as_any(&self) -> Option<&dyn std::any::Any> {
        None
    }
}

/// A table an input slot hands to a stage: in memory, or stored and read on demand.
pub struct Table {
    name: String,
    source: Source,
    /// The whole table, once a stage asked for it (see [`Table::whole`]).
    whole: OnceLock<RecordBatch>,
}

enum Source {
    Memory(RecordBatch),
    Stored(Box<dyn RowSource>),
}

impl Table {
    pub fn memory(name: &str, batch: RecordBatch) -> Self {
        Self {
            name: name.to_string(),
            source: Source::Memory(batch),
            whole: OnceLock::new(),
        }
    }

    pub fn stored(name: &str, source: Box<dyn RowSource>) -> Self {
        Self {
            name: name.to_string(),
            source: Source::Stored(source),
            whole: OnceLock::new(),
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn num_rows(&self) -> usize {
        match &self.source {
            Source::Memory(b) => b.num_rows(),
            Source::Stored(s) => s.num_rows(),
        }
    }

    pub fn schema(&self) -> SchemaRef {
        match &self.source {
            Source::Memory(b) => b.schema(),
            Source::Stored(s) => s.schema(),
        }
    }

    /// The whole table in memory (read once, then kept as long as the table): for tables that
    /// are small, or that a stage needs whole anyway.
    pub fn whole(&self) -> Result<&RecordBatch> {
        if let Some(b) = self.whole.get() {
            return Ok(b);
        }
        let b = match &self.source {
            Source::Memory(b) => b.clone(),
            Source::Stored(s) => s.read(0..s.num_rows(), None)?,
        };
        Ok(self.whole.get_or_init(|| b))
    }

    /// Rows `range` with only `columns` (all when `None`); nothing else is read or kept.
    pub fn rows(&self, range: Range<usize>, columns: Option<&[&str]>) -> Result<RecordBatch> {
        if range.end > self.num_rows() || range.start > range.end {
            return Err(StageError::Input(format!(
                "table `{}` has {} rows; rows {range:?} were asked for",
                self.name,
                self.num_rows()
            )));
        }
        if let Some(b) = self.whole.get() {
            return project(&self.name, &b.slice(range.start, range.len()), columns);
        }
        match &self.source {
            Source::Memory(b) => project(&self.name, &b.slice(range.start, range.len()), columns),
            Source::Stored(s) => s.read(range, columns),
        }
    }

    /// Row `i`, every column.
    pub fn row(&self, i: usize) -> Result<RecordBatch> {
        self.rows(i..i + 1, None)
    }

    /// Where a stored table's rows come from (`None` in memory).
    pub fn stored_source(&self) -> Option<&dyn RowSource> {
        match &self.source {
            Source::Stored(s) => Some(s.as_ref()),
            Source::Memory(_) => None,
        }
    }

    /// Row `i` with the columns of `replaced` in place of its own (each one row long, of the
    /// same type).
    pub fn row_with(&self, i: usize, replaced: &[(&str, ArrayRef)]) -> Result<RecordBatch> {
        let row = self.row(i)?;
        if replaced.is_empty() {
            return Ok(row);
        }
        let mut cols = row.columns().to_vec();
        for (name, col) in replaced {
            let at = row.schema().index_of(name).map_err(|_| {
                StageError::Input(format!("table `{}` has no column `{name}`", self.name))
            })?;
            cols[at] = col.clone();
        }
        RecordBatch::try_new(row.schema(), cols)
            .map_err(|e| StageError::Failed(format!("replacing columns of `{}`: {e}", self.name)))
    }

    /// The row of each image of a per-image table, by (frame, camera), read from those two
    /// columns alone.
    pub fn image_rows(&self) -> Result<std::collections::HashMap<(u32, u8), usize>> {
        crate::tables::frame_camera_index(&self.columns(&["frame", "camera"])?, &self.name)
    }

    /// Every row, only `columns`: e.g. the keys of a per-image table without its pixels.
    pub fn columns(&self, columns: &[&str]) -> Result<RecordBatch> {
        self.rows(0..self.num_rows(), Some(columns))
    }
}

/// `batch` with only `columns`, in that order (every column when `None`).
pub fn project(table: &str, batch: &RecordBatch, columns: Option<&[&str]>) -> Result<RecordBatch> {
    let Some(columns) = columns else {
        return Ok(batch.clone());
    };
    let idx = columns
        .iter()
        .map(|c| {
            batch
                .schema()
                .index_of(c)
                .map_err(|_| StageError::Input(format!("table `{table}` has no column `{c}`")))
        })
        .collect::<Result<Vec<_>>>()?;
    batch
        .project(&idx)
        .map_err(|e| StageError::Input(format!("table `{table}`: {e}")))
}

/// The tables of one stage's entry, by name.
#[derive(Default)]
pub struct TableSet {
    tables: BTreeMap<String, Table>,
}

impl TableSet {
    pub fn insert(&mut self, table: Table) {
        self.tables.insert(table.name.clone(), table);
    }

    pub fn get(&self, name: &str) -> Option<&Table> {
        self.tables.get(name)
    }

    pub fn contains(&self, name: &str) -> bool {
        self.tables.contains_key(name)
    }

    /// Table `name` whole in memory; an error names the tables there are.
    pub fn table(&self, name: &str) -> Result<&RecordBatch> {
        self.get(name)
            .ok_or_else(|| {
                StageError::Input(format!(
                    "no table `{name}` (there are: {})",
                    self.names().collect::<Vec<_>>().join(", ")
                ))
            })?
            .whole()
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.tables.keys().map(String::as_str)
    }

    pub fn iter(&self) -> impl Iterator<Item = &Table> {
        self.tables.values()
    }

    /// Every table whole in memory (for code that wants plain batches of small entries).
    pub fn whole_tables(&self) -> Result<Tables> {
        self.tables
            .iter()
            .map(|(n, t)| Ok((n.clone(), t.whole()?.clone())))
            .collect()
    }
}

impl From<Tables> for TableSet {
    /// In-memory tables (tests, and stages run without a cache).
    fn from(tables: Tables) -> Self {
        let mut set = TableSet::default();
        for (name, b) in tables {
            set.insert(Table::memory(&name, b));
        }
        set
    }
}

/// Where the runner takes one streamed output table (see [`TableWriter`]).
pub trait TableSink: Send {
    /// Appends `batch` (its schema checked against the table's schema file) as its own piece.
    fn write(&mut self, batch: &RecordBatch) -> Result<()>;
    /// Appends row `row` of `from` (a table of this one's schema) with the columns of
    /// `replaced` in place of its own, as its own piece. The runner copies the row's other
    /// columns as they are stored, without decoding them; this default decodes the row.
    fn write_from(
        &mut self,
        from: &Table,
        row: usize,
        replaced: &[(&str, ArrayRef)],
    ) -> Result<()> {
        self.write(&from.row_with(row, replaced)?)
    }
    /// Ends the table.
    fn finish(self: Box<Self>) -> Result<()>;
}

/// Opens the runner's sinks, one per streamed output table of a stage run.
pub trait Sinks: Sync {
    fn open(&self, table: &str) -> Result<Box<dyn TableSink>>;
}

/// One output table written a batch at a time. Batches go to the runner's sink as they come
/// when the stage runs under the runner; otherwise they are gathered and the table is returned
/// with the stage's other outputs ([`TableWriter::finish_into`]).
pub struct TableWriter {
    name: String,
    to: Target,
}

enum Target {
    Sink(Box<dyn TableSink>),
    Memory(Vec<RecordBatch>),
}

impl TableWriter {
    pub(crate) fn new(name: &str, sinks: Option<&dyn Sinks>) -> Result<Self> {
        let to = match sinks {
            Some(s) => Target::Sink(s.open(name)?),
            None => Target::Memory(Vec::new()),
        };
        Ok(Self {
            name: name.to_string(),
            to,
        })
    }

    pub fn write(&mut self, batch: RecordBatch) -> Result<()> {
        match &mut self.to {
            Target::Sink(s) => s.write(&batch),
            Target::Memory(v) => {
                v.push(batch);
                Ok(())
            }
        }
    }

    /// Appends row `row` of `from` with the columns of `replaced` in place of its own (see
    /// [`TableSink::write_from`]): what an update keeps of its previous output, copied as
    /// stored where the runner can.
    pub fn write_from(
        &mut self,
        from: &Table,
        row: usize,
        replaced: &[(&str, ArrayRef)],
    ) -> Result<()> {
        match &mut self.to {
            Target::Sink(s) => s.write_from(from, row, replaced),
            Target::Memory(v) => {
                v.push(from.row_with(row, replaced)?);
                Ok(())
            }
        }
    }

    /// Ends the table: a gathered table goes into `out` (a streamed one is the runner's
    /// already).
    pub fn finish_into(self, out: &mut Tables) -> Result<()> {
        match self.to {
            Target::Sink(s) => s.finish(),
            Target::Memory(v) => {
                let schema = match v.first() {
                    Some(b) => b.schema(),
                    None => crate::schema::get(&self.name).ok_or_else(|| {
                        StageError::Failed(format!("no schema file for table `{}`", self.name))
                    })?,
                };
                let b = concat_batches(&schema, &v).map_err(|e| {
                    StageError::Failed(format!("gathering table `{}`: {e}", self.name))
                })?;
                out.insert(self.name, b);
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tables;
    use arrow::datatypes::{DataType, Field, Schema, UInt32Type, UInt8Type};
    use std::sync::Arc;

    fn numbers(n: u32) -> RecordBatch {
        let (a, b) = (
            tables::prim::<UInt32Type>(0..n),
            tables::list::<UInt8Type>((0..n).map(|i| vec![i as u8; i as usize])),
        );
        let schema = Arc::new(Schema::new(vec![
            Field::new("n", DataType::UInt32, false),
            Field::new("values", b.data_type().clone(), false),
        ]));
        RecordBatch::try_new(schema, vec![a, b]).unwrap()
    }

    #[test]
    fn rows_and_columns_of_a_memory_table() {
        let t = Table::memory("numbers", numbers(5));
        assert_eq!(t.num_rows(), 5);
        let b = t.rows(1..3, Some(&["values"])).unwrap();
        assert_eq!(b.num_rows(), 2);
        assert_eq!(b.num_columns(), 1);
        let l = tables::get_list::<UInt8Type>(&b, "t", "values").unwrap();
        assert_eq!(l.row(1), &[2, 2]);
        let e = t.rows(4..6, None).unwrap_err().to_string();
        assert!(e.contains("has 5 rows"), "{e}");
        let e = t.columns(&["nope"]).unwrap_err().to_string();
        assert!(e.contains("no column `nope`"), "{e}");
        assert_eq!(t.whole().unwrap().num_rows(), 5);
    }

    #[test]
    fn a_writer_without_sinks_gathers_its_batches() {
        let mut w = TableWriter::new("numbers", None).unwrap();
        w.write(numbers(2)).unwrap();
        w.write(numbers(3)).unwrap();
        let mut out = Tables::new();
        w.finish_into(&mut out).unwrap();
        assert_eq!(out["numbers"].num_rows(), 5);
        // No batch at all is an empty table of the schema file's.
        let w = TableWriter::new("test_numbers", None).unwrap();
        let mut out = Tables::new();
        w.finish_into(&mut out).unwrap();
        assert_eq!(out["test_numbers"].num_rows(), 0);
        assert_eq!(
            out["test_numbers"].schema(),
            crate::schema::get("test_numbers").unwrap()
        );
    }
}
