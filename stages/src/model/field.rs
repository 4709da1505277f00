//! A trained field as its users see it, whatever the engine: the outputs of the heads they ask
//! for at a batch of samples. Compositing them into pixels is [`crate::model::composite`]'s.

use super::config::FieldSpec;

/// Which heads a pass computes (density always).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Heads {
    pub rgb: bool,
    pub semantics: bool,
}

impl Heads {
    /// Every head.
    pub const ALL: Heads = Heads {
        rgb: true,
        semantics: true,
    };
}

/// Field outputs at `R * S` samples (`S` consecutive samples per ray).
///
/// # Shapes
/// `sigma`: `[R*S]`; `rgb`: `[R*S, 3]` (empty unless asked); `logits`: `[R*S, C]` (empty unless
/// asked).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FieldSamples {
    pub sigma: Vec<f32>,
    pub rgb: Vec<f32>,
    pub logits: Vec<f32>,
}

/// A field with its weights loaded, ready for inference.
pub trait Field: Sync {
    fn spec(&self) -> &FieldSpec;
    /// Outputs at `positions` (`[R*S, 3]`, scene frame) of rays with view `directions` (`[R,
    /// 3]`, any length) and `samples` points each; `in_sky` (`[R*S]`, or empty for none) says
    /// which samples lie in their ray's sky interval (their colour sees the direction only
    /// under [`crate::model::SkyColourInput::Direction`]).
    fn evaluate(
        &self,
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        in_sky: &[bool],
        heads: Heads,
    ) -> FieldSamples;
}
