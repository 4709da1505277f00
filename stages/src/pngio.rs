//! PNG files in the formats the ecosystem reads: 8-bit label-id maps and 16-bit instance maps
//! (KITTI-360 `semantic/` and `instance/`), 16-bit depth (metres * 256), colour images, and the
//! KITTI-360-style file names.

use std::path::Path;

use image::{ImageBuffer, Luma, Rgb};

use crate::{labels, Result, StageError};

/// `<seq>_<frame:010>.png`, with `_01` before the extension for the right camera.
pub fn label_file_name(sequence: &str, frame: u32, camera: u8) -> String {
    match camera {
        0 => format!("{sequence}_{frame:010}.png"),
        c => format!("{sequence}_{frame:010}_{c:02}.png"),
    }
}

fn save<P, C>(path: &Path, img: ImageBuffer<P, C>) -> Result<()>
where
    P: image::Pixel + image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
    C: std::ops::Deref<Target = [P::Subpixel]>,
{
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)
            .map_err(|e| StageError::Failed(format!("creating {}: {e}", dir.display())))?;
    }
    img.save(path)
        .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))
}

fn size_error(path: &Path, w: u32, h: u32, len: usize) -> StageError {
    StageError::Failed(format!(
        "{}: {len} values do not make a {w}x{h} image",
        path.display()
    ))
}

/// An 8-bit single-channel PNG (label ids).
pub fn write_gray8(path: &Path, w: u32, h: u32, data: &[u8]) -> Result<()> {
    let img = ImageBuffer::<Luma<u8>, _>::from_raw(w, h, data.to_vec())
        .ok_or_else(|| size_error(path, w, h, data.len()))?;
    save(path, img)
}

/// A 16-bit single-channel PNG (instance ids, depth * 256).
pub fn write_gray16(path: &Path, w: u32, h: u32, data: &[u16]) -> Result<()> {
    let img = ImageBuffer::<Luma<u16>, _>::from_raw(w, h, data.to_vec())
        .ok_or_else(|| size_error(path, w, h, data.len()))?;
    save(path, img)
}

/// An 8-bit RGB PNG from `w*h*3` bytes.
pub fn write_rgb8(path: &Path, w: u32, h: u32, data: &[u8]) -> Result<()> {
    let img = ImageBuffer::<Rgb<u8>, _>::from_raw(w, h, data.to_vec())
        .ok_or_else(|| size_error(path, w, h, data.len()))?;
    save(path, img)
}

/// KITTI-style 16-bit depth: metres * 256, 0 = no depth; saturates at 255.99 m.
pub fn depth_to_u16(depth: &[f32]) -> Vec<u16> {
    depth
        .iter()
        .map(|&d| {
            if d.is_finite() && d > 0.0 {
                (d * 256.0).round().min(65535.0) as u16
            } else {
                0
            }
        })
        .collect()
}

/// Label ids -> palette colours (`w*h*3` bytes).
pub fn colorize(labels_map: &[u8]) -> Vec<u8> {
    labels_map.iter().flat_map(|&l| labels::color(l)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_follow_the_kitti_layout() {
        assert_eq!(label_file_name("seq", 42, 0), "seq_0000000042.png");
        assert_eq!(label_file_name("seq", 42, 1), "seq_0000000042_01.png");
    }

    #[test]
    fn png_round_trip_keeps_16_bit_values() {
        let dir = std::env::temp_dir().join(format!("pngio-{}", std::process::id()));
        let p = dir.join("x.png");
        write_gray16(&p, 3, 2, &[0, 1, 26001, 65535, 7000, 41003]).unwrap();
        let img = image::open(&p).unwrap().into_luma16();
        assert_eq!(img.into_raw(), vec![0, 1, 26001, 65535, 7000, 41003]);
        assert!(write_gray8(&p, 3, 3, &[0; 4]).is_err());
        assert_eq!(
            depth_to_u16(&[1.0, 0.0, f32::NAN, 300.0]),
            vec![256, 0, 0, 65535]
        );
        std::fs::remove_dir_all(dir).unwrap();
    }
}
