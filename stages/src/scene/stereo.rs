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
//! The aggregation is three sweeps over the volume: the horizontal paths (bands of rows in
//! parallel), then all downward paths together and all upward ones (a row's pixels in
//! parallel, each depending only on the row before). The path arithmetic is i16 over padded
//! disparity vectors, so the compiler vectorises it, AVX2-wide where the CPU has it; it gives
//! the plain per-path implementation's bytes (a test holds them equal). Memory: the cost
//! volume `w * h * max_disparity` u8 and the aggregated one u16, kept by a [`Matcher`] from one
//! pair to the next.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::model::fused::dispatch;
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
    let (side, pw) = (2 * r + 1, w + 2 * r);
    let mut out = vec![0u64; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        // The window's rows, clamped, each padded by `r` border pixels on both ends: the
        // neighbour at (dx, dy) of pixel x is then `padded[dy + r][x + dx + r]`.
        let mut padded = vec![0u8; side * pw];
        for (k, line) in padded.chunks_exact_mut(pw).enumerate() {
            let yy = (y + k).saturating_sub(r).min(h - 1);
            let src = &img[yy * w..(yy + 1) * w];
            for (i, p) in line.iter_mut().enumerate() {
                *p = src[i.saturating_sub(r).min(w - 1)];
            }
        }
        let centre = &img[y * w..(y + 1) * w];
        dispatch(|| {
            for k in 0..side {
                for j in 0..side {
                    if k == r && j == r {
                        continue;
                    }
                    let nb = &padded[k * pw + j..k * pw + j + w];
                    for ((o, &n), &c) in row.iter_mut().zip(nb).zip(centre) {
                        *o = (*o << 1) | (n < c) as u64;
                    }
                }
            }
        })
    });
    out
}

/// Disparity maps of a rectified pair: left disparities (sub-pixel, NaN where rejected).
///
/// # Shapes
/// `left`, `right`: `[h, w]` grey; result `[h, w]`.
pub fn disparity(left: &[u8], right: &[u8], w: usize, h: usize, p: &StereoParams) -> Vec<f32> {
    Matcher::default().disparity(left, right, w, h, p)
}

/// Semi-global matching with its two volumes (`[h, w, nd]`: costs u8, sums u16) kept from one
/// pair to the next: fresh zeroed pages for every pair cost about a fifth of a full-size match
/// in page faults.
#[derive(Default)]
pub struct Matcher {
    cost: Vec<u8>,
    sum: Vec<u16>,
}

impl Matcher {
    /// [`disparity`], reusing this matcher's volumes.
    pub fn disparity(
        &mut self,
        left: &[u8],
        right: &[u8],
        w: usize,
        h: usize,
        p: &StereoParams,
    ) -> Vec<f32> {
        let nd = p.max_disparity as usize;
        let r = p.census_radius as usize;
        let (cl, cr) = (census(left, w, h, r), census(right, w, h, r));
        let n = w * h * nd;
        let cost = &mut fit(&mut self.cost, n)[..n];
        matching_cost(&cl, &cr, w, nd, r, cost);
        let sum = &mut fit(&mut self.sum, n)[..n];
        aggregate(cost, sum, w, h, nd, p.paths, p.p1, p.p2);
        let mut disp = vec![f32::NAN; w * h];
        disp.par_chunks_mut(w)
            .zip(sum.par_chunks(w * nd))
            .for_each(|(row, srow)| dispatch(|| checked_row(srow, row, nd, p)));
        disp
    }
}

/// `v` with at least `n` values; a new allocation has its zeroed pages faulted in in parallel
/// (the sweeps that write them would take several times longer to fault them).
fn fit<T: Copy + Default + Send>(v: &mut Vec<T>, n: usize) -> &mut [T] {
    if v.len() < n {
        *v = Vec::new(); // the old volume goes before the new one comes
        *v = vec![T::default(); n];
        let page = (4096 / std::mem::size_of::<T>()).max(1);
        v.par_chunks_mut(page).for_each(|p| p[0] = T::default());
    }
    v
}

/// One row's left disparities: winner-takes-all with the uniqueness test and sub-pixel
/// refinement, then the left-right check against the right disparities of the same volume
/// (`d_R(x) = argmin_d sum(x + d, d)`, the smallest such `d` on ties).
#[inline(always)]
fn checked_row(srow: &[u16], row: &mut [f32], nd: usize, p: &StereoParams) {
    let w = row.len();
    for (x, o) in row.iter_mut().enumerate() {
        if let Some(d) = winner(&srow[x * nd..x * nd + nd.min(x + 1)], p.uniqueness) {
            *o = d;
        }
    }
    // The lowest (sum, d) of every right pixel: `d` fits 9 bits (`max_disparity` <= 512).
    let mut right = vec![u32::MAX; w];
    for xl in 0..w {
        let n = nd.min(xl + 1);
        // Right pixels xl - n + 1 ..= xl, against disparities n - 1 down to 0.
        let to = &mut right[xl + 1 - n..=xl];
        for (r, (d, &s)) in to
            .iter_mut()
            .zip(srow[xl * nd..xl * nd + n].iter().enumerate().rev())
        {
            *r = (*r).min((s as u32) << 9 | d as u32);
        }
    }
    for (x, o) in row.iter_mut().enumerate() {
        if o.is_nan() {
            continue;
        }
        let xr = (x as f32 - *o).round();
        if xr < 0.0 {
            *o = f32::NAN;
            continue;
        }
        let dr = (right[xr as usize] & 511) as f32;
        if (dr - *o).abs() > p.lr_tolerance {
            *o = f32::NAN;
        }
    }
}

/// Writes the Hamming matching cost `[h, w, nd]` of the census images: left pixel `x` against
/// right pixel `x - d`; where that leaves the image, the window's bit count (the largest cost).
fn matching_cost(cl: &[u64], cr: &[u64], w: usize, nd: usize, r: usize, cost: &mut [u8]) {
    let bits = ((2 * r + 1) * (2 * r + 1) - 1) as u8;
    cost.par_chunks_mut(w * nd)
        .enumerate()
        .for_each(|(y, row)| {
            let (l, r) = (&cl[y * w..(y + 1) * w], &cr[y * w..(y + 1) * w]);
            dispatch(|| {
                for (x, cx) in row.chunks_exact_mut(nd).enumerate() {
                    let n = nd.min(x + 1);
                    for (c, &rv) in cx[..n].iter_mut().zip(r[..=x].iter().rev()) {
                        *c = (l[x] ^ rv).count_ones() as u8;
                    }
                    cx[n..].fill(bits);
                }
            })
        });
}

/// The matching cost `[h, w, nd]` aggregated along 8 (or 4) scanline `paths` with penalties
/// `p1` (a one-step change) and `p2` (a larger jump): semi-global matching's summed volume.
///
/// Three sweeps: the two horizontal paths (bands of rows in parallel), then every downward
/// path in one pass over the rows, then every upward one (a row's pixels in parallel). A path
/// value is at most `cost + p2` (under 1100), and eight of them fit u16.
pub fn sgm_sum(
    cost: &[u8],
    w: usize,
    h: usize,
    nd: usize,
    paths: u32,
    p1: u16,
    p2: u16,
) -> Vec<u16> {
    let mut sum = Vec::new();
    fit(&mut sum, cost.len());
    aggregate(cost, &mut sum, w, h, nd, paths, p1, p2);
    sum
}

/// [`sgm_sum`] written into `sum` (every value overwritten).
#[allow(clippy::too_many_arguments)]
fn aggregate(
    cost: &[u8],
    sum: &mut [u16],
    w: usize,
    h: usize,
    nd: usize,
    paths: u32,
    p1: u16,
    p2: u16,
) {
    let pen = Penalties {
        p1: p1 as i16,
        p2: p2 as i16,
    };
    /// Rows stepped together by the horizontal paths.
    const BAND: usize = 8;
    sum.par_chunks_mut(BAND * w * nd)
        .zip(cost.par_chunks(BAND * w * nd))
        .for_each(|(sums, costs)| dispatch(|| horizontal(sums, costs, w, nd, pen)));
    // The x offset of a path's previous pixel: straight down or up, then the diagonals.
    let dxs: &[i64] = if paths == 8 { &[0, 1, -1] } else { &[0] };
    vertical(cost, sum, w, h, nd, true, dxs, pen);
    vertical(cost, sum, w, h, nd, false, dxs, pen);
}

/// The aggregation penalties in the path arithmetic's type.
#[derive(Clone, Copy)]
struct Penalties {
    p1: i16,
    p2: i16,
}

/// Padding on both ends of a path's disparity vector: never the minimum (it exceeds every
/// path value plus `p2`), and it stays in i16 when `p1` is added.
const PAD: i16 = 16_000;

/// The first pixel of a path: `L = C`. `out` is padded (`nd + 2`); returns `min L`.
#[inline(always)]
fn path_start(c: &[u8], out: &mut [i16]) -> i16 {
    let out = &mut out[1..=c.len()];
    let mut lowest = i16::MAX;
    for (o, &c) in out.iter_mut().zip(c) {
        *o = c as i16;
        lowest = lowest.min(*o);
    }
    lowest
}

/// One step along a path: `L(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d+-1) + p1, m + p2) - m`
/// with `m = min_k L(p-r, k)` (`prev_min`). `prev` and `out` are padded; returns `min L(p)`.
#[inline(always)]
fn path_step(prev: &[i16], prev_min: i16, c: &[u8], out: &mut [i16], pen: Penalties) -> i16 {
    let nd = c.len();
    let (below, at, above) = (&prev[..nd], &prev[1..nd + 1], &prev[2..nd + 2]);
    let out = &mut out[1..nd + 1];
    let jump = prev_min.wrapping_add(pen.p2);
    let mut lowest = i16::MAX;
    for d in 0..nd {
        let near = below[d].min(above[d]).wrapping_add(pen.p1);
        let v = at[d].min(near).min(jump);
        let l = (c[d] as i16).wrapping_add(v.wrapping_sub(prev_min));
        out[d] = l;
        lowest = lowest.min(l);
    }
    lowest
}

/// `sum = l` over the unpadded part of `l`.
#[inline(always)]
fn store(sum: &mut [u16], l: &[i16]) {
    let n = sum.len();
    for (s, &l) in sum.iter_mut().zip(&l[1..=n]) {
        *s = l as u16;
    }
}

/// `sum += l` over the unpadded part of `l`.
#[inline(always)]
fn accumulate(sum: &mut [u16], l: &[i16]) {
    let n = sum.len();
    for (s, &l) in sum.iter_mut().zip(&l[1..=n]) {
        *s = s.wrapping_add(l as u16);
    }
}

/// Writes the two horizontal paths of a band of rows (`[rows, w, nd]`) into `sums`; the rows
/// are independent and step together, pixel by pixel.
#[inline(always)]
fn horizontal(sums: &mut [u16], costs: &[u8], w: usize, nd: usize, pen: Penalties) {
    let (rows, stride) = (costs.len() / (w * nd), nd + 2);
    let (mut prev, mut cur) = (vec![PAD; rows * stride], vec![PAD; rows * stride]);
    let (mut prev_min, mut cur_min) = (vec![0i16; rows], vec![0i16; rows]);
    for rightwards in [true, false] {
        for k in 0..w {
            let x = if rightwards { k } else { w - 1 - k };
            for row in 0..rows {
                let at = (row * w + x) * nd;
                let c = &costs[at..at + nd];
                let out = &mut cur[row * stride..(row + 1) * stride];
                cur_min[row] = if k == 0 {
                    path_start(c, out)
                } else {
                    let from = &prev[row * stride..(row + 1) * stride];
                    path_step(from, prev_min[row], c, out, pen)
                };
                if rightwards {
                    store(&mut sums[at..at + nd], out);
                } else {
                    accumulate(&mut sums[at..at + nd], out);
                }
            }
            std::mem::swap(&mut prev, &mut cur);
            std::mem::swap(&mut prev_min, &mut cur_min);
        }
    }
}

/// Adds the paths that come from the row above (`down`) or below, one per x offset in `dxs`,
/// sweeping the rows; the pixels of a row are independent, in parallel.
#[allow(clippy::too_many_arguments)]
fn vertical(
    cost: &[u8],
    sum: &mut [u16],
    w: usize,
    h: usize,
    nd: usize,
    down: bool,
    dxs: &[i64],
    pen: Penalties,
) {
    /// Pixels per parallel task.
    const CHUNK: usize = 64;
    let (k, stride) = (dxs.len(), nd + 2);
    // Path vectors `[w, k, nd + 2]` of the previous and the current row, and their minima.
    let (mut prev, mut cur) = (vec![PAD; w * k * stride], vec![PAD; w * k * stride]);
    let (mut prev_min, mut cur_min) = (vec![0i16; w * k], vec![0i16; w * k]);
    for i in 0..h {
        let y = if down { i } else { h - 1 - i };
        let crow = &cost[y * w * nd..(y + 1) * w * nd];
        let srow = &mut sum[y * w * nd..(y + 1) * w * nd];
        let (last, last_min) = (&prev, &prev_min);
        cur.par_chunks_mut(CHUNK * k * stride)
            .zip(cur_min.par_chunks_mut(CHUNK * k))
            .zip(srow.par_chunks_mut(CHUNK * nd))
            .enumerate()
            .for_each(|(chunk, ((lc, mc), sc))| {
                dispatch(|| {
                    for (j, s) in sc.chunks_exact_mut(nd).enumerate() {
                        let x = chunk * CHUNK + j;
                        let c = &crow[x * nd..(x + 1) * nd];
                        for (q, &dx) in dxs.iter().enumerate() {
                            let out = &mut lc[(j * k + q) * stride..(j * k + q + 1) * stride];
                            let px = x as i64 - dx;
                            mc[j * k + q] = if i == 0 || px < 0 || px >= w as i64 {
                                path_start(c, out)
                            } else {
                                let from = px as usize * k + q;
                                path_step(
                                    &last[from * stride..(from + 1) * stride],
                                    last_min[from],
                                    c,
                                    out,
                                    pen,
                                )
                            };
                            accumulate(s, out);
                        }
                    }
                })
            });
        std::mem::swap(&mut prev, &mut cur);
        std::mem::swap(&mut prev_min, &mut cur_min);
    }
}

/// The index of the lowest of `s` (the first on ties) refined to sub-step by a parabola through
/// its neighbours; `None` unless it beats the lowest cost more than one step away by the
/// fraction `uniqueness`.
#[inline(always)]
pub(super) fn winner(s: &[u16], uniqueness: f32) -> Option<f32> {
    let bc = s.iter().copied().min()?;
    let best = s.iter().position(|&c| c == bc)?;
    let lowest = |part: &[u16]| part.iter().copied().min().unwrap_or(u16::MAX);
    let second = lowest(&s[..best.saturating_sub(1)]).min(lowest(&s[(best + 2).min(s.len())..]));
    if (second as f32) * (1.0 - uniqueness) < bc as f32 {
        return None;
    }
    Some(sub_step(s, best))
}

/// `best` moved to the vertex of the parabola through `s` at `best` and its two neighbours
/// (at most half a step; unmoved at either end).
#[inline(always)]
fn sub_step(s: &[u16], best: usize) -> f32 {
    let mut d = best as f32;
    if best > 0 && best + 1 < s.len() {
        let (a, b, c) = (s[best - 1] as f32, s[best] as f32, s[best + 1] as f32);
        let den = a - 2.0 * b + c;
        if den > 0.0 {
            d += (0.5 * (a - c) / den).clamp(-0.5, 0.5);
        }
    }
    d
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
#[path = "stereo_reference.rs"]
mod reference;

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

    /// The optimised matcher gives the plain implementation's bytes: every size (narrower than
    /// the disparity range too), census radius, path count and penalty, on textured and noisy
    /// pairs, with volumes reused from the pair before.
    #[test]
    fn the_matcher_gives_the_plain_implementations_bytes() {
        let noise = |i: usize, salt: u64| (crate::scene::rng::hash(&[i as u64, salt]) % 256) as u8;
        let cases = [
            (96, 24, 32, 2, 8, 8, 48),
            (37, 9, 64, 1, 8, 1, 1),
            (61, 13, 16, 3, 4, 1000, 1000),
            (70, 11, 24, 3, 8, 20, 1000),
            (5, 3, 8, 2, 8, 3, 7),
        ];
        // One matcher for every case: its volumes, left from a larger pair, must not leak.
        let mut matcher = Matcher::default();
        for (i, &(w, h, nd, r, paths, p1, p2)) in cases.iter().enumerate() {
            let p = StereoParams {
                max_disparity: nd,
                census_radius: r,
                paths,
                p1,
                p2,
                ..Default::default()
            };
            let (textured, shifted) = plane(w, h, 5.5 + i as f64);
            let noisy: Vec<u8> = (0..w * h).map(|k| noise(k, i as u64)).collect();
            for (l, r) in [(&textured, &shifted), (&noisy, &textured)] {
                let got = matcher.disparity(l, r, w, h, &p);
                let want = reference::disparity(l, r, w, h, &p);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(&got),
                    bits(&want),
                    "case {i}: {w}x{h}, {nd} disparities"
                );
                assert!(
                    got.iter().any(|d| d.is_finite()),
                    "case {i}: nothing matched"
                );
            }
            // The summed volume itself, on costs up to the sweep's largest (two census costs).
            let cost: Vec<u8> = (0..w * h * nd as usize).map(|k| noise(k, 7) % 97).collect();
            let wide: Vec<u16> = cost.iter().map(|&c| c as u16).collect();
            assert_eq!(
                sgm_sum(&cost, w, h, nd as usize, paths, p1, p2),
                reference::sgm_sum(&wide, w, h, nd as usize, paths, p1, p2),
                "case {i}: summed volume"
            );
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
