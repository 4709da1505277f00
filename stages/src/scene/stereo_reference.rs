//! The first, plain implementation of semi-global matching (one pass over the whole volume per
//! path, scalar), kept for the tests: the optimised matcher must give the same bytes.

use rayon::prelude::*;

use super::{census, sub_step, StereoParams};

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
pub fn sgm_sum(
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

/// The index of the lowest of `s` (the first on ties) refined to sub-step; `None` unless it
/// beats the lowest cost more than one step away by the fraction `uniqueness`.
fn winner(s: &[u16], uniqueness: f32) -> Option<f32> {
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
    Some(sub_step(s, best))
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
