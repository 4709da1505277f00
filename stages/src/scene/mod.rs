//! The `synthetic_scene` stage kind: a synthetic urban street with ground truth.
pub mod depth;
pub mod noise;
pub mod rng;
