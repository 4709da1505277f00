//! Depth sensors of the synthetic scene: weak stereo depth derived from the true depth (noise
//! growing with distance, holes, limited range) and a LiDAR scan (a spinning multi-beam
//! scanner cast against the true geometry, projected into the left camera).

use glam::DVec3;

use super::rng::{fbm2, Purpose, Rng};

/// Parameters of the stereo depth model.
#[derive(Debug, Clone, Copy)]
pub struct StereoModel {
    /// Farthest depth that stereo reports, metres.
    pub max_depth: f64,
    /// Focal length times baseline, pixel metres (disparity = fb / z).
    pub fb: f64,
    /// Pixels of a 176-pixel-wide image per field cell (hole blobs).
    pub width: usize,
    pub height: usize,
}

/// Standard deviation of stereo depth error at depth `z` (grows with z^2, as a fixed
/// disparity error does).
pub fn stereo_sigma(z: f64) -> f64 {
    0.02 + 0.003 * z * z
}

/// Weak stereo depth for one left image from its true z-depth (0 = sky) and over-exposure mask.
pub fn stereo_depth(
    m: &StereoModel,
    gt: &[f32],
    overexposed: &[bool],
    seed: u64,
    frame: u32,
) -> Vec<f32> {
    let (w, h) = (m.width, m.height);
    let mut rng = Rng::new(seed, Purpose::Stereo, &[frame as u64]);
    let hole_key = rng.next_u64();
    let cell = 7.0 * w as f64 / 176.0;
    let mut out = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            // Draw every pixel's randoms in a fixed order, whatever the branch below.
            let (n, u, o) = (rng.normal(), rng.f64(), rng.f64());
            let z = gt[i] as f64;
            if z <= 0.0 || z >= m.max_depth {
                continue;
            }
            // No match: the point leaves the right image, the patch is saturated (no
            // texture), it borders a depth discontinuity (occlusion), or a random hole blob.
            let disparity = m.fb / z;
            if (x as f64 + 0.5) - disparity < 0.0 {
                continue;
            }
            if overexposed[i] && u < 0.8 {
                continue;
            }
            let edge = [(x > 0).then(|| i - 1), (x + 1 < w).then(|| i + 1)]
                .into_iter()
                .chain([(y > 0).then(|| i - w), (y + 1 < h).then(|| i + w)])
                .flatten()
                .any(|j| {
                    let zj = gt[j] as f64;
                    zj <= 0.0 || (zj - z).abs() > 0.08 * z
                });
            if edge && u < 0.7 {
                continue;
            }
            if fbm2(hole_key, x as f64 / cell, y as f64 / cell) > 0.68 {
                continue;
            }
            let d = if o < 0.01 {
                1.0 + (m.max_depth - 1.0) * u // gross mismatch
            } else {
                z + stereo_sigma(z) * n
            };
            if d > 0.1 && d < m.max_depth {
                out[i] = d as f32;
            }
        }
    }
    out
}

/// A spinning multi-beam LiDAR (Velodyne HDL-64E-like, as on the KITTI-360 car).
#[derive(Debug, Clone, Copy)]
pub struct LidarModel {
    /// Beam elevations span [min_elevation, max_elevation] degrees, evenly.
    pub beams: u32,
    pub min_elevation_deg: f64,
    pub max_elevation_deg: f64,
    /// Horizontal angular step, degrees.
    pub azimuth_step_deg: f64,
    /// Range noise standard deviation, metres.
    pub sigma: f64,
    /// Maximum range, metres.
    pub max_range: f64,
}

impl Default for LidarModel {
    fn default() -> Self {
        Self {
            beams: 64,
            min_elevation_deg: -24.9,
            max_elevation_deg: 2.0,
            azimuth_step_deg: 0.2,
            sigma: 0.02,
            max_range: 100.0,
        }
    }
}

/// Sparse LiDAR depth in one camera. `origin` is the scanner centre and `basis` its axes
/// (forward, left, up) in the scene frame; `cast(origin, dir)` returns the distance to the
/// first true surface; `project(p)` returns pixel (u, v) and z-depth in the camera.
#[allow(clippy::too_many_arguments)]
pub fn lidar_depth(
    m: &LidarModel,
    origin: DVec3,
    basis: [DVec3; 3],
    width: u32,
    height: u32,
    cast: impl Fn(DVec3, DVec3) -> Option<f64>,
    project: impl Fn(DVec3) -> Option<(f64, f64, f64)>,
    seed: u64,
    frame: u32,
) -> Vec<f32> {
    let (w, h) = (width as usize, height as usize);
    let mut rng = Rng::new(seed, Purpose::Lidar, &[frame as u64]);
    let mut out = vec![0f32; w * h];
    let steps = (120.0 / m.azimuth_step_deg).round() as i64;
    for b in 0..m.beams {
        let e = (m.min_elevation_deg
            + (m.max_elevation_deg - m.min_elevation_deg) * b as f64 / (m.beams.max(2) - 1) as f64)
            .to_radians();
        for k in -steps / 2..=steps / 2 {
            let a = (k as f64 * m.azimuth_step_deg).to_radians();
            let n = rng.normal();
            let dir = basis[0] * (a.cos() * e.cos())
                + basis[1] * (a.sin() * e.cos())
                + basis[2] * e.sin();
            let Some(t) = cast(origin, dir) else { continue };
            if t > m.max_range {
                continue;
            }
            let p = origin + dir * (t + m.sigma * n);
            let Some((u, v, z)) = project(p) else {
                continue;
            };
            if u < 0.0 || v < 0.0 || z <= 0.0 || z > m.max_range {
                continue;
            }
            let (x, y) = (u as usize, v as usize);
            if x >= w || y >= h {
                continue;
            }
            let i = y * w + x;
            if out[i] == 0.0 || (z as f32) < out[i] {
                out[i] = z as f32;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stereo_is_range_limited_noisy_and_holey() {
        let (w, h) = (176, 47);
        let gt: Vec<f32> = (0..w * h).map(|i| 2.0 + (i % w) as f32 * 0.2).collect();
        let over = vec![false; w * h];
        let m = StereoModel {
            max_depth: 15.0,
            fb: 40.0,
            width: w,
            height: h,
        };
        let s = stereo_depth(&m, &gt, &over, 3, 7);
        assert_eq!(s, stereo_depth(&m, &gt, &over, 3, 7));
        let valid: Vec<usize> = (0..w * h).filter(|&i| s[i] > 0.0).collect();
        assert!(valid.iter().all(|&i| s[i] < 15.0));
        let near = gt.iter().filter(|&&z| z < 15.0).count();
        assert!(
            valid.len() < near && valid.len() > near / 3,
            "{} of {near}",
            valid.len()
        );
        let err: f64 = valid
            .iter()
            .map(|&i| (s[i] - gt[i]).abs() as f64)
            .sum::<f64>()
            / valid.len() as f64;
        assert!(err > 0.01 && err < 1.0, "{err}");
    }

    #[test]
    fn lidar_sees_a_wall_accurately() {
        // Camera at the origin looking along +x (scene frame) at a wall x = 10.
        let cast = |o: DVec3, d: DVec3| (d.x > 1e-9).then(|| (10.0 - o.x) / d.x);
        let project = |p: DVec3| {
            let z = p.x;
            Some((50.0 + 50.0 * (-p.y) / z, 25.0 + 50.0 * (-p.z) / z, z))
        };
        let basis = [DVec3::X, DVec3::Y, DVec3::Z];
        let d = lidar_depth(
            &LidarModel::default(),
            DVec3::ZERO,
            basis,
            100,
            50,
            cast,
            project,
            1,
            0,
        );
        let valid: Vec<f32> = d.into_iter().filter(|&z| z > 0.0).collect();
        assert!(valid.len() > 100);
        assert!(valid.iter().all(|&z| (z - 10.0).abs() < 0.2));
    }
}
