//! What people look at: pictures of label maps and plots of training, for the `report` and
//! `render` kinds.

pub mod pictures;
pub mod plots;

pub use pictures::{depth_colors, depth_error_colors, error_colors, panoptic_colors, png_data_uri};
pub use plots::{review_svg, training_svg};
