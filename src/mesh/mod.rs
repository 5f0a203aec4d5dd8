//! The `Mesh` type (vertices, triangles, optional normals, named vertex groups) and what
//! is computed from one mesh alone: bounding box, normals, file io, landmarks, topology,
//! and the quality figures of Ju et al. 2004, section 3.1.

pub mod decimate;
pub mod groups;
pub mod io;
pub mod landmarks;
pub mod quality;
pub mod topology;
pub mod transform;

use nalgebra::Vector3;
use std::collections::BTreeMap;

/// A 3-vector of `f64`, the geometry type used throughout conformd.
pub type V3 = Vector3<f64>;

pub use io::{FileError, read_mesh, write_mesh};
pub use landmarks::{Landmark, LandmarkPos, read_landmarks};

/// A triangle mesh or, with no triangles, a point cloud.
///
/// - `vertices`   #V list of positions
/// - `triangles`  #F list of vertex index triples, counter-clockwise seen from outside
/// - `normals`    optional #V list of unit normals (point clouds from scanners carry them)
/// - `groups`     named vertex groups (head, ears, legs...), sorted vertex indices
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<V3>,
    pub triangles: Vec<[u32; 3]>,
    pub normals: Option<Vec<V3>>,
    pub groups: BTreeMap<String, Vec<u32>>,
}

/// The normal of the plane through `points` (a neighbourhood), sign unspecified: the
/// least axis of their scatter about their centroid ([`least_axis`]).
pub fn plane_normal(points: impl Iterator<Item = V3> + Clone) -> V3 {
    let n = points.clone().count().max(1) as f64;
    let c = points.clone().sum::<V3>() / n;
    let scatter = points.fold(nalgebra::Matrix3::zeros(), |a, p| {
        let d = p - c;
        a + d * d.transpose()
    });
    least_axis(&scatter)
}

/// The unit axis of least spread of a symmetric positive semi-definite 3x3 matrix (a
/// neighbourhood's scatter: its plane's normal), sign unspecified. Closed form
/// (eigenvalues by the trigonometric formula, the vector from two rows' cross product),
/// many times faster than an iterative eigen-solver over a scan's every point; where the
/// two least eigenvalues are too close for that, the iterative solver decides.
pub fn least_axis(a: &nalgebra::Matrix3<f64>) -> V3 {
    let iterative = || -> V3 {
        let e = a.symmetric_eigen();
        e.eigenvectors.column(e.eigenvalues.imin()).into()
    };
    let off = a[(0, 1)].powi(2) + a[(0, 2)].powi(2) + a[(1, 2)].powi(2);
    let q = a.trace() / 3.0;
    let p2 =
        (a[(0, 0)] - q).powi(2) + (a[(1, 1)] - q).powi(2) + (a[(2, 2)] - q).powi(2) + 2.0 * off;
    let p = (p2 / 6.0).sqrt();
    if !(p > 0.0) || !p.is_finite() {
        return iterative();
    }
    let b = (a - nalgebra::Matrix3::identity() * q) / p;
    let phi = (b.determinant() / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    let least = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    let m = a - nalgebra::Matrix3::identity() * least;
    let rows: [V3; 3] = [0, 1, 2].map(|i| m.row(i).transpose());
    let best = [
        rows[0].cross(&rows[1]),
        rows[0].cross(&rows[2]),
        rows[1].cross(&rows[2]),
    ]
    .into_iter()
    .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))
    .unwrap_or_default();
    // the cross product scales with the gaps to the other two eigenvalues: next to
    // nothing when the least two are nearly equal (no one plane)
    if best.norm_squared() <= (1e-6 * m.norm_squared()).powi(2) {
        return iterative();
    }
    best.normalize()
}

/// Axis-aligned bounding box `(min, max)` of `points`; `None` when there are none.
pub fn bounds(points: impl IntoIterator<Item = V3>) -> Option<(V3, V3)> {
    let mut it = points.into_iter();
    let first = it.next()?;
    Some(it.fold((first, first), |(lo, hi), v| (lo.inf(&v), hi.sup(&v))))
}

impl Mesh {
    pub fn new(vertices: Vec<V3>, triangles: Vec<[u32; 3]>) -> Self {
        Mesh {
            vertices,
            triangles,
            normals: None,
            groups: BTreeMap::new(),
        }
    }

    /// The group names, comma-separated (for sentences naming what a mesh has).
    pub fn group_names(&self) -> String {
        self.groups.keys().cloned().collect::<Vec<_>>().join(", ")
    }

    pub fn is_point_cloud(&self) -> bool {
        self.triangles.is_empty()
    }

    /// Axis-aligned bounding box `(min, max)`; `None` for an empty mesh.
    pub fn bounding_box(&self) -> Option<(V3, V3)> {
        bounds(self.vertices.iter().copied())
    }

    /// Length of the bounding-box diagonal (0 for an empty mesh). Conformation tolerances
    /// are expressed relative to it so one config serves millimetres or metres.
    pub fn diagonal(&self) -> f64 {
        self.bounding_box().map_or(0.0, |(lo, hi)| (hi - lo).norm())
    }

    pub fn centroid(&self) -> V3 {
        if self.vertices.is_empty() {
            return V3::zeros();
        }
        self.vertices.iter().sum::<V3>() / self.vertices.len() as f64
    }

    /// Positions of one triangle's corners.
    pub fn corners(&self, t: usize) -> [V3; 3] {
        let [a, b, c] = self.triangles[t];
        [
            self.vertices[a as usize],
            self.vertices[b as usize],
            self.vertices[c as usize],
        ]
    }

    /// Unnormalised triangle normal (length = twice the area).
    pub fn face_normal_scaled(&self, t: usize) -> V3 {
        let [a, b, c] = self.corners(t);
        (b - a).cross(&(c - a))
    }
    /// Adds `other` as a loose part of its own, each vertex moved by `place`; returns
    /// the index of its first vertex here. Its groups are not carried, and stored
    /// normals are dropped (they would no longer cover every vertex).
    pub fn append(&mut self, other: &Mesh, place: impl Fn(&V3) -> V3) -> u32 {
        self.normals = None;
        let base = self.vertices.len() as u32;
        self.vertices.extend(other.vertices.iter().map(place));
        self.triangles
            .extend(other.triangles.iter().map(|t| t.map(|i| i + base)));
        base
    }

    /// Area-weighted vertex normals, unit length (zero for isolated vertices).
    pub fn vertex_normals(&self) -> Vec<V3> {
        vertex_normals(&self.vertices, &self.triangles)
    }

    /// `count` points spread evenly over the surface by area (stratified along the
    /// triangles' cumulative area), whatever the triangulation: statistics of the shape
    /// that a dense patch of small triangles does not outweigh. Deterministic.
    ///
    /// Returns min(count, ...) points; none for a mesh without area.
    pub fn surface_samples(&self, count: usize) -> Vec<V3> {
        let areas: Vec<f64> = (0..self.triangles.len())
            .map(|t| 0.5 * self.face_normal_scaled(t).norm())
            .collect();
        let total: f64 = areas.iter().sum();
        if !(total > 0.0) || count == 0 {
            return Vec::new();
        }
        let step = total / count as f64;
        let mut out = Vec::with_capacity(count);
        // the k-th sample sits at (k + 1/2) steps along the cumulative area; several in one
        // large triangle take different barycentric points (a low-discrepancy sequence)
        let mut next = 0.5 * step;
        let mut acc = 0.0;
        for (t, &a) in areas.iter().enumerate() {
            let mut j = 0usize;
            while next < acc + a && out.len() < count {
                let [p, q, r] = self.corners(t);
                let (mut u, mut v) = (
                    (0.5 + j as f64 * 0.618_033_988_75).fract(),
                    (0.5 + j as f64 * 0.754_877_666_25).fract(),
                );
                if u + v > 1.0 {
                    (u, v) = (1.0 - u, 1.0 - v);
                }
                out.push(p + (q - p) * u + (r - p) * v);
                next += step;
                j += 1;
            }
            acc += a;
        }
        out
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        (0..self.triangles.len())
            .map(|t| 0.5 * self.face_normal_scaled(t).norm())
            .sum()
    }

    /// Checks that every coordinate lies within [`MAX_COORDINATE`] of the origin; `what`
    /// names the mesh in the error.
    pub fn check_coordinates(&self, what: &str) -> Result<(), MeshError> {
        match self
            .vertices
            .iter()
            .enumerate()
            .find(|(_, p)| p.iter().any(|c| !(c.abs() <= MAX_COORDINATE)))
        {
            Some((index, p)) => Err(MeshError::TooFar {
                what: what.to_string(),
                index,
                at: [p.x, p.y, p.z],
            }),
            None => Ok(()),
        }
    }

    /// The first vertex with a coordinate that is not finite (NaN or infinite).
    pub fn first_non_finite(&self) -> Option<usize> {
        self.vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
    }

    /// Checks that every index is in range and every coordinate finite; `what` names the
    /// mesh in the error.
    pub fn validate(&self, what: &str) -> Result<(), MeshError> {
        let n = self.vertices.len() as u32;
        if let Some(index) = self.first_non_finite() {
            return Err(MeshError::NonFinite {
                what: what.to_string(),
                index,
            });
        }
        if let Some(triangle) = self
            .triangles
            .iter()
            .position(|t| t.iter().any(|&i| i >= n))
        {
            return Err(MeshError::IndexOutOfRange {
                what: what.to_string(),
                triangle,
                vertices: self.vertices.len(),
            });
        }
        if let Some(ns) = &self.normals
            && ns.len() != self.vertices.len()
        {
            return Err(MeshError::NormalCount {
                what: what.to_string(),
                normals: ns.len(),
                vertices: self.vertices.len(),
            });
        }
        Ok(())
    }
}

/// Why a mesh is unfit for geometry; `what` names the mesh (the template, the scan, a
/// file's mesh).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    #[error("{what}: vertex {index} has a non-finite coordinate")]
    NonFinite { what: String, index: usize },
    #[error(
        "{what}: triangle {triangle} refers to a vertex index out of range (the mesh has {vertices} vertices)"
    )]
    IndexOutOfRange {
        what: String,
        triangle: usize,
        vertices: usize,
    },
    #[error("{what}: {normals} normals for {vertices} vertices")]
    NormalCount {
        what: String,
        normals: usize,
        vertices: usize,
    },
    #[error(
        "{what}: vertex {index} at ({:e}, {:e}, {:e}) lies beyond {MAX_COORDINATE:e} from the origin",
        at[0], at[1], at[2]
    )]
    TooFar {
        what: String,
        index: usize,
        at: [f64; 3],
    },
    #[error("{what}: all {points} points lie in one place (no extent)")]
    NoExtent { what: String, points: usize },
    #[error("{what}: all {points} points lie on one line (no surface)")]
    OnALine { what: String, points: usize },
}

/// Largest coordinate accepted (kilometres in millimetres); beyond it squared distances
/// lose all precision, search structures misbehave and a picture's scale underflows, so
/// every mesh file read is held to it.
pub const MAX_COORDINATE: f64 = 1e9;

/// Keeps the triangles for which `keep(triangle index)` holds and drops vertices no kept
/// triangle uses. Returns the mesh and, for each new vertex, its old index.
pub fn keep_triangles(mesh: &Mesh, keep: impl Fn(usize) -> bool) -> (Mesh, Vec<u32>) {
    let mut map = vec![u32::MAX; mesh.vertices.len()];
    let mut old = Vec::new();
    let mut out = Mesh::default();
    for (t, tri) in mesh.triangles.iter().enumerate() {
        if !keep(t) {
            continue;
        }
        let nt = tri.map(|i| {
            if map[i as usize] == u32::MAX {
                map[i as usize] = old.len() as u32;
                old.push(i);
                out.vertices.push(mesh.vertices[i as usize]);
            }
            map[i as usize]
        });
        out.triangles.push(nt);
    }
    (out, old)
}

/// Area-weighted unit vertex normals of positions `v` (#V) and triangles `f` (#F).
pub fn vertex_normals(v: &[V3], f: &[[u32; 3]]) -> Vec<V3> {
    let mut n = vec![V3::zeros(); v.len()];
    for t in f {
        let [a, b, c] = t.map(|i| i as usize);
        let fn_ = (v[b] - v[a]).cross(&(v[c] - v[a]));
        n[a] += fn_;
        n[b] += fn_;
        n[c] += fn_;
    }
    for x in &mut n {
        let l = x.norm();
        if l > 0.0 {
            *x /= l;
        }
    }
    n
}

/// #V areas: a third of each triangle's area on each of its corners (the surface a
/// vertex stands for).
pub fn vertex_areas(v: &[V3], tris: &[[u32; 3]]) -> Vec<f64> {
    let mut a = vec![0.0; v.len()];
    for t in tris {
        let [p, q, r] = t.map(|i| v[i as usize]);
        let third = (q - p).cross(&(r - p)).norm() / 6.0;
        for &i in t {
            a[i as usize] += third;
        }
    }
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;

    #[test]
    fn least_axis_agrees_with_the_iterative_solver() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let iterative = |a: &Matrix3<f64>| -> V3 {
            let e = a.symmetric_eigen();
            e.eigenvectors.column(e.eigenvalues.imin()).into()
        };
        for k in 0..2000 {
            // a neighbourhood's scatter: flat (a plane with noise) or any shape
            let flat = if k % 2 == 0 { 1e-3 } else { 1.0 };
            let r = nalgebra::Rotation3::new(V3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
            ));
            let mut pts = Vec::new();
            for _ in 0..12 {
                let p = V3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0) * 0.7,
                    rng.random_range(-1.0..1.0) * flat,
                );
                pts.push(r * p * 0.004);
            }
            let c = pts.iter().sum::<V3>() / 12.0;
            let a = pts
                .iter()
                .fold(Matrix3::zeros(), |m, p| m + (p - c) * (p - c).transpose());
            let (got, want) = (least_axis(&a), iterative(&a));
            assert!((got.norm() - 1.0).abs() < 1e-12);
            assert!(
                got.dot(&want).abs() > 1.0 - 1e-9,
                "{k}: {got} against {want}"
            );
        }
        // no single least axis: any unit vector, never NaN
        for a in [
            Matrix3::identity(),
            Matrix3::zeros(),
            Matrix3::from_diagonal(&V3::new(0.0, 0.0, 1.0)),
        ] {
            let n = least_axis(&a);
            assert!((n.norm() - 1.0).abs() < 1e-12, "{a}: {n}");
        }
        let plane = Matrix3::from_diagonal(&V3::new(2.0, 1.0, 0.0));
        assert!((least_axis(&plane).z.abs() - 1.0).abs() < 1e-12);
    }
}
