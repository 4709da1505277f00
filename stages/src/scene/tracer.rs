//! Exact rendering of the true geometry: first hit via the geometry BVH, procedural textures,
//! sun + ambient shading with cast shadows, and a per-image exposure (with occasional glare)
//! that over-exposes some regions.
//!
//! The ray through the pixel centre gives the ground-truth class, instance and z-depth (point
//! labels, as annotators and LiDAR give them). The colour is that ray's radiance, or with
//! `supersample` n > 1 the mean radiance over an n x n grid of rays spread evenly over the
//! pixel, as a real sensor integrates light over the pixel's footprint.

use crate::geometry::{Bvh, Camera, DVec3, Hit, Primitive, Ray};
use crate::labels::{self, INSTANCE_FACTOR, SKY};

use super::layout::{Layout, Material, Pattern};
use super::rng::{fbm2, hash, unit, value2, value3, Purpose, Rng};

/// Direction towards the sun (scene frame, z up).
pub fn sun() -> DVec3 {
    DVec3::new(0.35, -0.55, 0.76).normalize()
}

/// Photometric settings of one image.
#[derive(Debug, Clone, Copy)]
pub struct Look {
    /// Exposure gain (1 = nominal).
    pub exposure: f64,
    /// Optional glare: image point (u, v), radius in pixels, strength.
    pub glare: Option<(f64, f64, f64, f64)>,
    /// Seed of the sensor noise.
    pub noise_key: u64,
}

impl Look {
    /// The look of image (frame, camera): exposure varies per frame (both cameras alike, with a
    /// small per-camera difference), glare now and then.
    pub fn of(seed: u64, frame: u32, camera: u8, width: u32, height: u32) -> Self {
        let mut f = Rng::new(seed, Purpose::Exposure, &[frame as u64]);
        let base = (0.12 + 0.2 * f.normal()).exp().clamp(0.75, 1.7);
        let mut c = Rng::new(seed, Purpose::Exposure, &[frame as u64, camera as u64]);
        let exposure = base * (0.03 * c.normal()).exp();
        let glare = c.chance(0.4).then(|| {
            (
                c.range(0.1, 0.9) * width as f64,
                c.range(0.0, 0.45) * height as f64,
                c.range(0.08, 0.18) * width as f64,
                c.range(0.4, 0.8),
            )
        });
        Look {
            exposure,
            glare,
            noise_key: hash(&[seed, Purpose::Pixel as u64, frame as u64, camera as u64]),
        }
    }
}

/// Everything rendered for one image (row-major, `width * height`).
pub struct Rendered {
    pub rgb: Vec<u8>,
    pub labels: Vec<u8>,
    /// `label * 1000 + instance`.
    pub instances: Vec<u16>,
    /// z-depth, 0 for sky.
    pub depth: Vec<f32>,
    /// Any channel clipped.
    pub overexposed: Vec<bool>,
}

/// Sky colour along a view direction.
fn sky(dir: DVec3) -> [f64; 3] {
    let h = dir.z.max(0.0).powf(0.6);
    let horizon = [0.84, 0.88, 0.94];
    let zenith = [0.38, 0.56, 0.84];
    let glow = dir.dot(sun()).max(0.0).powi(48) * 0.9;
    std::array::from_fn(|k| horizon[k] + (zenith[k] - horizon[k]) * h + glow)
}

fn scale(c: [f64; 3], s: f64) -> [f64; 3] {
    c.map(|v| v * s)
}

fn mix(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    std::array::from_fn(|k| a[k] + (b[k] - a[k]) * t)
}

/// The albedo of a material at world point `p` with outward normal `n`; `texture` scales every
/// random variation about its mean (0: flat colours, joints and markings kept).
pub fn albedo(m: &Material, p: DVec3, n: DVec3, texture: f64) -> [f64; 3] {
    let c = m.color;
    // Every noise below is in [0, 1] about 0.5; texture 1 leaves it bit for bit.
    let d = |v: f64| {
        if texture == 1.0 {
            v
        } else {
            0.5 + texture * (v - 0.5)
        }
    };
    let fbm2 = |k, x, y| d(fbm2(k, x, y));
    let value2 = |k, x, y| d(value2(k, x, y));
    let value3 = |k, x, y, z| d(value3(k, x, y, z));
    let unit = |key: &[u64]| d(unit(key));
    let up = n.z > 0.5;
    let k = 0x7E47;
    match m.pattern {
        Pattern::Asphalt => {
            let base = scale(c, 0.8 + 0.35 * fbm2(k, p.x * 2.0, p.y * 2.0));
            let centre = p.y.abs() < 0.07 && p.x.rem_euclid(6.0) < 3.0;
            let edge = (p.y.abs() - 3.8).abs() < 0.07;
            if up && (centre || edge) {
                [0.88, 0.88, 0.86]
            } else {
                base
            }
        }
        Pattern::Paving => {
            let (u, v) = (p.x / 0.25, p.y / 0.25);
            let joint = u.fract().abs() < 0.12 || v.fract().abs() < 0.12;
            let stone = 0.85 + 0.3 * unit(&[k, u.floor() as u64, v.floor() as u64]);
            scale(c, if joint { 0.6 } else { stone })
        }
        Pattern::Slabs => {
            if !up {
                return [0.55, 0.55, 0.53]; // kerb face
            }
            let (u, v) = (p.x / 0.6, p.y / 0.6);
            let joint = u.rem_euclid(1.0) < 0.05 || v.rem_euclid(1.0) < 0.05;
            let slab = 0.9 + 0.15 * unit(&[k + 1, u.floor() as u64, v.floor() as u64]);
            scale(
                c,
                if joint {
                    0.7
                } else {
                    slab * (0.9 + 0.2 * value2(k, p.x * 3.0, p.y * 3.0))
                },
            )
        }
        Pattern::Grass => {
            let t = fbm2(k + 2, p.x * 0.8, p.y * 0.8);
            let fine = value2(k + 3, p.x * 9.0, p.y * 9.0);
            let dry = [0.55, 0.5, 0.3];
            scale(mix(c, dry, (t - 0.35).clamp(0.0, 0.6)), 0.8 + 0.35 * fine)
        }
        Pattern::Facade { x0, bay, floor } => {
            if up {
                return scale(c, 0.55); // roof
            }
            let along = if n.y.abs() > 0.5 { p.x - x0 } else { p.y };
            let u = along.rem_euclid(bay) / bay;
            let f = p.z / floor;
            let v = f.rem_euclid(1.0);
            let window = (0.25..0.75).contains(&u) && (0.3..0.78).contains(&v) && f > 0.2;
            if window && n.y.abs() > 0.5 {
                let w = unit(&[k + 4, (along / bay).floor() as u64, f.floor() as u64]);
                [0.12 + 0.15 * w, 0.16 + 0.15 * w, 0.2 + 0.18 * w]
            } else {
                scale(
                    c,
                    0.88 + 0.18 * value3(k + 5, p.x * 1.5, p.y * 1.5, p.z * 1.5),
                )
            }
        }
        Pattern::Foliage => {
            let t = value3(k + 6, p.x * 2.2, p.y * 2.2, p.z * 2.2);
            let fine = value3(k + 7, p.x * 7.0, p.y * 7.0, p.z * 7.0);
            scale(mix(c, [0.38, 0.5, 0.15], t * 0.6), 0.55 + 0.7 * fine)
        }
        Pattern::Bark => scale(
            c,
            0.75 + 0.4 * value3(k + 8, p.x * 6.0, p.y * 6.0, p.z * 1.2),
        ),
        Pattern::Paint => c,
        Pattern::Glass => {
            if up {
                c
            } else {
                mix([0.1, 0.12, 0.15], c, 0.15)
            }
        }
        Pattern::Tyre => c,
        Pattern::Concrete => scale(
            c,
            0.88 + 0.2 * value3(k + 9, p.x * 2.0, p.y * 2.0, p.z * 2.0),
        ),
        Pattern::Brick => {
            let row = (p.z / 0.075).floor();
            let along = p.x + if row as i64 % 2 == 0 { 0.0 } else { 0.12 };
            let mortar = (p.z / 0.075).fract() < 0.15 || (along / 0.24).rem_euclid(1.0) < 0.06;
            if mortar {
                [0.72, 0.7, 0.66]
            } else {
                scale(
                    c,
                    0.85 + 0.3 * unit(&[k + 10, (along / 0.24).floor() as u64, row as u64]),
                )
            }
        }
        Pattern::Slats => {
            let along = if n.x.abs() > 0.5 { p.y } else { p.x };
            let gap = (along / 0.12).rem_euclid(1.0) < 0.3;
            scale(
                c,
                if gap {
                    0.45
                } else {
                    0.9 + 0.2 * value2(k + 11, along * 20.0, p.z)
                },
            )
        }
        Pattern::Metal => scale(
            c,
            0.92 + 0.12 * value3(k + 12, p.x * 3.0, p.y * 3.0, p.z * 3.0),
        ),
    }
}

/// What a pixel ray sees.
pub struct Sample {
    pub label: u8,
    pub instance: u16,
    /// Distance along the ray (`None`: sky).
    pub t: Option<f64>,
    /// Linear colour before exposure.
    pub radiance: [f64; 3],
}

/// The true geometry at one frame: the static street and the moving objects where that frame
/// puts them.
pub struct World<'a> {
    pub layout: &'a Layout,
    /// Over `layout.parts`.
    pub bvh: &'a Bvh,
    /// The movers' parts at this frame, their materials and hierarchy.
    moving: Vec<Primitive>,
    moving_materials: Vec<Material>,
    moving_bvh: Bvh,
}

impl<'a> World<'a> {
    /// The street at `frame`.
    pub fn at(layout: &'a Layout, bvh: &'a Bvh, frame: u32) -> Self {
        let (mut moving, mut moving_materials) = (Vec::new(), Vec::new());
        for m in layout.movers.iter().filter(|m| m.frames.contains(&frame)) {
            moving.extend(m.parts_at(frame));
            moving_materials.extend_from_slice(&m.materials);
        }
        let moving_bvh = Bvh::build(&moving);
        Self {
            layout,
            bvh,
            moving,
            moving_materials,
            moving_bvh,
        }
    }

    /// The nearest surface along `ray` in `[t_min, t_max]`: its hit, part and material.
    pub fn first_hit(
        &self,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
    ) -> Option<(Hit, &Primitive, &Material)> {
        let (hit, moving) = Bvh::first_hit_of_two(
            (self.bvh, &self.layout.parts),
            (&self.moving_bvh, &self.moving),
            ray,
            t_min,
            t_max,
        )?;
        let k = hit.prim as usize;
        Some(if moving {
            (hit, &self.moving[k], &self.moving_materials[k])
        } else {
            (hit, &self.layout.parts[k], &self.layout.materials[k])
        })
    }
}

/// Traces one ray against the true geometry.
pub fn trace(world: &World, ray: &Ray) -> Sample {
    let Some((hit, part, material)) = world.first_hit(ray, 0.0, 1.0e4) else {
        return Sample {
            label: SKY,
            instance: SKY as u16 * INSTANCE_FACTOR as u16,
            t: None,
            radiance: sky(ray.dir),
        };
    };
    let t = hit.t_in.max(0.0);
    let p = ray.at(t);
    let n = hit.normal_in;
    let a = albedo(material, p, n, world.layout.texture);
    let s = sun();
    let lit = n.dot(s).max(0.0);
    let shadow = lit > 0.0 && {
        let sray = Ray {
            origin: p + n * 1e-4,
            dir: s,
        };
        world.first_hit(&sray, 1e-3, 300.0).is_some()
    };
    let direct = if shadow { 0.0 } else { 0.75 * lit };
    // Contact darkening at the foot of vertical surfaces.
    let ao = if n.z.abs() < 0.5 {
        1.0 - 0.25 * (-(p.z.max(0.0)) / 0.35).exp()
    } else {
        1.0
    };
    let shade = (0.45 + 0.25 * n.z.max(0.0) + direct) * ao;
    // KITTI-360's thing classes (the paper's five among them) keep their instances.
    let instance = if labels::by_id(part.label).is_some_and(|l| l.has_instances) {
        part.instance
    } else {
        0
    };
    Sample {
        label: part.label,
        instance: (part.label as u32 * INSTANCE_FACTOR + instance) as u16,
        t: Some(t),
        radiance: scale(a, shade),
    }
}

/// The mean radiance over an `n` x `n` grid of rays spread evenly over pixel `(x, y)`;
/// `centre` is the radiance of the centre ray, which is one of the grid's when `n` is odd.
/// Sub-pixel rays outside a fisheye's lens are left out of the mean (the centre ray's radiance
/// when all are).
pub fn pixel_radiance(
    world: &World,
    cam: &Camera,
    (x, y): (usize, usize),
    n: u32,
    centre: [f64; 3],
) -> [f64; 3] {
    if n <= 1 {
        return centre;
    }
    let mut sum = [0.0; 3];
    let mut count = 0u32;
    for j in 0..n {
        for i in 0..n {
            let radiance = if n % 2 == 1 && i == n / 2 && j == n / 2 {
                centre
            } else {
                let u = x as f64 + (i as f64 + 0.5) / n as f64;
                let v = y as f64 + (j as f64 + 0.5) / n as f64;
                let Some(ray) = cam.ray(u, v) else {
                    continue;
                };
                trace(world, &ray).radiance
            };
            for k in 0..3 {
                sum[k] += radiance[k];
            }
            count += 1;
        }
    }
    if count == 0 {
        // A lens-rim pixel whose sub-rays (n even: the centre is not one) all miss the lens.
        return centre;
    }
    sum.map(|v| v / count as f64)
}

/// Renders one image; `supersample` rays per pixel side for the colour (1: the centre ray).
pub fn render(world: &World, cam: &Camera, look: &Look, supersample: u32) -> Rendered {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut out = Rendered {
        rgb: vec![0; w * h * 3],
        labels: vec![0; w * h],
        instances: vec![0; w * h],
        depth: vec![0.0; w * h],
        overexposed: vec![false; w * h],
    };
    let mut rng = Rng::new(look.noise_key, Purpose::Pixel, &[]);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            // Outside a fisheye's lens: black and unlabelled, as the real images are.
            let Some(ray) = cam.pixel_ray(x as u32, y as u32) else {
                continue;
            };
            let s = trace(world, &ray);
            out.labels[i] = s.label;
            out.instances[i] = s.instance;
            if let Some(t) = s.t {
                out.depth[i] = cam.depth(&ray, t) as f32;
            }
            let glare = look.glare.map_or(0.0, |(gu, gv, r, k)| {
                let d2 = (x as f64 + 0.5 - gu).powi(2) + (y as f64 + 0.5 - gv).powi(2);
                k * (-d2 / (r * r)).exp()
            });
            let radiance = pixel_radiance(world, cam, (x, y), supersample, s.radiance);
            let mut clipped = false;
            for (c, r) in radiance.iter().enumerate() {
                let v = r * look.exposure + glare + 0.006 * rng.normal();
                clipped |= v >= 1.0;
                out.rgb[i * 3 + c] = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
            }
            out.overexposed[i] = clipped;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::layout::Material;

    #[test]
    fn texture_scales_every_variation_about_its_mean_and_keeps_joints() {
        let points = [
            DVec3::new(0.31, 2.2, 0.4),
            DVec3::new(5.77, -1.3, 1.9),
            DVec3::new(-3.1, 7.45, 0.05),
        ];
        let wall = DVec3::new(0.0, 1.0, 0.0);
        for pattern in [Pattern::Concrete, Pattern::Metal, Pattern::Bark] {
            let m = Material {
                pattern,
                color: [0.5, 0.4, 0.3],
            };
            let a = |p, t| albedo(&m, p, wall, t);
            let mut most = 0f64;
            for q in &points[1..] {
                for k in 0..3 {
                    // Linear in the texture: half the detail, half the difference.
                    let full = a(*q, 1.0)[k] - a(points[0], 1.0)[k];
                    let half = a(*q, 0.5)[k] - a(points[0], 0.5)[k];
                    assert!((half - 0.5 * full).abs() < 1e-12, "{pattern:?}");
                    most = most.max(full.abs());
                    assert_eq!(a(*q, 0.0)[k], a(points[0], 0.0)[k], "{pattern:?} flat at 0");
                }
            }
            assert!(most > 1e-3, "{pattern:?} varies at texture 1");
        }
        // Brick at texture 0: every brick alike, the mortar still apart.
        let brick = Material {
            pattern: Pattern::Brick,
            color: [0.6, 0.3, 0.2],
        };
        let b = |x: f64, z: f64| albedo(&brick, DVec3::new(x, 0.0, z), wall, 0.0);
        assert_eq!(b(0.05, 0.04), b(0.53, 0.19));
        assert_ne!(b(0.05, 0.04), b(0.05, 0.076));
    }
}
