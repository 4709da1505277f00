//! The rays the sampler draws from ([`Rays`]): what the sampler and the compositor know of the
//! primitives ([`PrimInfo`]), one ray's intervals and targets, rays given one by one
//! ([`RaySet`]) and the rays of one planned image ([`PlannedImage`], what rendering reads).

use crate::geometry;
use crate::geometry::Primitive;
use crate::intervals::{ImagePlan, RayPlan};
use crate::labels;
use crate::stage::{Result, StageError};

/// Index meaning "no class / no label".
pub const NONE: u16 = u16::MAX;

/// What the sampler and the compositor know of the primitives: the classes the fields predict,
/// the thing instances, each primitive's class and thing, and the bounds of everything sampled.
#[derive(Debug, Clone, Default)]
pub struct PrimInfo {
    /// Label ids the fields predict: classes of the primitives ascending, then sky (last).
    pub classes: Vec<u8>,
    /// Thing instances (label, instance) of the primitives, sorted: the fixed instance field's
    /// entries.
    pub things: Vec<(u8, u32)>,
    /// Per primitive: its class index.
    pub prim_class: Vec<u16>,
    /// Per primitive: index into `things`, or `u32::MAX` for stuff.
    pub prim_thing: Vec<u32>,
    /// Scene bounds of everything sampled (primitive bounds), for the encoding.
    pub bounds_min: [f32; 3],
    pub bounds_max: [f32; 3],
}

impl PrimInfo {
    /// The classes (primitive classes ascending, then sky last, the fields' convention), the
    /// thing instances, each primitive's class and thing, and the primitives' bounds.
    pub fn of(prims: &[Primitive]) -> PrimInfo {
        let mut classes: Vec<u8> = prims
            .iter()
            .map(|p| p.label)
            .filter(|&l| l != labels::SKY)
            .collect();
        classes.sort_unstable();
        classes.dedup();
        classes.push(labels::SKY);
        let mut things: Vec<(u8, u32)> = prims
            .iter()
            .filter(|p| p.instance > 0)
            .map(|p| (p.label, p.instance))
            .collect();
        things.sort_unstable();
        things.dedup();
        let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
        for p in prims {
            let b = p.aabb();
            for k in 0..3 {
                lo[k] = lo[k].min(b.min[k]);
                hi[k] = hi[k].max(b.max[k]);
            }
        }
        PrimInfo {
            prim_class: prims
                .iter()
                .map(|p| class_index(&classes, p.label))
                .collect(),
            prim_thing: prims
                .iter()
                .map(|p| {
                    if p.instance == 0 {
                        u32::MAX
                    } else {
                        things
                            .binary_search(&(p.label, p.instance))
                            .map_or(u32::MAX, |i| i as u32)
                    }
                })
                .collect(),
            classes,
            things,
            bounds_min: lo.map(|v| v as f32),
            bounds_max: hi.map(|v| v as f32),
        }
    }

    pub fn sky_class(&self) -> usize {
        self.classes
            .iter()
            .position(|&c| c == labels::SKY)
            .expect("sky is always a class")
    }

    /// Class index of pseudo label `l` (0 = none), or [`NONE`].
    pub fn label_class(&self, l: u8) -> u16 {
        if l == 0 {
            NONE
        } else {
            class_index(&self.classes, l)
        }
    }

    /// u(r): pseudo label class `label` is the class of a primitive the ray crosses, or sky.
    pub fn ray_mask(&self, label: u16, iv: &Intervals) -> bool {
        label != NONE
            && (self.classes[label as usize] == labels::SKY
                || iv
                    .prim
                    .iter()
                    .any(|&p| self.prim_class[p as usize] == label))
    }
}

/// One ray's primitive intervals (sorted by entry, `t_out >= t_in`) and its sky interval.
#[derive(Debug, Clone, Copy)]
pub struct Intervals<'a> {
    pub t_in: &'a [f32],
    pub t_out: &'a [f32],
    pub prim: &'a [u32],
    pub sky: [f32; 2],
}

impl Intervals<'_> {
    /// Whether the ray crosses a primitive (otherwise it is pure sky: no network needed).
    pub fn hits_anything(&self) -> bool {
        !self.t_in.is_empty()
    }

    /// Whether distance `t` lies in the sky interval and in no primitive (where the fixed
    /// field is one-hot sky).
    pub fn in_sky(&self, t: f32) -> bool {
        let [s0, s1] = self.sky;
        s1 > s0
            && t >= s0
            && t <= s1
            && !self
                .t_in
                .iter()
                .zip(self.t_out)
                .any(|(&a, &b)| t >= a && t <= b)
    }
}

/// What a ray is trained towards (rendering rays have none: zeros and [`NONE`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayTargets {
    /// Colour in [0, 1].
    pub rgb: [f32; 3],
    /// Pseudo label as a class index, or [`NONE`].
    pub label: u16,
    /// The ray mask u(r): the pseudo label is the class of a primitive the ray hits, or sky.
    pub u_mask: bool,
    /// Stereo z-depth, 0 = none.
    pub depth: f32,
}

impl RayTargets {
    pub const NONE: RayTargets = RayTargets {
        rgb: [0.0; 3],
        label: NONE,
        u_mask: false,
        depth: 0.0,
    };
}

/// One ray as the sampler sees it. Scene frame, f32.
#[derive(Debug, Clone, Copy)]
pub struct SceneRay<'a> {
    pub origin: [f32; 3],
    /// Unit direction.
    pub dir: [f32; 3],
    /// Depth per metre along the ray (see [`geometry::Camera::depth`]): the camera-frame z of
    /// the unit direction for a pinhole, 1 for a fisheye.
    pub z_scale: f32,
    pub intervals: Intervals<'a>,
    pub targets: RayTargets,
}

/// Rays the sampler draws from, by id: every ray of a scene's images with its intervals traced
/// on demand ([`ImageRays`]), one image's planned rays ([`PlannedImage`]), or rays given one by
/// one ([`RaySet`]). `buf` holds intervals that have to be computed.
pub trait Rays: Sync {
    fn prims(&self) -> &PrimInfo;
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    fn ray<'s>(&'s self, r: u32, buf: &'s mut RayPlan) -> Result<SceneRay<'s>>;
}

/// Rays whose intervals are held (not traced on demand): a renderer reads many at once.
pub trait StoredRays: Rays {
    fn intervals(&self, r: u32) -> Intervals<'_>;
}

impl StoredRays for RaySet {
    fn intervals(&self, r: u32) -> Intervals<'_> {
        RaySet::intervals(self, r as usize)
    }
}

impl StoredRays for PlannedImage<'_> {
    fn intervals(&self, p: u32) -> Intervals<'_> {
        PlannedImage::intervals(self, p)
    }
}

/// The origin, unit direction and z scale of pixel `(x, y)` of `cam` as f32 (computed in f64);
/// an error for a pixel outside the lens (no ray: the plan gives it no samples).
pub fn pixel_ray(cam: &geometry::Camera, x: u32, y: u32) -> Result<([f32; 3], [f32; 3], f32)> {
    pixel_ray_f64(cam, x, y).map(|(ray, z_scale)| {
        let (origin, dir) = ray_f32(&ray);
        (origin, dir, z_scale)
    })
}

/// Origin and direction of `ray` as the f32 the network sees.
pub fn ray_f32(ray: &geometry::Ray) -> ([f32; 3], [f32; 3]) {
    (
        ray.origin.as_vec3().to_array(),
        ray.dir.as_vec3().to_array(),
    )
}

/// The f64 ray of pixel `(x, y)` (the one the plan was traced with) and its z scale.
pub fn pixel_ray_f64(cam: &geometry::Camera, x: u32, y: u32) -> Result<(geometry::Ray, f32)> {
    let (ray, d_cam) = cam
        .ray_and_dir_cam(x as f64 + 0.5, y as f64 + 0.5)
        .ok_or_else(|| {
            StageError::Input(format!(
                "pixel ({x}, {y}) is outside the camera's lens and has no ray"
            ))
        })?;
    Ok((ray, cam.depth_scale(d_cam) as f32))
}

/// Rays given one by one (tests and toy scenes): per-ray origin, direction, ragged intervals and
/// targets.
#[derive(Debug, Clone, Default)]
pub struct RaySet {
    pub prims: PrimInfo,
    // Per ray.
    pub origin: Vec<[f32; 3]>,
    pub dir: Vec<[f32; 3]>,
    pub z_scale: Vec<f32>,
    /// Ragged intervals: ray r has entries offsets[r]..offsets[r+1].
    pub offsets: Vec<u32>,
    pub t_in: Vec<f32>,
    pub t_out: Vec<f32>,
    pub prim: Vec<u32>,
    pub sky: Vec<[f32; 2]>,
    pub rgb: Vec<[f32; 3]>,
    pub label: Vec<u16>,
    pub u_mask: Vec<bool>,
    pub depth: Vec<f32>,
}

impl RaySet {
    /// The intervals of ray `r`.
    pub fn intervals(&self, r: usize) -> Intervals<'_> {
        let (a, b) = (self.offsets[r] as usize, self.offsets[r + 1] as usize);
        Intervals {
            t_in: &self.t_in[a..b],
            t_out: &self.t_out[a..b],
            prim: &self.prim[a..b],
            sky: self.sky[r],
        }
    }

    /// Whether ray `r` crosses any primitive.
    pub fn hits_anything(&self, r: usize) -> bool {
        self.offsets[r + 1] > self.offsets[r]
    }
}

impl Rays for RaySet {
    fn prims(&self) -> &PrimInfo {
        &self.prims
    }
    fn len(&self) -> usize {
        self.origin.len()
    }
    fn ray<'s>(&'s self, r: u32, _: &'s mut RayPlan) -> Result<SceneRay<'s>> {
        let r = r as usize;
        Ok(SceneRay {
            origin: self.origin[r],
            dir: self.dir[r],
            z_scale: self.z_scale[r],
            intervals: self.intervals(r),
            targets: RayTargets {
                rgb: self.rgb[r],
                label: self.label[r],
                u_mask: self.u_mask[r],
                depth: self.depth[r],
            },
        })
    }
}

/// The rays of one image with its plan (a `ray_intervals` row, or a plan traced here): what
/// rendering reads, one image at a time.
pub struct PlannedImage<'a> {
    pub prims: &'a PrimInfo,
    pub cam: &'a geometry::Camera,
    plan: &'a ImagePlan,
    /// Start of each pixel's intervals in the plan.
    offsets: Vec<u32>,
    /// The plan's exits, at least the entries (as every sampler input).
    t_out: Vec<f32>,
}

impl<'a> PlannedImage<'a> {
    pub fn new(
        prims: &'a PrimInfo,
        cam: &'a geometry::Camera,
        plan: &'a ImagePlan,
    ) -> Result<Self> {
        let n = (cam.width * cam.height) as usize;
        if plan.hits.len() != n || plan.sky_t0.len() != n || plan.sky_t1.len() != n {
            return Err(StageError::Input(format!(
                "a plan of {} pixels for a {}x{} image",
                plan.hits.len(),
                cam.width,
                cam.height
            )));
        }
        let mut offsets = Vec::with_capacity(n + 1);
        let mut k = 0u32;
        offsets.push(0);
        for &h in &plan.hits {
            k += h as u32;
            offsets.push(k);
        }
        if (k as usize) != plan.t_in.len() {
            return Err(StageError::Input(format!(
                "a plan whose hits sum to {k} lists {} intervals",
                plan.t_in.len()
            )));
        }
        let t_out = plan
            .t_out
            .iter()
            .zip(&plan.t_in)
            .map(|(&o, &i)| o.max(i))
            .collect();
        Ok(Self {
            prims,
            cam,
            plan,
            offsets,
            t_out,
        })
    }

    /// The intervals of pixel `p`.
    pub fn intervals(&self, p: u32) -> Intervals<'_> {
        let p = p as usize;
        let (a, b) = (self.offsets[p] as usize, self.offsets[p + 1] as usize);
        let (s0, s1) = (self.plan.sky_t0[p], self.plan.sky_t1[p]);
        Intervals {
            t_in: &self.plan.t_in[a..b],
            t_out: &self.t_out[a..b],
            prim: &self.plan.prim[a..b],
            sky: [s0, s1.max(s0)],
        }
    }

    /// Whether pixel `p` crosses any primitive.
    pub fn hits_anything(&self, p: usize) -> bool {
        self.plan.hits[p] > 0
    }
}

impl Rays for PlannedImage<'_> {
    fn prims(&self) -> &PrimInfo {
        self.prims
    }
    fn len(&self) -> usize {
        self.plan.hits.len()
    }
    fn ray<'s>(&'s self, r: u32, _: &'s mut RayPlan) -> Result<SceneRay<'s>> {
        let w = self.cam.width;
        let (origin, dir, z_scale) = pixel_ray(self.cam, r % w, r / w)?;
        Ok(SceneRay {
            origin,
            dir,
            z_scale,
            intervals: self.intervals(r),
            targets: RayTargets::NONE,
        })
    }
}

/// Index of label `l` in `classes`, or [`NONE`].
pub(super) fn class_index(classes: &[u8], l: u8) -> u16 {
    classes
        .iter()
        .position(|&c| c == l)
        .map_or(NONE, |i| i as u16)
}
