//! Rendering again after an edit of the primitives: an image no changed primitive (old or new
//! extent) can appear in keeps its previous row; in the others only the coarse-grid cells
//! holding a pixel whose ray meets a changed primitive are rendered again, with the updated
//! field, and every other pixel keeps its previous labels. Elsewhere the updated field differs
//! from the previous one only by the drift of shared weights, which would move labels the edit
//! did not touch.

use super::images::{render_all, Previously};
use super::params::RenderParams;
use crate::geometry::{changes::ChangeView, Primitive};
use crate::kinds::edited::Edited;
use crate::sampling::PrimInfo;
use crate::stage::{Changed, Inputs, Lineage, Previous, Progress, Result, Updated};

/// The previous maps can be updated when only the primitives, and so the plan and the field,
/// changed: the plan made as before, the field updated from the one the maps were rendered with.
pub(super) fn can_update(changed: &Changed, lineage: &Lineage) -> std::result::Result<(), String> {
    if changed.contains_key("rays") && !lineage.same_recipe("rays") {
        return Err("the plan was made with other parameters".into());
    }
    if changed.contains_key("train") && !lineage.descends("train") {
        return Err("the field was trained anew, not updated".into());
    }
    for (slot, tables) in changed {
        for t in tables {
            if !matches!(
                (slot.as_str(), t.as_str()),
                ("scene", "primitives") | ("rays", _) | ("train", _)
            ) {
                return Err(format!("the input `{slot}`.{t} changed"));
            }
        }
    }
    Ok(())
}

/// Why the previous maps cannot be kept anywhere, though the field was updated.
fn render_whole(old: &[Primitive], new: &[Primitive]) -> Option<&'static str> {
    if PrimInfo::of(old).classes != PrimInfo::of(new).classes {
        return Some("the scene's classes changed");
    }
    None
}

pub(super) fn update(
    p: &RenderParams,
    inputs: &Inputs,
    previous: &Previous,
    progress: &dyn Progress,
) -> Result<Updated> {
    let edited = Edited::read(previous, inputs)?;
    if let Some(why) = render_whole(&edited.old, &edited.new) {
        let (tables, _) = render_all(p, inputs, progress, None)?;
        return Ok(Updated {
            tables,
            redone: format!("every image rendered again: {why}"),
        });
    }
    let changed = edited.extents();
    let maps = previous.output("label_maps")?;
    let previously = Previously {
        maps,
        rows: maps.image_rows()?,
        view: ChangeView::new(&changed),
        changed,
    };
    let (tables, c) = render_all(p, inputs, progress, Some(previously))?;
    Ok(Updated {
        tables,
        redone: format!(
            "{} of {} images rendered again, {:.1} % of their pixels",
            c.images_rendered,
            c.images,
            100.0 * c.pixels_rendered as f64 / c.pixels.max(1) as f64
        ),
    })
}
