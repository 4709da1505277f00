//! Scripted edits of the primitives (`scene.edits`): what a labelling team does to its boxes
//! between two runs (reclassify, move, turn, resize, delete), written in the pipeline file for
//! scripts and benches. Editing the primitives file (`data_3d_bboxes`) does the same by hand.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use glam::{DAffine3, DVec3};

use crate::geometry::Primitive;
use crate::labels;
use crate::stage::{Result, StageError};

/// One edit of one primitive. Ids are rows of the scene's `primitives` table without edits.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Edit {
    /// The primitive: its id (row of the unedited scene's `primitives` table).
    pub primitive: u32,
    /// New class: a KITTI-360 label name (`caravan`) or id.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub class: Option<String>,
    /// New instance number (1..999 for things, 0 for stuff).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub instance: Option<u32>,
    /// Moves it by these metres along the scene's x, y, z.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub translate: Option<[f64; 3]>,
    /// Turns it by these degrees about the vertical through its local origin (a box's centre).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rotate_deg: Option<f64>,
    /// Scales it by these factors along its own axes, about its local origin.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scale: Option<[f64; 3]>,
    /// Deletes it; the ids after it shift down by one, as when a box is removed from the file.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub remove: bool,
}

/// The label id a class name or id stands for.
fn class_id(name: &str) -> Option<u8> {
    match name.trim().parse::<u8>() {
        Ok(id) => labels::by_id(id).map(|l| l.id),
        Err(_) => labels::by_name(name.trim()).map(|l| l.id),
    }
}

/// Checks every edit against a scene of `count` primitives: errors name `edits[i].field`.
pub fn check(edits: &[Edit], count: Option<usize>) -> Result<()> {
    let bad = |i: usize, field: &str, why: String| {
        Err(StageError::Params(format!("`edits[{i}].{field}`: {why}")))
    };
    for (i, e) in edits.iter().enumerate() {
        if let Some(n) = count {
            if e.primitive as usize >= n {
                return bad(
                    i,
                    "primitive",
                    format!(
                        "{} is not a primitive of the scene (it has {n})",
                        e.primitive
                    ),
                );
            }
        }
        if let Some(c) = &e.class {
            if class_id(c).is_none() {
                return bad(
                    i,
                    "class",
                    format!("unknown class `{c}` (a KITTI-360 label name or id)"),
                );
            }
        }
        if let Some(t) = e.translate {
            if !t.iter().all(|x| x.is_finite()) {
                return bad(i, "translate", format!("{t:?} must be finite metres"));
            }
        }
        if let Some(r) = e.rotate_deg {
            if !r.is_finite() {
                return bad(i, "rotate_deg", format!("{r} must be finite"));
            }
        }
        if let Some(s) = e.scale {
            if !s.iter().all(|x| x.is_finite() && *x > 0.0) {
                return bad(i, "scale", format!("{s:?} must be positive factors"));
            }
        }
    }
    Ok(())
}

/// The primitives after `edits`, in order; every id names a row of `prims`, whatever was deleted.
pub fn apply(prims: &[Primitive], edits: &[Edit]) -> Result<Vec<Primitive>> {
    check(edits, Some(prims.len()))?;
    let mut out: Vec<Option<Primitive>> = prims.iter().cloned().map(Some).collect();
    for (i, e) in edits.iter().enumerate() {
        let Some(q) = out[e.primitive as usize].take() else {
            continue;
        };
        let mut to_world = q.to_world;
        if let Some(s) = e.scale {
            to_world *= DAffine3::from_scale(DVec3::from(s));
        }
        if let Some(deg) = e.rotate_deg {
            let c = to_world.translation;
            to_world = DAffine3::from_translation(c)
                * DAffine3::from_rotation_z(deg.to_radians())
                * DAffine3::from_translation(-c)
                * to_world;
        }
        if let Some(t) = e.translate {
            to_world = DAffine3::from_translation(DVec3::from(t)) * to_world;
        }
        let label = e
            .class
            .as_deref()
            .map_or(Some(q.label), class_id)
            .expect("checked");
        let instance = e.instance.unwrap_or(q.instance);
        let edited = Primitive::new(q.shape.clone(), to_world, label, instance).map_err(|err| {
            StageError::Params(format!("`edits[{i}]`: primitive {}: {err}", e.primitive))
        })?;
        // A later edit of a deleted primitive has nothing to edit.
        if !e.remove {
            out[e.primitive as usize] = Some(edited);
        }
    }
    Ok(out.into_iter().flatten().collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Shape;

    fn boxes() -> Vec<Primitive> {
        (0..4)
            .map(|i| {
                let t = DAffine3::from_translation(DVec3::new(i as f64 * 5.0, 0.0, 1.0));
                Primitive::new(Shape::Cuboid, t, labels::CAR, i + 1).unwrap()
            })
            .collect()
    }

    #[test]
    fn edits_do_what_they_say_and_ids_name_the_unedited_rows() {
        let edits = vec![
            Edit {
                primitive: 1,
                remove: true,
                ..Default::default()
            },
            Edit {
                primitive: 2,
                class: Some("caravan".into()),
                translate: Some([0.0, 1.0, 0.0]),
                ..Default::default()
            },
            Edit {
                primitive: 3,
                rotate_deg: Some(90.0),
                scale: Some([2.0, 1.0, 1.0]),
                ..Default::default()
            },
        ];
        let out = apply(&boxes(), &edits).unwrap();
        assert_eq!(out.len(), 3);
        assert_eq!(out[1].label, labels::CARAVAN);
        assert_eq!(out[1].instance, 3);
        assert!((out[1].to_world.translation - DVec3::new(10.0, 1.0, 1.0)).length() < 1e-12);
        // Scaled 2x along its own x, then turned 90 degrees about z through its centre: 2 m
        // along the scene's y, 1 m along x, centre unmoved.
        let b = out[2].aabb();
        assert!(
            (b.max - b.min - DVec3::new(1.0, 2.0, 1.0)).length() < 1e-9,
            "{b:?}"
        );
        assert!(((b.max + b.min) * 0.5 - DVec3::new(15.0, 0.0, 1.0)).length() < 1e-9);
    }

    #[test]
    fn bad_edits_name_the_field() {
        let cases = [
            (
                Edit {
                    primitive: 9,
                    ..Default::default()
                },
                "`edits[0].primitive`: 9 is not a primitive of the scene (it has 4)",
            ),
            (
                Edit {
                    class: Some("spaceship".into()),
                    ..Default::default()
                },
                "`edits[0].class`: unknown class `spaceship`",
            ),
            (
                Edit {
                    scale: Some([1.0, 0.0, 1.0]),
                    ..Default::default()
                },
                "`edits[0].scale`",
            ),
            (
                Edit {
                    translate: Some([f64::NAN, 0.0, 0.0]),
                    ..Default::default()
                },
                "`edits[0].translate`",
            ),
        ];
        for (e, want) in cases {
            let err = apply(&boxes(), &[e]).unwrap_err().to_string();
            assert!(err.contains(want), "{err}");
        }
    }
}
