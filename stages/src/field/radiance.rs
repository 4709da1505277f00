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
//! sky as the last index; see [`FieldSpec::num_classes`].

use burn::module::Module;
use burn::tensor::activation::{sigmoid, softplus};
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use super::encoding::{
    grid_lookup, pe_dim, positional_encoding, EncodingKind, GridConfig, GridLookup, HashGrid,
};
use super::mlp::{Mlp, SplitMix64};

/// Hyper-parameters of the field (a stage parameter: serde, defaults, unknown keys rejected).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FieldConfig {
    /// Position encoding: `grid` (fast, default) or `pe` (the paper's).
    pub encoding: EncodingKind,
    /// The grid, when `encoding = grid`.
    pub grid: GridConfig,
    /// Octaves of the position encoding when `encoding = pe` (paper: 15; original NeRF: 10).
    pub pe_position_frequencies: usize,
    /// Octaves of the view-direction encoding (both encodings; paper: 4).
    pub pe_direction_frequencies: usize,
    /// Width of the hidden layers of every MLP.
    pub hidden: usize,
    /// Hidden layers of the trunk MLP (grid: 1 is enough; pe: 4-8).
    pub trunk_layers: usize,
    /// Geometry features passed from the trunk to the colour and semantic heads.
    pub geo_features: usize,
    /// Hidden layers of the colour and semantic heads.
    pub head_layers: usize,
    /// Density = softplus(raw + density_shift); -1 gives 0.31 per unit length at init.
    pub density_shift: f32,
}

impl Default for FieldConfig {
    fn default() -> Self {
        Self {
            encoding: EncodingKind::Grid,
            grid: GridConfig::default(),
            pe_position_frequencies: 15,
            pe_direction_frequencies: 4,
            hidden: 32,
            trunk_layers: 1,
            geo_features: 15,
            head_layers: 1,
            density_shift: -1.0,
        }
    }
}

impl FieldConfig {
    /// The paper-like positional-encoding field (L=15 positions, L=4 directions, 4x64 MLP).
    pub fn pe() -> Self {
        Self {
            encoding: EncodingKind::Pe,
            hidden: 64,
            trunk_layers: 4,
            ..Self::default()
        }
    }

    /// Width of the position encoding.
    pub fn position_dim(&self) -> usize {
        match self.encoding {
            EncodingKind::Grid => self.grid.output_dim(),
            EncodingKind::Pe => pe_dim(3, self.pe_position_frequencies),
        }
    }

    /// Width of the direction encoding.
    pub fn direction_dim(&self) -> usize {
        pe_dim(3, self.pe_direction_frequencies)
    }

    /// Checks ranges; errors name the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.encoding == EncodingKind::Grid {
            self.grid.validate()?;
        }
        if self.hidden == 0 || self.geo_features == 0 {
            return Err("field.hidden and field.geo_features must be >= 1".into());
        }
        if self.pe_position_frequencies > 20 || self.pe_direction_frequencies > 20 {
            return Err("field.pe_*_frequencies must be <= 20".into());
        }
        if !self.density_shift.is_finite() {
            return Err("field.density_shift must be finite".into());
        }
        Ok(())
    }
}

/// Everything needed to rebuild a field: its config, the scene's class count and AABB, and
/// the initialisation seed. Store it beside the weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FieldSpec {
    pub config: FieldConfig,
    /// Classes of the semantic head: the scene's primitive classes, then sky (last index).
    pub num_classes: usize,
    /// Scene-frame AABB used to normalise positions to the unit cube (outside: clamped).
    pub aabb_min: [f32; 3],
    pub aabb_max: [f32; 3],
    /// Seed of the initial weights.
    pub seed: u64,
}

impl FieldSpec {
    /// The sky's class index (`num_classes - 1`).
    pub fn sky_index(&self) -> usize {
        self.num_classes - 1
    }

    /// Checks the spec; errors name the field.
    pub fn validate(&self) -> Result<(), String> {
        self.config.validate()?;
        if self.num_classes < 2 {
            return Err(format!(
                "num_classes is {}; need at least one scene class plus sky",
                self.num_classes
            ));
        }
        for a in 0..3 {
            if self.aabb_max[a] <= self.aabb_min[a]
                || !self.aabb_min[a].is_finite()
                || !self.aabb_max[a].is_finite()
            {
                return Err(format!(
                    "aabb axis {a}: min {} must be < max {} and finite",
                    self.aabb_min[a], self.aabb_max[a]
                ));
            }
        }
        Ok(())
    }

    /// Scene coordinate `x` on `axis` mapped to `[0, 1]` over the AABB (clamped; 0.5 if not
    /// finite).
    pub fn unit_coordinate(&self, axis: usize, x: f32) -> f32 {
        let u = (x - self.aabb_min[axis]) / (self.aabb_max[axis] - self.aabb_min[axis]);
        if u.is_finite() {
            u.clamp(0.0, 1.0)
        } else {
            0.5
        }
    }

    /// A freshly initialised field on `device` (use an autodiff device to train).
    pub fn init(&self, device: &Device) -> RadianceField {
        RadianceField::new(self.clone(), device)
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
    /// A field initialised from `spec.seed`.
    pub fn new(spec: FieldSpec, device: &Device) -> Self {
        let c = &spec.config;
        let mut rng = SplitMix64::new(spec.seed);
        let grid = match c.encoding {
            EncodingKind::Grid => Some(HashGrid::new(&c.grid, &mut rng, device)),
            EncodingKind::Pe => None,
        };
        let trunk = Mlp::new(
            c.position_dim(),
            c.hidden,
            c.trunk_layers,
            1 + c.geo_features,
            &mut rng,
            device,
        );
        let colour = Mlp::new(
            c.geo_features + c.direction_dim(),
            c.hidden,
            c.head_layers,
            3,
            &mut rng,
            device,
        );
        let semantic = Mlp::new(
            c.geo_features,
            c.hidden,
            c.head_layers,
            spec.num_classes,
            &mut rng,
            device,
        );
        Self {
            grid,
            trunk,
            colour,
            semantic,
            spec,
        }
    }

    /// Normalises and encodes on the host. Each direction row applies to `samples_per_direction`
    /// consecutive points (the samples of one ray).
    ///
    /// # Shapes
    /// `positions`: `[points, 3]` (scene frame); `directions`: `[points / samples_per_direction,
    /// 3]` (need not be unit length).
    pub fn prepare(
        &self,
        positions: &[f32],
        directions: Option<&[f32]>,
        samples_per_direction: usize,
    ) -> FieldInput {
        let spec = &self.spec;
        let points = positions.len() / 3;
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
                Some(sigmoid(
                    self.colour.forward(Tensor::cat(vec![geo.clone(), d], 1)),
                ))
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
    use crate::field::Backend;

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
        let device = Backend::default().device();
        for config in [FieldConfig::default(), FieldConfig::pe()] {
            let f = spec(config).init(&device);
            let pos = [
                0.1f32, 0.2, 0.3, -0.5, 0.9, 0.0, 5.0, 5.0, 5.0, 0.0, 0.0, 0.0,
            ];
            let dirs = [0.0f32, 0.0, 1.0, 1.0, 0.0, 0.0];
            let input = f.prepare(&pos, Some(&dirs), 2);
            let out = f.forward(&input, &[FieldHead::Rgb, FieldHead::Semantics]);
            let d = out.density.into_data().try_to_vec::<f32>().unwrap();
            assert!(d.iter().all(|&x| x > 0.01 && x.is_finite()), "{d:?}");
            assert_eq!(out.rgb.unwrap().dims(), [4, 3]);
            assert_eq!(out.logits.unwrap().dims(), [4, 3]);
        }
    }

    #[test]
    fn same_seed_same_weights() {
        let device = Backend::default().device();
        let a = spec(FieldConfig::default()).init(&device);
        let b = spec(FieldConfig::default()).init(&device);
        let input = a.prepare(&[0.3, 0.1, -0.2], None, 1);
        let da = a.forward(&input, &[]).density.into_data();
        let db = b.forward(&input, &[]).density.into_data();
        assert_eq!(da, db);
    }
}
