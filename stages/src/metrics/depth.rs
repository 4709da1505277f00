//! Depth accuracy against LiDAR: RMSE and delta < 1.25, accumulated over frames as sums and
//! counts.

use super::error::{check_len, MetricError};

/// Sums over frames for depth RMSE and delta < 1.25.
///
/// Valid pixels are those with a finite LiDAR depth `0 < d* < max_depth`; the prediction does
/// not choose which pixels count. A predicted depth `d <= 0` is a failure for delta and its
/// value enters the RMSE as it is (error `d - d*`); a non-finite prediction (NaN, infinity)
/// is a failure for delta and enters the RMSE as if it were 0 (error `-d*`), so one bad pixel
/// cannot turn the RMSE into NaN.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthAccumulator {
    max_depth: f64,
    sq_err_sum: f64,
    pixels: u64,
    within: u64,
}

/// Depth metrics over the frames added.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthMetrics {
    /// Root mean squared error in metres; `None` without valid pixels.
    pub rmse: Option<f64>,
    /// Fraction of valid pixels with `max(d / d*, d* / d) < 1.25`.
    pub delta_1_25: Option<f64>,
    /// Valid pixels.
    pub pixels: u64,
}

impl Default for DepthAccumulator {
    /// `max_depth` 100 m (the paper's).
    fn default() -> Self {
        Self::new(100.0).expect("100 m is a valid range")
    }
}

impl DepthAccumulator {
    /// An empty accumulator counting LiDAR depths below `max_depth` metres (finite, > 0).
    pub fn new(max_depth: f64) -> Result<Self, MetricError> {
        if !(max_depth.is_finite() && max_depth > 0.0) {
            return Err(MetricError::Setting(format!(
                "max_depth must be a positive number of metres, got {max_depth}"
            )));
        }
        Ok(Self {
            max_depth,
            sq_err_sum: 0.0,
            pixels: 0,
            within: 0,
        })
    }

    /// Adds one frame.
    ///
    /// # Shapes
    /// `pred`, `lidar`: `[height * width]` z-depths in metres; `lidar` 0 where no point.
    pub fn add(&mut self, pred: &[f32], lidar: &[f32]) -> Result<(), MetricError> {
        check_len("predicted depth", lidar.len(), pred.len())?;
        for (&d, &g) in pred.iter().zip(lidar) {
            let Some((err, within)) = pixel_error(d, g, self.max_depth) else {
                continue;
            };
            self.pixels += 1;
            self.sq_err_sum += err * err;
            self.within += u64::from(within);
        }
        Ok(())
    }

    /// Adds the sums of `other`; both must have the same `max_depth`.
    pub fn merge(&mut self, other: &DepthAccumulator) -> Result<(), MetricError> {
        if self.max_depth != other.max_depth {
            return Err(MetricError::Merge(format!(
                "depth accumulators with max_depth {} and {}",
                self.max_depth, other.max_depth
            )));
        }
        self.sq_err_sum += other.sq_err_sum;
        self.pixels += other.pixels;
        self.within += other.within;
        Ok(())
    }

    /// RMSE and delta over all valid pixels of all frames.
    pub fn result(&self) -> DepthMetrics {
        let n = self.pixels as f64;
        DepthMetrics {
            rmse: (self.pixels > 0).then(|| (self.sq_err_sum / n).sqrt()),
            delta_1_25: (self.pixels > 0).then(|| self.within as f64 / n),
            pixels: self.pixels,
        }
    }
}

/// One pixel as the depth metrics score it: `None` where the LiDAR depth `g` is not valid
/// (`0 < g < max_depth`, finite), else the error `d - g` (a non-finite prediction counts as 0)
/// and whether `max(d / g, g / d) < 1.25`.
fn pixel_error(d: f32, g: f32, max_depth: f64) -> Option<(f64, bool)> {
    let g = g as f64;
    if !(g.is_finite() && g > 0.0 && g < max_depth) {
        return None;
    }
    let d = if (d as f64).is_finite() {
        d as f64
    } else {
        0.0
    };
    Some((d - g, d > 0.0 && (d / g).max(g / d) < 1.25))
}

/// Depth errors broken down by bins of pixels (distance band, class, ...): each pixel is
/// scored as [`DepthAccumulator`] scores it and counted in every bin it is given, and each bin
/// reports its share of the squared error of all the pixels added (which answers "where does
/// the RMSE come from?").
#[derive(Debug, Clone, PartialEq)]
pub struct DepthBins<K: Ord> {
    max_depth: f64,
    bins: std::collections::BTreeMap<K, BinSums>,
    total_sq: f64,
    total_pixels: u64,
}

#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct BinSums {
    pixels: u64,
    sq: f64,
    err: f64,
    within: u64,
}

/// One bin's depth figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BinResult {
    pub pixels: u64,
    pub rmse: Option<f64>,
    /// Mean signed error (prediction - LiDAR): positive = too far.
    pub mean_error: Option<f64>,
    pub delta_1_25: Option<f64>,
    /// The bin's squared error over that of every pixel added.
    pub share_sq_error: Option<f64>,
}

impl<K: Ord + Clone> DepthBins<K> {
    /// Empty bins counting LiDAR depths below `max_depth` metres (finite, > 0).
    pub fn new(max_depth: f64) -> Result<Self, MetricError> {
        DepthAccumulator::new(max_depth)?;
        Ok(Self {
            max_depth,
            bins: Default::default(),
            total_sq: 0.0,
            total_pixels: 0,
        })
    }

    /// Adds one pixel (prediction `d`, LiDAR `g`) to each bin of `keys`; returns whether the
    /// pixel counted (valid LiDAR).
    pub fn add(&mut self, keys: &[K], d: f32, g: f32) -> bool {
        let Some((err, within)) = pixel_error(d, g, self.max_depth) else {
            return false;
        };
        self.total_sq += err * err;
        self.total_pixels += 1;
        for k in keys {
            let b = self.bins.entry(k.clone()).or_default();
            b.pixels += 1;
            b.sq += err * err;
            b.err += err;
            b.within += u64::from(within);
        }
        true
    }

    /// Every bin that received a pixel, in key order.
    pub fn results(&self) -> Vec<(K, BinResult)> {
        self.bins
            .iter()
            .map(|(k, b)| {
                let n = b.pixels as f64;
                let some = |v: f64| (b.pixels > 0).then_some(v);
                (
                    k.clone(),
                    BinResult {
                        pixels: b.pixels,
                        rmse: some((b.sq / n).sqrt()),
                        mean_error: some(b.err / n),
                        delta_1_25: some(b.within as f64 / n),
                        share_sq_error: (self.total_sq > 0.0).then(|| b.sq / self.total_sq),
                    },
                )
            })
            .collect()
    }

    /// Pixels added with valid LiDAR.
    pub fn pixels(&self) -> u64 {
        self.total_pixels
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rmse_and_delta_on_hand_values() {
        // lidar  10   0    20   50   150  4
        // pred   11   7    30   50   1    -1
        // pixel 2 (no LiDAR) and 5 (beyond 100 m) do not count: 4 valid pixels.
        // errors 1, 10, 0, -5 -> squares 1 + 100 + 0 + 25 = 126 -> RMSE sqrt(126 / 4)
        // ratios 1.1 (ok), 1.5 (fail), 1 (ok), d <= 0 (fail) -> delta 2 / 4
        let lidar = [10.0, 0.0, 20.0, 50.0, 150.0, 4.0];
        let pred = [11.0, 7.0, 30.0, 50.0, 1.0, -1.0];
        let mut acc = DepthAccumulator::default();
        acc.add(&pred, &lidar).unwrap();
        let m = acc.result();
        assert_eq!(m.pixels, 4);
        assert!((m.rmse.unwrap() - (126.0f64 / 4.0).sqrt()).abs() < 1e-12);
        assert_eq!(m.delta_1_25, Some(0.5));
    }

    #[test]
    fn ratio_of_exactly_1_25_fails_and_nan_prediction_is_zero() {
        // 8 / 10: ratio 1.25 is not < 1.25; NaN -> 0: error -4, failure.
        let mut acc = DepthAccumulator::new(100.0).unwrap();
        acc.add(&[8.0, f32::NAN], &[10.0, 4.0]).unwrap();
        let m = acc.result();
        assert_eq!(m.delta_1_25, Some(0.0));
        // (4 + 16) / 2 = 10
        assert!((m.rmse.unwrap() - 10f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn frames_accumulate_as_sums_not_means_of_means() {
        // Frame 1: one pixel, error 4. Frame 2: three pixels, error 0.
        // Pooled RMSE sqrt(16 / 4) = 2 (a mean of per-frame RMSEs would say 2 as well only by
        // accident: (4 + 0) / 2 = 2; check delta instead: 0 of 1 and 3 of 3 -> 3/4, not 1/2).
        let mut a = DepthAccumulator::default();
        a.add(&[6.0], &[10.0]).unwrap();
        let mut b = DepthAccumulator::default();
        b.add(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]).unwrap();
        let mut one = a.clone();
        one.add(&[1.0, 2.0, 3.0], &[1.0, 2.0, 3.0]).unwrap();
        a.merge(&b).unwrap();
        assert_eq!(a, one);
        let m = a.result();
        assert_eq!(m.rmse, Some(2.0));
        assert_eq!(m.delta_1_25, Some(0.75));
        assert!(a.merge(&DepthAccumulator::new(80.0).unwrap()).is_err());
    }

    /// Every pixel in bin "all" and in one of two halves: "all" equals the accumulator over
    /// the same pixels, the halves' pixels and squared errors add up to it, shares sum to 1.
    #[test]
    fn bins_agree_with_the_accumulator_and_their_shares_add_up() {
        let lidar = [10.0, 0.0, 20.0, 50.0, 150.0, 4.0, 30.0, 7.0];
        let pred = [11.0, 7.0, 30.0, 50.0, 1.0, -1.0, f32::NAN, 7.5];
        let mut acc = DepthAccumulator::default();
        acc.add(&pred, &lidar).unwrap();
        let mut bins = DepthBins::new(100.0).unwrap();
        for (i, (&d, &g)) in pred.iter().zip(&lidar).enumerate() {
            let half = if i % 2 == 0 { "even" } else { "odd" };
            bins.add(&["all", half], d, g);
        }
        let r: std::collections::BTreeMap<_, _> = bins.results().into_iter().collect();
        let m = acc.result();
        assert_eq!(r["all"].pixels, m.pixels);
        assert_eq!(bins.pixels(), m.pixels);
        assert!((r["all"].rmse.unwrap() - m.rmse.unwrap()).abs() < 1e-12);
        assert_eq!(r["all"].delta_1_25, m.delta_1_25);
        assert_eq!(r["all"].share_sq_error, Some(1.0));
        assert_eq!(r["even"].pixels + r["odd"].pixels, m.pixels);
        let shares = r["even"].share_sq_error.unwrap() + r["odd"].share_sq_error.unwrap();
        assert!((shares - 1.0).abs() < 1e-12);
        // Even pixels 0, 2, 6 (4 beyond range): errors 1, 10, -30 -> mean -19 / 3.
        assert_eq!(r["even"].pixels, 3);
        assert!((r["even"].mean_error.unwrap() + 19.0 / 3.0).abs() < 1e-12);
        assert!(DepthBins::<u8>::new(-1.0).is_err());
    }

    #[test]
    fn empty_and_invalid() {
        let m = DepthAccumulator::default().result();
        assert_eq!((m.rmse, m.delta_1_25, m.pixels), (None, None, 0));
        assert!(DepthAccumulator::new(0.0).is_err());
        assert!(DepthAccumulator::new(f64::NAN).is_err());
        assert!(DepthAccumulator::default().add(&[1.0], &[]).is_err());
    }
}
