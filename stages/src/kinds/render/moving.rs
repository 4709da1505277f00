//! Moving objects' labels over the static field's maps. Training leaves out the rays that
//! cross a moving object's box at their own frame, so the field is the static scene's; each
//! moving object is labelled from its box at the image's frame: a pixel whose ray enters the
//! box before the static surface the field renders there, and whose pseudo label (where the
//! image has them) is the box's class, takes the class of the nearest such box, its instance
//! (one id per object for the whole sequence) and the depth where the ray enters the box.
//! Where boxes of two classes overlap (a rider's and its bicycle's) the pseudo label picks the
//! box. The box is coarse; the pseudo label trims it to the object's outline, the static depth
//! to what is in front. In an image without pseudo labels the object's hull ([`Hulls`], voted
//! from the images with them) takes the pseudo labels' place: a pixel is the object's where its
//! ray meets the hull before the static surface, at the depth where it meets it.

use std::collections::HashMap;

use arrow::datatypes::UInt8Type;

use super::hull::Hulls;
use crate::geometry::{
    self, changes::pixels_meeting, Camera, CameraRow, DynamicBox, Interval, Primitive,
};
use crate::labels::INSTANCE_FACTOR;
use crate::model::maps::ImageMaps;
use crate::stage::{Inputs, Result, StageError, Table};
use crate::tables;

/// What labelling the moving objects reads of the scene: their boxes and the pseudo labels.
pub(super) struct MovingLabels<'a> {
    pub(super) boxes: MovingBoxes,
    pseudo: &'a Table,
    rows: HashMap<(u32, u8), usize>,
}

impl<'a> MovingLabels<'a> {
    /// The boxes, and the objects' hulls voted from the pseudo labels of the images of `cams`.
    pub(super) fn new(inputs: &Inputs<'a>, cams: &[CameraRow]) -> Result<Self> {
        let boxes = geometry::dynamic_boxes_from_table(inputs.table("scene", "dynamic_boxes")?)?;
        let pseudo = inputs.stored("scene", "pseudo_labels")?;
        let mut labels = Self {
            boxes: MovingBoxes::new(boxes),
            rows: tables::frame_camera_index(
                &pseudo.columns(&["frame", "camera"])?,
                "pseudo_labels",
            )?,
            pseudo,
        };
        if labels.boxes.by_frame.is_empty() {
            return Ok(labels);
        }
        let mut hulls = std::mem::take(&mut labels.boxes.hulls);
        for c in cams {
            let n = (c.cam.width * c.cam.height) as usize;
            if let Some(l) = labels.pseudo_labels(c.frame, c.camera, n)? {
                let (prims, objects) = &labels.boxes.by_frame[&c.frame];
                hulls.vote(&c.cam, prims, objects, &l);
            }
        }
        hulls.settle();
        labels.boxes.hulls = hulls;
        Ok(labels)
    }

    /// The pseudo labels of image (`frame`, `camera`) of `n` pixels, read only where the image
    /// has them and a moving object's box is at its frame.
    pub(super) fn pseudo_labels(
        &self,
        frame: u32,
        camera: u8,
        n: usize,
    ) -> Result<Option<Vec<u8>>> {
        let Some(&row) = self.rows.get(&(frame, camera)) else {
            return Ok(None);
        };
        if !self.boxes.at(frame) {
            return Ok(None);
        }
        let b = self.pseudo.row(row)?;
        let l = tables::get_list::<UInt8Type>(&b, "pseudo_labels", "labels")?.row(0);
        if l.len() != n {
            return Err(StageError::Input(format!(
                "pseudo_labels: frame {frame} camera {camera} has {} labels for {n} pixels",
                l.len()
            )));
        }
        Ok(Some(l.to_vec()))
    }
}

/// The moving objects' boxes per frame (with their object), and their hulls.
#[derive(Default)]
pub(super) struct MovingBoxes {
    /// Per frame the boxes and, in the same order, their objects.
    by_frame: HashMap<u32, (Vec<Primitive>, Vec<u32>)>,
    hulls: Hulls,
}

impl MovingBoxes {
    /// The boxes, with empty hulls (see [`Hulls::vote`]).
    pub(super) fn new(boxes: Vec<DynamicBox>) -> Self {
        let hulls = Hulls::new(&boxes);
        let mut by_frame: HashMap<u32, (Vec<Primitive>, Vec<u32>)> = HashMap::new();
        for b in boxes {
            let (prims, objects) = by_frame.entry(b.frame).or_default();
            prims.push(b.primitive);
            objects.push(b.object);
        }
        Self { by_frame, hulls }
    }

    /// Whether any box is at `frame`.
    pub(super) fn at(&self, frame: u32) -> bool {
        self.by_frame.contains_key(&frame)
    }

    /// Labels the moving objects in `maps` (of camera `cam`); `pseudo`: the image's pseudo
    /// labels, if it has them. Returns the number of pixels labelled so.
    pub(super) fn overlay(
        &self,
        maps: &mut ImageMaps,
        cam: &Camera,
        pseudo: Option<&[u8]>,
    ) -> usize {
        let Some((prims, objects)) = self.by_frame.get(&maps.frame) else {
            return 0;
        };
        let mut buf: Vec<Interval> = Vec::new();
        let mut labelled = 0;
        for px in pixels_meeting(cam, prims, f64::INFINITY) {
            let p = px as usize;
            let Some(ray) = cam.pixel_ray(px % cam.width, px / cam.width) else {
                continue;
            };
            // Where the ray first meets a moving object: its hull where the image has no
            // pseudo labels and the object has one, else its box's entry; with pseudo labels,
            // only boxes of the pixel's pseudo class (a rider's box overlaps its bicycle's).
            let mut first: Option<(f64, &Primitive)> = None;
            for (b, object) in prims.iter().zip(objects) {
                if pseudo.is_some_and(|l| l[p] != b.label) {
                    continue;
                }
                let t = if pseudo.is_none() && self.hulls.has(*object) {
                    self.hulls.first_hit(*object, b, &ray, &mut buf)
                } else {
                    buf.clear();
                    b.intersect(&ray, &mut buf);
                    buf.iter().map(|iv| iv.t_in.max(0.0)).min_by(f64::total_cmp)
                };
                if let Some(t) = t {
                    if first.is_none_or(|(best, _)| t < best) {
                        first = Some((t, b));
                    }
                }
            }
            let Some((t, b)) = first else {
                continue;
            };
            let entry = cam.depth(&ray, t);
            // The static surface: 0 where the field rendered no surface (sky).
            let behind = maps.depth[p] <= 0.0 || entry < f64::from(maps.depth[p]);
            if behind {
                maps.semantic[p] = b.label;
                maps.instance[p] = (b.label as u32 * INSTANCE_FACTOR + b.instance.min(999)) as u16;
                maps.depth[p] = entry as f32;
                labelled += 1;
            }
        }
        labelled
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{DAffine3, DVec3, Lens, Shape};
    use crate::labels::{BICYCLE, CAR, RIDER, ROAD};

    fn maps(w: u32, h: u32, depth: f32) -> ImageMaps {
        let n = (w * h) as usize;
        ImageMaps {
            frame: 4,
            camera: 0,
            width: w,
            height: h,
            semantic: vec![ROAD; n],
            fixed: vec![ROAD; n],
            instance: vec![ROAD as u16 * 1000; n],
            depth: vec![depth; n],
            confidence: vec![1.0; n],
            rgb: Vec::new(),
        }
    }

    /// A 21 x 11 pinhole camera at the origin looking along +z (10 px a metre at 1 m).
    fn camera() -> Camera {
        Camera {
            width: 21,
            height: 11,
            fx: 10.0,
            fy: 10.0,
            cx: 10.5,
            cy: 5.5,
            lens: Lens::Pinhole,
            cam_to_world: DAffine3::IDENTITY,
        }
    }

    /// A box 1 m deep whose near face is 5 m ahead fills the middle of the view: where the
    /// static surface is behind it the pixels take its class, instance and entry depth; where
    /// the surface is in front (3 m) or the pseudo label says otherwise they keep theirs.
    #[test]
    fn a_box_labels_the_pixels_it_is_in_front_of_and_the_pseudo_label_agrees_with() {
        let cam = camera();
        let tf = DAffine3::from_scale_rotation_translation(
            DVec3::new(2.0, 2.0, 1.0),
            glam::DQuat::IDENTITY,
            DVec3::new(0.0, 0.0, 5.5),
        );
        let car = Primitive::new(Shape::Cuboid, tf, CAR, 7).unwrap();
        let moving = MovingBoxes::new(vec![DynamicBox {
            object: 26007,
            frame: 4,
            primitive: car,
        }]);
        let centre = 5 * 21 + 10;
        // Static surface at 20 m: the box's pixels (|x|, |y| < 1 m at 5 m: 2 px each side) are
        // the car's, at z-depth 5.
        let mut m = maps(21, 11, 20.0);
        let n = moving.overlay(&mut m, &cam, None);
        let expect: Vec<usize> = (0..21 * 11)
            .filter(|&p| {
                let (u, v) = ((p % 21) as f64 + 0.5, (p / 21) as f64 + 0.5);
                ((u - 10.5) / 10.0 * 5.0).abs() < 1.0 && ((v - 5.5) / 10.0 * 5.0).abs() < 1.0
            })
            .collect();
        assert_eq!(n, expect.len());
        for p in 0..21 * 11 {
            let inside = expect.contains(&p);
            assert_eq!(m.semantic[p] == CAR, inside, "pixel {p}");
            if inside {
                assert_eq!(m.instance[p], 26007);
                assert!((m.depth[p] - 5.0).abs() < 1e-5, "{}", m.depth[p]);
            }
        }
        // Sky behind (no depth) counts as behind.
        let mut sky = maps(21, 11, 0.0);
        assert_eq!(moving.overlay(&mut sky, &cam, None), expect.len());
        // A static surface in front of the box keeps its label.
        let mut near = maps(21, 11, 3.0);
        assert_eq!(moving.overlay(&mut near, &cam, None), 0);
        assert!(near.semantic.iter().all(|&l| l == ROAD));
        // Pseudo labels trim the box: only the pixels they call car.
        let mut pseudo = vec![ROAD; 21 * 11];
        pseudo[centre] = CAR;
        let mut trimmed = maps(21, 11, 20.0);
        assert_eq!(moving.overlay(&mut trimmed, &cam, Some(&pseudo)), 1);
        assert_eq!(trimmed.semantic[centre], CAR);
        // Another frame: nothing.
        let mut other = maps(21, 11, 20.0);
        other.frame = 5;
        assert_eq!(moving.overlay(&mut other, &cam, None), 0);
    }

    /// A rider's box in front of its bicycle's, both across the view: a pixel the pseudo labels
    /// call bicycle takes the bicycle's class, instance and entry depth though the ray enters
    /// the rider's box first; one they call rider takes the rider's.
    #[test]
    fn overlapping_boxes_of_two_classes_are_told_apart_by_the_pseudo_label() {
        let cam = camera();
        let slab = |z: f64, label: u8, instance: u32| {
            let tf = DAffine3::from_scale_rotation_translation(
                DVec3::new(20.0, 20.0, 1.0),
                glam::DQuat::IDENTITY,
                DVec3::new(0.0, 0.0, z),
            );
            Primitive::new(Shape::Cuboid, tf, label, instance).unwrap()
        };
        let moving = MovingBoxes::new(vec![
            DynamicBox {
                object: 25001,
                frame: 4,
                primitive: slab(4.5, RIDER, 1),
            },
            DynamicBox {
                object: 33001,
                frame: 4,
                primitive: slab(5.0, BICYCLE, 1),
            },
        ]);
        let mut pseudo = vec![ROAD; 21 * 11];
        let (bike, rider) = (5 * 21 + 10, 5 * 21 + 3);
        pseudo[bike] = BICYCLE;
        pseudo[rider] = RIDER;
        let mut m = maps(21, 11, 20.0);
        assert_eq!(moving.overlay(&mut m, &cam, Some(&pseudo)), 2);
        assert_eq!((m.semantic[bike], m.instance[bike]), (BICYCLE, 33001));
        assert!((m.depth[bike] - 4.5).abs() < 1e-5, "{}", m.depth[bike]);
        assert_eq!((m.semantic[rider], m.instance[rider]), (RIDER, 25001));
        assert!((m.depth[rider] - 4.0).abs() < 1e-5, "{}", m.depth[rider]);
        assert_eq!(
            m.semantic.iter().filter(|&&l| l == ROAD).count(),
            21 * 11 - 2
        );
    }
}
