//! The `render` kind's parameters.

use serde::{Deserialize, Serialize};

use crate::model::maps::DepthKind;
use crate::model::EngineChoice;

#[derive(Debug, Clone, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct RenderParams {
    /// Rays evaluated per network call.
    pub chunk: usize,
    /// Samples inside primitives per ray; 0 = as in training.
    pub samples: usize,
    /// Inference engine: `fused`, a burn backend, or empty for where training ran.
    /// Empty: the GPU the field was trained on, else the fused CPU path for grid fields (else
    /// the default burn backend). Burn backends: flex, ndarray, wgpu, cuda.
    pub backend: EngineChoice,
    /// Poses that are not in the scene, rendered too (camera ids 10, 11, ...).
    /// Their rows have camera id [`NOVEL_CAMERA_BASE`] + their index (files
    /// `<seq>_<frame>_10.png`, ...). Their rays are
    /// intersected with the primitives here, with the `intersect` kind's default params.
    pub novel_views: Vec<NovelView>,
    /// Render only the images of these frames; empty: every image the `rays` stage planned.
    /// For a preview or a timing.
    pub frames: Vec<u32>,
    /// Which images get a rendered colour map: `novel_views` (default), `all` or `none`. Colour
    /// checks the fit and labels nothing; it costs ~15 % of rendering. Images without one have
    /// an empty `rgb`.
    pub colour: Colour,
    /// Spacing (1, 2, 4, 8, 16) of the pixel grid rendered first; 1 renders every pixel.
    /// Halving the spacing, only the pixels where the coarser grid disagrees (labels, or the
    /// primitives crossed) are rendered; the others take their labels and interpolate depth,
    /// confidence and colour. On full-size street images 4 renders 2.4x faster than every pixel,
    /// with 0.1 % of the labels differing.
    pub coarse_stride: u32,
    /// The depth map: `expected` (sum w t / sum w) or `median` (where the weight reaches 0.5).
    /// Both only where the opacity reaches 0.5.
    pub depth: DepthKind,
}

/// Which images [`RenderParams::colour`] renders in colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Colour {
    All,
    NovelViews,
    None,
}

/// Camera id of the first novel view in `label_maps`.
pub const NOVEL_CAMERA_BASE: u8 = 10;

/// An existing camera of the scene, moved in its own frame (x right, y down, z forward); its
/// intrinsics and image size are kept.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct NovelView {
    /// Frame and camera id (0 left, 1 right) of the camera it starts from.
    pub frame: u32,
    pub camera: u8,
    /// Translation in that camera's frame, metres.
    #[serde(default)]
    pub translate: [f64; 3],
    /// Rotation about the camera's y axis, degrees (positive turns right).
    #[serde(default)]
    pub yaw_deg: f64,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            chunk: 4096,
            samples: 0,
            backend: EngineChoice::default(),
            novel_views: Vec::new(),
            frames: Vec::new(),
            colour: Colour::NovelViews,
            coarse_stride: 4,
            depth: DepthKind::Expected,
        }
    }
}
