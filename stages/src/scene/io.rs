//! Helpers shared by the scene readers and writers: the scene tables' common facts and keys,
//! and file writing that names the path in its errors.

use std::path::{Path, PathBuf};

use arrow::datatypes::{Float64Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;
use glam::DVec3;

use crate::stage::{Result, StageError, Tables};
use crate::tables;

/// The scene-level facts of `scene_info`.
pub struct SceneInfo {
    pub name: String,
    pub sequence: String,
    pub origin: DVec3,
    pub baseline: f64,
}

pub fn scene_info(t: &Tables) -> Result<SceneInfo> {
    let s = table(t, "scene_info")?;
    if s.num_rows() != 1 {
        return Err(StageError::Input(format!(
            "table `scene_info` has {} rows, expected 1",
            s.num_rows()
        )));
    }
    let (o, _) = tables::get_fixed_list::<Float64Type>(s, "scene_info", "origin")?;
    Ok(SceneInfo {
        name: tables::get_strings(s, "scene_info", "name")?
            .value(0)
            .to_string(),
        sequence: tables::get_strings(s, "scene_info", "sequence")?
            .value(0)
            .to_string(),
        origin: DVec3::new(o[0], o[1], o[2]),
        baseline: tables::get_prim::<Float64Type>(s, "scene_info", "baseline")?[0],
    })
}

pub fn table<'a>(t: &'a Tables, name: &str) -> Result<&'a RecordBatch> {
    t.get(name)
        .ok_or_else(|| StageError::Input(format!("the scene has no table `{name}`")))
}

/// Keys (frame, camera, width, height) of a per-image table.
pub fn image_keys(b: &RecordBatch, name: &str) -> Result<Vec<(u32, u8, u32, u32)>> {
    let f = tables::get_prim::<UInt32Type>(b, name, "frame")?;
    let c = tables::get_prim::<UInt8Type>(b, name, "camera")?;
    let w = tables::get_prim::<UInt32Type>(b, name, "width")?;
    let h = tables::get_prim::<UInt32Type>(b, name, "height")?;
    Ok((0..b.num_rows())
        .map(|i| (f[i], c[i], w[i], h[i]))
        .collect())
}

pub fn io_err(path: &Path, e: impl std::fmt::Display) -> StageError {
    StageError::Failed(format!("writing {}: {e}", path.display()))
}

pub fn create_parent(path: &Path) -> Result<()> {
    if let Some(d) = path.parent() {
        std::fs::create_dir_all(d).map_err(|e| io_err(d, e))?;
    }
    Ok(())
}

pub fn write_bytes(path: PathBuf, bytes: &[u8], files: &mut Vec<PathBuf>) -> Result<()> {
    create_parent(&path)?;
    std::fs::write(&path, bytes).map_err(|e| io_err(&path, e))?;
    files.push(path);
    Ok(())
}

pub fn write_text(path: PathBuf, text: &str, files: &mut Vec<PathBuf>) -> Result<()> {
    write_bytes(path, text.as_bytes(), files)
}

pub fn write_png(
    path: PathBuf,
    w: u32,
    h: u32,
    color: image::ExtendedColorType,
    bytes: &[u8],
    files: &mut Vec<PathBuf>,
) -> Result<()> {
    create_parent(&path)?;
    image::save_buffer_with_format(&path, bytes, w, h, color, image::ImageFormat::Png)
        .map_err(|e| io_err(&path, e))?;
    files.push(path);
    Ok(())
}
