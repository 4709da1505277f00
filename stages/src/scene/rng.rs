//! Deterministic randomness for the synthetic scene: a SplitMix64 stream keyed by
//! (seed, purpose, frame, camera, ...) and stateless hash-based value noise.
//!
//! Every random decision draws from a stream derived from a key, never from a shared
//! generator, so results do not depend on thread scheduling or on the order images are made.

pub use crate::rng::mix;
use crate::rng::{SplitMix64, GOLDEN_GAMMA};

/// Hash of a key (order matters).
pub fn hash(key: &[u64]) -> u64 {
    key.iter()
        .fold(0x243F_6A88_85A3_08D3, |h, &k| mix(h ^ mix(k)))
}

/// Purposes of random streams (part of every key, so streams never collide).
#[derive(Debug, Clone, Copy)]
#[repr(u64)]
pub enum Purpose {
    Layout = 1,
    Bounds = 2,
    Exposure = 3,
    Pixel = 4,
    Labels = 5,
    Stereo = 6,
    Lidar = 7,
    Texture = 8,
}

/// A SplitMix64 stream.
#[derive(Debug, Clone)]
pub struct Rng {
    stream: SplitMix64,
}

impl Rng {
    /// The stream for `(seed, purpose, key...)`.
    pub fn new(seed: u64, purpose: Purpose, key: &[u64]) -> Self {
        let mut k = vec![seed, purpose as u64];
        k.extend_from_slice(key);
        // One step ahead of the key: the streams the scene has always drawn (its outputs are
        // cached by content, so they must not change).
        Self {
            stream: SplitMix64::new(hash(&k).wrapping_add(GOLDEN_GAMMA)),
        }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.stream.next_u64()
    }

    /// Uniform in [0, 1).
    pub fn f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.f64()
    }

    /// Uniform integer in [0, n).
    pub fn below(&mut self, n: u64) -> u64 {
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        self.f64() < p
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f64 {
        let u1 = 1.0 - self.f64();
        let u2 = self.f64();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// Uniform [0, 1) from a key, without a stream.
pub fn unit(key: &[u64]) -> f64 {
    (hash(key) >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// 2D value noise in [0, 1): smooth, lattice spacing 1, keyed by `key`.
pub fn value2(key: u64, x: f64, y: f64) -> f64 {
    let (xf, yf) = (x.floor(), y.floor());
    let (ix, iy) = (xf as i64, yf as i64);
    let (tx, ty) = (smooth(x - xf), smooth(y - yf));
    let v = |dx: i64, dy: i64| unit(&[key, (ix + dx) as u64, (iy + dy) as u64]);
    let a = v(0, 0) + (v(1, 0) - v(0, 0)) * tx;
    let b = v(0, 1) + (v(1, 1) - v(0, 1)) * tx;
    a + (b - a) * ty
}

/// 3D value noise in [0, 1), lattice spacing 1.
pub fn value3(key: u64, x: f64, y: f64, z: f64) -> f64 {
    let (xf, yf, zf) = (x.floor(), y.floor(), z.floor());
    let (ix, iy, iz) = (xf as i64, yf as i64, zf as i64);
    let (tx, ty, tz) = (smooth(x - xf), smooth(y - yf), smooth(z - zf));
    let v = |dx: i64, dy: i64, dz: i64| {
        unit(&[key, (ix + dx) as u64, (iy + dy) as u64, (iz + dz) as u64])
    };
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = lerp(v(0, 0, 0), v(1, 0, 0), tx);
    let x10 = lerp(v(0, 1, 0), v(1, 1, 0), tx);
    let x01 = lerp(v(0, 0, 1), v(1, 0, 1), tx);
    let x11 = lerp(v(0, 1, 1), v(1, 1, 1), tx);
    lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz)
}

/// Fractal (two-octave) 2D value noise in [0, 1).
pub fn fbm2(key: u64, x: f64, y: f64) -> f64 {
    (value2(key, x, y) * 2.0 + value2(key ^ 0x5555, 2.0 * x + 17.3, 2.0 * y - 4.1)) / 3.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn streams_are_keyed_and_repeatable() {
        let a: Vec<u64> = {
            let mut r = Rng::new(1, Purpose::Pixel, &[3, 0]);
            (0..4).map(|_| r.next_u64()).collect()
        };
        let b: Vec<u64> = {
            let mut r = Rng::new(1, Purpose::Pixel, &[3, 0]);
            (0..4).map(|_| r.next_u64()).collect()
        };
        let c = Rng::new(1, Purpose::Pixel, &[3, 1]).next_u64();
        assert_eq!(a, b);
        assert_ne!(a[0], c);
    }

    #[test]
    fn uniform_and_noise_stay_in_range() {
        let mut r = Rng::new(7, Purpose::Layout, &[]);
        let mean: f64 = (0..10_000).map(|_| r.f64()).sum::<f64>() / 10_000.0;
        assert!((mean - 0.5).abs() < 0.02, "{mean}");
        for i in 0..1000 {
            let x = i as f64 * 0.173;
            let v = value2(3, x, -x * 0.7);
            let w = value3(3, x, 0.3 * x, -x);
            assert!((0.0..1.0).contains(&v) && (0.0..1.0).contains(&w));
        }
        assert!(r.below(5) < 5);
    }
}
