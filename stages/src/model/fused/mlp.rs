//! Dense layers on flat row-major buffers: [`gemm`] for forward and backward, ReLU between
//! layers, exactly the layout of [`crate::field::mlp::Dense`] (`y = x W + b`, `W`
//! is `[inputs, outputs]`).

pub use super::gemm::{gemm, View};

/// Adds `bias` to every row of `y: [rows, bias.len()]`.
#[inline(always)]
pub fn add_bias(y: &mut [f32], bias: &[f32]) {
    for row in y.chunks_exact_mut(bias.len()) {
        row.iter_mut().zip(bias).for_each(|(v, b)| *v += b);
    }
}

#[inline(always)]
pub fn relu_in_place(y: &mut [f32]) {
    y.iter_mut().for_each(|v| *v = v.max(0.0));
}

/// `db += column sums of dy: [rows, db.len()]`.
#[inline(always)]
pub fn add_column_sums(db: &mut [f32], dy: &[f32]) {
    for row in dy.chunks_exact(db.len()) {
        db.iter_mut().zip(row).for_each(|(g, v)| *g += v);
    }
}

/// Where one layer's parameters live in the parameter list.
#[derive(Debug, Clone, Copy)]
pub struct Layer {
    pub weight: usize,
    pub bias: usize,
    pub inputs: usize,
    pub outputs: usize,
}

/// Forward through `layers` from `x` (rows `n`). `acts[l]` receives layer `l`'s output
/// (post-ReLU for hidden layers, linear for the last). Buffers only grow.
#[inline(always)]
pub fn forward(layers: &[Layer], params: &[&[f32]], n: usize, x: View, acts: &mut [Vec<f32>]) {
    let last = layers.len() - 1;
    for (l, layer) in layers.iter().enumerate() {
        let (before, rest) = acts.split_at_mut(l);
        let out = &mut rest[0];
        grow(out, n * layer.outputs);
        let input = if l == 0 {
            x
        } else {
            View::rows(&before[l - 1], layers[l - 1].outputs)
        };
        gemm(
            n,
            layer.inputs,
            layer.outputs,
            input,
            View::rows(params[layer.weight], layer.outputs),
            0.0,
            out,
            layer.outputs,
        );
        let out = &mut out[..n * layer.outputs];
        add_bias(out, params[layer.bias]);
        if l < last {
            relu_in_place(out);
        }
    }
}

/// Backward through `layers`. `dy` holds the gradient of the last layer's output (`[n,
/// outputs]`) and is clobbered; `scratch` is a second buffer. Accumulates into `grads`
/// (indexed like the parameters). When `dx` is given it receives the gradient of the first
/// `dx_cols` columns (default: all) of the input `x` (`[n, dx_cols]`, overwritten).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn backward(
    layers: &[Layer],
    params: &[&[f32]],
    grads: &mut [Vec<f32>],
    n: usize,
    x: View,
    dx_cols: Option<usize>,
    acts: &[Vec<f32>],
    dy: &mut Vec<f32>,
    scratch: &mut Vec<f32>,
    dx: Option<&mut Vec<f32>>,
) {
    for l in (0..layers.len()).rev() {
        let layer = layers[l];
        let input = if l == 0 {
            x
        } else {
            View::rows(&acts[l - 1], layers[l - 1].outputs)
        };
        let d = &dy[..n * layer.outputs];
        // dW += x^T dy
        gemm(
            layer.inputs,
            n,
            layer.outputs,
            View {
                data: input.data,
                rs: input.cs,
                cs: input.rs,
            },
            View::rows(d, layer.outputs),
            1.0,
            &mut grads[layer.weight],
            layer.outputs,
        );
        add_column_sums(&mut grads[layer.bias], d);
        if l > 0 {
            // d(previous activation) = dy W^T, through the previous layer's ReLU
            grow(scratch, n * layer.inputs);
            gemm(
                n,
                layer.outputs,
                layer.inputs,
                View::rows(d, layer.outputs),
                View::transposed(params[layer.weight], layer.outputs),
                0.0,
                scratch,
                layer.inputs,
            );
            let prev = &acts[l - 1][..n * layer.inputs];
            scratch[..n * layer.inputs]
                .iter_mut()
                .zip(prev)
                .for_each(|(g, &a)| {
                    if a <= 0.0 {
                        *g = 0.0
                    }
                });
            std::mem::swap(dy, scratch);
        }
    }
    if let Some(dx) = dx {
        let layer = layers[0];
        let cols = dx_cols.unwrap_or(layer.inputs);
        grow(dx, n * cols);
        // W^T restricted to the first `cols` input rows of W
        gemm(
            n,
            layer.outputs,
            cols,
            View::rows(&dy[..n * layer.outputs], layer.outputs),
            View::transposed(params[layer.weight], layer.outputs),
            0.0,
            dx,
            cols,
        );
    }
}

/// Makes `v` at least `len` long (never shrinks: buffers are reused across steps).
pub fn grow(v: &mut Vec<f32>, len: usize) {
    if v.len() < len {
        v.resize(len, 0.0);
    }
}
