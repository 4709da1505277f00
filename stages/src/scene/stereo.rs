//! The `stereo_depth` stage kind: weak depth from rectified stereo pairs, as the paper obtains
//! its depth supervision, for scenes that bring no depth of their own (KITTI-360).
//!
//! Semi-global matching (Hirschmuller 2008): a census transform (`census_radius`, 5x5 by
//! default: 24 bits) of both grey images, Hamming matching cost over disparities
//! `0..max_disparity`, cost aggregation along 8 (or 4) scanline directions with penalties `p1`
//! (one-pixel disparity change) and `p2` (larger jumps), winner-takes-all, a left-right
//! consistency check (the right disparity map from the same aggregated volume, `|d_L - d_R| <=
//! lr_tolerance`), a uniqueness ratio, and parabola sub-pixel refinement. Depth `z = fx * b /
//! d`; only `z < max_depth_m` is kept (0 = no value), as the paper keeps near-range stereo.
//!
//! Rows of a horizontal path are independent (rayon over rows); a vertical or diagonal path is
//! a sweep over rows where every pixel of a row depends only on the previous row (rayon over
//! the row's pixels). Memory: the aggregated volume is `w * h * max_disparity` u16.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{Result, StageError};

/// Parameters of `stereo_depth`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct StereoParams {
    /// Number of disparities searched (0..max_disparity pixels).
    pub max_disparity: u32,
    /// Census window radius: 2 = 5x5, 3 = 7x7 (48 bits).
    pub census_radius: u32,
    /// Penalty of a one-pixel disparity change along a path.
    pub p1: u16,
    /// Penalty of a larger disparity jump.
    pub p2: u16,
    /// Aggregation paths: 4 (horizontal and vertical) or 8 (plus diagonals).
    pub paths: u32,
    /// Largest |d_left - d_right| accepted by the left-right check, pixels.
    pub lr_tolerance: f32,
    /// The best cost must beat the second best (outside +-1) by this fraction.
    pub uniqueness: f32,
    /// Depths at or beyond this are dropped, metres.
    pub max_depth_m: f64,
}

impl Default for StereoParams {
    fn default() -> Self {
        Self {
            max_disparity: 64,
            census_radius: 2,
            p1: 8,
            p2: 48,
            paths: 8,
            lr_tolerance: 1.0,
            uniqueness: 0.05,
            max_depth_m: 15.0,
        }
    }
}

/// Checks the parameters; errors name them.
impl StereoParams {
    pub fn validate(&self) -> Result<()> {
        let p = self;
        let bad = |m: String| Err(StageError::Params(m));
        if !(2..=512).contains(&p.max_disparity) {
            return bad(format!(
                "`max_disparity` must be in 2..=512, got {}",
                p.max_disparity
            ));
        }
        check_matching(p.census_radius, p.p1, p.p2)?;
        if p.paths != 4 && p.paths != 8 {
            return bad(format!("`paths` must be 4 or 8, got {}", p.paths));
        }
        if !(p.lr_tolerance >= 0.0 && (0.0..1.0).contains(&p.uniqueness)) {
            return bad("`lr_tolerance` must be >= 0 and `uniqueness` in [0, 1)".into());
        }
        if !(p.max_depth_m.is_finite() && p.max_depth_m > 0.0) {
            return bad(format!(
                "`max_depth_m` must be positive, got {}",
                p.max_depth_m
            ));
        }
        Ok(())
    }
}

/// Checks the census radius and the aggregation penalties (shared by the matchers); errors
/// name them.
pub(super) fn check_matching(census_radius: u32, p1: u16, p2: u16) -> Result<()> {
    if !(1..=3).contains(&census_radius) {
        return Err(StageError::Params(format!(
            "`census_radius` must be 1, 2 or 3, got {census_radius}"
        )));
    }
    if p1 == 0 || p2 < p1 || p2 > 1000 {
        return Err(StageError::Params(format!(
            "penalties must satisfy 0 < p1 <= p2 <= 1000, got p1 {p1} p2 {p2}"
        )));
    }
    Ok(())
}

/// Grey levels (Rec. 601 luma) of `w*h*3` RGB bytes.
pub fn grey(rgb: &[u8]) -> Vec<u8> {
    rgb.chunks_exact(3)
        .map(|c| ((77 * c[0] as u32 + 150 * c[1] as u32 + 29 * c[2] as u32) >> 8) as u8)
        .collect()
}

/// Census transform: bit k set when neighbour k of the window is darker than the centre
/// (clamped at the border).
pub fn census(img: &[u8], w: usize, h: usize, r: usize) -> Vec<u64> {
    let mut out = vec![0u64; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let c = img[y * w + x];
            let mut bits = 0u64;
            for dy in -(r as i64)..=r as i64 {
                for dx in -(r as i64)..=r as i64 {
                    if dx == 0 && dy == 0 {
                        continue;
                    }
                    let yy = (y as i64 + dy).clamp(0, h as i64 - 1) as usize;
                    let xx = (x as i64 + dx).clamp(0, w as i64 - 1) as usize;
                    bits = (bits << 1) | (img[yy * w + xx] < c) as u64;
                }
            }
            *o = bits;
        }
    });
    out
}

/// Disparity maps of a rectified pair: left disparities (sub-pixel, NaN where rejected).
///
/// # Shapes
/// `left`, `right`: `[h, w]` grey; result `[h, w]`.
pub fn disparity(left: &[u8], right: &[u8], w: usize, h: usize, p: &StereoParams) -> Vec<f32> {
    let nd = p.max_disparity as usize;
    let r = p.census_radius as usize;
    let (cl, cr) = (census(left, w, h, r), census(right, w, h, r));
    let bits = ((2 * r + 1) * (2 * r + 1) - 1) as u16;
    // Matching cost [h, w, nd]: left pixel x against right pixel x - d (out of view: max).
    let mut cost = vec![bits; w * h * nd];
    cost.par_chunks_mut(w * nd)
        .enumerate()
        .for_each(|(y, row)| {
            for x in 0..w {
                for d in 0..nd.min(x + 1) {
                    row[x * nd + d] = (cl[y * w + x] ^ cr[y * w + x - d]).count_ones() as u16;
                }
            }
        });
    let sum = sgm_sum(&cost, w, h, nd, p.paths, p.p1, p.p2);
    // Winner-takes-all, uniqueness and sub-pixel refinement on the left.
    let mut disp = vec![f32::NAN; w * h];
    disp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            let s = &sum[(y * w + x) * nd..(y * w + x + 1) * nd];
            if let Some(d) = winner(&s[..nd.min(x + 1)], p.uniqueness) {
                *o = d;
            }
        }
    });
    // Right disparities from the same volume: d_R(x) = argmin_d sum(x + d, d).
    let right_disp: Vec<u32> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (y, x) = (i / w, i % w);
            (0..nd.min(w - x))
                .min_by_key(|&d| sum[(y * w + x + d) * nd + d])
                .unwrap_or(0) as u32
        })
        .collect();
    disp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, o) in row.iter_mut().enumerate() {
            if o.is_nan() {
                continue;
            }
            let xr = x as f32 - *o;
            let xr = xr.round();
            if xr < 0.0 {
                *o = f32::NAN;
                continue;
            }
            let dr = right_disp[y * w + xr as usize] as f32;
            if (dr - *o).abs() > p.lr_tolerance {
                *o = f32::NAN;
            }
        }
    });
    disp
}

/// The matching cost `[h, w, nd]` aggregated along 8 (or 4) scanline `paths` with penalties
/// `p1` (a one-step change) and `p2` (a larger jump): semi-global matching's summed volume.
pub(super) fn sgm_sum(
    cost: &[u16],
    w: usize,
    h: usize,
    nd: usize,
    paths: u32,
    p1: u16,
    p2: u16,
) -> Vec<u16> {
    let mut dirs: Vec<(i64, i64)> = vec![(1, 0), (-1, 0), (0, 1), (0, -1)];
    if paths == 8 {
        dirs.extend([(1, 1), (-1, 1), (1, -1), (-1, -1)]);
    }
    let mut sum = vec![0u16; w * h * nd];
    for &(dx, dy) in &dirs {
        aggregate(cost, &mut sum, w, h, nd, dx, dy, p1, p2);
    }
    sum
}

/// The index of the lowest of `s` refined to sub-step by a parabola through its neighbours;
/// `None` unless it beats the lowest cost more than one step away by the fraction
/// `uniqueness`.
pub(super) fn winner(s: &[u16], uniqueness: f32) -> Option<f32> {
    let (best, &bc) = s.iter().enumerate().min_by_key(|&(_, c)| *c)?;
    let second = s
        .iter()
        .enumerate()
        .filter(|&(d, _)| d + 1 < best || d > best + 1)
        .map(|(_, &c)| c)
        .min()
        .unwrap_or(u16::MAX);
    if (second as f32) * (1.0 - uniqueness) < bc as f32 {
        return None;
    }
    let mut d = best as f32;
    if best > 0 && best + 1 < s.len() {
        let (a, b, c) = (s[best - 1] as f32, bc as f32, s[best + 1] as f32);
        let den = a - 2.0 * b + c;
        if den > 0.0 {
            d += (0.5 * (a - c) / den).clamp(-0.5, 0.5);
        }
    }
    Some(d)
}

/// Adds the path costs `L_r` of direction `(dx, dy)` to `sum`.
///
/// `L_r(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d+-1) + p1, min_k L(p-r, k) + p2) - min_k
/// L(p-r, k)`.
#[allow(clippy::too_many_arguments)]
fn aggregate(
    cost: &[u16],
    sum: &mut [u16],
    w: usize,
    h: usize,
    nd: usize,
    dx: i64,
    dy: i64,
    p1: u16,
    p2: u16,
) {
    let step = |prev: Option<&[u16]>, c: &[u16], out: &mut [u16]| match prev {
        None => out.copy_from_slice(c),
        Some(prev) => {
            let m = *prev.iter().min().unwrap_or(&0);
            for d in 0..nd {
                let mut best = prev[d];
                if d > 0 {
                    best = best.min(prev[d - 1].saturating_add(p1));
                }
                if d + 1 < nd {
                    best = best.min(prev[d + 1].saturating_add(p1));
                }
                best = best.min(m.saturating_add(p2));
                out[d] = c[d] + best - m;
            }
        }
    };
    if dy == 0 {
        // Each row on its own, swept along x.
        sum.par_chunks_mut(w * nd)
            .zip(cost.par_chunks(w * nd))
            .for_each(|(srow, crow)| {
                let mut prev = vec![0u16; nd];
                let mut cur = vec![0u16; nd];
                let xs: Box<dyn Iterator<Item = usize>> = if dx > 0 {
                    Box::new(0..w)
                } else {
                    Box::new((0..w).rev())
                };
                for (k, x) in xs.enumerate() {
                    let c = &crow[x * nd..(x + 1) * nd];
                    step(
                        if k == 0 { None } else { Some(prev.as_slice()) },
                        c,
                        &mut cur,
                    );
                    for d in 0..nd {
                        srow[x * nd + d] += cur[d];
                    }
                    std::mem::swap(&mut prev, &mut cur);
                }
            });
        return;
    }
    // Row by row along y; each pixel of a row depends on the previous row at x - dx.
    let mut prev = vec![0u16; w * nd];
    let mut cur = vec![0u16; w * nd];
    let ys: Vec<usize> = if dy > 0 {
        (0..h).collect()
    } else {
        (0..h).rev().collect()
    };
    for (k, &y) in ys.iter().enumerate() {
        cur.par_chunks_mut(nd).enumerate().for_each(|(x, out)| {
            let c = &cost[(y * w + x) * nd..(y * w + x + 1) * nd];
            let px = x as i64 - dx;
            let from = (k > 0 && px >= 0 && px < w as i64)
                .then(|| &prev[px as usize * nd..(px as usize + 1) * nd]);
            step(from, c, out);
        });
        sum[y * w * nd..(y + 1) * w * nd]
            .par_iter_mut()
            .zip(cur.par_iter())
            .for_each(|(s, &c)| *s += c);
        std::mem::swap(&mut prev, &mut cur);
    }
}

/// Depth `fx * b / d` where valid and below `max_depth`; 0 elsewhere.
pub fn depth_from_disparity(disp: &[f32], fx: f64, baseline: f64, max_depth: f64) -> Vec<f32> {
    disp.iter()
        .map(|&d| {
            if d.is_finite() && d > 0.0 {
                let z = fx * baseline / d as f64;
                if z < max_depth {
                    return z as f32;
                }
            }
            0.0
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinds::stereo_depth::StereoDepth;
    use crate::tables;
    use arrow::datatypes::Float32Type;

    /// A smooth random texture value at continuous x (linear interpolation of a seeded table).
    fn texture(x: f64, y: usize) -> u8 {
        let v = |i: i64| {
            let h = crate::scene::rng::hash(&[i as u64, y as u64, 99]);
            (h % 200) as f64 + 28.0
        };
        let (i, f) = (x.floor() as i64, x - x.floor());
        (v(i) * (1.0 - f) + v(i + 1) * f).round() as u8
    }

    /// A fronto-parallel textured plane at disparity `d`: left(x) = T(x), right(x) = T(x + d).
    fn plane(w: usize, h: usize, d: f64) -> (Vec<u8>, Vec<u8>) {
        let l = (0..h)
            .flat_map(|y| (0..w).map(move |x| texture(x as f64 / 1.5, y)))
            .collect();
        let r = (0..h)
            .flat_map(|y| (0..w).map(move |x| texture((x as f64 + d) / 1.5, y)))
            .collect();
        (l, r)
    }

    #[test]
    fn a_textured_plane_at_known_disparity_is_recovered() {
        let (w, h) = (96, 24);
        let p = StereoParams {
            max_disparity: 32,
            ..Default::default()
        };
        for d in [7.0, 12.5, 20.25] {
            let (l, r) = plane(w, h, d);
            let disp = disparity(&l, &r, w, h, &p);
            // Away from the left border (where x - d leaves the right image).
            let inner: Vec<f32> = (0..h)
                .flat_map(|y| (32..w - 4).map(move |x| y * w + x))
                .map(|i| disp[i])
                .collect();
            let valid: Vec<f32> = inner.iter().copied().filter(|v| v.is_finite()).collect();
            let mae = valid.iter().map(|v| (*v as f64 - d).abs()).sum::<f64>() / valid.len() as f64;
            let frac = valid.len() as f64 / inner.len() as f64;
            eprintln!(
                "plane d = {d}: {:.1}% valid, mean |error| {mae:.3} px",
                100.0 * frac
            );
            assert!(frac > 0.9, "d {d}: only {frac} valid");
            assert!(mae < 0.3, "d {d}: mean error {mae} px");
            // Depth of the plane: fx * b / d.
            let z = depth_from_disparity(&valid, 100.0, 0.5, 15.0);
            let want = 50.0 / d;
            let zerr = z
                .iter()
                .map(|&v| (v as f64 - want).abs() / want)
                .sum::<f64>()
                / z.len() as f64;
            assert!(zerr < 0.03, "d {d}: relative depth error {zerr}");
        }
    }

    #[test]
    fn far_depths_are_dropped_and_occlusions_rejected() {
        assert_eq!(
            depth_from_disparity(&[2.0, 10.0, f32::NAN, 0.0], 100.0, 0.5, 15.0),
            vec![0.0, 5.0, 0.0, 0.0]
        );
        // An untextured pair gives no depth (no disparity is preferred but 0 = infinitely far).
        let (w, h) = (40, 10);
        let flat = vec![128u8; w * h];
        let disp = disparity(&flat, &flat, w, h, &StereoParams::default());
        let z = depth_from_disparity(&disp, 100.0, 0.5, 15.0);
        let n = z.iter().filter(|&&v| v > 0.0).count();
        assert_eq!(n, 0, "{n} depths on a flat image");
    }

    /// The default synthetic scene: SGM depth against GT depth (pixels with a value).
    #[test]
    fn sgm_depth_on_the_synthetic_scene_is_close_to_gt() {
        let sp = crate::scene::synthetic::SceneParams::default();
        let t = crate::scene::synthetic::in_memory::to_tables(
            &sp,
            crate::scene::synthetic::generate(&sp, &crate::NoProgress).unwrap(),
        )
        .unwrap();
        let out = {
            let s = StereoDepth;
            let v = crate::Stage::canonical_params(&s, &serde_json::json!({})).unwrap();
            let mem = crate::MemoryInputs::new([("scene", t.clone())]);
            crate::Stage::run(&s, &v, &mem.inputs(), &crate::NoProgress).unwrap()
        };
        let sd =
            tables::get_list::<Float32Type>(&out["stereo_depth"], "stereo_depth", "depth").unwrap();
        let gt_t = &t["gt_depth"];
        let gk = crate::scene::io::image_keys(gt_t, "gt_depth").unwrap();
        let gt = tables::get_list::<Float32Type>(gt_t, "gt_depth", "depth").unwrap();
        let sk = crate::scene::io::image_keys(&out["stereo_depth"], "stereo_depth").unwrap();
        let (mut n_near, mut sq_near) = (0usize, 0f64);
        let (mut n, mut total, mut abs_rel, mut sq, mut within) =
            (0usize, 0usize, 0f64, 0f64, 0usize);
        for (i, k) in sk.iter().enumerate() {
            let j = gk.iter().position(|g| g.0 == k.0 && g.1 == 0).unwrap();
            for (&s, &g) in sd.row(i).iter().zip(gt.row(j)) {
                if g > 0.0 && g < 15.0 {
                    total += 1;
                }
                if s > 0.0 && g > 0.0 {
                    n += 1;
                    let e = (s - g) as f64;
                    abs_rel += e.abs() / g as f64;
                    sq += e * e;
                    within += ((s / g).max(g / s) < 1.25) as usize;
                    if g < 15.0 {
                        n_near += 1;
                        sq_near += e * e;
                    }
                }
            }
        }
        let (abs_rel, rmse, d125) = (
            abs_rel / n as f64,
            (sq / n as f64).sqrt(),
            within as f64 / n as f64,
        );
        eprintln!(
            "SGM on the synthetic scene ({} frames): {n} depths ({:.1}% of GT pixels under 15 m), abs rel {abs_rel:.3}, RMSE {rmse:.2} m, delta<1.25 {:.1}%; where GT < 15 m ({n_near} px): RMSE {:.2} m",
            sk.len(),
            100.0 * n as f64 / total.max(1) as f64,
            100.0 * d125,
            (sq_near / n_near.max(1) as f64).sqrt()
        );
        assert!(n > total / 4, "too few depths: {n} of {total}");
        assert!(abs_rel < 0.15, "abs rel {abs_rel}");
        assert!(d125 > 0.85, "delta {d125}");
    }
}
