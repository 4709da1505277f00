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
    let mut area: HashMap<u32, usize> = HashMap::new();
    for (&s, &i) in sem.iter().zip(inst.iter()) {
        if s != labels::UNLABELED {
            *area.entry(key(s, i)).or_default() += 1;
        }
    }
    let mut changed = 0;
    for (s, i) in sem.iter_mut().zip(inst.iter_mut()) {
        if *s == labels::UNLABELED || *s == sky_id || area[&key(*s, *i)] >= min_px {
            continue;
        }
        *s = sky_id;
        *i = I::default();
        changed += 1;
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
        for &k in &gt_key {
            if k != VOID {
                *gt_area.entry(k).or_default() += 1;
            }
        }
        // Small GT segments are void.
        let min_gt = self.config.min_gt_segment_px as u64;
        gt_area.retain(|&k, &mut a| is_crowd(k) || a >= min_gt);
        for k in &mut gt_key {
            if *k != VOID && !gt_area.contains_key(k) {
                *k = VOID;
            }
        }

        // Predicted segments, their areas and their intersections with GT keys (VOID too).
        let mut pred_area: HashMap<u32, u64> = HashMap::new();
        let mut pairs: HashMap<(u32, u32), u64> = HashMap::new();
        for ((&c, &i), &g) in p_sem.iter().zip(&p_inst).zip(&gt_key) {
            if !evaluated(c) {
                continue;
            }
            let p = segment_key(c, i, self.is_thing[c as usize]);
            *pred_area.entry(p).or_default() += 1;
            *pairs.entry((g, p)).or_default() += 1;
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
mod tests {
    use super::*;
    use crate::labels::{BUILDING, CAR, ROAD, SIDEWALK, SKY};
    use proptest::prelude::*;

    /// Runs of `(pixels, class, instance number)`: a one-row map.
    type Runs<'a> = &'a [(usize, u8, u16)];
    /// (GT, prediction) of one frame.
    type Frame<'a> = (Runs<'a>, Runs<'a>);

    /// A map built from runs of `(pixels, class, instance number)`, as KITTI-360 stores it:
    /// instance value `class * 1000 + instance`, or the bare class for instance 0. PQ does not
    /// look at the image shape, so the tests use one-row images.
    fn strip(runs: &[(usize, u8, u16)]) -> (Vec<u8>, Vec<u16>) {
        let mut sem = Vec::new();
        let mut inst = Vec::new();
        for &(n, c, i) in runs {
            let v = if i == 0 {
                c as u16
            } else {
                c as u16 * 1000 + i
            };
            sem.extend(std::iter::repeat_n(c, n));
            inst.extend(std::iter::repeat_n(v, n));
        }
        (sem, inst)
    }

    fn config() -> PanopticConfig {
        PanopticConfig {
            classes: vec![ROAD, SIDEWALK, BUILDING, SKY, CAR],
            things: vec![BUILDING, CAR],
            ..PanopticConfig::default()
        }
    }

    fn evaluate(cfg: PanopticConfig, frames: &[Frame<'_>]) -> PanopticResult {
        let mut acc = PanopticAccumulator::new(cfg).unwrap();
        for (gt, pred) in frames {
            let (gs, gi) = strip(gt);
            let (ps, pi) = strip(pred);
            acc.add_frame(&gs, &gi, &ps, &pi).unwrap();
        }
        acc.result()
    }

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() < 1e-12)
    }

    #[test]
    fn perfect_prediction_scores_one() {
        // 20 x 20 image: top half sky, bottom-left car 1, bottom-right car 2 (each 10 x 10).
        let (w, h) = (20, 20);
        let mut sem = vec![SKY; w * h];
        let mut inst = vec![SKY as u32; w * h];
        for y in 10..20 {
            for x in 0..20 {
                sem[y * w + x] = CAR;
                inst[y * w + x] = CAR as u32 * 1000 + if x < 10 { 1 } else { 2 };
            }
        }
        let mut acc = PanopticAccumulator::new(config()).unwrap();
        acc.add_frame(&sem, &inst, &sem, &inst).unwrap();
        let r = acc.result();
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (2, 0, 0));
        for s in [r.all, r.things, r.stuff] {
            let s = s.unwrap();
            assert_eq!((s.pq, s.sq, s.rq), (1.0, 1.0, 1.0));
        }
        assert_eq!(r.all.unwrap().classes, 2);
        assert_eq!(r.pq_dagger, Some(1.0));
        assert_eq!(
            r.class(ROAD).unwrap().pq,
            None,
            "absent classes are not averaged"
        );
    }

    #[test]
    fn iou_of_exactly_one_half_is_not_a_match() {
        // GT:   car 1 [0, 200)  road [200, 400)
        // pred: car 1 [0, 100)  road [100, 400)
        // car IoU 100 / 200 = 0.5 -> not matched: FP 1 + FN 1, PQ 0.
        // road IoU 200 / 300 = 2/3 -> matched: SQ 2/3, RQ 1, PQ 2/3.
        let r = evaluate(
            config(),
            &[(
                &[(200, CAR, 1), (200, ROAD, 0)],
                &[(100, CAR, 1), (300, ROAD, 0)],
            )],
        );
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (0, 1, 1));
        assert_eq!((car.pq, car.sq, car.rq), (Some(0.0), Some(0.0), Some(0.0)));
        let road = r.class(ROAD).unwrap();
        assert_eq!((road.tp, road.fp, road.fn_), (1, 0, 0));
        assert!(close(road.pq, 2.0 / 3.0));
        // All = (0 + 2/3) / 2; things = car only; stuff = road only.
        assert!(close(r.all.map(|s| s.pq), 1.0 / 3.0));
        assert_eq!(r.things.unwrap().pq, 0.0);
        assert!(close(r.stuff.map(|s| s.pq), 2.0 / 3.0));
        assert!(close(r.stuff.map(|s| s.sq), 2.0 / 3.0));
    }

    #[test]
    fn iou_of_0_51_is_a_match() {
        // GT car 1 [0, 200), road [200, 400); pred car 1 [0, 102), road [102, 400).
        // car IoU 102 / 200 = 0.51: TP, SQ 0.51, RQ 1. road IoU 200 / 298.
        let r = evaluate(
            config(),
            &[(
                &[(200, CAR, 1), (200, ROAD, 0)],
                &[(102, CAR, 1), (298, ROAD, 0)],
            )],
        );
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (1, 0, 0));
        assert!(close(car.pq, 0.51));
        assert!(close(r.class(ROAD).unwrap().sq, 200.0 / 298.0));
        assert!(close(r.things.map(|s| s.pq), 0.51));
    }

    #[test]
    fn gt_segment_under_100_px_is_void() {
        // GT road [0, 300), car 1 [300, 399) (99 px: void). Prediction: road everywhere.
        // No car FN; road union = 399 + 300 - 300 - 99 (pred on void) = 300 -> IoU 1.
        let r = evaluate(
            config(),
            &[(&[(300, ROAD, 0), (99, CAR, 1)], &[(399, ROAD, 0)])],
        );
        assert_eq!(r.class(CAR).unwrap().pq, None);
        assert_eq!(r.all.unwrap().pq, 1.0);
        assert_eq!(r.things, None);
        // With 100 px the car counts: missed -> FN, PQ 0.
        // road union = 400 + 300 - 300 - 0 = 400 -> IoU 3/4.
        let r = evaluate(
            config(),
            &[(&[(300, ROAD, 0), (100, CAR, 1)], &[(400, ROAD, 0)])],
        );
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (0, 0, 1));
        assert!(close(r.class(ROAD).unwrap().pq, 0.75));
        // And a 99 px predicted car on the 99 px GT car: relabelled sky, on void -> no FP.
        let r = evaluate(
            config(),
            &[(
                &[(300, ROAD, 0), (99, CAR, 1)],
                &[(300, ROAD, 0), (99, CAR, 1)],
            )],
        );
        assert_eq!(r.all.unwrap().classes, 1);
        assert_eq!(r.all.unwrap().pq, 1.0);
    }

    #[test]
    fn relabel_small_segments_turns_them_into_sky() {
        // road 150 | car 1: 50 | car 2: 120 | building 1: 99 | sidewalk 30 | void 10
        let (mut sem, mut inst) = strip(&[
            (150, ROAD, 0),
            (50, CAR, 1),
            (120, CAR, 2),
            (99, BUILDING, 1),
            (30, SIDEWALK, 0),
            (10, 0, 0),
        ]);
        let changed =
            relabel_small_segments(&mut sem, &mut inst, &[CAR, BUILDING], 100, SKY).unwrap();
        assert_eq!(changed, 50 + 99 + 30);
        let (want_sem, want_inst) = strip(&[
            (150, ROAD, 0),
            (50, SKY, 0),
            (120, CAR, 2),
            (129, SKY, 0),
            (10, 0, 0),
        ]);
        assert_eq!(sem, want_sem);
        // Relabelled pixels get instance value 0 (instance 0); the others are unchanged.
        assert!(inst[150..200].iter().all(|&v| v == 0));
        assert_eq!(&inst[..150], &want_inst[..150]);
        assert_eq!(&inst[200..320], &want_inst[200..320]);
        // Car 1 and car 2 are separate segments: 50 + 120 px of car do not protect car 1; as
        // stuff (no things) car is one segment of 170 px and stays.
        let (mut sem, mut inst) = strip(&[(50, CAR, 1), (120, CAR, 2)]);
        assert_eq!(
            relabel_small_segments(&mut sem, &mut inst, &[], 100, SKY).unwrap(),
            0
        );
    }

    #[test]
    fn small_predicted_segments_become_sky_before_matching() {
        // GT:   sky [0, 200), car 1 [200, 300)
        // pred: sky [0, 200), car 1 [200, 250), car 2 [250, 300) (50 px each)
        let frame: Frame<'_> = (
            &[(200, SKY, 0), (100, CAR, 1)],
            &[(200, SKY, 0), (50, CAR, 1), (50, CAR, 2)],
        );
        // Relabelled (default): pred sky [0, 300) -> sky IoU 200 / 300 matched; car FN only.
        let r = evaluate(config(), &[frame]);
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (0, 0, 1));
        assert!(close(r.class(SKY).unwrap().sq, 2.0 / 3.0));
        // The pixel IoU of PQ-dagger sees the relabelled prediction too: car IoU 0.
        assert_eq!(r.class(CAR).unwrap().iou, Some(0.0));
        // Without relabelling: each car half has IoU 50 / 100 = 0.5: 2 FP + 1 FN; sky IoU 1.
        let cfg = PanopticConfig {
            min_pred_segment_px: None,
            ..config()
        };
        let r = evaluate(cfg, &[frame]);
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (0, 2, 1));
        assert_eq!(r.class(SKY).unwrap().pq, Some(1.0));
    }

    #[test]
    fn void_gt_pixels_leave_the_union_and_excuse_false_positives() {
        // GT:   road [0, 200), void [200, 400), car 1 [400, 600)
        // pred: road [0, 300), car 1 [300, 400), car 2 [400, 600)
        // road union = 300 + 200 - 200 - 100 (pred on void) = 200 -> IoU 1 (not 2/3).
        // pred car 1 lies on void only -> not a FP. car 2 matches car 1 with IoU 1.
        let r = evaluate(
            config(),
            &[(
                &[(200, ROAD, 0), (200, 0, 0), (200, CAR, 1)],
                &[(300, ROAD, 0), (100, CAR, 1), (200, CAR, 2)],
            )],
        );
        assert_eq!(r.class(ROAD).unwrap().sq, Some(1.0));
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (1, 0, 0));
        assert_eq!(r.all.unwrap().pq, 1.0);

        // GT:   void [0, 100), road [100, 500)
        // pred: car 1 [0, 150): 100 of 150 px on void (2/3 > 1/2) -> ignored;
        //       road [150, 500): IoU 350 / 400.
        let r = evaluate(
            config(),
            &[(
                &[(100, 0, 0), (400, ROAD, 0)],
                &[(150, CAR, 1), (350, ROAD, 0)],
            )],
        );
        assert_eq!(r.class(CAR).unwrap().fp, 0);
        assert!(close(r.all.map(|s| s.pq), 350.0 / 400.0));
        // pred: car 1 [0, 250): 100 of 250 px on void (0.4) -> FP; road [250, 500): 250 / 400.
        let r = evaluate(
            config(),
            &[(
                &[(100, 0, 0), (400, ROAD, 0)],
                &[(250, CAR, 1), (250, ROAD, 0)],
            )],
        );
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_, car.pq), (0, 1, 0, Some(0.0)));
        assert!(close(r.class(ROAD).unwrap().pq, 0.625));
    }

    #[test]
    fn unevaluated_gt_classes_are_void_and_thing_pixels_without_instance_are_crowd() {
        // GT: pole (17, not evaluated) [0, 100), road [100, 300).
        // pred: road [0, 300): union 300 + 200 - 200 - 100 = 200 -> IoU 1.
        let r = evaluate(
            config(),
            &[(&[(100, 17, 0), (200, ROAD, 0)], &[(300, ROAD, 0)])],
        );
        assert_eq!(r.all.unwrap().pq, 1.0);
        // GT: car crowd (instance 0) [0, 150), road [150, 400).
        // pred: car 4 [0, 200): 150 of 200 px on the car crowd -> not a FP; the crowd is no
        // FN. road [200, 400): union 200 + 250 - 200 = 250 -> IoU 0.8.
        let r = evaluate(
            config(),
            &[(
                &[(150, CAR, 0), (250, ROAD, 0)],
                &[(200, CAR, 4), (200, ROAD, 0)],
            )],
        );
        assert_eq!(r.class(CAR).unwrap().pq, None);
        assert!(close(r.all.map(|s| s.pq), 0.8));
        // A road prediction on the car crowd is no excuse: crowd counts only for its class.
        let r = evaluate(
            config(),
            &[(
                &[(150, CAR, 0), (250, ROAD, 0)],
                &[(200, BUILDING, 4), (200, ROAD, 0)],
            )],
        );
        assert_eq!(r.class(BUILDING).unwrap().fp, 1);
    }

    #[test]
    fn things_are_split_by_instance_and_stuff_is_one_segment_per_class() {
        // GT building 1 [0, 150), building 2 [150, 300); pred building 9 [0, 300).
        // As a thing: IoU 150 / 300 = 0.5 with each -> TP 0, FP 1, FN 2.
        let frame: Frame<'_> = (
            &[(150, BUILDING, 1), (150, BUILDING, 2)],
            &[(300, BUILDING, 9)],
        );
        let b = *evaluate(config(), &[frame]).class(BUILDING).unwrap();
        assert_eq!((b.tp, b.fp, b.fn_, b.is_thing), (0, 1, 2, true));
        // RQ = 0 / (0 + 0.5 + 1) = 0
        assert_eq!(b.rq, Some(0.0));
        // As stuff: one segment on each side, IoU 1; it counts in the stuff average.
        let cfg = PanopticConfig {
            things: vec![CAR],
            ..config()
        };
        let r = evaluate(cfg, &[frame]);
        assert_eq!(r.class(BUILDING).unwrap().pq, Some(1.0));
        assert_eq!((r.things, r.stuff.unwrap().pq), (None, 1.0));
    }

    #[test]
    fn pq_dagger_scores_stuff_by_class_iou() {
        // GT:   road [0, 200), sky [200, 400), car 1 [400, 600)
        // pred: road [0, 100), sky [100, 400), car 1 [400, 600)
        // road: segment IoU 0.5 -> PQ 0; pixel IoU 100 / 200 = 0.5.
        // sky:  IoU 200 / 300 -> PQ 2/3; pixel IoU 2/3.   car: PQ 1.
        // PQ = (0 + 2/3 + 1) / 3 = 5/9;  PQ-dagger = (0.5 + 2/3 + 1) / 3 = 13/18.
        let r = evaluate(
            config(),
            &[(
                &[(200, ROAD, 0), (200, SKY, 0), (200, CAR, 1)],
                &[(100, ROAD, 0), (300, SKY, 0), (200, CAR, 1)],
            )],
        );
        assert!(close(r.all.map(|s| s.pq), 5.0 / 9.0));
        assert!(close(r.pq_dagger, 13.0 / 18.0));
        assert!(close(r.class(ROAD).unwrap().pq_dagger, 0.5));
        assert_eq!(r.class(CAR).unwrap().pq_dagger, Some(1.0));
    }

    #[test]
    fn frames_accumulate_per_class_sums() {
        // Frame 1: car IoU 150 / 200 = 0.75 (pred 150 px inside GT 200 px, rest road).
        // Frame 2: car IoU 180 / 200 = 0.9, plus a 100 px predicted car on GT road (FP).
        // car: TP 2, FP 1, FN 0, SQ (0.75 + 0.9) / 2 = 0.825, RQ 2 / 2.5 = 0.8, PQ 0.66.
        let f1: Frame<'_> = (
            &[(200, CAR, 1), (300, ROAD, 0)],
            &[(150, CAR, 1), (350, ROAD, 0)],
        );
        let f2: Frame<'_> = (
            &[(200, CAR, 1), (300, ROAD, 0)],
            &[(180, CAR, 1), (20, ROAD, 0), (100, CAR, 2), (200, ROAD, 0)],
        );
        let r = evaluate(config(), &[f1, f2]);
        let car = r.class(CAR).unwrap();
        assert_eq!((car.tp, car.fp, car.fn_), (2, 1, 0));
        assert!(close(car.sq, 0.825));
        assert!(close(car.rq, 0.8));
        assert!(close(car.pq, 0.66));
        assert_eq!(r.frames, 2);

        // Merging two accumulators gives the same as one.
        let mut a = PanopticAccumulator::new(config()).unwrap();
        let mut b = PanopticAccumulator::new(config()).unwrap();
        for (acc, (gt, pred)) in [(&mut a, f1), (&mut b, f2)] {
            let ((gs, gi), (ps, pi)) = (strip(gt), strip(pred));
            acc.add_frame(&gs, &gi, &ps, &pi).unwrap();
        }
        a.merge(&b).unwrap();
        assert_eq!(a.result(), r);
        assert!(a
            .merge(&PanopticAccumulator::new(PanopticConfig::default()).unwrap())
            .is_err());
    }

    #[test]
    fn u32_instance_maps_and_bad_inputs() {
        let (sem, inst) = strip(&[(200, CAR, 3)]);
        let inst32: Vec<u32> = inst.iter().map(|&v| v as u32).collect();
        let mut acc = PanopticAccumulator::new(config()).unwrap();
        acc.add_frame(&sem, &inst32, &sem, &inst).unwrap();
        assert_eq!(acc.result().all.unwrap().pq, 1.0);
        assert!(acc.add_frame(&sem, &inst32[1..], &sem, &inst).is_err());
        let bad = PanopticConfig {
            things: vec![17],
            ..config()
        };
        assert!(PanopticAccumulator::new(bad).is_err());
    }

    proptest! {
        #[test]
        fn prediction_equal_to_gt_scores_one(
            runs in prop::collection::vec(
                (1usize..150, prop::sample::select(vec![0u8, ROAD, SKY, BUILDING, CAR]), 1u16..4),
                1..12,
            )
        ) {
            // Things always carry an instance (no crowd): then every counted class is perfect.
            let runs: Vec<(usize, u8, u16)> = runs
                .into_iter()
                .map(|(n, c, i)| (n, c, if c == BUILDING || c == CAR { i } else { 0 }))
                .collect();
            let (sem, inst) = strip(&runs);
            // Relabelling small predicted segments leaves PQ at 1 (their pixels are void in GT:
            // the same segments are small there) but can lower the pixel IoU of a small stuff
            // class, so PQ-dagger is 1 only without it.
            for relabel in [Some(100), None] {
                let cfg = PanopticConfig { min_pred_segment_px: relabel, ..config() };
                let mut acc = PanopticAccumulator::new(cfg).unwrap();
                acc.add_frame(&sem, &inst, &sem, &inst).unwrap();
                let r = acc.result();
                for c in &r.per_class {
                    prop_assert_eq!(c.fp + c.fn_, 0, "{:?}", c);
                }
                if let Some(all) = r.all {
                    prop_assert!((all.pq - 1.0).abs() < 1e-12);
                }
                if let (None, Some(d)) = (relabel, r.pq_dagger) {
                    prop_assert!((d - 1.0).abs() < 1e-12);
                }
            }
        }

        #[test]
        fn scores_are_in_the_unit_interval(
            gt in prop::collection::vec((prop::sample::select(vec![0u8, ROAD, SKY, CAR]), 0u16..3), 400),
            pred in prop::collection::vec((prop::sample::select(vec![0u8, ROAD, SKY, CAR]), 0u16..3), 400),
        ) {
            let to_maps = |px: &[(u8, u16)]| -> (Vec<u8>, Vec<u16>) {
                px.iter().map(|&(c, i)| (c, if i == 0 { c as u16 } else { c as u16 * 1000 + i })).unzip()
            };
            let ((gs, gi), (ps, pi)) = (to_maps(&gt), to_maps(&pred));
            let cfg = PanopticConfig { min_gt_segment_px: 10, min_pred_segment_px: Some(10), ..config() };
            let mut acc = PanopticAccumulator::new(cfg).unwrap();
            acc.add_frame(&gs, &gi, &ps, &pi).unwrap();
            let r = acc.result();
            for s in [r.all, r.things, r.stuff].into_iter().flatten() {
                for v in [s.pq, s.sq, s.rq] {
                    prop_assert!((0.0..=1.0).contains(&v), "{:?}", s);
                }
            }
            for c in &r.per_class {
                prop_assert!(c.iou_sum <= c.tp as f64 + 1e-9);
            }
        }
    }
}
