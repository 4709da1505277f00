//! Inference with the fused engine: field outputs at many samples, parallel over rays.

use std::cell::RefCell;

use rayon::prelude::*;

use super::field::FusedField;
use super::simd::dispatch;
use super::work::Work;
use crate::model::config::FieldSpec;
use crate::model::field::{Field, FieldSamples, Heads};

thread_local! {
    /// The inference buffers of this thread, reused across calls.
    static WORK: RefCell<Work> = RefCell::new(Work::default());
}

impl FusedField {
    /// Field outputs for `rays` rays of `samples` points each (inference, parallel over rays):
    /// density `[R*S]`, rgb `[R*S*3]` (empty unless `heads.rgb`), logits `[R*S*C]` (empty unless
    /// `heads.semantics`).
    pub fn evaluate(
        &self,
        positions: &[f32],
        directions: &[f32],
        samples: usize,
        in_sky: &[bool],
        heads: Heads,
    ) -> FieldSamples {
        let rays = directions.len() / 3;
        let n = rays * samples;
        assert_eq!(
            positions.len(),
            n * 3,
            "positions must be [rays, samples, 3]"
        );
        assert!(
            in_sky.is_empty() || in_sky.len() == n,
            "in_sky must be empty or [rays, samples]"
        );
        let c = self.spec.num_classes;
        let chunk = 256;
        let params = self.params();
        let last = self.semantic.len() - 1;
        let mut sigma = vec![0f32; n];
        let mut rgb = vec![0f32; if heads.rgb { n * 3 } else { 0 }];
        let mut logits = vec![0f32; if heads.semantics { n * c } else { 0 }];
        // Each task writes its rays' outputs in place, and each worker thread keeps one `Work`
        // across tasks and calls: no buffer is allocated, zeroed or copied per chunk (fresh
        // buffers per chunk cost ~20 % of a full-size render in memset alone).
        let mut rgb_parts = rgb.chunks_mut(chunk * samples * 3);
        let mut logit_parts = logits.chunks_mut(chunk * samples * c);
        let parts: Vec<_> = sigma
            .chunks_mut(chunk * samples)
            .enumerate()
            .map(|(ci, s)| (ci, s, rgb_parts.next(), logit_parts.next()))
            .collect();
        parts.into_par_iter().for_each(|(ci, sig, col, log)| {
            WORK.with_borrow_mut(|w| {
                let (r0, r1) = (ci * chunk, ((ci + 1) * chunk).min(rays));
                let m = (r1 - r0) * samples;
                dispatch(
                    #[inline(always)]
                    || {
                        w.forward_field(
                            self,
                            &params,
                            &positions[r0 * samples * 3..r1 * samples * 3],
                            &directions[r0 * 3..r1 * 3],
                            samples,
                            in_sky.get(r0 * samples..r1 * samples).unwrap_or(&[]),
                            heads,
                            false,
                        )
                    },
                );
                sig.copy_from_slice(&w.sigma[..m]);
                if let Some(col) = col {
                    col.copy_from_slice(&w.rgb[..m * 3]);
                }
                if let Some(log) = log {
                    log.copy_from_slice(&w.sem[last][..m * c]);
                }
            })
        });
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
        in_sky: &[bool],
        heads: Heads,
    ) -> FieldSamples {
        FusedField::evaluate(self, positions, directions, samples, in_sky, heads)
    }
}
