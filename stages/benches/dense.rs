//! Micro-benchmark: the fused engine's dense-layer products on 16384 rows (samples), for
//! the field's shapes: forward `x W`, input gradient `dy W^T`, weight gradient
//! `x^T dy`. Prints ms and GMAC/s per product on one thread.
//!
//! Run: `cargo bench -p stages --bench dense`.

use stages::model::fused::mlp::{gemm, View};
use std::time::Instant;

const REPS: usize = 200;

/// Times `REPS` calls of `product`, after one untimed, and prints them as `macs` multiply-adds
/// each.
fn time(label: &str, macs: usize, mut product: impl FnMut()) {
    product();
    let t = Instant::now();
    for _ in 0..REPS {
        product();
    }
    let dt = t.elapsed().as_secs_f64() / REPS as f64;
    println!(
        "{label}: {:.3} ms  {:.1} GMAC/s",
        dt * 1e3,
        macs as f64 / dt / 1e9
    );
}

fn main() {
    let n = 16384usize;
    let big: Vec<f32> = (0..n * 64).map(|i| ((i % 97) as f32) * 0.01).collect();
    let big2: Vec<f32> = (0..n * 64).map(|i| ((i % 89) as f32) * 0.01).collect();
    let w: Vec<f32> = (0..64 * 64).map(|i| ((i % 13) as f32) * 0.1).collect();
    let mut c = vec![0f32; n * 64];
    let mut small = vec![0f32; 64 * 64];
    println!("dense: {n} rows, {REPS} repetitions, one thread");
    // forward: [n, k] x [k, o]
    for (k, o) in [(16, 32), (32, 16), (15, 32), (32, 10), (32, 3)] {
        time(&format!("fwd  k={k:2} o={o:2}"), n * k * o, || {
            gemm(
                n,
                k,
                o,
                View::rows(&big, k),
                View::rows(&w, o),
                0.0,
                &mut c,
                o,
            )
        });
    }
    // input gradient: [n, o] x W^T [o, i]
    for (o, i) in [(16, 32), (10, 32), (32, 15), (3, 32), (32, 16)] {
        time(&format!("dx   o={o:2} i={i:2}"), n * i * o, || {
            gemm(
                n,
                o,
                i,
                View::rows(&big, o),
                View::transposed(&w, o),
                0.0,
                &mut c,
                i,
            )
        });
    }
    // weight gradient: x^T [i, n] x dy [n, o]
    for (i, o) in [(16, 32), (32, 16), (15, 32), (32, 10), (32, 3)] {
        time(&format!("dW   i={i:2} o={o:2}"), n * i * o, || {
            gemm(
                i,
                n,
                o,
                View::transposed(&big, i),
                View::rows(&big2, o),
                1.0,
                &mut small,
                o,
            )
        });
    }
}
