//! Training on after an edit of the primitives: from the previous run's weights (fresh
//! optimiser state), a short run whose batches draw a share of their rays from the pixels the
//! edit can change (rays meeting a changed primitive's old or new extent) and the rest from
//! every ray, so what the edit did not touch stays as it was.

use arrow::compute::concat_batches;

use super::fit::{
    candidate_count, candidate_sample, from_scratch, nothing_crossed, outputs, training_rays,
    LogColumns, Steps,
};
use super::params::TrainParams;
use crate::geometry::{
    changes::{pixels_meeting, ChangeView},
    Primitive,
};
use crate::kinds::edited::Edited;
use crate::model::{weights, BatchOrder};
use crate::rng::mix;
use crate::stage::{Changed, Inputs, Lineage, Previous, Progress, Result, StageError, Updated};

/// Training can go on from the previous weights when only the primitives (and so the plan)
/// changed: the images, labels and depth it fits are the same, and the plan was made as before.
pub(super) fn can_update(changed: &Changed, lineage: &Lineage) -> std::result::Result<(), String> {
    if changed.contains_key("rays") && !lineage.same_recipe("rays") {
        return Err("the plan was made with other parameters".into());
    }
    for (slot, tables) in changed {
        for t in tables {
            if !matches!(
                (slot.as_str(), t.as_str()),
                ("scene", "primitives") | ("rays", _)
            ) {
                return Err(format!("the input `{slot}`.{t} changed"));
            }
        }
    }
    Ok(())
}

pub(super) fn update(
    p: &TrainParams,
    inputs: &Inputs,
    previous: &Previous,
    progress: &dyn Progress,
) -> Result<Updated> {
    p.update.validate()?;
    let rays = training_rays(p, inputs)?;
    // Read once and dropped (not kept whole for the run): memory stays that of a cold run.
    let weights_table = previous.output("weights")?;
    let (info, before) = weights::read(
        &weights_table.rows(0..weights_table.num_rows(), None)?,
        previous.output("model")?.whole()?,
    )?;
    if info.classes != rays.prims.classes {
        // A class appeared or went: the semantic head has another shape.
        let tables = from_scratch(p, inputs, progress)?;
        return Ok(Updated {
            tables,
            redone: "trained from scratch (the scene's classes changed)".into(),
        });
    }
    let edit = Edited::read(previous, inputs)?;
    let only_removes = edit.changes.added.is_empty();
    let changed = edit.extents();
    drop(edit);
    // Before the candidates: its passing allocations stay below theirs.
    let edited = edited_rays(&rays, &p.cameras, &changed);
    let n_all = candidate_count(&rays, &p.cameras);
    if n_all == 0 {
        return Err(StageError::Input(nothing_crossed(inputs, &p.cameras)?));
    }
    let log_before = previous.output("train_log")?.whole()?;
    if edited.is_empty() {
        let tables = outputs(p, rays, info.spec, before, log_before.clone())?;
        return Ok(Updated {
            tables,
            redone: "no ray can see the edit: the previous weights".into(),
        });
    }
    let (iterations, budget) = if only_removes {
        (
            p.update.removal_iterations,
            " (`update.removal_iterations`: the edit only removes)",
        )
    } else {
        (p.update.iterations, "")
    };
    let mut config = p.model_config();
    config.iterations = iterations;
    config.optimiser.lr *= p.update.lr_factor;
    let mut trainer = p.backend.trainer_from(&config, info.spec.clone(), before)?;
    let batch = p.schedule.rays_per_batch.min(n_all);
    let from_edited = ((batch as f64 * p.update.edited_share).round() as usize).min(batch);
    let (training, n_edited) = (n_all as f64, edited.len());
    let seed = p.seed ^ 0x5EED_ED17;
    let mut edited_order =
        (from_edited > 0).then(|| BatchOrder::over(seed, edited, from_edited.min(n_edited)));
    // The rest of each batch from every ray: the run's draws of them, a uniform sample (the
    // first pass of a shuffle of all, in law) instead of the tens of millions of ids, so an
    // update holds less than a run from scratch.
    let mut all_order = (batch > from_edited).then(|| {
        let draws = iterations.saturating_mul(batch - from_edited);
        let all = candidate_sample(&rays, &p.cameras, n_all, mix(seed), draws);
        BatchOrder::over(!seed, all, batch - from_edited)
    });
    let first = tables_last_iteration(log_before)? + 1;
    let steps = Steps {
        iterations,
        batch,
        training_rays: training,
        first,
    };
    let mut log = LogColumns::default();
    steps.train(
        p,
        &rays,
        trainer.as_mut(),
        |it| {
            let mut ids = Vec::with_capacity(batch);
            if let Some(o) = edited_order.as_mut() {
                ids.extend_from_slice(o.batch(it));
            }
            if let Some(o) = all_order.as_mut() {
                ids.extend_from_slice(o.batch(it));
            }
            ids
        },
        &mut log,
        progress,
    )?;
    let added = log.table()?;
    let log = concat_batches(&added.schema(), [log_before, &added])
        .map_err(|e| StageError::Failed(format!("appending to the train log: {e}")))?;
    let weights = trainer.weights();
    drop((trainer, edited_order, all_order));
    let tables = outputs(p, rays, info.spec, weights, log)?;
    Ok(Updated {
        tables,
        redone: format!(
            "{iterations} steps from the previous weights{budget}, {:.0} % of each batch from the \
             {n_edited} rays the edit can change",
            100.0 * from_edited as f64 / batch as f64
        ),
    })
}

/// The last iteration of a train log (0 when empty).
fn tables_last_iteration(log: &arrow::record_batch::RecordBatch) -> Result<usize> {
    let it =
        crate::tables::get_prim::<arrow::datatypes::UInt32Type>(log, "train_log", "iteration")?;
    Ok(it.iter().copied().max().unwrap_or(0) as usize)
}

/// The training rays (ascending, among [`candidates`]) whose pixel ray meets a changed
/// primitive.
fn edited_rays(
    rays: &crate::sampling::ImageRays,
    cameras: &[u8],
    changed: &[Primitive],
) -> Vec<u32> {
    let mut view = ChangeView::new(changed);
    let mut out = Vec::new();
    let used = rays
        .images
        .iter()
        .filter(|im| cameras.is_empty() || cameras.contains(&im.camera));
    for im in used {
        if !view.seen_by(&im.cam, f64::INFINITY) {
            continue;
        }
        out.extend(
            pixels_meeting(&im.cam, changed, f64::INFINITY)
                .into_iter()
                .filter(|&px| im.hits[px as usize] > 0 && im.moving.binary_search(&px).is_err())
                .map(|px| im.first_ray + px),
        );
    }
    // Held through the whole update: not the up to twice its length that growing left.
    out.shrink_to_fit();
    out
}
