//! The review score: per pixel, an estimate of the probability that the rendered label is
//! wrong, from the run's own signals (no ground truth), and the reason it is high.
//!
//! The score is a logistic combination of cues: low confidence of the learned field, our label
//! against the pseudo label and against the fixed (primitive) field, nearness to a boundary of
//! our label map, rendered depth outside every primitive the ray crosses, and a coverage gap
//! (a ray that crosses no primitive where the pseudo label, or a ray pointing below the
//! horizon, says it is not sky). The weights were fitted by logistic regression on the
//! synthetic street at two scales and rounded (docs/experiments/review.md).

pub mod distance;
pub mod regions;

use serde::{Deserialize, Serialize};

use crate::intervals::ImagePlan;
use crate::labels;

/// Why a pixel is flagged: the cue that added most to its score. Stored as `u8` codes (the
/// index here); 0 is an unflagged pixel.
pub const REASONS: &[&str] = &[
    "",
    "low_confidence",
    "pseudo_label_disagrees",
    "fixed_field_disagrees",
    "label_boundary",
    "depth_outside_primitives",
    "coverage_gap",
];

pub const LOW_CONFIDENCE: u8 = 1;
pub const PSEUDO_DISAGREES: u8 = 2;
pub const FIXED_DISAGREES: u8 = 3;
pub const BOUNDARY: u8 = 4;
pub const OUTSIDE: u8 = 5;
pub const GAP: u8 = 6;

/// No primitive (a pixel whose ray crosses none, or a region without one).
pub const NO_PRIMITIVE: u32 = u32::MAX;

/// The logistic weights of the cues (the log-odds each adds when present).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Weights {
    /// Log-odds of a pixel with no cue at all.
    pub bias: f32,
    /// Per unit of ln(1 - confidence) of the learned semantic rendering.
    pub confidence: f32,
    /// Our label differs from the pseudo label (cameras with pseudo labels).
    pub pseudo: f32,
    /// Our label differs from the fixed field's (the primitives' class along the ray).
    pub fixed: f32,
    /// Times exp(-d / band), d the distance in pixels to a boundary of our label map.
    pub boundary: f32,
    /// Within two bands of a boundary of our label map.
    pub near_boundary: f32,
    /// Rendered depth outside every primitive interval the ray crosses.
    pub outside: f32,
    /// A coverage gap: no primitive on the ray, and the pixel is not sky.
    pub gap: f32,
}

impl Default for Weights {
    fn default() -> Self {
        Self {
            bias: -5.0,
            confidence: 0.7,
            pseudo: 2.5,
            fixed: 0.3,
            boundary: 2.0,
            near_boundary: 1.0,
            outside: 0.3,
            gap: 3.5,
        }
    }
}

/// The confidence at which the confidence cue counts as a reason (1 - 0.95).
const CONFIDENCE_REASON_AT: f32 = 0.05;

/// What the score of one image is computed from (row-major, `width * height` each).
pub struct ImageSignals<'a> {
    pub width: usize,
    pub height: usize,
    /// Argmax of the learned and of the fixed semantic rendering.
    pub ours: &'a [u8],
    pub fixed: &'a [u8],
    /// Max probability of the learned semantic rendering.
    pub confidence: &'a [f32],
    /// Rendered depth as the camera's depth maps hold it (0: none).
    pub depth: &'a [f32],
    pub pseudo: Option<&'a [u8]>,
    pub plan: &'a ImagePlan,
    /// Per pixel: depth per metre along the ray ([`crate::geometry::Camera::depth_scale`]); 0
    /// for a pixel that is no ray (outside a fisheye's lens).
    pub depth_scale: &'a [f32],
    /// Per pixel: whether the ray may see the sky ([`crate::intervals::may_see_sky`]).
    pub may_see_sky: &'a [bool],
}

/// Tunables of [`review_image`] besides the weights.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shape {
    /// Boundary band in pixels.
    pub band: f32,
    /// Slack, metres, when a rendered depth is tested against a primitive's interval.
    pub slack: f32,
}

/// The review of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageReview {
    /// Estimated probability that the label is wrong (0 for a pixel that is no ray).
    pub score: Vec<f32>,
    /// The cue that added most ([`REASONS`] index; never 0).
    pub reason: Vec<u8>,
    /// The primitive the pixel's label comes from: the crossed primitive whose interval holds
    /// the rendered depth, else the first crossed; [`NO_PRIMITIVE`] when none is crossed.
    pub primitive: Vec<u32>,
    /// Coverage gaps: a ray that crosses no primitive on a pixel that is not sky.
    pub gap: Vec<bool>,
}

/// Per pixel, whether a 4-neighbour has another label; both must be rays (`is_ray`), so a
/// fisheye's lens rim is no boundary.
fn boundaries(labels_map: &[u8], is_ray: &[f32], w: usize, h: usize) -> Vec<bool> {
    let mut b = vec![false; labels_map.len()];
    let differ =
        |p: usize, q: usize| labels_map[p] != labels_map[q] && is_ray[p] > 0.0 && is_ray[q] > 0.0;
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if x + 1 < w && differ(p, p + 1) {
                b[p] = true;
                b[p + 1] = true;
            }
            if y + 1 < h && differ(p, p + w) {
                b[p] = true;
                b[p + w] = true;
            }
        }
    }
    b
}

/// Scores every pixel of one image.
pub fn review_image(s: &ImageSignals, w: &Weights, shape: Shape) -> ImageReview {
    let n = s.width * s.height;
    let edges = boundaries(s.ours, s.depth_scale, s.width, s.height);
    let dist = distance::distance_to(&edges, s.width, s.height);
    let mut out = ImageReview {
        score: vec![0.0; n],
        reason: vec![LOW_CONFIDENCE; n],
        primitive: vec![NO_PRIMITIVE; n],
        gap: vec![false; n],
    };
    let mut offset = 0usize;
    for p in 0..n {
        let hits = s.plan.hits[p] as usize;
        let intervals = offset..offset + hits;
        offset += hits;
        if s.depth_scale[p] <= 0.0 {
            continue;
        }
        let pseudo = s.pseudo.map(|m| m[p]);
        // A coverage gap: nothing annotated on the ray, and the pixel is not sky.
        let gap = hits == 0
            && (!s.may_see_sky[p]
                || pseudo.is_some_and(|l| l != labels::SKY && l != labels::UNLABELED));
        // Outside: a rendered surface that no crossed primitive holds.
        let t = s.depth[p] / s.depth_scale[p];
        let holding = intervals
            .clone()
            .find(|&i| t >= s.plan.t_in[i] - shape.slack && t <= s.plan.t_out[i] + shape.slack);
        let outside = hits > 0 && s.depth[p] > 0.0 && holding.is_none();
        out.primitive[p] = match (holding, hits) {
            (Some(i), _) => s.plan.prim[i],
            (None, 0) => NO_PRIMITIVE,
            (None, _) => s.plan.prim[intervals.start],
        };
        out.gap[p] = gap;
        // A non-finite confidence counts as none at all.
        let c = s.confidence[p];
        let u = if c.is_finite() {
            (1.0 - c).clamp(1e-4, 1.0)
        } else {
            1.0
        };
        let near = (-dist[p] / shape.band).exp();
        let cues = [
            (
                LOW_CONFIDENCE,
                w.confidence * (u.ln() - CONFIDENCE_REASON_AT.ln()),
            ),
            (
                PSEUDO_DISAGREES,
                if pseudo.is_some_and(|l| l != s.ours[p]) {
                    w.pseudo
                } else {
                    0.0
                },
            ),
            (
                FIXED_DISAGREES,
                if s.fixed[p] != s.ours[p] {
                    w.fixed
                } else {
                    0.0
                },
            ),
            (
                BOUNDARY,
                w.boundary * near
                    + if dist[p] <= 2.0 * shape.band {
                        w.near_boundary
                    } else {
                        0.0
                    },
            ),
            (OUTSIDE, if outside { w.outside } else { 0.0 }),
            (GAP, if gap { w.gap } else { 0.0 }),
        ];
        let z = w.bias
            + w.confidence * CONFIDENCE_REASON_AT.ln()
            + cues.iter().map(|(_, v)| v).sum::<f32>();
        out.score[p] = 1.0 / (1.0 + (-z).exp());
        // The cue that added most; low confidence when none added anything.
        out.reason[p] = cues
            .iter()
            .fold((LOW_CONFIDENCE, 0.0), |best, &(r, v)| {
                if v > best.1 {
                    (r, v)
                } else {
                    best
                }
            })
            .0;
    }
    out
}

#[cfg(test)]
mod tests;
