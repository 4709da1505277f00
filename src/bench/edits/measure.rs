//! Scores of one edit, from the cached tables of the runs before, updated and from scratch: on
//! the pixels whose ray meets a changed box (old or new extent), mIoU and PQ against GT with the
//! edit applied (a relabelled object's GT pixels take its new class) and the update against
//! the cold run; the edited object's GT pixels labelled with the class its box has; and
//! elsewhere, the share of pixels whose label changed from the run before. One image at a time.

use arrow::datatypes::{UInt16Type, UInt8Type};
use serde_yaml::Value as Yaml;

use stages::geometry::{self, changes::pixels_meeting, Primitive, PrimitiveChanges};
use stages::metrics::{ConfusionMatrix, PanopticAccumulator, PanopticConfig};
use stages::{labels, tables, TableSet};

use crate::bench::BenchError;
use crate::store::{Entry, Store};

/// The cache entries one edit is scored from.
pub struct Entries {
    /// Scene stages: the unedited scene (whose rows `object` counts), before and after the edit.
    pub unedited: String,
    pub before: String,
    pub after: String,
    /// Render stages: before the edit, the update and the run from scratch.
    pub maps_before: String,
    pub maps_update: String,
    pub maps_cold: String,
}

/// The scores of one run (the update or the cold run).
#[derive(Debug, Clone, Default)]
pub struct Scores {
    pub miou: Option<f64>,
    /// The reach's IoU of each class in its GT or labels (label id, IoU), which `miou` averages.
    pub class_iou: Vec<(u8, f64)>,
    pub pq: Option<f64>,
    /// The object's GT pixels labelled with the class its box has after the edit.
    pub object: Option<f64>,
    /// Pixels outside the edit's reach whose label differs from the run before.
    pub elsewhere_changed: f64,
}

/// The scores of one edit.
#[derive(Debug, Clone, Default)]
pub struct Measured {
    pub update: Scores,
    pub cold: Scores,
    /// mIoU of the update's labels against the cold run's, on the pixels the edit can change.
    pub update_vs_cold: Option<f64>,
    /// The share of the pixels the edit can change.
    pub reach: f64,
    /// The class the object's pixels should have after the edit.
    pub class: u8,
}

fn bench_err(what: impl std::fmt::Display) -> BenchError {
    BenchError::Results(what.to_string())
}

fn open(store: &Store, key: &str) -> Result<TableSet, BenchError> {
    match store.check(key, false) {
        Entry::Valid(m) => store.open_tables(&m, true).map_err(bench_err),
        _ => Err(bench_err(format!(
            "cache entry {key} is missing or corrupt"
        ))),
    }
}

fn primitives(
    t: &TableSet,
) -> Result<(Vec<Primitive>, &arrow::record_batch::RecordBatch), BenchError> {
    let table = t
        .get("primitives")
        .ok_or_else(|| bench_err("the scene entry has no `primitives`"))?
        .whole()
        .map_err(bench_err)?;
    Ok((
        geometry::primitives_from_table(table).map_err(bench_err)?,
        table,
    ))
}

fn table<'a>(t: &'a TableSet, name: &str) -> Result<&'a stages::Table, BenchError> {
    t.get(name)
        .ok_or_else(|| bench_err(format!("the scene has no `{name}`")))
}

/// The class `object` has after `edits` (its new class if one edit gives it one).
fn class_after(edits: &Yaml, object: u32, old: u8) -> Result<u8, BenchError> {
    for e in edits.as_sequence().into_iter().flatten() {
        if e.get("primitive").and_then(Yaml::as_u64) != Some(object as u64) {
            continue;
        }
        let Some(c) = e.get("class") else { continue };
        let name = match c {
            Yaml::Number(n) => n.to_string(),
            other => other.as_str().unwrap_or_default().to_string(),
        };
        let label = match name.parse::<u8>() {
            Ok(id) => labels::by_id(id),
            Err(_) => labels::by_name(&name),
        };
        return label
            .map(|l| l.id)
            .ok_or_else(|| bench_err(format!("edit of {object}: unknown class `{name}`")));
    }
    Ok(old)
}

/// Running counts of one run.
struct Tally {
    confusion: ConfusionMatrix,
    panoptic: PanopticAccumulator,
    object: (u64, u64),
    elsewhere: (u64, u64),
}

impl Tally {
    fn new() -> Result<Self, BenchError> {
        Ok(Self {
            confusion: ConfusionMatrix::new(labels::PAPER_CLASSES).map_err(bench_err)?,
            panoptic: PanopticAccumulator::new(PanopticConfig::default()).map_err(bench_err)?,
            object: (0, 0),
            elsewhere: (0, 0),
        })
    }

    fn scores(&self) -> Scores {
        let share = |(a, b): (u64, u64)| (b > 0).then(|| a as f64 / b as f64);
        Scores {
            miou: self.confusion.miou(),
            class_iou: self
                .confusion
                .table()
                .iter()
                .filter_map(|c| Some((c.class, c.iou?)))
                .collect(),
            pq: self.panoptic.result().all.map(|s| s.pq),
            object: share(self.object),
            elsewhere_changed: share(self.elsewhere).unwrap_or(0.0),
        }
    }
}

/// The semantic and instance maps of image `key` of a `label_maps` entry.
fn maps(
    t: &TableSet,
    key: (u32, u8),
    rows: &std::collections::HashMap<(u32, u8), usize>,
) -> Result<(Vec<u8>, Vec<u16>), BenchError> {
    let table = t
        .get("label_maps")
        .ok_or_else(|| bench_err("no `label_maps`"))?;
    let row = rows.get(&key).ok_or_else(|| {
        bench_err(format!(
            "no rendered image for frame {} camera {}",
            key.0, key.1
        ))
    })?;
    let b = table.row(*row).map_err(bench_err)?;
    let sem = tables::get_list::<UInt8Type>(&b, "label_maps", "semantic").map_err(bench_err)?;
    let inst = tables::get_list::<UInt16Type>(&b, "label_maps", "instance").map_err(bench_err)?;
    Ok((sem.row(0).to_vec(), inst.row(0).to_vec()))
}

/// Scores one edit of `object` (`edits` as in the suite) from the entries `e`.
pub fn measure(
    store: &Store,
    e: &Entries,
    object: u32,
    edits: &Yaml,
) -> Result<Measured, BenchError> {
    let unedited = open(store, &e.unedited)?;
    let (prims, _) = primitives(&unedited)?;
    let obj = prims
        .get(object as usize)
        .ok_or_else(|| bench_err(format!("the scene has no primitive {object}")))?;
    let obj_value = (obj.label as u32 * labels::INSTANCE_FACTOR + obj.instance) as u16;
    let class = class_after(edits, object, obj.label)?;
    let (before, after) = (open(store, &e.before)?, open(store, &e.after)?);
    let ((old, old_t), (new, new_t)) = (primitives(&before)?, primitives(&after)?);
    let changes = PrimitiveChanges::between(old_t, new_t).map_err(bench_err)?;
    let changed = changes.extents(&old, &new);
    let cams = geometry::cameras_from_table(table(&after, "cameras")?.whole().map_err(bench_err)?)
        .map_err(bench_err)?;
    let (gt_sem, gt_inst) = (table(&after, "gt_semantic")?, table(&after, "gt_instance")?);
    let (sem_rows, inst_rows) = (
        gt_sem.image_rows().map_err(bench_err)?,
        gt_inst.image_rows().map_err(bench_err)?,
    );
    let runs = [&e.maps_before, &e.maps_update, &e.maps_cold].map(|k| open(store, k));
    let [before_maps, update_maps, cold_maps] = runs;
    let (before_maps, update_maps, cold_maps) = (before_maps?, update_maps?, cold_maps?);
    let rows = |t: &TableSet| -> Result<_, BenchError> {
        t.get("label_maps")
            .ok_or_else(|| bench_err("no `label_maps`"))?
            .image_rows()
            .map_err(bench_err)
    };
    let (rb, ru, rc) = (rows(&before_maps)?, rows(&update_maps)?, rows(&cold_maps)?);
    let (mut update, mut cold) = (Tally::new()?, Tally::new()?);
    let mut agree = ConfusionMatrix::new(labels::PAPER_CLASSES).map_err(bench_err)?;
    let (mut reach, mut pixels) = (0u64, 0u64);
    let mut keys: Vec<(u32, u8)> = sem_rows.keys().copied().collect();
    keys.sort_unstable();
    for key in keys {
        let Some(&inst_row) = inst_rows.get(&key) else {
            continue;
        };
        let cam = &cams
            .iter()
            .find(|c| (c.frame, c.camera) == key)
            .ok_or_else(|| bench_err(format!("no camera for frame {} camera {}", key.0, key.1)))?
            .cam;
        let b = gt_sem.row(sem_rows[&key]).map_err(bench_err)?;
        let mut ref_sem = tables::get_list::<UInt8Type>(&b, "gt_semantic", "labels")
            .map_err(bench_err)?
            .row(0)
            .to_vec();
        let b = gt_inst.row(inst_row).map_err(bench_err)?;
        let mut ref_inst = tables::get_list::<UInt16Type>(&b, "gt_instance", "instances")
            .map_err(bench_err)?
            .row(0)
            .to_vec();
        let n = ref_sem.len();
        let mut inside = vec![false; n];
        for p in pixels_meeting(cam, &changed, f64::INFINITY) {
            inside[p as usize] = true;
        }
        let object_px: Vec<bool> = ref_inst.iter().map(|&v| v == obj_value).collect();
        for p in 0..n {
            if object_px[p] {
                ref_sem[p] = class;
                ref_inst[p] = (class as u32 * labels::INSTANCE_FACTOR + obj.instance) as u16;
            }
            if !inside[p] {
                ref_sem[p] = labels::UNLABELED;
                ref_inst[p] = 0;
            }
        }
        reach += inside.iter().filter(|&&x| x).count() as u64;
        pixels += n as u64;
        let (sem_before, _) = maps(&before_maps, key, &rb)?;
        let (sem_cold, inst_cold) = maps(&cold_maps, key, &rc)?;
        let (sem_update, inst_update) = maps(&update_maps, key, &ru)?;
        for (t, sem, inst) in [
            (&mut update, &sem_update, &inst_update),
            (&mut cold, &sem_cold, &inst_cold),
        ] {
            if sem.len() != n {
                return Err(bench_err(format!(
                    "frame {} camera {}: maps of another size than GT",
                    key.0, key.1
                )));
            }
            t.confusion.add(&ref_sem, sem).map_err(bench_err)?;
            t.panoptic
                .add_frame(&ref_sem, &ref_inst, sem, inst)
                .map_err(bench_err)?;
            for p in 0..n {
                if object_px[p] {
                    t.object.1 += 1;
                    t.object.0 += u64::from(sem[p] == class);
                }
                if !inside[p] {
                    t.elsewhere.1 += 1;
                    t.elsewhere.0 += u64::from(sem[p] != sem_before[p]);
                }
            }
        }
        let cold_in: Vec<u8> = (0..n)
            .map(|p| {
                if inside[p] {
                    sem_cold[p]
                } else {
                    labels::UNLABELED
                }
            })
            .collect();
        agree.add(&cold_in, &sem_update).map_err(bench_err)?;
    }
    Ok(Measured {
        update: update.scores(),
        cold: cold.scores(),
        update_vs_cold: agree.miou(),
        reach: reach as f64 / pixels.max(1) as f64,
        class,
    })
}
