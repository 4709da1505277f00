//! A closed triangle mesh in local space (KITTI-360's general primitives), possibly non-convex.
//!
//! Ray intersection: every triangle crossing of the whole line (Moller-Trumbore, with a tiny
//! barycentric tolerance so a line through a shared edge or vertex is never missed), each signed
//! +1 entering / -1 leaving by the face orientation; crossings at the same `t` with the same
//! sign (one edge or vertex reported by several triangles) are merged, and the running winding
//! number gives the inside intervals (winding > 0). A line grazing a silhouette edge yields a
//! +1 and a -1 at the same `t`: an empty interval, dropped. Validation guarantees every edge
//! has exactly two faces traversing it in opposite directions, which makes the signs
//! meaningful. A mesh of more than 8 faces splits them in halves down to clusters of up to 8
//! nearby faces, and a line tests only the faces under nodes whose (padded) bounds it meets; the
//! crossings are then put back in face order, so the result is the face-by-face loop's, bit for
//! bit (tested).
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
    /// Crossings of one ray: (t, +1/-1, face normal, face). Reused so intersecting allocates
    /// nothing.
    static CROSSINGS: RefCell<Vec<(f64, i32, DVec3, u32)>> = const { RefCell::new(Vec::new()) };
}

/// Barycentric tolerance of the triangle test (relative).
const BARY_EPS: f64 = 1e-9;

/// Most faces in a cluster; a mesh with no more faces than this has none.
const CLUSTER_FACES: usize = 8;

/// A node of the hierarchy over a mesh's faces, in depth-first order: a line tests a leaf's
/// faces, or an inner node's subtree, only when it meets the node's bounds.
#[derive(Clone, Debug)]
struct Cluster {
    /// The bounds of the faces below, padded as `Mesh::ray_bounds` is.
    bounds: Aabb,
    /// A leaf's indices into `Mesh::order`; empty for an inner node.
    faces: std::ops::Range<usize>,
    /// The node after this one's subtree: where a line that misses `bounds` goes on.
    skip: u32,
}

#[derive(Clone, Debug)]
struct Tri {
    v0: DVec3,
    e1: DVec3,
    e2: DVec3,
    /// `1e-14 |e1| |e2|`: times `|d|`, the smallest `|det|` not taken for parallel.
    parallel: f64,
}

impl Tri {
    /// Pushes the crossing of the line `o + t d` (`dl = |d|`) with this face, if any
    /// (Moller-Trumbore with the tolerance `BARY_EPS`).
    #[inline]
    fn cross(&self, face: u32, o: DVec3, d: DVec3, dl: f64, out: &mut Vec<(f64, i32, DVec3, u32)>) {
        let pvec = d.cross(self.e2);
        let det = self.e1.dot(pvec);
        if det.abs() <= self.parallel * dl {
            return; // parallel to the face: its neighbours report the crossing
        }
        let inv = 1.0 / det;
        let tvec = o - self.v0;
        let u = tvec.dot(pvec) * inv;
        if !(-BARY_EPS..=1.0 + BARY_EPS).contains(&u) {
            return;
        }
        let qvec = tvec.cross(self.e1);
        let v = d.dot(qvec) * inv;
        if v < -BARY_EPS || u + v > 1.0 + BARY_EPS {
            return;
        }
        let t = self.e2.dot(qvec) * inv;
        // det > 0 <=> d . (e1 x e2) < 0 <=> entering through an outward face.
        let sign = if det > 0.0 { 1 } else { -1 };
        out.push((t, sign, self.e1.cross(self.e2), face));
    }

    fn bounds(&self) -> Aabb {
        let [a, b, c] = [self.v0, self.v0 + self.e1, self.v0 + self.e2];
        Aabb::new(a.min(b).min(c), a.max(b).max(c))
    }
}

/// The faces split at the median of their centres along the longest axis until at most
/// [`CLUSTER_FACES`] remain together, every split a node; bounds padded by `pad` (far beyond what
/// the barycentric tolerance lets a crossing stray from its face).
fn clusters(tris: &[Tri], pad: DVec3) -> (Vec<u32>, Vec<Cluster>) {
    if tris.len() <= CLUSTER_FACES {
        return (Vec::new(), Vec::new());
    }
    let mut order: Vec<u32> = (0..tris.len() as u32).collect();
    let mut out = Vec::new();
    split(tris, pad, &mut order, 0, &mut out);
    (order, out)
}

/// Appends the subtree over `order` (which starts at `start` in the whole order) to `out`.
fn split(tris: &[Tri], pad: DVec3, order: &mut [u32], start: usize, out: &mut Vec<Cluster>) {
    let centre = |i: u32| {
        let t = &tris[i as usize];
        t.v0 + (t.e1 + t.e2) / 3.0
    };
    let bounds = order
        .iter()
        .map(|&i| tris[i as usize].bounds())
        .reduce(|a, b| Aabb::new(a.min.min(b.min), a.max.max(b.max)))
        .expect("a cluster has faces");
    let node = out.len();
    let leaf = order.len() <= CLUSTER_FACES;
    out.push(Cluster {
        bounds: Aabb::new(bounds.min - pad, bounds.max + pad),
        faces: if leaf {
            start..start + order.len()
        } else {
            start..start
        },
        skip: 0,
    });
    if !leaf {
        let spread = Aabb::from_points(order.iter().map(|&i| centre(i))).extent();
        let axis = if spread.x >= spread.y && spread.x >= spread.z {
            0
        } else if spread.y >= spread.z {
            1
        } else {
            2
        };
        let mid = order.len() / 2;
        order.select_nth_unstable_by(mid, |&a, &b| centre(a)[axis].total_cmp(&centre(b)[axis]));
        let (lo, hi) = order.split_at_mut(mid);
        split(tris, pad, lo, start, out);
        split(tris, pad, hi, start + mid, out);
    }
    out[node].skip = out.len() as u32;
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
    /// Face indices grouped by [`Cluster`]s (a tessellated ellipsoid's line crosses few of its
    /// 224 faces); empty for small meshes.
    order: Vec<u32>,
    clusters: Vec<Cluster>,
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
                let (e1, e2) = (b - a, c - a);
                Tri {
                    v0: a,
                    e1,
                    e2,
                    parallel: 1e-14 * e1.length() * e2.length(),
                }
            })
            .collect::<Vec<Tri>>();
        let pad = DVec3::splat(1e-7 * diag);
        let (order, clusters) = clusters(&tris, pad);
        Ok(Self {
            order,
            clusters,
            verts: vertices.to_vec(),
            faces,
            tris,
            bounds,
            ray_bounds: Aabb::new(bounds.min - pad, bounds.max + pad),
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
            if self.clusters.is_empty() {
                for (i, tri) in self.tris.iter().enumerate() {
                    tri.cross(i as u32, o, d, dl, &mut c);
                }
            } else {
                let inv = Aabb::inv_dir(d);
                let (lo, hi) = (f64::NEG_INFINITY, f64::INFINITY);
                let mut k = 0;
                while let Some(cl) = self.clusters.get(k) {
                    if cl.bounds.ray_overlap(o, inv, lo, hi).is_some() {
                        for &i in &self.order[cl.faces.clone()] {
                            self.tris[i as usize].cross(i, o, d, dl, &mut c);
                        }
                        k += 1;
                    } else {
                        k = cl.skip as usize;
                    }
                }
                // Back in face order: the sort below then orders ties (a crossing through an
                // edge, seen by both faces) as the face-by-face loop did.
                c.sort_unstable_by_key(|x| x.3);
            }
            c.sort_unstable_by(|x, y| x.0.total_cmp(&y.0).then(y.1.cmp(&x.1)));
            let eps_t = self.merge_eps / dl;
            let mut w = 0i32;
            let mut start = (0.0, DVec3::Z);
            let mut last: Option<(f64, i32)> = None;
            for &(t, s, n, _) in c.iter() {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::demo::{star_mesh, Rng};
    use crate::geometry::Shape;

    /// Every interval (bits of `t_in`, `t_out` and the normal) of the line `o + t d`.
    fn intervals(m: &Mesh, o: DVec3, d: DVec3) -> Vec<[u64; 5]> {
        let mut out = Vec::new();
        m.intersect(o, d, &mut |li| {
            let n = li.n_in;
            out.push([li.t_in, li.t_out, n.x, n.y, n.z].map(f64::to_bits))
        });
        out
    }

    /// Testing the faces cluster by cluster gives the face-by-face loop's bytes, on lines aimed
    /// at random points, at vertices and at edge midpoints (ties between faces).
    #[test]
    fn clusters_give_the_bytes_of_every_face_tested() {
        let mut rng = Rng::new(5);
        let ellipsoid = crate::scene::kitti360_export::local_mesh(&Shape::Ellipsoid);
        let Shape::Mesh { vertices, faces } = star_mesh(5, 9, || rng.range(0.6, 1.4)) else {
            unreachable!()
        };
        for (v, f) in [ellipsoid, (vertices, faces)] {
            let clustered = Mesh::new(&v, &f).unwrap();
            assert!(clustered.clusters.len() > 4, "{} faces", f.len());
            let every_face = Mesh {
                order: Vec::new(),
                clusters: Vec::new(),
                ..clustered.clone()
            };
            let mut targets: Vec<DVec3> = v.clone();
            for t in &clustered.tris {
                targets.push(t.v0 + 0.5 * t.e1);
                targets.push(t.v0 + 0.5 * (t.e1 + t.e2));
                targets.push(t.v0 + rng.range(0.0, 0.5) * t.e1 + rng.range(0.0, 0.5) * t.e2);
            }
            let mut crossed = 0;
            for (k, target) in targets.iter().enumerate() {
                let o = DVec3::new(
                    rng.range(-3.0, 3.0),
                    rng.range(-3.0, 3.0),
                    rng.range(-3.0, 3.0),
                );
                let (o, d) = if k % 7 == 0 {
                    // Axis-parallel lines through the target, as camera rays often are not.
                    (DVec3::new(-3.0, target.y, target.z), DVec3::X)
                } else {
                    (o, *target - o)
                };
                let want = intervals(&every_face, o, d);
                crossed += !want.is_empty() as usize;
                assert_eq!(intervals(&clustered, o, d), want, "line {o} + t {d}");
            }
            assert!(
                crossed > targets.len() / 2,
                "{crossed} of {}",
                targets.len()
            );
        }
    }
}
