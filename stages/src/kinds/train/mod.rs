//! The `train` stage kind: fits the radiance field with dual semantic fields to one scene.
//! Rays come from the `intersect` stage's sampling plan (samples only inside primitives plus the
//! sky interval, re-jittered every iteration); targets from the scene (RGB, pseudo labels,
//! stereo depth). Writes the weights as `(name, shape, values)` rows readable by pyarrow, the
//! model description needed to rebuild the field, and the training log. The model itself is
//! [`crate::model`]'s; this is glue between tables, the sampler and the engine.

use crate::stage::{
    Changed, InputSlot, Inputs, Lineage, Previous, Progress, Result, StageError, Tables,
    TypedStage, Updated,
};

mod fit;
mod params;
mod update;

pub use fit::spec_for;
pub use params::{Experimental, TrainParams, UpdateParams};

pub struct Train;

impl TypedStage for Train {
    type Params = TrainParams;
    const KIND: &'static str = "train";
    // 17: rays that cross a moving object's box (the scene's `dynamic_boxes`) at their own
    // frame are left out; the same weights for a scene without moving objects.
    // 16: parameters grouped (schedule, field, sampling, losses, optimiser, experimental) and
    // `cameras` defaulting to the plan's; the same weights for the same settings.
    // 15: the train log has a `loss_sky_prior` column (null unless `losses.sky_prior` > 0).
    // 14: the train log has no wall-clock column (the same seed and config give the same bytes;
    // the runner times the stage); `late_jitter` (on by default) changes runs past 8 passes.
    const VERSION: u32 = 18;
    const DESCRIPTION: &'static str =
        "fits the radiance field with dual semantic fields (L_fixed2D, L_learned2D, L_3D, L_rgb, L_depth)";
    const INPUTS: &'static [InputSlot] = &[
        InputSlot {
            name: "scene",
            tables: &[
                "cameras",
                "primitives",
                "dynamic_boxes",
                "images",
                "pseudo_labels",
                "stereo_depth",
            ],
            optional: false,
            doc: "posed images, primitives (and moving objects' boxes, whose rays are left \
                  out), pseudo labels and stereo depth",
        },
        InputSlot {
            name: "rays",
            tables: &["ray_intervals"],
            optional: false,
            doc: "the sampling plan",
        },
        InputSlot {
            name: "depth",
            tables: &["stereo_depth"],
            optional: true,
            doc: "stereo depth for L_depth (default: the scene's own stereo_depth table)",
        },
    ];
    const OUTPUTS: &'static [&'static str] = &["weights", "model", "train_log"];
    const BUDGET_PARAM: Option<&'static str> = Some("schedule.iterations");
    const UPDATES: bool = true;
    // 1: an update draws the rest of each batch from a uniform sample of the candidate rays
    // (as many as it draws) instead of a shuffle of all of them.
    const UPDATE_VERSION: u32 = 1;
    const PARENT_INPUTS: &'static [(&'static str, &'static str)] = &[("scene", "primitives")];
    const UPDATE_ONLY: &'static [&'static str] = &["update"];
    const MOVED: &'static [(&'static str, &'static str)] = params::MOVED;

    fn validate(p: &TrainParams) -> Result<()> {
        p.schedule.validate()?;
        p.update.validate()?;
        let config = p.model_config();
        config.validate()?;
        p.sampling.validate()?;
        p.sampling_params().validate()?;
        if p.cameras.iter().any(|&c| c > 3) {
            return Err(StageError::Params(
                "`cameras` must list KITTI-360 cameras 0 .. 3 (2, 3: the fisheye cameras)".into(),
            ));
        }
        p.backend.supports(&p.field)?;
        p.backend.supports_train(&config)?;
        p.depth_class_ids()?;
        Ok(())
    }

    fn run(&self, p: &TrainParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        fit::from_scratch(p, inputs, progress)
    }

    /// After an edit of the primitives alone, trains on from the previous weights.
    fn can_update(
        &self,
        _: &TrainParams,
        changed: &Changed,
        lineage: &Lineage,
    ) -> std::result::Result<(), String> {
        update::can_update(changed, lineage)
    }

    fn update(
        &self,
        p: &TrainParams,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated> {
        update::update(p, inputs, previous, progress)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::DVec3;
    use crate::labels;
    use crate::model::TrainConfig;
    use crate::sampling::PrimInfo;

    fn prims(lo: [f32; 3], hi: [f32; 3]) -> PrimInfo {
        PrimInfo {
            classes: vec![7, 23],
            bounds_min: lo,
            bounds_max: hi,
            ..PrimInfo::default()
        }
    }

    /// A street's far terrain reaches 450 m; cameras drive x in 0..20 at y = 0, z = 1.6.
    #[test]
    fn the_field_box_is_the_primitives_clipped_around_the_cameras() {
        let p = prims([-450.0, -450.0, -1.5], [500.0, 450.0, 18.5]);
        let cams = [DVec3::new(0.0, 0.0, 1.6), DVec3::new(20.0, 0.0, 1.6)];
        let config = TrainConfig::default();
        assert_eq!(config.field.margin, 50.0);
        let s = spec_for(&p, &cams, &config);
        assert_eq!(s.aabb_min, [-50.0, -50.0, -2.5]);
        assert_eq!(s.aabb_max, [70.0, 50.0, 19.5]);
        // 0 keeps the primitives' (padded) bounds, as do scenes with no camera.
        let mut whole = config.clone();
        whole.field.margin = 0.0;
        let s = spec_for(&p, &cams, &whole);
        assert_eq!(s.aabb_min, [-451.0, -451.0, -2.5]);
        assert_eq!(s.aabb_max, [501.0, 451.0, 19.5]);
        assert_eq!(spec_for(&p, &[], &config).aabb_max, [501.0, 451.0, 19.5]);
        // Primitives wholly beyond the margin on an axis keep their own extent there.
        let far = prims([200.0, -5.0, 0.0], [210.0, 5.0, 3.0]);
        let s = spec_for(&far, &cams, &config);
        assert_eq!((s.aabb_min[0], s.aabb_max[0]), (199.0, 211.0));
        assert_eq!((s.aabb_min[1], s.aabb_max[1]), (-6.0, 6.0));
        s.validate().unwrap();
    }

    /// The `update` group says only how an update works: the kind names it update-only (the
    /// runner leaves it out of a run from scratch's key), and the canonical params keep its
    /// values, which the stage needs when it updates.
    #[test]
    fn update_params_are_update_only_and_reach_the_stage() {
        use crate::Stage;
        assert_eq!(Train.update_only_params(), &["update"]);
        let canonical = |v: serde_json::Value| Train.canonical_params(&v).unwrap();
        let plain = canonical(serde_json::json!({}));
        assert_eq!(plain["update"]["iterations"], 400);
        let set = canonical(serde_json::json!({"update": {"iterations": 50}}));
        assert_eq!(set["update"]["iterations"], 50);
        assert_eq!(
            canonical(plain.clone()),
            plain,
            "canonical params are a fixed point"
        );
        let bad = Train
            .canonical_params(&serde_json::json!({"update": {"edited_share": 1.5}}))
            .unwrap_err()
            .to_string();
        assert!(
            bad.contains("`update.edited_share`: 1.5 must be in 0..=1"),
            "{bad}"
        );
        let bad = Train
            .canonical_params(&serde_json::json!({"update": {"removal_iterations": 0}}))
            .unwrap_err()
            .to_string();
        assert!(
            bad.contains("`update.removal_iterations`: 0 must be at least 1"),
            "{bad}"
        );
    }

    /// `depth_classes` resolves names and refuses unknown ones by name.
    #[test]
    fn depth_classes_are_named_and_checked() {
        let mut p = TrainParams::default();
        p.losses.depth_classes = vec!["parking".into(), "wall".into(), "gate".into()];
        assert_eq!(
            p.depth_class_ids().unwrap(),
            [labels::PARKING, labels::WALL, labels::GATE]
        );
        Train::validate(&p).unwrap();
        let json = serde_json::to_value(&p).unwrap();
        assert_eq!(json["losses"]["depth_classes"][2], "gate");
        for bad in ["parkng", "sky"] {
            let mut q = TrainParams::default();
            q.losses.depth_classes = vec![bad.into()];
            let e = Train::validate(&q).unwrap_err().to_string();
            assert!(e.contains("losses.depth_classes") && e.contains(bad), "{e}");
        }
    }
}
