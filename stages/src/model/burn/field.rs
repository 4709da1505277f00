//! The radiance field with its learned semantic head: density (>= 0), view-dependent colour and
//! semantic logits, for either position encoding ([`EncodingKind`]).
//!
//! Structure (both encodings): `trunk: enc(x) -> [raw density, geometry features]`;
//! `colour: [geometry features, enc(d)] -> rgb` (sigmoid); `semantic: geometry features ->
//! logits` (position only, as in the paper's s_phi). Density is a shifted softplus
//! `softplus(raw + density_shift)`: strictly positive, so a fresh model is not zero everywhere
//! and every sample gets a gradient from the first step.
//!
//! Host preparation ([`RadianceField::prepare`]) normalises positions by the scene AABB and
//! computes the parameter-free part of the encodings in plain Rust; [`RadianceField::forward`]
//! is the burn part. The classes are the scene's classes (those of its primitives) followed by
//! sky as the last index; see [`FieldSpec::num_classes`]. Parameters come from named rows
//! ([`crate::model::params`]): a fresh field from [`params::initial`], a trained one from the
//! `weights` table.

use burn::module::{Module, Param};
use burn::tensor::activation::{relu, sigmoid, softplus};
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::model::config::{EncodingKind, FieldSpec, SkyColourInput};
use crate::model::encoding::{grid_lookup, positional_encoding, unit_direction, GridLookup};
use crate::model::error::ModelError;
use crate::model::params::{self, NamedWeight};

/// The learnable tables of the grid (all levels stacked).
#[derive(Module, Debug)]
pub struct HashGrid {
    /// `[levels * table_size, features_per_level]`.
    pub table: Param<Tensor<2>>,
    #[module(skip)]
    pub levels: usize,
    #[module(skip)]
    pub features: usize,
}

/// Corner reads per `select` call (see [`HashGrid::forward`]).
const SELECT_ROWS: usize = 1 << 15;

impl HashGrid {
    /// Interpolated features.
    ///
    /// # Shapes
    /// returns `[points, levels * features_per_level]`.
    pub fn forward(&self, lookup: &GridLookup) -> Tensor<2> {
        let device = self.table.device();
        let rows = lookup.points * self.levels * 8;
        let w = Tensor::<2>::from_data(TensorData::new(lookup.weights.clone(), [rows, 1]), &device);
        // Rows in parts of at most SELECT_ROWS: on wgpu (burn 0.22, cubecl 0.11) the gradient of
        // `select` drops or garbles every read past the 65535th (one workgroup per read, and
        // WebGPU allows at most 65535 per dimension), so a training batch (millions of corner
        // reads) got a wrong grid gradient. Tested in `grid_gradient_counts_every_corner_read`.
        let table = self.table.val();
        let parts: Vec<Tensor<2>> = lookup
            .indices
            .chunks(SELECT_ROWS)
            .map(|part| {
                let idx = Tensor::<1, Int>::from_data(
                    TensorData::new(part.to_vec(), [part.len()]),
                    &device,
                );
                table.clone().select(0, idx)
            })
            .collect();
        let corners = Tensor::cat(parts, 0) * w; // [points*levels*8, F]
        corners
            .reshape([lookup.points * self.levels, 8, self.features])
            .sum_dim(1) // [points*levels, 1, F]
            .reshape([lookup.points, self.levels * self.features])
    }
}

/// One affine layer `x W + b`.
#[derive(Module, Debug)]
pub struct Dense {
    /// `[inputs, outputs]`.
    pub weight: Param<Tensor<2>>,
    /// `[outputs]`.
    pub bias: Param<Tensor<1>>,
}

impl Dense {
    /// # Shapes
    /// `x`: `[rows, inputs]` -> `[rows, outputs]`.
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        x.matmul(self.weight.val()) + self.bias.val().unsqueeze::<2>()
    }
}

/// `inputs -> hidden (x depth) -> outputs`, ReLU after every layer but the last.
#[derive(Module, Debug)]
pub struct Mlp {
    pub layers: Vec<Dense>,
}

impl Mlp {
    /// # Shapes
    /// `x`: `[rows, inputs]` -> `[rows, outputs]`.
    pub fn forward(&self, mut x: Tensor<2>) -> Tensor<2> {
        let last = self.layers.len() - 1;
        for (i, layer) in self.layers.iter().enumerate() {
            x = layer.forward(x);
            if i < last {
                x = relu(x);
            }
        }
        x
    }
}

/// Parameter tensors by name, from rows checked against the layout.
struct Rows<'a> {
    rows: &'a [NamedWeight],
    device: &'a Device,
}

impl Rows<'_> {
    fn row(&self, name: &str) -> &NamedWeight {
        &self.rows[params::index(self.rows, name).expect("rows checked against the layout")]
    }

    fn tensor<const D: usize>(&self, name: &str) -> Param<Tensor<D>> {
        let r = self.row(name);
        Param::from_tensor(Tensor::from_data(
            TensorData::new(r.values.clone(), r.shape.clone()),
            self.device,
        ))
    }

    fn mlp(&self, prefix: &str) -> Mlp {
        let layers = (0..)
            .map_while(|i| {
                let w = format!("{prefix}.layers.{i}.weight");
                params::index(self.rows, &w).map(|_| Dense {
                    weight: self.tensor(&w),
                    bias: self.tensor(&format!("{prefix}.layers.{i}.bias")),
                })
            })
            .collect();
        Mlp { layers }
    }
}

/// The heads a caller wants from [`RadianceField::forward`] (density is always computed).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum FieldHead {
    Density,
    Rgb,
    Semantics,
}

/// Position encoding prepared on the host.
#[derive(Debug, Clone)]
pub enum PreparedPositions {
    /// Grid rows and trilinear weights.
    Grid(GridLookup),
    /// Dense positional-encoding features, `[points, position_dim]` flattened.
    Features(Vec<f32>),
}

/// The host-prepared input of one forward pass.
#[derive(Debug, Clone)]
pub struct FieldInput {
    pub points: usize,
    pub positions: PreparedPositions,
    /// Encoded view directions, `[points, direction_dim]` flattened; `None` skips colour.
    pub directions: Option<Vec<f32>>,
    /// Per point, 1 where the colour head sees the geometry features and 0 where it sees the
    /// direction only (sky samples under `sky_colour: direction`); `None`: 1 everywhere.
    pub colour_geometry: Option<Vec<f32>>,
}

/// Outputs of the field per point.
///
/// # Shapes
/// `density`: `[points]`; `rgb`: `[points, 3]`; `logits`: `[points, classes]`.
#[derive(Debug, Clone)]
pub struct FieldOutputs {
    pub density: Tensor<1>,
    pub rgb: Option<Tensor<2>>,
    pub logits: Option<Tensor<2>>,
}

/// The learned radiance + semantic field.
#[derive(Module, Debug)]
pub struct RadianceField {
    /// Present iff `encoding = grid`.
    pub grid: Option<HashGrid>,
    pub trunk: Mlp,
    pub colour: Mlp,
    pub semantic: Mlp,
    #[module(skip)]
    pub spec: FieldSpec,
}

impl RadianceField {
    /// A field initialised from `spec.seed` ([`params::initial`]) on `device` (use an
    /// autodiff device to train).
    pub fn init(spec: FieldSpec, device: &Device) -> Self {
        let rows = params::initial(&spec);
        Self::from_weights(spec, &rows, device).expect("the initial rows follow the layout")
    }

    /// The field with parameters `rows` (checked against the layout of `spec`) on `device`.
    pub fn from_weights(
        spec: FieldSpec,
        rows: &[NamedWeight],
        device: &Device,
    ) -> Result<Self, ModelError> {
        params::check(&spec, rows)?;
        let r = Rows { rows, device };
        let grid = (spec.config.encoding == EncodingKind::Grid).then(|| HashGrid {
            table: r.tensor("grid.table"),
            levels: spec.config.grid.levels,
            features: spec.config.grid.features_per_level,
        });
        Ok(Self {
            grid,
            trunk: r.mlp("trunk"),
            colour: r.mlp("colour"),
            semantic: r.mlp("semantic"),
            spec,
        })
    }

    /// Normalises and encodes on the host. Each direction row applies to `samples_per_direction`
    /// consecutive points (the samples of one ray); `in_sky` flags the points in their ray's
    /// sky interval (or is empty: none).
    ///
    /// # Shapes
    /// `positions`: `[points, 3]` (scene frame); `directions`: `[points / samples_per_direction,
    /// 3]` (need not be unit length); `in_sky`: `[points]` or empty.
    pub fn prepare(
        &self,
        positions: &[f32],
        directions: Option<&[f32]>,
        samples_per_direction: usize,
        in_sky: &[bool],
    ) -> FieldInput {
        let spec = &self.spec;
        let points = positions.len() / 3;
        let colour_geometry = (spec.config.sky_colour == SkyColourInput::Direction
            && in_sky.contains(&true))
        .then(|| {
            assert_eq!(in_sky.len(), points, "in_sky must have one flag per point");
            in_sky.iter().map(|&s| if s { 0.0 } else { 1.0 }).collect()
        });
        let mut unit = Vec::with_capacity(positions.len());
        for p in positions.chunks_exact(3) {
            for (a, &x) in p.iter().enumerate() {
                unit.push(spec.unit_coordinate(a, x));
            }
        }
        let positions = match spec.config.encoding {
            EncodingKind::Grid => PreparedPositions::Grid(grid_lookup(&spec.config.grid, &unit)),
            EncodingKind::Pe => {
                // [-1, 1] so the lowest octave sees one period over the AABB
                let centred: Vec<f32> = unit.iter().map(|u| 2.0 * u - 1.0).collect();
                PreparedPositions::Features(positional_encoding(
                    &centred,
                    3,
                    spec.config.pe_position_frequencies,
                ))
            }
        };
        let directions = directions.map(|d| {
            assert_eq!(
                d.len() / 3 * samples_per_direction,
                points,
                "direction count"
            );
            let mut rows = Vec::with_capacity(points * 3);
            for dir in d.chunks_exact(3) {
                let unit = unit_direction(dir);
                for _ in 0..samples_per_direction {
                    rows.extend_from_slice(&unit);
                }
            }
            positional_encoding(&rows, 3, spec.config.pe_direction_frequencies)
        });
        FieldInput {
            points,
            positions,
            directions,
            colour_geometry,
        }
    }

    /// The burn part: encodings -> MLPs -> outputs. Colour needs `input.directions`.
    pub fn forward(&self, input: &FieldInput, heads: &[FieldHead]) -> FieldOutputs {
        let device = self.trunk.layers[0].weight.device();
        let c = &self.spec.config;
        let p = input.points;
        let enc = match (&input.positions, &self.grid) {
            (PreparedPositions::Grid(lu), Some(grid)) => grid.forward(lu),
            (PreparedPositions::Features(f), None) => {
                Tensor::from_data(TensorData::new(f.clone(), [p, c.position_dim()]), &device)
            }
            _ => panic!("field input was prepared for another encoding"),
        }; // [points, position_dim]
        let trunk = self.trunk.forward(enc); // [points, 1 + geo]
        let raw = trunk.clone().narrow(1, 0, 1).reshape([p]);
        let density = softplus(raw.add_scalar(c.density_shift), 1.0);
        let geo = trunk.narrow(1, 1, c.geo_features); // [points, geo]
        let rgb = match (&input.directions, heads.contains(&FieldHead::Rgb)) {
            (Some(dirs), true) => {
                let d = Tensor::from_data(
                    TensorData::new(dirs.clone(), [p, c.direction_dim()]),
                    &device,
                );
                let seen = match &input.colour_geometry {
                    Some(m) => {
                        let m: Tensor<2> =
                            Tensor::from_data(TensorData::new(m.clone(), [p, 1]), &device);
                        geo.clone() * m
                    }
                    None => geo.clone(),
                };
                Some(sigmoid(self.colour.forward(Tensor::cat(vec![seen, d], 1))))
            }
            _ => None,
        };
        let logits = heads
            .contains(&FieldHead::Semantics)
            .then(|| self.semantic.forward(geo));
        FieldOutputs {
            density,
            rgb,
            logits,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::burn::Backend;
    use crate::model::{FieldConfig, GridConfig};

    /// Every corner read adds its weight times the output's gradient to its row, on every
    /// backend this build has, past the 65535 reads where burn's wgpu `select` gradient breaks.
    #[test]
    fn grid_gradient_counts_every_corner_read() {
        let (rows, features, points) = (300_000usize, 2usize, 9000usize);
        let reads = points * 8;
        assert!(reads > 1 << 16);
        // Spread over the table, and crowded onto a few rows (a coarse dense level, where
        // thousands of reads of one batch share a vertex).
        for crowded in [false, true] {
            let indices: Vec<i32> = (0..reads)
                .map(|k| {
                    if crowded {
                        (k % 5) as i32
                    } else {
                        ((k * 7919 + k / 3) % rows) as i32
                    }
                })
                .collect();
            let weights: Vec<f32> = (0..reads).map(|k| ((k * 17) % 23) as f32 / 23.0).collect();
            let c: Vec<f32> = (0..points * features)
                .map(|i| ((i * 13) % 7) as f32 - 3.0)
                .collect();
            let mut want = vec![0f64; rows * features];
            for k in 0..reads {
                for f in 0..features {
                    want[indices[k] as usize * features + f] +=
                        weights[k] as f64 * c[(k / 8) * features + f] as f64;
                }
            }
            let lookup = crate::model::encoding::GridLookup {
                points,
                indices,
                weights,
            };
            for b in Backend::available() {
                if b.check_device().is_err() && !std::env::var("CI").is_ok_and(|v| v == "true") {
                    continue;
                }
                let d = b.train_device();
                let table = Tensor::<2>::from_data(
                    TensorData::new(vec![0.5f32; rows * features], [rows, features]),
                    &d,
                );
                let grid = HashGrid {
                    table: Param::from_tensor(table),
                    levels: 1,
                    features,
                };
                let ct = Tensor::<2>::from_data(TensorData::new(c.clone(), [points, features]), &d);
                let grads = (grid.forward(&lookup) * ct).sum().backward();
                let got = grid
                    .table
                    .grad(&grads)
                    .unwrap()
                    .into_data()
                    .try_to_vec::<f32>()
                    .unwrap();
                let bad = got
                    .iter()
                    .zip(&want)
                    .filter(|(g, w)| (**g as f64 - **w).abs() > 1e-3 * (1.0 + w.abs()))
                    .count();
                assert_eq!(
                    bad,
                    0,
                    "{} (crowded: {crowded}): {bad} of {} table entries",
                    b.name(),
                    got.len()
                );
            }
        }
    }

    fn spec(config: FieldConfig) -> FieldSpec {
        FieldSpec {
            config,
            num_classes: 3,
            aabb_min: [-1.0, -1.0, -1.0],
            aabb_max: [1.0, 1.0, 1.0],
            seed: 3,
        }
    }

    #[test]
    fn fresh_field_has_positive_density_and_all_heads_for_both_encodings() {
        let device = Backend::REFERENCE.device();
        for config in [FieldConfig::default(), FieldConfig::pe()] {
            let f = RadianceField::init(spec(config), &device);
            let pos = [
                0.1f32, 0.2, 0.3, -0.5, 0.9, 0.0, 5.0, 5.0, 5.0, 0.0, 0.0, 0.0,
            ];
            let dirs = [0.0f32, 0.0, 1.0, 1.0, 0.0, 0.0];
            let input = f.prepare(&pos, Some(&dirs), 2, &[]);
            let out = f.forward(&input, &[FieldHead::Rgb, FieldHead::Semantics]);
            let d = out.density.into_data().try_to_vec::<f32>().unwrap();
            assert!(d.iter().all(|&x| x > 0.01 && x.is_finite()), "{d:?}");
            assert_eq!(out.rgb.unwrap().dims(), [4, 3]);
            assert_eq!(out.logits.unwrap().dims(), [4, 3]);
        }
    }

    #[test]
    fn a_field_built_from_rows_gives_the_same_rows_back() {
        let device = Backend::REFERENCE.device();
        for config in [FieldConfig::default(), FieldConfig::pe()] {
            let s = spec(config);
            let rows = params::initial(&s);
            let f = RadianceField::from_weights(s.clone(), &rows, &device).unwrap();
            assert_eq!(f.weights(), rows);
            let mut bad = rows.clone();
            bad.pop();
            assert!(RadianceField::from_weights(s, &bad, &device).is_err());
        }
    }

    #[test]
    fn grid_interpolates_a_linear_table_exactly_on_dense_levels() {
        // With a table holding the x coordinate of each dense vertex, trilinear interpolation
        // returns x itself.
        let cfg = GridConfig {
            levels: 1,
            features_per_level: 1,
            log2_table_size: 12,
            base_resolution: 8,
            max_resolution: 8,
            init_scale: 0.0,
        };
        let device = Backend::REFERENCE.device();
        let n = 9usize;
        let mut values = vec![0f32; cfg.table_size()];
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    values[x + n * (y + n * z)] = x as f32 / 8.0;
                }
            }
        }
        let grid = HashGrid {
            table: Param::from_tensor(Tensor::from_data(
                TensorData::new(values, [cfg.table_size(), 1]),
                &device,
            )),
            levels: 1,
            features: 1,
        };
        let pts = [0.37f32, 0.2, 0.9, 0.81, 0.5, 0.1];
        let out = grid
            .forward(&grid_lookup(&cfg, &pts))
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        assert!(
            (out[0] - 0.37).abs() < 1e-5 && (out[1] - 0.81).abs() < 1e-5,
            "{out:?}"
        );
    }
}
