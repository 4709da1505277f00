//! Multi-view consistency (MC): do two frames give the same label to the same 3D point?
//! LiDAR depth of both frames is unprojected to the scene frame; each point of frame A is
//! paired with its nearest point of frame B closer than `max_dist` (0.1 m in the paper), found
//! through a uniform grid hash; MC = pairs with equal labels / pairs.
//!
//! Independent of the geometry module on purpose: a view is given by plain pinhole
//! intrinsics and a row-major 4x4 camera-to-world matrix.

use std::collections::HashMap;

use rayon::prelude::*;

use super::error::{check_len, MetricError};

/// Pinhole intrinsics in pixels. Camera axes: x right, y down, z forward; the centre of pixel
/// `(x, y)` is at `(x + 0.5, y + 0.5)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinhole {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// One frame for the consistency metric: its labels, LiDAR depth and camera.
///
/// # Shapes
/// `labels`, `depth`: `[height * width]`, row-major; `depth` is z-depth in metres, 0 (or
/// non-finite) where there is no LiDAR point.
#[derive(Debug, Clone, Copy)]
pub struct LabelledView<'a> {
    pub width: usize,
    pub height: usize,
    pub labels: &'a [u8],
    pub depth: &'a [f32],
    pub intrinsics: Pinhole,
    /// Row-major 4x4 rigid transform from camera to scene coordinates.
    pub cam_to_world: [f64; 16],
}

/// Counts of the consistency metric; sums over frame pairs with [`Consistency::merge`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Consistency {
    /// Points of A with a point of B within the distance.
    pub matched: u64,
    /// Of those, pairs whose labels are equal.
    pub agreeing: u64,
}

impl Consistency {
    /// MC = agreeing / matched; `None` without pairs.
    pub fn value(&self) -> Option<f64> {
        (self.matched > 0).then(|| self.agreeing as f64 / self.matched as f64)
    }

    /// Adds the counts of another frame pair.
    pub fn merge(&mut self, other: &Consistency) {
        self.matched += other.matched;
        self.agreeing += other.agreeing;
    }
}

impl LabelledView<'_> {
    fn check(&self, name: &'static str) -> Result<(), MetricError> {
        let n = self.width * self.height;
        check_len(name, n, self.labels.len())?;
        check_len(name, n, self.depth.len())
    }

    /// Scene-frame points of the pixels with LiDAR depth, with their labels.
    fn points(&self) -> Vec<([f64; 3], u8)> {
        let Pinhole { fx, fy, cx, cy } = self.intrinsics;
        let m = &self.cam_to_world;
        let mut out = Vec::new();
        for y in 0..self.height {
            for x in 0..self.width {
                let i = y * self.width + x;
                let z = self.depth[i] as f64;
                if !(z.is_finite() && z > 0.0) {
                    continue;
                }
                let c = [
                    (x as f64 + 0.5 - cx) / fx * z,
                    (y as f64 + 0.5 - cy) / fy * z,
                    z,
                ];
                let w = [0, 1, 2].map(|r| {
                    m[4 * r] * c[0] + m[4 * r + 1] * c[1] + m[4 * r + 2] * c[2] + m[4 * r + 3]
                });
                out.push((w, self.labels[i]));
            }
        }
        out
    }
}

fn cell(p: &[f64; 3], size: f64) -> [i64; 3] {
    p.map(|v| (v / size).floor() as i64)
}

/// Multi-view consistency of frame `a` against frame `b`: each LiDAR point of `a` is paired
/// with the nearest LiDAR point of `b` strictly closer than `max_dist` metres (ties: the first
/// in row-major order); points without one are left out. Not symmetric in `a` and `b`. All
/// labels take part as they are (label 0 included: two unlabeled points agree).
pub fn multiview_consistency(
    a: &LabelledView,
    b: &LabelledView,
    max_dist: f64,
) -> Result<Consistency, MetricError> {
    a.check("view A labels/depth")?;
    b.check("view B labels/depth")?;
    if !(max_dist.is_finite() && max_dist > 0.0) {
        return Err(MetricError::Setting(format!(
            "max_dist must be a positive distance, got {max_dist}"
        )));
    }
    let pa = a.points();
    let pb = b.points();
    // Cells of side max_dist: a point's neighbours within max_dist lie in the 27 cells around.
    let mut grid: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
    for (i, (p, _)) in pb.iter().enumerate() {
        grid.entry(cell(p, max_dist)).or_default().push(i as u32);
    }
    let r2 = max_dist * max_dist;
    let counts = pa
        .par_iter()
        .map(|(p, label)| {
            let c = cell(p, max_dist);
            let mut best: Option<(f64, u32)> = None;
            for dx in -1..=1 {
                for dy in -1..=1 {
                    for dz in -1..=1 {
                        let Some(ids) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) else {
                            continue;
                        };
                        for &j in ids {
                            let q = &pb[j as usize].0;
                            let d2 = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>();
                            if d2 < r2 && best.is_none_or(|b| (d2, j) < b) {
                                best = Some((d2, j));
                            }
                        }
                    }
                }
            }
            match best {
                Some((_, j)) => Consistency {
                    matched: 1,
                    agreeing: (pb[j as usize].1 == *label) as u64,
                },
                None => Consistency::default(),
            }
        })
        .reduce(Consistency::default, |mut x, y| {
            x.merge(&y);
            x
        });
    Ok(counts)
}

/// Cross-view consistency of view `a` against a view of another camera model (a fisheye)
/// that has no LiDAR of its own: each LiDAR point of `a` is carried into the other view by
/// `project` (scene point -> image point `(u, v)` of that view, `None` where its lens does not
/// see the point) and its label there is compared with its label in `a`. The same question as
/// [`multiview_consistency`] (do two views give one 3D point one label?) with the point
/// itself as the match. Points `project` does not place inside the `width` x `height` image,
/// and pixels of it labelled `ignore` (outside the lens), are left out.
///
/// # Shapes
/// `labels_b`: `[height * width]`, row-major.
pub fn cross_view_consistency(
    a: &LabelledView,
    labels_b: &[u8],
    (width, height): (usize, usize),
    ignore: u8,
    project: impl Fn([f64; 3]) -> Option<(f64, f64)> + Sync,
) -> Result<Consistency, MetricError> {
    a.check("view A labels/depth")?;
    check_len("view B labels", width * height, labels_b.len())?;
    let counts = a
        .points()
        .par_iter()
        .map(|&(p, label)| {
            let Some((u, v)) = project(p) else {
                return Consistency::default();
            };
            if !(u >= 0.0 && v >= 0.0 && u < width as f64 && v < height as f64) {
                return Consistency::default();
            }
            let other = labels_b[v as usize * width + u as usize];
            if other == ignore {
                return Consistency::default();
            }
            Consistency {
                matched: 1,
                agreeing: (other == label) as u64,
            }
        })
        .reduce(Consistency::default, |mut x, y| {
            x.merge(&y);
            x
        });
    Ok(counts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::labels::{CAR, ROAD};
    use proptest::prelude::*;

    const IDENTITY: [f64; 16] = [
        1., 0., 0., 0., //
        0., 1., 0., 0., //
        0., 0., 1., 0., //
        0., 0., 0., 1.,
    ];

    fn translated(tx: f64, ty: f64, tz: f64) -> [f64; 16] {
        let mut m = IDENTITY;
        m[3] = tx;
        m[7] = ty;
        m[11] = tz;
        m
    }

    // 8 x 4 image, fx = fy = 10, principal point at the centre; a wall at z = 5 m: neighbouring
    // pixels are 5 / 10 = 0.5 m apart on it.
    const W: usize = 8;
    const H: usize = 4;
    const K: Pinhole = Pinhole {
        fx: 10.0,
        fy: 10.0,
        cx: 4.0,
        cy: 2.0,
    };

    fn view<'a>(labels: &'a [u8], depth: &'a [f32], pose: [f64; 16]) -> LabelledView<'a> {
        LabelledView {
            width: W,
            height: H,
            labels,
            depth,
            intrinsics: K,
            cam_to_world: pose,
        }
    }

    /// Left half road, right half car.
    fn halves() -> Vec<u8> {
        (0..W * H)
            .map(|i| if i % W < W / 2 { ROAD } else { CAR })
            .collect()
    }

    /// A second camera 1 m to the right (x) looking the same way sees the wall through its own
    /// pinhole, written as the `project` closure; its labels are the first view's shifted by
    /// the parallax (1 m at 5 m depth = 2 px), so agreement is exact after the shift and drops
    /// where the second view's labels are changed.
    #[test]
    fn cross_view_carries_each_point_into_the_other_view() {
        let labels = halves();
        let depth = vec![5.0f32; W * H];
        let a = view(&labels, &depth, IDENTITY);
        // Camera B at x = 1: a wall point (X, Y, 5) lands at u = 10 (X - 1) / 5 + 4.
        let project = |p: [f64; 3]| {
            let z = p[2];
            (z > 0.0).then(|| (K.fx * (p[0] - 1.0) / z + K.cx, K.fy * p[1] / z + K.cy))
        };
        // B's labels: A's shifted left by 2 px; its last 2 columns see nothing of A's points.
        let mut b = vec![0u8; W * H];
        for y in 0..H {
            for x in 0..W - 2 {
                b[y * W + x] = labels[y * W + x + 2];
            }
        }
        let c = cross_view_consistency(&a, &b, (W, H), 255, project).unwrap();
        // A's first 2 columns fall left of B's image: 6 of 8 columns pair.
        assert_eq!(c.matched, (6 * H) as u64);
        assert_eq!(c.agreeing, c.matched);
        // Relabel one column of B (its H points disagree) and ignore another (they leave the count).
        let mut b2 = b.clone();
        for y in 0..H {
            b2[y * W + 1] = CAR; // A's column 3: road
            b2[y * W + 4] = 255;
        }
        let c = cross_view_consistency(&a, &b2, (W, H), 255, project).unwrap();
        assert_eq!(c.matched, (5 * H) as u64);
        assert_eq!(c.agreeing, (4 * H) as u64);
        // A view B that sees nothing (everything behind it) pairs nothing.
        let none = cross_view_consistency(&a, &b, (W, H), 255, |_| None).unwrap();
        assert_eq!(none, Consistency::default());
        assert!(cross_view_consistency(&a, &b[1..], (W, H), 255, project).is_err());
    }

    #[test]
    fn identical_frames_are_fully_consistent() {
        let labels = halves();
        let depth = vec![5.0f32; W * H];
        let a = view(&labels, &depth, IDENTITY);
        let mc = multiview_consistency(&a, &a, 0.1).unwrap();
        assert_eq!(mc.matched, (W * H) as u64);
        assert_eq!(mc.value(), Some(1.0));
    }

    #[test]
    fn half_the_labels_flipped_gives_one_half() {
        let labels = halves();
        // Flip the labels of rows 0 and 1 (half of the pixels).
        let flipped: Vec<u8> = labels
            .iter()
            .enumerate()
            .map(|(i, &l)| match (i / W < 2, l) {
                (true, ROAD) => CAR,
                (true, _) => ROAD,
                (false, l) => l,
            })
            .collect();
        let depth = vec![5.0f32; W * H];
        let mc = multiview_consistency(
            &view(&labels, &depth, IDENTITY),
            &view(&flipped, &depth, IDENTITY),
            0.1,
        )
        .unwrap();
        assert_eq!(
            mc,
            Consistency {
                matched: 32,
                agreeing: 16
            }
        );
        assert_eq!(mc.value(), Some(0.5));
    }

    #[test]
    fn moved_camera_pairs_points_through_the_scene_frame() {
        // Camera B is 0.5 m to the right of A: B's pixel column x sees A's column x + 1.
        // A's column 0 has no partner (the nearest B point is 0.5 m away): 7 columns x 4 rows
        // are matched.
        let depth = vec![5.0f32; W * H];
        let a_labels = halves(); // road in columns 0-3, car in 4-7
        let a = view(&a_labels, &depth, IDENTITY);
        let pose_b = translated(0.5, 0.0, 0.0);

        // B labelled consistently: B column x has A's label at x + 1 (road 0-2, car 3-7).
        let b_good: Vec<u8> = (0..W * H)
            .map(|i| if i % W < W / 2 - 1 { ROAD } else { CAR })
            .collect();
        let mc = multiview_consistency(&a, &view(&b_good, &depth, pose_b), 0.1).unwrap();
        assert_eq!(
            mc,
            Consistency {
                matched: 28,
                agreeing: 28
            }
        );

        // B labelled like A pixel for pixel (ignoring the motion): A column x pairs with B
        // column x - 1; only A column 4 (car) meets B column 3 (road): 6 of 7 columns agree.
        let mc = multiview_consistency(&a, &view(&a_labels, &depth, pose_b), 0.1).unwrap();
        assert_eq!(
            mc,
            Consistency {
                matched: 28,
                agreeing: 24
            }
        );
        assert!((mc.value().unwrap() - 6.0 / 7.0).abs() < 1e-12);
    }

    #[test]
    fn pixels_without_lidar_and_far_points_are_not_paired() {
        let labels = halves();
        let mut depth_a = vec![5.0f32; W * H];
        depth_a[0] = 0.0;
        depth_a[1] = f32::NAN;
        // B's wall is 0.2 m behind A's: every A-B distance is at least 0.2 m.
        let depth_b = vec![5.2f32; W * H];
        let a = view(&labels, &depth_a, IDENTITY);
        assert_eq!(
            multiview_consistency(&a, &view(&labels, &depth_a, IDENTITY), 0.1)
                .unwrap()
                .matched,
            30
        );
        let mc = multiview_consistency(&a, &view(&labels, &depth_b, IDENTITY), 0.1).unwrap();
        assert_eq!((mc.matched, mc.value()), (0, None));
        assert!(multiview_consistency(&a, &a, 0.0).is_err());
        let short = [ROAD; 3];
        assert!(multiview_consistency(&a, &view(&short, &depth_a, IDENTITY), 0.1).is_err());
    }

    #[test]
    fn unprojection_uses_pixel_centres_and_the_rotation() {
        // Camera looking along world +x: camera z -> world x, camera x -> world -y,
        // camera y -> world -z; camera centre at (1, 2, 3).
        let pose = [
            0., 0., 1., 1., //
            -1., 0., 0., 2., //
            0., -1., 0., 3., //
            0., 0., 0., 1.,
        ];
        let mut depth = vec![0.0f32; W * H];
        depth[W + 5] = 10.0; // pixel (5, 1): centre (5.5, 1.5)
        let labels = halves();
        let pts = view(&labels, &depth, pose).points();
        // camera point ((5.5 - 4) / 10 * 10, (1.5 - 2) / 10 * 10, 10) = (1.5, -0.5, 10)
        // world = (10 + 1, -1.5 + 2, 0.5 + 3) = (11, 0.5, 3.5)
        assert_eq!(pts, vec![([11.0, 0.5, 3.5], CAR)]);
    }

    #[test]
    fn ten_thousand_points_are_paired_quickly() {
        // A 100 x 100 view of a slanted plane against itself: 10^4 points, each with itself.
        let (w, h) = (100, 100);
        let depth: Vec<f32> = (0..w * h).map(|i| 5.0 + (i % w) as f32 * 0.05).collect();
        let labels: Vec<u8> = (0..w * h).map(|i| (i % 7) as u8).collect();
        let v = LabelledView {
            width: w,
            height: h,
            labels: &labels,
            depth: &depth,
            intrinsics: Pinhole {
                fx: 100.0,
                fy: 100.0,
                cx: 50.0,
                cy: 50.0,
            },
            cam_to_world: translated(3.0, -1.0, 2.0),
        };
        let start = std::time::Instant::now();
        let mc = multiview_consistency(&v, &v, 0.1).unwrap();
        assert_eq!(
            mc,
            Consistency {
                matched: 10_000,
                agreeing: 10_000
            }
        );
        assert!(start.elapsed().as_secs_f64() < 5.0, "{:?}", start.elapsed());
    }

    proptest! {
        #[test]
        fn a_view_against_itself_is_consistent(
            depth in prop::collection::vec(prop_oneof![Just(0.0f32), 0.5f32..50.0], W * H),
            labels in prop::collection::vec(0u8..4, W * H),
            tx in -10.0f64..10.0,
        ) {
            let v = view(&labels, &depth, translated(tx, 1.0, -2.0));
            let mc = multiview_consistency(&v, &v, 0.1).unwrap();
            let valid = depth.iter().filter(|&&d| d > 0.0).count() as u64;
            prop_assert_eq!(mc.matched, valid);
            // Coincident points of different pixels can only come from equal depths along the
            // same ray, impossible here: every point pairs with itself.
            prop_assert_eq!(mc.agreeing, valid);
        }
    }
}
