//! Static and moving pixels scored apart, where the scene has moving objects (its
//! `dynamic_boxes`): the moving part is the pixels whose ray meets a moving object's box at the
//! image's frame (the object and what is seen around it through its coarse box), the static
//! part the rest. Each part is the whole evaluation with the other part's GT made void (labels
//! and instances 0, no depth reference), so its mIoU, PQ and depth count only its own pixels,
//! as masked evaluations do. Within the boxes' outlines a method must tell the object from
//! what is around it: labelling the whole box (the box projection) scores low there.

use std::collections::BTreeMap;

use super::sums::{FrameMaps, Group};
use super::EvaluateParams;
use crate::geometry::{Bvh, DynamicBox, Primitive};
use crate::{labels, Result};

/// The parts, as the `motion_metrics` table names them.
pub const PARTS: [&str; 2] = ["static", "moving"];

/// The scene's moving objects: their boxes per frame.
#[derive(Default)]
pub(super) struct MovingObjects {
    by_frame: BTreeMap<u32, (Vec<Primitive>, Bvh)>,
    /// The hierarchy of no box.
    none: Bvh,
}

impl MovingObjects {
    pub(super) fn new(boxes: Vec<DynamicBox>) -> Self {
        let mut frames: BTreeMap<u32, Vec<Primitive>> = BTreeMap::new();
        for b in boxes {
            frames.entry(b.frame).or_default().push(b.primitive);
        }
        let by_frame = frames
            .into_iter()
            .map(|(f, prims)| {
                let bvh = Bvh::build(&prims);
                (f, (prims, bvh))
            })
            .collect();
        Self {
            by_frame,
            none: Bvh::default(),
        }
    }

    pub(super) fn is_empty(&self) -> bool {
        self.by_frame.is_empty()
    }

    /// The boxes at `frame` and their hierarchy (empty where none is).
    pub(super) fn at(&self, frame: u32) -> (&[Primitive], &Bvh) {
        self.by_frame
            .get(&frame)
            .map_or((&[][..], &self.none), |(p, b)| (&p[..], b))
    }
}

/// The static and the moving part's accumulators.
pub(super) struct MotionGroups {
    pub(super) parts: [Group; 2],
}

impl MotionGroups {
    pub(super) fn new(p: &EvaluateParams) -> Result<Self> {
        Ok(Self {
            parts: [Group::for_part(p)?, Group::for_part(p)?],
        })
    }
}

/// One part's GT and depth references: the image's, void where the pixel is in the other part.
pub(super) struct PartGt {
    gsem: Vec<u8>,
    ginst: Vec<u16>,
    lidar: Option<Vec<f32>>,
    exact: Option<Vec<f32>>,
}

impl PartGt {
    /// The moving part's (`in_moving`) or the static part's of image `f`, `moving` its moving
    /// pixels.
    pub(super) fn of(f: &FrameMaps, moving: &[bool], in_moving: bool) -> PartGt {
        let keep = |i: usize| moving[i] == in_moving;
        let depth = |d: &[f32]| -> Vec<f32> {
            d.iter()
                .enumerate()
                .map(|(i, &v)| if keep(i) { v } else { 0.0 })
                .collect()
        };
        PartGt {
            gsem: (0..f.gsem.len())
                .map(|i| {
                    if keep(i) {
                        f.gsem[i]
                    } else {
                        labels::UNLABELED
                    }
                })
                .collect(),
            ginst: (0..f.ginst.len())
                .map(|i| if keep(i) { f.ginst[i] } else { 0 })
                .collect(),
            lidar: f.lidar.map(depth),
            exact: f.exact.map(depth),
        }
    }

    /// Image `f`'s maps with this part's GT and references.
    pub(super) fn maps<'a>(&'a self, f: &FrameMaps<'a>) -> FrameMaps<'a> {
        FrameMaps {
            gsem: &self.gsem,
            ginst: &self.ginst,
            lidar: self.lidar.as_deref(),
            exact: self.exact.as_deref(),
            ..*f
        }
    }
}

#[cfg(test)]
mod tests {
    use arrow::array::{Array, Float64Array};
    use arrow::record_batch::RecordBatch;
    use std::collections::{HashMap, HashSet};

    use super::*;
    use crate::kinds::evaluate::{testing::label_maps, Evaluate};
    use crate::scene::synthetic::{generate, in_memory::to_tables, SceneParams};
    use crate::{tables, MemoryInputs, NoProgress, Stage, Tables};

    /// `(part, method, metric)` of `motion_metrics`.
    fn value(t: &Tables, part: &str, method: &str, metric: &str) -> Option<f64> {
        let m = &t["motion_metrics"];
        let col = |c| tables::get_strings(m, "motion_metrics", c).unwrap();
        let (parts, methods, metrics) = (col("part"), col("method"), col("metric"));
        let values = m["value"].as_any().downcast_ref::<Float64Array>().unwrap();
        (0..m.num_rows())
            .find(|&i| {
                (parts.value(i), methods.value(i), metrics.value(i)) == (part, method, metric)
            })
            .and_then(|i| values.is_valid(i).then(|| values.value(i)))
    }

    fn evaluate(scene: &Tables, render: Tables) -> Tables {
        let s = Evaluate;
        let v = Stage::canonical_params(&s, &serde_json::json!({})).unwrap();
        let mem = MemoryInputs::new([("scene", scene.clone()), ("render", render)]);
        Stage::run(&s, &v, &mem.inputs(), &NoProgress).unwrap()
    }

    #[test]
    fn moving_and_static_pixels_are_scored_apart() {
        let p = SceneParams {
            frames: 6,
            moving_objects: 3,
            ..SceneParams::default()
        };
        let scene = to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap();
        let boxes = crate::geometry::dynamic_boxes_from_table(&scene["dynamic_boxes"]).unwrap();
        let objects: HashSet<u16> = boxes.iter().map(|b| b.object as u16).collect();

        // GT as the labels: every part perfect.
        let exact = evaluate(&scene, label_maps(&scene, &objects, None));
        for part in PARTS {
            assert_eq!(
                value(&exact, part, "panoptic_nerf", "miou"),
                Some(1.0),
                "{part}"
            );
            assert_eq!(
                value(&exact, part, "panoptic_nerf", "pq"),
                Some(1.0),
                "{part}"
            );
        }
        // The moving cars labelled road: the moving part (the boxes' outlines) fails, the
        // static part is untouched (its GT is void there), the whole in between.
        let wrong = evaluate(&scene, label_maps(&scene, &objects, Some(labels::ROAD)));
        let acc = value(&wrong, "moving", "panoptic_nerf", "acc").unwrap();
        assert!(acc < 0.75, "{acc}");
        let miou = value(&wrong, "moving", "panoptic_nerf", "miou").unwrap();
        assert!(miou < 0.9, "{miou}");
        assert_eq!(value(&wrong, "static", "panoptic_nerf", "miou"), Some(1.0));
        let all = |t: &Tables, method: &str, metric: &str| {
            let m = &t["metrics"];
            let methods = tables::get_strings(m, "metrics", "method").unwrap();
            let metrics = tables::get_strings(m, "metrics", "metric").unwrap();
            let values = m["value"].as_any().downcast_ref::<Float64Array>().unwrap();
            (0..m.num_rows())
                .find(|&i| (methods.value(i), metrics.value(i)) == (method, metric))
                .map(|i| values.value(i))
                .unwrap()
        };
        // One camera model (the left perspective camera): its rows are the whole's.
        let rows = |t: &RecordBatch, name: &str| {
            let methods = tables::get_strings(t, name, "method").unwrap();
            let metrics = tables::get_strings(t, name, "metric").unwrap();
            let values = t["value"].as_any().downcast_ref::<Float64Array>().unwrap();
            (0..t.num_rows())
                .map(|i| {
                    let v = values.is_valid(i).then(|| values.value(i).to_bits());
                    (
                        (methods.value(i).to_string(), metrics.value(i).to_string()),
                        v,
                    )
                })
                .collect::<Vec<_>>()
        };
        let whole_rows: HashMap<_, _> = rows(&wrong["metrics"], "metrics").into_iter().collect();
        let model_rows = rows(&wrong["camera_metrics"], "camera_metrics");
        assert!(
            model_rows.len() > 20,
            "{} camera_metrics rows",
            model_rows.len()
        );
        for (key, v) in &model_rows {
            assert_eq!(whole_rows.get(key), Some(v), "{key:?}");
        }
        let whole = all(&wrong, "panoptic_nerf", "miou");
        assert!(whole > 0.5 && whole < 1.0, "{whole}");
        // Pixels of the two parts add up to the whole.
        let px = |part| value(&wrong, part, "panoptic_nerf", "pixels").unwrap();
        assert_eq!(
            px("static") + px("moving"),
            all(&wrong, "panoptic_nerf", "pixels")
        );
        assert!(px("moving") > 100.0, "{} moving pixels", px("moving"));

        // The box projection labels the boxes' outlines whole: right on the object, wrong
        // around it; without the moving boxes the object's pixels would be whatever static box
        // or sky lies behind.
        let fp = value(&wrong, "moving", "first_primitive", "acc").unwrap();
        let mut still = scene.clone();
        still.insert(
            "dynamic_boxes".into(),
            crate::geometry::dynamic_boxes_to_table(&[]).unwrap(),
        );
        assert!(
            fp > 0.3 && fp < 0.95,
            "box projection on moving pixels: {fp}"
        );
        let none = evaluate(&still, label_maps(&scene, &objects, None));
        assert_eq!(
            none["motion_metrics"].num_rows(),
            0,
            "no moving objects, no split"
        );
        let (with, without) = (
            all(&wrong, "first_primitive", "acc"),
            all(&none, "first_primitive", "acc"),
        );
        assert!(
            with > without,
            "box projection {with} with the moving boxes, {without} without"
        );
    }

    /// The mask against every pixel's ray through the boxes, and the labels against the first
    /// hit of the union of the static primitives and the boxes.
    #[test]
    fn the_moving_pixels_are_those_whose_ray_meets_a_moving_box() {
        use crate::geometry::changes::pixels_meeting;
        let p = SceneParams {
            frames: 4,
            moving_objects: 3,
            ..SceneParams::default()
        };
        let scene = to_tables(&p, generate(&p, &NoProgress).unwrap()).unwrap();
        let boxes = crate::geometry::dynamic_boxes_from_table(&scene["dynamic_boxes"]).unwrap();
        let moving = MovingObjects::new(boxes);
        let prims = crate::geometry::primitives_from_table(&scene["primitives"]).unwrap();
        let bvh = Bvh::build(&prims);
        let cameras = crate::geometry::cameras_from_table(&scene["cameras"]).unwrap();
        let mut met = 0;
        for c in &cameras {
            let (boxes, boxes_bvh) = moving.at(c.frame);
            let (sem, _, mask) =
                super::super::first_primitive_maps(&c.cam, &prims, &bvh, (boxes, boxes_bvh));
            for (i, &s) in sem.iter().enumerate() {
                let ray = c
                    .cam
                    .pixel_ray(i as u32 % c.cam.width, i as u32 / c.cam.width);
                let first = ray.as_ref().and_then(|r| {
                    Bvh::first_hit_of_two((&bvh, &prims), (boxes_bvh, boxes), r, 0.0, f64::INFINITY)
                });
                let want = match first {
                    Some((h, true)) => boxes[h.prim as usize].label,
                    Some((h, false)) => prims[h.prim as usize].label,
                    None if ray.is_some() => labels::SKY,
                    None => labels::UNLABELED,
                };
                assert_eq!(s, want, "frame {} camera {} pixel {i}", c.frame, c.camera);
            }
            let mut want = vec![false; mask.len()];
            for i in pixels_meeting(&c.cam, moving.at(c.frame).0, f64::INFINITY) {
                want[i as usize] = true;
            }
            assert_eq!(mask, want, "frame {} camera {}", c.frame, c.camera);
            met += want.iter().filter(|&&m| m).count();
        }
        assert!(met > 100, "{met} moving pixels");
    }
}
