//! Each moving object's shape in its own box's frame, voted from the pseudo labels of every
//! image that has them: a voxel of the box is the object's when, over the images it projects
//! into at that image's frame, most pseudo labels there are the box's class (a visual hull that
//! tolerates noisy labels and occluders). Images without pseudo labels (KITTI-360's right
//! camera) are labelled by marching their rays through the hull.

use std::collections::HashMap;

use crate::geometry::{Camera, DynamicBox, Interval, Primitive, Ray};

/// Target voxel edge, metres.
const VOXEL_M: f64 = 0.1;
/// Voxels per axis, at most and at least.
const MAX_VOXELS: usize = 64;
const MIN_VOXELS: usize = 4;
/// A voxel is the object's when at least this share of the pseudo labels it projects onto are
/// the box's class: near one, as a visual hull carves, but below it for noisy labels (a share
/// of one half keeps the voxels seen on the object from only half the views, a wide hull).
const SHARE: f64 = 0.7;

/// One object's votes and shape, in the unit cube of its box.
struct ObjectHull {
    label: u8,
    n: [usize; 3],
    /// The voxel centres in the box's unit cube, in index order.
    centres: Vec<glam::DVec3>,
    class_votes: Vec<u32>,
    seen: Vec<u32>,
    occupied: Vec<bool>,
}

impl ObjectHull {
    fn new(label: u8, size: [f64; 3]) -> Self {
        let n = size.map(|s| ((s / VOXEL_M).ceil() as usize).clamp(MIN_VOXELS, MAX_VOXELS));
        let len = n[0] * n[1] * n[2];
        let [nx, ny, nz] = n;
        let centres = (0..nz)
            .flat_map(|z| (0..ny).flat_map(move |y| (0..nx).map(move |x| [x, y, z])))
            .map(|[x, y, z]| {
                glam::DVec3::new(
                    (x as f64 + 0.5) / nx as f64 - 0.5,
                    (y as f64 + 0.5) / ny as f64 - 0.5,
                    (z as f64 + 0.5) / nz as f64 - 0.5,
                )
            })
            .collect();
        Self {
            label,
            n,
            centres,
            class_votes: vec![0; len],
            seen: vec![0; len],
            occupied: Vec::new(),
        }
    }

    fn index(&self, q: glam::DVec3) -> Option<usize> {
        let i = |v: f64, n: usize| {
            let k = ((v + 0.5) * n as f64).floor();
            (k >= 0.0 && k < n as f64).then_some(k as usize)
        };
        let (x, y, z) = (i(q.x, self.n[0])?, i(q.y, self.n[1])?, i(q.z, self.n[2])?);
        Some((z * self.n[1] + y) * self.n[0] + x)
    }

    /// The first `t` in `[t0, t1]` where `ray` is in an occupied voxel of the box `b`.
    fn first_occupied(&self, b: &Primitive, ray: &Ray, t0: f64, t1: f64) -> Option<f64> {
        let o = b.to_local().transform_point3(ray.origin);
        let d = b.to_local().transform_vector3(ray.dir);
        let step = 0.5 / (*self.n.iter().max().unwrap_or(&1) as f64 * d.length().max(1e-12));
        let mut t = t0 + 0.5 * step;
        while t <= t1 {
            if self.index(o + d * t).is_some_and(|i| self.occupied[i]) {
                return Some(t);
            }
            t += step;
        }
        None
    }
}

/// The moving objects' hulls, by object.
#[derive(Default)]
pub(super) struct Hulls {
    by_object: HashMap<u32, ObjectHull>,
}

impl Hulls {
    /// Empty hulls of the objects of `boxes` (the voxel counts from their largest box).
    pub(super) fn new(boxes: &[DynamicBox]) -> Self {
        let mut size: HashMap<u32, (u8, [f64; 3])> = HashMap::new();
        for b in boxes {
            let m = b.primitive.to_world.matrix3;
            let s = [m.x_axis.length(), m.y_axis.length(), m.z_axis.length()];
            let e = size.entry(b.object).or_insert((b.primitive.label, s));
            for (e, s) in e.1.iter_mut().zip(s) {
                *e = e.max(s);
            }
        }
        Self {
            by_object: size
                .into_iter()
                .map(|(o, (label, s))| (o, ObjectHull::new(label, s)))
                .collect(),
        }
    }

    /// Counts the votes of one image's pseudo labels (`cam` at the frame of `boxes`, whose
    /// objects are `objects`).
    pub(super) fn vote(
        &mut self,
        cam: &Camera,
        boxes: &[Primitive],
        objects: &[u32],
        pseudo: &[u8],
    ) {
        for (b, object) in boxes.iter().zip(objects) {
            let Some(h) = self.by_object.get_mut(object) else {
                continue;
            };
            for (i, &c) in h.centres.iter().enumerate() {
                let Some((u, v, _)) = cam.project(b.to_world.transform_point3(c)) else {
                    continue;
                };
                if u < 0.0 || v < 0.0 || u >= cam.width as f64 || v >= cam.height as f64 {
                    continue;
                }
                let p = v as usize * cam.width as usize + u as usize;
                h.seen[i] += 1;
                if pseudo[p] == h.label {
                    h.class_votes[i] += 1;
                }
            }
        }
    }

    /// Settles each voxel from its votes; objects no pseudo label saw keep no hull.
    pub(super) fn settle(&mut self) {
        self.by_object.retain(|_, h| h.seen.iter().any(|&s| s > 0));
        for h in self.by_object.values_mut() {
            h.occupied = h
                .class_votes
                .iter()
                .zip(&h.seen)
                .map(|(&c, &s)| s > 0 && c as f64 >= SHARE * s as f64)
                .collect();
        }
    }

    /// Whether `object` has a hull (votes settled, some pseudo label saw it).
    pub(super) fn has(&self, object: u32) -> bool {
        self.by_object
            .get(&object)
            .is_some_and(|h| !h.occupied.is_empty())
    }

    /// Where `ray` first meets `object`'s hull inside its box `b` (world `t`), if it does.
    pub(super) fn first_hit(
        &self,
        object: u32,
        b: &Primitive,
        ray: &Ray,
        buf: &mut Vec<Interval>,
    ) -> Option<f64> {
        let h = self
            .by_object
            .get(&object)
            .filter(|h| !h.occupied.is_empty())?;
        buf.clear();
        b.intersect(ray, buf);
        buf.iter()
            .filter_map(|iv| h.first_occupied(b, ray, iv.t_in.max(0.0), iv.t_out))
            .min_by(f64::total_cmp)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{DAffine3, DVec3, Lens, Shape};
    use crate::labels::{CAR, ROAD};

    /// A camera at `eye` looking at the origin (z forward, y down), 64x48.
    fn looking_at_origin(eye: DVec3) -> Camera {
        let z = (-eye).normalize();
        let x = DVec3::Z.cross(z).normalize();
        let y = z.cross(x);
        Camera {
            width: 64,
            height: 48,
            fx: 60.0,
            fy: 60.0,
            cx: 32.0,
            cy: 24.0,
            lens: Lens::Pinhole,
            cam_to_world: DAffine3::from_cols(x, y, z, eye),
        }
    }

    /// Per pixel of `cam`: whether its ray meets `p`.
    fn silhouette(cam: &Camera, p: &Primitive) -> Vec<bool> {
        let mut buf = Vec::new();
        (0..cam.width * cam.height)
            .map(|i| {
                let ray = cam.pixel_ray(i % cam.width, i / cam.width).unwrap();
                buf.clear();
                p.intersect(&ray, &mut buf);
                !buf.is_empty()
            })
            .collect()
    }

    /// A car (a 4 x 1.8 x 1.5 m cuboid) in a box twice its size, seen from behind as a car
    /// ahead is, from eight points 8 to 15 m back, with pseudo labels of which one pixel in six
    /// is wrong and one image whose labels are all wrong: from a camera half a metre beside one
    /// of them without pseudo labels (a stereo pair's right camera), the pixels whose rays meet
    /// the hull are the car's silhouette, not the box's, at a depth no worse than the box's.
    #[test]
    fn the_hull_voted_from_pseudo_labels_is_the_object_not_its_box() {
        let car = Primitive::new(
            Shape::Cuboid,
            DAffine3::from_scale(DVec3::new(4.0, 1.8, 1.5)),
            CAR,
            3,
        )
        .unwrap();
        let bx = Primitive::new(
            Shape::Cuboid,
            DAffine3::from_scale(DVec3::new(8.0, 3.6, 3.0)),
            CAR,
            3,
        )
        .unwrap();
        let boxes = [DynamicBox {
            object: 26003,
            frame: 0,
            primitive: bx.clone(),
        }];
        let behind = |k: u64| DVec3::new(-8.0 - k as f64, 0.3 * (k as f64 - 3.5), 1.2);
        let mut hulls = Hulls::new(&boxes);
        for k in 0..8 {
            let cam = looking_at_origin(behind(k));
            let pseudo: Vec<u8> = silhouette(&cam, &car)
                .into_iter()
                .enumerate()
                .map(|(i, on)| {
                    let flip = (i as u64 * 2654435761 + k) % 6 == 0 || k == 5;
                    if on != flip {
                        CAR
                    } else {
                        ROAD
                    }
                })
                .collect();
            hulls.vote(&cam, std::slice::from_ref(&bx), &[26003], &pseudo);
        }
        hulls.settle();
        assert!(hulls.has(26003));
        let cam = looking_at_origin(behind(2) + DVec3::new(0.0, -0.54, 0.0));
        let want = silhouette(&cam, &car);
        let outline = silhouette(&cam, &bx);
        let mut buf = Vec::new();
        let (mut both, mut either) = (0, 0);
        let mut depth_errors = Vec::new();
        for i in 0..cam.width * cam.height {
            let ray = cam.pixel_ray(i % cam.width, i / cam.width).unwrap();
            let hit = hulls.first_hit(26003, &bx, &ray, &mut buf);
            let on = hit.is_some();
            both += (on && want[i as usize]) as usize;
            either += (on || want[i as usize]) as usize;
            if let (Some(t), true) = (hit, want[i as usize]) {
                buf.clear();
                car.intersect(&ray, &mut buf);
                let surface = buf[0].t_in;
                buf.clear();
                bx.intersect(&ray, &mut buf);
                depth_errors.push(((t - surface).abs(), (buf[0].t_in - surface).abs()));
            }
        }
        // Views from behind carve little in depth: the hull's depth is the box's or nearer.
        let n = depth_errors.len() as f64;
        let hull = depth_errors.iter().map(|e| e.0).sum::<f64>() / n;
        let entry = depth_errors.iter().map(|e| e.1).sum::<f64>() / n;
        assert!(
            hull <= entry,
            "mean depth error: hull {hull} m, box entry {entry} m"
        );
        let iou = both as f64 / either as f64;
        let car_px = want.iter().filter(|&&w| w).count();
        let box_px = outline.iter().filter(|&&w| w).count();
        // At 64x48 the car is 153 pixels: a pixel's rim around it is a third of that.
        assert!(iou > 0.6, "hull against car silhouette IoU {iou}");
        let box_iou = car_px as f64 / box_px as f64;
        assert!(
            box_iou < 0.2,
            "box outline against car silhouette IoU {box_iou}"
        );
        // An object no pseudo label saw has no hull.
        let mut unseen = Hulls::new(&boxes);
        unseen.settle();
        assert!(!unseen.has(26003));
    }
}
