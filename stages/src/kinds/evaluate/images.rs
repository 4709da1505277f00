//! One image's maps in a per-image table, checked against its size.

use arrow::{
    datatypes::{Float32Type, UInt16Type, UInt32Type, UInt8Type},
    record_batch::RecordBatch,
};

use crate::{tables, Result, StageError};

/// One image's maps, keyed by (frame, camera).
pub(super) struct Image<'a> {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) row: usize,
    pub(super) batch: &'a RecordBatch,
}

/// The image of a one-row batch of a per-image table (see `RowIndex`).
pub(super) fn one_image<'a>(batch: &'a RecordBatch, table: &str) -> Result<Image<'a>> {
    if batch.num_rows() != 1 {
        return Err(StageError::Input(format!(
            "table `{table}`: expected one image's row, got {}",
            batch.num_rows()
        )));
    }
    let w = tables::get_prim::<UInt32Type>(batch, table, "width")?;
    let h = tables::get_prim::<UInt32Type>(batch, table, "height")?;
    Ok(Image {
        width: w[0] as usize,
        height: h[0] as usize,
        row: 0,
        batch,
    })
}

pub(super) fn map_u8<'a>(img: &Image<'a>, table: &str, col: &str) -> Result<&'a [u8]> {
    let v = tables::get_list::<UInt8Type>(img.batch, table, col)?.row(img.row);
    check_size(v.len(), img, table, col)?;
    Ok(v)
}

pub(super) fn map_u16<'a>(img: &Image<'a>, table: &str, col: &str) -> Result<&'a [u16]> {
    let v = tables::get_list::<UInt16Type>(img.batch, table, col)?.row(img.row);
    check_size(v.len(), img, table, col)?;
    Ok(v)
}

pub(super) fn map_f32<'a>(img: &Image<'a>, table: &str, col: &str) -> Result<&'a [f32]> {
    let v = tables::get_list::<Float32Type>(img.batch, table, col)?.row(img.row);
    check_size(v.len(), img, table, col)?;
    Ok(v)
}

pub(super) fn check_size(len: usize, img: &Image, table: &str, col: &str) -> Result<()> {
    if len != img.width * img.height {
        return Err(StageError::Input(format!(
            "table `{table}` row {} column `{col}` has {len} values, expected {}x{}",
            img.row, img.width, img.height
        )));
    }
    Ok(())
}
