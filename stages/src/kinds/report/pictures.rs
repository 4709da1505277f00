//! The report's rows of pictures: per image RGB, pseudo labels, ours, GT, error, panoptic and
//! depth, read one pictured image at a time.

use std::{collections::BTreeMap, fmt::Write as _};

use arrow::{
    datatypes::{Float32Type, UInt16Type, UInt32Type, UInt8Type},
    record_batch::RecordBatch,
};

use rayon::prelude::*;

use super::{spread, Page, ReportParams};
use crate::labels;
use crate::report::{
    depth_colors, depth_error_colors, error_colors, panoptic_colors, png_data_uri,
};
use crate::stage::{Inputs, Progress, Result, Table};
use crate::tables;

/// A per-image table, read one pictured image at a time.
pub(super) struct Maps<'a> {
    table: &'a Table,
    pub(super) index: BTreeMap<(u32, u8), usize>,
}

impl<'a> Maps<'a> {
    pub(super) fn new(table: &'a Table) -> Result<Self> {
        let keys = table.columns(&["frame", "camera"])?;
        Ok(Maps {
            index: tables::frame_camera_index(&keys, table.name())?,
            table,
        })
    }

    /// The row of image `key`, if the table has one.
    pub(super) fn get(&self, key: (u32, u8)) -> Result<Option<Row>> {
        self.index
            .get(&key)
            .map(|&r| {
                Ok(Row {
                    batch: self.table.row(r)?,
                    table: self.table.name().to_string(),
                })
            })
            .transpose()
    }
}

/// One image's row of a per-image table.
pub(super) struct Row {
    batch: RecordBatch,
    table: String,
}

impl Row {
    pub(super) fn u8(&self, col: &str) -> Result<&[u8]> {
        Ok(tables::get_list::<UInt8Type>(&self.batch, &self.table, col)?.row(0))
    }
    pub(super) fn u16(&self, col: &str) -> Result<&[u16]> {
        Ok(tables::get_list::<UInt16Type>(&self.batch, &self.table, col)?.row(0))
    }
    pub(super) fn f32(&self, col: &str) -> Result<&[f32]> {
        Ok(tables::get_list::<Float32Type>(&self.batch, &self.table, col)?.row(0))
    }
    pub(super) fn bytes(&self, col: &str) -> Result<&[u8]> {
        Ok(tables::get_binary(&self.batch, &self.table, col)?.value(0))
    }
    pub(super) fn size(&self) -> Result<(u32, u32)> {
        let w = tables::get_prim::<UInt32Type>(&self.batch, &self.table, "width")?;
        let h = tables::get_prim::<UInt32Type>(&self.batch, &self.table, "height")?;
        Ok((w[0], h[0]))
    }
}

/// The per-image tables a row of pictures reads.
pub(super) struct Pictured<'a> {
    images: Maps<'a>,
    pseudo: Maps<'a>,
    pub(super) maps: Maps<'a>,
    pub(super) gt: Maps<'a>,
    lidar: Maps<'a>,
}

impl<'a> Pictured<'a> {
    pub(super) fn new(inputs: &'a Inputs) -> Result<Self> {
        Ok(Self {
            images: Maps::new(inputs.stored("scene", "images")?)?,
            pseudo: Maps::new(inputs.stored("scene", "pseudo_labels")?)?,
            maps: Maps::new(inputs.stored("render", "label_maps")?)?,
            gt: Maps::new(inputs.stored("evaluate", "eval_gt")?)?,
            lidar: Maps::new(inputs.stored("scene", "lidar_depth")?)?,
        })
    }

    /// The caption of the row's columns, in order.
    pub(super) fn captions(has_gt: bool) -> &'static str {
        if has_gt {
            "RGB · pseudo labels (2D input) · ours (learned semantic field) · ground truth · error map \
             (green correct, red wrong, black void) · panoptic (instances shaded) · rendered depth \
             (yellow near, purple far) · depth error at LiDAR points (green within a factor 1.25, \
             yellow to red up to a factor 2, magenta no depth rendered)"
        } else {
            "RGB · pseudo labels (2D input) · ours (learned semantic field) · panoptic (instances \
             shaded) · rendered depth (yellow near, purple far)"
        }
    }

    /// Image `key`'s row (`<tr>`) of pictures, GT and error columns where `has_gt`; nothing
    /// where the image has neither GT nor rendered maps.
    pub(super) fn row(
        &self,
        key: (u32, u8),
        has_gt: bool,
        p: &ReportParams,
        html: &mut String,
    ) -> Result<()> {
        let m = self.maps.get(key)?;
        let g = self.gt.get(key)?;
        // The size of the pictured image, from its GT or else its rendered maps.
        let Some((w, h)) = g.as_ref().or(m.as_ref()).map(Row::size).transpose()? else {
            return Ok(());
        };
        let mut cells: Vec<(&str, Option<Vec<u8>>)> = vec![
            (
                "RGB",
                self.images
                    .get(key)?
                    .map(|r| r.bytes("rgb").map(<[u8]>::to_vec))
                    .transpose()?,
            ),
            (
                "pseudo labels",
                self.pseudo
                    .get(key)?
                    .map(|r| r.u8("labels").map(crate::pngio::colorize))
                    .transpose()?,
            ),
        ];
        let ours = m.as_ref().map(|m| m.u8("semantic")).transpose()?;
        cells.push(("ours", ours.map(crate::pngio::colorize)));
        if has_gt {
            // Rendered images without GT (a fisheye camera not evaluated) say "n/a".
            let gsem = g.as_ref().map(|g| g.u8("semantic")).transpose()?;
            cells.push(("ground truth", gsem.map(crate::pngio::colorize)));
            cells.push((
                "error",
                ours.zip(gsem).map(|(o, gsem)| error_colors(o, gsem)),
            ));
        }
        cells.push((
            "panoptic",
            m.as_ref()
                .map(|m| m.u16("instance"))
                .transpose()?
                .map(panoptic_colors),
        ));
        let depth = m.as_ref().map(|m| m.f32("depth")).transpose()?;
        cells.push(("depth", depth.map(|d| depth_colors(d, p.depth_range))));
        if has_gt {
            let l = self.lidar.get(key)?;
            let l = l.as_ref().map(|l| l.f32("depth")).transpose()?;
            cells.push((
                "depth error",
                depth.zip(l).map(|(d, l)| depth_error_colors(d, l)),
            ));
        }
        let _ = write!(
            html,
            "<tr><td class=\"cap\">frame {}<br>cam {}</td>",
            key.0, key.1
        );
        // The pictures encoded in parallel: PNG encoding is most of the report's time.
        let uris: Vec<Option<String>> = cells
            .par_iter()
            .map(|(_, rgb)| match rgb {
                Some(rgb) if rgb.len() == (w * h * 3) as usize => {
                    png_data_uri(w, h, rgb, p.zoom).map(Some)
                }
                _ => Ok(None),
            })
            .collect::<Result<_>>()?;
        for ((cap, _), uri) in cells.iter().zip(uris) {
            match uri {
                Some(uri) => {
                    let _ = write!(html, "<td><img src=\"{uri}\" alt=\"{cap}\"><span class=\"cap\">{cap}</span></td>");
                }
                None => {
                    let _ = write!(html, "<td class=\"cap\">{cap}: n/a</td>");
                }
            }
        }
        html.push_str("</tr>");
        Ok(())
    }
}

impl Page {
    /// Per evaluation frame a row of pictures; without GT, the same for rendered frames spread
    /// over the sequence (no GT and error columns).
    pub(super) fn pictures(
        &mut self,
        p: &ReportParams,
        inputs: &Inputs,
        present: &[u8],
        progress: &dyn Progress,
    ) -> Result<()> {
        let html = &mut self.html;
        let pictured = Pictured::new(inputs)?;
        let has_gt = !pictured.gt.index.is_empty();
        let mut keys: Vec<(u32, u8)> = if has_gt {
            pictured
                .gt
                .index
                .keys()
                .copied()
                .take(p.max_frames)
                .collect()
        } else {
            let all: Vec<(u32, u8)> = pictured.maps.index.keys().copied().collect();
            spread(&all, p.max_frames)
        };
        // Fisheye cameras rendered but not pictured (not evaluated, or past `max_frames`): one
        // frame of each, the middle one, so the report shows them too.
        for camera in [2u8, 3] {
            if keys.iter().any(|k| k.1 == camera) {
                continue;
            }
            let theirs: Vec<(u32, u8)> = pictured
                .maps
                .index
                .keys()
                .copied()
                .filter(|k| k.1 == camera)
                .collect();
            if let Some(&k) = theirs.get(theirs.len() / 2) {
                keys.push(k);
            }
        }
        let (title, what) = if has_gt {
            ("Evaluation frames", "Per frame")
        } else {
            ("Rendered frames (no GT)", "Frames spread over the sequence")
        };
        let _ = write!(
            html,
            "<h2>{title}</h2><p class=\"cap\">{what}: {}.</p><div class=\"legend\">",
            Pictured::captions(has_gt)
        );
        for &id in present {
            let c = labels::color(id);
            let _ = write!(
                html,
                "<span><i style=\"background:rgb({},{},{})\"></i>{}</span>",
                c[0],
                c[1],
                c[2],
                labels::by_id(id).map_or("?", |l| l.name)
            );
        }
        html.push_str("</div><table class=\"frames\">");
        for (n, key) in keys.iter().enumerate() {
            progress.update(n as u64, keys.len() as u64, "pictures");
            pictured.row(*key, has_gt, p, html)?;
        }
        Ok(())
    }
}
