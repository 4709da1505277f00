//! An edit of the primitives updates the stages that can update (their previous entry is the
//! parent) instead of computing them from scratch: the result is the from-scratch result's
//! bytes, the same parent and edit give the same entry in any cache, `pipe status` and the run
//! log say what was updated, and a changed pose falls back to a run from scratch.

mod common;

use std::fs;

use common::{Workspace, EDIT_PIPELINE};
use pipe::runner::{Outcome, RunReport};

const PIPELINE: &str = "
stages:
  scene:
    uses: synthetic_scene
    params: {frames: 6, scale: 0.0625}
  depth:
    uses: stereo_depth
    inputs: {scene: scene}
  rays:
    uses: intersect
    inputs: {scene: scene}
";

/// Primitive 57 of the default street (a small thing beside the road) scaled up by a fifth.
const EDIT: &str = "scene.edits=[{primitive: 57, scale: [1.2, 1.2, 1.2]}]";

fn manifest(ws: &Workspace, key: &str) -> serde_json::Value {
    let path = ws.cache().join("objects").join(key).join("manifest.json");
    serde_json::from_slice(&fs::read(path).unwrap()).unwrap()
}

/// (outcome, reason) of `stage` in the last run.
fn last(ws: &Workspace, stage: &str) -> (Outcome, String) {
    let rep: RunReport =
        serde_json::from_slice(&fs::read(ws.cache().join("runs/last-run.json")).unwrap()).unwrap();
    let s = rep.stages.into_iter().find(|s| s.stage == stage).unwrap();
    (s.outcome, s.reason)
}

#[test]
fn an_edit_updates_rays_and_depth_to_the_bytes_of_a_cold_run() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);
    let parent = ws.stage_key("rays");
    let scene_parent = ws.stage_key("scene");
    // Once the edited scene is read, status knows what rays will update from.
    ws.run_ok(&["--set", EDIT, "--until", "scene"]);
    // The scene itself: only the annotation is written again, the rest is the parent's files.
    let (outcome, why) = last(&ws, "scene");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert!(
        why.starts_with(&format!(
            "updated from {}: the annotation edited",
            &scene_parent[..8]
        )),
        "{why}"
    );
    let scene_updated = ws.stage_key("scene");
    let (before, after) = (manifest(&ws, &scene_parent), manifest(&ws, &scene_updated));
    for table in ["images", "gt_semantic", "pseudo_labels", "cameras"] {
        let file = format!("{table}.parquet");
        assert_eq!(before["files"][&file], after["files"][&file], "{table}");
    }
    assert_ne!(
        before["files"]["primitives.parquet"],
        after["files"]["primitives.parquet"]
    );
    let status = ws.status(&["--set", EDIT]);
    let line = ws.status_line(&status, "rays");
    assert!(
        line.contains("stale") && line.contains(&format!("will update entry {}", &parent[..8])),
        "{line}"
    );
    assert!(line.contains("`scene`.primitives changed"), "{line}");

    let out = ws.run_ok(&["--set", EDIT]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Updated, "{out}");
    assert!(
        why.starts_with(&format!("updated from {}: ", &parent[..8])),
        "{why}"
    );
    assert!(
        why.contains(" of 12 images intersected again, ")
            && why.contains(" % of their pixels (1 primitive changed)"),
        "{why}"
    );
    assert!(
        out.contains("updated "),
        "the summary names the outcome:\n{out}"
    );
    // Depth depends on the images alone: the update takes the previous maps.
    let (outcome, why) = last(&ws, "depth");
    assert_eq!(outcome, Outcome::Updated);
    assert!(why.ends_with("0 of 6 pairs matched again"), "{why}");
    let status = ws.status(&["--set", EDIT]);
    let line = ws.status_line(&status, "rays");
    assert!(
        line.contains("fresh") && line.contains(&format!("updated from {}: ", &parent[..8])),
        "{line}"
    );
    let updated = ws.stage_key("rays");
    let m = manifest(&ws, &updated);
    assert_eq!(m["parent"], parent.as_str());
    // Once more: nothing to do.
    ws.run_ok(&["--set", EDIT]);
    assert_eq!(last(&ws, "rays").0, Outcome::Cached);
    // Forced, the stage computes its entry again the same way: an update of the same parent.
    ws.run_ok(&["--set", EDIT, "--force", "rays"]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert_eq!(ws.stage_key("rays"), updated);
    assert_eq!(manifest(&ws, &updated)["output_digest"], m["output_digest"]);

    // The same edit from scratch: another key, the same bytes.
    ws.run_ok(&["--set", EDIT, "--cold"]);
    assert_eq!(last(&ws, "rays").0, Outcome::Ran);
    let cold = ws.stage_key("rays");
    assert_ne!(cold, updated);
    let read = |k: &str| {
        fs::read(
            ws.cache()
                .join("objects")
                .join(k)
                .join("ray_intervals.parquet"),
        )
        .unwrap()
    };
    assert!(
        read(&cold) == read(&updated),
        "the update's bytes differ from the cold run's"
    );
    assert_eq!(manifest(&ws, &cold)["output_digest"], m["output_digest"]);
    // The scene from scratch: the updated scene's bytes.
    assert_eq!(last(&ws, "scene").0, Outcome::Ran);
    assert_eq!(
        manifest(&ws, &ws.stage_key("scene"))["output_digest"],
        after["output_digest"]
    );
    // Forced after that run from scratch: from scratch again (there is nothing to update).
    ws.run_ok(&["--set", EDIT, "--force", "rays"]);
    assert_eq!(last(&ws, "rays").0, Outcome::Ran);
    assert_eq!(ws.stage_key("rays"), cold);

    // A removal renumbers the ids after it in every image's plan (rows the update copies with
    // their `prim` column replaced): still the bytes of a run from scratch.
    const REMOVE: &str = "scene.edits=[{primitive: 57, remove: true}]";
    ws.run_ok(&["--set", REMOVE]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    let removed = ws.stage_key("rays");
    // Back to it after another configuration ran: its entry, cached; forced, an update of its
    // own parent again (not of the other configuration's entry).
    ws.run_ok(&[]);
    ws.run_ok(&["--set", REMOVE]);
    assert_eq!(last(&ws, "rays").0, Outcome::Cached);
    assert_eq!(ws.stage_key("rays"), removed);
    ws.run_ok(&[]);
    ws.run_ok(&["--set", REMOVE, "--force", "rays"]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert_eq!(ws.stage_key("rays"), removed);
    ws.run_ok(&["--set", REMOVE, "--cold"]);
    assert!(
        read(&ws.stage_key("rays")) == read(&removed),
        "after a removal the update's bytes differ from the cold run's"
    );

    // The same parent and the same edit in another cache: the same key and bytes.
    let other = Workspace::new(PIPELINE);
    other.run_ok(&[]);
    assert_eq!(other.stage_key("rays"), parent);
    other.run_ok(&["--set", EDIT]);
    assert_eq!(other.stage_key("rays"), updated);
    assert_eq!(
        manifest(&other, &updated)["output_digest"],
        m["output_digest"]
    );
}

#[test]
fn a_changed_pose_or_a_missing_parent_computes_from_scratch_and_says_why() {
    let ws = Workspace::new(PIPELINE);
    ws.run_ok(&[]);
    // The edit and a camera height: every pose moved.
    ws.run_ok(&["--set", EDIT, "--set", "scene.camera_height_m=1.6"]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Ran);
    assert!(
        why.contains("from scratch: the scene's `cameras` changed"),
        "{why}"
    );
    let (outcome, why) = last(&ws, "depth");
    assert_eq!(outcome, Outcome::Ran);
    assert!(why.contains("from scratch: the scene's `"), "{why}");

    // The parent's entry removed (gc, a colleague's clean-up): from scratch, saying so.
    let parent = ws.stage_key("rays");
    fs::remove_dir_all(ws.cache().join("objects").join(&parent)).unwrap();
    ws.run_ok(&["--set", "scene.camera_height_m=1.6"]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Ran);
    assert!(
        why.contains(&format!(
            "from scratch: its last entry {} is no longer in the cache",
            &parent[..8]
        )),
        "{why}"
    );

    // The entry the last run read is gone, but one with the same bytes is cached (a version
    // bump that wrote the same bytes, then `pipe gc`): that one serves, and rays updates.
    let record = ws.cache().join("runs/rays.json");
    let mut rec: serde_json::Value = serde_json::from_slice(&fs::read(&record).unwrap()).unwrap();
    rec["inputs"]["scene"]["key"] = serde_json::json!("0".repeat(64));
    fs::write(&record, serde_json::to_vec(&rec).unwrap()).unwrap();
    ws.run_ok(&["--set", EDIT, "--set", "scene.camera_height_m=1.6"]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Updated, "{why}");

    // The key the last run read holds other bytes than it read (a forced run of a stage that
    // is not deterministic, on a GPU say, wrote it again): not a parent, from scratch.
    let mut rec: serde_json::Value = serde_json::from_slice(&fs::read(&record).unwrap()).unwrap();
    rec["inputs"]["scene"]["digest"] = serde_json::json!("f".repeat(64));
    fs::write(&record, serde_json::to_vec(&rec).unwrap()).unwrap();
    let other = "scene.edits=[{primitive: 57, scale: [1.3, 1.3, 1.3]}]";
    ws.run_ok(&["--set", other, "--set", "scene.camera_height_m=1.6"]);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Ran, "{why}");
    assert!(
        why.contains("the input `scene` of its last run was computed again since"),
        "{why}"
    );
}

/// The edit a team makes by hand: the box moved in the `data_3d_bboxes` XML and saved. The
/// scene is read again, and rays is updated to the bytes of a run from scratch.
#[test]
fn an_edited_bboxes_file_updates_rays() {
    let ws = Workspace::new("");
    let root = ws.dir().join("k360");
    let scene = common::kitti360_fixture(&root);
    ws.write_pipeline(&format!(
        "stages:\n{scene}  rays:\n    uses: intersect\n    inputs: {{scene: scene}}\n"
    ));
    ws.run_ok(&[]);
    let parent = ws.stage_key("rays");
    let xml = root.join("data_3d_bboxes/train/seq_a.xml");
    let text = fs::read_to_string(&xml).unwrap();
    assert!(text.contains("2. 0. 0. 1000.5"));
    fs::write(&xml, text.replace("2. 0. 0. 1000.5", "2. 0. 0. 1001.5")).unwrap();
    ws.run_ok(&[]);
    assert_eq!(last(&ws, "scene").0, Outcome::Ran);
    let (outcome, why) = last(&ws, "rays");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert!(
        why.starts_with(&format!("updated from {}", &parent[..8])),
        "{why}"
    );
    let updated = ws.stage_key("rays");
    ws.run_ok(&["--cold"]);
    let cold = ws.stage_key("rays");
    assert_ne!(cold, updated);
    assert_eq!(
        manifest(&ws, &cold)["output_digest"],
        manifest(&ws, &updated)["output_digest"]
    );
}

/// Train goes on from the previous weights after an edit: a short run appended to the log, the
/// same bytes for the same parent and edit in another cache; a new class trains from scratch.
/// Render renders again only the images (and cells) that can see the edit. A plan made with
/// other params trains from scratch.
#[test]
fn an_edit_trains_on_from_the_previous_weights_and_renders_only_what_it_changes() {
    // Car 93 of the street becomes a caravan (a class the street has).
    const RELABEL: &str = "scene.edits=[{primitive: 93, class: caravan, instance: 5}]";
    let log_rows = |ws: &Workspace| {
        let key = ws.stage_key("train");
        let f = fs::File::open(
            ws.cache()
                .join("objects")
                .join(key)
                .join("train_log.parquet"),
        )
        .unwrap();
        parquet::file::reader::SerializedFileReader::new(f)
            .map(|r| {
                use parquet::file::reader::FileReader;
                r.metadata().file_metadata().num_rows()
            })
            .unwrap()
    };
    let ws = Workspace::new(EDIT_PIPELINE);
    ws.run_ok(&[]);
    let parent = ws.stage_key("train");
    assert_eq!(log_rows(&ws), 60);
    ws.run_ok(&["--set", RELABEL]);
    let (outcome, why) = last(&ws, "train");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert!(
        why.starts_with(&format!(
            "updated from {}: 20 steps from the previous weights",
            &parent[..8]
        )),
        "{why}"
    );
    assert_eq!(
        log_rows(&ws),
        80,
        "the update's steps are appended to the log"
    );
    let updated = ws.stage_key("train");
    let digest = manifest(&ws, &updated)["output_digest"].clone();
    assert_ne!(digest, manifest(&ws, &parent)["output_digest"]);
    let (outcome, why) = last(&ws, "render");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    // "updated from X: N of 8 images rendered again, P % of their pixels"
    let pct: f64 = why
        .split(", ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{why}"));
    assert!(
        why.contains(" of 8 images rendered again, ") && pct > 0.0 && pct < 30.0,
        "only the cells car 93 can be in: {why}"
    );
    let render_key = ws.stage_key("render");
    let render_digest = manifest(&ws, &render_key)["output_digest"].clone();

    let other = Workspace::new(EDIT_PIPELINE);
    other.run_ok(&[]);
    other.run_ok(&["--set", RELABEL]);
    assert_eq!(other.stage_key("train"), updated);
    assert_eq!(manifest(&other, &updated)["output_digest"], digest);
    assert_eq!(other.stage_key("render"), render_key);
    assert_eq!(
        manifest(&other, &render_key)["output_digest"],
        render_digest
    );

    // The plan made with other params: every ray may differ, no update holds.
    other.run_ok(&["--set", RELABEL, "--set", "rays.far=60"]);
    for stage in ["train", "render"] {
        let (outcome, why) = last(&other, stage);
        assert_eq!(outcome, Outcome::Ran, "{stage}: {why}");
        assert!(
            why.ends_with("from scratch: the plan was made with other parameters"),
            "{stage}: {why}"
        );
    }

    // How an update works is no part of what it starts from: another budget still updates.
    ws.run_ok(&[
        "--set",
        "scene.edits=[{primitive: 93, class: caravan, instance: 6}]",
        "--set",
        "train.update.iterations=10",
    ]);
    let (outcome, why) = last(&ws, "train");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert!(
        why.contains(": 10 steps from the previous weights, "),
        "{why}"
    );

    // An edit that only removes a primitive trains the removal's budget.
    ws.run_ok(&[
        "--set",
        "scene.edits=[{primitive: 93, remove: true}]",
        "--set",
        "train.update.removal_iterations=7",
    ]);
    let (outcome, why) = last(&ws, "train");
    assert_eq!(outcome, Outcome::Updated, "{why}");
    assert!(
        why.contains(": 7 steps from the previous weights (`update.removal_iterations`"),
        "{why}"
    );

    // A class the scene did not have: the semantic head changes shape.
    ws.run_ok(&["--set", "scene.edits=[{primitive: 93, class: bus}]"]);
    let (outcome, why) = last(&ws, "train");
    assert_eq!(outcome, Outcome::Updated);
    assert!(
        why.ends_with("trained from scratch (the scene's classes changed)"),
        "{why}"
    );
    // The scene's class list changed with it: render renders from scratch and says why.
    let (outcome, why) = last(&ws, "render");
    assert_eq!(outcome, Outcome::Ran);
    assert!(
        why.ends_with("from scratch: the input `scene`.scene_info changed"),
        "{why}"
    );
}
