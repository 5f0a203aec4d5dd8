//! A virtual scanner: sees a mesh from a few viewpoints (a triangle counts as seen when it
//! faces a viewpoint and the ray to its centre is not blocked), then resamples what was
//! seen as a point cloud with normals and noise, sharing no vertex with the mesh.

use crate::mesh::{Mesh, V3};
use parry3d_f64::math::Vector as PVec;
use parry3d_f64::query::{Ray, RayCast};
use parry3d_f64::shape::TriMesh;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// #F flags: seen from at least one of `viewpoints`.
pub fn visible_triangles(mesh: &Mesh, viewpoints: &[V3]) -> Vec<bool> {
    use rayon::prelude::*;
    let verts: Vec<PVec> = mesh
        .vertices
        .iter()
        .map(|p| PVec::new(p.x, p.y, p.z))
        .collect();
    let Ok(tm) = TriMesh::new(verts, mesh.triangles.clone()) else {
        return vec![false; mesh.triangles.len()];
    };
    let eps = mesh.diagonal() * 1e-6;
    (0..mesh.triangles.len())
        .into_par_iter()
        .map(|t| {
            let [a, b, c] = mesh.corners(t);
            let centre = (a + b + c) / 3.0;
            let n = mesh.face_normal_scaled(t);
            viewpoints.iter().any(|v| {
                let to = centre - v;
                if n.dot(&-to) <= 0.0 {
                    return false;
                }
                let dist = to.norm();
                let dir = to / dist;
                let ray = Ray::new(PVec::new(v.x, v.y, v.z), PVec::new(dir.x, dir.y, dir.z));
                tm.cast_local_ray(&ray, dist + eps, false)
                    .is_none_or(|toi| toi >= dist - 10.0 * eps)
            })
        })
        .collect()
}

/// `count` points on the triangles flagged in `mask`, spread by area, with normals
/// interpolated from the mesh's vertex normals and Gaussian noise of standard deviation
/// `noise` (scan units) along the normal. Deterministic for a given `seed`.
pub fn sample_points(mesh: &Mesh, mask: &[bool], count: usize, noise: f64, seed: u64) -> Mesh {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let vn = mesh.vertex_normals();
    let tris: Vec<usize> = (0..mesh.triangles.len()).filter(|&t| mask[t]).collect();
    let mut cum = Vec::with_capacity(tris.len());
    let mut total = 0.0;
    for &t in &tris {
        total += mesh.face_normal_scaled(t).norm() * 0.5;
        cum.push(total);
    }
    let mut out = Mesh::default();
    let mut normals = Vec::with_capacity(count);
    if tris.is_empty() {
        return out;
    }
    let gauss = Normal::new(0.0, noise.max(0.0)).expect("valid sigma");
    for _ in 0..count {
        let r = rng.random::<f64>() * total;
        let k = cum.partition_point(|&c| c < r).min(tris.len() - 1);
        let t = tris[k];
        let (mut u, mut v) = (rng.random::<f64>(), rng.random::<f64>());
        if u + v > 1.0 {
            u = 1.0 - u;
            v = 1.0 - v;
        }
        let [a, b, c] = mesh.corners(t);
        let [ia, ib, ic] = mesh.triangles[t].map(|i| i as usize);
        let n = (vn[ia] * (1.0 - u - v) + vn[ib] * u + vn[ic] * v).normalize();
        let p = a * (1.0 - u - v) + b * u + c * v + n * gauss.sample(&mut rng);
        out.vertices.push(p);
        normals.push(n);
    }
    out.normals = Some(normals);
    out
}

/// Viewpoints on a ring around `centre` at `radius`, `height` above it, starting at
/// `start_deg` (0 = +x) and stepping `step_deg`.
pub fn ring_viewpoints(
    centre: V3,
    radius: f64,
    height: f64,
    start_deg: f64,
    step_deg: f64,
    n: usize,
) -> Vec<V3> {
    (0..n)
        .map(|i| {
            let a = (start_deg + step_deg * i as f64).to_radians();
            centre + V3::new(radius * a.cos(), radius * a.sin(), height)
        })
        .collect()
}
