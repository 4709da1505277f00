//! The parameter-free part of the field's encodings, on the host: the multi-resolution
//! hash/dense grid's corner rows and trilinear weights (default, fast), the paper's sinusoidal
//! positional encoding (`pe`) and unit view directions.
//!
//! Design (measured on the 2-core dev machine, see issue 5 and the `train_step` bench): the
//! integer part of a grid lookup (which 8 vertices of which cell, per level) and the trilinear
//! weights carry no gradient, so they are computed in plain Rust with rayon into flat buffers
//! ([`GridLookup`]); burn then only does `select` rows of the learnable table + a weighted sum,
//! so the tables stay ordinary burn parameters with autodiff on every backend. Building the
//! indices with burn tensor ops instead cost 220-330 ms more per 131072 samples, and `gather`
//! was slower than `select` on flex.
//!
//! The positional encoding has no parameters, so it is computed entirely on the host.
//!
//! Positions are expected in the unit cube `[0, 1]^3` (normalised by the scene AABB and
//! clamped, [`crate::model::FieldSpec::unit_coordinate`]). Both engines use these host parts;
//! only the table reads differ (burn `select` in [`crate::model::burn`], a gather loop in
//! [`crate::model::fused`]).

use rayon::prelude::*;

use super::config::{pe_dim, GridConfig};

/// Host-computed plan of one grid lookup: for each point, level and cell corner, the row of the
/// (all levels stacked) table and its trilinear weight.
///
/// # Shapes
/// `indices`, `weights`: `[points, levels, 8]` flattened row-major.
#[derive(Debug, Clone)]
pub struct GridLookup {
    pub points: usize,
    pub indices: Vec<i32>,
    pub weights: Vec<f32>,
}

const HASH_PRIMES: [u32; 3] = [1, 2_654_435_761, 805_459_861];

/// Per level: cells per axis, and whether the level is dense (every vertex has its own row).
pub fn level_info(config: &GridConfig) -> Vec<(u32, bool)> {
    (0..config.levels)
        .map(|l| {
            let n = config.resolution(l);
            let vertices = (n as u64 + 1).pow(3);
            (n, vertices <= config.table_size() as u64)
        })
        .collect()
}

/// Corner rows (of the stacked table) and trilinear weights of one point `p` in `[0,1]^3`
/// (clamped): `idx`, `w` have `levels * 8` entries, level-major.
pub fn lookup_point(
    config: &GridConfig,
    levels: &[(u32, bool)],
    p: &[f32],
    idx: &mut [i32],
    w: &mut [f32],
) {
    for (l, &level) in levels.iter().enumerate() {
        let corners = l * 8..(l + 1) * 8;
        lookup_level(
            config,
            l,
            level,
            p,
            &mut idx[corners.clone()],
            &mut w[corners],
        );
    }
}

/// The 8 corner rows and weights of point `p` on level `l` (`level` from [`level_info`]).
#[inline(always)]
pub fn lookup_level(
    config: &GridConfig,
    l: usize,
    (n, dense): (u32, bool),
    p: &[f32],
    idx: &mut [i32],
    w: &mut [f32],
) {
    let table = config.table_size();
    let mut cell = [0u32; 3];
    let mut frac = [0f32; 3];
    for a in 0..3 {
        let x = p[a].clamp(0.0, 1.0) * n as f32;
        // x >= 0 (or NaN, which casts to 0), so truncation is floor without a libm call
        let c = (x as u32).min(n - 1);
        cell[a] = c;
        frac[a] = (x - c as f32).clamp(0.0, 1.0);
    }
    let offset = (l * table) as u32;
    // Per axis, the weights and row terms of its two vertices; a corner combines one of each
    // (the same products and rows as vertex by vertex, without recomputing them 8 times).
    let wa = frac.map(|f| [1.0 - f, f]);
    let terms: [[u32; 2]; 3] = if dense {
        let side = n + 1;
        let scale = [1, side, side * side];
        std::array::from_fn(|a| [cell[a] * scale[a], (cell[a] + 1) * scale[a]])
    } else {
        std::array::from_fn(|a| {
            [
                cell[a].wrapping_mul(HASH_PRIMES[a]),
                (cell[a] + 1).wrapping_mul(HASH_PRIMES[a]),
            ]
        })
    };
    let mask = table as u32 - 1;
    for corner in 0..8 {
        let (b0, b1, b2) = (corner & 1, (corner >> 1) & 1, (corner >> 2) & 1);
        let row = if dense {
            terms[0][b0] + terms[1][b1] + terms[2][b2]
        } else {
            (terms[0][b0] ^ terms[1][b1] ^ terms[2][b2]) & mask
        };
        idx[corner] = (offset + row) as i32;
        w[corner] = wa[0][b0] * wa[1][b1] * wa[2][b2];
    }
}

/// Computes the corner rows and trilinear weights of `unit_positions` (in `[0,1]^3`, clamped).
///
/// # Shapes
/// `unit_positions`: `[points, 3]` flattened.
pub fn grid_lookup(config: &GridConfig, unit_positions: &[f32]) -> GridLookup {
    assert_eq!(unit_positions.len() % 3, 0, "positions must be [points, 3]");
    let points = unit_positions.len() / 3;
    let per_point = config.levels * 8;
    let mut indices = vec![0i32; points * per_point];
    let mut weights = vec![0f32; points * per_point];
    let levels = level_info(config);
    indices
        .par_chunks_mut(per_point)
        .zip(weights.par_chunks_mut(per_point))
        .zip(unit_positions.par_chunks(3))
        .for_each(|((idx, w), p)| lookup_point(config, &levels, p, idx, w));
    GridLookup {
        points,
        indices,
        weights,
    }
}

/// `d` (3 values) scaled to unit length; +z when it has no finite direction.
pub fn unit_direction(d: &[f32]) -> [f32; 3] {
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if n > 0.0 && n.is_finite() {
        [d[0] / n, d[1] / n, d[2] / n]
    } else {
        [0.0, 0.0, 1.0]
    }
}

/// NeRF positional encoding `[x, sin(2^k pi x), cos(2^k pi x)]_{k<L}` of each row.
///
/// # Shapes
/// `values`: `[rows, dims]` flattened; returns `[rows, pe_dim(dims, frequencies)]` flattened.
pub fn positional_encoding(values: &[f32], dims: usize, frequencies: usize) -> Vec<f32> {
    let width = pe_dim(dims, frequencies);
    let rows = values.len() / dims;
    let mut out = vec![0f32; rows * width];
    out.par_chunks_mut(width)
        .zip(values.par_chunks(dims))
        .for_each(|(o, v)| {
            o[..dims].copy_from_slice(v);
            for k in 0..frequencies {
                let scale = std::f32::consts::PI * (1u32 << k) as f32;
                for (a, &x) in v.iter().enumerate() {
                    let (s, c) = (x * scale).sin_cos();
                    o[dims + (2 * k) * dims + a] = s;
                    o[dims + (2 * k + 1) * dims + a] = c;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trilinear_weights_sum_to_one_and_rows_stay_in_their_level() {
        let cfg = GridConfig::default();
        let pts = [
            0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.3, 0.71, 0.5, -2.0, 3.0, 0.999,
        ];
        let lu = grid_lookup(&cfg, &pts);
        for p in 0..4 {
            for l in 0..cfg.levels {
                let s: f32 = (0..8)
                    .map(|c| lu.weights[(p * cfg.levels + l) * 8 + c])
                    .sum();
                assert!((s - 1.0).abs() < 1e-5, "point {p} level {l}: {s}");
                for c in 0..8 {
                    let row = lu.indices[(p * cfg.levels + l) * 8 + c] as usize;
                    assert_eq!(row / cfg.table_size(), l);
                }
            }
        }
        // Coarsest level is dense: a vertex has the analytic row.
        assert!((cfg.resolution(0) as u64 + 1).pow(3) <= cfg.table_size() as u64);
        assert_eq!(lu.indices[0], 0);
    }

    /// The rows and weights vertex by vertex, as the definition reads.
    fn lookup_by_vertex(
        config: &GridConfig,
        l: usize,
        (n, dense): (u32, bool),
        p: &[f32],
    ) -> ([i32; 8], [f32; 8]) {
        let table = config.table_size();
        let x: [f32; 3] = std::array::from_fn(|a| p[a].clamp(0.0, 1.0) * n as f32);
        let cell: [u32; 3] = std::array::from_fn(|a| (x[a] as u32).min(n - 1));
        let frac: [f32; 3] = std::array::from_fn(|a| (x[a] - cell[a] as f32).clamp(0.0, 1.0));
        let (mut idx, mut w) = ([0i32; 8], [0f32; 8]);
        for corner in 0..8 {
            let mut weight = 1.0f32;
            let mut v = [0u32; 3];
            for a in 0..3 {
                let bit = (corner >> a) & 1;
                v[a] = cell[a] + bit as u32;
                weight *= if bit == 1 { frac[a] } else { 1.0 - frac[a] };
            }
            let row = if dense {
                let side = n + 1;
                v[0] + side * (v[1] + side * v[2])
            } else {
                (v[0].wrapping_mul(HASH_PRIMES[0])
                    ^ v[1].wrapping_mul(HASH_PRIMES[1])
                    ^ v[2].wrapping_mul(HASH_PRIMES[2]))
                    & (table as u32 - 1)
            };
            idx[corner] = ((l * table) as u32 + row) as i32;
            w[corner] = weight;
        }
        (idx, w)
    }

    #[test]
    fn lookups_equal_the_vertex_by_vertex_definition_bit_for_bit() {
        let cfg = GridConfig::default();
        let levels = level_info(&cfg);
        assert!(levels.iter().any(|l| l.1) && levels.iter().any(|l| !l.1));
        let mut rng = crate::rng::SplitMix64::new(3);
        for _ in 0..2000 {
            let p = [
                rng.uniform(-0.1, 1.1),
                rng.uniform(0.0, 1.0),
                rng.uniform(0.0, 1.0),
            ];
            for (l, &level) in levels.iter().enumerate() {
                let (mut idx, mut w) = ([0i32; 8], [0f32; 8]);
                lookup_level(&cfg, l, level, &p, &mut idx, &mut w);
                let (ri, rw) = lookup_by_vertex(&cfg, l, level, &p);
                assert_eq!(idx, ri, "{p:?} level {l}");
                assert_eq!(w.map(f32::to_bits), rw.map(f32::to_bits), "{p:?} level {l}");
            }
        }
    }

    #[test]
    fn positional_encoding_layout() {
        let e = positional_encoding(&[0.5, 0.25, 0.0], 3, 2);
        assert_eq!(e.len(), pe_dim(3, 2));
        assert_eq!(&e[..3], &[0.5, 0.25, 0.0]);
        assert!((e[3] - (std::f32::consts::PI * 0.5).sin()).abs() < 1e-6);
        assert!((e[6] - (std::f32::consts::PI * 0.5).cos()).abs() < 1e-6);
        assert!((e[9 + 1] - (std::f32::consts::PI * 2.0 * 0.25).sin()).abs() < 1e-6);
    }
}
