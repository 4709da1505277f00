//! Arrow codecs of the `cameras`, `primitives` and `dynamic_boxes` tables (their files in
//! `data_schema/`). Transforms are stored as row-major 4x4 matrices; reading
//! checks the bottom row and validates every primitive, naming the row and column on error.

use arrow::{
    array::ArrayRef,
    datatypes::{Float64Type, UInt32Type, UInt8Type},
    record_batch::RecordBatch,
};
use glam::{DAffine3, DMat3, DVec3};

use super::{Camera, Lens, Mei, Primitive, Shape};
use crate::{tables, Result, StageError};

/// One row of the cameras table.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraRow {
    pub frame: u32,
    /// 0 = left, 1 = right.
    pub camera: u8,
    pub eval: bool,
    pub cam: Camera,
}

/// Row-major 4x4 of an affine transform.
pub fn affine_to_row_major(m: &DAffine3) -> [f64; 16] {
    let r = m.matrix3.transpose(); // columns of r = rows of m
    let t = m.translation;
    [
        r.x_axis.x, r.x_axis.y, r.x_axis.z, t.x, //
        r.y_axis.x, r.y_axis.y, r.y_axis.z, t.y, //
        r.z_axis.x, r.z_axis.y, r.z_axis.z, t.z, //
        0.0, 0.0, 0.0, 1.0,
    ]
}

/// An affine transform from a row-major 4x4; errors if the bottom row is not `0 0 0 1`.
pub fn affine_from_row_major(m: &[f64]) -> std::result::Result<DAffine3, String> {
    if m.len() != 16 {
        return Err(format!("expected 16 values, found {}", m.len()));
    }
    if m[12..16] != [0.0, 0.0, 0.0, 1.0] {
        return Err(format!(
            "bottom row must be 0 0 0 1, found {:?} (not an affine transform)",
            &m[12..16]
        ));
    }
    let rows = DMat3::from_cols(
        DVec3::new(m[0], m[1], m[2]),
        DVec3::new(m[4], m[5], m[6]),
        DVec3::new(m[8], m[9], m[10]),
    );
    Ok(DAffine3 {
        matrix3: rows.transpose(),
        translation: DVec3::new(m[3], m[7], m[11]),
    })
}

fn row_err(table: &str, row: usize, col: &str, msg: impl std::fmt::Display) -> StageError {
    StageError::Input(format!("table `{table}` row {row} column `{col}`: {msg}"))
}

/// The primitives table (row index = `id`).
pub fn primitives_to_table(prims: &[Primitive]) -> Result<RecordBatch> {
    let mut cols = vec![tables::prim::<UInt32Type>(0..prims.len() as u32)];
    cols.extend(shape_columns(prims.iter()));
    tables::build("primitives", cols)
}

/// Validated primitives from the primitives table; `id` must equal the row index.
pub fn primitives_from_table(t: &RecordBatch) -> Result<Vec<Primitive>> {
    const T: &str = "primitives";
    let ids = tables::get_prim::<UInt32Type>(t, T, "id")?;
    if let Some(row) = (0..t.num_rows()).find(|&r| ids[r] as usize != r) {
        return Err(row_err(
            T,
            row,
            "id",
            format!("id {} is not the row index", ids[row]),
        ));
    }
    shapes_from_columns(t, T)
}

/// A moving object's box at one frame (KITTI-360's dynamic objects: one box per frame).
#[derive(Clone, Debug)]
pub struct DynamicBox {
    /// Stable over the sequence: label id * 1000 + instance (its value in the instance maps).
    pub object: u32,
    pub frame: u32,
    pub primitive: Primitive,
}

/// The `dynamic_boxes` table, rows in the order given.
pub fn dynamic_boxes_to_table(boxes: &[DynamicBox]) -> Result<RecordBatch> {
    let mut cols = vec![
        tables::prim::<UInt32Type>(boxes.iter().map(|b| b.object)),
        tables::prim::<UInt32Type>(boxes.iter().map(|b| b.frame)),
    ];
    cols.extend(shape_columns(boxes.iter().map(|b| &b.primitive)));
    tables::build("dynamic_boxes", cols)
}

/// Validated boxes of the `dynamic_boxes` table; each row's `object` must be its label and
/// instance, and an object may hold one box per frame.
pub fn dynamic_boxes_from_table(t: &RecordBatch) -> Result<Vec<DynamicBox>> {
    const T: &str = "dynamic_boxes";
    let objects = tables::get_prim::<UInt32Type>(t, T, "object")?;
    let frames = tables::get_prim::<UInt32Type>(t, T, "frame")?;
    let prims = shapes_from_columns(t, T)?;
    let mut seen = std::collections::BTreeMap::new();
    let mut out = Vec::with_capacity(prims.len());
    for (row, primitive) in prims.into_iter().enumerate() {
        let (object, frame) = (objects[row], frames[row]);
        let expected =
            u32::from(primitive.label) * crate::labels::INSTANCE_FACTOR + primitive.instance;
        if object != expected {
            return Err(row_err(
                T,
                row,
                "object",
                format!(
                    "{object} is not label * 1000 + instance ({} * 1000 + {})",
                    primitive.label, primitive.instance
                ),
            ));
        }
        if let Some(first) = seen.insert((object, frame), row) {
            return Err(row_err(
                T,
                row,
                "frame",
                format!("object {object} has a box at frame {frame} in row {first} already"),
            ));
        }
        out.push(DynamicBox {
            object,
            frame,
            primitive,
        });
    }
    Ok(out)
}

/// The columns `kind` to `faces` of a table of primitives (as in `primitives`).
fn shape_columns<'a>(prims: impl ExactSizeIterator<Item = &'a Primitive> + Clone) -> Vec<ArrayRef> {
    let mut transform = Vec::with_capacity(prims.len() * 16);
    let (mut polygon, mut vertices, mut faces) = (vec![], vec![], vec![]);
    for p in prims.clone() {
        transform.extend(affine_to_row_major(&p.to_world));
        let (mut pg, mut vs, mut fs) = (vec![], vec![], vec![]);
        match &p.shape {
            Shape::Cuboid | Shape::Ellipsoid => {}
            Shape::Extruded { polygon } => pg = polygon.iter().flatten().copied().collect(),
            Shape::Mesh { vertices, faces } => {
                vs = vertices.iter().flat_map(|v| v.to_array()).collect();
                fs = faces.iter().flatten().copied().collect();
            }
        }
        polygon.push(pg);
        vertices.push(vs);
        faces.push(fs);
    }
    vec![
        tables::strings(prims.clone().map(|p| p.shape.kind())),
        tables::prim::<UInt8Type>(prims.clone().map(|p| p.label)),
        tables::prim::<UInt32Type>(prims.map(|p| p.instance)),
        tables::fixed_list::<Float64Type>(16, transform),
        tables::list::<Float64Type>(polygon),
        tables::list::<Float64Type>(vertices),
        tables::list::<UInt32Type>(faces),
    ]
}

/// Validated primitives of the columns `kind` to `faces` of `table`, one per row.
fn shapes_from_columns(t: &RecordBatch, table: &str) -> Result<Vec<Primitive>> {
    let kinds = tables::get_strings(t, table, "kind")?;
    let labels = tables::get_prim::<UInt8Type>(t, table, "label")?;
    let instances = tables::get_prim::<UInt32Type>(t, table, "instance")?;
    let (transform, n) = tables::get_fixed_list::<Float64Type>(t, table, "transform")?;
    if n != 16 {
        return Err(row_err(
            table,
            0,
            "transform",
            format!("expected 16 values per row, found {n}"),
        ));
    }
    let polygon = tables::get_list::<Float64Type>(t, table, "polygon")?;
    let vertices = tables::get_list::<Float64Type>(t, table, "vertices")?;
    let faces = tables::get_list::<UInt32Type>(t, table, "faces")?;
    let mut out = Vec::with_capacity(t.num_rows());
    for row in 0..t.num_rows() {
        let m = affine_from_row_major(&transform[row * 16..row * 16 + 16])
            .map_err(|e| row_err(table, row, "transform", e))?;
        let (kind, col) = (kinds.value(row), "kind");
        let shape = match kind {
            "cuboid" => Shape::Cuboid,
            "ellipsoid" => Shape::Ellipsoid,
            "extruded" => {
                let flat = polygon.row(row);
                if flat.len() % 2 != 0 {
                    return Err(row_err(table, row, "polygon", "odd number of coordinates"));
                }
                Shape::Extruded {
                    polygon: flat.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
                }
            }
            "mesh" => {
                let (vs, fs) = (vertices.row(row), faces.row(row));
                if vs.len() % 3 != 0 {
                    return Err(row_err(
                        table,
                        row,
                        "vertices",
                        "length is not a multiple of 3",
                    ));
                }
                if fs.len() % 3 != 0 {
                    return Err(row_err(
                        table,
                        row,
                        "faces",
                        "length is not a multiple of 3",
                    ));
                }
                Shape::Mesh {
                    vertices: vs.chunks_exact(3).map(DVec3::from_slice).collect(),
                    faces: fs.chunks_exact(3).map(|f| [f[0], f[1], f[2]]).collect(),
                }
            }
            other => {
                return Err(row_err(
                    table,
                    row,
                    col,
                    format!(
                        "unknown kind `{other}` (expected cuboid, ellipsoid, extruded or mesh)"
                    ),
                ))
            }
        };
        let bad_col = match &shape {
            Shape::Cuboid | Shape::Ellipsoid => "transform",
            Shape::Extruded { .. } => "polygon",
            Shape::Mesh { .. } => "faces",
        };
        let p = Primitive::new(shape, m, labels[row], instances[row]).map_err(|e| {
            let col = if e.to_string().contains("transform") {
                "transform"
            } else if matches!(e, super::GeometryError::NonFinite("mesh vertices")) {
                "vertices"
            } else {
                bad_col
            };
            row_err(table, row, col, e)
        })?;
        out.push(p);
    }
    Ok(out)
}

/// Values per row of the `lens_params` column.
const LENS_PARAMS: usize = 6;

/// The `lens_params` of a lens: MEI's xi, k1, k2, p1, p2 and its half angle; zeros for a
/// pinhole.
fn lens_params(lens: &Lens) -> [f64; LENS_PARAMS] {
    match lens {
        Lens::Pinhole => [0.0; LENS_PARAMS],
        Lens::Mei(m) => [m.xi, m.k1, m.k2, m.p1, m.p2, m.max_half_angle_deg],
    }
}

/// The cameras table.
pub fn cameras_to_table(rows: &[CameraRow]) -> Result<RecordBatch> {
    let f = |g: fn(&CameraRow) -> f64| tables::prim::<Float64Type>(rows.iter().map(g));
    tables::build(
        "cameras",
        vec![
            tables::prim::<UInt32Type>(rows.iter().map(|r| r.frame)),
            tables::prim::<UInt8Type>(rows.iter().map(|r| r.camera)),
            tables::prim::<UInt32Type>(rows.iter().map(|r| r.cam.width)),
            tables::prim::<UInt32Type>(rows.iter().map(|r| r.cam.height)),
            f(|r| r.cam.fx),
            f(|r| r.cam.fy),
            f(|r| r.cam.cx),
            f(|r| r.cam.cy),
            tables::strings(rows.iter().map(|r| r.cam.lens.name())),
            tables::fixed_list::<Float64Type>(
                LENS_PARAMS,
                rows.iter().flat_map(|r| lens_params(&r.cam.lens)).collect(),
            ),
            tables::fixed_list::<Float64Type>(
                16,
                rows.iter()
                    .flat_map(|r| affine_to_row_major(&r.cam.cam_to_world))
                    .collect(),
            ),
            tables::bools(rows.iter().map(|r| r.eval)),
        ],
    )
}

/// Camera rows from the cameras table; checks positive sizes and focal lengths and finite
/// values.
pub fn cameras_from_table(t: &RecordBatch) -> Result<Vec<CameraRow>> {
    const T: &str = "cameras";
    let frame = tables::get_prim::<UInt32Type>(t, T, "frame")?;
    let camera = tables::get_prim::<UInt8Type>(t, T, "camera")?;
    let width = tables::get_prim::<UInt32Type>(t, T, "width")?;
    let height = tables::get_prim::<UInt32Type>(t, T, "height")?;
    let fx = tables::get_prim::<Float64Type>(t, T, "fx")?;
    let fy = tables::get_prim::<Float64Type>(t, T, "fy")?;
    let cx = tables::get_prim::<Float64Type>(t, T, "cx")?;
    let cy = tables::get_prim::<Float64Type>(t, T, "cy")?;
    let lens_name = tables::get_strings(t, T, "lens")?;
    let (lens_values, k) = tables::get_fixed_list::<Float64Type>(t, T, "lens_params")?;
    if k != LENS_PARAMS {
        return Err(row_err(
            T,
            0,
            "lens_params",
            format!("expected {LENS_PARAMS} values per row, found {k}"),
        ));
    }
    let (pose, n) = tables::get_fixed_list::<Float64Type>(t, T, "cam_to_world")?;
    if n != 16 {
        return Err(row_err(
            T,
            0,
            "cam_to_world",
            format!("expected 16 values per row, found {n}"),
        ));
    }
    let eval = tables::get_bools(t, T, "eval")?;
    (0..t.num_rows())
        .map(|row| {
            if width[row] == 0 || height[row] == 0 {
                return Err(row_err(T, row, "width", "image size must be positive"));
            }
            for (col, v) in [
                ("fx", fx[row]),
                ("fy", fy[row]),
                ("cx", cx[row]),
                ("cy", cy[row]),
            ] {
                if !v.is_finite() || (col.starts_with('f') && v <= 0.0) {
                    return Err(row_err(T, row, col, format!("bad value {v}")));
                }
            }
            let v = &lens_values[row * LENS_PARAMS..(row + 1) * LENS_PARAMS];
            let lens = match lens_name.value(row) {
                "pinhole" => Lens::Pinhole,
                "MEI" => {
                    let mei = Mei {
                        xi: v[0],
                        k1: v[1],
                        k2: v[2],
                        p1: v[3],
                        p2: v[4],
                        max_half_angle_deg: v[5],
                    };
                    mei.validate()
                        .map_err(|e| row_err(T, row, "lens_params", e))?;
                    Lens::Mei(mei)
                }
                other => {
                    return Err(row_err(
                        T,
                        row,
                        "lens",
                        format!("unknown lens `{other}` (known: pinhole, MEI)"),
                    ))
                }
            };
            let m = affine_from_row_major(&pose[row * 16..row * 16 + 16])
                .map_err(|e| row_err(T, row, "cam_to_world", e))?;
            if !m.is_finite() {
                return Err(row_err(T, row, "cam_to_world", "non-finite value"));
            }
            Ok(CameraRow {
                frame: frame[row],
                camera: camera[row],
                eval: eval[row],
                cam: Camera {
                    width: width[row],
                    height: height[row],
                    fx: fx[row],
                    fy: fy[row],
                    cx: cx[row],
                    cy: cy[row],
                    lens,
                    cam_to_world: m,
                },
            })
        })
        .collect()
}
