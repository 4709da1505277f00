//! Training from scratch, and the pieces an update shares with it: the training rays, the
//! field's spec, the steps with their batches and log, and the output tables.

use std::sync::Arc;

use arrow::array::{ArrayRef, Float32Array};
use arrow::datatypes::{Float32Type, Float64Type, UInt32Type};
use arrow::record_batch::RecordBatch;

use super::params::TrainParams;
use crate::geometry::{self, DVec3};
use crate::model::{
    fit, selection_sample, weights, BatchOrder, FieldSpec, LossTerm, LossTerms, ModelInfo,
    NamedWeight, RayBatch, TrainConfig, TrainError,
};
use crate::rng::{mix, SplitMix64};
use crate::sampling::{self, ImageRays, JitterLabels, JitteredRays, PrimInfo, TrainImage};
use crate::stage::{Inputs, Progress, Result, StageError, Tables};
use crate::{labels, tables};

/// Trains the field from its initial weights.
pub(super) fn from_scratch(
    p: &TrainParams,
    inputs: &Inputs,
    progress: &dyn Progress,
) -> Result<Tables> {
    let rays = training_rays(p, inputs)?;
    let candidates = candidates(&rays, &p.cameras);
    if candidates.is_empty() {
        return Err(StageError::Input(nothing_crossed(inputs, &p.cameras)?));
    }
    let config = p.model_config();
    let centres: Vec<DVec3> = rays.images.iter().map(|im| im.cam.centre()).collect();
    let spec = spec_for(&rays.prims, &centres, &config);
    let mut trainer = p.backend.trainer(&config, spec.clone())?;
    let batch = p.schedule.rays_per_batch.min(candidates.len());
    let training = candidates.len() as f64;
    let mut order = BatchOrder::over(p.seed, candidates, batch);
    // Epoch-wise shuffles: every ray is visited once per epoch. (Drawing each batch from a
    // SplitMix stream seeded with `seed ^ it * GOLDEN` made consecutive batches share all
    // but one ray: training saw only ~iterations + batch distinct rays.)
    let steps = Steps {
        iterations: p.schedule.iterations,
        batch,
        training_rays: training,
        first: 0,
    };
    let mut log = LogColumns::default();
    steps.train(
        p,
        &rays,
        trainer.as_mut(),
        |it| order.batch(it).to_vec(),
        &mut log,
        progress,
    )?;
    let weights = trainer.weights();
    // The run's rays, order and optimiser state are done with: the tables are written without them.
    drop((trainer, order));
    outputs(p, rays, spec, weights, log.table()?)
}

/// The field spec of a scene: its classes, and as its box the bounds of its primitives
/// (padded by 1 m) clipped to `config.field.margin` around the centres of `cameras`.
pub fn spec_for(prims: &PrimInfo, cameras: &[DVec3], config: &TrainConfig) -> FieldSpec {
    let pad = 1.0;
    let mut lo = prims.bounds_min.map(|v| v - pad);
    let mut hi = prims.bounds_max.map(|v| v + pad);
    if config.field.margin > 0.0 && !cameras.is_empty() {
        let m = f64::from(config.field.margin);
        for a in 0..3 {
            let c_lo = cameras.iter().map(|c| c[a]).fold(f64::INFINITY, f64::min) - m;
            let c_hi = cameras
                .iter()
                .map(|c| c[a])
                .fold(f64::NEG_INFINITY, f64::max)
                + m;
            let (l, h) = (lo[a].max(c_lo as f32), hi[a].min(c_hi as f32));
            // Primitives wholly beyond the margin on this axis: keep their own bounds.
            if l < h {
                (lo[a], hi[a]) = (l, h);
            }
        }
    }
    FieldSpec {
        config: config.field.clone(),
        num_classes: prims.classes.len(),
        aabb_min: lo,
        aabb_max: hi,
        seed: config.seed,
    }
}

/// Rays of the selected cameras (empty: every camera) that cross a primitive and no moving
/// object's box: the ones training draws from.
pub(super) fn candidates(rays: &ImageRays, cameras: &[u8]) -> Vec<u32> {
    let n = candidate_count(rays, cameras);
    candidate_sample(rays, cameras, n, 0, n)
}

/// How many [`candidates`] there are.
pub(super) fn candidate_count(rays: &ImageRays, cameras: &[u8]) -> usize {
    used_images(rays, cameras)
        .map(|im| trained_pixels(im).count())
        .sum()
}

/// `k` of the `n` [`candidates`] ([`candidate_count`]), ascending, chosen uniformly by `seed`
/// (all when `k >= n`). Sized before it is filled: tens of millions of ids, which a growing Vec
/// would hold up to twice over.
pub(super) fn candidate_sample(
    rays: &ImageRays,
    cameras: &[u8],
    n: usize,
    seed: u64,
    k: usize,
) -> Vec<u32> {
    let ids =
        used_images(rays, cameras).flat_map(|im| trained_pixels(im).map(move |p| im.first_ray + p));
    selection_sample(seed, n, k, ids)
}

fn used_images<'a>(rays: &'a ImageRays, cameras: &'a [u8]) -> impl Iterator<Item = &'a TrainImage> {
    rays.images
        .iter()
        .filter(move |im| cameras.is_empty() || cameras.contains(&im.camera))
}

/// The pixels of `im` training draws: those crossing a primitive, less the moving ones (both
/// walked in ascending order).
fn trained_pixels(im: &TrainImage) -> impl Iterator<Item = u32> + '_ {
    let mut moving = im.moving.iter().copied().peekable();
    (0..im.hits.len() as u32).filter(move |&p| {
        while moving.next_if(|&m| m < p).is_some() {}
        im.hits[p as usize] > 0 && moving.peek() != Some(&p)
    })
}

/// The scene's training rays, with stereo depth kept where `losses.depth_classes` says.
pub(super) fn training_rays(p: &TrainParams, inputs: &Inputs) -> Result<ImageRays> {
    let mut rays = sampling::train_rays(inputs)?;
    let moving = geometry::dynamic_boxes_from_table(inputs.table("scene", "dynamic_boxes")?)?;
    rays.mark_moving(&moving);
    let depth_classes = p.depth_class_ids()?;
    if !depth_classes.is_empty() && !depth_classes.iter().any(|c| rays.prims.classes.contains(c)) {
        // L_depth would silently be off.
        return Err(StageError::Params(format!(
            "`losses.depth_classes`: no primitive of the scene has one of [{}] (its classes: {})",
            p.losses.depth_classes.join(", "),
            rays.prims
                .classes
                .iter()
                .filter_map(|&c| labels::by_id(c).map(|l| l.name))
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    rays.restrict_depth_to(&depth_classes);
    Ok(rays)
}

/// The stage's tables: the weights, the model description and the log.
pub(super) fn outputs(
    p: &TrainParams,
    rays: ImageRays,
    spec: FieldSpec,
    weights: Vec<NamedWeight>,
    log: RecordBatch,
) -> Result<Tables> {
    let classes = rays.prims.classes.clone();
    // Hundreds of MB at full size, not needed to write the tables.
    drop(rays);
    let info = ModelInfo {
        spec,
        sampling: p.sampling_params(),
        classes,
    };
    Ok(Tables::from([
        ("weights".to_string(), weights::weights_table(&weights)?),
        ("model".to_string(), weights::model_table(&info, p.backend)?),
        ("train_log".to_string(), log),
    ]))
}

/// A run of training steps: how many, the batch, the rays drawn from, and the number of the
/// first step (an update continues the previous run's count: its jitter and log go on).
pub(super) struct Steps {
    pub iterations: usize,
    pub batch: usize,
    pub training_rays: f64,
    pub first: usize,
}

impl Steps {
    /// Trains `trainer` on the rays `ids_at(step)` names at each step, logging every step.
    pub(super) fn train(
        &self,
        p: &TrainParams,
        rays: &ImageRays,
        trainer: &mut dyn crate::model::Trainer,
        mut ids_at: impl FnMut(usize) -> Vec<u32> + Send,
        log: &mut LogColumns,
        progress: &dyn Progress,
    ) -> Result<()> {
        let plan = p.sampling_params();
        let (iters, batch, first) = (self.iterations, self.batch, self.first);
        let start = std::time::Instant::now();
        let next_batch = |step: usize| {
            let ids = ids_at(step);
            let it = first + step;
            let jitter = SplitMix64::new(p.seed ^ (it as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
                .next_u64();
            let (width, labels) = p
                .sampling
                .jitter_at(it as f64 * batch as f64 / self.training_rays);
            let batch = if width > 0.0 {
                let jittered = JitteredRays {
                    rays,
                    seed: mix(jitter),
                    width: width as f64,
                    bilinear_labels: labels == JitterLabels::Bilinear,
                };
                sampling::sample_batch(&jittered, &ids, &plan, Some(jitter))
            } else {
                sampling::sample_batch(rays, &ids, &plan, Some(jitter))
            };
            batch
                .map(|b| {
                    let mut batch = RayBatch::from_samples(&b);
                    if p.losses.exposure {
                        batch.targets.image = b
                            .ray_ids
                            .iter()
                            .map(|&r| rays.image_index(r) as u32)
                            .collect();
                    }
                    batch
                })
                .map_err(|e| TrainError::Batch(e.message().to_string()))
        };
        let mut step = 0usize;
        fit(trainer, iters, next_batch, |losses| {
            log.push((first + step) as u32, losses);
            if step % 10 == 0 || step + 1 == iters {
                let secs = start.elapsed().as_secs_f64();
                let rays_s = (step + 1) as f64 * batch as f64 / secs.max(1e-9);
                progress.update(
                    step as u64 + 1,
                    iters as u64,
                    &format!("loss {:.4} ({:.0} rays/s)", losses.total, rays_s),
                );
            }
            step += 1;
        })?;
        Ok(())
    }
}

/// Columns of the train log.
#[derive(Default)]
pub(super) struct LogColumns {
    iteration: Vec<u32>,
    lr: Vec<f64>,
    total: Vec<f32>,
    grad_norm: Vec<f32>,
    terms: [Vec<Option<f32>>; LossTerm::ALL.len()],
}

impl LogColumns {
    pub(super) fn push(&mut self, it: u32, l: &LossTerms) {
        self.iteration.push(it);
        self.lr.push(l.lr);
        self.total.push(l.total);
        self.grad_norm.push(l.grad_norm);
        for (k, term) in LossTerm::ALL.into_iter().enumerate() {
            self.terms[k].push(l.get(term));
        }
    }

    pub(super) fn table(self) -> Result<RecordBatch> {
        let mut cols: Vec<ArrayRef> = vec![
            tables::prim::<UInt32Type>(self.iteration),
            tables::prim::<Float64Type>(self.lr),
            tables::prim::<Float32Type>(self.total),
            tables::prim::<Float32Type>(self.grad_norm),
        ];
        for t in self.terms {
            cols.push(Arc::new(Float32Array::from(t)));
        }
        tables::build("train_log", cols)
    }
}

/// Why no ray can be trained on, as far as the scene shows: which images were looked at and
/// how far the primitives are from their cameras.
pub(super) fn nothing_crossed(inputs: &Inputs, cameras: &[u8]) -> Result<String> {
    let rows = crate::geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
    let prims = crate::geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
    let used: Vec<_> = rows
        .iter()
        .filter(|r| cameras.is_empty() || cameras.contains(&r.camera))
        .collect();
    let cameras: Vec<u8> = used
        .iter()
        .map(|r| r.camera)
        .collect::<std::collections::BTreeSet<u8>>()
        .into_iter()
        .collect();
    let frames: std::collections::BTreeSet<u32> = used.iter().map(|r| r.frame).collect();
    let nearest = used
        .iter()
        .flat_map(|r| {
            let at = r.cam.cam_to_world.translation;
            prims.iter().map(move |p| p.aabb().centre().distance(at))
        })
        .fold(f64::INFINITY, f64::min);
    let frames = match (frames.first(), frames.last()) {
        (Some(a), Some(b)) => format!("frames {a}..={b}"),
        _ => "no frame".to_string(),
    };
    Ok(format!(
        "no ray of the {} images of cameras {cameras:?} ({frames}) crosses any of the {} \
         primitives; the nearest primitive centre is {nearest:.1} m from a camera. Check that \
         the poses and the primitives (the scene stage's poses file and bboxes XML) are of \
         the same sequence and frames",
        used.len(),
        prims.len()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Camera, DAffine3, Lens};
    use crate::sampling::Targets;

    fn image(hits: Vec<u8>, moving: Vec<u32>) -> TrainImage {
        let n = hits.len() as u32;
        TrainImage {
            frame: 0,
            camera: 0,
            cam: Camera {
                width: n,
                height: 1,
                fx: 1.0,
                fy: 1.0,
                cx: 0.5,
                cy: 0.5,
                lens: Lens::Pinhole,
                cam_to_world: DAffine3::IDENTITY,
            },
            first_ray: 0,
            hits,
            targets: Targets {
                rgb: Vec::new(),
                labels: None,
            },
            depth: None,
            moving,
        }
    }

    /// Training draws the pixels that cross a primitive and are not moving, against a brute
    /// force over every pattern of 6 pixels.
    #[test]
    fn trained_pixels_are_the_hit_ones_less_the_moving_ones() {
        for hit_bits in 0u32..64 {
            for moving_bits in (0u32..64).step_by(7) {
                let hits: Vec<u8> = (0..6).map(|p| ((hit_bits >> p) & 1) as u8 * 2).collect();
                let moving: Vec<u32> = (0..6).filter(|p| (moving_bits >> p) & 1 == 1).collect();
                let want: Vec<u32> = (0..6)
                    .filter(|&p| hits[p as usize] > 0 && !moving.contains(&p))
                    .collect();
                let im = image(hits, moving);
                assert_eq!(trained_pixels(&im).collect::<Vec<_>>(), want);
            }
        }
    }

    /// The moving pixels of an image are those whose ray crosses a box of its own frame,
    /// against a brute-force test of every pixel's ray, trimmed to the box's class where the
    /// image has pseudo labels; a box of another frame marks none.
    #[test]
    fn moving_pixels_are_those_whose_ray_crosses_a_box_of_their_frame() {
        use crate::geometry::{DVec3, DynamicBox, Interval, Primitive, Shape};
        let cam = Camera {
            width: 40,
            height: 30,
            fx: 30.0,
            fy: 30.0,
            cx: 20.0,
            cy: 15.0,
            lens: Lens::Pinhole,
            cam_to_world: DAffine3::IDENTITY,
        };
        let n = (cam.width * cam.height) as usize;
        let mut im = image(vec![1; n], Vec::new());
        im.cam = cam.clone();
        im.frame = 7;
        let tf = DAffine3::from_scale_rotation_translation(
            DVec3::new(1.5, 1.0, 2.0),
            glam::DQuat::from_rotation_y(0.4),
            DVec3::new(0.6, -0.3, 6.0),
        );
        let car = Primitive::new(Shape::Cuboid, tf, labels::CAR, 3).unwrap();
        let boxes = |frame| {
            vec![DynamicBox {
                object: 26003,
                frame,
                primitive: car.clone(),
            }]
        };
        let mut rays = ImageRays::new(
            Vec::new(),
            vec![im],
            crate::intervals::IntersectParams::default(),
        )
        .unwrap();
        rays.mark_moving(&boxes(7));
        let mut buf: Vec<Interval> = Vec::new();
        let want: Vec<u32> = (0..n as u32)
            .filter(|&p| {
                buf.clear();
                let ray = cam.pixel_ray(p % cam.width, p / cam.width).unwrap();
                car.intersect(&ray, &mut buf);
                buf.iter().any(|i| i.t_out > 0.0)
            })
            .collect();
        assert!(
            want.len() > 50 && want.len() < n / 2,
            "{} pixels",
            want.len()
        );
        assert_eq!(rays.images[0].moving, want);
        let kept: Vec<u32> = candidates(&rays, &[]);
        assert_eq!(kept.len(), n - want.len());
        assert!(kept.iter().all(|p| want.binary_search(p).is_err()));
        // With pseudo labels: only where they call the pixel the box's class.
        let labels: Vec<u8> = (0..n)
            .map(|p| {
                if p % 3 == 0 {
                    labels::CAR
                } else {
                    labels::ROAD
                }
            })
            .collect();
        rays.images[0].targets.labels = Some(labels.clone());
        rays.mark_moving(&boxes(7));
        let cars: Vec<u32> = want
            .iter()
            .copied()
            .filter(|&p| labels[p as usize] == labels::CAR)
            .collect();
        assert!(!cars.is_empty());
        assert_eq!(rays.images[0].moving, cars);
        rays.mark_moving(&boxes(8));
        assert!(rays.images[0].moving.is_empty());
    }
}
