//! The fused engine against the burn engine's autodiff: losses, gradients and inference.

use super::*;
use crate::model::batch::RayBatch;
use crate::model::burn::{reference_gradients, Backend, FieldHead, RadianceField};
use crate::model::config::Losses;
use crate::model::config::{FieldConfig, GridConfig, SkyColourInput, TrainConfig};
use crate::model::field::Heads;
use crate::model::loss::LossTerm;
use crate::model::optimiser::Optimiser;
use crate::model::params::{self, NamedWeight};
use crate::model::testing::{lively, toy_scene, toy_spec};

/// A toy field whose grid holds large random values, so every path carries signal.
fn toy_fields() -> (RadianceField, FusedField) {
    toy_fields_with_heads(1)
}

/// [`toy_fields`] with `head_layers` hidden layers in the colour and semantic heads.
fn toy_fields_with_heads(head_layers: usize) -> (RadianceField, FusedField) {
    toy_fields_where(head_layers, SkyColourInput::Field)
}

/// [`toy_fields_with_heads`] whose colour head sees `sky_colour` in the sky interval.
fn toy_fields_where(head_layers: usize, sky_colour: SkyColourInput) -> (RadianceField, FusedField) {
    let mut spec = toy_spec();
    spec.config = FieldConfig {
        grid: GridConfig {
            levels: 3,
            log2_table_size: 10,
            base_resolution: 4,
            max_resolution: 32,
            ..Default::default()
        },
        hidden: 16,
        geo_features: 7,
        trunk_layers: 2,
        head_layers,
        sky_colour,
        ..Default::default()
    };
    let weights = lively(params::initial(&spec), 9);
    let burn =
        RadianceField::from_weights(spec.clone(), &weights, &Backend::REFERENCE.train_device())
            .unwrap();
    let fused = FusedField::from_weights(spec, weights).unwrap();
    (burn, fused)
}

/// The toy scene with overlapping (two-class) samples, varied deltas, some unlabelled rays
/// and rays masked out by u(r).
fn varied_batch() -> RayBatch {
    let mut b = toy_scene();
    let (c, n) = (b.samples.classes, b.samples.samples);
    for r in 0..b.samples.rays {
        if r % 5 == 1 {
            for k in 2..6 {
                let row = &mut b.samples.fixed_semantics[(r * n + k) * c..(r * n + k + 1) * c];
                row.copy_from_slice(&[0.5, 0.5, 0.0]);
            }
        }
        if r % 7 == 2 {
            b.targets.labels[r] = -1;
        }
        if r % 6 == 0 {
            b.targets.ray_mask[r] = 0.0;
        }
        for k in 0..n {
            b.samples.deltas[r * n + k] *= 1.0 + 0.5 * ((r * 31 + k * 7) % 5) as f32 / 5.0;
        }
    }
    b
}

fn assert_close(what: &str, fused: &[NamedWeight], burn: &[NamedWeight]) {
    assert_eq!(fused.len(), burn.len());
    for (a, b) in fused.iter().zip(burn) {
        assert_eq!(a.name, b.name);
        let scale = b.values.iter().fold(0f32, |m, v| m.max(v.abs()));
        let worst = a
            .values
            .iter()
            .zip(&b.values)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max);
        assert!(
            worst <= 2e-3 * scale + 1e-6,
            "{what}: gradient of `{}` differs by {worst} (scale {scale})",
            a.name
        );
    }
}

#[test]
fn losses_and_gradients_match_burn_autodiff_per_term_and_together() {
    let batch = varied_batch();
    let mut configs: Vec<(String, TrainConfig)> = Vec::new();
    let base = TrainConfig {
        losses: Losses {
            sigma_threshold: 0.3,
            ..Losses::default()
        },
        ..Default::default()
    };
    configs.push(("all terms".into(), base.clone()));
    for term in LossTerm::ALL {
        let mut c = base.clone();
        c.losses = Losses {
            fixed_2d: 0.0,
            learned_2d: 0.0,
            point_3d: 0.0,
            rgb: 0.0,
            depth: 0.0,
            sky_prior: 0.0,
            ..base.losses.clone()
        };
        match term {
            LossTerm::Fixed2d => c.losses.fixed_2d = 1.0,
            LossTerm::Learned2d => c.losses.learned_2d = 1.0,
            LossTerm::Point3d => c.losses.point_3d = 1.0,
            LossTerm::Rgb => c.losses.rgb = 1.0,
            LossTerm::Depth => c.losses.depth = 0.1,
            LossTerm::SkyPrior => c.losses.sky_prior = 1.0,
        }
        configs.push((term.name().to_string(), c));
    }
    configs.push((
        "without u(r)".into(),
        TrainConfig {
            ray_mask: false,
            ..base.clone()
        },
    ));
    for (what, config) in configs {
        let (burn, fused) = toy_fields();
        let (want_terms, want) = reference_gradients(&burn, &batch, &config);
        let mut trainer = FusedTrainer::new(config, fused).unwrap();
        let got = trainer.gradients(&batch).unwrap();
        for ((t1, v1), (t2, v2)) in got.terms.iter().zip(&want_terms) {
            assert_eq!(t1, t2);
            assert!(
                (v1 - v2).abs() <= 1e-4 * v2.abs().max(1.0),
                "{what}: loss {t1} fused {v1} burn {v2}"
            );
        }
        assert_close(&what, &got.grads, &want);
    }
}

/// The colour head's split first layer (per-sample geometry, per-ray direction) holds with
/// no hidden head layer (the first layer is the output) and with two.
#[test]
fn gradients_match_burn_for_other_head_depths() {
    let batch = varied_batch();
    let config = TrainConfig {
        losses: Losses {
            sigma_threshold: 0.3,
            ..Losses::default()
        },
        ..Default::default()
    };
    for head_layers in [0, 2] {
        let (burn, fused) = toy_fields_with_heads(head_layers);
        let (want_terms, want) = reference_gradients(&burn, &batch, &config);
        let mut trainer = FusedTrainer::new(config.clone(), fused).unwrap();
        let got = trainer.gradients(&batch).unwrap();
        for ((t1, v1), (_, v2)) in got.terms.iter().zip(&want_terms) {
            assert!(
                (v1 - v2).abs() <= 1e-4 * v2.abs().max(1.0),
                "head_layers {head_layers}: loss {t1} fused {v1} burn {v2}"
            );
        }
        assert_close(&format!("head_layers {head_layers}"), &got.grads, &want);
    }
}

#[test]
fn inference_matches_the_burn_forward() {
    let (burn, fused) = toy_fields();
    let batch = varied_batch();
    let s = &batch.samples;
    let heads = Heads {
        rgb: true,
        semantics: true,
    };
    let out = fused.evaluate(&s.positions, &s.directions, s.samples, &s.in_sky(), heads);
    let (sigma, rgb, logits) = (out.sigma, out.rgb, out.logits);
    let input = burn.prepare(&s.positions, Some(&s.directions), s.samples, &s.in_sky());
    let o = burn.forward(&input, &[FieldHead::Rgb, FieldHead::Semantics]);
    let read1 = |t: burn::tensor::Tensor<1>| t.into_data().try_to_vec::<f32>().unwrap();
    let read2 = |t: burn::tensor::Tensor<2>| t.into_data().try_to_vec::<f32>().unwrap();
    for (name, a, b) in [
        ("density", sigma, read1(o.density)),
        ("rgb", rgb, read2(o.rgb.unwrap())),
        ("logits", logits, read2(o.logits.unwrap())),
    ] {
        assert_eq!(a.len(), b.len(), "{name}");
        for (x, y) in a.iter().zip(&b) {
            assert!(
                (x - y).abs() <= 1e-4 * y.abs().max(1.0),
                "{name}: {x} vs {y}"
            );
        }
    }
}

/// `sky_colour: direction`: both engines give every sky sample of a direction one colour
/// (whatever its position), the same colour, and the same gradients (the colour loss no longer
/// reaches the trunk through sky samples), which differ from `field`'s.
#[test]
fn a_direction_only_sky_colour_is_the_same_in_both_engines_and_ignores_position() {
    let batch = varied_batch();
    let s = &batch.samples;
    let in_sky = s.in_sky();
    assert!(in_sky.contains(&true) && in_sky.contains(&false));
    let (burn, fused) = toy_fields_where(1, SkyColourInput::Direction);
    let out = fused.evaluate(&s.positions, &s.directions, s.samples, &in_sky, Heads::ALL);
    let input = burn.prepare(&s.positions, Some(&s.directions), s.samples, &in_sky);
    let o = burn.forward(&input, &[FieldHead::Rgb]);
    let want = o.rgb.unwrap().into_data().try_to_vec::<f32>().unwrap();
    let worst = out.rgb.iter().zip(&want).map(|(a, b)| (a - b).abs());
    assert!(worst.fold(0f32, f32::max) < 1e-5);
    // Every toy ray looks along +z: one sky colour, and varied colours elsewhere.
    let colour = |i: usize| &out.rgb[i * 3..i * 3 + 3];
    let first = in_sky.iter().position(|&x| x).unwrap();
    for (i, _) in in_sky.iter().enumerate().filter(|(_, &x)| x) {
        assert_eq!(colour(i), colour(first), "sky sample {i}");
    }
    let (_, field_fused) = toy_fields_where(1, SkyColourInput::Field);
    let by_field =
        field_fused.evaluate(&s.positions, &s.directions, s.samples, &in_sky, Heads::ALL);
    let moved = (0..in_sky.len())
        .filter(|&i| in_sky[i] && by_field.rgb[i * 3..i * 3 + 3] != *colour(first))
        .count();
    assert!(
        moved > 0,
        "under `field` the sky colour depends on position"
    );
    for (i, _) in in_sky.iter().enumerate().filter(|(_, &x)| !x) {
        assert_eq!(
            colour(i),
            &by_field.rgb[i * 3..i * 3 + 3],
            "non-sky sample {i}"
        );
    }

    let config = TrainConfig {
        losses: Losses {
            sigma_threshold: 0.3,
            ..Losses::default()
        },
        ..Default::default()
    };
    for head_layers in [0, 1, 2] {
        let (burn, fused) = toy_fields_where(head_layers, SkyColourInput::Direction);
        let (_, want) = reference_gradients(&burn, &batch, &config);
        let mut trainer = FusedTrainer::new(config.clone(), fused).unwrap();
        let got = trainer.gradients(&batch).unwrap();
        assert_close(
            &format!("direction sky, head_layers {head_layers}"),
            &got.grads,
            &want,
        );
        let (burn, _) = toy_fields_where(head_layers, SkyColourInput::Field);
        let (_, by_field) = reference_gradients(&burn, &batch, &config);
        let trunk = |g: &[NamedWeight]| {
            g.iter()
                .find(|w| w.name == "trunk.layers.0.weight")
                .unwrap()
                .values
                .clone()
        };
        assert_ne!(trunk(&want), trunk(&by_field), "head_layers {head_layers}");
    }
}

#[test]
fn training_lowers_every_loss_and_is_deterministic() {
    let batch = varied_batch();
    let config = TrainConfig {
        optimiser: Optimiser {
            lr: 1e-2,
            ..Optimiser::default()
        },
        ..Default::default()
    };
    let run = || {
        let (_, fused) = toy_fields();
        let mut t = FusedTrainer::new(config.clone(), fused).unwrap();
        let first = t.step(&batch).unwrap();
        let mut last = first.clone();
        for _ in 0..150 {
            last = t.step(&batch).unwrap();
        }
        (first, last, t.into_field().weights)
    };
    let (first, last, w1) = run();
    for (term, v) in &first.terms {
        let after = last.get(*term).unwrap();
        assert!(after < 0.7 * v, "{term}: {v} -> {after}");
    }
    let (_, _, w2) = run();
    assert_eq!(w1, w2, "same seed and batch, same bytes");
}

#[test]
fn non_finite_targets_are_named_not_trained_on() {
    let (_, fused) = toy_fields();
    let mut batch = varied_batch();
    batch.samples.deltas[5] = 1e38;
    batch.samples.positions[0] = 1e30;
    let mut t = FusedTrainer::new(TrainConfig::default(), fused).unwrap();
    let before = t.field().weights.clone();
    let r = t.step(&batch);
    if let Err(e) = &r {
        let msg = e.to_string();
        assert!(msg.contains("iteration 0"), "{msg}");
        assert_eq!(t.field().weights, before, "weights unchanged on error");
    } else {
        // Extreme but finite inputs may train; then every weight stays finite.
        assert!(t
            .field()
            .weights
            .iter()
            .all(|w| w.values.iter().all(|v| v.is_finite())));
    }
}

/// `losses.exposure`: with every gain at 1 the losses and the field's gradients are those
/// without it, and the gains' own gradients, and the field's under other gains, are the
/// derivatives of the loss (central differences).
#[test]
fn exposure_gradients_match_finite_differences() {
    let config = TrainConfig {
        losses: Losses {
            sigma_threshold: 0.3,
            exposure: true,
            ..Losses::default()
        },
        ..Default::default()
    };
    let plain = varied_batch();
    let mut batch = plain.clone();
    batch.targets.image = (0..batch.samples.rays).map(|r| (r % 3) as u32).collect();
    let (_, fused) = toy_fields();
    let (spec, weights) = (fused.spec.clone(), fused.weights.clone());
    let trainer = |weights: &[NamedWeight], log_gains: &[[f32; 3]]| {
        let field = FusedField::from_weights(spec.clone(), weights.to_vec()).unwrap();
        let mut t = FusedTrainer::new(config.clone(), field).unwrap();
        t.set_exposure(log_gains.to_vec());
        t
    };
    let total = |g: &crate::model::train::Gradients| -> f64 {
        g.terms
            .iter()
            .map(|&(t, v)| config.losses.get(t) as f64 * v as f64)
            .sum()
    };

    let without = trainer(&weights, &[]).gradients(&plain).unwrap();
    let unit = trainer(&weights, &[[0.0; 3]; 3]).gradients(&batch).unwrap();
    assert_eq!(unit.terms, without.terms);
    assert_eq!(unit.grads[..without.grads.len()], without.grads[..]);
    assert_eq!(unit.grads.last().unwrap().name, EXPOSURE);

    let gains = [[0.2, -0.1, 0.05], [-0.3, 0.1, 0.0], [0.1, 0.25, -0.2]];
    let got = trainer(&weights, &gains).gradients(&batch).unwrap();
    assert!(
        total(&got) > total(&unit) * 0.5,
        "the gains change the colour loss"
    );
    let h = 1e-2f32;
    let exposure = &got.grads.last().unwrap().values;
    for k in 0..9 {
        let (mut up, mut down) = (gains, gains);
        up[k / 3][k % 3] += h;
        down[k / 3][k % 3] -= h;
        let fd = (total(&trainer(&weights, &up).gradients(&batch).unwrap())
            - total(&trainer(&weights, &down).gradients(&batch).unwrap()))
            / (2.0 * h as f64);
        let an = exposure[k] as f64;
        assert!(
            (fd - an).abs() <= 1e-4 + 2e-2 * an.abs(),
            "log gain {k}: analytic {an}, finite difference {fd}"
        );
    }
    // The colour head's output bias: its gradient passes through the gains.
    let b = params::index(&weights, "colour.layers.1.bias").unwrap();
    let analytic = &got.grads[b].values;
    for ch in 0..3 {
        let shifted = |d: f32| {
            let mut w = weights.clone();
            w[b].values[ch] += d;
            total(&trainer(&w, &gains).gradients(&batch).unwrap())
        };
        let fd = (shifted(h) - shifted(-h)) / (2.0 * h as f64);
        let an = analytic[ch] as f64;
        assert!(
            an.abs() > 1e-4 && (fd - an).abs() <= 1e-4 + 2e-2 * an.abs(),
            "colour bias {ch}: analytic {an}, finite difference {fd}"
        );
    }
}

/// A gain learns an image's exposure: two copies of the same rays, the second's colours
/// darker by a known factor, and the ratio of the two images' gains goes to that factor.
#[test]
fn exposure_learns_a_darker_image() {
    let config = TrainConfig {
        losses: Losses {
            exposure: true,
            ..Losses::default()
        },
        optimiser: Optimiser {
            lr: 1e-2,
            lr_final_factor: 1.0,
            ..Optimiser::default()
        },
        ..Default::default()
    };
    let one = varied_batch();
    let rays = one.samples.rays;
    let mut batch = one.select(&(0..2 * rays).map(|i| i % rays).collect::<Vec<_>>());
    let factor = 0.7f32;
    for v in &mut batch.targets.rgb[3 * rays..] {
        *v *= factor;
    }
    batch.targets.image = (0..2 * rays).map(|i| (i / rays) as u32).collect();
    let (_, fused) = toy_fields();
    let mut trainer = FusedTrainer::new(config, fused).unwrap();
    for _ in 0..400 {
        trainer.step(&batch).unwrap();
    }
    let g = trainer.exposure();
    for ch in 0..3 {
        let ratio = (g[1][ch] - g[0][ch]).exp();
        assert!(
            (ratio - factor).abs() < 0.05,
            "channel {ch}: gain ratio {ratio}, the targets' {factor}"
        );
    }
}

#[test]
fn the_avx2_path_gives_the_bytes_of_the_baseline_path() {
    let batch = varied_batch();
    let run = |baseline: bool| {
        super::simd::baseline_only(baseline);
        let (_, fused) = toy_fields();
        let mut t = FusedTrainer::new(TrainConfig::default(), fused).unwrap();
        let losses: Vec<_> = (0..20).map(|_| t.step(&batch).unwrap()).collect();
        let field = t.into_field();
        let s = &batch.samples;
        let heads = Heads {
            rgb: true,
            semantics: true,
        };
        let maps = field.evaluate(&s.positions, &s.directions, s.samples, &[], heads);
        super::simd::baseline_only(false);
        (losses, field.weights, maps.sigma, maps.rgb, maps.logits)
    };
    if !super::simd::avx2() {
        eprintln!("no AVX2 on this CPU: both runs take the baseline path");
    }
    let wide = run(false);
    let baseline = run(true);
    assert_eq!(wide.0, baseline.0, "losses");
    assert_eq!(wide.1, baseline.1, "weights after 20 steps");
    assert_eq!(wide.2, baseline.2, "density");
    assert_eq!(wide.3, baseline.3, "colour");
    assert_eq!(wide.4, baseline.4, "logits");
}
