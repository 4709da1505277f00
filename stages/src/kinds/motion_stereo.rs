//! The `motion_stereo` kind: weak depth of cameras without a stereo partner (KITTI-360's side
//! fisheye cameras) from their own neighbouring frames ([`crate::scene::sweep`]), added to the
//! stereo depth that is already there, so that `train` gets one `stereo_depth` table.

use std::collections::{BTreeMap, HashMap};

use arrow::datatypes::Float32Type;

use super::stereo_depth::{depth_tables, DepthRow};
use crate::geometry::{cameras_from_table, Camera};
use crate::scene::io::image_keys;
use crate::scene::stereo::grey;
use crate::scene::sweep::{
    confirm, lens_mask, shrink, shrink_factor, shrink_grey, shrink_mask, spread, sweep, trim_edges,
    SweepParams, View,
};
use crate::stage::{InputSlot, Inputs, Progress, Result, StageError, Tables, TypedStage};
use crate::tables;

/// The motion stereo stage kind.
pub struct MotionStereo;

impl TypedStage for MotionStereo {
    type Params = SweepParams;
    const KIND: &'static str = "motion_stereo";
    const VERSION: u32 = 1;
    const DESCRIPTION: &'static str =
        "weak depth of cameras with no stereo partner (the side fisheye cameras) by matching each \
         image against the same camera's neighbouring frames: a sweep of distances along every \
         pixel's ray (any lens), census cost, 8-path aggregation, checked against the neighbours' \
         own depth; keeps the stereo depth of the other cameras";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &["cameras", "images", "stereo_depth"],
            optional: false,
            doc: "posed images (and the scene's own stereo depth, kept for the other cameras)",
        },
        InputSlot {
            name: "depth",
            tables: &["stereo_depth"],
            optional: true,
            doc: "stereo depth to keep for the other cameras instead of the scene's (e.g. a \
                  `stereo_depth` stage)",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &["stereo_depth"];

    fn validate(p: &SweepParams) -> Result<()> {
        p.validate()
    }

    fn run(&self, p: &SweepParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let cams = cameras_from_table(inputs.table("scene", "cameras")?)?;
        let images = inputs.table("scene", "images")?;
        let rgb = tables::get_binary(images, "images", "rgb")?;
        let index: HashMap<(u32, u8), usize> = image_keys(images, "images")?
            .iter()
            .enumerate()
            .map(|(i, k)| ((k.0, k.1), i))
            .collect();
        // Per chosen camera, its frames in order.
        let mut by_camera: BTreeMap<u8, BTreeMap<u32, &Camera>> = BTreeMap::new();
        for c in cams.iter().filter(|c| p.cameras.contains(&c.camera)) {
            by_camera
                .entry(c.camera)
                .or_default()
                .insert(c.frame, &c.cam);
        }
        if by_camera.is_empty() && !p.cameras.is_empty() {
            return Err(StageError::Input(format!(
                "no image of the `cameras` table has a camera id in {:?} (`cameras` of \
                 motion_stereo)",
                p.cameras
            )));
        }
        let total: usize = by_camera.values().map(BTreeMap::len).sum();
        let mut done = 0;
        let mut rows: Vec<DepthRow> = Vec::new();
        for (&camera, frames) in &by_camera {
            // Each image at the size it is matched at ([`shrink_factor`]), with its lens mask
            // (which depends on the intrinsics only: computed once per set of them).
            let mut masks: Vec<(&Camera, Vec<bool>)> = Vec::new();
            let mut small: BTreeMap<u32, (Camera, u32, Vec<u8>, usize)> = BTreeMap::new();
            for (&frame, &cam) in frames {
                let i = *index.get(&(frame, camera)).ok_or_else(|| {
                    StageError::Input(format!(
                        "no `images` row for frame {frame} camera {camera} of `cameras`"
                    ))
                })?;
                let (w, h) = (cam.width as usize, cam.height as usize);
                if rgb.value(i).len() != w * h * 3 {
                    return Err(StageError::Input(format!(
                        "images: frame {frame} camera {camera} is not {w}x{h} RGB as the \
                         cameras table says"
                    )));
                }
                let m = match masks.iter().position(|(c, _)| same_intrinsics(c, cam)) {
                    Some(m) => m,
                    None => {
                        masks.push((cam, lens_mask(cam)));
                        masks.len() - 1
                    }
                };
                let f = shrink_factor(cam, p.max_side);
                let g = shrink_grey(&grey(rgb.value(i)), w, h, f);
                small.insert(frame, (shrink(cam, f), f, g, m));
            }
            let shrunk_masks: Vec<Vec<bool>> = masks
                .iter()
                .map(|(cam, m)| {
                    let f = shrink_factor(cam, p.max_side);
                    shrink_mask(m, cam.width as usize, cam.height as usize, f)
                })
                .collect();
            let view = |f: u32| {
                let (cam, _, grey, m) = &small[&f];
                View {
                    cam,
                    grey,
                    in_lens: &shrunk_masks[*m],
                }
            };
            let near = |f: u32| -> Vec<u32> {
                p.neighbours
                    .iter()
                    .filter_map(|&o| f.checked_add_signed(o))
                    .filter(|g| frames.contains_key(g))
                    .collect()
            };
            let mut raw: BTreeMap<u32, Vec<f32>> = BTreeMap::new();
            for &f in frames.keys() {
                progress.update(done as u64, total as u64, "matching");
                let sources: Vec<View> = near(f).into_iter().map(view).collect();
                let d = if sources.is_empty() {
                    vec![0.0; view(f).grey.len()]
                } else {
                    sweep(&view(f), &sources, p)
                };
                raw.insert(f, d);
                done += 1;
            }
            for (&f, d) in &raw {
                let others: Vec<(View, &[f32])> = near(f)
                    .into_iter()
                    .map(|g| (view(g), raw[&g].as_slice()))
                    .collect();
                let (cam, factor) = (frames[&f], small[&f].1);
                let v = view(f);
                let (w, h) = (v.cam.width as usize, v.cam.height as usize);
                let confirmed = confirm(&v, d, &others, p.consistency);
                let trimmed = trim_edges(&confirmed, w, h, p.max_jump, p.max_missing_neighbours);
                rows.push((
                    (f, camera, cam.width, cam.height),
                    spread(&trimmed, w, cam.width as usize, cam.height as usize, factor),
                ));
            }
        }
        progress.update(total as u64, total as u64, "matching");
        // The other cameras' stereo depth, as it came.
        let kept = match inputs.optional_table("depth", "stereo_depth")? {
            Some(t) => t,
            None => inputs.table("scene", "stereo_depth")?,
        };
        let keys = image_keys(kept, "stereo_depth")?;
        let values = tables::get_list::<Float32Type>(kept, "stereo_depth", "depth")?;
        for (i, k) in keys.into_iter().enumerate() {
            if !p.cameras.contains(&k.1) {
                rows.push((k, values.row(i).to_vec()));
            }
        }
        rows.sort_by_key(|r| (r.0 .0, r.0 .1));
        depth_tables(rows)
    }
}

/// Whether two cameras image the same pixels (size, projection and lens; any pose).
fn same_intrinsics(a: &Camera, b: &Camera) -> bool {
    (a.width, a.height, a.fx, a.fy, a.cx, a.cy, a.lens)
        == (b.width, b.height, b.fx, b.fy, b.cx, b.cy, b.lens)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::synthetic::{generate, in_memory::to_tables, SceneParams};

    fn run(params: serde_json::Value, scene: &Tables) -> Result<Tables> {
        let s = MotionStereo;
        let v = crate::Stage::canonical_params(&s, &params)?;
        let mem = crate::MemoryInputs::new([("scene", scene.clone())]);
        crate::Stage::run(&s, &v, &mem.inputs(), &crate::NoProgress)
    }

    /// The synthetic street of `frames` frames, with its fisheye cameras when `fisheye`.
    fn street(frames: u32, fisheye: bool) -> (SceneParams, Tables) {
        let sp = SceneParams {
            frames,
            cameras: if fisheye {
                vec![0, 1, 2, 3]
            } else {
                vec![0, 1]
            },
            ..Default::default()
        };
        let scene = to_tables(&sp, generate(&sp, &crate::NoProgress).unwrap()).unwrap();
        (sp, scene)
    }

    /// The synthetic street with its fisheye cameras: the fisheye images get depth that agrees
    /// with the exact distance, the left camera keeps the scene's stereo depth unchanged.
    #[test]
    fn fisheye_images_get_depth_and_the_left_camera_keeps_its_own() {
        let (sp, scene) = street(4, true);
        let out = run(serde_json::json!({}), &scene).unwrap();
        let t = &out["stereo_depth"];
        let keys = image_keys(t, "stereo_depth").unwrap();
        let depth = tables::get_list::<Float32Type>(t, "stereo_depth", "depth").unwrap();
        let own = &scene["stereo_depth"];
        let own_keys = image_keys(own, "stereo_depth").unwrap();
        let own_depth = tables::get_list::<Float32Type>(own, "stereo_depth", "depth").unwrap();
        assert_eq!(keys.iter().filter(|k| k.1 == 0).count(), own_keys.len());
        assert_eq!(
            keys.iter().filter(|k| k.1 >= 2).count(),
            2 * sp.frames as usize
        );
        let gt_t = &scene["gt_depth"];
        let gt_keys = image_keys(gt_t, "gt_depth").unwrap();
        let gt = tables::get_list::<Float32Type>(gt_t, "gt_depth", "depth").unwrap();
        let (mut near, mut found, mut gross, mut sky) = (0, 0, 0, 0);
        for (i, k) in keys.iter().enumerate() {
            if k.1 == 0 {
                let j = own_keys.iter().position(|o| o == k).unwrap();
                assert_eq!(depth.row(i), own_depth.row(j), "frame {} left changed", k.0);
                continue;
            }
            let j = gt_keys.iter().position(|g| g == k).unwrap();
            for (&d, &g) in depth.row(i).iter().zip(gt.row(j)) {
                near += (g > 0.0 && g < 10.0) as usize;
                if d > 0.0 {
                    found += 1;
                    sky += (g == 0.0) as usize;
                    gross += (g > 0.0 && ((d - g) / g).abs() > 0.1) as usize;
                }
            }
        }
        eprintln!(
            "fisheye depth: {found} values ({:.1}% of pixels under 10 m), {gross} more than 10% \
             off, {sky} on sky",
            100.0 * found as f64 / near as f64
        );
        assert!(
            found * 5 > near,
            "only {found} depths for {near} pixels under 10 m"
        );
        assert!(
            gross * 50 < found,
            "{gross} of {found} depths are more than 10% off"
        );
        assert!(sky * 100 < found, "{sky} of {found} depths lie on the sky");
    }

    #[test]
    fn no_cameras_pass_the_stereo_depth_through() {
        let (_, scene) = street(2, true);
        let out = run(serde_json::json!({"cameras": []}), &scene).unwrap();
        assert_eq!(out["stereo_depth"], scene["stereo_depth"]);
    }

    #[test]
    fn a_camera_the_scene_lacks_is_an_error_naming_the_parameter() {
        let (_, scene) = street(2, false);
        let e = run(serde_json::json!({}), &scene).unwrap_err().to_string();
        assert!(e.contains("`cameras` of motion_stereo"), "{e}");
        let e = run(serde_json::json!({"neighbours": [0]}), &scene)
            .unwrap_err()
            .to_string();
        assert!(e.contains("neighbours"), "{e}");
    }
}
