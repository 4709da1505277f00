//! Scenes: the synthetic street generator ([`synthetic`]: [`layout`], [`tracer`], [`noise`],
//! [`depth`], [`rng`]), the KITTI-360 reader ([`kitti360`]) and writer ([`kitti360_export`]),
//! previews, semi-global stereo matching ([`stereo`]), and the helpers they share ([`io`]).

pub mod depth;
pub mod edits;
pub mod io;
pub mod kitti360;
pub mod kitti360_export;
pub mod layout;
pub mod noise;
pub mod preview;
pub mod rng;
pub mod stereo;
pub mod sweep;
pub mod synthetic;
pub mod tracer;
