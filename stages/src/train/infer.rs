//! Inference: render every ray of a [`RaySamples`] set in chunks, on the field's device without
//! autodiff, to plain host vectors (the render stage turns them into label maps).

use burn::module::Module;
use burn::tensor::activation::softmax;
use burn::tensor::{Tensor, TensorData};

use super::batch::RaySamples;
use crate::field::{
    render_depth, render_rgb, render_semantics, render_weights, FieldHead, RadianceField,
};

/// Rendered per-ray quantities.
///
/// # Shapes
/// `rgb`: `[rays, 3]`; `depth`, `opacity`: `[rays]`; `semantics` (S, learned) and
/// `fixed_semantics` (S_hat): `[rays, classes]`, sky last.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RenderedRays {
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
    pub semantics: Vec<f32>,
    pub fixed_semantics: Vec<f32>,
}

/// Renders `samples` with `field` (autodiff is stripped), `chunk` rays at a time.
pub fn render_rays(
    field: &RadianceField,
    samples: &RaySamples,
    chunk: usize,
) -> Result<RenderedRays, String> {
    samples.validate()?;
    if samples.classes != field.spec.num_classes {
        return Err(format!(
            "samples have {} classes, the field {}",
            samples.classes, field.spec.num_classes
        ));
    }
    let field = field.valid();
    let device = field.trunk.layers[0].weight.device();
    let (n, c) = (samples.samples, samples.classes);
    let mut out = RenderedRays::default();
    let chunk = chunk.max(1);
    let read = |t: Tensor<2>| t.into_data().try_to_vec::<f32>().expect("f32");
    let mut start = 0;
    while start < samples.rays {
        let idx: Vec<usize> = (start..(start + chunk).min(samples.rays)).collect();
        let part = samples.select(&idx);
        let r = part.rays;
        let input = field.prepare(&part.positions, Some(&part.directions), n);
        let o = field.forward(&input, &[FieldHead::Rgb, FieldHead::Semantics]);
        let deltas = Tensor::<2>::from_data(TensorData::new(part.deltas.clone(), [r, n]), &device);
        let t = Tensor::<2>::from_data(TensorData::new(part.t_mid.clone(), [r, n]), &device);
        let fixed = Tensor::<3>::from_data(
            TensorData::new(part.fixed_semantics.clone(), [r, n, c]),
            &device,
        );
        let w = render_weights(o.density.reshape([r, n]), deltas);
        let probs = softmax(o.logits.expect("semantics").reshape([r, n, c]), 2);
        out.rgb
            .extend(read(render_rgb(&w, o.rgb.expect("rgb").reshape([r, n, 3]))));
        out.depth.extend(read(render_depth(&w, t).unsqueeze_dim(1)));
        out.semantics
            .extend(read(render_semantics(&w, probs, c - 1)));
        out.fixed_semantics
            .extend(read(render_semantics(&w, fixed, c - 1)));
        out.opacity.extend(read(w.opacity.unsqueeze_dim(1)));
        start += chunk;
    }
    Ok(out)
}
