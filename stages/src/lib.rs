//! The domain of panoptic-pipe: the stage kinds and the library they are glue over.
//!
//! A stage kind is a pure function from named input tables (the outputs of upstream stage
//! instances) and validated parameters to named output tables ([`stage`]). It never touches the
//! cache or another stage's files. The kinds live in [`kinds`], one module each, with the
//! registry the runner looks them up in; everything else is the library below them, which never
//! imports a kind:
//!
//! - [`model`]: the radiance field with dual semantic fields, its losses and rendering, behind
//!   one engine seam (fused CPU kernels, burn backends);
//! - [`sampling`] (samples inside the primitives a ray crosses) over [`intervals`] (the
//!   `ray_intervals` plan) over [`geometry`] (cameras, rays, primitives, BVH);
//! - [`scene`] (synthetic street, KITTI-360 read and write, stereo), [`metrics`], [`report`];
//! - [`tables`] and [`schema`] (typed rows and Arrow schemas from `data_schema/`), [`labels`]
//!   (KITTI-360 label ids and colours), [`pngio`], [`rng`].

pub mod error;
pub mod geometry;
pub mod input_file;
pub mod intervals;
pub mod kinds;
pub mod labels;
pub mod metrics;
pub mod model;
pub mod params_doc;
pub mod pngio;
pub mod report;
pub mod review;
pub mod rng;
pub mod sampling;
pub mod scene;
pub mod schema;
pub mod stage;
pub mod stream;
pub mod tables;

pub use stage::{
    Changed, InputSlot, Inputs, Lineage, MemoryInputs, MethodInfo, MetricInfo, NoProgress,
    Previous, Progress, Result, ScoreSpec, Stage, StageError, Table, TableSet, TableWriter, Tables,
    TypedStage, Updated,
};
