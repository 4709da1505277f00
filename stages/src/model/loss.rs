//! What training reports: the loss terms of Panoptic NeRF by name and the losses of one step
//! (their settings: [`crate::model::config::Losses`]). The terms themselves are defined once, on
//! tensors, in [`crate::model::burn::loss`] (differentiable, gradient-checked); the fused engine
//! computes the same formulas by hand and is held equal to them by tests.

/// The smallest `losses.label_eps`, the paper's `-log p` in effect (the gradient is at most
/// `1 / PROB_EPS`, and `-log(PROB_EPS)` ~ 13.8 bounds the loss of an impossible label); the
/// default is 0.3 (see [`crate::model::config::Losses::label_eps`]).
pub const PROB_EPS: f32 = 1e-6;

/// The loss terms, for names in errors and logs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum LossTerm {
    /// L_fixed2D: -log S_hat(label), the semantically guided geometry term.
    Fixed2d,
    /// L_learned2D: u(r) * -log S(label).
    Learned2d,
    /// L_3D: per-point CE between the fixed and learned distributions.
    Point3d,
    /// L_rgb: squared colour error.
    Rgb,
    /// L_depth: squared error against stereo depth.
    Depth,
    /// L_sky: on rays without a pseudo label, `g(r) (1 - S_hat(sky))`, the gate `g(r)` saying
    /// how close the ray's colour is to its sky interval's (not in the paper).
    SkyPrior,
}

impl LossTerm {
    pub const ALL: [LossTerm; 6] = [
        LossTerm::Fixed2d,
        LossTerm::Learned2d,
        LossTerm::Point3d,
        LossTerm::Rgb,
        LossTerm::Depth,
        LossTerm::SkyPrior,
    ];

    /// Column name in the train log (`fixed_2d`, `learned_2d`, `point_3d`, `rgb`, `depth`,
    /// `sky_prior`).
    pub fn name(self) -> &'static str {
        match self {
            LossTerm::Fixed2d => "fixed_2d",
            LossTerm::Learned2d => "learned_2d",
            LossTerm::Point3d => "point_3d",
            LossTerm::Rgb => "rgb",
            LossTerm::Depth => "depth",
            LossTerm::SkyPrior => "sky_prior",
        }
    }
}

impl std::fmt::Display for LossTerm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What one step reports.
#[derive(Debug, Clone, PartialEq)]
pub struct LossTerms {
    pub iteration: usize,
    pub lr: f64,
    /// Unweighted value of each enabled term.
    pub terms: Vec<(LossTerm, f32)>,
    /// Weighted sum, the optimised quantity.
    pub total: f32,
    /// Global gradient norm before clipping.
    pub grad_norm: f32,
}

impl LossTerms {
    /// Unweighted value of `term`, `None` when disabled.
    pub fn get(&self, term: LossTerm) -> Option<f32> {
        self.terms.iter().find(|(t, _)| *t == term).map(|(_, v)| *v)
    }
}
