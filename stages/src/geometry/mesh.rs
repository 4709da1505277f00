//! A closed triangle mesh in local space (KITTI-360's general primitives), possibly non-convex.
//!
//! Ray intersection: every triangle crossing of the whole line (Moller-Trumbore, with a tiny
//! barycentric tolerance so a line through a shared edge or vertex is never missed), each signed
//! +1 entering / -1 leaving by the face orientation; crossings at the same `t` with the same
//! sign (one edge or vertex reported by several triangles) are merged, and the running winding
//! number gives the inside intervals (winding > 0). A line grazing a silhouette edge yields a
//! +1 and a -1 at the same `t`: an empty interval, dropped. Validation guarantees every edge
//! has exactly two faces traversing it in opposite directions, which makes the signs
//! meaningful.
//!
//! Point test: the generalised winding number (sum of signed solid angles / 4 pi), independent
//! of the ray code, so tests can use one to check the other.

use std::{
    cell::RefCell,
    collections::{BTreeMap, HashMap},
    f64::consts::PI,
};

use glam::DVec3;

use super::aabb::Aabb;
use super::error::GeometryError;
use super::ray::LocalInterval;

thread_local! {
    /// Crossings of one ray: (t, +1/-1, face normal). Reused so intersecting allocates nothing.
    static CROSSINGS: RefCell<Vec<(f64, i32, DVec3)>> = const { RefCell::new(Vec::new()) };
}

/// Barycentric tolerance of the triangle test (relative).
const BARY_EPS: f64 = 1e-9;

#[derive(Clone, Debug)]
struct Tri {
    v0: DVec3,
    e1: DVec3,
    e2: DVec3,
}

/// A validated, outward-oriented mesh.
#[derive(Clone, Debug)]
pub struct Mesh {
    verts: Vec<DVec3>,
    faces: Vec<[u32; 3]>,
    tris: Vec<Tri>,
    bounds: Aabb,
    /// `bounds` padded by a hair, for the ray's early-out test (the triangle test has a tolerance).
    ray_bounds: Aabb,
    /// Crossings closer than this in `t * |d|` are one crossing.
    merge_eps: f64,
}

impl Mesh {
    /// Validates: finite, non-empty, indices in range, no degenerate face, every edge used by
    /// exactly two faces in opposite directions (after welding vertices with identical
    /// coordinates; error messages use the lowest index of each welded vertex), non-zero volume. An inward-wound mesh (negative
    /// volume) is flipped.
    pub fn new(vertices: &[DVec3], faces: &[[u32; 3]]) -> Result<Self, GeometryError> {
        if vertices.iter().any(|v| !v.is_finite()) {
            return Err(GeometryError::NonFinite("mesh vertices"));
        }
        if faces.is_empty() {
            return Err(GeometryError::MeshNoFaces);
        }
        let bounds = Aabb::from_points(vertices.iter().copied());
        let diag = bounds.extent().length();
        for (fi, f) in faces.iter().enumerate() {
            for &index in f {
                if index as usize >= vertices.len() {
                    return Err(GeometryError::MeshIndexOutOfRange {
                        face: fi,
                        index,
                        vertices: vertices.len(),
                    });
                }
            }
        }
        // Weld vertices with identical coordinates (meshes exported with per-face vertex
        // copies), so that connectivity is judged by position, not by index.
        let mut first_at: HashMap<[u64; 3], u32> = HashMap::new();
        let canon: Vec<u32> = vertices
            .iter()
            .enumerate()
            .map(|(i, v)| {
                let key = (*v + DVec3::ZERO).to_array().map(f64::to_bits); // -0.0 == 0.0
                *first_at.entry(key).or_insert(i as u32)
            })
            .collect();
        let faces: Vec<[u32; 3]> = faces.iter().map(|f| f.map(|i| canon[i as usize])).collect();
        let faces = &faces[..];
        let mut edges: BTreeMap<(u32, u32), (u32, u32)> = BTreeMap::new();
        for (fi, f) in faces.iter().enumerate() {
            let [a, b, c] = f.map(|i| vertices[i as usize]);
            if f[0] == f[1]
                || f[1] == f[2]
                || f[0] == f[2]
                || (b - a).cross(c - a).length() <= 1e-14 * diag * diag
            {
                return Err(GeometryError::MeshDegenerateFace { face: fi });
            }
            for k in 0..3 {
                let (i, j) = (f[k], f[(k + 1) % 3]);
                let e = edges.entry((i.min(j), i.max(j))).or_default();
                if i < j {
                    e.0 += 1
                } else {
                    e.1 += 1
                }
            }
        }
        for (&(a, b), &(fwd, back)) in &edges {
            if fwd + back != 2 {
                return Err(GeometryError::MeshOpen {
                    a,
                    b,
                    faces: fwd + back,
                });
            }
            if fwd != 1 {
                return Err(GeometryError::MeshFlippedFace { a, b });
            }
        }
        let volume: f64 = faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| vertices[i as usize] - bounds.centre());
                a.dot(b.cross(c)) / 6.0
            })
            .sum();
        let e = bounds.extent();
        if volume.abs() <= 1e-12 * (e.x * e.y * e.z).max(diag.powi(3) * 1e-6) {
            return Err(GeometryError::MeshZeroVolume);
        }
        let faces: Vec<[u32; 3]> = if volume < 0.0 {
            faces.iter().map(|&[a, b, c]| [a, c, b]).collect()
        } else {
            faces.to_vec()
        };
        let tris = faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| vertices[i as usize]);
                Tri {
                    v0: a,
                    e1: b - a,
                    e2: c - a,
                }
            })
            .collect();
        Ok(Self {
            verts: vertices.to_vec(),
            faces,
            tris,
            bounds,
            ray_bounds: Aabb::new(
                bounds.min - DVec3::splat(1e-7 * diag),
                bounds.max + DVec3::splat(1e-7 * diag),
            ),
            merge_eps: 1e-9 * diag,
        })
    }

    pub fn bounds(&self) -> Aabb {
        self.bounds
    }

    /// Outward-oriented faces (flipped if the input was inward-wound).
    pub fn faces(&self) -> &[[u32; 3]] {
        &self.faces
    }

    /// Generalised winding number of `q` (1 inside, 0 outside, 1/2 on a face).
    pub fn winding_number(&self, q: DVec3) -> f64 {
        let mut sum = 0.0;
        for f in &self.faces {
            let [a, b, c] = f.map(|i| self.verts[i as usize] - q);
            let (la, lb, lc) = (a.length(), b.length(), c.length());
            let det = a.dot(b.cross(c));
            let den = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
            sum += 2.0 * det.atan2(den);
        }
        sum / (4.0 * PI)
    }

    pub(crate) fn contains(&self, q: DVec3) -> bool {
        self.bounds.contains(q) && self.winding_number(q) >= 0.5
    }

    /// Calls `emit` with every interval of the whole line `o + t d` inside the mesh, in order.
    pub(crate) fn intersect(&self, o: DVec3, d: DVec3, emit: &mut impl FnMut(LocalInterval)) {
        if self
            .ray_bounds
            .ray_overlap(o, Aabb::inv_dir(d), f64::NEG_INFINITY, f64::INFINITY)
            .is_none()
        {
            return; // misses the local bounds: no triangle can be hit
        }
        let dl = d.length();
        CROSSINGS.with(|c| {
            let mut c = c.borrow_mut();
            c.clear();
            for tri in &self.tris {
                let pvec = d.cross(tri.e2);
                let det = tri.e1.dot(pvec);
                if det.abs() <= 1e-14 * tri.e1.length() * tri.e2.length() * dl {
                    continue; // parallel to the face: its neighbours report the crossing
                }
                let inv = 1.0 / det;
                let tvec = o - tri.v0;
                let u = tvec.dot(pvec) * inv;
                if !(-BARY_EPS..=1.0 + BARY_EPS).contains(&u) {
                    continue;
                }
                let qvec = tvec.cross(tri.e1);
                let v = d.dot(qvec) * inv;
                if v < -BARY_EPS || u + v > 1.0 + BARY_EPS {
                    continue;
                }
                let t = tri.e2.dot(qvec) * inv;
                // det > 0 <=> d . (e1 x e2) < 0 <=> entering through an outward face.
                let sign = if det > 0.0 { 1 } else { -1 };
                c.push((t, sign, tri.e1.cross(tri.e2)));
            }
            c.sort_unstable_by(|x, y| x.0.total_cmp(&y.0).then(y.1.cmp(&x.1)));
            let eps_t = self.merge_eps / dl;
            let mut w = 0i32;
            let mut start = (0.0, DVec3::Z);
            let mut last: Option<(f64, i32)> = None;
            for &(t, s, n) in c.iter() {
                if let Some((lt, ls)) = last {
                    if ls == s && t - lt <= eps_t {
                        continue; // the same crossing seen by a neighbouring triangle
                    }
                }
                last = Some((t, s));
                let prev = w;
                w = (w + s).max(0);
                if prev == 0 && w > 0 {
                    start = (t, n);
                } else if prev > 0 && w == 0 {
                    emit(LocalInterval {
                        t_in: start.0,
                        t_out: t,
                        n_in: start.1,
                    });
                }
            }
        });
    }
}
