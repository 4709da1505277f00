//! The synthetic street's cameras: KITTI-360's rectified stereo pair and side fisheye cameras,
//! on a rig driving along the street with a little wobble.

use super::params::{SceneParams, KITTI_CX, KITTI_CY, KITTI_F, KITTI_HEIGHT, KITTI_WIDTH};
use crate::geometry::{Camera, DAffine3, DMat3, DVec3, Lens, Mei};
use crate::scene::layout::RIG_Y;
use crate::scene::rng;

/// KITTI-360's fisheye cameras (image_02, image_03) at full size: the shape of their MEI
/// calibration (rounded), and where they sit in the left camera's frame (x right, y down, z
/// forward), metres.
const FISHEYE_SIDE: f64 = 1400.0;
const FISHEYE_GAMMA: [f64; 2] = [1336.3, 1335.8];
const FISHEYE_CENTRE: [f64; 2] = [716.9, 705.8];
const FISHEYE_MEI: Mei = Mei {
    xi: 2.2134,
    k1: 0.01693,
    k2: 1.6798,
    p1: 4.2e-4,
    p2: 4.2e-4,
    max_half_angle_deg: crate::geometry::FISHEYE_HALF_ANGLE_DEG,
};
const FISHEYE_POSITION: [[f64; 3]; 2] = [[-0.7, -0.1, -0.8], [1.3, -0.1, -0.8]];

/// The left (camera 0) and right (camera 1) cameras of `frame`.
pub fn rig(p: &SceneParams, frame: u32) -> [Camera; 2] {
    let (width, height) = p.image_size();
    let s = width as f64 / KITTI_WIDTH;
    let (rot, pos) = rig_pose(p, frame);
    let cam = |centre: DVec3| Camera {
        width,
        height,
        fx: KITTI_F * s,
        fy: KITTI_F * s,
        // KITTI's principal point is in OpenCV pixel coordinates (centres at integers); ours
        // has pixel (0, 0) spanning [0, 1), hence the half-pixel shift before scaling.
        cx: (KITTI_CX + 0.5) * s,
        cy: (KITTI_CY + 0.5) * (height as f64 / KITTI_HEIGHT),
        lens: Lens::Pinhole,
        cam_to_world: DAffine3::from_mat3_translation(rot, centre),
    };
    let right = pos + rot * DVec3::new(p.baseline_m, 0.0, 0.0);
    [cam(pos), cam(right)]
}

/// The side fisheye cameras of `frame` (cameras 2 and 3): left-looking, with its x axis
/// forward, and right-looking, with its x axis backward, both with the left camera's y (down).
pub fn fisheye_rig(p: &SceneParams, frame: u32) -> [Camera; 2] {
    let side = (FISHEYE_SIDE * p.scale).round().max(8.0) as u32;
    let s = side as f64 / FISHEYE_SIDE;
    let (rot, pos) = rig_pose(p, frame);
    let looking = [
        DMat3::from_cols(DVec3::Z, DVec3::Y, -DVec3::X),
        DMat3::from_cols(-DVec3::Z, DVec3::Y, DVec3::X),
    ];
    std::array::from_fn(|k| Camera {
        width: side,
        height: side,
        fx: FISHEYE_GAMMA[0] * s,
        fy: FISHEYE_GAMMA[1] * s,
        cx: (FISHEYE_CENTRE[0] + 0.5) * s,
        cy: (FISHEYE_CENTRE[1] + 0.5) * s,
        lens: Lens::Mei(FISHEYE_MEI),
        cam_to_world: DAffine3::from_mat3_translation(
            rot * looking[k],
            pos + rot * DVec3::from_array(FISHEYE_POSITION[k]),
        ),
    })
}

/// The left camera's axes and centre in the scene frame at `frame`.
fn rig_pose(p: &SceneParams, frame: u32) -> (DMat3, DVec3) {
    // A little deterministic wobble of heading and pitch, like a real drive.
    let mut r = rng::Rng::new(p.seed, rng::Purpose::Layout, &[0xCA, frame as u64]);
    let (yaw, pitch) = (r.normal() * 0.006, r.normal() * 0.004);
    // Camera axes (x right, y down, z forward) in the scene frame (x forward, y left, z up).
    let base = DMat3::from_cols(-DVec3::Y, -DVec3::Z, DVec3::X);
    let rot = DMat3::from_rotation_z(yaw) * DMat3::from_rotation_y(-pitch) * base;
    let pos = DVec3::new(
        frame as f64 * p.frame_spacing_m,
        RIG_Y + r.normal() * 0.05,
        p.camera_height_m,
    );
    (rot, pos)
}
