//! Every stage kind, one module each, named after the kind, and the [`registry`] the runner
//! looks them up in. A kind is glue between tables and the library below; it never imports
//! another kind (what two kinds share lives in the library).

pub mod aggregate;
mod edited;
pub mod evaluate;
pub mod intersect;
pub mod kitti360_scene;
pub mod motion_stereo;
pub mod registry;
pub mod render;
pub mod report;
pub mod review;
pub mod stereo_depth;
pub mod synthetic_scene;
pub mod testing;
pub mod train;

pub use registry::{find, registry};
