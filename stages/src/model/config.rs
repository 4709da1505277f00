//! The model's parameters as users write them (the `train` stage's `field` and `losses` groups:
//! serde, defaults, unknown keys rejected; [`FieldConfig`], [`GridConfig`], [`Losses`]), what a
//! trained field needs besides its weights ([`FieldSpec`]), and what an engine's trainer is given
//! ([`TrainConfig`]: those and the [`Optimiser`], built by the `train` kind). Every engine reads
//! these same structs; options an engine lacks are refused by
//! [`crate::model::Engine::supports`].

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::error::ModelError;
use super::loss::LossTerm;
use super::optimiser::Optimiser;

fn invalid(message: impl Into<String>) -> ModelError {
    ModelError::Param(message.into())
}

/// Which position encoding the field uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum EncodingKind {
    /// Multi-resolution hash/dense grid + small MLPs (instant-NGP style): fast.
    #[default]
    Grid,
    /// Sinusoidal positional encoding + a wider MLP (the paper's NeRF).
    Pe,
}

/// What the colour head sees at samples in a ray's sky interval.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum SkyColourInput {
    /// The geometry features and the view direction, as everywhere (the paper).
    #[default]
    Field,
    /// The view direction only (the geometry features are zeroed): the sky is a function of
    /// direction, like light from infinitely far away, so a ray's colour can be put in its sky
    /// interval only where that colour is the sky's in that direction. Without it, density in
    /// the sky interval can copy any colour, and nothing but a pseudo label tells a coarse
    /// primitive's empty top (filled with sky-coloured density) from the sky behind it.
    Direction,
}

/// Parameters of the multi-resolution grid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct GridConfig {
    /// Number of resolution levels.
    pub levels: usize,
    /// Learned features per level (the encoding has `levels * features_per_level` values).
    pub features_per_level: usize,
    /// log2 of the table rows per level; coarse levels that fit are dense, fine ones hashed.
    pub log2_table_size: u32,
    /// Cells per axis of the coarsest level.
    pub base_resolution: u32,
    /// Cells per axis of the finest level (levels are geometric in between). 256 suits the
    /// 1/8-scale scenes (cells of about 0.5 m over a 120 m box, a pixel's footprint at 30 m);
    /// full-size images need 2048 (`pipelines/kitti360.yaml`; docs/experiments/grid-resolution.md).
    pub max_resolution: u32,
    /// Table entries start uniform in [-init_scale, init_scale].
    pub init_scale: f32,
}

impl Default for GridConfig {
    fn default() -> Self {
        Self {
            levels: 8,
            features_per_level: 2,
            log2_table_size: 16,
            base_resolution: 16,
            max_resolution: 256,
            init_scale: 1e-4,
        }
    }
}

impl GridConfig {
    /// Width of the encoding.
    pub fn output_dim(&self) -> usize {
        self.levels * self.features_per_level
    }

    /// Rows of one level's table.
    pub fn table_size(&self) -> usize {
        1usize << self.log2_table_size
    }

    /// Cells per axis of level `l`.
    pub fn resolution(&self, level: usize) -> u32 {
        if self.levels <= 1 {
            return self.base_resolution;
        }
        let growth = ((self.max_resolution as f64).ln() - (self.base_resolution as f64).ln())
            / (self.levels - 1) as f64;
        ((self.base_resolution as f64) * (growth * level as f64).exp()).floor() as u32
    }

    /// Checks the ranges; errors name the field.
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.levels == 0 || self.features_per_level == 0 {
            return Err(invalid(
                "`field.grid.levels` and `field.grid.features_per_level` must be >= 1",
            ));
        }
        if !(4..=24).contains(&self.log2_table_size) {
            return Err(invalid("`field.grid.log2_table_size` must be in 4..=24"));
        }
        if self.base_resolution == 0 || self.max_resolution < self.base_resolution {
            return Err(invalid(
                "`field.grid.base_resolution` must be >= 1 and <= `field.grid.max_resolution`",
            ));
        }
        Ok(())
    }
}

/// Hyper-parameters of the field (a stage parameter: serde, defaults, unknown keys rejected).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct FieldConfig {
    /// Position encoding: `grid` (fast, default) or `pe` (the paper's; burn engines only).
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
    /// What the colour head sees in the sky interval: `field` (the paper) or `direction`.
    /// `direction` ([`SkyColourInput::Direction`]) is for cameras without pseudo labels.
    pub sky_colour: SkyColourInput,
    /// Metres around the camera centres that the field's box reaches; 0: the primitives' bounds.
    /// The box, which the grid's resolution spans, is the primitives' bounds clipped to this.
    /// A street's primitives reach hundreds of metres (far terrain), but the labelled geometry
    /// lies near the cameras: spread over 950 m, the finest cells would be too coarse for a wall.
    pub margin: f32,
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
            sky_colour: SkyColourInput::Field,
            margin: 50.0,
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
    pub fn validate(&self) -> Result<(), ModelError> {
        if self.encoding == EncodingKind::Grid {
            self.grid.validate()?;
        }
        if self.hidden == 0 || self.geo_features == 0 {
            return Err(invalid(
                "`field.hidden` and `field.geo_features` must be >= 1",
            ));
        }
        if self.pe_position_frequencies > 20 || self.pe_direction_frequencies > 20 {
            return Err(invalid("`field.pe_position_frequencies` and `field.pe_direction_frequencies` must be <= 20"));
        }
        if !self.density_shift.is_finite() {
            return Err(invalid("`field.density_shift` must be finite"));
        }
        if !(self.margin.is_finite() && self.margin >= 0.0) {
            return Err(invalid(format!(
                "`field.margin`: {} must be finite and >= 0",
                self.margin
            )));
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
    pub fn validate(&self) -> Result<(), ModelError> {
        self.config.validate()?;
        if self.num_classes < 2 {
            return Err(invalid(format!(
                "num_classes is {}; need at least one scene class plus sky",
                self.num_classes
            )));
        }
        for a in 0..3 {
            if self.aabb_max[a] <= self.aabb_min[a]
                || !self.aabb_min[a].is_finite()
                || !self.aabb_max[a].is_finite()
            {
                return Err(invalid(format!(
                    "aabb axis {a}: min {} must be < max {} and finite",
                    self.aabb_min[a], self.aabb_max[a]
                )));
            }
        }
        Ok(())
    }

    /// Scene coordinate `x` on `axis` mapped to `[0, 1]` over the AABB (clamped; 0.5 if not
    /// finite).
    #[inline(always)]
    pub fn unit_coordinate(&self, axis: usize, x: f32) -> f32 {
        let u = (x - self.aabb_min[axis]) / (self.aabb_max[axis] - self.aabb_min[axis]);
        if u.is_finite() {
            u.clamp(0.0, 1.0)
        } else {
            0.5
        }
    }
}

/// Width of the positional encoding of `dims`-vectors with `frequencies` octaves.
pub fn pe_dim(dims: usize, frequencies: usize) -> usize {
    dims * (1 + 2 * frequencies)
}

/// Each term's weight (0 turns a term off: it is then not even computed) and its settings.
///
/// The semantic terms default to 0.1 against L_rgb (the paper writes 1, the published code
/// 0.01): best at 1/8 scale; the full-size pipelines set the paper's 1
/// (docs/experiments/semantic-weight.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct Losses {
    /// Weight of L_fixed2D, -log S_hat(pseudo label): semantically guided geometry.
    pub fixed_2d: f32,
    /// Weight of L_learned2D, u(r) * -log S(pseudo label).
    pub learned_2d: f32,
    /// Weight of L_3D, the learned semantics' cross-entropy to the fixed field's, per point.
    /// Only at points whose primitive class is unique and whose density exceeds
    /// `sigma_threshold`.
    pub point_3d: f32,
    /// Weight of L_rgb, the squared colour error.
    pub rgb: f32,
    /// Weight of L_depth, the squared error to the stereo depth (paper: 0.1).
    pub depth: f32,
    /// Weight of L_sky, a sky prior for rays without pseudo labels (not in the paper; 0 = off).
    /// On those rays (cameras without a 2D network) it is `g(r) (1 - S_hat(sky))`, with the gate
    /// `g(r) = exp(-|C* - C_sky|^2 / sky_prior_colour^2)` and `C_sky` the mean colour of the ray's
    /// sky samples (detached): it prefers the sky interval where the ray's colour is the sky's.
    /// Use with `field.sky_colour: direction`.
    pub sky_prior: f32,
    /// The 2D label terms' `-log(p + label_eps)`: bounds the pull of any one label to 1/label_eps.
    /// The labels the rendering contradicts most are mostly wrong pseudo labels; unbounded, they
    /// carve the geometry (docs/experiments/depth-drift.md).
    pub label_eps: f32,
    /// sigma_th of L_3D's point mask (paper: 0.1).
    pub sigma_threshold: f32,
    /// Colour distance (RGB in [0, 1]) at which the gate of `sky_prior` falls to 1/e.
    pub sky_prior_colour: f32,
    /// Classes (KITTI-360 names) whose rays get L_depth; empty: every ray with a stereo depth.
    /// A ray gets it when it crosses a primitive of one of them: the published code's per-scene
    /// `depth_object` (e.g. parking, wall, gate). Empty is the paper's form.
    pub depth_classes: Vec<String>,
    /// Learn a colour gain per training image (per channel) for L_rgb; engine `fused` only.
    /// It scales the image's rendered colour in L_rgb and in the gate of `sky_prior`: cameras
    /// expose frames differently, and without it the field explains that with floaters.
    /// Rendering shows the field's own colour.
    pub exposure: bool,
}

impl Default for Losses {
    fn default() -> Self {
        Self {
            fixed_2d: 0.1,
            learned_2d: 0.1,
            point_3d: 0.1,
            rgb: 1.0,
            depth: 0.1,
            sky_prior: 0.0,
            label_eps: 0.3,
            sigma_threshold: 0.1,
            sky_prior_colour: 0.1,
            depth_classes: Vec::new(),
            exposure: false,
        }
    }
}

impl Losses {
    /// Weight of `term`.
    pub fn get(&self, term: LossTerm) -> f32 {
        match term {
            LossTerm::Fixed2d => self.fixed_2d,
            LossTerm::Learned2d => self.learned_2d,
            LossTerm::Point3d => self.point_3d,
            LossTerm::Rgb => self.rgb,
            LossTerm::Depth => self.depth,
            LossTerm::SkyPrior => self.sky_prior,
        }
    }

    /// Terms with a non-zero weight.
    pub fn enabled(&self) -> Vec<LossTerm> {
        LossTerm::ALL
            .into_iter()
            .filter(|&t| self.get(t) != 0.0)
            .collect()
    }

    /// Checks ranges; errors name the parameter (`losses.label_eps`, ...).
    pub fn validate(&self) -> Result<(), ModelError> {
        let invalid = |m: String| Err(ModelError::Param(m));
        for t in LossTerm::ALL {
            let w = self.get(t);
            if !(w.is_finite() && w >= 0.0) {
                return invalid(format!(
                    "`losses.{}`: {w} must be finite and >= 0",
                    t.name()
                ));
            }
        }
        if self.enabled().is_empty() {
            return invalid("every loss weight is 0: nothing to optimise".into());
        }
        if !(self.label_eps.is_finite() && self.label_eps > 0.0 && self.label_eps <= 1.0) {
            return invalid(format!(
                "`losses.label_eps`: {} must be in (0, 1]",
                self.label_eps
            ));
        }
        if !(self.sky_prior_colour.is_finite() && self.sky_prior_colour > 0.0) {
            return invalid(format!(
                "`losses.sky_prior_colour`: {} must be finite and > 0",
                self.sky_prior_colour
            ));
        }
        if !(self.sigma_threshold.is_finite() && self.sigma_threshold >= 0.0) {
            return invalid(format!(
                "`losses.sigma_threshold`: {} must be finite and >= 0",
                self.sigma_threshold
            ));
        }
        Ok(())
    }
}

/// What an engine's trainer is given: the field, the losses and the optimiser, and the length
/// of the run (the learning rate decays over it). The `train` kind builds it from its params.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    pub field: FieldConfig,
    pub losses: Losses,
    pub optimiser: Optimiser,
    /// Optimisation steps.
    pub iterations: usize,
    /// Seed of the initial weights.
    pub seed: u64,
    /// Apply the ray mask u(r) to L_learned2D (false: the ablation "without u(r)").
    pub ray_mask: bool,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            field: FieldConfig::default(),
            losses: Losses::default(),
            optimiser: Optimiser::default(),
            iterations: 1700,
            seed: 0,
            ray_mask: true,
        }
    }
}

impl TrainConfig {
    /// Checks ranges; errors name the parameter.
    pub fn validate(&self) -> Result<(), ModelError> {
        self.field.validate()?;
        self.losses.validate()?;
        self.optimiser.validate()
    }

    /// Learning rate at `iteration`.
    pub fn lr_at(&self, iteration: usize) -> f64 {
        self.optimiser.lr_at(iteration, self.iterations)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_defaults_round_trip_and_reject_unknown_keys() {
        let c = FieldConfig::default();
        c.validate().unwrap();
        let v = serde_json::to_value(&c).unwrap();
        assert_eq!(serde_json::from_value::<FieldConfig>(v).unwrap(), c);
        let partial: FieldConfig =
            serde_json::from_str(r#"{"encoding": "pe", "grid": {"levels": 4}}"#).unwrap();
        assert_eq!(partial.encoding, EncodingKind::Pe);
        assert_eq!(partial.grid.levels, 4);
        assert_eq!(partial.grid.log2_table_size, 16);
        assert!(serde_json::from_str::<FieldConfig>(r#"{"margn": 5}"#).is_err());
        for bad in [-1.0, f32::NAN, f32::INFINITY] {
            let c = FieldConfig {
                margin: bad,
                ..FieldConfig::default()
            };
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains("field.margin"), "{e}");
        }
        let bad = FieldConfig {
            grid: GridConfig {
                log2_table_size: 30,
                ..GridConfig::default()
            },
            ..FieldConfig::default()
        };
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("field.grid.log2_table_size"), "{e}");
    }

    #[test]
    fn train_config_checks_every_group_and_schedules_the_rate() {
        let mut c = TrainConfig::default();
        c.validate().unwrap();
        c.optimiser.lr = -1.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("optimiser.lr"), "{e}");
        let c = TrainConfig {
            iterations: 11,
            optimiser: Optimiser {
                lr: 5e-4,
                lr_final_factor: 0.5,
                ..Optimiser::default()
            },
            ..TrainConfig::default()
        };
        assert_eq!(c.lr_at(0), 5e-4);
        assert!((c.lr_at(10) - 2.5e-4).abs() < 1e-12);
    }

    #[test]
    fn loss_settings_are_checked_by_name() {
        let l = Losses::default();
        l.validate().unwrap();
        assert_eq!(l.enabled().len(), 5, "L_sky is off by default");
        let v = serde_json::to_value(&l).unwrap();
        assert_eq!(serde_json::from_value::<Losses>(v).unwrap(), l);
        assert!(serde_json::from_str::<Losses>(r#"{"fixed2d": 1}"#).is_err());
        for (bad, key) in [
            (
                Losses {
                    depth: -1.0,
                    ..Default::default()
                },
                "losses.depth",
            ),
            (
                Losses {
                    rgb: f32::NAN,
                    ..Default::default()
                },
                "losses.rgb",
            ),
            (
                Losses {
                    label_eps: 0.0,
                    ..Default::default()
                },
                "losses.label_eps",
            ),
            (
                Losses {
                    label_eps: 1.5,
                    ..Default::default()
                },
                "losses.label_eps",
            ),
            (
                Losses {
                    sky_prior_colour: 0.0,
                    ..Default::default()
                },
                "losses.sky_prior_colour",
            ),
            (
                Losses {
                    sigma_threshold: -0.1,
                    ..Default::default()
                },
                "losses.sigma_threshold",
            ),
        ] {
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
        let none = Losses {
            fixed_2d: 0.0,
            learned_2d: 0.0,
            point_3d: 0.0,
            rgb: 0.0,
            depth: 0.0,
            ..Default::default()
        };
        let e = none.validate().unwrap_err().to_string();
        assert!(e.contains("nothing to optimise"), "{e}");
    }
}
