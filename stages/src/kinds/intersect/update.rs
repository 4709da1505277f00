//! Updating the plan after an edit of the primitives: in the images a ray of which can meet a
//! changed primitive (its old or its new extent) the pixels whose ray meets one are traced
//! again; every other pixel, and every other image's row, is the previous one, its primitive
//! ids renumbered where a removal shifted them. The result equals a run from scratch.

use arrow::{array::ArrayRef, datatypes::UInt32Type, record_batch::RecordBatch};

use crate::geometry::{
    self,
    changes::{pixels_meeting, ChangeView},
    Bvh, CameraRow, PrimitiveChanges,
};
use crate::intervals::{plan_image, plan_row, ImagePlan, IntersectParams};
use crate::kinds::edited::Edited;
use crate::stage::{
    Changed, Inputs, Previous, Progress, Result, StageError, Table, Tables, Updated,
};
use crate::tables;
use rayon::prelude::*;

/// Why the previous plan cannot be updated: anything but the primitives changed.
pub(super) fn can_update(changed: &Changed) -> std::result::Result<(), String> {
    let other: Vec<&String> = changed
        .values()
        .flatten()
        .filter(|t| *t != "primitives")
        .collect();
    match other.first() {
        None => Ok(()),
        Some(t) => Err(format!("the scene's `{t}` changed")),
    }
}

/// The selected camera rows, as a run from scratch plans them.
pub(super) fn selected_rows<'a>(
    rows: &'a [CameraRow],
    p: &IntersectParams,
) -> Result<Vec<&'a CameraRow>> {
    let rows: Vec<&CameraRow> = rows
        .iter()
        .filter(|r| p.cameras.is_empty() || p.cameras.contains(&r.camera))
        .collect();
    if rows.is_empty() {
        return Err(StageError::Input(if p.cameras.is_empty() {
            "the scene's `cameras` table has no image".to_string()
        } else {
            format!(
                "no image of the scene's `cameras` table has a camera id in {:?}",
                p.cameras
            )
        }));
    }
    Ok(rows)
}

pub(super) fn update(
    p: &IntersectParams,
    inputs: &Inputs,
    previous: &Previous,
    progress: &dyn Progress,
) -> Result<Updated> {
    let edited = Edited::read(previous, inputs)?;
    let extents = edited.extents();
    let mut view = ChangeView::new(&extents);
    let (changes, prims) = (&edited.changes, &edited.new);
    // Removing or adding keeps the ids in order; a reordered table may swap tied entries.
    let in_order = changes
        .old_to_new
        .iter()
        .flatten()
        .is_sorted_by(|a, b| a < b);
    let rows = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
    let rows = selected_rows(&rows, p)?;
    let before = previous.output("ray_intervals")?;
    let before_rows = before.image_rows()?;
    let bvh = Bvh::build(prims);
    let mut out = inputs.writer("ray_intervals")?;
    let total = rows.len();
    let (mut redone, mut pixels, mut traced) = (0usize, 0usize, 0usize);
    let sees: Vec<bool> = rows.iter().map(|r| view.seen_by(&r.cam, p.far)).collect();
    // An image that cannot see the change keeps its previous row (renumbered); in one that
    // can, the pixels whose ray meets a changed extent are traced again.
    let one = |(row, &sees_change): (&&CameraRow, &bool)| -> Result<Image> {
        let Some(&r) = before_rows.get(&(row.frame, row.camera)) else {
            let plan = plan_image(prims, &bvh, &row.cam, p);
            let n = plan.len();
            return Ok(Image::Planned(plan_row(row, plan, p)?, Some(n)));
        };
        if !sees_change && in_order {
            if let Some(prim) = renumbered(before, r, changes)? {
                return Ok(Image::Kept(r, prim));
            }
        }
        let n = (row.cam.width * row.cam.height) as usize;
        let old = ImagePlan::whole_from_row(&before.row(r)?, 0, n, edited.old.len())?;
        let meeting = if sees_change {
            pixels_meeting(&row.cam, &extents, p.far)
        } else {
            Vec::new()
        };
        let plan = old
            .replanned(&meeting, &changes.old_to_new, prims, &bvh, &row.cam, p)
            .unwrap_or_else(|| plan_image(prims, &bvh, &row.cam, p));
        Ok(Image::Planned(
            plan_row(row, plan, p)?,
            sees_change.then_some(meeting.len()),
        ))
    };
    // A few images at a time in parallel, written in order; a kept row is copied as stored.
    const AT_ONCE: usize = 4;
    for (c, (chunk, sees)) in rows.chunks(AT_ONCE).zip(sees.chunks(AT_ONCE)).enumerate() {
        let first = &chunk[0];
        progress.update(
            (c * AT_ONCE) as u64,
            total as u64,
            &format!("frame {} camera {}", first.frame, first.camera),
        );
        let done: Vec<Result<Image>> = chunk.par_iter().zip(sees.par_iter()).map(one).collect();
        for (d, row) in done.into_iter().zip(chunk) {
            match d? {
                Image::Kept(r, None) => out.write_from(before, r, &[])?,
                Image::Kept(r, Some(prim)) => out.write_from(before, r, &[("prim", prim)])?,
                Image::Planned(batch, again) => {
                    if let Some(m) = again {
                        redone += 1;
                        traced += m;
                        pixels += (row.cam.width * row.cam.height) as usize;
                    }
                    out.write(batch)?;
                }
            }
        }
    }
    progress.update(total as u64, total as u64, "done");
    let mut tables = Tables::new();
    out.finish_into(&mut tables)?;
    let n_changed = changes.removed.len().max(changes.added.len());
    Ok(Updated {
        tables,
        redone: format!(
            "{redone} of {total} images intersected again, {:.1} % of their pixels ({n_changed} primitive{} changed)",
            100.0 * traced as f64 / pixels.max(1) as f64,
            if n_changed == 1 { "" } else { "s" }
        ),
    })
}

/// What becomes of one image's row.
enum Image {
    /// Previous row `r`, with this `prim` column where a removal renumbered its ids.
    Kept(usize, Option<ArrayRef>),
    /// Planned (again): the row, and the pixels traced again where the image sees the change.
    Planned(RecordBatch, Option<usize>),
}

/// What previous row `r` (an image that sees no change) keeps: `Some(None)` every id as it was,
/// `Some(Some(prim))` its `prim` column renumbered; `None` where it names a primitive that
/// changed after all (then the image is planned again).
fn renumbered(
    before: &Table,
    r: usize,
    changes: &PrimitiveChanges,
) -> Result<Option<Option<ArrayRef>>> {
    if !changes.renumbers() {
        return Ok(Some(None));
    }
    let row = before.rows(r..r + 1, Some(&["prim"]))?;
    let ids = tables::get_list::<UInt32Type>(&row, "ray_intervals", "prim")?.row(0);
    let mut mapped = Vec::with_capacity(ids.len());
    for &id in ids {
        match changes.old_to_new.get(id as usize).copied().flatten() {
            Some(n) => mapped.push(n),
            None => return Ok(None),
        }
    }
    Ok(Some(Some(tables::list::<UInt32Type>([mapped]))))
}
