use super::*;

/// Signals of a `w` x 1 image, everything agreeing, every ray inside one primitive interval
/// [5, 15] m and rendered at 10 m.
struct Fixture {
    w: usize,
    ours: Vec<u8>,
    fixed: Vec<u8>,
    confidence: Vec<f32>,
    depth: Vec<f32>,
    pseudo: Option<Vec<u8>>,
    plan: ImagePlan,
    scale: Vec<f32>,
    sky: Vec<bool>,
}

impl Fixture {
    fn new(w: usize) -> Self {
        Self {
            w,
            ours: vec![7; w],
            fixed: vec![7; w],
            confidence: vec![0.99; w],
            depth: vec![10.0; w],
            pseudo: Some(vec![7; w]),
            plan: ImagePlan {
                hits: vec![1; w],
                t_in: vec![5.0; w],
                t_out: vec![15.0; w],
                prim: vec![3; w],
                ..Default::default()
            },
            scale: vec![1.0; w],
            sky: vec![true; w],
        }
    }

    fn review(&self) -> ImageReview {
        let s = ImageSignals {
            width: self.w,
            height: 1,
            ours: &self.ours,
            fixed: &self.fixed,
            confidence: &self.confidence,
            depth: &self.depth,
            pseudo: self.pseudo.as_deref(),
            plan: &self.plan,
            depth_scale: &self.scale,
            may_see_sky: &self.sky,
        };
        review_image(
            &s,
            &Weights::default(),
            Shape {
                band: 1.0,
                slack: 0.5,
            },
        )
    }
}

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

#[test]
fn with_no_cue_the_score_is_the_confidence_term_alone() {
    let r = Fixture::new(3).review();
    let w = Weights::default();
    let z = w.bias + w.confidence * 0.01f32.ln();
    for &s in &r.score {
        assert!((logit(s) - z).abs() < 1e-4, "{} vs {z}", logit(s));
    }
    assert_eq!(r.reason, vec![LOW_CONFIDENCE; 3]);
    assert_eq!(r.primitive, vec![3; 3]);
    assert_eq!(r.gap, vec![false; 3]);
}

#[test]
fn each_cue_adds_its_weight_to_the_log_odds_and_names_the_reason() {
    let w = Weights::default();
    let base = logit(Fixture::new(1).review().score[0]);
    let mut f = Fixture::new(1);
    f.pseudo = Some(vec![8]);
    let r = f.review();
    assert!((logit(r.score[0]) - base - w.pseudo).abs() < 1e-3);
    assert_eq!(r.reason[0], PSEUDO_DISAGREES);

    let mut f = Fixture::new(1);
    f.fixed = vec![8];
    let r = f.review();
    assert!((logit(r.score[0]) - base - w.fixed).abs() < 1e-3);
    assert_eq!(r.reason[0], FIXED_DISAGREES);

    let mut f = Fixture::new(1);
    f.depth = vec![30.0];
    let r = f.review();
    assert!((logit(r.score[0]) - base - w.outside).abs() < 1e-3);
    assert_eq!((r.reason[0], r.primitive[0]), (OUTSIDE, 3));

    // Just inside the slack is not outside.
    let mut f = Fixture::new(1);
    f.depth = vec![15.4];
    assert!((logit(f.review().score[0]) - base).abs() < 1e-3);
}

#[test]
fn a_boundary_adds_its_decaying_weight() {
    let w = Weights::default();
    let mut f = Fixture::new(8);
    f.ours = vec![7, 7, 7, 7, 9, 9, 9, 9];
    f.fixed = f.ours.clone();
    f.pseudo = Some(f.ours.clone());
    let r = f.review();
    let base = logit(Fixture::new(1).review().score[0]);
    // Pixels 3 and 4 are on the boundary (distance 0), pixel 1 two pixels away, pixel 0 three.
    let want = |d: f32| w.boundary * (-d).exp() + if d <= 2.0 { w.near_boundary } else { 0.0 };
    for (p, d) in [(3, 0.0), (4, 0.0), (1, 2.0), (0, 3.0), (7, 3.0)] {
        assert!(
            (logit(r.score[p]) - base - want(d)).abs() < 1e-3,
            "pixel {p}: {} vs {}",
            logit(r.score[p]) - base,
            want(d)
        );
    }
    assert_eq!(r.reason[3], BOUNDARY);
}

#[test]
fn coverage_gaps_need_a_non_sky_pixel_without_primitives() {
    let mut f = Fixture::new(4);
    f.plan = ImagePlan {
        hits: vec![0; 4],
        ..Default::default()
    };
    f.depth = vec![0.0; 4];
    // Pseudo: building, sky, unlabelled, building below the horizon.
    f.pseudo = Some(vec![11, labels::SKY, labels::UNLABELED, labels::SKY]);
    f.sky = vec![true, true, true, false];
    let r = f.review();
    assert_eq!(r.gap, vec![true, false, false, true]);
    assert_eq!(r.primitive, vec![NO_PRIMITIVE; 4]);
    assert_eq!(r.reason[0], GAP);
    assert!(r.score[0] > r.score[1]);
    // Without pseudo labels only a ray below the horizon is known not to be sky.
    f.pseudo = None;
    assert_eq!(f.review().gap, vec![false, false, false, true]);
}

#[test]
fn the_primitive_is_the_one_holding_the_depth() {
    let mut f = Fixture::new(2);
    f.plan = ImagePlan {
        hits: vec![2, 2],
        t_in: vec![1.0, 8.0, 1.0, 8.0],
        t_out: vec![3.0, 12.0, 3.0, 12.0],
        prim: vec![4, 9, 4, 9],
        ..Default::default()
    };
    // Depth per metre 0.5: a depth of 5 is 10 m along the ray, in the second interval.
    f.scale = vec![0.5, 0.5];
    f.depth = vec![5.0, 0.0];
    let r = f.review();
    assert_eq!(r.primitive, vec![9, 4]);
}

#[test]
fn extreme_inputs_give_finite_scores() {
    let mut f = Fixture::new(4);
    f.confidence = vec![1.0, 0.0, f32::NAN, -3.0];
    f.depth = vec![f32::INFINITY, 10.0, f32::NAN, 10.0];
    let r = f.review();
    assert!(r
        .score
        .iter()
        .all(|s| s.is_finite() && (0.0..=1.0).contains(s)));
    // No confidence at all is the least confident.
    assert!(r.score[2] >= r.score[1] - 1e-6);
    // A pixel that is no ray has score 0.
    f.scale = vec![0.0; 4];
    assert!(f.review().score.iter().all(|&s| s == 0.0));
}

#[test]
fn the_edge_of_a_fisheye_lens_is_no_label_boundary() {
    let mut f = Fixture::new(4);
    // Pixels 0 and 1 are outside the lens (no ray; rendered unlabeled).
    f.scale = vec![0.0, 0.0, 1.0, 1.0];
    f.ours = vec![labels::UNLABELED, labels::UNLABELED, 7, 7];
    f.fixed = f.ours.clone();
    f.pseudo = Some(f.ours.clone());
    let inside = Fixture::new(1).review().score[0];
    let r = f.review();
    assert_eq!(&r.score[..2], &[0.0, 0.0]);
    assert!(
        (r.score[2] - inside).abs() < 1e-6,
        "{} vs {inside}",
        r.score[2]
    );
    assert_eq!(r.reason[2], LOW_CONFIDENCE);
}
