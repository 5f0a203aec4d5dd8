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
    pub fn check_coordinates(&self, what: &str) -> Result<(), String> {
        match self
            .vertices
            .iter()
            .enumerate()
            .find(|(_, p)| p.iter().any(|c| !(c.abs() <= MAX_COORDINATE)))
        {
            Some((i, p)) => Err(format!(
                "{what}: vertex {i} at ({:e}, {:e}, {:e}) lies beyond {MAX_COORDINATE:e} from the origin",
                p.x, p.y, p.z
            )),
            None => Ok(()),
        }
    }

    /// Checks that every index is in range and every coordinate finite; `what` names the
    /// mesh in the error.
    pub fn validate(&self, what: &str) -> Result<(), String> {
        let n = self.vertices.len() as u32;
        if let Some(i) = self
            .vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(format!("{what}: vertex {i} has a non-finite coordinate"));
        }
        if let Some(t) = self
            .triangles
            .iter()
            .position(|t| t.iter().any(|&i| i >= n))
        {
            return Err(format!(
                "{what}: triangle {t} refers to a vertex index out of range (the mesh has {n} vertices)"
            ));
        }
        if let Some(ns) = &self.normals
            && ns.len() != self.vertices.len()
        {
            return Err(format!("{what}: {} normals for {} vertices", ns.len(), n));
        }
        Ok(())
    }
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
