//! Pictures of label maps for people: PNG data URIs, panoptic, error and depth colourings.

use std::io::Cursor;

use base64::Engine as _;
use plotters::style::colors::colormaps::ViridisRGB;

use crate::labels;
use crate::stage::{Result, StageError};

/// `rgb` as an inline PNG (`data:` URI), scaled up `zoom` times (nearest neighbour).
pub fn png_data_uri(w: u32, h: u32, rgb: &[u8], zoom: u32) -> Result<String> {
    if rgb.len() != (w as usize) * (h as usize) * 3 {
        return Err(StageError::Input(format!(
            "{} bytes do not make a {w}x{h} RGB image",
            rgb.len()
        )));
    }
    let (zw, zh, zoomed) = zoom_rgb(w, h, rgb, zoom.max(1));
    let img = image::RgbImage::from_raw(zw, zh, zoomed).expect("sized above");
    let mut buf = Cursor::new(Vec::new());
    img.write_to(&mut buf, image::ImageFormat::Png)
        .map_err(|e| StageError::Failed(format!("encoding PNG: {e}")))?;
    Ok(format!(
        "data:image/png;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(buf.into_inner())
    ))
}

/// `rgb` (`w` x `h`) with every pixel made a `zoom` x `zoom` block: nearest-neighbour scaling
/// by an integer factor, a row built once and copied.
fn zoom_rgb(w: u32, h: u32, rgb: &[u8], zoom: u32) -> (u32, u32, Vec<u8>) {
    let z = zoom as usize;
    if z == 1 {
        return (w, h, rgb.to_vec());
    }
    let row_bytes = w as usize * 3;
    let mut out = Vec::with_capacity(rgb.len() * z * z);
    for row in rgb.chunks_exact(row_bytes) {
        let start = out.len();
        for px in row.chunks_exact(3) {
            for _ in 0..z {
                out.extend_from_slice(px);
            }
        }
        for _ in 1..z {
            out.extend_from_within(start..start + row_bytes * z);
        }
    }
    (w * zoom, h * zoom, out)
}

/// Panoptic colours: the class colour, shifted per instance so neighbouring things differ.
pub fn panoptic_colors(instance: &[u16]) -> Vec<u8> {
    instance
        .iter()
        .flat_map(|&v| {
            let class = (v as u32 / labels::INSTANCE_FACTOR) as u8;
            let inst = v as u32 % labels::INSTANCE_FACTOR;
            let base = labels::color(class);
            if inst == 0 {
                return base;
            }
            let h = inst.wrapping_mul(2654435761);
            let jitter =
                |c: u8, s: u32| (c as i32 + ((h >> s) & 0x7f) as i32 - 64).clamp(0, 255) as u8;
            [jitter(base[0], 0), jitter(base[1], 8), jitter(base[2], 16)]
        })
        .collect()
}

/// Green where the prediction equals GT, red where it differs, black where GT is void.
pub fn error_colors(pred: &[u8], gt: &[u8]) -> Vec<u8> {
    pred.iter()
        .zip(gt)
        .flat_map(|(&p, &g)| match (g, p == g) {
            (0, _) => [0, 0, 0],
            (_, true) => [40, 160, 60],
            (_, false) => [220, 40, 40],
        })
        .collect()
}

/// Depth as colour: near = yellow, far = dark purple, no depth = black.
pub fn depth_colors(depth: &[f32], range: f32) -> Vec<u8> {
    depth
        .iter()
        .flat_map(|&d| {
            if !(d.is_finite() && d > 0.0) {
                return [0, 0, 0];
            }
            let c = ViridisRGB::get_color((1.0 - (d / range).clamp(0.0, 1.0)) as f64);
            [c.0, c.1, c.2]
        })
        .collect()
}

/// Depth error at LiDAR pixels: green where the rendered depth is within a factor 1.25 of the
/// LiDAR depth, shading through yellow to red at a factor of 2 or more (too near or too far
/// alike), magenta where no depth was rendered; black where there is no LiDAR point.
pub fn depth_error_colors(pred: &[f32], lidar: &[f32]) -> Vec<u8> {
    pred.iter()
        .zip(lidar)
        .flat_map(|(&d, &g)| {
            if !(g.is_finite() && g > 0.0) {
                return [0, 0, 0];
            }
            if !(d.is_finite() && d > 0.0) {
                return [220, 0, 220];
            }
            let ratio = (d / g).max(g / d);
            if ratio < 1.25 {
                return [40, 170, 60];
            }
            // 1.25 -> yellow, 2 and beyond -> red.
            let k = ((ratio.log2() - 1.25f32.log2()) / (1.0 - 1.25f32.log2())).clamp(0.0, 1.0);
            [230, (220.0 * (1.0 - k)) as u8, 30]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zooming_makes_each_pixel_a_block_as_the_image_crate_does() {
        let (w, h) = (7u32, 5u32);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i * 37 % 251) as u8).collect();
        for zoom in [1u32, 2, 3] {
            let (zw, zh, z) = zoom_rgb(w, h, &rgb, zoom);
            assert_eq!((zw, zh), (w * zoom, h * zoom));
            for y in 0..zh {
                for x in 0..zw {
                    let o = ((y * zw + x) * 3) as usize;
                    let i = (((y / zoom) * w + x / zoom) * 3) as usize;
                    assert_eq!(z[o..o + 3], rgb[i..i + 3], "zoom {zoom} at {x},{y}");
                }
            }
            let img = image::RgbImage::from_raw(w, h, rgb.clone()).unwrap();
            let theirs =
                image::imageops::resize(&img, zw, zh, image::imageops::FilterType::Nearest);
            assert_eq!(theirs.into_raw(), z, "zoom {zoom}");
        }
        assert!(png_data_uri(w, h, &rgb[1..], 2).is_err());
    }

    #[test]
    fn depth_error_colours_by_ratio_either_way() {
        let c = depth_error_colors(
            &[10.0, 5.0, 10.0, 0.0, 12.0, 20.0, 5.0],
            &[0.0, 5.5, 40.0, 8.0, 10.0, 10.0, 10.0],
        );
        assert_eq!(&c[0..3], &[0, 0, 0], "no LiDAR");
        assert_eq!(&c[3..6], &[40, 170, 60], "within 1.25");
        assert_eq!(&c[6..9], &[230, 0, 30], "4x too near: red");
        assert_eq!(&c[9..12], &[220, 0, 220], "no depth rendered");
        assert_eq!(&c[12..15], &[40, 170, 60], "1.2x too far");
        // 2x too far and 2x too near look the same.
        assert_eq!(&c[15..18], &[230, 0, 30]);
        assert_eq!(&c[15..18], &c[18..21]);
    }
}
