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
            let g = g as f64;
            if !(g.is_finite() && g > 0.0 && g < self.max_depth) {
                continue;
            }
            let d = if (d as f64).is_finite() {
                d as f64
            } else {
                0.0
            };
            self.pixels += 1;
            self.sq_err_sum += (d - g) * (d - g);
            if d > 0.0 && (d / g).max(g / d) < 1.25 {
                self.within += 1;
            }
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

    #[test]
    fn empty_and_invalid() {
        let m = DepthAccumulator::default().result();
        assert_eq!((m.rmse, m.delta_1_25, m.pixels), (None, None, 0));
        assert!(DepthAccumulator::new(0.0).is_err());
        assert!(DepthAccumulator::new(f64::NAN).is_err());
        assert!(DepthAccumulator::default().add(&[1.0], &[]).is_err());
    }
}
