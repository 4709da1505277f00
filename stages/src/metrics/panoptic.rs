//! Panoptic quality (Kirillov et al. 2019) with the Panoptic NeRF paper's conventions, and
//! PQ-dagger (Porzi et al. 2019), accumulated over frames.
//!
//! Segments are per frame: for a thing class, all pixels with the same `id * 1000 + instance`
//! value form one segment (not connected components); for a stuff class, all pixels of the
//! class form one segment. Matching follows the reference implementation (panopticapi):
//! - a predicted and a GT segment of the same class match when IoU > 0.5 (strictly; this
//!   makes matches unique), where the union leaves out the predicted pixels that are void in
//!   GT: `union = pred_area + gt_area - intersection - (pred ∩ void)`;
//! - GT void is: label 0, classes outside the evaluated list, and GT segments under
//!   `min_gt_segment_px` (100) pixels;
//! - GT pixels of a thing class with instance 0 form that class's "crowd" region: not a
//!   segment (never matched, never a false negative);
//! - an unmatched predicted segment is a false positive unless more than half of its pixels
//!   are void in GT or in the crowd region of its class;
//! - predicted segments under `min_pred_segment_px` (100) pixels are first relabelled sky
//!   ([`relabel_small_segments`]);
//! - predicted pixels of label 0 or of a class outside the list are no segment.
//!
//! Per class, over all frames: `SQ = sum IoU(matches) / TP`, `RQ = TP / (TP + FP/2 + FN/2)`,
//! `PQ = SQ * RQ`; class averages leave out classes with `TP + FP + FN = 0`.
//!
//! PQ-dagger scores a stuff class by its pixel IoU over the same frames (no matching, no
//! threshold) and a thing class by its PQ. The pixel IoU is taken on the same prediction as
//! PQ, i.e. after small segments were relabelled sky; the project's mIoU is computed
//! separately, on the raw semantic prediction ([`ConfusionMatrix`]).

use std::{
    collections::{HashMap, HashSet},
    fmt,
    hash::Hash,
};

use super::confusion::{mean, ConfusionMatrix};
use super::error::{check_len, class_index, instance_number, MetricError};
use crate::labels::{self, INSTANCE_FACTOR};

/// Settings of the panoptic evaluation. The default is the paper's.
#[derive(Debug, Clone, PartialEq)]
pub struct PanopticConfig {
    /// Evaluated classes (label ids). Default: [`labels::PAPER_CLASSES`].
    pub classes: Vec<u8>,
    /// Which of them are things; the others are stuff. Default: [`labels::PAPER_THINGS`].
    pub things: Vec<u8>,
    /// GT segments with fewer pixels are void. Default 100.
    pub min_gt_segment_px: usize,
    /// Predicted segments with fewer pixels are relabelled `sky_id` before matching; `None`
    /// turns this off. Default `Some(100)`.
    pub min_pred_segment_px: Option<usize>,
    /// The class small predicted segments become. Default [`labels::SKY`].
    pub sky_id: u8,
}

impl Default for PanopticConfig {
    fn default() -> Self {
        Self {
            classes: labels::PAPER_CLASSES.to_vec(),
            things: labels::PAPER_THINGS.to_vec(),
            min_gt_segment_px: 100,
            min_pred_segment_px: Some(100),
            sky_id: labels::SKY,
        }
    }
}

impl PanopticConfig {
    /// These classes scored as panopticapi scores them (and the Cityscapes and KITTI-360
    /// scripts built on it): predicted segments are taken as they are, however small. The GT
    /// stays what this evaluation defines (segments under `min_gt_segment_px` void), as in
    /// the GT maps `evaluate` exports, so both conventions score against the same GT.
    pub fn panopticapi(self) -> Self {
        Self {
            min_pred_segment_px: None,
            ..self
        }
    }
}

/// Sums over frames for one class.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct ClassSums {
    tp: u64,
    fp: u64,
    fn_: u64,
    iou_sum: f64,
}

/// Accumulates panoptic matching over frames; read the result with
/// [`PanopticAccumulator::result`]. Also keeps the pixel confusion matrix of the same
/// (relabelled) predictions, which gives the stuff IoUs of PQ-dagger.
#[derive(Debug, Clone, PartialEq)]
pub struct PanopticAccumulator {
    config: PanopticConfig,
    /// Label id -> class index, `u16::MAX` when not evaluated.
    index: [u16; 256],
    is_thing: [bool; 256],
    // [classes]
    sums: Vec<ClassSums>,
    confusion: ConfusionMatrix,
    frames: u64,
}

/// PQ, SQ and RQ of one class over all frames.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClassPq {
    /// Label id.
    pub class: u8,
    pub is_thing: bool,
    /// Matched segment pairs.
    pub tp: u64,
    /// Unmatched predicted segments (not mostly void).
    pub fp: u64,
    /// Unmatched GT segments.
    pub fn_: u64,
    /// Sum of the IoUs of the matches.
    pub iou_sum: f64,
    /// `None` when `tp + fp + fn = 0` (the class takes no part in the averages).
    pub pq: Option<f64>,
    /// Mean IoU of the matches (0 without matches).
    pub sq: Option<f64>,
    pub rq: Option<f64>,
    /// Pixel IoU of the class over the same frames (confusion matrix, no matching), on the
    /// prediction after small segments were relabelled.
    pub iou: Option<f64>,
    /// The class's PQ-dagger score: `iou` for stuff, `pq` for things.
    pub pq_dagger: Option<f64>,
}

/// Class averages of PQ, SQ and RQ (each averaged separately, as panopticapi does).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PqSummary {
    pub pq: f64,
    pub sq: f64,
    pub rq: f64,
    /// Number of classes averaged.
    pub classes: usize,
}

/// The panoptic evaluation of all frames added.
#[derive(Debug, Clone, PartialEq)]
pub struct PanopticResult {
    /// In class-list order.
    pub per_class: Vec<ClassPq>,
    /// Averages over all classes, things and stuff; `None` where no class counts.
    pub all: Option<PqSummary>,
    pub things: Option<PqSummary>,
    pub stuff: Option<PqSummary>,
    /// Mean over classes of [`ClassPq::pq_dagger`] (classes without a score left out).
    pub pq_dagger: Option<f64>,
    /// Frames added.
    pub frames: u64,
}

/// The segment key of a pixel: `class * 1000 + instance` for things, `class * 1000` for
/// stuff (one segment per class).
fn segment_key(class: u8, instance_value: u32, thing: bool) -> u32 {
    let inst = if thing {
        instance_number(instance_value)
    } else {
        0
    };
    class as u32 * INSTANCE_FACTOR + inst
}

fn key_class(key: u32) -> u8 {
    (key / INSTANCE_FACTOR) as u8
}

/// GT pixels that are void (no segment) in the matching.
const VOID: u32 = u32::MAX;

/// Adds one to `counts[key]` per `Some(key)`, a run of equal items at a time: label maps are
/// runs of equal values along a row, so this hashes once per run, not once per pixel.
fn count_runs<K: Copy + Eq + Hash>(
    items: impl Iterator<Item = Option<K>>,
    counts: &mut HashMap<K, u64>,
) {
    let mut run: Option<(Option<K>, u64)> = None;
    for item in items {
        match &mut run {
            Some((k, n)) if *k == item => *n += 1,
            _ => {
                if let Some((Some(k), n)) = run {
                    *counts.entry(k).or_default() += n;
                }
                run = Some((item, 1));
            }
        }
    }
    if let Some((Some(k), n)) = run {
        *counts.entry(k).or_default() += n;
    }
}

/// Relabels the predicted segments with fewer than `min_px` pixels as `sky_id` (instance 0),
/// in place; returns the number of pixels changed. Segments are as in the panoptic
/// evaluation: per `things` class one per instance value, per other class one per class.
/// Pixels of label 0 are left alone; segments already of class `sky_id` too.
///
/// # Shapes
/// `sem`, `inst`: `[height * width]`; `inst` in KITTI-360 encoding (`id * 1000 + instance`).
pub fn relabel_small_segments<I>(
    sem: &mut [u8],
    inst: &mut [I],
    things: &[u8],
    min_px: usize,
    sky_id: u8,
) -> Result<usize, MetricError>
where
    I: Copy + Default + Into<u32>,
{
    check_len("instance map", sem.len(), inst.len())?;
    let mut is_thing = [false; 256];
    for &t in things {
        is_thing[t as usize] = true;
    }
    let key = |s: u8, i: I| segment_key(s, i.into(), is_thing[s as usize]);
    let mut area: HashMap<u32, u64> = HashMap::new();
    count_runs(
        sem.iter()
            .zip(inst.iter())
            .map(|(&s, &i)| (s != labels::UNLABELED).then(|| key(s, i))),
        &mut area,
    );
    let mut changed = 0;
    // The last key looked up and whether it is small: a run of one segment asks once.
    let mut last: Option<(u32, bool)> = None;
    for (s, i) in sem.iter_mut().zip(inst.iter_mut()) {
        if *s == labels::UNLABELED || *s == sky_id {
            continue;
        }
        let k = key(*s, *i);
        let small = match last {
            Some((lk, small)) if lk == k => small,
            _ => {
                let small = area[&k] < min_px as u64;
                last = Some((k, small));
                small
            }
        };
        if small {
            *s = sky_id;
            *i = I::default();
            changed += 1;
        }
    }
    Ok(changed)
}

impl PanopticAccumulator {
    /// An empty accumulator. `config.things` must be a subset of `config.classes`.
    pub fn new(config: PanopticConfig) -> Result<Self, MetricError> {
        let index = class_index(&config.classes)?;
        let mut is_thing = [false; 256];
        for &t in &config.things {
            if index[t as usize] == u16::MAX {
                return Err(MetricError::Classes(format!(
                    "thing class {t} is not among the evaluated classes"
                )));
            }
            is_thing[t as usize] = true;
        }
        if config.min_pred_segment_px.is_some() && config.sky_id == labels::UNLABELED {
            return Err(MetricError::Setting(
                "sky_id must not be 0 when small predicted segments are relabelled".into(),
            ));
        }
        Ok(Self {
            index,
            is_thing,
            sums: vec![ClassSums::default(); config.classes.len()],
            confusion: ConfusionMatrix::new(&config.classes)?,
            frames: 0,
            config,
        })
    }

    /// The settings this accumulator was built with.
    pub fn config(&self) -> &PanopticConfig {
        &self.config
    }

    /// The pixel confusion matrix of the frames added (predictions after relabelling).
    pub fn confusion(&self) -> &ConfusionMatrix {
        &self.confusion
    }

    /// Matches the segments of one frame and adds the counts.
    ///
    /// # Shapes
    /// All four maps `[height * width]`; instance maps in KITTI-360 encoding
    /// (`id * 1000 + instance`, `u16` or `u32`). The class of a pixel is read from the
    /// semantic map, only the instance number from the instance map.
    pub fn add_frame<I, J>(
        &mut self,
        gt_sem: &[u8],
        gt_inst: &[I],
        pred_sem: &[u8],
        pred_inst: &[J],
    ) -> Result<(), MetricError>
    where
        I: Copy + Into<u32>,
        J: Copy + Into<u32>,
    {
        let n = gt_sem.len();
        check_len("GT instance map", n, gt_inst.len())?;
        check_len("predicted semantic map", n, pred_sem.len())?;
        check_len("predicted instance map", n, pred_inst.len())?;

        let mut p_sem = pred_sem.to_vec();
        let mut p_inst: Vec<u32> = pred_inst.iter().map(|&v| v.into()).collect();
        if let Some(min_px) = self.config.min_pred_segment_px {
            relabel_small_segments(
                &mut p_sem,
                &mut p_inst,
                &self.config.things,
                min_px,
                self.config.sky_id,
            )?;
        }
        self.confusion.add(gt_sem, &p_sem)?;

        let evaluated = |c: u8| self.index[c as usize] != u16::MAX;
        // GT segment key per pixel (VOID for void and unevaluated classes); crowd regions
        // keep the key `class * 1000` of a thing class.
        let mut gt_key: Vec<u32> = gt_sem
            .iter()
            .zip(gt_inst)
            .map(|(&c, &i)| {
                if evaluated(c) {
                    segment_key(c, i.into(), self.is_thing[c as usize])
                } else {
                    VOID
                }
            })
            .collect();
        let is_crowd =
            |key: u32| key % INSTANCE_FACTOR == 0 && self.is_thing[key_class(key) as usize];
        let mut gt_area: HashMap<u32, u64> = HashMap::new();
        count_runs(
            gt_key.iter().map(|&k| (k != VOID).then_some(k)),
            &mut gt_area,
        );
        // Small GT segments are void.
        let min_gt = self.config.min_gt_segment_px as u64;
        gt_area.retain(|&k, &mut a| is_crowd(k) || a >= min_gt);
        let mut last: Option<(u32, bool)> = None;
        for k in &mut gt_key {
            if *k == VOID {
                continue;
            }
            let kept = match last {
                Some((lk, kept)) if lk == *k => kept,
                _ => {
                    let kept = gt_area.contains_key(k);
                    last = Some((*k, kept));
                    kept
                }
            };
            if !kept {
                *k = VOID;
            }
        }

        // Intersections of predicted segments with GT keys (VOID too), and from them the
        // predicted segments' areas.
        let mut pairs: HashMap<(u32, u32), u64> = HashMap::new();
        count_runs(
            p_sem
                .iter()
                .zip(&p_inst)
                .zip(&gt_key)
                .map(|((&c, &i), &g)| {
                    evaluated(c).then(|| (g, segment_key(c, i, self.is_thing[c as usize])))
                }),
            &mut pairs,
        );
        let mut pred_area: HashMap<u32, u64> = HashMap::new();
        for (&(_, p), &n) in &pairs {
            *pred_area.entry(p).or_default() += n;
        }

        // Sorted so that float sums are reproducible.
        let mut pairs: Vec<((u32, u32), u64)> = pairs.into_iter().collect();
        pairs.sort_unstable();
        let void_of = |p: u32| {
            pairs
                .binary_search_by_key(&(VOID, p), |&(k, _)| k)
                .map_or(0, |i| pairs[i].1)
        };
        let mut gt_matched: HashSet<u32> = HashSet::new();
        let mut pred_matched: HashSet<u32> = HashSet::new();
        for &((g, p), inter) in &pairs {
            if g == VOID || is_crowd(g) || key_class(g) != key_class(p) {
                continue;
            }
            let union = pred_area[&p] + gt_area[&g] - inter - void_of(p);
            let iou = inter as f64 / union as f64;
            if iou > 0.5 {
                let s = &mut self.sums[self.index[key_class(g) as usize] as usize];
                s.tp += 1;
                s.iou_sum += iou;
                gt_matched.insert(g);
                pred_matched.insert(p);
            }
        }
        for &g in gt_area.keys() {
            if !is_crowd(g) && !gt_matched.contains(&g) {
                self.sums[self.index[key_class(g) as usize] as usize].fn_ += 1;
            }
        }
        for (&p, &area) in &pred_area {
            if pred_matched.contains(&p) {
                continue;
            }
            let class = key_class(p);
            let mut ignored = void_of(p);
            if self.is_thing[class as usize] {
                let crowd = class as u32 * INSTANCE_FACTOR;
                ignored += pairs
                    .binary_search_by_key(&(crowd, p), |&(k, _)| k)
                    .map_or(0, |i| pairs[i].1);
            }
            if ignored as f64 / area as f64 > 0.5 {
                continue;
            }
            self.sums[self.index[class as usize] as usize].fp += 1;
        }
        self.frames += 1;
        Ok(())
    }

    /// Adds the counts of `other` (frames evaluated elsewhere); the settings must be equal.
    pub fn merge(&mut self, other: &PanopticAccumulator) -> Result<(), MetricError> {
        if self.config != other.config {
            return Err(MetricError::Merge(
                "panoptic accumulators with different settings".into(),
            ));
        }
        for (a, b) in self.sums.iter_mut().zip(&other.sums) {
            a.tp += b.tp;
            a.fp += b.fp;
            a.fn_ += b.fn_;
            a.iou_sum += b.iou_sum;
        }
        self.confusion.merge(&other.confusion)?;
        self.frames += other.frames;
        Ok(())
    }

    /// PQ / SQ / RQ per class and averaged (All / Things / Stuff), and PQ-dagger.
    pub fn result(&self) -> PanopticResult {
        let per_class: Vec<ClassPq> = self
            .config
            .classes
            .iter()
            .zip(&self.sums)
            .map(|(&class, s)| {
                let counted = s.tp + s.fp + s.fn_ > 0;
                let sq = if s.tp > 0 {
                    s.iou_sum / s.tp as f64
                } else {
                    0.0
                };
                let rq = s.tp as f64 / (s.tp as f64 + 0.5 * s.fp as f64 + 0.5 * s.fn_ as f64);
                let is_thing = self.is_thing[class as usize];
                let pq = counted.then_some(sq * rq);
                let iou = self.confusion.iou(class);
                ClassPq {
                    class,
                    is_thing,
                    tp: s.tp,
                    fp: s.fp,
                    fn_: s.fn_,
                    iou_sum: s.iou_sum,
                    pq,
                    sq: counted.then_some(sq),
                    rq: counted.then_some(rq),
                    iou,
                    pq_dagger: if is_thing { pq } else { iou },
                }
            })
            .collect();
        let summary = |keep: &dyn Fn(&ClassPq) -> bool| {
            let counted: Vec<&ClassPq> = per_class
                .iter()
                .filter(|c| c.pq.is_some() && keep(c))
                .collect();
            let avg = |f: fn(&ClassPq) -> Option<f64>| mean(counted.iter().filter_map(|c| f(c)));
            Some(PqSummary {
                pq: avg(|c| c.pq)?,
                sq: avg(|c| c.sq)?,
                rq: avg(|c| c.rq)?,
                classes: counted.len(),
            })
        };
        PanopticResult {
            all: summary(&|_| true),
            things: summary(&|c| c.is_thing),
            stuff: summary(&|c| !c.is_thing),
            pq_dagger: mean(per_class.iter().filter_map(|c| c.pq_dagger)),
            per_class,
            frames: self.frames,
        }
    }
}

impl PanopticResult {
    /// The row of `class`, if evaluated.
    pub fn class(&self, class: u8) -> Option<&ClassPq> {
        self.per_class.iter().find(|c| c.class == class)
    }
}

/// The per-class table, then the All / Things / Stuff averages and PQ-dagger, as fixed-width
/// text (percentages).
impl fmt::Display for PanopticResult {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let pct = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{:.1}", 100.0 * v));
        writeln!(
            f,
            "{:<22} {:>6} {:>6} {:>6} {:>6} {:>7} {:>7} {:>7} {:>6}",
            "class", "PQ %", "SQ %", "RQ %", "IoU %", "TP", "FP", "FN", "kind"
        )?;
        for c in &self.per_class {
            let name = labels::by_id(c.class).map_or("?", |l| l.name);
            writeln!(
                f,
                "{:<22} {:>6} {:>6} {:>6} {:>6} {:>7} {:>7} {:>7} {:>6}",
                format!("{name} ({})", c.class),
                pct(c.pq),
                pct(c.sq),
                pct(c.rq),
                pct(c.iou),
                c.tp,
                c.fp,
                c.fn_,
                if c.is_thing { "thing" } else { "stuff" }
            )?;
        }
        for (name, s) in [
            ("All", self.all),
            ("Things", self.things),
            ("Stuff", self.stuff),
        ] {
            writeln!(
                f,
                "{name:<7} PQ {} SQ {} RQ {} ({} classes)",
                pct(s.map(|s| s.pq)),
                pct(s.map(|s| s.sq)),
                pct(s.map(|s| s.rq)),
                s.map_or(0, |s| s.classes)
            )?;
        }
        write!(
            f,
            "PQ-dagger {} ({} frames)",
            pct(self.pq_dagger),
            self.frames
        )
    }
}

#[cfg(test)]
mod tests;
