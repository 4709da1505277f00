//! Motion stereo for any lens: weak depth of one image from the same camera's images of
//! neighbouring frames. KITTI-360's side fisheye cameras look across the car's motion, so two
//! frames of one of them are a stereo pair with the frame spacing as baseline; they have no
//! partner camera, and no 2D network labels them, so this is where their depth comes from.
//!
//! A sweep along each pixel's ray (not a plane sweep: a fisheye sees 180 degrees): at each of
//! `hypotheses` distances, evenly spaced in inverse distance from `min_depth_m` to infinity
//! (the sky and far facades then have a hypothesis of their own), the point on every reference ray is projected into each neighbour image and
//! its grey level sampled (bilinear), which warps the neighbour into the reference view as if
//! the scene were a sphere of that radius. The census transform (as in [`super::stereo`]) of the
//! warped image against the reference's gives a Hamming cost per pixel and distance; per pixel
//! the sum of the two lowest neighbours' costs is kept (a point hidden in one neighbour is seen
//! by another), then aggregated along 8 paths (semi-global matching), and the winner refined
//! and checked for uniqueness. Winners at the near end (too near to tell) and at or beyond
//! `max_depth_m` (too far for the baseline) are dropped. Last, every depth must be confirmed by a neighbour's own depth map (the
//! left-right check of rectified stereo, through the poses): its point, seen from that
//! neighbour, lies within `consistency` (relative) of the neighbour's depth there.
//!
//! Depths are distances along the ray for a fisheye (the `stereo_depth` convention for a lens
//! that sees beyond 90 degrees), z-depths for a pinhole.

use glam::{DAffine3, DVec3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::stereo::{census, check_matching, sgm_sum, winner};
use crate::geometry::Camera;
use crate::{Result, StageError};

/// Parameters of `motion_stereo`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct SweepParams {
    /// Cameras whose images get depth (numbers or KITTI-360 names; 2, 3: the fisheye cameras).
    /// Empty: none, the stereo depth passes through unchanged (a switch for comparisons).
    #[serde(deserialize_with = "crate::geometry::camera::camera_ids")]
    #[schemars(with = "Vec<crate::geometry::camera::CameraName>")]
    pub cameras: Vec<u8>,
    /// Frame offsets of the images each one is matched against (those present are used).
    pub neighbours: Vec<i32>,
    /// The nearest distance searched, metres (a winner there is dropped).
    pub min_depth_m: f64,
    /// Depths at or beyond this are dropped, metres (the search goes on to infinity). 10, not
    /// the perspective stereo's 15: all of 10 to 15 m spans about two distance steps, and
    /// training with those depths made far depth worse (docs/experiments/fisheye.md).
    pub max_depth_m: f64,
    /// Distances searched per pixel, evenly spaced in inverse distance from `min_depth_m` to
    /// infinity.
    pub hypotheses: u32,
    /// Census window radius: 3 = 7x7. It found more of the weakly textured surfaces than 5x5
    /// on the synthetic street at the same error rate.
    pub census_radius: u32,
    /// Penalty of a one-step change of distance step along a path.
    pub p1: u16,
    /// Penalty of a larger change of distance step along a path.
    pub p2: u16,
    /// The best cost must beat the second best (more than a step away) by this fraction.
    pub uniqueness: f32,
    /// A depth is kept when a neighbour's depth map confirms its point within this fraction.
    pub consistency: f64,
    /// A depth is kept only where none of its 8 neighbours differs by more than this fraction.
    /// Wrong matches gather along holes and depth edges.
    pub max_jump: f64,
    /// A depth is kept only where at most this many of its 8 neighbours have no depth.
    pub max_missing_neighbours: u32,
    /// Images wider or taller than this (pixels) are matched at 1/n of their size. The n is the
    /// smallest whole number that brings both within it (n x n pixels averaged), and each depth
    /// is given back to the n x n pixels it came from: at 1400 px the distance steps lie several
    /// pixels apart, so full resolution would cost 16 times the time for no finer depth.
    pub max_side: u32,
}

impl Default for SweepParams {
    fn default() -> Self {
        Self {
            cameras: vec![2, 3],
            neighbours: vec![-2, -1, 1, 2],
            min_depth_m: 1.0,
            max_depth_m: 10.0,
            hypotheses: 64,
            census_radius: 3,
            p1: 8,
            p2: 48,
            uniqueness: 0.05,
            consistency: 0.05,
            max_jump: 0.1,
            max_missing_neighbours: 2,
            max_side: 400,
        }
    }
}

impl SweepParams {
    /// Checks the parameters; errors name them.
    pub fn validate(&self) -> Result<()> {
        let p = self;
        let bad = |m: String| Err(StageError::Params(m));
        if p.cameras.iter().any(|&c| c > 3) {
            return bad(
                "`cameras` may list only KITTI-360 cameras 0 .. 3 (2, 3: the fisheye ones)".into(),
            );
        }
        if p.neighbours.is_empty() || p.neighbours.contains(&0) {
            return bad(format!(
                "`neighbours` must list non-zero frame offsets, got {:?}",
                p.neighbours
            ));
        }
        if !(p.min_depth_m.is_finite()
            && p.max_depth_m.is_finite()
            && 0.0 < p.min_depth_m
            && p.min_depth_m < p.max_depth_m)
        {
            return bad(format!(
                "need 0 < `min_depth_m` < `max_depth_m`, got {} and {}",
                p.min_depth_m, p.max_depth_m
            ));
        }
        if !(4..=256).contains(&p.hypotheses) {
            return bad(format!(
                "`hypotheses` must be in 4..=256, got {}",
                p.hypotheses
            ));
        }
        check_matching(p.census_radius, p.p1, p.p2)?;
        if !(0.0..1.0).contains(&p.uniqueness) {
            return bad(format!(
                "`uniqueness` must be in [0, 1), got {}",
                p.uniqueness
            ));
        }
        if !(p.consistency > 0.0 && p.consistency < 1.0) {
            return bad(format!(
                "`consistency` must be in (0, 1), got {}",
                p.consistency
            ));
        }
        if !(p.max_jump > 0.0 && p.max_jump.is_finite()) {
            return bad(format!("`max_jump` must be positive, got {}", p.max_jump));
        }
        if p.max_side < 16 {
            return bad(format!(
                "`max_side` must be at least 16, got {}",
                p.max_side
            ));
        }
        if p.max_missing_neighbours > 8 {
            return bad(format!(
                "`max_missing_neighbours` must be at most 8, got {}",
                p.max_missing_neighbours
            ));
        }
        Ok(())
    }

    /// Distance of (fractional) hypothesis `k`: evenly spaced in inverse distance, `k = 0` at
    /// `min_depth_m`, the last one at infinity.
    pub fn distance(&self, k: f64) -> f64 {
        let n = (self.hypotheses - 1) as f64;
        self.min_depth_m / (1.0 - k / n).max(0.0)
    }
}

/// One image: its camera and grey levels (`width * height`).
#[derive(Clone, Copy)]
pub struct View<'a> {
    pub cam: &'a Camera,
    pub grey: &'a [u8],
    /// Per pixel: inside the lens (see [`lens_mask`]).
    pub in_lens: &'a [bool],
}

/// Per pixel of `cam`: whether it sees the scene through the lens (computed once per lens: it
/// does not depend on the pose).
pub fn lens_mask(cam: &Camera) -> Vec<bool> {
    let w = cam.width;
    (0..cam.width * cam.height)
        .into_par_iter()
        .map(|i| cam.pixel_in_lens(i % w, i / w))
        .collect()
}

/// The factor an image of `cam` is shrunk by to fit within `max_side` pixels.
pub fn shrink_factor(cam: &Camera, max_side: u32) -> u32 {
    cam.width.max(cam.height).div_ceil(max_side).max(1)
}

/// `cam` for its image shrunk by `f` (`f` x `f` pixels to one, leftover rows and columns
/// dropped): image coordinates scale by 1 / f.
pub fn shrink(cam: &Camera, f: u32) -> Camera {
    let s = f as f64;
    Camera {
        width: cam.width / f,
        height: cam.height / f,
        fx: cam.fx / s,
        fy: cam.fy / s,
        cx: cam.cx / s,
        cy: cam.cy / s,
        ..cam.clone()
    }
}

/// Grey levels (`w` x `h`) shrunk by `f`: the mean of each `f` x `f` block.
pub fn shrink_grey(grey: &[u8], w: usize, h: usize, f: u32) -> Vec<u8> {
    let f = f as usize;
    if f == 1 {
        return grey.to_vec();
    }
    let (ws, hs) = (w / f, h / f);
    (0..ws * hs)
        .map(|i| {
            let (x, y) = (i % ws * f, i / ws * f);
            let sum: u32 = (y..y + f)
                .flat_map(|yy| grey[yy * w + x..yy * w + x + f].iter())
                .map(|&g| g as u32)
                .sum();
            ((sum + (f * f / 2) as u32) / (f * f) as u32) as u8
        })
        .collect()
}

/// A lens mask (`w` x `h`) shrunk by `f`: a pixel is in the lens when its whole block is.
pub fn shrink_mask(mask: &[bool], w: usize, h: usize, f: u32) -> Vec<bool> {
    let f = f as usize;
    let (ws, hs) = (w / f, h / f);
    (0..ws * hs)
        .map(|i| {
            let (x, y) = (i % ws * f, i / ws * f);
            (y..y + f).all(|yy| mask[yy * w + x..yy * w + x + f].iter().all(|&m| m))
        })
        .collect()
}

/// A depth map of width `ws` matched at 1/f of a `w` x `h` image, given back to every pixel
/// of each block (0 for the leftover rows and columns).
pub fn spread(small: &[f32], ws: usize, w: usize, h: usize, f: u32) -> Vec<f32> {
    let f = f as usize;
    let hs = small.len() / ws.max(1);
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w / f, i / w / f);
            if x < ws && y < hs {
                small[y * ws + x]
            } else {
                0.0
            }
        })
        .collect()
}

/// Unit world direction of every pixel's centre ray (`None` outside the lens).
fn pixel_dirs(v: &View) -> Vec<Option<DVec3>> {
    let w = v.cam.width;
    (0..v.cam.width * v.cam.height)
        .into_par_iter()
        .map(|i| {
            if !v.in_lens[i as usize] {
                return None;
            }
            v.cam.pixel_ray(i % w, i / w).map(|r| r.dir)
        })
        .collect()
}

/// Bilinear grey level of `v` at image point `(u, v)` (pixel centres at +0.5); `None` outside
/// the image or where a tap lies outside the lens.
fn sample(v: &View, u: f64, y: f64) -> Option<f32> {
    let (w, h) = (v.cam.width as usize, v.cam.height as usize);
    let (fx, fy) = (u - 0.5, y - 0.5);
    if !(fx >= 0.0 && fy >= 0.0) {
        return None;
    }
    let (x0, y0) = (fx as usize, fy as usize);
    if x0 + 1 >= w || y0 + 1 >= h {
        return None;
    }
    let (ax, ay) = ((fx - x0 as f64) as f32, (fy - y0 as f64) as f32);
    let i = y0 * w + x0;
    let taps = [i, i + 1, i + w, i + w + 1];
    if taps.iter().any(|&t| !v.in_lens[t]) {
        return None;
    }
    let g = taps.map(|t| v.grey[t] as f32);
    Some((g[0] * (1.0 - ax) + g[1] * ax) * (1.0 - ay) + (g[2] * (1.0 - ax) + g[3] * ax) * ay)
}

/// Image point of the camera-frame point (or direction) `q` ([`Camera::project`] without its
/// per-call pose inversion); `None` where the lens does not image it.
fn image_point(cam: &Camera, q: DVec3) -> Option<(f64, f64)> {
    let m = cam.lens.to_plane(q)?;
    Some((cam.fx * m.x + cam.cx, cam.fy * m.y + cam.cy))
}

/// The depth value a depth map of `cam` (world -> camera `to_cam`) holds for the point `t`
/// metres along the unit world direction `dir` from its centre.
fn depth_value(cam: &Camera, to_cam: &DAffine3, dir: DVec3, t: f64) -> f64 {
    t * cam.depth_scale(to_cam.transform_vector3(dir))
}

/// Distance along the ray of the reference pixel with world direction `dir` for depth-map value
/// `d` (inverse of [`depth_value`]).
fn ray_distance(cam: &Camera, to_cam: &DAffine3, dir: DVec3, d: f64) -> f64 {
    d / cam.depth_scale(to_cam.transform_vector3(dir))
}

/// Depth map of `reference` (0 = no value) matched against `neighbours`, before the
/// cross-frame check ([`confirm`]).
pub fn sweep(reference: &View, neighbours: &[View], p: &SweepParams) -> Vec<f32> {
    let cam = reference.cam;
    let (w, h) = (cam.width as usize, cam.height as usize);
    let n = w * h;
    let nd = p.hypotheses as usize;
    let r = p.census_radius as usize;
    let bits = ((2 * r + 1) * (2 * r + 1) - 1) as u16;
    let dirs = pixel_dirs(reference);
    let ref_census = census(reference.grey, w, h, r);
    let origin = cam.centre();
    // Per distance step ([nd, n]): the lowest and second-lowest neighbour cost.
    let mut best = vec![[bits, bits]; nd * n];
    for nb in neighbours {
        // In the neighbour's frame the point at distance s is o + s d; the lens sees only its
        // direction, so o / s + d serves, infinity (1 / s = 0) included.
        let to_nb = nb.cam.world_to_cam();
        let o = to_nb.transform_point3(origin);
        let dirs_nb: Vec<Option<DVec3>> = dirs
            .iter()
            .map(|d| d.map(|d| to_nb.transform_vector3(d)))
            .collect();
        best.par_chunks_mut(n).enumerate().for_each(|(k, best_k)| {
            let inv = 1.0 / p.distance(k as f64);
            let mut warped = vec![0u8; n];
            let mut valid = vec![false; n];
            for (i, d) in dirs_nb.iter().enumerate() {
                let Some(d) = d else { continue };
                let Some((u, v)) = image_point(nb.cam, o * inv + *d) else {
                    continue;
                };
                if let Some(g) = sample(nb, u, v) {
                    warped[i] = g.round() as u8;
                    valid[i] = true;
                }
            }
            let c = census(&warped, w, h, r);
            for i in 0..n {
                if !valid[i] {
                    continue;
                }
                let cost = (ref_census[i] ^ c[i]).count_ones() as u16;
                let b = &mut best_k[i];
                if cost < b[0] {
                    *b = [cost, b[0]];
                } else if cost < b[1] {
                    b[1] = cost;
                }
            }
        });
    }
    // Matching cost [h, w, nd] from the two best neighbours.
    let mut cost = vec![0u8; n * nd];
    cost.par_chunks_mut(nd).enumerate().for_each(|(i, c)| {
        for (k, ck) in c.iter_mut().enumerate() {
            let b = best[k * n + i];
            *ck = (b[0] + b[1]) as u8;
        }
    });
    drop(best);
    let sum = sgm_sum(&cost, w, h, nd, 8, p.p1, p.p2);
    drop(cost);
    let to_cam = cam.world_to_cam();
    (0..n)
        .into_par_iter()
        .map(|i| {
            let Some(d) = dirs[i] else { return 0.0 };
            let Some(k) = winner(&sum[i * nd..(i + 1) * nd], p.uniqueness) else {
                return 0.0;
            };
            let t = p.distance(k as f64);
            if k < 0.5 || t >= p.max_depth_m {
                return 0.0;
            }
            depth_value(cam, &to_cam, d, t) as f32
        })
        .collect()
}

/// `depth` (of `reference`) with the values no neighbour confirms set to 0: a value's point,
/// seen from a neighbour, must lie within `tolerance` (relative) of that neighbour's own depth
/// map (nearest pixel).
pub fn confirm(
    reference: &View,
    depth: &[f32],
    neighbours: &[(View, &[f32])],
    tolerance: f64,
) -> Vec<f32> {
    let cam = reference.cam;
    let w = cam.width;
    let to_cam = cam.world_to_cam();
    let origin = cam.centre();
    let others: Vec<_> = neighbours
        .iter()
        .map(|(v, d)| (v, *d, v.cam.world_to_cam()))
        .collect();
    (0..depth.len())
        .into_par_iter()
        .map(|i| {
            let di = depth[i];
            if di <= 0.0 {
                return 0.0;
            }
            let Some(ray) = cam.pixel_ray(i as u32 % w, i as u32 / w) else {
                return 0.0;
            };
            let x = origin + ray_distance(cam, &to_cam, ray.dir, di as f64) * ray.dir;
            let confirmed = others.iter().any(|(v, dm, to_v)| {
                let c = v.cam;
                let Some((u, y)) = image_point(c, to_v.transform_point3(x)) else {
                    return false;
                };
                if !(u >= 0.0 && y >= 0.0 && u < c.width as f64 && y < c.height as f64) {
                    return false;
                }
                let j = y as usize * c.width as usize + u as usize;
                let dj = dm[j] as f64;
                if dj <= 0.0 {
                    return false;
                }
                let seen = x - c.centre();
                let want = depth_value(c, to_v, seen.normalize(), seen.length());
                (want - dj).abs() <= tolerance * dj
            });
            if confirmed {
                di
            } else {
                0.0
            }
        })
        .collect()
}

/// `depth` (`w` x `h`, 0 = none) without the values next to a depth edge (a neighbour more than
/// `max_jump` away, relative) or next to more than `max_missing` holes (pixels outside the
/// image count as holes).
pub fn trim_edges(depth: &[f32], w: usize, h: usize, max_jump: f64, max_missing: u32) -> Vec<f32> {
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            let d = depth[i];
            if d <= 0.0 {
                return 0.0;
            }
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let mut missing = 0;
            for (dx, dy) in [
                (-1, -1),
                (0, -1),
                (1, -1),
                (-1, 0),
                (1, 0),
                (-1, 1),
                (0, 1),
                (1, 1),
            ] {
                let (xx, yy) = (x + dx, y + dy);
                let n = if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                    0.0
                } else {
                    depth[yy as usize * w + xx as usize]
                };
                if n <= 0.0 {
                    missing += 1;
                } else if ((n - d).abs() as f64) > max_jump * d as f64 {
                    return 0.0;
                }
            }
            if missing > max_missing {
                0.0
            } else {
                d
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Lens, Mei};
    use glam::DMat3;

    /// A KITTI-360-shaped fisheye (MEI, about 190 degrees) of `side` pixels at `pos`, looking
    /// along +z.
    fn fisheye(side: u32, pos: DVec3) -> Camera {
        let s = side as f64 / 1400.0;
        Camera {
            width: side,
            height: side,
            fx: 1336.0 * s,
            fy: 1336.0 * s,
            cx: 700.0 * s,
            cy: 700.0 * s,
            lens: Lens::Mei(Mei {
                xi: 2.2,
                k1: 0.017,
                k2: 1.65,
                p1: 4e-4,
                p2: 4e-4,
                max_half_angle_deg: crate::geometry::FISHEYE_HALF_ANGLE_DEG,
            }),
            cam_to_world: DAffine3::from_mat3_translation(DMat3::IDENTITY, pos),
        }
    }

    /// A smooth random texture on a 0.2 m grid (bilinear between hashed values).
    fn texture(x: f64, y: f64) -> f64 {
        let v = |i: i64, j: i64| {
            (crate::scene::rng::hash(&[i as u64, j as u64, 7]) % 200) as f64 + 28.0
        };
        let (gx, gy) = (x / 0.2, y / 0.2);
        let (i, j) = (gx.floor() as i64, gy.floor() as i64);
        let (fx, fy) = (gx - i as f64, gy - j as f64);
        (v(i, j) * (1.0 - fx) + v(i + 1, j) * fx) * (1.0 - fy)
            + (v(i, j + 1) * (1.0 - fx) + v(i + 1, j + 1) * fx) * fy
    }

    /// The image of a textured wall `z = wall` in front of a uniform sky, and each pixel's
    /// distance to the wall (0: sky or outside the lens).
    fn render(cam: &Camera, wall: f64) -> (Vec<u8>, Vec<f32>) {
        let w = cam.width;
        (0..w * cam.height)
            .map(|i| match cam.pixel_ray(i % w, i / w) {
                None => (0, 0.0),
                Some(r) if r.dir.z > 0.2 => {
                    let t = (wall - r.origin.z) / r.dir.z;
                    let p = r.at(t);
                    (texture(p.x, p.y).round() as u8, t as f32)
                }
                Some(_) => (200, 0.0),
            })
            .unzip()
    }

    #[test]
    fn distances_are_even_in_inverse_from_the_nearest_to_infinity() {
        let p = SweepParams::default();
        let n = (p.hypotheses - 1) as f64;
        assert!((p.distance(0.0) - p.min_depth_m).abs() < 1e-12);
        assert!(p.distance(n).is_infinite());
        let step = 1.0 / p.distance(0.0) - 1.0 / p.distance(1.0);
        for k in 1..p.hypotheses - 1 {
            let k = k as f64;
            let s = 1.0 / p.distance(k) - 1.0 / p.distance(k + 1.0);
            assert!((s - step).abs() < 1e-12, "step {k}: {s} vs {step}");
        }
    }

    /// A fisheye moving across a textured wall (0.8 m a frame, as the side cameras do): the
    /// middle view's depth, confirmed by its neighbours', is the wall's distance.
    #[test]
    fn a_fisheye_moving_across_a_textured_wall_finds_its_distance() {
        let side = 160;
        let wall = 5.0;
        let cams: Vec<Camera> = [-1.6, -0.8, 0.0, 0.8, 1.6]
            .iter()
            .map(|&x| fisheye(side, DVec3::new(x, 0.0, 0.0)))
            .collect();
        let rendered: Vec<_> = cams.iter().map(|c| render(c, wall)).collect();
        let masks: Vec<Vec<bool>> = cams.iter().map(lens_mask).collect();
        let views: Vec<View> = (0..cams.len())
            .map(|i| View {
                cam: &cams[i],
                grey: &rendered[i].0,
                in_lens: &masks[i],
            })
            .collect();
        let p = SweepParams {
            census_radius: 3,
            ..Default::default()
        };
        let raw: Vec<Vec<f32>> = (1..4)
            .map(|i| sweep(&views[i], &[views[i - 1], views[i + 1]], &p))
            .collect();
        let mid = confirm(
            &views[2],
            &raw[1],
            &[(views[1], &raw[0]), (views[3], &raw[2])],
            p.consistency,
        );
        let mid = trim_edges(&mid, side as usize, side as usize, p.max_jump, 2);
        let gt = &rendered[2].1;
        // Wall pixels within 60 degrees of the axis and nearer than max_depth_m: the texture
        // is resolved there and both neighbours see them.
        let (mut n, mut found, mut errs, mut sky) = (0, 0, Vec::new(), 0);
        for (i, (&d, &g)) in mid.iter().zip(gt).enumerate() {
            let Some(r) = cams[2].pixel_ray(i as u32 % side, i as u32 / side) else {
                assert_eq!(d, 0.0, "pixel {i} outside the lens has a depth");
                continue;
            };
            if g == 0.0 {
                sky += (d > 0.0) as usize;
                continue;
            }
            if r.dir.z < 0.5 || g as f64 >= p.max_depth_m {
                continue;
            }
            n += 1;
            if d > 0.0 {
                found += 1;
                errs.push(((d - g) / g).abs() as f64);
            }
        }
        errs.sort_by(f64::total_cmp);
        let median = errs[errs.len() / 2];
        let gross = errs.iter().filter(|&&e| e > 0.1).count() as f64 / errs.len() as f64;
        eprintln!(
            "wall at {wall} m: {found} of {n} pixels ({:.1}%), median |rel err| {median:.4}, \
             >10%: {:.2}%, sky pixels with a depth: {sky}",
            100.0 * found as f64 / n as f64,
            100.0 * gross
        );
        assert!(
            found * 2 > n,
            "only {found} of {n} wall pixels have a depth"
        );
        assert!(median < 0.03, "median relative error {median}");
        assert!(
            gross < 0.02,
            "{:.3} of the depths are more than 10% off",
            gross
        );
        assert_eq!(sky, 0, "the uniform sky got depths");
    }

    #[test]
    fn trimming_drops_depths_beside_edges_and_holes() {
        // 5 x 3: a step from 2 m to 4 m between columns 1 and 2, a hole at (4, 0).
        let d = [
            2.0, 2.0, 4.0, 4.0, 0.0, //
            2.0, 2.0, 4.0, 4.0, 4.0, //
            2.0, 2.0, 4.0, 4.0, 4.0f32,
        ];
        // Border pixels miss 3 or 5 neighbours: with 5 missing allowed only the edge and the
        // hole decide.
        let t = trim_edges(&d, 5, 3, 0.1, 5);
        assert_eq!(
            t,
            vec![
                2.0, 0.0, 0.0, 4.0, 0.0, //
                2.0, 0.0, 0.0, 4.0, 4.0, //
                2.0, 0.0, 0.0, 4.0, 4.0,
            ]
        );
        // With no hole allowed only the two pixels with eight neighbours can stay, and a 100%
        // jump is under a 150% threshold.
        let t = trim_edges(&d, 5, 3, 1.5, 0);
        let mut want = vec![0.0; 15];
        (want[6], want[7]) = (2.0, 4.0);
        assert_eq!(t, want);
        let t = trim_edges(&d, 5, 3, 1.5, 3);
        assert_eq!(t[8], 4.0, "(3, 1) misses only the hole at (4, 0)");
        assert_eq!(t[0], 0.0, "a corner misses 5 neighbours");
    }
}
