//! `c = beta c + a b` for the field's matrices: one side narrow (a layer's 3 to 64 inputs or
//! outputs), the other a partition's samples. A general sgemm first packs both operands into
//! panels; with 16 to 32 columns the copy costs about as much as the products. Here a register
//! block of `R` rows of `c` by `8 NB` columns reads `a` in place and `b` row by row, which is
//! contiguous for every product the engine forms (a transposed weight matrix, small, is copied).
//!
//! Every element of `c` is `beta c` plus the products in increasing `p`, one multiply and one
//! add each (Rust never fuses them into an FMA), so the baseline and the AVX2 build, and every
//! block shape, give the same bits.

use super::simd::dispatch;

/// A strided read-only matrix view: element `(i, j)` is `data[i * rs + j * cs]`.
#[derive(Clone, Copy)]
pub struct View<'a> {
    pub data: &'a [f32],
    pub rs: usize,
    pub cs: usize,
}

impl<'a> View<'a> {
    /// A contiguous row-major `[_, cols]` matrix.
    pub fn rows(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            rs: cols,
            cs: 1,
        }
    }

    /// The transpose of a contiguous row-major `[_, cols]` matrix.
    pub fn transposed(data: &'a [f32], cols: usize) -> Self {
        Self {
            data,
            rs: 1,
            cs: cols,
        }
    }
}

/// Columns of `c` one register block covers at most (4 vectors of 8).
const BLOCK_COLS: usize = 32;

thread_local! {
    /// `b` copied with its rows padded to whole vectors, reused between calls.
    static PADDED: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// `c = beta * c + a b` with `a: [m, k]`, `b: [k, n]`, `c: [m, n]` row-major with row stride
/// `ldc`. With `beta == 0` the old `c` is not read (it may hold anything, NaN included).
#[allow(clippy::too_many_arguments)]
pub fn gemm(m: usize, k: usize, n: usize, a: View, b: View, beta: f32, c: &mut [f32], ldc: usize) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(
        k == 0 || a.data.len() > (m - 1) * a.rs + (k - 1) * a.cs,
        "gemm: a too short"
    );
    assert!(
        k == 0 || b.data.len() > (k - 1) * b.rs + (n - 1) * b.cs,
        "gemm: b too short"
    );
    assert!(
        n <= ldc && c.len() >= (m - 1) * ldc + n,
        "gemm: c too short"
    );
    let mut args = Args {
        m,
        k,
        n,
        a: a.data,
        a_rs: a.rs,
        a_cs: a.cs,
        b: b.data,
        b_rs: b.rs,
        c_rs: ldc,
        c_cs: 1,
        beta,
    };
    // A weight gradient `x^T dy` with a ragged `dy` (10 classes, 3 colours) is computed as
    // `dy^T x`, whose rows (a layer's inputs) are whole vectors: c^T = b^T a^T.
    if n % 8 != 0 && a.rs == 1 && b.cs == 1 && m % 8 == 0 {
        args = Args {
            m: n,
            n: m,
            a: b.data,
            a_rs: 1,
            a_cs: b.rs,
            b: a.data,
            b_rs: a.cs,
            c_rs: 1,
            c_cs: ldc,
            ..args
        };
    } else if n % 8 != 0 || b.cs != 1 {
        // Rows of b padded with zeros to whole vectors (a weight matrix: small).
        return PADDED.with_borrow_mut(|pad| {
            let width = n.div_ceil(8) * 8;
            pad.clear();
            pad.resize(k * width, 0.0);
            for (p, row) in pad.chunks_exact_mut(width).enumerate() {
                for (j, v) in row[..n].iter_mut().enumerate() {
                    *v = b.data[p * b.rs + j * b.cs];
                }
            }
            run(
                &Args {
                    b: pad,
                    b_rs: width,
                    ..args
                },
                c,
            )
        });
    }
    run(&args, c)
}

/// The AVX2 build where the CPU has it, else the baseline one.
fn run(args: &Args, c: &mut [f32]) {
    dispatch(
        #[inline(always)]
        || gemm_blocks(args, c),
    )
}

/// The operands of one product, checked by [`gemm`]: `b` is row-major with row stride `b_rs`
/// and readable `8 ceil(n / 8)` columns wide in every row; `c` has strides `c_rs`, `c_cs`.
struct Args<'a> {
    m: usize,
    k: usize,
    n: usize,
    a: &'a [f32],
    a_rs: usize,
    a_cs: usize,
    b: &'a [f32],
    b_rs: usize,
    c_rs: usize,
    c_cs: usize,
    beta: f32,
}

/// Column blocks of up to [`BLOCK_COLS`], each swept over the rows of `c` by register blocks:
/// fewer rows per block where the block is wider, so the accumulators fit in 16 registers.
#[inline(always)]
fn gemm_blocks(args: &Args, c: &mut [f32]) {
    let mut j0 = 0;
    while j0 < args.n {
        let cols = (args.n - j0).min(BLOCK_COLS);
        match cols.div_ceil(8) {
            1 => rows_of::<8, 1>(args, j0, cols, c),
            2 => rows_of::<4, 2>(args, j0, cols, c),
            3 => rows_of::<2, 3>(args, j0, cols, c),
            _ => rows_of::<2, 4>(args, j0, cols, c),
        }
        j0 += cols;
    }
}

/// Columns `j0..j0 + cols` of every row of `c`, `R` rows at a time, then the leftover rows
/// one at a time.
#[inline(always)]
fn rows_of<const R: usize, const NB: usize>(args: &Args, j0: usize, cols: usize, c: &mut [f32]) {
    let full = args.m / R * R;
    let mut i = 0;
    while i < full {
        block::<R, NB>(args, i, j0, cols, c);
        i += R;
    }
    while i < args.m {
        block::<1, NB>(args, i, j0, cols, c);
        i += 1;
    }
}

/// `c[i0..i0 + R, j0..j0 + cols] = beta c + a[i0.., :] b[:, j0..]` in registers (the
/// columns past `cols`, where `b` is padded, are computed and dropped).
#[inline(always)]
fn block<const R: usize, const NB: usize>(
    args: &Args,
    i0: usize,
    j0: usize,
    cols: usize,
    c: &mut [f32],
) {
    let at = |r: usize, j: usize| (i0 + r) * args.c_rs + (j0 + j) * args.c_cs;
    // Whole rows of contiguous c move as vectors; the rest element by element.
    let whole = args.c_cs == 1 && cols == NB * 8;
    let mut acc = [[[0f32; 8]; NB]; R];
    if args.beta != 0.0 {
        for (r, acc) in acc.iter_mut().enumerate() {
            if whole {
                let row = &c[at(r, 0)..][..NB * 8];
                for (q, v) in acc.iter_mut().enumerate() {
                    let old: [f32; 8] = row[q * 8..q * 8 + 8].try_into().expect("8 columns");
                    *v = old.map(|x| args.beta * x);
                }
            } else {
                // Through a buffer: a dynamic index into `acc` would keep it out of registers.
                let mut buf = [0f32; BLOCK_COLS];
                for (j, v) in buf[..cols].iter_mut().enumerate() {
                    *v = args.beta * c[at(r, j)];
                }
                for (q, v) in acc.iter_mut().enumerate() {
                    *v = buf[q * 8..q * 8 + 8].try_into().expect("8 columns");
                }
            }
        }
    }
    // The last element either operand reads, checked once for the whole block.
    if args.k > 0 {
        let last_a = (i0 + R - 1) * args.a_rs + (args.k - 1) * args.a_cs;
        let last_b = (args.k - 1) * args.b_rs + j0 + NB * 8;
        assert!(last_a < args.a.len() && last_b <= args.b.len());
    }
    let (a, b) = (args.a.as_ptr(), args.b.as_ptr());
    for p in 0..args.k {
        let mut bv = [[0f32; 8]; NB];
        for (q, v) in bv.iter_mut().enumerate() {
            // SAFETY: rows `p < k` of b, `8 NB` columns from `j0`, reach `last_b`.
            *v = unsafe { std::ptr::read_unaligned(b.add(p * args.b_rs + j0 + q * 8).cast()) };
        }
        for (r, acc) in acc.iter_mut().enumerate() {
            // SAFETY: rows `i0 + r < i0 + R` and columns `p < k` of a reach `last_a`.
            let x = unsafe { *a.add((i0 + r) * args.a_rs + p * args.a_cs) };
            for q in 0..NB {
                for l in 0..8 {
                    acc[q][l] += x * bv[q][l];
                }
            }
        }
    }
    for (r, acc) in acc.iter().enumerate() {
        if whole {
            let row = &mut c[at(r, 0)..][..NB * 8];
            for (q, v) in acc.iter().enumerate() {
                let dst: &mut [f32; 8] = (&mut row[q * 8..q * 8 + 8]).try_into().expect("8");
                *dst = *v;
            }
        } else {
            let mut buf = [0f32; BLOCK_COLS];
            for (q, v) in acc.iter().enumerate() {
                buf[q * 8..q * 8 + 8].copy_from_slice(v);
            }
            for (j, &v) in buf[..cols].iter().enumerate() {
                c[at(r, j)] = v;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The same sums in the same order, one element at a time.
    fn naive(m: usize, k: usize, n: usize, a: View, b: View, beta: f32, c: &[f32]) -> Vec<f32> {
        let mut out = vec![0f32; m * n];
        for i in 0..m {
            for j in 0..n {
                let mut s = if beta != 0.0 {
                    beta * c[i * n + j]
                } else {
                    0.0
                };
                for p in 0..k {
                    s += a.data[i * a.rs + p * a.cs] * b.data[p * b.rs + j * b.cs];
                }
                out[i * n + j] = s;
            }
        }
        out
    }

    fn values(len: usize, seed: f32) -> Vec<f32> {
        (0..len).map(|i| ((i as f32 + seed) * 0.37).sin()).collect()
    }

    #[test]
    fn gemm_matches_naive_with_strides_and_beta() {
        let (m, k, n) = (7, 5, 3);
        let a = values(m * 6, 0.0);
        let b = values(k * n, 1.0);
        // a viewed with row stride 6 and a column offset of 1
        let av = View {
            data: &a[1..],
            rs: 6,
            cs: 1,
        };
        let c0 = vec![1f32; m * n];
        let want = naive(m, k, n, av, View::rows(&b, n), 2.0, &c0);
        let mut c = c0.clone();
        gemm(m, k, n, av, View::rows(&b, n), 2.0, &mut c, n);
        assert_eq!(c, want);
        // transposed b: b^T is [n, k]; NaN in c must not leak through beta = 0
        let bt = values(n * k, 2.0);
        let want = naive(m, k, n, av, View::transposed(&bt, k), 0.0, &c0);
        let mut c = vec![f32::NAN; m * n];
        gemm(m, k, n, av, View::transposed(&bt, k), 0.0, &mut c, n);
        assert_eq!(c, want);
    }

    #[test]
    fn a_row_stride_of_c_leaves_the_other_columns_alone() {
        let (m, k, n, ldc) = (5, 4, 9, 12);
        let a = values(m * k, 0.5);
        let b = values(k * n, 1.5);
        let mut c = vec![7f32; (m - 1) * ldc + n];
        gemm(
            m,
            k,
            n,
            View::rows(&a, k),
            View::rows(&b, n),
            0.0,
            &mut c,
            ldc,
        );
        let want = naive(m, k, n, View::rows(&a, k), View::rows(&b, n), 0.0, &[]);
        for i in 0..m {
            assert_eq!(&c[i * ldc..i * ldc + n], &want[i * n..(i + 1) * n]);
            if i + 1 < m {
                assert!(c[i * ldc + n..(i + 1) * ldc].iter().all(|&v| v == 7.0));
            }
        }
    }

    proptest! {
        /// Every block shape, column tail and row tail, both layouts of `a` and `b`, both
        /// betas, and the baseline and AVX2 builds: the naive loop's bits.
        #[test]
        fn gemm_gives_the_naive_bits(
            m in 1usize..40,
            k in 0usize..40,
            n in 1usize..70,
            a_t in any::<bool>(),
            b_t in any::<bool>(),
            beta in prop_oneof![Just(0.0f32), Just(1.0f32), Just(-0.5f32)],
            seed in 0f32..100.0,
        ) {
            let a = values(m * k.max(1), seed);
            let b = values(k.max(1) * n, seed + 7.0);
            let av = if a_t { View::transposed(&a, m) } else { View::rows(&a, k.max(1)) };
            let bv = if b_t { View::transposed(&b, k.max(1)) } else { View::rows(&b, n) };
            let c0 = values(m * n, seed + 3.0);
            let want = naive(m, k, n, av, bv, beta, &c0);
            for baseline in [false, true] {
                crate::model::fused::baseline_only(baseline);
                let mut c = c0.clone();
                gemm(m, k, n, av, bv, beta, &mut c, n);
                crate::model::fused::baseline_only(false);
                prop_assert_eq!(&c, &want);
            }
        }
    }
}
