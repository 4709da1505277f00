//! Pixel confusion matrix over a fixed list of classes, and what is read from it: per-class
//! IoU, mIoU (the paper's, and the public code's for comparison) and pixel accuracy.

use std::fmt;

use super::error::{check_len, class_index, MetricError};
use crate::labels;

/// Confusion matrix of ground truth (rows) against prediction (columns) over a class list.
///
/// Only pixels whose GT is one of the classes count ("valid" pixels): GT void (0) and GT
/// classes outside the list are skipped. A prediction outside the list (including 0) is kept
/// in an extra "other" column: it is a wrong pixel, a false negative of the GT class, and a
/// false positive of no class.
///
/// # Shapes
/// `counts`: `[classes, classes + 1]` row-major, the last column being "other".
#[derive(Debug, Clone, PartialEq)]
pub struct ConfusionMatrix {
    classes: Vec<u8>,
    /// Label id -> row/column index, `u16::MAX` when not evaluated.
    index: [u16; 256],
    // [classes (gt), classes + 1 (pred)]
    counts: Vec<u64>,
}

/// One row of the per-class table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClassIou {
    /// Label id.
    pub class: u8,
    /// Pixels of the class predicted as the class.
    pub tp: u64,
    /// Valid pixels of another GT class predicted as this class.
    pub fp: u64,
    /// Pixels of the class predicted as something else.
    pub fn_: u64,
    /// `tp / (tp + fp + fn)`; `None` when the class is absent from both GT and prediction.
    pub iou: Option<f64>,
}

impl ConfusionMatrix {
    /// An empty matrix over `classes` (label ids, non-zero, distinct; order is kept).
    pub fn new(classes: &[u8]) -> Result<Self, MetricError> {
        let index = class_index(classes)?;
        let n = classes.len();
        Ok(Self {
            classes: classes.to_vec(),
            index,
            counts: vec![0; n * (n + 1)],
        })
    }

    /// The evaluated classes, in the order given to [`ConfusionMatrix::new`].
    pub fn classes(&self) -> &[u8] {
        &self.classes
    }

    fn cols(&self) -> usize {
        self.classes.len() + 1
    }

    /// Counts one frame.
    ///
    /// # Shapes
    /// `gt`, `pred`: `[height * width]` label ids, same length.
    pub fn add(&mut self, gt: &[u8], pred: &[u8]) -> Result<(), MetricError> {
        check_len("prediction", gt.len(), pred.len())?;
        let other = self.classes.len();
        let cols = self.cols();
        for (&g, &p) in gt.iter().zip(pred) {
            let gi = self.index[g as usize];
            if gi == u16::MAX {
                continue; // void or not evaluated
            }
            let pi = match self.index[p as usize] {
                u16::MAX => other,
                i => i as usize,
            };
            self.counts[gi as usize * cols + pi] += 1;
        }
        Ok(())
    }

    /// Adds the counts of `other` (e.g. a matrix filled from other frames on another thread).
    /// Both must have the same class list.
    pub fn merge(&mut self, other: &ConfusionMatrix) -> Result<(), MetricError> {
        if self.classes != other.classes {
            return Err(MetricError::Merge(format!(
                "confusion matrices over different classes ({:?} and {:?})",
                self.classes, other.classes
            )));
        }
        for (a, b) in self.counts.iter_mut().zip(&other.counts) {
            *a += b;
        }
        Ok(())
    }

    /// Number of valid pixels with GT `gt` predicted as `pred` (`None` for `pred` = "other",
    /// i.e. outside the class list). 0 for classes not in the list.
    pub fn count(&self, gt: u8, pred: Option<u8>) -> u64 {
        let gi = self.index[gt as usize];
        let pi = match pred {
            None => self.classes.len() as u16,
            Some(p) => self.index[p as usize],
        };
        if gi == u16::MAX || pi == u16::MAX {
            return 0;
        }
        self.counts[gi as usize * self.cols() + pi as usize]
    }

    /// Valid pixels counted so far.
    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// Valid pixels predicted correctly.
    pub fn correct(&self) -> u64 {
        (0..self.classes.len())
            .map(|i| self.counts[i * self.cols() + i])
            .sum()
    }

    fn stats(&self, i: usize) -> ClassIou {
        let cols = self.cols();
        let tp = self.counts[i * cols + i];
        let row: u64 = self.counts[i * cols..(i + 1) * cols].iter().sum();
        let col: u64 = (0..self.classes.len())
            .map(|g| self.counts[g * cols + i])
            .sum();
        let (fp, fn_) = (col - tp, row - tp);
        let denom = tp + fp + fn_;
        ClassIou {
            class: self.classes[i],
            tp,
            fp,
            fn_,
            iou: (denom > 0).then(|| tp as f64 / denom as f64),
        }
    }

    /// IoU of `class`; `None` when TP + FP + FN = 0 (absent from GT and prediction) or when
    /// the class is not evaluated.
    pub fn iou(&self, class: u8) -> Option<f64> {
        match self.index[class as usize] {
            u16::MAX => None,
            i => self.stats(i as usize).iou,
        }
    }

    /// The per-class table, in class-list order.
    pub fn table(&self) -> Vec<ClassIou> {
        (0..self.classes.len()).map(|i| self.stats(i)).collect()
    }

    /// Mean IoU over the classes present in GT or prediction (the paper's mIoU); a class
    /// predicted but absent from GT has IoU 0 and lowers it (predictions on void GT pixels do
    /// not count: such a class stays absent). `None` when no class is present.
    pub fn miou(&self) -> Option<f64> {
        mean(self.table().iter().filter_map(|c| c.iou))
    }

    /// mIoU as the public Panoptic NeRF code computes it: the mean over only the classes with
    /// 0.1 < IoU < 1, which hides failed and trivially perfect classes. For comparison with
    /// published numbers only; report [`ConfusionMatrix::miou`].
    pub fn miou_public_code_style(&self) -> Option<f64> {
        mean(
            self.table()
                .iter()
                .filter_map(|c| c.iou)
                .filter(|&iou| iou > 0.1 && iou < 1.0),
        )
    }

    /// Pixel accuracy: correct / valid pixels; `None` when no pixel is valid.
    pub fn accuracy(&self) -> Option<f64> {
        let total = self.total();
        (total > 0).then(|| self.correct() as f64 / total as f64)
    }
}

/// Mean of the values; `None` for none.
pub(crate) fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// The per-class table, then mIoU and accuracy, as fixed-width text (percentages).
impl fmt::Display for ConfusionMatrix {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let pct = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{:.1}", 100.0 * v));
        writeln!(
            f,
            "{:<22} {:>7} {:>12} {:>12} {:>12}",
            "class", "IoU %", "TP", "FP", "FN"
        )?;
        for c in self.table() {
            let name = labels::by_id(c.class).map_or("?", |l| l.name);
            writeln!(
                f,
                "{:<22} {:>7} {:>12} {:>12} {:>12}",
                format!("{name} ({})", c.class),
                pct(c.iou),
                c.tp,
                c.fp,
                c.fn_
            )?;
        }
        writeln!(f, "mIoU {} %", pct(self.miou()))?;
        write!(f, "Acc  {} %", pct(self.accuracy()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::labels::{BUILDING as B, CAR as C, ROAD as R, SKY as S};
    use proptest::prelude::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn iou_miou_acc_on_a_4x4_map() {
        // GT                 prediction
        // R R R R            R R R R
        // R R R R            R R B B
        // B B B B            B B B B
        // B B S S            S B S S
        let gt = [R, R, R, R, R, R, R, R, B, B, B, B, B, B, S, S];
        let pred = [R, R, R, R, R, R, B, B, B, B, B, B, S, B, S, S];
        let mut m = ConfusionMatrix::new(&[R, B, S]).unwrap();
        m.add(&gt, &pred).unwrap();
        // road: TP 6, FN 2 (-> B), FP 0            IoU 6/8 = 0.75
        // building: TP 5, FP 2 (from R), FN 1 (-> S) IoU 5/8 = 0.625
        // sky: TP 2, FP 1 (from B), FN 0           IoU 2/3
        assert_eq!(m.count(R, Some(B)), 2);
        assert_eq!(m.count(B, Some(S)), 1);
        let t = m.table();
        assert_eq!((t[0].tp, t[0].fp, t[0].fn_), (6, 0, 2));
        assert_eq!((t[1].tp, t[1].fp, t[1].fn_), (5, 2, 1));
        assert_eq!((t[2].tp, t[2].fp, t[2].fn_), (2, 1, 0));
        assert!(close(m.iou(R).unwrap(), 0.75));
        assert!(close(m.iou(B).unwrap(), 0.625));
        assert!(close(m.iou(S).unwrap(), 2.0 / 3.0));
        // mIoU = (0.75 + 0.625 + 2/3) / 3 = 2.041666.. / 3 = 0.680555..
        assert!(close(m.miou().unwrap(), (0.75 + 0.625 + 2.0 / 3.0) / 3.0));
        // Acc = 13 correct / 16
        assert!(close(m.accuracy().unwrap(), 13.0 / 16.0));
        assert_eq!(m.iou(C), None, "not evaluated");
        let text = m.to_string();
        assert!(text.contains("road (7)") && text.contains("75.0"), "{text}");
    }

    #[test]
    fn void_and_unevaluated_gt_pixels_are_ignored() {
        // GT: 0 0 R R / pole(17) R R R; prediction all road except one building.
        let gt = [0, 0, R, R, 17, R, R, R];
        let pred = [B, B, R, R, B, R, R, B];
        let mut m = ConfusionMatrix::new(&[R, B]).unwrap();
        m.add(&gt, &pred).unwrap();
        // Valid pixels: the 5 road pixels; 4 correct, 1 -> building.
        assert_eq!(m.total(), 5);
        assert!(close(m.accuracy().unwrap(), 0.8));
        assert!(close(m.iou(R).unwrap(), 0.8));
        // building: TP 0, FP 1 (the predictions on void / pole do not count) -> IoU 0.
        assert_eq!(m.table()[1].fp, 1);
        assert_eq!(m.iou(B), Some(0.0));
    }

    #[test]
    fn class_only_in_prediction_lowers_miou() {
        let gt = [R, R, R, R];
        let mut right = ConfusionMatrix::new(&[R, B, S]).unwrap();
        right.add(&gt, &[R, R, R, R]).unwrap();
        // Only road is present: mIoU = 1; building and sky are absent and excluded.
        assert_eq!(right.miou(), Some(1.0));
        assert_eq!(right.iou(S), None);

        let mut wrong = ConfusionMatrix::new(&[R, B, S]).unwrap();
        wrong.add(&gt, &[R, R, R, S]).unwrap();
        // road 3/4; sky present in prediction only: IoU 0/1 = 0 -> mIoU (0.75 + 0) / 2.
        assert_eq!(wrong.miou(), Some(0.375));
        // The public code's average drops sky (IoU 0 is not > 0.1): it reports 0.75.
        assert_eq!(wrong.miou_public_code_style(), Some(0.75));
        // ... and it drops perfect classes too.
        assert_eq!(right.miou_public_code_style(), None);
    }

    #[test]
    fn prediction_outside_the_list_is_a_wrong_pixel() {
        let mut m = ConfusionMatrix::new(&[R, B]).unwrap();
        m.add(&[R, R, B, B], &[R, 0, 17, B]).unwrap();
        // road: TP 1, FN 1; building: TP 1, FN 1; the "other" predictions are FP of nothing.
        assert_eq!(m.count(R, None), 1);
        assert_eq!(m.iou(R), Some(0.5));
        assert_eq!(m.iou(B), Some(0.5));
        assert_eq!(m.accuracy(), Some(0.5));
    }

    #[test]
    fn empty_matrix_and_bad_class_lists() {
        let m = ConfusionMatrix::new(&[R]).unwrap();
        assert_eq!((m.miou(), m.accuracy()), (None, None));
        assert!(ConfusionMatrix::new(&[]).is_err());
        assert!(ConfusionMatrix::new(&[R, 0]).is_err());
        assert!(ConfusionMatrix::new(&[R, B, R]).is_err());
        let mut a = ConfusionMatrix::new(&[R, B]).unwrap();
        assert!(a.merge(&ConfusionMatrix::new(&[B, R]).unwrap()).is_err());
        assert!(matches!(
            a.add(&[R, R], &[R]),
            Err(MetricError::Length {
                expected: 2,
                got: 1,
                ..
            })
        ));
    }

    fn label() -> impl Strategy<Value = u8> {
        prop::sample::select(vec![0u8, R, B, S, C, 17])
    }

    proptest! {
        #[test]
        fn miou_and_accuracy_are_in_unit_interval(
            pixels in prop::collection::vec((label(), label()), 1..200)
        ) {
            let (gt, pred): (Vec<u8>, Vec<u8>) = pixels.into_iter().unzip();
            let mut m = ConfusionMatrix::new(&[R, B, S, C]).unwrap();
            m.add(&gt, &pred).unwrap();
            for v in [m.miou(), m.accuracy(), m.miou_public_code_style()].into_iter().flatten() {
                prop_assert!((0.0..=1.0).contains(&v), "{v}");
            }
            for c in m.table() {
                prop_assert_eq!(c.iou.is_some(), c.tp + c.fp + c.fn_ > 0);
            }
        }

        #[test]
        fn merging_equals_accumulating_in_one(
            frames in prop::collection::vec(prop::collection::vec((label(), label()), 0..50), 1..5),
            split in 0usize..5,
        ) {
            let classes = [R, B, S, C];
            let mut one = ConfusionMatrix::new(&classes).unwrap();
            let mut left = ConfusionMatrix::new(&classes).unwrap();
            let mut right = ConfusionMatrix::new(&classes).unwrap();
            for (i, f) in frames.iter().enumerate() {
                let (gt, pred): (Vec<u8>, Vec<u8>) = f.iter().copied().unzip();
                one.add(&gt, &pred).unwrap();
                if i < split { &mut left } else { &mut right }.add(&gt, &pred).unwrap();
            }
            left.merge(&right).unwrap();
            prop_assert_eq!(left, one);
        }
    }
}
