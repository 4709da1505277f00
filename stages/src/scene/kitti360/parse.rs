//! Readers of the KITTI-360 file formats: `cam0_to_world.txt`, `perspective.txt`,
//! `calib_cam_to_velo.txt`, the `data_3d_bboxes` OpenCV FileStorage XML, PNGs (RGB, 8-bit
//! labels, 16-bit instances and depth) and velodyne `.bin` scans.
//!
//! Every error is a [`StageError::Input`] whose message starts with the file's path, then names
//! the element (line number and key, XML element and child, pixel) and the problem. Nothing
//! here panics on malformed input.

use std::collections::BTreeMap;
use std::path::Path;

use glam::{DAffine3, DMat3, DVec3};

use crate::geometry::io::affine_from_row_major;
use crate::{Result, StageError};

/// An input error naming `path` and what is wrong with it.
pub fn err(path: &Path, what: impl std::fmt::Display) -> StageError {
    StageError::Input(format!("{}: {what}", path.display()))
}

/// The whole file as text; a missing or unreadable file is an error naming it.
pub fn read_text(path: &Path) -> Result<String> {
    let bytes = read_bytes(path)?;
    let text = String::from_utf8(bytes)
        .map_err(|e| err(path, format!("cannot read: not UTF-8 text: {e}")))?;
    // Editors on Windows write a byte order mark; it is not part of the first key.
    Ok(match text.strip_prefix('\u{feff}') {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// The bytes of an input file (a regular file only: see [`crate::input_file`]).
pub fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    if let Some(what) = crate::input_file::not_regular(path) {
        return Err(err(path, format!("is {what}, expected a regular file")));
    }
    std::fs::read(path).map_err(|e| err(path, format!("cannot read: {e}")))
}

fn parse_f64(path: &Path, at: &str, tok: &str) -> Result<f64> {
    let v: f64 = tok
        .parse()
        .map_err(|_| err(path, format!("{at}: `{tok}` is not a number")))?;
    if !v.is_finite() {
        return Err(err(path, format!("{at}: non-finite value `{tok}`")));
    }
    Ok(v)
}

/// Checks the upper 3x3 of a pose is a rotation (orthonormal, determinant +1).
pub(super) fn check_rotation(path: &Path, at: &str, m: &DMat3) -> Result<()> {
    let d = m.transpose() * *m - DMat3::IDENTITY;
    let off = d.x_axis.abs().max_element() + d.y_axis.abs().max_element();
    let off = off + d.z_axis.abs().max_element();
    if off > 1e-3 || m.determinant() < 0.0 {
        return Err(err(
            path,
            format!("{at}: the upper 3x3 is not a rotation (not orthonormal with determinant +1)"),
        ));
    }
    Ok(())
}

/// `cam0_to_world.txt`: per line a frame number and a row-major 4x4 (rectified left camera ->
/// world). Frames need not be contiguous; a frame listed twice is an error. A 3x4 line (12
/// numbers) is accepted with the bottom row implied.
pub fn poses(path: &Path, text: &str) -> Result<BTreeMap<u32, DAffine3>> {
    let mut out = BTreeMap::new();
    let mut lines = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let at = format!("line {}", i + 1);
        let mut toks = line.split_whitespace();
        let ftok = toks.next().unwrap_or_default();
        let frame: u32 = ftok.parse().map_err(|_| {
            err(
                path,
                format!("{at}: frame number `{ftok}` is not an integer"),
            )
        })?;
        let at = format!("line {} (frame {frame})", i + 1);
        let mut v = toks
            .map(|t| parse_f64(path, &at, t))
            .collect::<Result<Vec<f64>>>()?;
        if v.len() == 12 {
            v.extend([0.0, 0.0, 0.0, 1.0]);
        }
        if v.len() != 16 {
            return Err(err(
                path,
                format!(
                    "{at}: expected the frame number and 16 numbers (a 4x4 matrix), found {}",
                    v.len()
                ),
            ));
        }
        let m = affine_from_row_major(&v).map_err(|e| err(path, format!("{at}: {e}")))?;
        check_rotation(path, &at, &m.matrix3)?;
        if out.insert(frame, m).is_some() {
            return Err(err(path, format!("{at}: frame {frame} is listed twice")));
        }
        lines.insert(frame, i + 1);
    }
    if out.is_empty() {
        return Err(err(path, "no poses in the file"));
    }
    check_trajectory(path, &out, &lines)?;
    Ok(out)
}

/// The farthest a camera may move per frame: a car at 10 Hz moves a few metres; this is
/// 1000 m/s, so only a broken pose exceeds it.
pub const MAX_STEP_M_PER_FRAME: f64 = 100.0;

/// Consecutive poses (by frame number) are at most [`MAX_STEP_M_PER_FRAME`] per frame apart.
/// A jump names the frame of the two that is farther from the sequence's median position (an
/// outlier moves away and back; the median ignores it).
fn check_trajectory(
    path: &Path,
    poses: &BTreeMap<u32, DAffine3>,
    lines: &BTreeMap<u32, usize>,
) -> Result<()> {
    let median = |axis: usize| {
        let mut v: Vec<f64> = poses.values().map(|p| p.translation[axis]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let centre = DVec3::new(median(0), median(1), median(2));
    let frames: Vec<(&u32, &DAffine3)> = poses.iter().collect();
    for pair in frames.windows(2) {
        let ((&fa, a), (&fb, b)) = (pair[0], pair[1]);
        let step = a.translation.distance(b.translation);
        let gap = f64::from(fb - fa);
        if step.is_finite() && step <= MAX_STEP_M_PER_FRAME * gap {
            continue;
        }
        let far_a = a.translation.distance(centre) > b.translation.distance(centre);
        let (bad, other) = if far_a { (fa, fb) } else { (fb, fa) };
        let pos = poses[&bad].translation;
        return Err(err(
            path,
            format!(
                "line {} (frame {bad}): the camera is at ({:.6e}, {:.6e}, {:.6e}), {step:.3e} m \
                 from frame {other} ({gap} frames apart) and {:.3e} m from the sequence's median \
                 position; a pose may move at most {MAX_STEP_M_PER_FRAME} m per frame",
                lines[&bad],
                pos.x,
                pos.y,
                pos.z,
                pos.distance(centre),
            ),
        ));
    }
    Ok(())
}

/// The largest image width or height `S_rect_00` may give.
pub const MAX_IMAGE_SIDE: u32 = 100_000;

/// `KEY: numbers` lines (perspective.txt, calib_cam_to_velo.txt without key).
pub(super) fn keyed(path: &Path, text: &str) -> Result<BTreeMap<String, (usize, Vec<f64>)>> {
    let mut out = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        let Some((key, rest)) = line.split_once(':') else {
            continue;
        };
        let key = key.trim().to_string();
        let at = format!("line {} `{key}`", i + 1);
        let v = rest
            .split_whitespace()
            .map(|t| parse_f64(path, &at, t))
            .collect::<Result<Vec<f64>>>();
        if let Some((first, _)) = out.get(&key) {
            // Which one was meant? (Duplicate pose frames are an error for the same reason.)
            return Err(err(
                path,
                format!("{at}: `{key}` is given twice (first on line {first})"),
            ));
        }
        // Lines we do not use (calib_time, ...) may hold anything.
        match v {
            Ok(v) => {
                out.insert(key, (i + 1, v));
            }
            Err(e) if ["P_rect_00", "P_rect_01", "R_rect_00", "S_rect_00"].contains(&&*key) => {
                return Err(e)
            }
            Err(_) => {}
        }
    }
    Ok(out)
}

/// The rectified stereo calibration of `perspective.txt`.
#[derive(Clone, Debug, PartialEq)]
pub struct Perspective {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    /// Principal point in KITTI/OpenCV pixel coordinates (pixel centres at integers).
    pub cx_file: f64,
    pub cy_file: f64,
    /// Baseline from `P_rect_01[0,3] = -fx * b`, metres.
    pub baseline: f64,
    /// `R_rect_00` (unrectified -> rectified left camera), identity when absent.
    pub r_rect: DMat3,
}

/// Parses `perspective.txt` (`P_rect_00`, `P_rect_01`, `S_rect_00`, optional `R_rect_00`).
pub fn perspective(path: &Path, text: &str) -> Result<Perspective> {
    let k = keyed(path, text)?;
    let get = |key: &str, n: usize| -> Result<&Vec<f64>> {
        let (line, v) = k
            .get(key)
            .ok_or_else(|| err(path, format!("no `{key}` line")))?;
        if v.len() != n {
            return Err(err(
                path,
                format!(
                    "line {line} `{key}`: expected {n} numbers, found {}",
                    v.len()
                ),
            ));
        }
        Ok(v)
    };
    let p0 = get("P_rect_00", 12)?;
    let p1 = get("P_rect_01", 12)?;
    let s = get("S_rect_00", 2)?;
    let r_rect = match k.get("R_rect_00") {
        Some((line, _)) => {
            let r = get("R_rect_00", 9)?;
            let m = DMat3::from_cols_array(&[r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8]]);
            check_rotation(path, &format!("line {line} `R_rect_00`"), &m)?;
            m
        }
        None => DMat3::IDENTITY,
    };
    let size = |v: f64, what: &str| -> Result<u32> {
        if v.fract() != 0.0 || v < 1.0 {
            return Err(err(
                path,
                format!("`S_rect_00`: {what} {v} is not a positive whole number of pixels"),
            ));
        }
        if v > MAX_IMAGE_SIDE as f64 {
            return Err(err(
                path,
                format!(
                    "`S_rect_00`: {what} {v} is more than {MAX_IMAGE_SIDE} pixels, the largest \
                     image side this tool reads (KITTI-360's are 1408x376)"
                ),
            ));
        }
        Ok(v as u32)
    };
    let (width, height) = (size(s[0], "width")?, size(s[1], "height")?);
    let (fx, fy) = (p0[0], p0[5]);
    if fx <= 0.0 || fy <= 0.0 {
        return Err(err(
            path,
            format!("`P_rect_00`: focal lengths must be positive, found fx {fx} fy {fy}"),
        ));
    }
    let shape_ok = |p: &[f64]| {
        p[1] == 0.0 && p[4] == 0.0 && p[8] == 0.0 && p[9] == 0.0 && p[10] == 1.0 && p[11] == 0.0
    };
    if !shape_ok(p0) || p0[3] != 0.0 || p0[7] != 0.0 {
        return Err(err(
            path,
            "`P_rect_00`: not a rectified left projection [fx 0 cx 0; 0 fy cy 0; 0 0 1 0]",
        ));
    }
    let same = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(1.0);
    if !shape_ok(p1) || !same(p1[0], fx) || !same(p1[5], fy) || !same(p1[2], p0[2]) {
        return Err(err(
            path,
            "`P_rect_01`: the right projection must share P_rect_00's intrinsics (fx, fy, cx, cy) \
             with only P_rect_01[0,3] = -fx * baseline differing",
        ));
    }
    if !same(p1[6], p0[6]) || p1[7] != 0.0 {
        return Err(err(
            path,
            "`P_rect_01`: cy and P[1,3] must match a rectified pair",
        ));
    }
    let baseline = -p1[3] / fx;
    if baseline <= 0.0 {
        return Err(err(
            path,
            format!(
                "`P_rect_01`: P[0,3] = {} gives baseline {baseline} m; a right camera needs a \
                 negative P[0,3] (= -fx * baseline)",
                p1[3]
            ),
        ));
    }
    Ok(Perspective {
        width,
        height,
        fx,
        fy,
        cx_file: p0[2],
        cy_file: p0[6],
        baseline,
        r_rect,
    })
}

/// `calib_cam_to_velo.txt`: one line of 12 numbers, the 3x4 rigid transform from the
/// unrectified camera 0 to the velodyne.
pub fn cam_to_velo(path: &Path, text: &str) -> Result<DAffine3> {
    let at = "the 3x4 camera -> velodyne matrix";
    let v = text
        .split_whitespace()
        .map(|t| parse_f64(path, at, t))
        .collect::<Result<Vec<f64>>>()?;
    if v.len() != 12 {
        return Err(err(
            path,
            format!("{at}: expected 12 numbers, found {}", v.len()),
        ));
    }
    let mut m = v;
    m.extend([0.0, 0.0, 0.0, 1.0]);
    let m = affine_from_row_major(&m).map_err(|e| err(path, format!("{at}: {e}")))?;
    check_rotation(path, at, &m.matrix3)?;
    Ok(m)
}

/// One object of the `data_3d_bboxes` XML, as written (world frame, label not yet mapped).
#[derive(Clone, Debug)]
pub struct XmlObject {
    /// The element name (`object12`), for messages.
    pub element: String,
    pub semantic_id: i64,
    pub instance_id: i64,
    pub timestamp: i64,
    /// Local -> world (upper 3x3 = R * diag(size)).
    pub transform: DAffine3,
    pub vertices: Vec<DVec3>,
    pub faces: Vec<[u32; 3]>,
}

/// An OpenCV FileStorage matrix: `rows`, `cols`, `dt`, `data` (whitespace-separated, row-major,
/// may wrap lines).
fn matrix(path: &Path, obj: &str, node: roxmltree::Node) -> Result<(usize, usize, Vec<f64>)> {
    let name = node.tag_name().name();
    let at = format!("<{obj}>/<{name}>");
    let child = |tag: &str| -> Result<&str> {
        node.children()
            .find(|c| c.has_tag_name(tag))
            .map(|c| c.text().unwrap_or("").trim())
            .ok_or_else(|| err(path, format!("{at}: missing <{tag}>")))
    };
    let dim = |tag: &str| -> Result<usize> {
        let t = child(tag)?;
        t.parse()
            .map_err(|_| err(path, format!("{at}: <{tag}> `{t}` is not a whole number")))
    };
    let (rows, cols) = (dim("rows")?, dim("cols")?);
    let data = child("data")?;
    let v = data
        .split_whitespace()
        .map(|t| parse_f64(path, &at, t))
        .collect::<Result<Vec<f64>>>()?;
    // Checked: a hostile <rows> x <cols> must not overflow (and then match a short <data>).
    if rows.checked_mul(cols) != Some(v.len()) {
        let needs = rows
            .checked_mul(cols)
            .map_or_else(|| "more than 2^64".to_string(), |n| n.to_string());
        return Err(err(
            path,
            format!(
                "{at}: {rows} x {cols} matrix needs {needs} values, <data> has {}",
                v.len()
            ),
        ));
    }
    Ok((rows, cols, v))
}

fn int_child(path: &Path, obj: &str, node: roxmltree::Node, tag: &str) -> Result<Option<i64>> {
    let Some(c) = node.children().find(|c| c.has_tag_name(tag)) else {
        return Ok(None);
    };
    let t = c.text().unwrap_or("").trim();
    t.parse()
        .map(Some)
        .map_err(|_| err(path, format!("<{obj}>/<{tag}>: `{t}` is not an integer")))
}

/// Parses the `data_3d_bboxes` XML: every child element of `<opencv_storage>` is one object.
pub fn bboxes(path: &Path, text: &str) -> Result<Vec<XmlObject>> {
    let doc = roxmltree::Document::parse(text)
        .map_err(|e| err(path, format!("not well-formed XML: {e}")))?;
    let root = doc.root_element();
    if !root.has_tag_name("opencv_storage") {
        return Err(err(
            path,
            format!(
                "root element is <{}>, expected <opencv_storage>",
                root.tag_name().name()
            ),
        ));
    }
    let mut out = Vec::new();
    for node in root.children().filter(|n| n.is_element()) {
        let obj = node.tag_name().name().to_string();
        let find = |tag: &str| {
            node.children()
                .find(|c| c.has_tag_name(tag))
                .ok_or_else(|| err(path, format!("<{obj}>: missing <{tag}>")))
        };
        let need = |tag: &str| -> Result<i64> {
            int_child(path, &obj, node, tag)?
                .ok_or_else(|| err(path, format!("<{obj}>: missing <{tag}>")))
        };
        let semantic_id = need("semanticId")?;
        let instance_id = need("instanceId")?;
        let timestamp = int_child(path, &obj, node, "timestamp")?.unwrap_or(-1);
        let (r, c, t) = matrix(path, &obj, find("transform")?)?;
        if (r, c) != (4, 4) {
            return Err(err(
                path,
                format!("<{obj}>/<transform>: expected a 4 x 4 matrix, found {r} x {c}"),
            ));
        }
        let transform = affine_from_row_major(&t)
            .map_err(|e| err(path, format!("<{obj}>/<transform>: {e}")))?;
        let (vr, vc, vd) = matrix(path, &obj, find("vertices")?)?;
        if vc != 3 || vr == 0 {
            return Err(err(
                path,
                format!("<{obj}>/<vertices>: expected an N x 3 matrix, found {vr} x {vc}"),
            ));
        }
        let (fr, fc, fd) = matrix(path, &obj, find("faces")?)?;
        if fc != 3 || fr == 0 {
            return Err(err(
                path,
                format!("<{obj}>/<faces>: expected an M x 3 matrix, found {fr} x {fc}"),
            ));
        }
        let mut faces = Vec::with_capacity(fr);
        for (k, f) in fd.chunks_exact(3).enumerate() {
            let mut tri = [0u32; 3];
            for (j, &x) in f.iter().enumerate() {
                if x.fract() != 0.0 || x < 0.0 || x >= vr as f64 {
                    return Err(err(
                        path,
                        format!(
                            "<{obj}>/<faces>: face {k} refers to vertex {x}, but there are {vr} \
                             vertices (0-based)"
                        ),
                    ));
                }
                tri[j] = x as u32;
            }
            faces.push(tri);
        }
        out.push(XmlObject {
            element: obj,
            semantic_id,
            instance_id,
            timestamp,
            transform,
            vertices: vd.chunks_exact(3).map(DVec3::from_slice).collect(),
            faces,
        });
    }
    Ok(out)
}

/// The size an image must have: width, height and the camera (0..3) whose calibration sets it.
pub type Size = (u32, u32, u8);

/// Width and height in a PNG's header (`None` when it has none).
fn png_header_size(bytes: &[u8]) -> Option<(u32, u32)> {
    let be = |i: usize| Some(u32::from_be_bytes(bytes.get(i..i + 4)?.try_into().ok()?));
    (bytes.get(12..16) == Some(b"IHDR")).then_some(())?;
    Some((be(16)?, be(20)?))
}

/// Decodes a PNG; a missing, truncated, corrupt or too large file is an error naming it.
pub fn png(path: &Path) -> Result<image::DynamicImage> {
    let bytes = read_bytes(path)?;
    image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).map_err(|e| match e {
        image::ImageError::Limits(_) => {
            let size = png_header_size(&bytes)
                .map_or("its size".to_string(), |(w, h)| format!("{w}x{h} pixels"));
            err(
                path,
                format!(
                    "too large to decode: {size} is over the decoder's limit of 512 MiB of \
                     pixels (a KITTI-360 image is 1408x376)"
                ),
            )
        }
        e => err(
            path,
            format!("not a readable PNG (truncated or corrupt?): {e}"),
        ),
    })
}

/// Where the expected size of camera `camera`'s images comes from.
fn size_source(camera: u8) -> String {
    match camera {
        0 | 1 => format!("S_rect_0{camera} in perspective.txt"),
        c => format!("image_width and image_height in image_0{c}.yaml"),
    }
}

fn check_size(path: &Path, img_w: u32, img_h: u32, (w, h, camera): Size) -> Result<()> {
    if (img_w, img_h) != (w, h) {
        return Err(err(
            path,
            format!(
                "image is {img_w}x{img_h}, expected {w}x{h} ({})",
                size_source(camera)
            ),
        ));
    }
    Ok(())
}

/// The indices of an 8-bit palette (indexed) PNG, as they are (`None` for any other PNG).
fn palette_indices(path: &Path, bytes: &[u8]) -> Result<Option<(u32, u32, Vec<u8>)>> {
    // IHDR's colour type (byte 25) is 3 for a palette image.
    if bytes.get(25) != Some(&3) {
        return Ok(None);
    }
    let bad = |e: png::DecodingError| {
        err(
            path,
            format!("not a readable PNG (truncated or corrupt?): {e}"),
        )
    };
    let mut d = png::Decoder::new(std::io::Cursor::new(bytes));
    d.set_transformations(png::Transformations::IDENTITY);
    let mut r = d.read_info().map_err(bad)?;
    let info = r.info();
    if info.color_type != png::ColorType::Indexed {
        return Ok(None);
    }
    if info.bit_depth != png::BitDepth::Eight {
        return Err(err(
            path,
            format!(
                "a palette PNG with {}-bit indices: label ids need 8 bits (save it as an 8-bit \
                 palette or single-channel PNG)",
                info.bit_depth as u8
            ),
        ));
    }
    let mut buf = vec![0; r.output_buffer_size().unwrap_or(0)];
    let frame = r.next_frame(&mut buf).map_err(bad)?;
    buf.truncate(frame.buffer_size());
    Ok(Some((frame.width, frame.height, buf)))
}

/// An 8-bit colour image as `w*h*3` RGB bytes (grey and RGBA are converted).
pub fn rgb(path: &Path, size: Size) -> Result<Vec<u8>> {
    let img = png(path)?;
    check_size(path, img.width(), img.height(), size)?;
    use image::ColorType::*;
    match img.color() {
        Rgb8 | Rgba8 | L8 | La8 => Ok(img.into_rgb8().into_raw()),
        other => Err(err(
            path,
            format!("expected an 8-bit colour image, found {other:?}"),
        )),
    }
}

/// An 8-bit single-channel label map of KITTI-360 label ids (or an 8-bit palette PNG, whose
/// indices are the ids); unknown ids are errors naming the pixel.
pub fn labels(path: &Path, size: Size) -> Result<Vec<u8>> {
    let w = size.0;
    let v = match palette_indices(path, &read_bytes(path)?)? {
        Some((pw, ph, v)) => {
            check_size(path, pw, ph, size)?;
            v
        }
        None => {
            let img = png(path)?;
            check_size(path, img.width(), img.height(), size)?;
            if img.color() != image::ColorType::L8 {
                return Err(err(
                    path,
                    format!(
                        "expected an 8-bit single-channel label-id PNG (or an 8-bit palette PNG of \
                         label ids), found {:?}",
                        img.color()
                    ),
                ));
            }
            img.into_luma8().into_raw()
        }
    };
    if let Some(i) = v.iter().position(|&l| crate::labels::by_id(l).is_none()) {
        return Err(err(
            path,
            format!(
                "pixel ({}, {}): {} is not a KITTI-360 label id",
                i % w as usize,
                i / w as usize,
                v[i]
            ),
        ));
    }
    Ok(v)
}

/// A 16-bit single-channel PNG (instance maps `id*1000 + instance`, depth `metres*256`).
pub fn gray16(path: &Path, size: Size, what: &str) -> Result<Vec<u16>> {
    let img = png(path)?;
    check_size(path, img.width(), img.height(), size)?;
    if img.color() != image::ColorType::L16 {
        return Err(err(
            path,
            format!(
                "expected a 16-bit single-channel {what} PNG, found {:?}",
                img.color()
            ),
        ));
    }
    Ok(img.into_luma16().into_raw())
}

/// A velodyne scan: float32 N x 4 (x, y, z, intensity), little-endian.
pub fn velodyne(path: &Path) -> Result<Vec<DVec3>> {
    let bytes = read_bytes(path)?;
    if bytes.len() % 16 != 0 {
        return Err(err(
            path,
            format!(
                "{} bytes is not a whole number of points (16 bytes each: float32 x, y, z, \
                 intensity); truncated?",
                bytes.len()
            ),
        ));
    }
    let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64;
    bytes
        .chunks_exact(16)
        .enumerate()
        .map(|(i, p)| {
            let q = DVec3::new(f(&p[0..4]), f(&p[4..8]), f(&p[8..12]));
            if !q.is_finite() {
                return Err(err(
                    path,
                    format!(
                        "point {i} (byte {}): non-finite coordinate ({}, {}, {})",
                        16 * i,
                        q.x,
                        q.y,
                        q.z
                    ),
                ));
            }
            Ok(q)
        })
        .collect()
}
