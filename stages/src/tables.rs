//! Typed access to Arrow tables: building a batch against its `data_schema/` file, and reading
//! columns with errors that name the table and column instead of panicking.

use std::sync::Arc;

use arrow::{
    array::{
        Array, ArrayRef, AsArray, BinaryArray, BooleanArray, FixedSizeListArray, ListArray,
        PrimitiveArray, StringArray,
    },
    buffer::{OffsetBuffer, ScalarBuffer},
    datatypes::{ArrowPrimitiveType, DataType},
    record_batch::RecordBatch,
};

use crate::{schema, Result, StageError};

/// Builds table `name` from its columns, in the order of `data_schema/<name>.json`.
pub fn build(name: &str, columns: Vec<ArrayRef>) -> Result<RecordBatch> {
    let schema = schema::get(name)
        .ok_or_else(|| StageError::Failed(format!("no schema file data_schema/{name}.json")))?;
    RecordBatch::try_new(schema, columns)
        .map_err(|e| StageError::Failed(format!("building table `{name}`: {e}")))
}

/// A primitive column from a slice.
pub fn prim<T: ArrowPrimitiveType>(values: impl IntoIterator<Item = T::Native>) -> ArrayRef {
    Arc::new(PrimitiveArray::<T>::from_iter_values(values))
}

pub fn strings<S: AsRef<str>>(values: impl IntoIterator<Item = S>) -> ArrayRef {
    Arc::new(StringArray::from_iter_values(values))
}

pub fn bools(values: impl IntoIterator<Item = bool>) -> ArrayRef {
    Arc::new(BooleanArray::from_iter(values.into_iter().map(Some)))
}

pub fn binary<B: AsRef<[u8]>>(values: impl IntoIterator<Item = B>) -> ArrayRef {
    Arc::new(BinaryArray::from_iter_values(values))
}

/// A `list<T>` column from one vector per row. The values buffer is allocated once, at its
/// size, and each row is freed as soon as it is copied in: a column of a scene's images then
/// takes its size once, not twice or more.
pub fn list<T: ArrowPrimitiveType>(rows: impl IntoIterator<Item = Vec<T::Native>>) -> ArrayRef {
    let rows: Vec<Vec<T::Native>> = rows.into_iter().collect();
    let offsets = OffsetBuffer::from_lengths(rows.iter().map(|r| r.len()));
    let mut flat = Vec::with_capacity(rows.iter().map(Vec::len).sum());
    for row in rows {
        flat.extend_from_slice(&row);
    }
    let values = PrimitiveArray::<T>::new(ScalarBuffer::from(flat), None);
    Arc::new(ListArray::new(
        schema::list_item(T::DATA_TYPE),
        offsets,
        Arc::new(values),
        None,
    ))
}

/// A `fixed_size_list<T, n>` column from a flat vector of `rows * n` values.
pub fn fixed_list<T: ArrowPrimitiveType>(n: usize, flat: Vec<T::Native>) -> ArrayRef {
    assert_eq!(
        flat.len() % n,
        0,
        "flat length is not a multiple of the list size"
    );
    let values = PrimitiveArray::<T>::from_iter_values(flat);
    Arc::new(FixedSizeListArray::new(
        schema::list_item(T::DATA_TYPE),
        n as i32,
        Arc::new(values),
        None,
    ))
}

fn column<'a>(batch: &'a RecordBatch, table: &str, col: &str) -> Result<&'a ArrayRef> {
    batch
        .column_by_name(col)
        .ok_or_else(|| StageError::Input(format!("table `{table}` has no column `{col}`")))
}

fn type_error(table: &str, col: &str, want: &str, got: &DataType) -> StageError {
    StageError::Input(format!(
        "table `{table}` column `{col}`: expected {want}, found {}",
        schema::format_type(got)
    ))
}

/// A primitive column as a slice.
pub fn get_prim<'a, T: ArrowPrimitiveType>(
    batch: &'a RecordBatch,
    table: &str,
    col: &str,
) -> Result<&'a [T::Native]> {
    let c = column(batch, table, col)?;
    c.as_primitive_opt::<T>()
        .map(|a| a.values().as_ref())
        .ok_or_else(|| {
            type_error(
                table,
                col,
                &schema::format_type(&T::DATA_TYPE),
                c.data_type(),
            )
        })
}

pub fn get_strings<'a>(batch: &'a RecordBatch, table: &str, col: &str) -> Result<&'a StringArray> {
    let c = column(batch, table, col)?;
    c.as_string_opt::<i32>()
        .ok_or_else(|| type_error(table, col, "utf8", c.data_type()))
}

pub fn get_bools(batch: &RecordBatch, table: &str, col: &str) -> Result<Vec<bool>> {
    let c = column(batch, table, col)?;
    c.as_boolean_opt()
        .map(|a| a.iter().map(|v| v.unwrap_or(false)).collect())
        .ok_or_else(|| type_error(table, col, "bool", c.data_type()))
}

pub fn get_binary<'a>(batch: &'a RecordBatch, table: &str, col: &str) -> Result<&'a BinaryArray> {
    let c = column(batch, table, col)?;
    c.as_binary_opt::<i32>()
        .ok_or_else(|| type_error(table, col, "binary", c.data_type()))
}

/// Row of each `(frame, camera)` key of a per-image table (every such table has both columns).
pub fn frame_camera_index<C: FromIterator<((u32, u8), usize)>>(
    batch: &RecordBatch,
    table: &str,
) -> Result<C> {
    use arrow::datatypes::{UInt32Type, UInt8Type};
    let f = get_prim::<UInt32Type>(batch, table, "frame")?;
    let c = get_prim::<UInt8Type>(batch, table, "camera")?;
    Ok(f.iter()
        .zip(c)
        .enumerate()
        .map(|(r, (&f, &c))| ((f, c), r))
        .collect())
}

/// A `list<T>` column: per-row slices of one flat value buffer.
pub struct ListColumn<'a, N> {
    offsets: &'a [i32],
    values: &'a [N],
}

impl<'a, N> ListColumn<'a, N> {
    pub fn row(&self, i: usize) -> &'a [N] {
        &self.values[self.offsets[i] as usize..self.offsets[i + 1] as usize]
    }
    pub fn len(&self) -> usize {
        self.offsets.len() - 1
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

pub fn get_list<'a, T: ArrowPrimitiveType>(
    batch: &'a RecordBatch,
    table: &str,
    col: &str,
) -> Result<ListColumn<'a, T::Native>> {
    let c = column(batch, table, col)?;
    let want = format!("list<{}>", schema::format_type(&T::DATA_TYPE));
    let list = c
        .as_list_opt::<i32>()
        .ok_or_else(|| type_error(table, col, &want, c.data_type()))?;
    let values = list
        .values()
        .as_primitive_opt::<T>()
        .ok_or_else(|| type_error(table, col, &want, c.data_type()))?;
    // Sliced arrays keep absolute offsets into the shared value buffer.
    Ok(ListColumn {
        offsets: list.value_offsets(),
        values: values.values().as_ref(),
    })
}

/// A `fixed_size_list<T, n>` column as a flat slice of `rows * n` values, and `n`.
pub fn get_fixed_list<'a, T: ArrowPrimitiveType>(
    batch: &'a RecordBatch,
    table: &str,
    col: &str,
) -> Result<(&'a [T::Native], usize)> {
    let c = column(batch, table, col)?;
    let want = format!("fixed_size_list<{}, n>", schema::format_type(&T::DATA_TYPE));
    let list = c
        .as_fixed_size_list_opt()
        .ok_or_else(|| type_error(table, col, &want, c.data_type()))?;
    let n = list.value_length() as usize;
    let values = list
        .values()
        .as_primitive_opt::<T>()
        .ok_or_else(|| type_error(table, col, &want, c.data_type()))?;
    let start = list.offset() * n;
    Ok((&values.values()[start..start + list.len() * n], n))
}

/// Writes `batch` as CSV (a header of column names, nulls empty, text quoted where it holds a
/// comma, quote or line break) to `path`, creating its directory.
pub fn write_csv(batch: &RecordBatch, path: &std::path::Path) -> Result<()> {
    use arrow::util::display::{ArrayFormatter, FormatOptions};
    use std::fmt::Write as _;
    let fail = |e: String| StageError::Failed(format!("writing {}: {e}", path.display()));
    let quote = |s: &str| {
        if s.contains([',', '"', '\n', '\r']) {
            format!("\"{}\"", s.replace('"', "\"\""))
        } else {
            s.to_string()
        }
    };
    let schema = batch.schema();
    let mut out: String = schema
        .fields()
        .iter()
        .map(|f| quote(f.name()))
        .collect::<Vec<_>>()
        .join(",");
    out.push('\n');
    let options = FormatOptions::default().with_null("");
    let formatters = batch
        .columns()
        .iter()
        .map(|c| ArrayFormatter::try_new(c.as_ref(), &options))
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| fail(e.to_string()))?;
    for r in 0..batch.num_rows() {
        for (i, f) in formatters.iter().enumerate() {
            if i > 0 {
                out.push(',');
            }
            let cell = f
                .value(r)
                .try_to_string()
                .map_err(|e| fail(e.to_string()))?;
            let _ = write!(out, "{}", quote(&cell));
        }
        out.push('\n');
    }
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| fail(e.to_string()))?;
    }
    std::fs::write(path, out).map_err(|e| fail(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::datatypes::{Float64Type, UInt32Type};

    #[test]
    fn list_columns_round_trip() {
        let a = list::<UInt32Type>(vec![vec![1, 2], vec![], vec![3]]);
        let b = fixed_list::<Float64Type>(2, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let schema = Arc::new(arrow::datatypes::Schema::new(vec![
            arrow::datatypes::Field::new("a", a.data_type().clone(), false),
            arrow::datatypes::Field::new("b", b.data_type().clone(), false),
        ]));
        let batch = RecordBatch::try_new(schema, vec![a, b]).unwrap();
        let l = get_list::<UInt32Type>(&batch, "t", "a").unwrap();
        assert_eq!(l.row(0), &[1, 2]);
        assert!(l.row(1).is_empty());
        assert_eq!(l.row(2), &[3]);
        let sliced = batch.slice(1, 2);
        let (flat, n) = get_fixed_list::<Float64Type>(&sliced, "t", "b").unwrap();
        assert_eq!((flat, n), (&[3.0, 4.0, 5.0, 6.0][..], 2));
        let err = get_prim::<UInt32Type>(&batch, "t", "b").unwrap_err();
        assert!(err.to_string().contains("column `b`"), "{err}");
        assert!(get_prim::<UInt32Type>(&batch, "t", "zzz").is_err());
    }
}
