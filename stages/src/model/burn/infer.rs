//! Inference with the burn engine: field outputs at many samples, read back to the host.

use burn::tensor::Tensor;

use super::field::{FieldHead, RadianceField};
use crate::model::config::FieldSpec;
use crate::model::field::{Field, FieldSamples, Heads};

fn read<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default()
}

impl Field for RadianceField {
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
        let mut want = Vec::new();
        if heads.rgb {
            want.push(FieldHead::Rgb);
        }
        if heads.semantics {
            want.push(FieldHead::Semantics);
        }
        let input = self.prepare(positions, Some(directions), samples, in_sky);
        let o = self.forward(&input, &want);
        FieldSamples {
            sigma: read(o.density),
            rgb: o.rgb.map(read).unwrap_or_default(),
            logits: o.logits.map(read).unwrap_or_default(),
        }
    }
}
