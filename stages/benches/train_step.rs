//! Micro-benchmark: one training step (host prep + forward + 5 losses + backward + clipping +
//! Adam) at 1024 and 4096 rays x 32 samples, per compiled-in engine and per encoding.
//!
//! Run: `cargo bench -p stages --bench train_step` (add `--features ndarray` to compare with
//! burn-ndarray; `BENCH_STEPS=n` sets the timed steps, default 5, after 2 warm-up steps;
//! `BENCH_FUSED_ONLY=1` times the fused engine only, `BENCH_NO_V1=1` without its baseline build;
//! `BENCH_GRID=12,18,2048` the KITTI-360 pipeline's grid).

use std::time::Instant;

use stages::model::fused::{FusedField, FusedTrainer};
use stages::model::{
    EncodingKind, Engine, FieldConfig, FieldSpec, RayBatch, RaySamples, RayTargets, TrainConfig,
};
use stages::rng::SplitMix64;

const SAMPLES: usize = 32;
const CLASSES: usize = 10;

fn random_batch(rays: usize, seed: u64) -> RayBatch {
    let mut rng = SplitMix64::new(seed);
    let mut s = RaySamples {
        rays,
        samples: SAMPLES,
        classes: CLASSES,
        ..Default::default()
    };
    let mut t = RayTargets::default();
    for _ in 0..rays {
        let o = [
            rng.uniform(-10.0, 10.0),
            rng.uniform(-10.0, 10.0),
            rng.uniform(0.0, 2.0),
        ];
        let d = [rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 1.0];
        let mut z = rng.uniform(1.0, 5.0);
        for _ in 0..SAMPLES {
            let delta = rng.uniform(0.05, 0.5);
            z += delta;
            s.positions.extend((0..3).map(|a| o[a] + z * d[a]));
            s.deltas.push(delta);
            s.t_mid.push(z);
            let mut p = vec![0f32; CLASSES];
            p[rng.below(CLASSES)] = 1.0;
            s.fixed_semantics.extend(p);
        }
        s.directions.extend_from_slice(&d);
        t.labels.push(rng.below(CLASSES) as i32);
        t.ray_mask.push((rng.unit() < 0.8) as u8 as f32);
        t.depth.push(rng.uniform(2.0, 20.0));
        t.depth_valid.push(rng.unit() < 0.5);
        t.rgb.extend((0..3).map(|_| rng.unit()));
    }
    RayBatch {
        samples: s,
        targets: t,
    }
}

/// The fused CPU path on the default grid field, with its phase breakdown: its AVX2 kernels
/// (`fused`) and, on a CPU that has AVX2, the same kernels for baseline x86-64 (`fused-v1`).
fn bench_fused(steps: usize) {
    let paths: &[bool] = match (
        stages::model::fused::avx2(),
        std::env::var("BENCH_NO_V1").is_ok(),
    ) {
        (true, false) => &[false, true],
        (true, true) => &[false],
        (false, _) => &[true],
    };
    for (rays, &baseline) in [1024, 4096]
        .into_iter()
        .flat_map(|r| paths.iter().map(move |b| (r, b)))
    {
        stages::model::fused::baseline_only(baseline);
        let field = bench_field();
        let config = TrainConfig {
            field: field.clone(),
            ..Default::default()
        };
        let spec = FieldSpec {
            config: field,
            num_classes: CLASSES,
            aabb_min: [-12.0, -12.0, 0.0],
            aabb_max: [12.0, 12.0, 40.0],
            seed: 0,
        };
        let init = FusedField::init(spec).expect("grid");
        let mut trainer = FusedTrainer::new(config, init).expect("trainer");
        let batch = random_batch(rays, 1);
        for _ in 0..2 {
            trainer.step(&batch).expect("warm-up step");
        }
        let mut times = Vec::new();
        let mut phases = [0f64; 3];
        for _ in 0..steps {
            let t0 = Instant::now();
            trainer.step(&batch).expect("step");
            times.push(t0.elapsed().as_secs_f64() * 1e3);
            for (p, t) in phases.iter_mut().zip(trainer.timings) {
                *p += t * 1e3 / steps as f64;
            }
        }
        let mean = times.iter().sum::<f64>() / times.len() as f64;
        let min = times.iter().cloned().fold(f64::INFINITY, f64::min);
        println!(
            "{:<8} {:<5} {:>6} {:>10.1} {:>10.1}   (forward {:.1}, backward {:.1}, reduce+adam {:.1} ms)",
            if baseline && paths.len() == 2 { "fused-v1" } else { "fused" },
            "grid",
            rays, mean, min, phases[0], phases[1], phases[2]
        );
    }
    stages::model::fused::baseline_only(false);
}

/// The default field, or with `BENCH_GRID=levels,log2_table_size,max_resolution` another grid
/// (`12,18,2048`: the KITTI-360 pipeline's).
fn bench_field() -> FieldConfig {
    let mut field = FieldConfig::default();
    if let Ok(v) = std::env::var("BENCH_GRID") {
        let n: Vec<u32> = v
            .split(',')
            .map(|x| x.parse().expect("BENCH_GRID: three integers"))
            .collect();
        assert_eq!(
            n.len(),
            3,
            "BENCH_GRID: levels,log2_table_size,max_resolution"
        );
        field.grid.levels = n[0] as usize;
        field.grid.log2_table_size = n[1];
        field.grid.max_resolution = n[2];
    }
    field
}

fn main() {
    let steps: usize = std::env::var("BENCH_STEPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(5);
    println!(
        "train_step: {} threads, {steps} timed steps after 2 warm-up",
        rayon::current_num_threads()
    );
    println!(
        "{:<8} {:<5} {:>6} {:>10} {:>10}",
        "backend", "enc", "rays", "mean ms", "min ms"
    );
    let configs = [
        ("grid", FieldConfig::default()),
        (
            "pe",
            FieldConfig {
                pe_position_frequencies: 10,
                ..FieldConfig::pe()
            },
        ),
    ];
    bench_fused(steps);
    if std::env::var("BENCH_FUSED_ONLY").is_ok() {
        return;
    }
    for engine in Engine::available() {
        if engine == Engine::Fused {
            continue; // timed above, with its phases
        }
        for (name, field) in &configs {
            for rays in [1024, 4096] {
                if field.encoding == EncodingKind::Pe
                    && rays > 1024
                    && std::env::var("BENCH_PE_4096").is_err()
                {
                    continue;
                }
                let config = TrainConfig {
                    field: field.clone(),
                    ..Default::default()
                };
                let spec = FieldSpec {
                    config: field.clone(),
                    num_classes: CLASSES,
                    aabb_min: [-12.0, -12.0, 0.0],
                    aabb_max: [12.0, 12.0, 40.0],
                    seed: 0,
                };
                let mut trainer = engine.trainer(&config, spec).expect("trainer");
                let batch = random_batch(rays, 1);
                for _ in 0..2 {
                    trainer.step(&batch).expect("warm-up step");
                }
                let mut times = Vec::new();
                for _ in 0..steps {
                    let t0 = Instant::now();
                    trainer.step(&batch).expect("step");
                    times.push(t0.elapsed().as_secs_f64() * 1e3);
                }
                let mean = times.iter().sum::<f64>() / times.len() as f64;
                let min = times.iter().cloned().fold(f64::INFINITY, f64::min);
                println!(
                    "{:<8} {:<5} {:>6} {:>10.1} {:>10.1}",
                    engine.name(),
                    name,
                    rays,
                    mean,
                    min
                );
            }
        }
    }
}
