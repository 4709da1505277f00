//! The KITTI-360 label table (ids, kittiIds, trainIds, colours, thing/stuff) and the subset of
//! classes the Panoptic NeRF paper evaluates. Label maps everywhere in the project hold the
//! label `id` (as KITTI-360's `semantic/*.png` do); instance maps hold `id * 1000 + instance`.

/// One KITTI-360 class.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Label {
    pub name: &'static str,
    /// The label id stored in semantic PNGs.
    pub id: u8,
    /// The id used by the 3D bounding primitives' `semanticId` in the XML annotations.
    pub kitti_id: i16,
    pub train_id: u8,
    /// Whether the class has instances in KITTI-360's panoptic ground truth.
    pub has_instances: bool,
    pub color: [u8; 3],
}

const fn l(
    name: &'static str,
    id: u8,
    kitti_id: i16,
    train_id: u8,
    inst: bool,
    color: [u8; 3],
) -> Label {
    Label {
        name,
        id,
        kitti_id,
        train_id,
        has_instances: inst,
        color,
    }
}

/// The KITTI-360 classes this project knows (the devkit's `labels.py`, the rows that occur in
/// annotations used for label transfer).
pub const LABELS: &[Label] = &[
    l("unlabeled", 0, -1, 255, false, [0, 0, 0]),
    l("road", 7, 1, 0, false, [128, 64, 128]),
    l("sidewalk", 8, 3, 1, false, [244, 35, 232]),
    l("parking", 9, 2, 255, false, [250, 170, 160]),
    l("rail track", 10, 10, 255, false, [230, 150, 140]),
    l("building", 11, 11, 2, true, [70, 70, 70]),
    l("wall", 12, 7, 3, false, [102, 102, 156]),
    l("fence", 13, 8, 4, false, [190, 153, 153]),
    l("guard rail", 14, 30, 255, false, [180, 165, 180]),
    l("bridge", 15, 31, 255, false, [150, 100, 100]),
    l("tunnel", 16, 32, 255, false, [150, 120, 90]),
    l("pole", 17, 21, 5, true, [153, 153, 153]),
    l("polegroup", 18, -1, 255, false, [153, 153, 153]),
    l("traffic light", 19, 23, 6, true, [250, 170, 30]),
    l("traffic sign", 20, 24, 7, true, [220, 220, 0]),
    l("vegetation", 21, 5, 8, false, [107, 142, 35]),
    l("terrain", 22, 4, 9, false, [152, 251, 152]),
    l("sky", 23, 9, 10, false, [70, 130, 180]),
    l("person", 24, 19, 11, true, [220, 20, 60]),
    l("rider", 25, 20, 12, true, [255, 0, 0]),
    l("car", 26, 13, 13, true, [0, 0, 142]),
    l("truck", 27, 14, 14, true, [0, 0, 70]),
    l("bus", 28, 34, 15, true, [0, 60, 100]),
    l("caravan", 29, 16, 255, true, [0, 0, 90]),
    l("trailer", 30, 15, 255, true, [0, 0, 110]),
    l("train", 31, 33, 16, true, [0, 80, 100]),
    l("motorcycle", 32, 17, 17, true, [0, 0, 230]),
    l("bicycle", 33, 18, 18, true, [119, 11, 32]),
    l("garage", 34, 12, 2, true, [64, 128, 128]),
    l("gate", 35, 6, 4, false, [190, 153, 153]),
    l("stop", 36, 29, 255, true, [150, 120, 90]),
    l("smallpole", 37, 22, 5, true, [153, 153, 153]),
    l("lamp", 38, 25, 255, true, [0, 64, 64]),
    l("trash bin", 39, 26, 255, true, [0, 128, 192]),
    l("vending machine", 40, 27, 255, true, [128, 64, 0]),
    l("box", 41, 28, 255, true, [64, 64, 128]),
    l("unknown construction", 42, 35, 255, false, [102, 0, 0]),
    l("unknown vehicle", 43, 36, 255, false, [51, 0, 51]),
    l("unknown object", 44, 37, 255, false, [32, 32, 32]),
];

pub const UNLABELED: u8 = 0;
pub const ROAD: u8 = 7;
pub const SIDEWALK: u8 = 8;
pub const PARKING: u8 = 9;
pub const BUILDING: u8 = 11;
pub const WALL: u8 = 12;
pub const FENCE: u8 = 13;
pub const VEGETATION: u8 = 21;
pub const TERRAIN: u8 = 22;
pub const SKY: u8 = 23;
pub const RIDER: u8 = 25;
pub const CAR: u8 = 26;
pub const CARAVAN: u8 = 29;
pub const TRAILER: u8 = 30;
pub const BICYCLE: u8 = 33;
pub const GATE: u8 = 35;
pub const BOX: u8 = 41;

/// The classes the Panoptic NeRF paper evaluates (label ids), in label-id order.
pub const PAPER_CLASSES: &[u8] = &[
    ROAD, SIDEWALK, PARKING, BUILDING, WALL, FENCE, VEGETATION, TERRAIN, SKY, CAR, CARAVAN,
    TRAILER, GATE, BOX,
];

/// The "thing" classes of the paper's panoptic evaluation.
pub const PAPER_THINGS: &[u8] = &[BUILDING, CAR, CARAVAN, TRAILER, BOX];

/// Instance maps encode `id * 1000 + instance`.
pub const INSTANCE_FACTOR: u32 = 1000;

/// The label with this id.
pub fn by_id(id: u8) -> Option<&'static Label> {
    LABELS.iter().find(|l| l.id == id)
}

/// The label whose kittiId (the XML `semanticId`) is `kitti_id`.
pub fn by_kitti_id(kitti_id: i16) -> Option<&'static Label> {
    LABELS
        .iter()
        .find(|l| l.kitti_id == kitti_id && l.kitti_id >= 0)
}

/// The label with this name.
pub fn by_name(name: &str) -> Option<&'static Label> {
    LABELS.iter().find(|l| l.name == name)
}

/// Palette colour of a label id (black for unknown ids).
pub fn color(id: u8) -> [u8; 3] {
    by_id(id).map_or([0, 0, 0], |l| l.color)
}

/// Whether the paper treats this class as a "thing" in panoptic evaluation.
pub fn is_paper_thing(id: u8) -> bool {
    PAPER_THINGS.contains(&id)
}

/// Whether pixel `p` of a row-major label map `width` wide has a pixel of another label in
/// its 8-neighbourhood (inside the image).
fn on_label_edge(labels: &[u8], width: usize, p: usize) -> bool {
    let height = labels.len() / width;
    let (x, y) = (p % width, p / width);
    let l = labels[p];
    (y.saturating_sub(1)..(y + 2).min(height))
        .any(|ny| (x.saturating_sub(1)..(x + 2).min(width)).any(|nx| labels[ny * width + nx] != l))
}

/// Per pixel of a row-major label map `width` wide: [`on_label_edge`] (a class boundary, where
/// foreground and background, or LiDAR and camera, meet).
pub fn label_edges(labels: &[u8], width: usize) -> Vec<bool> {
    if width == 0 {
        return vec![false; labels.len()];
    }
    (0..labels.len())
        .map(|p| on_label_edge(labels, width, p))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_and_kitti_ids_are_unique() {
        for (i, a) in LABELS.iter().enumerate() {
            for b in &LABELS[i + 1..] {
                assert_ne!(a.id, b.id, "{} / {}", a.name, b.name);
                if a.kitti_id >= 0 {
                    assert_ne!(a.kitti_id, b.kitti_id, "{} / {}", a.name, b.name);
                }
            }
        }
    }

    #[test]
    fn paper_classes_match_the_reference_table() {
        // (name, id, kittiId, colour) from the reference's label list.
        let expect: &[(&str, u8, i16, [u8; 3])] = &[
            ("road", 7, 1, [128, 64, 128]),
            ("sidewalk", 8, 3, [244, 35, 232]),
            ("parking", 9, 2, [250, 170, 160]),
            ("building", 11, 11, [70, 70, 70]),
            ("wall", 12, 7, [102, 102, 156]),
            ("fence", 13, 8, [190, 153, 153]),
            ("vegetation", 21, 5, [107, 142, 35]),
            ("terrain", 22, 4, [152, 251, 152]),
            ("sky", 23, 9, [70, 130, 180]),
            ("car", 26, 13, [0, 0, 142]),
            ("caravan", 29, 16, [0, 0, 90]),
            ("trailer", 30, 15, [0, 0, 110]),
            ("gate", 35, 6, [190, 153, 153]),
            ("box", 41, 28, [64, 64, 128]),
        ];
        for &(name, id, kid, color) in expect {
            let l = by_name(name).unwrap();
            assert_eq!((l.id, l.kitti_id, l.color), (id, kid, color), "{name}");
            assert_eq!(by_kitti_id(kid).unwrap().id, id);
            assert!(PAPER_CLASSES.contains(&id));
        }
        assert_eq!(PAPER_CLASSES.len(), expect.len());
    }

    /// `on_label_edge` against a brute-force scan of the 8-neighbourhood, on random small maps
    /// (one-pixel, one-row and one-column images included).
    #[test]
    fn label_edges_match_a_brute_force_scan() {
        let mut rng = crate::rng::SplitMix64::new(3);
        for (w, h) in [(1, 1), (1, 5), (6, 1), (7, 5), (4, 4)] {
            for _ in 0..20 {
                let map: Vec<u8> = (0..w * h).map(|_| (rng.unit() * 2.5) as u8).collect();
                let edges = label_edges(&map, w);
                for p in 0..w * h {
                    let (x, y) = ((p % w) as i64, (p / w) as i64);
                    let mut want = false;
                    for dy in -1..=1i64 {
                        for dx in -1..=1i64 {
                            let (nx, ny) = (x + dx, y + dy);
                            if nx >= 0 && ny >= 0 && nx < w as i64 && ny < h as i64 {
                                want |= map[(ny * w as i64 + nx) as usize] != map[p];
                            }
                        }
                    }
                    assert_eq!(
                        (edges[p], on_label_edge(&map, w, p)),
                        (want, want),
                        "{w}x{h} map {map:?} pixel {p}"
                    );
                }
            }
        }
    }
}
