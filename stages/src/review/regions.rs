//! Connected regions of a pixel mask (8-connected), numbered in raster order of their first
//! pixel.

/// Per pixel of a `width` x `height` row-major mask, the number of its region (1, 2, ...; 0
/// off the mask), and how many regions there are.
pub fn connected_regions(mask: &[bool], width: usize, height: usize) -> (Vec<u32>, u32) {
    assert_eq!(mask.len(), width * height, "connected_regions: mask size");
    let mut parent: Vec<u32> = Vec::new();
    let mut provisional = vec![0u32; mask.len()];
    fn root(parent: &mut [u32], mut a: u32) -> u32 {
        while parent[a as usize] != a {
            parent[a as usize] = parent[parent[a as usize] as usize];
            a = parent[a as usize];
        }
        a
    }
    for y in 0..height {
        for x in 0..width {
            let p = y * width + x;
            if !mask[p] {
                continue;
            }
            // The already-visited neighbours: left, and the three above.
            let mut seen = [u32::MAX; 4];
            if x > 0 && mask[p - 1] {
                seen[0] = provisional[p - 1];
            }
            if y > 0 {
                let up = p - width;
                if x > 0 && mask[up - 1] {
                    seen[1] = provisional[up - 1];
                }
                if mask[up] {
                    seen[2] = provisional[up];
                }
                if x + 1 < width && mask[up + 1] {
                    seen[3] = provisional[up + 1];
                }
            }
            let mut label = u32::MAX;
            for &s in seen.iter().filter(|&&s| s != u32::MAX) {
                let r = root(&mut parent, s);
                if label == u32::MAX {
                    label = r;
                } else if r != label {
                    let (lo, hi) = (label.min(r), label.max(r));
                    parent[hi as usize] = lo;
                    label = lo;
                }
            }
            if label == u32::MAX {
                label = parent.len() as u32;
                parent.push(label);
            }
            provisional[p] = label;
        }
    }
    // Final numbers in raster order of each region's first pixel.
    let mut number = vec![0u32; parent.len()];
    let mut count = 0u32;
    let mut out = vec![0u32; mask.len()];
    for p in 0..mask.len() {
        if mask[p] {
            let r = root(&mut parent, provisional[p]) as usize;
            if number[r] == 0 {
                count += 1;
                number[r] = count;
            }
            out[p] = number[r];
        }
    }
    (out, count)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Flood fill, the obvious way.
    fn brute(mask: &[bool], w: usize, h: usize) -> (Vec<u32>, u32) {
        let mut out = vec![0u32; mask.len()];
        let mut n = 0;
        for start in 0..mask.len() {
            if !mask[start] || out[start] != 0 {
                continue;
            }
            n += 1;
            let mut stack = vec![start];
            out[start] = n;
            while let Some(p) = stack.pop() {
                let (x, y) = ((p % w) as i64, (p / w) as i64);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (nx, ny) = (x + dx, y + dy);
                        if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                            continue;
                        }
                        let q = ny as usize * w + nx as usize;
                        if mask[q] && out[q] == 0 {
                            out[q] = n;
                            stack.push(q);
                        }
                    }
                }
            }
        }
        (out, n)
    }

    #[test]
    fn a_u_shape_is_one_region_and_diagonals_connect() {
        #[rustfmt::skip]
        let m = [
            1, 0, 1, 0, 0,
            1, 0, 1, 0, 1,
            1, 1, 1, 0, 0,
            0, 0, 0, 1, 0,
        ].map(|v| v == 1);
        let (ids, n) = connected_regions(&m, 5, 4);
        assert_eq!(n, 2);
        assert_eq!(ids[0], 1);
        assert_eq!(ids[3 * 5 + 3], 1, "diagonal neighbour of the U");
        assert_eq!(ids[5 + 4], 2);
    }

    proptest! {
        #[test]
        fn equals_flood_fill(w in 1usize..16, h in 1usize..12, bits in proptest::collection::vec(0u8..3, 192)) {
            let mask: Vec<bool> = (0..w * h).map(|i| bits[i] == 0).collect();
            prop_assert_eq!(connected_regions(&mask, w, h), brute(&mask, w, h));
        }
    }
}
