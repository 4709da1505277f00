//! The `label_maps` writer on a thread of its own: building and storing an image's row (tens of
//! milliseconds of one core) overlaps the next image's rendering. Rows are stored in the order
//! they are sent, so the table's bytes are those of writing them in place.

use std::sync::mpsc::{sync_channel, SyncSender};
use std::thread::{Scope, ScopedJoinHandle};

use arrow::datatypes::{Float32Type, UInt16Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;

use crate::model::maps::ImageMaps;
use crate::stage::{Result, StageError, Table, TableWriter};
use crate::tables;

/// One row to store.
enum Row<'t> {
    /// Row `usize` of a previous `label_maps` table, as it is.
    Copy(&'t Table, usize),
    /// An image's new maps.
    Maps(ImageMaps),
}

pub(super) struct MapWriter<'s, 't> {
    rows: Option<SyncSender<Row<'t>>>,
    thread: Option<ScopedJoinHandle<'s, Result<TableWriter>>>,
}

impl<'s, 't> MapWriter<'s, 't> {
    /// Starts the thread that writes into `out`, rows of sequence `seq`.
    pub(super) fn start<'e>(s: &'s Scope<'s, 'e>, mut out: TableWriter, seq: &'s str) -> Self
    where
        't: 's,
    {
        // One row waiting at most: an image's maps are megabytes.
        let (tx, rx) = sync_channel::<Row<'t>>(1);
        let thread = s.spawn(move || {
            for row in rx {
                match row {
                    Row::Copy(table, r) => out.write_from(table, r, &[])?,
                    Row::Maps(maps) => out.write(label_maps_row(seq, maps)?)?,
                }
            }
            Ok(out)
        });
        Self {
            rows: Some(tx),
            thread: Some(thread),
        }
    }

    /// Stores row `row` of the previous `table` as it is.
    pub(super) fn copy(&mut self, table: &'t Table, row: usize) -> Result<()> {
        self.send(Row::Copy(table, row))
    }

    /// Stores an image's maps.
    pub(super) fn maps(&mut self, maps: ImageMaps) -> Result<()> {
        self.send(Row::Maps(maps))
    }

    fn send(&mut self, row: Row<'t>) -> Result<()> {
        let sent = self.rows.as_ref().map(|tx| tx.send(row).is_ok());
        if sent == Some(true) {
            return Ok(());
        }
        // The writer stopped: its error says why.
        self.rows = None;
        match self.join() {
            Err(e) => Err(e),
            Ok(_) => Err(StageError::Failed("the label_maps writer stopped".into())),
        }
    }

    /// Waits for every row sent to be stored; the writer, to finish the table.
    pub(super) fn finish(mut self) -> Result<TableWriter> {
        self.rows = None;
        self.join()
    }

    fn join(&mut self) -> Result<TableWriter> {
        let thread = self
            .thread
            .take()
            .ok_or_else(|| StageError::Failed("the label_maps writer stopped".into()))?;
        thread
            .join()
            .unwrap_or_else(|e| std::panic::resume_unwind(e))
    }
}

/// The `label_maps` row of one rendered image.
pub(super) fn label_maps_row(sequence: &str, m: ImageMaps) -> Result<RecordBatch> {
    tables::build(
        "label_maps",
        vec![
            tables::strings([sequence]),
            tables::prim::<UInt32Type>([m.frame]),
            tables::prim::<UInt8Type>([m.camera]),
            tables::prim::<UInt32Type>([m.width]),
            tables::prim::<UInt32Type>([m.height]),
            tables::list::<UInt8Type>([m.semantic]),
            tables::list::<UInt8Type>([m.fixed]),
            tables::list::<UInt16Type>([m.instance]),
            tables::list::<Float32Type>([m.depth]),
            tables::list::<Float32Type>([m.confidence]),
            tables::binary([m.rgb]),
        ],
    )
}
