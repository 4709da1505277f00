//! Every ray of a scene's images as training draws them ([`ImageRays`]): the images the `rays`
//! input planned (in its row order), each with its camera, the plan's hit counts, its targets
//! (RGB, pseudo labels) read from the `scene` tables an image at a time and its stereo depth
//! (from `depth` or `scene`) kept where it has a value; each ray's intervals are traced again
//! when it is drawn.

use std::collections::HashMap;

use arrow::datatypes::{Float32Type, Float64Type, UInt32Type, UInt8Type};
use arrow::record_batch::RecordBatch;

use super::rays::{pixel_ray_f64, ray_f32, Intervals, PrimInfo, RayTargets, Rays, SceneRay, NONE};
use crate::geometry::{self, Primitive};
use crate::intervals::{may_see_sky, IntersectParams, RayPlan};
use crate::rng::{mix, SplitMix64};
use crate::stage::{Inputs, Result, StageError};
use crate::stream::Table;
use crate::{labels, tables};

/// One image of the scene as training sees it: its camera and per-pixel targets.
pub struct TrainImage {
    pub frame: u32,
    pub camera: u8,
    pub cam: geometry::Camera,
    /// First ray of this image among all images' rays.
    pub first_ray: u32,
    /// Per pixel: primitive intervals the `intersect` stage kept (0 = pure sky).
    pub hits: Vec<u8>,
    pub targets: Targets,
    /// Stereo depth, where the image has one.
    pub depth: Option<SparseDepth>,
    /// Pixels (ascending) where a moving object may be seen (see [`ImageRays::mark_moving`]):
    /// training leaves them out, so a moving car does not smear into the static field.
    pub moving: Vec<u32>,
}

/// The per-pixel targets of one image: RGB (bytes), and pseudo labels where the image has them;
/// copied out of the input tables an image at a time (read whole, a stored table is gathered
/// from its row groups into one more copy).
#[derive(Debug, Clone)]
pub struct Targets {
    pub rgb: Vec<u8>,
    pub labels: Option<Vec<u8>>,
}

/// The stereo depth of one image at the pixels that have one: most have none (motion stereo
/// gives about a sixth of a fisheye image's pixels a depth), and the dense maps of every image
/// of a full-size scene with fisheye cameras took 1.3 GB.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseDepth {
    /// Pixel indices, ascending.
    pixels: Vec<u32>,
    depth: Vec<f32>,
}

impl SparseDepth {
    /// The finite, positive values of a dense map (0 or NaN: no depth).
    pub fn from_dense(dense: &[f32]) -> Self {
        let (mut pixels, mut depth): (Vec<u32>, Vec<f32>) = dense
            .iter()
            .enumerate()
            .filter(|(_, &d)| d.is_finite() && d > 0.0)
            .map(|(p, &d)| (p as u32, d))
            .unzip();
        // Grown by doubling: up to half of each would be spare capacity, kept for the whole run.
        pixels.shrink_to_fit();
        depth.shrink_to_fit();
        Self { pixels, depth }
    }

    /// The depth at pixel `p`; 0 where there is none.
    pub fn get(&self, p: usize) -> f32 {
        let Ok(p) = u32::try_from(p) else { return 0.0 };
        match self.pixels.binary_search(&p) {
            Ok(i) => self.depth[i],
            Err(_) => 0.0,
        }
    }
}

/// Every ray of a scene's images, its intervals traced again whenever it is drawn: holding them
/// for every ray of a full-size scene (68 M rays) took gigabytes, tracing a batch of 2048 rays
/// takes about a millisecond.
pub struct ImageRays {
    pub prims: PrimInfo,
    pub images: Vec<TrainImage>,
    primitives: Vec<Primitive>,
    bvh: geometry::Bvh,
    params: IntersectParams,
    rays: u32,
    /// Per primitive: whether a ray crossing it keeps its stereo depth (`None`: every ray).
    depth_prims: Option<Vec<bool>>,
}

impl ImageRays {
    pub fn new(
        primitives: Vec<Primitive>,
        images: Vec<TrainImage>,
        params: IntersectParams,
    ) -> Result<Self> {
        let mut rays = 0u64;
        for im in &images {
            if im.first_ray as u64 != rays {
                return Err(StageError::Failed(
                    "images must be listed in ray order".into(),
                ));
            }
            rays += im.hits.len() as u64;
        }
        let rays = u32::try_from(rays).map_err(|_| {
            StageError::Input(format!(
                "{rays} rays: more than 2^32 rays in one scene; split the sequence into scenes"
            ))
        })?;
        Ok(Self {
            prims: PrimInfo::of(&primitives),
            bvh: geometry::Bvh::build(&primitives),
            primitives,
            images,
            params,
            rays,
            depth_prims: None,
        })
    }

    /// Keeps the stereo depth target only on rays that cross a primitive of one of `labels`
    /// (label ids), as the published implementation does with its per-scene `depth_object`
    /// list; an empty list keeps every ray's depth (the paper's form).
    pub fn restrict_depth_to(&mut self, labels: &[u8]) {
        self.depth_prims = (!labels.is_empty()).then(|| {
            self.primitives
                .iter()
                .map(|p| labels.contains(&p.label))
                .collect()
        });
    }

    /// The image of ray `r` and the pixel in it.
    pub fn locate(&self, r: u32) -> (&TrainImage, usize) {
        let im = &self.images[self.image_index(r)];
        (im, (r - im.first_ray) as usize)
    }

    /// The index in `images` of ray `r`'s image.
    pub fn image_index(&self, r: u32) -> usize {
        self.images.partition_point(|im| im.first_ray <= r) - 1
    }

    /// Marks in every image the pixels a moving object may be seen at
    /// ([`TrainImage::moving`]): whose ray crosses one of `boxes` (moving objects' boxes) at the
    /// image's frame and, in an image with pseudo labels, whose pseudo label is a class of those
    /// boxes. The rest of a box's outline sees the static scene around the object and trains it.
    pub fn mark_moving(&mut self, boxes: &[geometry::DynamicBox]) {
        let mut by_frame: HashMap<u32, Vec<Primitive>> = HashMap::new();
        for b in boxes {
            by_frame
                .entry(b.frame)
                .or_default()
                .push(b.primitive.clone());
        }
        for im in &mut self.images {
            let Some(b) = by_frame.get(&im.frame) else {
                im.moving = Vec::new();
                continue;
            };
            let mut pixels = geometry::changes::pixels_meeting(&im.cam, b, f64::INFINITY);
            if let Some(labels) = &im.targets.labels {
                pixels.retain(|&p| b.iter().any(|x| x.label == labels[p as usize]));
            }
            im.moving = pixels;
        }
    }

    /// Whether ray `r` crosses a primitive, by the `intersect` stage's plan.
    pub fn hits_anything(&self, r: u32) -> bool {
        let (im, p) = self.locate(r);
        im.hits[p] > 0
    }
}

impl Rays for ImageRays {
    fn prims(&self) -> &PrimInfo {
        &self.prims
    }
    fn len(&self) -> usize {
        self.rays as usize
    }
    fn ray<'s>(&'s self, r: u32, buf: &'s mut RayPlan) -> Result<SceneRay<'s>> {
        self.ray_at(r, None, buf)
    }
}

impl ImageRays {
    /// Ray `r` through the point `offset` (in pixels, each in [0, 1)) of its pixel; `None`: the
    /// pixel's centre, the ray the plan was traced with, whose interval count is checked
    /// against the plan. An offset ray that leaves the lens, or crosses no primitive where the
    /// centre ray crosses one, falls back to the centre ray (its targets are the pixel's).
    pub fn ray_at<'s>(
        &'s self,
        r: u32,
        offset: Option<[f64; 2]>,
        buf: &'s mut RayPlan,
    ) -> Result<SceneRay<'s>> {
        self.ray_labelled_by(r, offset, [0, 0], buf)
    }

    /// [`Self::ray_at`], the pseudo label (and u(r)) taken from the pixel `label_shift` away
    /// (clamped to the image) when the offset ray is used; the centre ray keeps its own.
    pub fn ray_labelled_by<'s>(
        &'s self,
        r: u32,
        offset: Option<[f64; 2]>,
        label_shift: [i32; 2],
        buf: &'s mut RayPlan,
    ) -> Result<SceneRay<'s>> {
        let (im, p) = self.locate(r);
        let w = im.cam.width;
        let (x, y) = (p as u32 % w, p as u32 / w);
        let offset_ray = offset.and_then(|[du, dv]| {
            let (ray, d_cam) = im.cam.ray_and_dir_cam(x as f64 + du, y as f64 + dv)?;
            buf.trace(&self.primitives, &self.bvh, &ray, &self.params);
            (!buf.t_in.is_empty() || im.hits[p] == 0)
                .then(|| (ray, im.cam.depth_scale(d_cam) as f32))
        });
        let mut label_pixel = p;
        let (ray, z_scale) = match offset_ray {
            Some(r) => {
                let clamp = |v: u32, d: i32, n: u32| (v as i64 + d as i64).clamp(0, n as i64 - 1);
                let lx = clamp(x, label_shift[0], w);
                let ly = clamp(y, label_shift[1], im.cam.height);
                label_pixel = (ly * w as i64 + lx) as usize;
                r
            }
            None => {
                let (ray, z_scale) = pixel_ray_f64(&im.cam, x, y)?;
                buf.trace(&self.primitives, &self.bvh, &ray, &self.params);
                if buf.t_in.len() != im.hits[p] as usize {
                    return Err(StageError::Input(format!(
                        "ray_intervals does not match the scene: pixel ({x}, {y}) of frame {} \
                         camera {} has {} intervals there but crosses {} primitive intervals \
                         now (was the `intersect` stage run on other primitives or cameras?)",
                        im.frame,
                        im.camera,
                        im.hits[p],
                        buf.t_in.len()
                    )));
                }
                (ray, z_scale)
            }
        };
        let (origin, dir) = ray_f32(&ray);
        let t = &im.targets;
        let mut label = t
            .labels
            .as_ref()
            .map_or(NONE, |l| self.prims.label_class(l[label_pixel]));
        // A pseudo label of sky on a ray below the horizon is the 2D network's mistake: no
        // setting of the fields can honour it (the ray has no sky interval), and chasing it
        // would make the ray transparent. Both 2D terms skip it.
        if label != NONE
            && self.prims.classes[label as usize] == labels::SKY
            && !may_see_sky(ray.dir)
        {
            label = NONE;
        }
        let intervals = Intervals {
            t_in: &buf.t_in,
            t_out: &buf.t_out,
            prim: &buf.prim,
            sky: buf.sky,
        };
        let keeps_depth = self
            .depth_prims
            .as_ref()
            .is_none_or(|keep| intervals.prim.iter().any(|&p| keep[p as usize]));
        Ok(SceneRay {
            origin,
            dir,
            z_scale,
            targets: RayTargets {
                rgb: [0, 1, 2].map(|c| t.rgb[p * 3 + c] as f32 / 255.0),
                label,
                u_mask: self.prims.ray_mask(label, &intervals),
                depth: match &im.depth {
                    Some(d) if keeps_depth => d.get(p),
                    _ => 0.0,
                },
            },
            intervals,
        })
    }
}

/// A per-image input table, stored, with its (frame, camera) -> row index; rows are read one
/// at a time.
struct ImageRows<'a> {
    index: HashMap<(u32, u8), usize>,
    table: &'a Table,
    name: &'static str,
}

impl<'a> ImageRows<'a> {
    fn new(table: &'a Table, name: &'static str) -> Result<Self> {
        Ok(Self {
            index: tables::frame_camera_index(&table.columns(&["frame", "camera"])?, name)?,
            table,
            name,
        })
    }

    /// Row `i`'s column `col`, alone.
    fn row(&self, i: usize, col: &str) -> Result<RecordBatch> {
        self.table.rows(i..i + 1, Some(&[col]))
    }
}

/// Columns of `ray_intervals` training reads whole (the per-pixel `hits` it reads an image at a
/// time; the intervals not at all: it traces them again).
const PLAN_COLUMNS: &[&str] = &[
    "frame",
    "camera",
    "width",
    "height",
    "k",
    "far",
    "sky_interval",
];

/// The rays of every image of the `rays` input's plan, with their targets from `scene` (and a
/// connected `depth` stage, which takes precedence over the scene's own stereo depth). Images
/// without pseudo labels (right camera) get none.
pub fn train_rays(inputs: &Inputs) -> Result<ImageRays> {
    let cams = geometry::cameras_from_table(inputs.table("scene", "cameras")?)?;
    let prims = geometry::primitives_from_table(inputs.table("scene", "primitives")?)?;
    // Every per-image table an image at a time (one row group each): whole, the stereo depth
    // and the plan's hits were the largest tables training held, and a table read whole is
    // gathered from its row groups into one more copy.
    let images = ImageRows::new(inputs.stored("scene", "images")?, "images")?;
    let pseudo = ImageRows::new(inputs.stored("scene", "pseudo_labels")?, "pseudo_labels")?;
    let stereo = match inputs.optional_stored("depth", "stereo_depth")? {
        Some(t) => Some(t),
        None => inputs.optional_stored("scene", "stereo_depth")?,
    }
    .map(|t| ImageRows::new(t, "stereo_depth"))
    .transpose()?;
    let plan_table = inputs.stored("rays", "ray_intervals")?;
    let plan = plan_table.columns(PLAN_COLUMNS)?;
    let params = plan_params(&plan)?;
    const T: &str = "ray_intervals";
    let frames = tables::get_prim::<UInt32Type>(&plan, T, "frame")?;
    let cameras = tables::get_prim::<UInt8Type>(&plan, T, "camera")?;
    let mut out = Vec::with_capacity(plan.num_rows());
    let mut first_ray = 0u64;
    for r in 0..plan.num_rows() {
        let key = (frames[r], cameras[r]);
        let cam = cams
            .iter()
            .find(|c| (c.frame, c.camera) == key)
            .ok_or_else(|| {
                StageError::Input(format!(
                    "ray_intervals row {r}: frame {} camera {} is not in `cameras`",
                    key.0, key.1
                ))
            })?;
        let (w, h) = (cam.cam.width, cam.cam.height);
        let n = (w * h) as usize;
        let hits_row = plan_table.rows(r..r + 1, Some(&["hits"]))?;
        let hits = tables::get_list::<UInt8Type>(&hits_row, T, "hits")?.row(0);
        if hits.len() != n {
            return Err(StageError::Input(format!(
                "ray_intervals row {r}: per-pixel arrays do not have {w}x{h} entries"
            )));
        }
        let first = u32::try_from(first_ray).map_err(|_| {
            StageError::Input(format!(
                "more than 2^32 rays in one scene (at frame {} camera {}); split the sequence \
                 into scenes",
                key.0, key.1
            ))
        })?;
        out.push(TrainImage {
            frame: key.0,
            camera: key.1,
            cam: cam.cam.clone(),
            first_ray: first,
            hits: hits.to_vec(),
            targets: image_targets(key, w, h, &images, &pseudo)?,
            depth: match &stereo {
                Some(rows) => rows
                    .index
                    .get(&key)
                    .map(|&i| image_depth(key, w, h, rows, i))
                    .transpose()?,
                None => None,
            },
            moving: Vec::new(),
        });
        first_ray += n as u64;
    }
    ImageRays::new(prims, out, params)
}

/// The `intersect` parameters a plan was made with (every row must agree).
fn plan_params(plan: &RecordBatch) -> Result<IntersectParams> {
    const T: &str = "ray_intervals";
    let k = tables::get_prim::<UInt32Type>(plan, T, "k")?;
    let far = tables::get_prim::<Float64Type>(plan, T, "far")?;
    let sky = tables::get_prim::<Float64Type>(plan, T, "sky_interval")?;
    let Some(((&k0, &far0), &sky0)) = k.iter().zip(far).zip(sky).next() else {
        return Err(StageError::Input(
            "ray_intervals has no rows: no image was planned".into(),
        ));
    };
    for (r, ((&a, &b), &c)) in k.iter().zip(far).zip(sky).enumerate() {
        if (a, b, c) != (k0, far0, sky0) {
            return Err(StageError::Input(format!(
                "ray_intervals row {r}: k, far and sky_interval differ from row 0's"
            )));
        }
    }
    Ok(IntersectParams {
        k: k0,
        far: far0,
        sky_interval: sky0,
        cameras: Vec::new(),
    })
}

/// Per-pixel RGB and pseudo labels of image `key` (`w` x `h`): RGB must exist, pseudo labels
/// may be absent; each must have one value per pixel.
fn image_targets(
    key: (u32, u8),
    w: u32,
    h: u32,
    images: &ImageRows,
    pseudo: &ImageRows,
) -> Result<Targets> {
    let n = (w * h) as usize;
    let i = *images.index.get(&key).ok_or_else(|| {
        StageError::Input(format!(
            "no `images` row for frame {} camera {}",
            key.0, key.1
        ))
    })?;
    let row = images.row(i, "rgb")?;
    let rgb = tables::get_binary(&row, images.name, "rgb")?
        .value(0)
        .to_vec();
    if rgb.len() != n * 3 {
        return Err(StageError::Input(format!(
            "images: frame {} camera {} has {} bytes, expected {w}x{h}x3",
            key.0,
            key.1,
            rgb.len()
        )));
    }
    let labels = match pseudo.index.get(&key) {
        Some(&i) => {
            let row = pseudo.row(i, "labels")?;
            let labels = tables::get_list::<UInt8Type>(&row, pseudo.name, "labels")?
                .row(0)
                .to_vec();
            check_len("pseudo_labels", key, w, h, labels.len())?;
            Some(labels)
        }
        None => None,
    };
    Ok(Targets { rgb, labels })
}

/// The stereo depth of image `key` (`w` x `h`), row `row` of `stereo`.
fn image_depth(
    key: (u32, u8),
    w: u32,
    h: u32,
    stereo: &ImageRows,
    row: usize,
) -> Result<SparseDepth> {
    let batch = stereo.row(row, "depth")?;
    let dense = tables::get_list::<Float32Type>(&batch, stereo.name, "depth")?.row(0);
    check_len("stereo_depth", key, w, h, dense.len())?;
    Ok(SparseDepth::from_dense(dense))
}

/// An error unless a per-pixel row of table `what` has `w * h` values.
fn check_len(what: &str, key: (u32, u8), w: u32, h: u32, len: usize) -> Result<()> {
    if len != (w * h) as usize {
        return Err(StageError::Input(format!(
            "{what}: frame {} camera {} has {len} values, expected {w}x{h}",
            key.0, key.1
        )));
    }
    Ok(())
}

/// The rays of an [`ImageRays`] each cast through a random point of a `width`-pixel window
/// around its pixel's centre (the point a hash of `seed` and the ray id; a new `seed` per batch
/// draws new points). The targets stay the pixel's (the label too, unless `bilinear_labels`):
/// where a pixel straddles a class boundary no ray's label can be met exactly, which keeps
/// training from carving the geometry to fit one wrong pseudo label ray by ray.
pub struct JitteredRays<'r> {
    pub rays: &'r ImageRays,
    pub seed: u64,
    /// Window width in pixels, 0..=1 (1: the whole pixel).
    pub width: f64,
    /// Label a ray by a neighbour drawn with the bilinear weights of its point
    /// ([`crate::sampling::JitterLabels::Bilinear`]) instead of by its own pixel.
    pub bilinear_labels: bool,
}

impl JitteredRays<'_> {
    /// The point of ray `r`'s pixel it is cast through, each coordinate in [0, 1).
    pub fn offset(&self, r: u32) -> [f64; 2] {
        self.draw(r).0
    }

    /// The point of [`Self::offset`] and the pixel (relative to ray `r`'s own) whose label the
    /// ray takes: per axis the neighbour on the point's side with probability equal to the
    /// point's distance from the centre, which is that neighbour's bilinear weight.
    pub fn draw(&self, r: u32) -> ([f64; 2], [i32; 2]) {
        let mut g = SplitMix64::new(self.seed ^ mix(r as u64));
        let offset = [0, 1].map(|_| 0.5 + self.width * (g.unit() as f64 - 0.5));
        let shift = if self.bilinear_labels {
            offset.map(|o| (o - 0.5 + g.unit() as f64).floor() as i32)
        } else {
            [0, 0]
        };
        (offset, shift)
    }
}

impl Rays for JitteredRays<'_> {
    fn prims(&self) -> &PrimInfo {
        &self.rays.prims
    }
    fn len(&self) -> usize {
        self.rays.len()
    }
    fn ray<'s>(&'s self, r: u32, buf: &'s mut RayPlan) -> Result<SceneRay<'s>> {
        let (offset, shift) = self.draw(r);
        self.rays.ray_labelled_by(r, Some(offset), shift, buf)
    }
}
