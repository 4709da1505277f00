//! Tests of panoptic quality: hand-computed cases, merging, relabelling and properties.

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
fn the_panopticapi_convention_keeps_small_predicted_segments() {
    let api = config().panopticapi();
    // A 40 px predicted building on GT road stays a building: a false positive (the paper
    // makes it sky, a false positive of sky there). Road IoU 360/400 either way.
    let frame: Frame = (&[(400, ROAD, 0)], &[(360, ROAD, 0), (40, BUILDING, 1)]);
    let r = evaluate(api.clone(), &[frame]);
    let b = r.class(BUILDING).unwrap();
    assert_eq!((b.tp, b.fp, b.fn_), (0, 1, 0));
    assert_eq!(r.class(SKY).map(|c| c.fp), Some(0));
    let paper = evaluate(config(), &[frame]);
    assert_eq!(paper.class(BUILDING).map(|c| c.fp), Some(0));
    assert_eq!(paper.class(SKY).map(|c| c.fp), Some(1));
    for res in [&r, &paper] {
        assert!(close(res.class(ROAD).unwrap().pq, 0.9));
    }
    // A small predicted car on a large GT car: the paper loses the match (sky), panopticapi
    // keeps it. GT car 150 px, predicted car 1: 90 px inside it, road elsewhere.
    // api: car IoU 90/150 = 0.6 > 0.5, TP; road: pred 310, GT 250, IoU 250/310.
    let frame: Frame = (
        &[(250, ROAD, 0), (150, CAR, 1)],
        &[(250, ROAD, 0), (60, ROAD, 0), (90, CAR, 1)],
    );
    let r = evaluate(api.clone(), &[frame]);
    let car = r.class(CAR).unwrap();
    assert_eq!((car.tp, car.fp, car.fn_), (1, 0, 0));
    assert!(close(car.pq, 0.6));
    assert!(close(r.class(ROAD).unwrap().pq, 250.0 / 310.0));
    let paper = evaluate(config(), &[frame]);
    let car = paper.class(CAR).unwrap();
    assert_eq!((car.tp, car.fp, car.fn_), (0, 0, 1));
    // GT segments under min_gt_segment_px stay void in both (the evaluated GT is the same).
    let small_gt: Frame = (&[(300, ROAD, 0), (99, CAR, 1)], &[(399, ROAD, 0)]);
    assert_eq!(evaluate(api, &[small_gt]).all.unwrap().pq, 1.0);
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
    let changed = relabel_small_segments(&mut sem, &mut inst, &[CAR, BUILDING], 100, SKY).unwrap();
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

    #[test]
    fn counting_runs_counts_every_item(items in prop::collection::vec(prop::option::of(0u8..4), 0..300)) {
        let mut runs: HashMap<u8, u64> = HashMap::new();
        runs.insert(3, 7); // counts add to what is there
        count_runs(items.iter().copied(), &mut runs);
        let mut one_by_one: HashMap<u8, u64> = HashMap::from([(3, 7)]);
        for k in items.iter().flatten() {
            *one_by_one.entry(*k).or_default() += 1;
        }
        prop_assert_eq!(runs, one_by_one);
    }
}
