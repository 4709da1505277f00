//! Inference with the fused engine: field outputs at many samples, parallel over rays.

use rayon::prelude::*;

use super::field::FusedField;
use super::work::Work;
use crate::model::config::FieldSpec;
use crate::model::field::{Field, FieldSamples, Heads};

impl FusedField {
    /// Field outputs for `rays` rays of `samples` points each (inference, parallel over rays):
    /// density `[R*S]`, rgb `[R*S*3]` (empty unless `heads.rgb`), logits `[R*S*C]` (empty unless
    /// `heads.semantics`).
    pub fn evaluate(
        &self,
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        heads: Heads,
    ) -> FieldSamples {
        let rays = directions.len() / 3;
        let n = rays * samples;
        assert_eq!(
            positions.len(),
            n * 3,
            "positions must be [rays, samples, 3]"
        );
        let c = self.spec.num_classes;
        let chunk = 256;
        let params = self.params();
        let last = self.semantic.len() - 1;
        let parts: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..rays.div_ceil(chunk))
            .into_par_iter()
            .map(|ci| {
                let (r0, r1) = (ci * chunk, ((ci + 1) * chunk).min(rays));
                let m = (r1 - r0) * samples;
                let mut w = Work::default();
                w.forward_field(
                    self,
                    &params,
                    &positions[r0 * samples * 3..r1 * samples * 3],
                    &directions[r0 * 3..r1 * 3],
                    samples,
                    heads,
                );
                (
                    w.sigma[..m].to_vec(),
                    if heads.rgb {
                        w.rgb[..m * 3].to_vec()
                    } else {
                        Vec::new()
                    },
                    if heads.semantics {
                        w.sem[last][..m * c].to_vec()
                    } else {
                        Vec::new()
                    },
                )
            })
            .collect();
        let mut sigma = Vec::with_capacity(n);
        let mut rgb = Vec::new();
        let mut logits = Vec::new();
        for (s, r, l) in parts {
            sigma.extend(s);
            rgb.extend(r);
            logits.extend(l);
        }
        FieldSamples { sigma, rgb, logits }
    }
}

impl Field for FusedField {
    fn spec(&self) -> &FieldSpec {
        &self.spec
    }

    fn evaluate(
        &self,
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        heads: Heads,
    ) -> FieldSamples {
        FusedField::evaluate(self, positions, directions, samples, heads)
    }
}
