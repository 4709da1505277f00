//! How well a per-pixel score finds wrong labels, where ground truth says which are wrong:
//! AUROC, the share of wrong pixels in the top share of pixels by score, the precision of the
//! top regions, and the rank correlation of per-image scores with per-image error.
//!
//! Scores are quantised to [`LEVELS`] levels in [0, 1], so pixels are counted in histograms
//! (memory independent of the number of images); ties within a level count half, as in the
//! Mann-Whitney form of the AUROC.

/// Levels of a quantised score.
pub const LEVELS: usize = 1 << 16;

/// The level of score `s` in [0, 1] (clamped; NaN is 0).
pub fn level(s: f32) -> usize {
    if s.is_nan() {
        return 0;
    }
    (s.clamp(0.0, 1.0) * (LEVELS - 1) as f32).round() as usize
}

/// Pixels counted per score level, wrong and right.
#[derive(Debug, Clone)]
pub struct ScoreHistogram {
    wrong: Vec<u64>,
    right: Vec<u64>,
}

impl Default for ScoreHistogram {
    fn default() -> Self {
        Self {
            wrong: vec![0; LEVELS],
            right: vec![0; LEVELS],
        }
    }
}

impl ScoreHistogram {
    pub fn add(&mut self, score: f32, wrong: bool) {
        let l = level(score);
        if wrong {
            self.wrong[l] += 1;
        } else {
            self.right[l] += 1;
        }
    }

    pub fn wrong_pixels(&self) -> u64 {
        self.wrong.iter().sum()
    }

    pub fn pixels(&self) -> u64 {
        self.wrong_pixels() + self.right.iter().sum::<u64>()
    }

    /// The probability that a wrong pixel scores higher than a right one (ties half); `None`
    /// without both kinds of pixel.
    pub fn auroc(&self) -> Option<f64> {
        let (p, n) = (
            self.wrong_pixels() as f64,
            self.right.iter().sum::<u64>() as f64,
        );
        if p == 0.0 || n == 0.0 {
            return None;
        }
        let mut right_below = 0f64;
        let mut sum = 0f64;
        for (&w, &r) in self.wrong.iter().zip(&self.right) {
            sum += w as f64 * (right_below + 0.5 * r as f64);
            right_below += r as f64;
        }
        Some(sum / (p * n))
    }

    /// The share of wrong pixels among the `share` of pixels with the highest scores (a level
    /// cut by the share takes its pixels in proportion); `None` without wrong pixels.
    pub fn recall_at(&self, share: f64) -> Option<f64> {
        let total = self.wrong_pixels() as f64;
        if total == 0.0 {
            return None;
        }
        let mut budget = share * self.pixels() as f64;
        let mut found = 0f64;
        for (&w, &r) in self.wrong.iter().zip(&self.right).rev() {
            let here = (w + r) as f64;
            if here == 0.0 {
                continue;
            }
            let take = here.min(budget);
            found += w as f64 * take / here;
            budget -= take;
            if budget <= 0.0 {
                break;
            }
        }
        Some(found / total)
    }
}

/// Spearman's rank correlation (average ranks for ties); `None` for fewer than three pairs or
/// a constant side.
pub fn spearman(a: &[f64], b: &[f64]) -> Option<f64> {
    if a.len() != b.len() || a.len() < 3 {
        return None;
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let mean = (a.len() as f64 + 1.0) / 2.0;
    let (mut cov, mut va, mut vb) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        cov += (x - mean) * (y - mean);
        va += (x - mean).powi(2);
        vb += (y - mean).powi(2);
    }
    (va > 0.0 && vb > 0.0).then(|| cov / (va * vb).sqrt())
}

/// 1-based ranks, ties averaged (NaN ranks last).
fn ranks(v: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..v.len()).collect();
    order.sort_by(|&i, &j| v[i].total_cmp(&v[j]));
    let mut out = vec![0.0; v.len()];
    let mut i = 0;
    while i < order.len() {
        let mut j = i;
        while j + 1 < order.len() && v[order[j + 1]] == v[order[i]] {
            j += 1;
        }
        let r = (i + j) as f64 / 2.0 + 1.0;
        for &k in &order[i..=j] {
            out[k] = r;
        }
        i = j + 1;
    }
    out
}

/// A scored region with what ground truth says of it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoredRegion {
    /// The rank key: expected wrong pixels (the sum of the score).
    pub expected_wrong: f64,
    /// Pixels with ground truth, and those of them labelled wrong.
    pub judged: u64,
    pub wrong: u64,
}

/// The share of the `n` highest-ranked regions with ground truth in which at least half the
/// judged pixels are wrong; `None` without judged regions.
pub fn top_region_precision(regions: &[ScoredRegion], n: usize) -> Option<f64> {
    let mut judged: Vec<&ScoredRegion> = regions.iter().filter(|r| r.judged > 0).collect();
    judged.sort_by(|a, b| b.expected_wrong.total_cmp(&a.expected_wrong));
    judged.truncate(n);
    if judged.is_empty() {
        return None;
    }
    let hits = judged.iter().filter(|r| 2 * r.wrong >= r.judged).count();
    Some(hits as f64 / judged.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// AUROC by comparing every pair.
    fn brute_auroc(s: &[(f32, bool)]) -> f64 {
        let (mut sum, mut pairs) = (0.0, 0.0);
        for &(a, wa) in s.iter().filter(|x| x.1) {
            let _ = wa;
            for &(b, _) in s.iter().filter(|x| !x.1) {
                let (la, lb) = (level(a), level(b));
                sum += if la > lb {
                    1.0
                } else if la == lb {
                    0.5
                } else {
                    0.0
                };
                pairs += 1.0;
            }
        }
        sum / pairs
    }

    #[test]
    fn perfect_random_and_inverted_scores() {
        let mut h = ScoreHistogram::default();
        for i in 0..100 {
            h.add(i as f32 / 100.0, i >= 90);
        }
        assert_eq!(h.auroc(), Some(1.0));
        assert_eq!(h.recall_at(0.1), Some(1.0));
        assert_eq!(h.recall_at(0.05), Some(0.5));
        let mut h = ScoreHistogram::default();
        for i in 0..100 {
            h.add(0.5, i % 2 == 0);
        }
        assert_eq!(h.auroc(), Some(0.5));
        assert!((h.recall_at(0.2).unwrap() - 0.2).abs() < 1e-12);
        let mut h = ScoreHistogram::default();
        for i in 0..10 {
            h.add(i as f32 / 10.0, i < 3);
        }
        assert_eq!(h.auroc(), Some(0.0));
        assert_eq!(ScoreHistogram::default().auroc(), None);
        assert_eq!(ScoreHistogram::default().recall_at(0.05), None);
    }

    proptest! {
        #[test]
        fn auroc_equals_pair_counting(v in proptest::collection::vec((0f32..1.0, any::<bool>()), 2..60)) {
            let mut h = ScoreHistogram::default();
            for &(s, w) in &v {
                h.add(s, w);
            }
            match h.auroc() {
                Some(a) => prop_assert!((a - brute_auroc(&v)).abs() < 1e-9),
                None => prop_assert!(v.iter().all(|x| x.1) || v.iter().all(|x| !x.1)),
            }
        }
    }

    #[test]
    fn spearman_of_monotone_reversed_and_tied() {
        let a = [1.0, 2.0, 3.0, 4.0];
        assert_eq!(spearman(&a, &[10.0, 20.0, 25.0, 100.0]), Some(1.0));
        assert_eq!(spearman(&a, &[4.0, 3.0, 2.0, 1.0]), Some(-1.0));
        assert_eq!(spearman(&a, &[1.0, 1.0, 1.0, 1.0]), None);
        assert_eq!(spearman(&a[..2], &[1.0, 2.0]), None);
        // scipy.stats.spearmanr([1, 2, 3, 4, 5], [2, 1, 4, 3, 3]) = 0.5642880936468347
        let r = spearman(&[1.0, 2.0, 3.0, 4.0, 5.0], &[2.0, 1.0, 4.0, 3.0, 3.0]).unwrap();
        assert!((r - 0.564_288_093_646_834_7).abs() < 1e-12, "{r}");
    }

    #[test]
    fn region_precision_counts_the_top_judged_regions() {
        let r = |e: f64, judged: u64, wrong: u64| ScoredRegion {
            expected_wrong: e,
            judged,
            wrong,
        };
        let regions = [r(9.0, 10, 5), r(8.0, 0, 0), r(7.0, 10, 4), r(1.0, 4, 4)];
        assert_eq!(top_region_precision(&regions, 2), Some(0.5));
        assert_eq!(top_region_precision(&regions, 20), Some(2.0 / 3.0));
        assert_eq!(top_region_precision(&regions[1..2], 20), None);
    }
}
