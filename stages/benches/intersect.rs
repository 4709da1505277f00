//! Benchmark of the sampling plan's hot kernel: 1M camera rays (a 1000x1000 image, rows in
//! parallel with rayon) against 1000 primitives of every kind through the BVH, keeping the
//! first k = 10 intervals per ray, as the `intersect` stage does. Goal: <= 2 s on 2 cores.
//! Then the sampler's placement of 32 samples along each of those rays, on one thread (what
//! every training batch and every rendered pixel pays once per ray).
//!
//! `cargo bench -p stages --bench intersect`

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use stages::{
    geometry::{demo::city_scene, Bvh},
    intervals::{plan_image, IntersectParams},
    sampling::{place_samples, Intervals, SamplingParams},
};

fn bench(c: &mut Criterion) {
    let (prims, cam) = city_scene(1000, 1000, 1000, 42);
    let p = IntersectParams::default();
    let mut g = c.benchmark_group("intersect");
    g.sample_size(10);
    g.bench_function("bvh_build_1000_prims", |b| {
        b.iter(|| Bvh::build(black_box(&prims)))
    });
    let bvh = Bvh::build(&prims);
    let plan = plan_image(&prims, &bvh, &cam, &p);
    let total: usize = plan.hits.iter().map(|&h| h as usize).sum();
    eprintln!(
        "scene: {} primitives, {} BVH nodes (depth {}); {} rays, {:.2} intervals per ray, {:.1}% rays hit",
        prims.len(),
        bvh.node_count(),
        bvh.depth(),
        plan.hits.len(),
        total as f64 / plan.hits.len() as f64,
        100.0 * plan.hits.iter().filter(|&&h| h > 0).count() as f64 / plan.hits.len() as f64
    );
    g.throughput(Throughput::Elements(1_000_000));
    g.bench_function("plan_1M_rays_1000_prims", |b| {
        b.iter(|| plan_image(black_box(&prims), &bvh, &cam, &p))
    });
    g.finish();

    let offsets: Vec<usize> = std::iter::once(0)
        .chain(plan.hits.iter().scan(0, |o, &h| {
            *o += h as usize;
            Some(*o)
        }))
        .collect();
    let sp = SamplingParams::default();
    let s_n = sp.per_ray();
    let mut g = c.benchmark_group("sampling");
    g.sample_size(10);
    g.throughput(Throughput::Elements(plan.hits.len() as u64));
    g.bench_function("place_32_samples_1M_rays", |b| {
        let (mut t, mut d) = (vec![0.0; s_n], vec![0.0; s_n]);
        b.iter(|| {
            let mut sum = 0.0;
            for r in 0..plan.hits.len() {
                let (a, z) = (offsets[r], offsets[r + 1]);
                let iv = Intervals {
                    t_in: &plan.t_in[a..z],
                    t_out: &plan.t_out[a..z],
                    prim: &plan.prim[a..z],
                    sky: [plan.sky_t0[r], plan.sky_t1[r]],
                };
                place_samples(&iv, &sp, None, &mut t, &mut d);
                sum += d[0];
            }
            black_box(sum)
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
