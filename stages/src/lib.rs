//! The stage kinds of panoptic-pipe and the contract the runner holds them to.
//!
//! A stage kind is a pure function from named input tables (the outputs of upstream stage
//! instances) and validated parameters to named output tables ([`stage`]). It never touches the
//! cache or another stage's files. The kinds live in [`kinds`], one file each, with the
//! registry the runner looks them up in; everything else is the library they are glue over.

pub mod aggregate;
pub mod compose;
pub mod evaluate;
pub mod field;
pub mod fused;
pub mod geometry;
pub mod kinds;
pub mod labels;
pub mod metrics;
pub mod pngio;
pub mod rays;
pub mod render;
pub mod report;
pub mod sampling;
pub mod scene;
pub mod schema;
pub mod stage;
pub mod stereo;
pub mod tables;
pub mod testing;
pub mod train;
pub mod train_stage;

pub use kinds::registry::{find, registry};
pub use stage::{
    InputSlot, Inputs, MethodInfo, MetricInfo, NoProgress, Progress, Result, ScoreSpec, Stage,
    StageError, Tables, TypedStage,
};
