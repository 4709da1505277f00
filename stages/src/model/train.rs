//! Training, whatever the engine: the [`Trainer`] seam (one step, gradients, weights out), the
//! one training loop over it, and how long it runs ([`Schedule`], the `train` stage's `schedule`
//! group).

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::batch::RayBatch;
use super::error::{ModelError, TrainError};
use super::loss::{LossTerm, LossTerms};
use super::params::NamedWeight;

/// How long training runs and how many rays each step draws.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Schedule {
    /// Optimisation steps (paper: 80000).
    pub iterations: usize,
    /// Rays drawn per step (paper: 2048); every training ray once per pass, in a seeded order.
    pub rays_per_batch: usize,
}

impl Default for Schedule {
    fn default() -> Self {
        Self {
            iterations: 1700,
            rays_per_batch: 1024,
        }
    }
}

/// The most rays one step may draw: 2^20 (a batch's samples and their activations are held
/// whole in memory; 2^20 rays of 32 samples are several GB).
pub const MAX_RAYS_PER_BATCH: usize = 1 << 20;

impl Schedule {
    /// Checks ranges; errors name the parameter, its value and the range allowed.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.iterations == 0 {
            return Err(ModelError::Param(
                "`schedule.iterations`: 0 trains nothing; it must be >= 1".into(),
            ));
        }
        if !(1..=MAX_RAYS_PER_BATCH).contains(&self.rays_per_batch) {
            return Err(ModelError::Param(format!(
                "`schedule.rays_per_batch`: {} must be in 1..={MAX_RAYS_PER_BATCH}",
                self.rays_per_batch
            )));
        }
        Ok(())
    }
}

/// Loss values and gradients of one batch, without an update (tests, the failure path).
#[derive(Debug, Clone, PartialEq)]
pub struct Gradients {
    /// Unweighted value of each enabled term.
    pub terms: Vec<(LossTerm, f32)>,
    /// The gradient of the weighted sum, per parameter (the layout of the weights).
    pub grads: Vec<NamedWeight>,
}

/// A field being trained, with its optimiser state.
pub trait Trainer {
    /// One step on `batch`: forward, the enabled losses, backward, global-norm clipping, Adam
    /// at the scheduled learning rate. On error the weights are unchanged.
    fn step(&mut self, batch: &RayBatch) -> Result<LossTerms, TrainError>;
    /// Losses and gradients of `batch` at the current weights, changing nothing.
    fn gradients(&mut self, batch: &RayBatch) -> Result<Gradients, TrainError>;
    /// Steps done so far.
    fn iteration(&self) -> usize;
    /// The current parameters (the layout of [`crate::model::params`]).
    fn weights(&self) -> Vec<NamedWeight>;
}

/// Trains for `iterations` steps on the batches `batch(iteration)` gives; `on_step` sees every
/// step's losses (logs, progress).
pub fn fit(
    trainer: &mut dyn Trainer,
    iterations: usize,
    mut batch: impl FnMut(usize) -> Result<RayBatch, TrainError> + Send,
    mut on_step: impl FnMut(&LossTerms),
) -> Result<(), TrainError> {
    // The next batch is built on a thread of its own while a step trains: its rays do not depend
    // on the weights, and its parallel parts fill the moments the step leaves a core idle.
    let mut next = (iterations > 0).then(|| batch(0));
    for it in 0..iterations {
        let current = next.take().expect("a batch for every step")?;
        let losses = std::thread::scope(|s| {
            let builder = (it + 1 < iterations).then(|| s.spawn(|| batch(it + 1)));
            let losses = trainer.step(&current);
            if let Some(b) = builder {
                next = Some(b.join().unwrap_or_else(|e| std::panic::resume_unwind(e)));
            }
            losses
        })?;
        on_step(&losses);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_or_oversized_schedules_are_refused_with_the_range() {
        Schedule::default().validate().unwrap();
        let none = Schedule {
            iterations: 0,
            ..Schedule::default()
        };
        let e = none.validate().unwrap_err().to_string();
        assert!(e.contains("`schedule.iterations`: 0"), "{e}");
        for rays in [0, MAX_RAYS_PER_BATCH + 1, 4_000_000_000] {
            let s = Schedule {
                rays_per_batch: rays,
                ..Schedule::default()
            };
            let e = s.validate().unwrap_err().to_string();
            assert!(
                e.contains(&format!("`schedule.rays_per_batch`: {rays}")) && e.contains("1..="),
                "{e}"
            );
        }
    }
}
