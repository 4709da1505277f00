//! Colour previews of a scene for people: per left frame one PNG stacking, top to bottom, the
//! RGB image, the GT semantic colours, the pseudo-label colours and the label of the first
//! bounding primitive each pixel ray enters (sky where none), enlarged with nearest-neighbour
//! sampling so that small images are readable.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use arrow::datatypes::UInt8Type;

use super::io::{image_keys, table, write_png};
use crate::geometry::{cameras_from_table, primitives_from_table, Bvh};
use crate::labels::{self, SKY, UNLABELED};
use crate::{tables, Result, Tables};

/// The label map of the first primitive hit per pixel (sky where no primitive is hit).
pub fn first_primitive_labels(
    prims: &[crate::geometry::Primitive],
    bvh: &Bvh,
    cam: &crate::geometry::Camera,
) -> Vec<u8> {
    let mut out = Vec::with_capacity((cam.width * cam.height) as usize);
    for y in 0..cam.height {
        for x in 0..cam.width {
            out.push(cam.pixel_ray(x, y).map_or(UNLABELED, |ray| {
                bvh.first_hit(prims, &ray, 0.0, 1.0e4)
                    .map_or(SKY, |h| prims[h.prim as usize].label)
            }));
        }
    }
    out
}

fn colorize(labels_: &[u8]) -> Vec<u8> {
    labels_.iter().flat_map(|&l| labels::color(l)).collect()
}

/// Writes `dir/<frame:010>.png` for every left image; returns the files.
pub fn write(t: &Tables, dir: &Path) -> Result<Vec<PathBuf>> {
    let cams = cameras_from_table(table(t, "cameras")?)?;
    let prims = primitives_from_table(table(t, "primitives")?)?;
    let bvh = Bvh::build(&prims);
    let images = table(t, "images")?;
    let rgb = tables::get_binary(images, "images", "rgb")?;
    let rows = |name: &str, col: &str| -> Result<BTreeMap<(u32, u8), Vec<u8>>> {
        let b = table(t, name)?;
        let c = tables::get_list::<UInt8Type>(b, name, col)?;
        Ok(image_keys(b, name)?
            .into_iter()
            .enumerate()
            .map(|(i, k)| ((k.0, k.1), c.row(i).to_vec()))
            .collect())
    };
    let gt = rows("gt_semantic", "labels")?;
    let pseudo = rows("pseudo_labels", "labels")?;
    let mut files = Vec::new();
    for (i, (f, cam, w, h)) in image_keys(images, "images")?.into_iter().enumerate() {
        if cam != 0 {
            continue;
        }
        let Some(row) = cams.iter().find(|r| r.frame == f && r.camera == cam) else {
            continue;
        };
        let fixed = first_primitive_labels(&prims, &bvh, &row.cam);
        let blank = vec![0u8; (w * h) as usize];
        let panels = [
            rgb.value(i).to_vec(),
            colorize(gt.get(&(f, cam)).unwrap_or(&blank)),
            colorize(pseudo.get(&(f, cam)).unwrap_or(&blank)),
            colorize(&fixed),
        ];
        let k = (704 / w.max(1)).max(1); // enlarge small images to ~704 px wide
        let (ow, oh) = (w * k, h * k * panels.len() as u32);
        let mut out = vec![0u8; (ow * oh * 3) as usize];
        for (pi, panel) in panels.iter().enumerate() {
            for y in 0..h * k {
                for x in 0..ow {
                    let src = (((y / k) * w + x / k) * 3) as usize;
                    let dst = ((((pi as u32 * h * k) + y) * ow + x) * 3) as usize;
                    out[dst..dst + 3].copy_from_slice(&panel[src..src + 3]);
                }
            }
        }
        write_png(
            dir.join(format!("{f:010}.png")),
            ow,
            oh,
            image::ExtendedColorType::Rgb8,
            &out,
            &mut files,
        )?;
    }
    Ok(files)
}
