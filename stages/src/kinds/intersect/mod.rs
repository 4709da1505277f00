//! The `intersect` kind: the sampling plan of Panoptic NeRF ([`crate::intervals`]) for every
//! pixel of the selected images, and first-hit previews.

use std::path::{Path, PathBuf};

use crate::geometry::{self, Bvh};
use crate::intervals::{first_hit_images, plan_image, plan_row, IntersectParams};
use crate::stage::{
    Changed, InputSlot, Inputs, Lineage, Previous, Progress, Result, StageError, TableSet, Tables,
    TypedStage, Updated,
};

mod update;

pub struct Intersect;

impl TypedStage for Intersect {
    type Params = IntersectParams;
    const KIND: &'static str = "intersect";
    // 4: `cameras` defaults to every camera of the scene (the same plan for the same cameras).
    // 5: an update after a reordering of the primitives keeps tied entries in trace order.
    const VERSION: u32 = 5;
    const DESCRIPTION: &'static str =
        "ray-primitive intervals of every pixel (the first k per ray, plus a sky interval)";
    const INPUTS: &'static [InputSlot] = &[InputSlot {
        name: "scene",
        tables: &["cameras", "primitives"],
        optional: false,
        doc: "posed cameras and 3D bounding primitives",
    }];
    const OUTPUTS: &'static [&'static str] = &["ray_intervals"];
    const UPDATES: bool = true;
    const PARENT_INPUTS: &'static [(&'static str, &'static str)] = &[("scene", "primitives")];

    fn validate(p: &IntersectParams) -> Result<()> {
        if !(1..=255).contains(&p.k) {
            return Err(StageError::Params(format!(
                "`k` must be in 1..=255, got {}",
                p.k
            )));
        }
        if !(p.sky_interval.is_finite() && p.sky_interval > 0.0) {
            return Err(StageError::Params(format!(
                "`sky_interval` must be a positive number of metres, got {}",
                p.sky_interval
            )));
        }
        if !(p.far.is_finite() && p.far > 0.0) {
            return Err(StageError::Params(format!(
                "`far` must be a positive number of metres, got {}",
                p.far
            )));
        }
        if p.cameras.iter().any(|&c| c > 3) {
            return Err(StageError::Params(
                "`cameras` must list KITTI-360 cameras 0 .. 3 (2, 3: the fisheye cameras)".into(),
            ));
        }
        Ok(())
    }

    fn run(&self, p: &IntersectParams, inputs: &Inputs, progress: &dyn Progress) -> Result<Tables> {
        let prims = geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
        let rows = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
        let rows = update::selected_rows(&rows, p)?;
        let bvh = Bvh::build(&prims);
        let total = rows.len() as u64;
        // One image at a time, each row stored as it is planned: the plan of a full-size scene
        // (68 M rays) is gigabytes.
        let mut out = inputs.writer("ray_intervals")?;
        for (i, row) in rows.into_iter().enumerate() {
            progress.update(
                i as u64,
                total,
                &format!("frame {} camera {}", row.frame, row.camera),
            );
            out.write(plan_row(row, plan_image(&prims, &bvh, &row.cam, p), p)?)?;
        }
        progress.update(total, total, "done");
        let mut tables = Tables::new();
        out.finish_into(&mut tables)?;
        Ok(tables)
    }

    /// After an edit of the primitives alone, intersects again only the images that can see it.
    fn can_update(
        &self,
        _: &IntersectParams,
        changed: &Changed,
        _: &Lineage,
    ) -> std::result::Result<(), String> {
        update::can_update(changed)
    }

    fn update(
        &self,
        p: &IntersectParams,
        inputs: &Inputs,
        previous: &Previous,
        progress: &dyn Progress,
    ) -> Result<Updated> {
        update::update(p, inputs, previous, progress)
    }

    fn export(&self, p: &IntersectParams, t: &TableSet, dir: &Path) -> Result<Vec<PathBuf>> {
        let table = t
            .get("ray_intervals")
            .ok_or_else(|| StageError::Input("missing table `ray_intervals`".into()))?;
        let out_dir = dir.join("first_hit");
        std::fs::create_dir_all(&out_dir)
            .map_err(|e| StageError::Failed(format!("creating {}: {e}", out_dir.display())))?;
        let mut written = Vec::new();
        for r in 0..table.num_rows() {
            for img in first_hit_images(&table.row(r)?, p.far)? {
                let path = out_dir.join(format!("{:010}_{}.png", img.frame, img.camera));
                img.image
                    .save(&path)
                    .map_err(|e| StageError::Failed(format!("writing {}: {e}", path.display())))?;
                written.push(path);
            }
        }
        Ok(written)
    }
}

#[cfg(test)]
mod tests;
