//! Test fixtures of the model: a toy scene of two boxes and a sky interval, as a ready
//! [`RayBatch`] and as a [`RaySet`] for the sampler and the compositor, and a small field.

use crate::labels::{CAR, ROAD, SKY};
use crate::model::batch::{RayBatch, RaySamples, RayTargets};
use crate::model::config::{FieldConfig, FieldSpec, GridConfig, TrainConfig};
use crate::model::params::NamedWeight;
use crate::rng::SplitMix64;
use crate::sampling::{sample_batch, PrimInfo, RaySet, SamplingParams, NONE};

/// 64 rays along +z through a 2-class toy scene: left half hits a class-0 box, right half a
/// class-1 box (z in [2, 3]), then a sky interval (z in [5, 7]); every 4th ray sees only
/// the sky interval. Classes: [0, 1, sky].
pub fn toy_scene() -> RayBatch {
    let (rays, n, c) = (64usize, 32usize, 3usize);
    let mut s = RaySamples {
        rays,
        samples: n,
        classes: c,
        ..Default::default()
    };
    let mut t = RayTargets::default();
    for i in 0..rays {
        let x = -0.9 + 1.8 * (i % 8) as f32 / 7.0;
        let y = -0.9 + 1.8 * (i / 8) as f32 / 7.0;
        let sky_only = i % 4 == 3;
        let class = if x < 0.0 { 0 } else { 1 };
        for k in 0..n {
            let (z, delta, label) = if sky_only {
                (5.0 + 2.0 * (k as f32 + 0.5) / n as f32, 2.0 / n as f32, 2)
            } else if k < 16 {
                (2.0 + (k as f32 + 0.5) / 16.0, 1.0 / 16.0, class)
            } else {
                (5.0 + 2.0 * (k as f32 - 15.5) / 16.0, 2.0 / 16.0, 2)
            };
            s.positions.extend_from_slice(&[x, y, z]);
            s.deltas.push(delta);
            s.t_mid.push(z);
            let mut p = [0f32; 3];
            p[label] = 1.0;
            s.fixed_semantics.extend_from_slice(&p);
        }
        s.directions.extend_from_slice(&[0.0, 0.0, 1.0]);
        t.labels.push(if sky_only { 2 } else { class as i32 });
        t.ray_mask.push(1.0);
        t.depth.push(if sky_only { f32::NAN } else { 2.0 });
        t.depth_valid.push(!sky_only);
        t.rgb.extend_from_slice(match (sky_only, class) {
            (true, _) => &[0.5, 0.7, 1.0],
            (false, 0) => &[1.0, 0.0, 0.0],
            _ => &[0.0, 1.0, 0.0],
        });
    }
    let b = RayBatch {
        samples: s,
        targets: t,
    };
    b.validate().unwrap();
    b
}

pub fn toy_spec() -> FieldSpec {
    FieldSpec {
        config: toy_field(),
        num_classes: 3,
        aabb_min: [-1.0, -1.0, 0.0],
        aabb_max: [1.0, 1.0, 8.0],
        seed: 0,
    }
}

pub fn toy_field() -> FieldConfig {
    FieldConfig {
        grid: GridConfig {
            levels: 4,
            log2_table_size: 12,
            max_resolution: 64,
            ..Default::default()
        },
        ..Default::default()
    }
}

pub fn toy_config() -> TrainConfig {
    TrainConfig {
        field: toy_field(),
        optimiser: super::optimiser::Optimiser {
            lr: 1e-2,
            ..Default::default()
        },
        iterations: 100,
        // The paper's weights, whatever the pipeline's default: the toy tests were sized on them.
        losses: super::config::Losses {
            fixed_2d: 1.0,
            learned_2d: 1.0,
            point_3d: 1.0,
            rgb: 1.0,
            depth: 0.1,
            sky_prior: 0.0,
            ..Default::default()
        },
        ..Default::default()
    }
}

/// The toy scene as a ray set: 8 x 8 rays along +z through x, y in [-0.9, 0.9]; rays with x < 0
/// cross a road slab, the others a car box (z in [2, 3]; instance 1 of the scene's one thing);
/// every ray then has a sky interval z in [5, 7]; every 4th ray crosses no primitive.
pub fn toy_set() -> RaySet {
    let mut s = RaySet {
        prims: PrimInfo {
            classes: vec![ROAD, CAR, SKY],
            things: vec![(CAR, 1)],
            prim_class: vec![0, 1],
            prim_thing: vec![u32::MAX, 0],
            bounds_min: [-1.0, -1.0, 2.0],
            bounds_max: [1.0, 1.0, 3.0],
        },
        offsets: vec![0],
        ..Default::default()
    };
    for i in 0..64 {
        let x = -0.9 + 1.8 * (i % 8) as f32 / 7.0;
        let y = -0.9 + 1.8 * (i / 8) as f32 / 7.0;
        let sky_only = i % 4 == 3;
        let class = if x < 0.0 { 0u16 } else { 1 };
        s.origin.push([x, y, 0.0]);
        s.dir.push([0.0, 0.0, 1.0]);
        s.z_scale.push(1.0);
        if !sky_only {
            s.t_in.push(2.0);
            s.t_out.push(3.0);
            s.prim.push(class as u32);
        }
        s.offsets.push(s.t_in.len() as u32);
        s.sky.push([5.0, 7.0]);
        s.rgb.push(match (sky_only, class) {
            (true, _) => [0.5, 0.7, 1.0],
            (false, 0) => [1.0, 0.0, 0.0],
            _ => [0.0, 1.0, 0.0],
        });
        s.label.push(if sky_only { 2 } else { class });
        s.u_mask.push(true);
        s.depth.push(if sky_only { 0.0 } else { 2.0 });
    }
    assert!(s.label.iter().all(|&l| l != NONE));
    s
}

/// Sampling of the toy set: 12 samples inside primitives, 4 in the sky.
pub fn toy_sampling() -> SamplingParams {
    SamplingParams {
        samples: 12,
        sky_samples: 4,
        ..Default::default()
    }
}

/// Training batch `iteration` of the toy set: every ray, freshly jittered.
pub fn toy_batch(set: &RaySet, iteration: usize) -> RayBatch {
    let ids: Vec<u32> = (0..set.origin.len() as u32).collect();
    let b = sample_batch(
        set,
        &ids,
        &toy_sampling(),
        Some(iteration as u64 * 7919 + 1),
    )
    .expect("toy rays sample");
    RayBatch::from_samples(&b)
}

/// `rows` with a grid of large random values and random biases, so every path of the field
/// carries signal from the first step.
pub fn lively(mut rows: Vec<NamedWeight>, seed: u64) -> Vec<NamedWeight> {
    let mut rng = SplitMix64::new(seed);
    for w in &mut rows {
        if w.name == "grid.table" {
            w.values
                .iter_mut()
                .for_each(|v| *v = rng.uniform(-0.5, 0.5));
        } else if w.name.ends_with("bias") {
            w.values
                .iter_mut()
                .for_each(|v| *v = rng.uniform(-0.2, 0.2));
        }
    }
    rows
}
