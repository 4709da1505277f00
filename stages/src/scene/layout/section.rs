//! The street's cross-section: the |y| boundaries and heights of its strips, and where the
//! rig drives.

/// Half-widths of the cross-section strips (|y| boundaries), metres.
pub const ROAD_HALF: f64 = 4.0;
pub const PARKING_OUTER: f64 = 6.2;
/// A planted verge (terrain, street trees) between the parking strip and the sidewalk.
pub const VERGE_OUTER: f64 = 7.2;
pub const SIDEWALK_OUTER: f64 = 9.0;
pub const KERB: f64 = 0.12;
pub const GARDEN_TOP: f64 = 0.1;
pub const GARDEN_OUTER: f64 = 45.0;
/// Lateral position of the left camera (the rig drives in the right lane).
pub const RIG_Y: f64 = -2.0;
