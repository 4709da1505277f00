//! Copying a row group of a stored table into a new table as it is stored: what an update keeps
//! of its previous output (an image's row, or all of it but one column) is not decoded and
//! encoded again. Only the columns given anew are encoded; the copied column chunks keep their
//! bytes, statistics and page indexes, so the new file is the bytes encoding the rows gives.

use std::{io::Write, sync::Arc};

use arrow::array::ArrayRef;
use parquet::{
    arrow::arrow_writer::compute_leaves,
    column::writer::ColumnCloseResult,
    errors::ParquetError,
    file::metadata::{
        PageIndexPolicy, ParquetMetaData, ParquetMetaDataOptions, ParquetMetaDataReader,
    },
};

use super::codec::{CodecError, Positional, StoredTable, TableEncoder};

impl StoredTable {
    /// The row group that holds row `row` and no other, if one does.
    pub fn group_alone(&self, row: usize) -> Option<usize> {
        let g = self.starts.partition_point(|&s| s <= row).checked_sub(1)?;
        (self.starts.get(g + 1) == Some(&(row + 1))).then_some(g)
    }

    /// The file's metadata with its page indexes (read once); `None` when it has none.
    fn indexed(&self) -> Option<&Arc<ParquetMetaData>> {
        self.indexed
            .get_or_init(|| {
                // The pages' encoding statistics in full, as the writer writes them (a copied
                // chunk keeps the metadata it is read with).
                let full = ParquetMetaDataOptions::new().with_encoding_stats_as_mask(false);
                ParquetMetaDataReader::new()
                    .with_page_index_policy(PageIndexPolicy::Optional)
                    .with_metadata_options(Some(full))
                    .parse_and_finish(&Positional(self.file.clone(), self.len))
                    .ok()
                    .filter(|m| m.page_index().is_some_and(|p| p.is_complete()))
                    .map(Arc::new)
            })
            .as_ref()
    }
}

impl<W: Write + Send> TableEncoder<W> {
    /// Appends row group `group` of `from` as a row group of its own, the columns named in
    /// `replaced` encoded from those arrays (as long as the group), every other column chunk
    /// copied as stored. `Ok(false)`, having written nothing, where `from` cannot be copied
    /// from (another schema, no page indexes): the caller encodes the rows instead.
    pub fn splice(
        &mut self,
        from: &StoredTable,
        group: usize,
        replaced: &[(&str, ArrayRef)],
    ) -> Result<bool, CodecError> {
        if from.meta.schema().fields() != self.schema.fields() {
            return Ok(false);
        }
        let Some(meta) = from.indexed() else {
            return Ok(false);
        };
        let Some(index) = meta.page_index() else {
            return Ok(false);
        };
        let rg = meta.row_group(group);
        let rows = rg.num_rows() as usize;
        // Which top-level field each leaf column belongs to.
        let fields = self.schema.fields();
        let leaf_field: Vec<Option<usize>> = self
            .writer
            .schema_descr()
            .columns()
            .iter()
            .map(|c| {
                let top = c.path().parts().first()?;
                fields.iter().position(|f| f.name() == top)
            })
            .collect();
        if leaf_field.len() != rg.num_columns() || leaf_field.contains(&None) {
            return Ok(false);
        }
        let mut fresh = vec![false; fields.len()];
        let out_group = self.writer.flushed_row_groups().len();
        let mut writers = self.factory.create_column_writers(out_group)?;
        for (name, array) in replaced {
            let Some(f) = fields.iter().position(|f| f.name() == name) else {
                return Err(ParquetError::General(format!("no column `{name}` to replace")).into());
            };
            if array.len() != rows || array.data_type() != fields[f].data_type() {
                return Err(ParquetError::General(format!(
                    "column `{name}` replaced by {} values of {}, expected {rows} of {}",
                    array.len(),
                    array.data_type(),
                    fields[f].data_type()
                ))
                .into());
            }
            fresh[f] = true;
            let mut leaves = leaf_field
                .iter()
                .zip(writers.iter_mut())
                .filter(|(lf, _)| **lf == Some(f))
                .map(|(_, w)| w);
            for leaf in compute_leaves(&fields[f], array)? {
                leaves
                    .next()
                    .ok_or_else(|| ParquetError::General("more leaves than columns".into()))?
                    .write(&leaf)?;
            }
        }
        let source = Positional(from.file.clone(), from.len);
        let mut out = self.writer.next_row_group()?;
        for (leaf, (w, f)) in writers.into_iter().zip(&leaf_field).enumerate() {
            if fresh[f.expect("checked")] {
                w.close()?.append_to_row_group(&mut out)?;
                continue;
            }
            let chunk = rg.column(leaf);
            out.append_column(
                &source,
                ColumnCloseResult {
                    bytes_written: chunk.compressed_size() as u64,
                    rows_written: rows as u64,
                    metadata: chunk.clone(),
                    bloom_filter: None,
                    column_index: index.column_index(group, leaf).cloned(),
                    offset_index: index.offset_index(group, leaf).cloned(),
                },
            )?;
        }
        out.close()?;
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::super::codec::HashingFile;
    use super::*;
    use arrow::{
        array::{Array, BinaryArray, Float32Array, ListArray, UInt32Array},
        datatypes::{DataType, Field, Float32Type, Schema, UInt32Type},
        record_batch::RecordBatch,
    };
    use stages::stream::RowSource;

    /// Images as a per-image table would hold them: a key, a ragged list of ids and of floats,
    /// and bytes; each row large enough to be a row group of its own.
    fn images(n: u32, seed: u32) -> RecordBatch {
        let px = 70_000usize;
        let ids = ListArray::from_iter_primitive::<UInt32Type, _, _>(
            (0..n).map(|i| Some((0..px).map(move |j| Some((j as u32 * 31 + i * seed) % 500)))),
        );
        let depth =
            ListArray::from_iter_primitive::<Float32Type, _, _>((0..n).map(|i| {
                Some((0..px).map(move |j| Some((j as f32 * 0.01 + i as f32) * seed as f32)))
            }));
        let schema = Arc::new(Schema::new(vec![
            Field::new("frame", DataType::UInt32, false),
            Field::new("ids", ids.data_type().clone(), false),
            Field::new("depth", depth.data_type().clone(), false),
            Field::new("score", DataType::Float32, false),
            Field::new("rgb", DataType::Binary, false),
        ]));
        RecordBatch::try_new(
            schema,
            vec![
                Arc::new(UInt32Array::from_iter_values(0..n)),
                Arc::new(ids),
                Arc::new(depth),
                Arc::new(Float32Array::from_iter_values((0..n).map(|i| i as f32))),
                Arc::new(BinaryArray::from_iter_values(
                    (0..n).map(|i| vec![(i * seed) as u8; 300_000]),
                )),
            ],
        )
        .unwrap()
    }

    fn stored(dir: &std::path::Path, name: &str, b: &RecordBatch) -> StoredTable {
        let path = dir.join(name);
        let mut enc = TableEncoder::new(HashingFile::create(&path).unwrap(), b.schema()).unwrap();
        enc.write_whole(b).unwrap();
        enc.finish().unwrap().finish().unwrap();
        StoredTable::open(&path).unwrap()
    }

    /// Rows copied as stored, some with a column replaced, interleaved with rows encoded anew:
    /// the file is the bytes of encoding the same rows, and reads back as them.
    #[test]
    fn spliced_rows_are_the_bytes_of_the_rows_encoded() {
        let dir = tempfile::tempdir().unwrap();
        let (old, other) = (images(5, 3), images(5, 7));
        let t = stored(dir.path(), "old.parquet", &old);
        assert_eq!(
            (0..5).map(|r| t.group_alone(r)).collect::<Vec<_>>(),
            (0..5).map(Some).collect::<Vec<_>>()
        );
        // Row 1 kept, row 3 with other ids, row 2 of the other table, row 4 with other depth
        // and score.
        let ids = other.column(1).slice(3, 1);
        let (depth, score) = (other.column(2).slice(4, 1), other.column(3).slice(4, 1));
        let mut enc = TableEncoder::new(Vec::new(), old.schema()).unwrap();
        assert!(enc.splice(&t, 1, &[]).unwrap());
        assert!(enc.splice(&t, 3, &[("ids", ids.clone())]).unwrap());
        enc.write(&other.slice(2, 1)).unwrap();
        assert!(enc
            .splice(&t, 4, &[("score", score.clone()), ("depth", depth.clone())])
            .unwrap());
        let spliced = enc.finish().unwrap();

        let with = |r: usize, cols: &[(usize, &ArrayRef)]| {
            let mut c = old.slice(r, 1).columns().to_vec();
            for (i, a) in cols {
                c[*i] = (*a).clone();
            }
            RecordBatch::try_new(old.schema(), c).unwrap()
        };
        let mut enc = TableEncoder::new(Vec::new(), old.schema()).unwrap();
        for b in [
            with(1, &[]),
            with(3, &[(1, &ids)]),
            other.slice(2, 1),
            with(4, &[(2, &depth), (3, &score)]),
        ] {
            enc.write(&b).unwrap();
        }
        let encoded = enc.finish().unwrap();
        assert!(
            spliced == encoded,
            "the spliced file differs from the encoded rows"
        );
        let back = super::super::codec::read_parquet(spliced).unwrap();
        assert_eq!(back.num_rows(), 4);
        assert_eq!(back.column(1).slice(1, 1).as_ref(), ids.as_ref());
        assert_eq!(back.slice(0, 1), old.slice(1, 1));
    }

    /// What cannot be copied is refused before anything is written; bad replacements are
    /// errors that name the column.
    #[test]
    fn splicing_refuses_another_schema_and_bad_columns() {
        let dir = tempfile::tempdir().unwrap();
        let old = images(3, 3);
        let t = stored(dir.path(), "old.parquet", &old);
        let narrower = Arc::new(old.schema().project(&[0, 1]).unwrap());
        let mut enc = TableEncoder::new(Vec::new(), narrower).unwrap();
        assert!(!enc.splice(&t, 0, &[]).unwrap());
        assert_eq!(enc.writer.flushed_row_groups().len(), 0);
        let mut enc = TableEncoder::new(Vec::new(), old.schema()).unwrap();
        let e = enc
            .splice(&t, 0, &[("nope", old.column(0).slice(0, 1))])
            .unwrap_err()
            .to_string();
        assert!(e.contains("no column `nope`"), "{e}");
        let e = enc
            .splice(&t, 0, &[("score", old.column(3).slice(0, 2))])
            .unwrap_err()
            .to_string();
        assert!(e.contains("`score` replaced by 2 values"), "{e}");
        // A table of small rows holds several rows per group: none is alone.
        let small = stored(
            dir.path(),
            "small.parquet",
            &old.slice(0, 3).project(&[0, 3]).unwrap(),
        );
        assert_eq!(small.num_rows(), 3);
        assert_eq!(small.group_alone(1), None);
        assert_eq!(t.group_alone(3), None);
    }
}
