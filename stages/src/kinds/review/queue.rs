//! The review's tables beside the maps: regions, the ranked queue of objects, per-image figures.

use std::collections::BTreeMap;
use std::sync::Arc;

use arrow::array::{ArrayRef, UInt32Array};
use arrow::datatypes::{Float32Type, Float64Type, UInt16Type, UInt32Type, UInt64Type, UInt8Type};
use arrow::record_batch::RecordBatch;

use crate::geometry::Primitive;
use crate::review::REASONS;
use crate::stage::Result;
use crate::{labels, tables};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RegionKind {
    Label,
    CoverageGap,
}

impl RegionKind {
    fn name(self) -> &'static str {
        match self {
            RegionKind::Label => "label",
            RegionKind::CoverageGap => "coverage_gap",
        }
    }
}

/// One listed region (a `review_regions` row).
#[derive(Debug, Clone, PartialEq)]
pub struct Region {
    pub id: u32,
    pub frame: u32,
    pub camera: u8,
    pub index: u16,
    pub kind: RegionKind,
    pub class: u8,
    pub reason: u8,
    pub primitive: Option<u32>,
    pub pixels: u32,
    /// x0, y0, x1, y1 (inclusive).
    pub bbox: [u32; 4],
    pub expected_wrong: f64,
}

/// One `review_frames` row.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRow {
    pub frame: u32,
    pub camera: u8,
    pub score: f64,
    pub flagged: f64,
    pub coverage: f64,
    pub gap_pixels: u64,
    pub regions: u32,
}

fn nullable_u32(v: impl IntoIterator<Item = Option<u32>>) -> ArrayRef {
    Arc::new(UInt32Array::from(v.into_iter().collect::<Vec<_>>()))
}

pub fn regions_table(seq: &str, regions: &[Region]) -> Result<RecordBatch> {
    let col = |f: fn(&Region) -> u32| tables::prim::<UInt32Type>(regions.iter().map(f));
    tables::build(
        "review_regions",
        vec![
            col(|r| r.id),
            tables::strings(regions.iter().map(|_| seq)),
            col(|r| r.frame),
            tables::prim::<UInt8Type>(regions.iter().map(|r| r.camera)),
            tables::prim::<UInt16Type>(regions.iter().map(|r| r.index)),
            tables::strings(regions.iter().map(|r| r.kind.name())),
            tables::prim::<UInt8Type>(regions.iter().map(|r| r.class)),
            tables::strings(
                regions
                    .iter()
                    .map(|r| REASONS.get(r.reason as usize).copied().unwrap_or("")),
            ),
            nullable_u32(regions.iter().map(|r| r.primitive)),
            col(|r| r.pixels),
            col(|r| r.bbox[0]),
            col(|r| r.bbox[1]),
            col(|r| r.bbox[2]),
            col(|r| r.bbox[3]),
            tables::prim::<Float64Type>(regions.iter().map(|r| r.expected_wrong)),
            tables::prim::<Float32Type>(
                regions
                    .iter()
                    .map(|r| (r.expected_wrong / r.pixels.max(1) as f64) as f32),
            ),
        ],
    )
}

/// One queue entry under construction.
struct Entry<'r> {
    kind: &'static str,
    primitive: Option<u32>,
    regions: Vec<&'r Region>,
}

impl Entry<'_> {
    fn expected_wrong(&self) -> f64 {
        self.regions.iter().map(|r| r.expected_wrong).sum()
    }
}

fn class_name(id: u8) -> &'static str {
    labels::by_id(id).map(|l| l.name).unwrap_or("unlabeled")
}

/// Label regions of one primitive become one entry; every other region is its own.
pub fn queue_table(regions: &[Region], prims: &[Primitive]) -> Result<RecordBatch> {
    let mut by_prim: BTreeMap<u32, Vec<&Region>> = BTreeMap::new();
    let mut entries: Vec<Entry> = Vec::new();
    for r in regions {
        match (r.kind, r.primitive) {
            (RegionKind::Label, Some(p)) if (p as usize) < prims.len() => {
                by_prim.entry(p).or_default().push(r)
            }
            (kind, _) => entries.push(Entry {
                kind: match kind {
                    RegionKind::Label => "label",
                    RegionKind::CoverageGap => "coverage_gap",
                },
                primitive: None,
                regions: vec![r],
            }),
        }
    }
    entries.extend(by_prim.into_iter().map(|(p, regions)| Entry {
        kind: "primitive",
        primitive: Some(p),
        regions,
    }));
    // Highest expected wrong pixels first; ties by the first region's id (stable bytes).
    entries.sort_by(|a, b| {
        b.expected_wrong()
            .total_cmp(&a.expected_wrong())
            .then(a.regions[0].id.cmp(&b.regions[0].id))
    });
    let mut rows = Rows::default();
    for (rank, e) in entries.iter().enumerate() {
        let first = e.regions[0];
        let (class, instance) = match e.primitive {
            Some(p) => (prims[p as usize].label, prims[p as usize].instance),
            None => (first.class, 0),
        };
        let object = match (e.kind, e.primitive) {
            (_, Some(p)) if instance > 0 => {
                format!("{} {} (primitive {p})", class_name(class), instance)
            }
            (_, Some(p)) => format!("{} (primitive {p})", class_name(class)),
            ("coverage_gap", _) => format!(
                "coverage gap ({}?), frame {} camera {}",
                class_name(class),
                first.frame,
                first.camera
            ),
            _ => format!(
                "{} without a primitive, frame {} camera {}",
                class_name(class),
                first.frame,
                first.camera
            ),
        };
        let mut images: Vec<(u32, u8)> = e.regions.iter().map(|r| (r.frame, r.camera)).collect();
        images.sort_unstable();
        images.dedup();
        let worst = e
            .regions
            .iter()
            .max_by(|a, b| {
                a.expected_wrong
                    .total_cmp(&b.expected_wrong)
                    .then(b.id.cmp(&a.id))
            })
            .expect("an entry has a region");
        rows.rank.push(rank as u32 + 1);
        rows.object.push(object);
        rows.kind.push(e.kind);
        rows.primitive.push(e.primitive);
        rows.class.push(class);
        rows.instance.push(instance);
        rows.regions.push(e.regions.len() as u32);
        rows.images.push(images.len() as u32);
        rows.pixels
            .push(e.regions.iter().map(|r| r.pixels as u64).sum());
        rows.expected_wrong.push(e.expected_wrong());
        rows.first_frame
            .push(e.regions.iter().map(|r| r.frame).min().unwrap_or(0));
        rows.last_frame
            .push(e.regions.iter().map(|r| r.frame).max().unwrap_or(0));
        rows.worst.push(worst.id);
    }
    rows.table()
}

#[derive(Default)]
struct Rows {
    rank: Vec<u32>,
    object: Vec<String>,
    kind: Vec<&'static str>,
    primitive: Vec<Option<u32>>,
    class: Vec<u8>,
    instance: Vec<u32>,
    regions: Vec<u32>,
    images: Vec<u32>,
    pixels: Vec<u64>,
    expected_wrong: Vec<f64>,
    first_frame: Vec<u32>,
    last_frame: Vec<u32>,
    worst: Vec<u32>,
}

impl Rows {
    fn table(self) -> Result<RecordBatch> {
        tables::build(
            "review_queue",
            vec![
                tables::prim::<UInt32Type>(self.rank),
                tables::strings(self.object),
                tables::strings(self.kind),
                nullable_u32(self.primitive),
                tables::prim::<UInt8Type>(self.class),
                tables::prim::<UInt32Type>(self.instance),
                tables::prim::<UInt32Type>(self.regions),
                tables::prim::<UInt32Type>(self.images),
                tables::prim::<UInt64Type>(self.pixels),
                tables::prim::<Float64Type>(self.expected_wrong),
                tables::prim::<UInt32Type>(self.first_frame),
                tables::prim::<UInt32Type>(self.last_frame),
                tables::prim::<UInt32Type>(self.worst),
            ],
        )
    }
}

pub fn frames_table(seq: &str, frames: &[FrameRow]) -> Result<RecordBatch> {
    tables::build(
        "review_frames",
        vec![
            tables::strings(frames.iter().map(|_| seq)),
            tables::prim::<UInt32Type>(frames.iter().map(|f| f.frame)),
            tables::prim::<UInt8Type>(frames.iter().map(|f| f.camera)),
            tables::prim::<Float64Type>(frames.iter().map(|f| f.score)),
            tables::prim::<Float64Type>(frames.iter().map(|f| f.flagged)),
            tables::prim::<Float64Type>(frames.iter().map(|f| f.coverage)),
            tables::prim::<UInt64Type>(frames.iter().map(|f| f.gap_pixels)),
            tables::prim::<UInt32Type>(frames.iter().map(|f| f.regions)),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow::array::Array;

    fn region(id: u32, frame: u32, kind: RegionKind, primitive: Option<u32>, e: f64) -> Region {
        Region {
            id,
            frame,
            camera: 0,
            index: 1,
            kind,
            class: 26,
            reason: 2,
            primitive,
            pixels: 10,
            bbox: [0, 0, 3, 3],
            expected_wrong: e,
        }
    }

    #[test]
    fn regions_of_one_primitive_are_one_object_ranked_by_expected_wrong_pixels() {
        use crate::geometry::{DAffine3, Primitive, Shape};
        let prim = |label, instance| {
            Primitive::new(Shape::Cuboid, DAffine3::IDENTITY, label, instance).unwrap()
        };
        let prims = vec![prim(11, 0), prim(26, 3)];
        let car = 1;
        let regions = [
            region(1, 3, RegionKind::Label, Some(car), 4.0),
            region(2, 3, RegionKind::CoverageGap, None, 6.0),
            region(3, 4, RegionKind::Label, Some(car), 5.0),
            region(4, 5, RegionKind::Label, None, 1.0),
        ];
        let t = queue_table(&regions, &prims).unwrap();
        assert_eq!(t.num_rows(), 3);
        let kind = tables::get_strings(&t, "review_queue", "kind").unwrap();
        assert_eq!(
            (0..3).map(|i| kind.value(i)).collect::<Vec<_>>(),
            ["primitive", "coverage_gap", "label"]
        );
        let n = tables::get_prim::<UInt32Type>(&t, "review_queue", "regions").unwrap();
        assert_eq!(n, &[2, 1, 1]);
        let worst = tables::get_prim::<UInt32Type>(&t, "review_queue", "worst_region").unwrap();
        assert_eq!(worst, &[3, 2, 4]);
        let (first, last) = (
            tables::get_prim::<UInt32Type>(&t, "review_queue", "first_frame").unwrap(),
            tables::get_prim::<UInt32Type>(&t, "review_queue", "last_frame").unwrap(),
        );
        assert_eq!((first[0], last[0]), (3, 4));
        let prim = t.column_by_name("primitive").unwrap();
        assert!(!prim.is_null(0) && prim.is_null(1) && prim.is_null(2));
        let object = tables::get_strings(&t, "review_queue", "object").unwrap();
        assert_eq!(object.value(0), "car 3 (primitive 1)");
        assert!(
            object.value(1).starts_with("coverage gap"),
            "{}",
            object.value(1)
        );
    }
}
