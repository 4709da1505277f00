//! `pipe export review`: the review maps as PNGs in the label layout, and its tables as CSV.

use std::path::{Path, PathBuf};

use arrow::datatypes::{UInt16Type, UInt32Type, UInt8Type};

use crate::stage::{Result, StageError, TableSet};
use crate::{pngio, tables};

/// Under `dir`: `score/` (8-bit, probability * 255), `reason/` (8-bit reason codes, 0 not
/// flagged) and `regions/` (16-bit region index of `regions.csv`), named as the label maps are
/// (`{seq}_{frame}.png`, right camera `_01`); `queue.csv`, `regions.csv` and `frames.csv`.
pub fn export(t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
    const M: &str = "review_maps";
    let maps = t
        .get(M)
        .ok_or_else(|| StageError::Input(format!("missing table `{M}`")))?;
    let mut files = Vec::new();
    for r in 0..maps.num_rows() {
        let b = maps.row(r)?;
        let seq = tables::get_strings(&b, M, "sequence")?.value(0).to_string();
        let frame = tables::get_prim::<UInt32Type>(&b, M, "frame")?[0];
        let camera = tables::get_prim::<UInt8Type>(&b, M, "camera")?[0];
        let w = tables::get_prim::<UInt32Type>(&b, M, "width")?[0];
        let h = tables::get_prim::<UInt32Type>(&b, M, "height")?[0];
        let name = pngio::label_file_name(&seq, frame, camera);
        let score: Vec<u8> = tables::get_list::<UInt16Type>(&b, M, "score")?
            .row(0)
            .iter()
            .map(|&s| ((s as u32 * 255 + 32767) / 65535) as u8)
            .collect();
        let (reason, region) = (
            tables::get_list::<UInt8Type>(&b, M, "reason")?.row(0),
            tables::get_list::<UInt16Type>(&b, M, "region")?.row(0),
        );
        let (s, why, reg) = (
            dir.join("score").join(&name),
            dir.join("reason").join(&name),
            dir.join("regions").join(&name),
        );
        pngio::write_gray8(&s, w, h, &score)?;
        pngio::write_gray8(&why, w, h, reason)?;
        pngio::write_gray16(&reg, w, h, region)?;
        files.extend([s, why, reg]);
    }
    for (table, file) in [
        ("review_queue", "queue.csv"),
        ("review_regions", "regions.csv"),
        ("review_frames", "frames.csv"),
    ] {
        let path = dir.join(file);
        tables::write_csv(t.table(table)?, &path)?;
        files.push(path);
    }
    Ok(files)
}
