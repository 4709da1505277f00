//! Benchmark of semi-global matching (`stereo_depth`) on one full-size KITTI-360 pair: 1408x376,
//! 128 disparities, 8 paths, as `pipelines/kitti360.yaml` runs it 64 times. A textured ground
//! plane whose disparity grows towards the bottom of the image, with a box in front of it.
//! Before the three-sweep matcher (2026-12-07) a pair took 1.34 s on this project's 2-core VM.
//!
//! `cargo bench -p stages --bench sgm`

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion};
use stages::scene::stereo::{census, disparity, Matcher, StereoParams};

/// A smooth pseudo-random texture at continuous `x` on row `y`.
fn texture(x: f64, y: usize) -> u8 {
    let v = |i: i64| {
        let h = (i as u64)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add((y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
        ((h ^ (h >> 29)).wrapping_mul(0x1656_67B1_9E37_79F9) >> 56) as f64 * 0.8 + 20.0
    };
    let (i, f) = (x.floor() as i64, x - x.floor());
    (v(i) * (1.0 - f) + v(i + 1) * f).round() as u8
}

/// A rectified pair `(left, right)` of `w x h` grey images.
pub fn pair(w: usize, h: usize) -> (Vec<u8>, Vec<u8>) {
    let disp = |x: usize, y: usize| {
        let ground = 2.0 + 100.0 * (y as f64 / h as f64).powi(2);
        let in_box = (w / 3..w / 2).contains(&x) && (h / 4..3 * h / 4).contains(&y);
        if in_box {
            ground.max(45.5)
        } else {
            ground
        }
    };
    let mut l = Vec::with_capacity(w * h);
    let mut r = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            l.push(texture(x as f64 / 1.7, y));
            r.push(texture((x as f64 + disp(x, y)) / 1.7, y));
        }
    }
    (l, r)
}

fn bench(c: &mut Criterion) {
    let (w, h) = (1408, 376);
    let (l, r) = pair(w, h);
    let p = StereoParams {
        max_disparity: 128,
        ..Default::default()
    };
    let mut g = c.benchmark_group("sgm");
    g.sample_size(10);
    g.bench_function("census_1408x376", |b| {
        b.iter(|| census(black_box(&l), w, h, 2))
    });
    // The first pair (fresh volumes) and every later one (the stage's matcher keeps them).
    g.bench_function("first_pair_1408x376_128d_8paths", |b| {
        b.iter(|| disparity(black_box(&l), black_box(&r), w, h, &p))
    });
    let mut matcher = Matcher::default();
    g.bench_function("next_pair_1408x376_128d_8paths", |b| {
        b.iter(|| matcher.disparity(black_box(&l), black_box(&r), w, h, &p))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
