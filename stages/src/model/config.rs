//! The model's parameters as users write them (stage parameters: serde, defaults, unknown keys
//! rejected): the field's architecture ([`FieldConfig`], [`GridConfig`]), what a trained field
//! needs besides its weights ([`FieldSpec`]), and the optimiser and losses ([`TrainConfig`]).
//! Every engine reads these same structs; options an engine lacks are refused by
//! [`crate::model::Engine::supports`].

use serde::{Deserialize, Serialize};

use super::error::ModelError;
use super::loss::LossTerm;

fn invalid(message: impl Into<String>) -> ModelError {
    ModelError::Param(message.into())
}

/// Which position encoding the field uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum EncodingKind {
    /// Multi-resolution hash/dense grid + small MLPs (instant-NGP style): fast.
    #[default]
    Grid,
    /// Sinusoidal positional encoding + a wider MLP (the paper's NeRF).
    Pe,
}

/// What the colour head sees at samples in a ray's sky interval.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
    /// Cells per axis of the finest level (levels are geometric in between). The default, 256,
    /// suits the 1/8-scale scenes: over the field's box (about 120 m) its cells are about 0.5 m,
    /// a pixel's footprint at 30 m. With 512 (0.23 m) the field fitted finer detail than any
    /// pixel resolves, and far, weakly observed geometry drifted with training (standard bench,
    /// 1700 / 6000 steps; 512 -> 256: mIoU 88.2 / 89.2 -> 87.5 / 88.5 and 78.9 / 76.9 -> 80.3 /
    /// 80.3 on the noisier street; depth RMSE against the exact depth 2.76 / 2.88 -> 2.67 /
    /// 2.68 m and 3.50 / 3.65 -> 3.29 / 3.54 m). Full-size images need a finer grid
    /// (`pipelines/kitti360.yaml`).
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
                "grid.levels and grid.features_per_level must be >= 1",
            ));
        }
        if !(4..=24).contains(&self.log2_table_size) {
            return Err(invalid("grid.log2_table_size must be in 4..=24"));
        }
        if self.base_resolution == 0 || self.max_resolution < self.base_resolution {
            return Err(invalid(
                "grid.base_resolution must be >= 1 and <= grid.max_resolution",
            ));
        }
        Ok(())
    }
}

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
    /// What the colour head sees in the sky interval: `field` (default, the paper) or
    /// `direction` ([`SkyColourInput::Direction`]; for cameras without pseudo labels).
    pub sky_colour: SkyColourInput,
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
            return Err(invalid("field.hidden and field.geo_features must be >= 1"));
        }
        if self.pe_position_frequencies > 20 || self.pe_direction_frequencies > 20 {
            return Err(invalid("field.pe_*_frequencies must be <= 20"));
        }
        if !self.density_shift.is_finite() {
            return Err(invalid("field.density_shift must be finite"));
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

/// Weight of each loss term; 0 disables a term (it is then not even computed).
///
/// The semantic terms default to 0.1 against L_rgb: the paper writes 1, the published code 0.01.
/// On the 1/8-scale synthetic streets (three seeds) 0.1 gave the best depth, and the only setting
/// where L_fixed2D improved depth on the noisy street; 0.01 lost 2-6 mIoU. The weight depends on
/// how often each pixel is drawn: at full size, where labels are still being learned, 1 scores
/// better and the full-size pipelines set it (README, "The semantic terms' weight").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LossWeights {
    /// L_fixed2D: -log S_hat(pseudo label) (semantically guided geometry).
    pub fixed_2d: f32,
    /// L_learned2D: u(r) * -log S(pseudo label).
    pub learned_2d: f32,
    /// L_3D: per-point CE(s_hat_i, s_i) where the class is unique and density > sigma_th.
    pub point_3d: f32,
    /// L_rgb: squared colour error.
    pub rgb: f32,
    /// L_depth: squared error to stereo depth (paper: 0.1).
    pub depth: f32,
    /// L_sky (default 0, off; not in the paper): on rays without a pseudo label (cameras
    /// without a 2D network), `g(r) (1 - S_hat(sky))` with the gate `g(r) = exp(-|C* -
    /// C_sky|^2 / sky_prior_colour^2)`, `C_sky` the mean colour of the ray's sky-interval
    /// samples (detached). Where the ray's colour is the sky's, it prefers the sky interval to
    /// sky-coloured density in a coarse primitive; use with `field.sky_colour: direction`, so
    /// `C_sky` is the sky's colour in that direction.
    pub sky_prior: f32,
}

impl Default for LossWeights {
    fn default() -> Self {
        Self {
            fixed_2d: 0.1,
            learned_2d: 0.1,
            point_3d: 0.1,
            rgb: 1.0,
            depth: 0.1,
            sky_prior: 0.0,
        }
    }
}

impl LossWeights {
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
}

/// Parameters of the `train` stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// The field's architecture.
    pub field: FieldConfig,
    /// Loss weights (0 disables a term).
    pub losses: LossWeights,
    /// sigma_th of the L_3D point mask (paper: 0.1).
    pub sigma_threshold: f32,
    /// Colour distance (RGB in [0, 1]) at which the gate of `losses.sky_prior` falls to 1/e.
    pub sky_prior_colour: f32,
    /// Apply the ray mask u(r) to L_learned2D (false: every labelled ray counts; the ablation
    /// "without u(r)").
    pub ray_mask: bool,
    /// Adam learning rate. The paper's 5e-4 suits its 8x256 MLP; the hash grid's tables learn
    /// far slower at that rate. Measured on the default scene (decaying to a tenth): 45.6 mIoU
    /// after 400 steps at 5e-4; after 1700 steps 84.5 at 1e-2, 85.3 at 2e-2, 85.2 at 3e-2;
    /// 86.1 after 6000 steps at 2e-2. Hence 2e-2.
    pub lr: f64,
    /// The learning rate decays exponentially to `lr * lr_final_factor` at the last iteration
    /// (1 = constant; the public code halves it: 0.5).
    pub lr_final_factor: f64,
    /// Clip the global gradient norm to this value (0 disables).
    pub grad_clip_norm: f32,
    /// Adam beta_1.
    pub adam_beta1: f32,
    /// Adam beta_2.
    pub adam_beta2: f32,
    /// Adam epsilon.
    pub adam_epsilon: f32,
    /// Rays per batch (paper: 2048).
    pub rays_per_batch: usize,
    /// Optimisation steps (paper: 80000).
    pub iterations: usize,
    /// Seed of the initial weights and of the ray order.
    pub seed: u64,
    /// Added to a rendered label probability before the log in the two 2D label terms:
    /// `-log(p + label_eps)`. The paper's `-log p` (`label_eps` 1e-6) pulls hardest on the
    /// labels the rendering contradicts most, which with noisy pseudo labels are mostly the
    /// wrong ones: over training it carved the geometry to fit them (depth RMSE inside regions
    /// 0.94 m after 400 steps, 1.68 m after 1700, 1.99 m after 6000 on the default street).
    /// 0.1 bounds that pull to 10 and leaves correct labels' gradients nearly as they were
    /// (standard bench scenes, 1700 steps: mIoU 87.3 -> 88.2 and 77.7 -> 78.9, depth RMSE inside
    /// regions 1.68 -> 1.07 m and 1.12 -> 0.89 m). With the 256-cell grid 0.3 did better still on
    /// the noisier street (0.1 -> 0.3, 1700 / 6000 steps: mIoU 80.3 / 80.3 -> 81.5 / 80.9, depth
    /// RMSE against the exact depth 3.29 / 3.54 -> 3.14 / 3.19 m) and on `street0` 87.5 -> 87.9
    /// mIoU at 2.67 -> 2.75 m: hence 0.3, which bounds the pull to 3.3.
    pub label_eps: f32,
    /// The field's box (which the grid's resolution spans): the primitives' bounds, clipped
    /// to this many metres around the camera centres; points beyond share the features of the
    /// box's boundary. A street's primitives reach hundreds of metres (far terrain) while the
    /// labelled geometry lies near the cameras: spread over 950 m, the grid's finest cells
    /// were 1.9 m wide, too coarse for a wall or a gate. 0 = the primitives' bounds whole.
    pub field_margin: f32,
    /// Cast each training ray through a random point of a window of this width (in pixels,
    /// 0..=1) around its pixel's centre, drawn anew every time the ray is drawn; the targets
    /// stay the pixel's and rendering keeps the centres. At the centre alone (0) every ray
    /// comes back identical, and over many passes the 2D label terms fit the pseudo labels'
    /// boundary mistakes ray by ray, carving the geometry (the noisier 1/8-scale street, seed
    /// 1, exact-depth RMSE 2.91 -> 3.17 m from 1700 to 6000 steps). Seed 1, 1700 -> 6000
    /// steps, m / mIoU: 0.25: 2.86 / 82.2 -> 2.88 / 82.8, and on `street0` at 1700 2.73 m / 89.5
    /// against 2.72 / 89.6; 0.5: 2.75 / 81.5 -> 2.89 / 83.0, `street0` 2.77 / 87.5; 1 (three
    /// seeds): 2.82 / 80.3 -> 2.77 / 81.0, `street0` 3.06 / 83.9 against 2.70 / 89.2. Hence 0.25.
    pub pixel_jitter: f32,
    /// The pseudo label a jittered ray trains on. `pixel`: its own pixel's. `bilinear`: a
    /// neighbour's with the bilinear weight of the ray's point (a ray 0.3 px right of its pixel's
    /// centre takes the right neighbour's label with probability 0.3), drawn anew with the point:
    /// in expectation the cross-entropy against the bilinear mix of the 2 x 2 nearest pixels'
    /// labels, which is what a point-sampled label map says about a point between its samples.
    /// With `pixel_jitter` 0.5 it stops the depth drift of the noisy 1/8-scale streets (three
    /// seeds, exact-depth RMSE 1700 -> 6000 steps: 2.80 -> 2.79 m against the default's 2.83 ->
    /// 2.90; with stereo to 6 m 3.29 -> 3.25) but costs `street0` 0.17 m and 2.3 mIoU at 1700
    /// steps (86.8 against 89.1), hence not the default (README, drift section).
    pub jitter_labels: JitterLabels,
    /// The window and labels of the jittered rays once training has gone over every ray more
    /// than `after_passes` times (`null`: never). Late passes over few pixels fit the pseudo
    /// labels' boundary mistakes ray by ray and the depth drifts (README, drift section); a
    /// 0.5-px window with `bilinear` labels stops that, but from the start it costs `street0`
    /// 2.3 mIoU at the default budget. After 8 passes it leaves the default budget (7.7
    /// passes on the 1/8-scale street) as it was; a full-size run (0.12 passes) never gets there.
    pub late_jitter: Option<LateJitter>,
    /// Learn a colour gain per training image (per channel, starting at 1) that scales the
    /// rendered colour of its rays in L_rgb and in the gate of `losses.sky_prior`: cameras
    /// expose each frame differently (auto exposure), and without it the field explains one
    /// surface's brighter and darker images with floaters in front of it, or takes a
    /// brighter-than-usual sky for something else. Rendering shows the field's own colour.
    /// The fused engine only. Off by default (the paper has none).
    #[serde(skip_serializing_if = "is_false")]
    pub exposure: bool,
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// See [`TrainConfig::late_jitter`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LateJitter {
    /// Passes over the training rays (iterations x rays per batch / training rays) after which
    /// the two settings below replace `pixel_jitter` and `jitter_labels`.
    pub after_passes: f32,
    /// Window width in pixels, as `pixel_jitter`.
    pub pixel_jitter: f32,
    /// Labels of the jittered rays, as `jitter_labels`.
    pub jitter_labels: JitterLabels,
}

impl Default for LateJitter {
    fn default() -> Self {
        Self {
            after_passes: 8.0,
            pixel_jitter: 0.5,
            jitter_labels: JitterLabels::Bilinear,
        }
    }
}

/// See [`TrainConfig::jitter_labels`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JitterLabels {
    #[default]
    Pixel,
    Bilinear,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            field: FieldConfig::default(),
            losses: LossWeights::default(),
            sigma_threshold: 0.1,
            sky_prior_colour: 0.1,
            ray_mask: true,
            lr: 2e-2,
            lr_final_factor: 0.1,
            grad_clip_norm: 1.0,
            adam_beta1: 0.9,
            adam_beta2: 0.999,
            adam_epsilon: 1e-8,
            rays_per_batch: 1024,
            iterations: 1700,
            seed: 0,
            field_margin: 50.0,
            label_eps: 0.3,
            pixel_jitter: 0.25,
            jitter_labels: JitterLabels::Pixel,
            late_jitter: Some(LateJitter::default()),
            exposure: false,
        }
    }
}

/// The window and labels of `pixel_jitter` / `jitter_labels` (under `prefix`) make sense.
fn check_jitter(prefix: &str, width: f32, labels: JitterLabels) -> Result<(), ModelError> {
    if !(width.is_finite() && (0.0..=1.0).contains(&width)) {
        return Err(invalid(format!(
            "{prefix}pixel_jitter = {width} must be in [0, 1] (pixels)"
        )));
    }
    if labels == JitterLabels::Bilinear && width == 0.0 {
        return Err(invalid(format!(
            "{prefix}jitter_labels = bilinear labels jittered rays by their point, but \
             {prefix}pixel_jitter = 0 casts every ray through its pixel's centre: set it > 0 \
             (e.g. 0.5)"
        )));
    }
    Ok(())
}

impl TrainConfig {
    /// The jitter window (pixels) and labels of a batch drawn after `passes` passes over the
    /// training rays.
    pub fn jitter_at(&self, passes: f64) -> (f32, JitterLabels) {
        match &self.late_jitter {
            Some(late) if passes >= late.after_passes as f64 => {
                (late.pixel_jitter, late.jitter_labels)
            }
            _ => (self.pixel_jitter, self.jitter_labels),
        }
    }

    /// Checks ranges; errors name the parameter.
    pub fn validate(&self) -> Result<(), ModelError> {
        self.field.validate()?;
        for t in LossTerm::ALL {
            let w = self.losses.get(t);
            if !(w.is_finite() && w >= 0.0) {
                return Err(invalid(format!(
                    "losses.{} = {w} must be finite and >= 0",
                    t.name()
                )));
            }
        }
        if !(self.label_eps.is_finite() && self.label_eps > 0.0 && self.label_eps <= 1.0) {
            return Err(invalid(format!(
                "label_eps = {} must be in (0, 1]",
                self.label_eps
            )));
        }
        check_jitter("", self.pixel_jitter, self.jitter_labels)?;
        if let Some(late) = &self.late_jitter {
            if !(late.after_passes.is_finite() && late.after_passes >= 0.0) {
                return Err(invalid(format!(
                    "late_jitter.after_passes = {} must be finite and >= 0",
                    late.after_passes
                )));
            }
            check_jitter("late_jitter.", late.pixel_jitter, late.jitter_labels)?;
        }
        if !(self.field_margin.is_finite() && self.field_margin >= 0.0) {
            return Err(invalid(format!(
                "field_margin = {} must be finite and >= 0",
                self.field_margin
            )));
        }
        if self.losses.enabled().is_empty() {
            return Err(invalid("every loss weight is 0: nothing to optimise"));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(invalid(format!("lr = {} must be > 0", self.lr)));
        }
        if !(self.lr_final_factor.is_finite() && self.lr_final_factor > 0.0) {
            return Err(invalid(format!(
                "lr_final_factor = {} must be > 0",
                self.lr_final_factor
            )));
        }
        if !(self.grad_clip_norm.is_finite() && self.grad_clip_norm >= 0.0) {
            return Err(invalid(format!(
                "grad_clip_norm = {} must be >= 0",
                self.grad_clip_norm
            )));
        }
        if !(0.0..1.0).contains(&self.adam_beta1) || !(0.0..1.0).contains(&self.adam_beta2) {
            return Err(invalid("adam_beta1 and adam_beta2 must be in [0, 1)"));
        }
        if !(self.adam_epsilon.is_finite() && self.adam_epsilon > 0.0) {
            return Err(invalid("adam_epsilon must be > 0"));
        }
        if self.rays_per_batch == 0 {
            return Err(invalid("rays_per_batch must be >= 1"));
        }
        if !(self.sky_prior_colour.is_finite() && self.sky_prior_colour > 0.0) {
            return Err(invalid("sky_prior_colour must be finite and > 0"));
        }
        if !(self.sigma_threshold.is_finite() && self.sigma_threshold >= 0.0) {
            return Err(invalid("sigma_threshold must be finite and >= 0"));
        }
        Ok(())
    }

    /// Learning rate at `iteration`.
    pub fn lr_at(&self, iteration: usize) -> f64 {
        let progress = iteration as f64 / self.iterations.saturating_sub(1).max(1) as f64;
        self.lr * self.lr_final_factor.powf(progress.min(1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_defaults_round_trip_and_reject_unknown_keys() {
        let c = TrainConfig::default();
        c.validate().unwrap();
        let v = serde_json::to_value(&c).unwrap();
        assert_eq!(serde_json::from_value::<TrainConfig>(v).unwrap(), c);
        let partial: TrainConfig =
            serde_json::from_str(r#"{"iterations": 5, "field": {"encoding": "pe"}}"#).unwrap();
        assert_eq!(partial.iterations, 5);
        assert_eq!(partial.field.encoding, EncodingKind::Pe);
        assert!(serde_json::from_str::<TrainConfig>(r#"{"iteration": 5}"#).is_err());
        let bad = TrainConfig {
            lr: -1.0,
            ..Default::default()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("lr"));
        for jitter in [-0.1, 1.5, f32::NAN] {
            let bad = TrainConfig {
                pixel_jitter: jitter,
                ..Default::default()
            };
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains("pixel_jitter"), "{e}");
        }
        for jitter in [0.0, 1.0] {
            let ok = TrainConfig {
                pixel_jitter: jitter,
                ..Default::default()
            };
            ok.validate().unwrap();
        }
        let idle = TrainConfig {
            pixel_jitter: 0.0,
            jitter_labels: JitterLabels::Bilinear,
            ..Default::default()
        };
        let e = idle.validate().unwrap_err().to_string();
        assert!(
            e.contains("jitter_labels") && e.contains("pixel_jitter"),
            "{e}"
        );
        let e = serde_json::from_str::<TrainConfig>(r#"{"jitter_labels": "bilinar"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bilinar") && e.contains("bilinear"), "{e}");
    }

    #[test]
    fn late_jitter_takes_over_after_its_passes_and_is_checked() {
        let c = TrainConfig::default();
        assert_eq!(c.jitter_at(0.0), (0.25, JitterLabels::Pixel));
        assert_eq!(c.jitter_at(7.99), (0.25, JitterLabels::Pixel));
        assert_eq!(c.jitter_at(8.0), (0.5, JitterLabels::Bilinear));
        let off: TrainConfig = serde_json::from_str(r#"{"late_jitter": null}"#).unwrap();
        assert_eq!(off.jitter_at(1e6), (0.25, JitterLabels::Pixel));
        // Settings not given keep their defaults (`--set train.train.late_jitter.after_passes=12`).
        let partial: TrainConfig =
            serde_json::from_str(r#"{"late_jitter": {"after_passes": 2}}"#).unwrap();
        assert_eq!(partial.jitter_at(2.0), (0.5, JitterLabels::Bilinear));
        assert_eq!(partial.jitter_at(1.9), (0.25, JitterLabels::Pixel));
        assert!(serde_json::from_str::<TrainConfig>(r#"{"late_jitter": {"after": 2}}"#).is_err());
        for (late, key) in [
            (
                LateJitter {
                    after_passes: f32::NAN,
                    ..Default::default()
                },
                "late_jitter.after_passes",
            ),
            (
                LateJitter {
                    pixel_jitter: 2.0,
                    ..Default::default()
                },
                "late_jitter.pixel_jitter",
            ),
            (
                LateJitter {
                    pixel_jitter: 0.0,
                    ..Default::default()
                },
                "late_jitter.jitter_labels",
            ),
        ] {
            let bad = TrainConfig {
                late_jitter: Some(late),
                ..Default::default()
            };
            let e = bad.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
    }

    #[test]
    fn lr_decays_to_the_final_factor() {
        let c = TrainConfig {
            lr: 5e-4,
            lr_final_factor: 0.5,
            iterations: 11,
            ..Default::default()
        };
        assert_eq!(c.lr_at(0), 5e-4);
        assert!((c.lr_at(10) - 2.5e-4).abs() < 1e-12);
        assert!(c.lr_at(5) < 5e-4 && c.lr_at(5) > 2.5e-4);
    }
}
