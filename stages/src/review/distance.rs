//! Exact Euclidean distance to the nearest marked pixel (Felzenszwalb and Huttenlocher's
//! separable transform: a lower envelope of parabolas per row, then per column).

/// Squared distance transform of one line in place: `f[i]` in, `min_j (f[j] + (i - j)^2)` out.
/// `v`, `z` and `d` are scratch of at least `f.len()` (+1 for `z`) entries.
fn line(f: &mut [f32], v: &mut [usize], z: &mut [f32], d: &mut [f32]) {
    let n = f.len();
    if n == 0 {
        return;
    }
    let mut k = 0usize;
    v[0] = 0;
    z[0] = f32::NEG_INFINITY;
    z[1] = f32::INFINITY;
    for q in 1..n {
        if !f[q].is_finite() {
            continue;
        }
        loop {
            let p = v[k];
            // Where the parabola of q overtakes that of p. With an infinite f[p] (no marked
            // pixel yet), q takes over everywhere.
            let s = if f[p].is_finite() {
                ((f[q] + (q * q) as f32) - (f[p] + (p * p) as f32)) / (2.0 * (q - p) as f32)
            } else {
                f32::NEG_INFINITY
            };
            if s <= z[k] {
                if k == 0 {
                    v[0] = q;
                    z[1] = f32::INFINITY;
                    break;
                }
                k -= 1;
            } else {
                k += 1;
                v[k] = q;
                z[k] = s;
                z[k + 1] = f32::INFINITY;
                break;
            }
        }
    }
    k = 0;
    for (q, out) in d.iter_mut().enumerate().take(n) {
        while z[k + 1] < q as f32 {
            k += 1;
        }
        let p = v[k];
        let dq = q as f32 - p as f32;
        *out = if f[p].is_finite() {
            f[p] + dq * dq
        } else {
            f32::INFINITY
        };
    }
    f.copy_from_slice(&d[..n]);
}

/// Per pixel of a `width` x `height` row-major image, the Euclidean distance in pixels to the
/// nearest pixel where `marked` is true (0 on a marked pixel; infinite when none is marked).
pub fn distance_to(marked: &[bool], width: usize, height: usize) -> Vec<f32> {
    assert_eq!(marked.len(), width * height, "distance_to: mask size");
    let mut g: Vec<f32> = marked
        .iter()
        .map(|&m| if m { 0.0 } else { f32::INFINITY })
        .collect();
    let longest = width.max(height);
    let (mut v, mut z, mut d) = (
        vec![0usize; longest],
        vec![0f32; longest + 1],
        vec![0f32; longest],
    );
    let mut col = vec![0f32; height];
    for x in 0..width {
        for y in 0..height {
            col[y] = g[y * width + x];
        }
        line(&mut col, &mut v, &mut z, &mut d);
        for y in 0..height {
            g[y * width + x] = col[y];
        }
    }
    for row in g.chunks_mut(width.max(1)) {
        line(row, &mut v, &mut z, &mut d);
    }
    g.iter_mut().for_each(|x| *x = x.sqrt());
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn brute(marked: &[bool], w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as f32, (p / w) as f32);
                marked
                    .iter()
                    .enumerate()
                    .filter(|(_, &m)| m)
                    .map(|(q, _)| {
                        let (qx, qy) = ((q % w) as f32, (q / w) as f32);
                        ((x - qx).powi(2) + (y - qy).powi(2)).sqrt()
                    })
                    .fold(f32::INFINITY, f32::min)
            })
            .collect()
    }

    #[test]
    fn one_marked_pixel_gives_the_euclidean_distance() {
        let (w, h) = (7, 5);
        let mut m = vec![false; w * h];
        m[2 * w + 3] = true;
        let d = distance_to(&m, w, h);
        assert_eq!(d[2 * w + 3], 0.0);
        assert!((d[0] - (9.0f32 + 4.0).sqrt()).abs() < 1e-6);
        assert!((d[4 * w + 6] - (9.0f32 + 4.0).sqrt()).abs() < 1e-6);
    }

    #[test]
    fn nothing_marked_is_infinitely_far_and_empty_images_work() {
        assert!(distance_to(&[false; 6], 3, 2)
            .iter()
            .all(|d| d.is_infinite()));
        assert!(distance_to(&[], 0, 0).is_empty());
        assert!(distance_to(&[], 0, 4).is_empty());
    }

    proptest! {
        #[test]
        fn equals_brute_force(w in 1usize..14, h in 1usize..11, bits in proptest::collection::vec(0u8..12, 154)) {
            let marked: Vec<bool> = (0..w * h).map(|i| bits[i] == 0).collect();
            let fast = distance_to(&marked, w, h);
            let slow = brute(&marked, w, h);
            for (a, b) in fast.iter().zip(&slow) {
                prop_assert!(a == b || (a - b).abs() < 1e-4, "{a} vs {b}");
            }
        }
    }
}
