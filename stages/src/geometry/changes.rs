//! What an edit of the primitives changed, and which cameras can see it: the rows of two
//! `primitives` tables matched by content (removing a primitive renumbers the rows after it),
//! and a conservative test of whether any pixel ray of a camera can meet a ball.

use std::collections::HashMap;

use arrow::{
    datatypes::{Float64Type, UInt32Type, UInt8Type},
    record_batch::RecordBatch,
};
use glam::DVec3;

use rayon::prelude::*;

use super::{Aabb, Bvh, Camera, Primitive};
use crate::{stage::Result, tables};

/// How the primitives of a new table relate to those of an old one.
#[derive(Debug, Clone, PartialEq)]
pub struct PrimitiveChanges {
    /// For each old id, its id in the new table when it is there unchanged.
    pub old_to_new: Vec<Option<u32>>,
    /// Old ids without an unchanged counterpart: moved, resized, relabelled or removed.
    pub removed: Vec<u32>,
    /// New ids without an unchanged counterpart: moved, resized, relabelled or added.
    pub added: Vec<u32>,
}

impl PrimitiveChanges {
    /// Matches the rows of `old` and `new` by their content (every column but `id`); equal rows
    /// are matched in order.
    pub fn between(old: &RecordBatch, new: &RecordBatch) -> Result<Self> {
        let (a, b) = (row_digests(old)?, row_digests(new)?);
        let mut free: HashMap<blake3::Hash, Vec<u32>> = HashMap::new();
        for (id, d) in b.iter().enumerate().rev() {
            free.entry(*d).or_default().push(id as u32);
        }
        let old_to_new: Vec<Option<u32>> = a
            .iter()
            .map(|d| free.get_mut(d).and_then(Vec::pop))
            .collect();
        let mut matched = vec![false; b.len()];
        for &n in old_to_new.iter().flatten() {
            matched[n as usize] = true;
        }
        Ok(Self {
            removed: (0..a.len() as u32)
                .filter(|&o| old_to_new[o as usize].is_none())
                .collect(),
            added: (0..b.len() as u32)
                .filter(|&n| !matched[n as usize])
                .collect(),
            old_to_new,
        })
    }

    pub fn is_empty(&self) -> bool {
        self.removed.is_empty() && self.added.is_empty()
    }

    /// The changed primitives' extents: the old ones that went (`old`: the old table's
    /// primitives) and the new ones that came (`new`); a pixel whose ray meets none of them
    /// sees no change.
    pub fn extents(&self, old: &[Primitive], new: &[Primitive]) -> Vec<Primitive> {
        self.removed
            .iter()
            .map(|&o| old[o as usize].clone())
            .chain(self.added.iter().map(|&n| new[n as usize].clone()))
            .collect()
    }

    /// Whether an unchanged primitive has a new id.
    pub fn renumbers(&self) -> bool {
        self.old_to_new
            .iter()
            .enumerate()
            .any(|(o, n)| n.is_some_and(|n| n as usize != o))
    }
}

/// blake3 of each row's content: kind, label, instance, transform, polygon, vertices, faces.
fn row_digests(t: &RecordBatch) -> Result<Vec<blake3::Hash>> {
    const T: &str = "primitives";
    let kinds = tables::get_strings(t, T, "kind")?;
    let labels = tables::get_prim::<UInt8Type>(t, T, "label")?;
    let instances = tables::get_prim::<UInt32Type>(t, T, "instance")?;
    let (transform, n) = tables::get_fixed_list::<Float64Type>(t, T, "transform")?;
    let polygon = tables::get_list::<Float64Type>(t, T, "polygon")?;
    let vertices = tables::get_list::<Float64Type>(t, T, "vertices")?;
    let faces = tables::get_list::<UInt32Type>(t, T, "faces")?;
    Ok((0..t.num_rows())
        .map(|r| {
            let mut h = blake3::Hasher::new();
            h.update(kinds.value(r).as_bytes());
            h.update(&[0, labels[r]]);
            h.update(&instances[r].to_le_bytes());
            let floats = |h: &mut blake3::Hasher, v: &[f64]| {
                h.update(&(v.len() as u64).to_le_bytes());
                for x in v {
                    h.update(&x.to_bits().to_le_bytes());
                }
            };
            floats(&mut h, &transform[r * n..(r + 1) * n]);
            floats(&mut h, polygon.row(r));
            floats(&mut h, vertices.row(r));
            let f = faces.row(r);
            h.update(&(f.len() as u64).to_le_bytes());
            for x in f {
                h.update(&x.to_le_bytes());
            }
            h.finalize()
        })
        .collect())
}

/// The smallest ball around a box (centre, radius).
pub fn bounding_ball(b: &Aabb) -> (DVec3, f64) {
    ((b.min + b.max) * 0.5, (b.max - b.min).length() * 0.5)
}

/// The largest angle (radians) between a camera's optical axis and the ray of one of its
/// pixels (through pixel centres, as every ray of the plan is).
pub fn widest_pixel_angle(cam: &Camera) -> f64 {
    let mut min_cos = 1.0f64;
    for y in 0..cam.height {
        for x in 0..cam.width {
            if let Some(d) = cam.dir_cam(x as f64 + 0.5, y as f64 + 0.5) {
                min_cos = min_cos.min(d.z / d.length());
            }
        }
    }
    min_cos.clamp(-1.0, 1.0).acos()
}

/// Whether a ray of `cam` (pixel rays within `widest`, see [`widest_pixel_angle`]) can meet the
/// ball (`centre`, `radius`) no farther than `far`. Never false where one can; may be true
/// where none does.
pub fn camera_may_see(cam: &Camera, widest: f64, centre: DVec3, radius: f64, far: f64) -> bool {
    let v = centre - cam.centre();
    let d = v.length();
    if d <= radius {
        return true;
    }
    if d - radius > far {
        return false;
    }
    let axis = cam.cam_to_world.transform_vector3(DVec3::Z).normalize();
    let angle = (v.dot(axis) / d).clamp(-1.0, 1.0).acos();
    let spread = (radius / d).clamp(0.0, 1.0).asin();
    // A margin for rounding: being wrong here would drop an image that sees the change.
    angle <= widest + spread + 1e-6
}

/// Which cameras can see a set of changed primitives: their bounding balls, and each camera
/// model's widest pixel angle computed once (a scene has a few models and many poses).
pub struct ChangeView {
    balls: Vec<(DVec3, f64)>,
    widest: Vec<(Camera, f64)>,
}

impl ChangeView {
    pub fn new<'a>(changed: impl IntoIterator<Item = &'a Primitive>) -> Self {
        Self {
            balls: changed
                .into_iter()
                .map(|q| bounding_ball(&q.aabb()))
                .collect(),
            widest: Vec::new(),
        }
    }

    /// Whether a ray of `cam` can meet a changed primitive no farther than `far` (see
    /// [`camera_may_see`]).
    pub fn seen_by(&mut self, cam: &Camera, far: f64) -> bool {
        if self.balls.is_empty() {
            return false;
        }
        let w = match self.widest.iter().find(|(c, _)| c.same_pixels(cam)) {
            Some(&(_, w)) => w,
            None => {
                let w = widest_pixel_angle(cam);
                self.widest.push((cam.clone(), w));
                w
            }
        };
        self.balls
            .iter()
            .any(|&(c, r)| camera_may_see(cam, w, c, r, far))
    }
}

/// The pixels of `cam` (row-major indices, ascending) whose ray meets one of `changed` no
/// farther than `far`: where an edit of those primitives (their old and new extents both
/// listed) can change what the image's rays cross.
pub fn pixels_meeting(cam: &Camera, changed: &[Primitive], far: f64) -> Vec<u32> {
    if changed.is_empty() {
        return Vec::new();
    }
    let bvh = Bvh::build(changed);
    (0..cam.height)
        .into_par_iter()
        .map_init(Vec::new, |hits, y| {
            (0..cam.width)
                .filter(|&x| {
                    cam.pixel_ray(x, y).is_some_and(|ray| {
                        bvh.intersect_all(changed, &ray, 0.0, far, hits);
                        !hits.is_empty()
                    })
                })
                .map(|x| y * cam.width + x)
                .collect::<Vec<u32>>()
        })
        .flatten()
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{
        primitives_to_table, Lens, Mei, Primitive, Ray, Shape, FISHEYE_HALF_ANGLE_DEG,
    };
    use glam::DAffine3;
    use proptest::prelude::*;

    fn cuboid(x: f64, label: u8) -> Primitive {
        let t = DAffine3::from_translation(DVec3::new(x, 0.0, 0.0));
        Primitive::new(Shape::Cuboid, t, label, 1).unwrap()
    }

    #[test]
    fn matching_survives_renumbering_and_names_what_changed() {
        let old: Vec<Primitive> = (0..5).map(|i| cuboid(i as f64 * 3.0, 26)).collect();
        let mut new = old.clone();
        new.remove(1); // deleted: ids 2.. shift down by one
        new[2] = cuboid(9.5, 26); // old 3 moved
        new.push(cuboid(30.0, 27)); // added
        let c = PrimitiveChanges::between(
            &primitives_to_table(&old).unwrap(),
            &primitives_to_table(&new).unwrap(),
        )
        .unwrap();
        assert_eq!(c.old_to_new, vec![Some(0), None, Some(1), None, Some(3)]);
        assert_eq!(c.removed, vec![1, 3]);
        assert_eq!(c.added, vec![2, 4]);
        assert!(c.renumbers());
        let same = PrimitiveChanges::between(
            &primitives_to_table(&old).unwrap(),
            &primitives_to_table(&old).unwrap(),
        )
        .unwrap();
        assert!(same.is_empty() && !same.renumbers());
        // A relabel is a change of the primitive, though its geometry stays.
        let mut relabelled = old.clone();
        relabelled[4] = cuboid(12.0, 30);
        let c = PrimitiveChanges::between(
            &primitives_to_table(&old).unwrap(),
            &primitives_to_table(&relabelled).unwrap(),
        )
        .unwrap();
        assert_eq!((c.removed, c.added), (vec![4], vec![4]));
    }

    fn camera(lens: Lens, yaw: f64) -> Camera {
        Camera {
            width: 24,
            height: 10,
            fx: 12.0,
            fy: 12.0,
            cx: 12.0,
            cy: 5.0,
            lens,
            cam_to_world: DAffine3::from_rotation_y(yaw),
        }
    }

    /// Every pixel whose plan differs after an edit is one of `pixels_meeting` of the old and
    /// new extents, and that set is not every pixel.
    #[test]
    fn pixels_meeting_holds_every_pixel_an_edit_changes() {
        use crate::intervals::{plan_image, IntersectParams};
        let (prims, cam) = crate::geometry::demo::street_scene(64, 24);
        let p = IntersectParams::default();
        for i in [5, prims.len() / 2, prims.len() - 1] {
            let q = &prims[i];
            let moved = Primitive::new(
                q.shape.clone(),
                DAffine3::from_translation(DVec3::new(0.0, 0.7, 0.3)) * q.to_world,
                q.label,
                q.instance,
            )
            .unwrap();
            let mut edited = prims.clone();
            edited[i] = moved.clone();
            let before = plan_image(&prims, &Bvh::build(&prims), &cam, &p);
            let after = plan_image(&edited, &Bvh::build(&edited), &cam, &p);
            let meeting = pixels_meeting(&cam, &[q.clone(), moved], p.far);
            let (mut off_a, mut off_b, mut differ) = (0usize, 0usize, 0usize);
            for px in 0..before.hits.len() {
                let (ha, hb) = (before.hits[px] as usize, after.hits[px] as usize);
                let same = ha == hb
                    && before.t_in[off_a..off_a + ha] == after.t_in[off_b..off_b + hb]
                    && before.t_out[off_a..off_a + ha] == after.t_out[off_b..off_b + hb]
                    && before.sky_t1[px] == after.sky_t1[px];
                if !same {
                    differ += 1;
                    assert!(
                        meeting.binary_search(&(px as u32)).is_ok(),
                        "pixel {px} of edit {i}"
                    );
                }
                (off_a, off_b) = (off_a + ha, off_b + hb);
            }
            assert!(
                meeting.len() < before.hits.len(),
                "edit {i} meets every pixel"
            );
            assert!(differ > 0, "edit {i} changed nothing: a useless test case");
        }
    }

    proptest! {
        /// Brute force: whenever a pixel ray meets the ball within `far`, the test says so.
        #[test]
        fn the_cone_test_never_misses_a_ball_a_pixel_ray_meets(
            yaw in -3.2f64..3.2,
            cx in -30.0f64..30.0, cy in -10.0f64..10.0, cz in -30.0f64..30.0,
            r in 0.05f64..4.0,
            far in 5.0f64..60.0,
            fisheye in any::<bool>(),
        ) {
            let lens = if fisheye {
                Lens::Mei(Mei {
                    xi: 1.0, k1: 0.0, k2: 0.0, p1: 0.0, p2: 0.0,
                    max_half_angle_deg: FISHEYE_HALF_ANGLE_DEG,
                })
            } else {
                Lens::Pinhole
            };
            let cam = camera(lens, yaw);
            let widest = widest_pixel_angle(&cam);
            let centre = DVec3::new(cx, cy, cz);
            let mut met = false;
            for y in 0..cam.height {
                for x in 0..cam.width {
                    if let Some(ray) = cam.pixel_ray(x, y) {
                        let Ray { origin, dir } = ray;
                        let t = (centre - origin).dot(dir).clamp(0.0, far);
                        met |= (origin + dir * t - centre).length() <= r;
                    }
                }
            }
            if met {
                prop_assert!(camera_may_see(&cam, widest, centre, r, far));
            }
        }
    }
}
