//! Training, whatever the engine: the [`Trainer`] seam (one step, gradients, weights out) and the
//! one training loop over it.

use super::batch::RayBatch;
use super::error::TrainError;
use super::loss::{LossTerm, LossTerms};
use super::params::NamedWeight;

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
    mut batch: impl FnMut(usize) -> Result<RayBatch, TrainError>,
    mut on_step: impl FnMut(&LossTerms),
) -> Result<(), TrainError> {
    for it in 0..iterations {
        let losses = trainer.step(&batch(it)?)?;
        on_step(&losses);
    }
    Ok(())
}
