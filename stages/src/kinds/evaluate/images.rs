//! One image's maps in a per-image table, checked against its size.

use std::collections::HashMap;

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

pub(super) fn index_images<'a>(
    batch: &'a RecordBatch,
    table: &str,
) -> Result<HashMap<(u32, u8), Image<'a>>> {
    let frames = tables::get_prim::<UInt32Type>(batch, table, "frame")?;
    let cams = tables::get_prim::<UInt8Type>(batch, table, "camera")?;
    let w = tables::get_prim::<UInt32Type>(batch, table, "width")?;
    let h = tables::get_prim::<UInt32Type>(batch, table, "height")?;
    Ok((0..batch.num_rows())
        .map(|r| {
            (
                (frames[r], cams[r]),
                Image {
                    width: w[r] as usize,
                    height: h[r] as usize,
                    row: r,
                    batch,
                },
            )
        })
        .collect())
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
