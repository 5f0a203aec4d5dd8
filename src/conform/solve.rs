//! The elastic solve (Ju et al. 2004, equation 2) as a sparse linear system: spring
//! (edge) weights, the weighted graph Laplacian, a preconditioned conjugate gradient for
//! `(diag(d) + eps L) X = B` with three right-hand columns at once, and per-vertex
//! best-fit rotations for the rotation-aware (as-rigid-as-possible) springs.

use crate::mesh::V3;
use nalgebra::{Matrix3, UnitQuaternion};
use rayon::prelude::*;
use sprs::{CsMat, TriMat};

/// A symmetric weighted Laplacian `L x|_i = sum_j c_ij (x_i - x_j)` stored as CSR of the
/// off-diagonal weights plus the diagonal sums.
#[derive(Debug, Clone)]
pub struct Laplacian {
    pub weights: CsMat<f64>,
    pub diag: Vec<f64>,
}

/// Edge weights: uniform springs (the paper's `k_ij`) or cotangent weights (clamped from
/// below so obtuse triangles cannot make the system indefinite), each scaled by the
/// stiffer of the two end vertices' group stiffness.
///
/// - `v`: #V rest positions; `tris`: #F triangles; `stiffness`: #V per-vertex factors
/// - `bridges`: extra springs between pieces of a fragmented mesh, weighted as a typical
///   edge (the median weight)
/// - returns the Laplacian with #V rows
pub fn laplacian(
    v: &[V3],
    tris: &[[u32; 3]],
    cotangent: bool,
    stiffness: &[f64],
    bridges: &[[u32; 2]],
) -> Laplacian {
    let n = v.len();
    let mut tri = TriMat::new((n, n));
    let mut typical: Vec<f64> = Vec::new();
    if cotangent {
        let mut raw: Vec<(u32, u32, f64)> = Vec::with_capacity(tris.len() * 3);
        for t in tris {
            for k in 0..3 {
                let (i, j, o) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
                let (a, b) = (v[i as usize] - v[o as usize], v[j as usize] - v[o as usize]);
                let cot = a.dot(&b) / a.cross(&b).norm().max(1e-300);
                raw.push((i.min(j), i.max(j), 0.5 * cot));
            }
        }
        raw.sort_unstable_by_key(|&(i, j, _)| (i, j));
        let mean = raw.iter().map(|r| r.2.abs()).sum::<f64>() / raw.len().max(1) as f64;
        let floor = 0.05 * mean;
        let mut k = 0;
        while k < raw.len() {
            let (i, j) = (raw[k].0, raw[k].1);
            let mut w = 0.0;
            while k < raw.len() && raw[k].0 == i && raw[k].1 == j {
                w += raw[k].2;
                k += 1;
            }
            let w = w.max(floor) * stiffness[i as usize].max(stiffness[j as usize]);
            typical.push(w);
            tri.add_triplet(i as usize, j as usize, w);
            tri.add_triplet(j as usize, i as usize, w);
        }
    } else {
        for [i, j] in crate::mesh::topology::edges(tris) {
            let w = stiffness[i as usize].max(stiffness[j as usize]);
            tri.add_triplet(i as usize, j as usize, w);
            tri.add_triplet(j as usize, i as usize, w);
        }
    }
    let bridge_weight = if typical.is_empty() {
        1.0
    } else {
        let k = typical.len() / 2;
        *typical.select_nth_unstable_by(k, f64::total_cmp).1
    };
    for &[i, j] in bridges {
        tri.add_triplet(i as usize, j as usize, bridge_weight);
        tri.add_triplet(j as usize, i as usize, bridge_weight);
    }
    let weights: CsMat<f64> = tri.to_csr();
    let diag = (0..n)
        .map(|i| weights.outer_view(i).map_or(0.0, |r| r.data().iter().sum()))
        .collect();
    Laplacian { weights, diag }
}

impl Laplacian {
    /// `L x` for #V vectors.
    pub fn apply(&self, x: &[V3]) -> Vec<V3> {
        let (ip, idx, w) = (
            self.weights.indptr(),
            self.weights.indices(),
            self.weights.data(),
        );
        let ip = ip.raw_storage();
        (0..x.len())
            .into_par_iter()
            .with_min_len(2048)
            .map(|i| {
                let mut s = x[i] * self.diag[i];
                for k in ip[i]..ip[i + 1] {
                    s -= x[idx[k]] * w[k];
                }
                s
            })
            .collect()
    }

    /// The right-hand side of rotation-aware springs:
    /// `b_i = sum_j c_ij (R_i + R_j)/2 (rest_i - rest_j)`; with all `R = I` it is `L rest`.
    pub fn rotated_rest(&self, rest: &[V3], rot: Option<&[Matrix3<f64>]>) -> Vec<V3> {
        let (ip, idx, w) = (
            self.weights.indptr(),
            self.weights.indices(),
            self.weights.data(),
        );
        let ip = ip.raw_storage();
        (0..rest.len())
            .into_par_iter()
            .with_min_len(2048)
            .map(|i| {
                let mut s = V3::zeros();
                for k in ip[i]..ip[i + 1] {
                    let j = idx[k];
                    let e = (rest[i] - rest[j]) * w[k];
                    s += match rot {
                        Some(r) => (r[i] + r[j]) * e * 0.5,
                        None => e,
                    };
                }
                s
            })
            .collect()
    }
}

impl Laplacian {
    /// The Laplacian over the `free` vertices alone with the others held (Dirichlet):
    /// the free-free weights, each free vertex's full diagonal. Returns it and the free
    /// vertices' indices in the whole mesh, in its row order.
    pub fn restricted(&self, free: &[bool]) -> (Laplacian, Vec<u32>) {
        let index: Vec<u32> = (0..free.len() as u32)
            .filter(|&i| free[i as usize])
            .collect();
        let mut row = vec![u32::MAX; free.len()];
        for (k, &i) in index.iter().enumerate() {
            row[i as usize] = k as u32;
        }
        let mut tri = TriMat::new((index.len(), index.len()));
        for (k, &i) in index.iter().enumerate() {
            if let Some(r) = self.weights.outer_view(i as usize) {
                for (j, &w) in r.iter() {
                    if free[j] {
                        tri.add_triplet(k, row[j] as usize, w);
                    }
                }
            }
        }
        let diag = index.iter().map(|&i| self.diag[i as usize]).collect();
        (
            Laplacian {
                weights: tri.to_csr(),
                diag,
            },
            index,
        )
    }

    /// `sum_j c_ij x_j` over vertex `i`'s neighbours that are not `free`: what the held
    /// vertices add to a free vertex's right-hand side.
    pub fn held_pull(&self, i: usize, free: &[bool], x: &[V3]) -> V3 {
        self.weights.outer_view(i).map_or(V3::zeros(), |r| {
            r.iter()
                .filter(|(j, _)| !free[*j])
                .map(|(j, &w)| x[j] * w)
                .sum()
        })
    }
}

/// Outcome of one linear solve.
#[derive(Debug, Clone, Copy, Default)]
pub struct SolveStats {
    pub iterations: usize,
    pub relative_residual: f64,
}

/// Solves `(diag(d) + eps L) X = B` by Jacobi-preconditioned conjugate gradients, the
/// three columns together, warm-started from `x`.
///
/// - `d`: #V non-negative data weights (at least one positive, or `eps L` regularised)
/// - `b`: #V right-hand sides; `x`: #V start values, overwritten with the solution
pub fn pcg(
    lap: &Laplacian,
    eps: f64,
    d: &[f64],
    b: &[V3],
    x: &mut [V3],
    rel_tol: f64,
    max_iter: usize,
) -> SolveStats {
    let n = x.len();
    let apply = |p: &[V3]| -> Vec<V3> {
        let lp = lap.apply(p);
        lp.into_par_iter()
            .with_min_len(4096)
            .enumerate()
            .map(|(i, l)| l * eps + p[i] * d[i])
            .collect()
    };
    let inv_diag: Vec<f64> = (0..n)
        .map(|i| 1.0 / (d[i] + eps * lap.diag[i]).max(1e-300))
        .collect();
    let ax = apply(x);
    let mut r: Vec<V3> = (0..n).map(|i| b[i] - ax[i]).collect();
    let bnorm = b
        .iter()
        .map(|v| v.norm_squared())
        .sum::<f64>()
        .sqrt()
        .max(1e-300);
    let dot = |a: &[V3], c: &[V3]| -> V3 {
        a.par_iter()
            .with_min_len(4096)
            .zip(c)
            .map(|(p, q)| p.component_mul(q))
            .reduce(V3::zeros, |s, t| s + t)
    };
    let mut z: Vec<V3> = (0..n).map(|i| r[i] * inv_diag[i]).collect();
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    for it in 0..max_iter {
        let rnorm = r.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
        if rnorm <= rel_tol * bnorm {
            return SolveStats {
                iterations: it,
                relative_residual: rnorm / bnorm,
            };
        }
        let ap = apply(&p);
        let pap = dot(&p, &ap);
        // Per-column step lengths: the three coordinates are independent systems.
        let alpha = V3::from_fn(|k, _| if pap[k] > 0.0 { rz[k] / pap[k] } else { 0.0 });
        x.par_iter_mut()
            .with_min_len(4096)
            .zip(&p)
            .for_each(|(xi, pi)| *xi += pi.component_mul(&alpha));
        r.par_iter_mut()
            .with_min_len(4096)
            .zip(&ap)
            .for_each(|(ri, ai)| *ri -= ai.component_mul(&alpha));
        z.par_iter_mut()
            .with_min_len(4096)
            .enumerate()
            .for_each(|(i, zi)| *zi = r[i] * inv_diag[i]);
        let rz_new = dot(&r, &z);
        let beta = V3::from_fn(|k, _| if rz[k] > 0.0 { rz_new[k] / rz[k] } else { 0.0 });
        rz = rz_new;
        p.par_iter_mut()
            .with_min_len(4096)
            .zip(&z)
            .for_each(|(pi, zi)| *pi = zi + pi.component_mul(&beta));
    }
    let rnorm = r.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
    SolveStats {
        iterations: max_iter,
        relative_residual: rnorm / bnorm,
    }
}

/// Over how much of the surface each vertex's rotation is fitted: `rings` rings of
/// neighbour averaging where triangles are of the typical size, and as many more passes
/// (at a rate falling with the triangle size) where they are finer, so that the support
/// is about the same patch of surface whatever the triangulation. With rings counted
/// alone, a densely triangulated part gets a support a few noise-widths across, and its
/// small triangles tilt with the scan's noise.
#[derive(Debug, Clone)]
pub struct RotationSupport {
    /// #V averaging rate per pass, in (0, 1]
    rate: Vec<f64>,
    passes: usize,
}

/// The most passes per ring a fine part gets (a part this much finer in area, or more).
const MAX_PASSES_PER_RING: usize = 8;

impl RotationSupport {
    /// - `lap`: the springs (their pattern gives the neighbours); `rest`: #V positions
    pub fn new(lap: &Laplacian, rest: &[V3], rings: usize) -> RotationSupport {
        let (ip, idx) = (lap.weights.indptr(), lap.weights.indices());
        let ip = ip.raw_storage();
        let n = rest.len();
        let size: Vec<f64> = (0..n)
            .map(|i| {
                let k = (ip[i + 1] - ip[i]).max(1) as f64;
                (ip[i]..ip[i + 1])
                    .map(|e| (rest[i] - rest[idx[e]]).norm())
                    .sum::<f64>()
                    / k
            })
            .collect();
        let mut sorted: Vec<f64> = size.iter().copied().filter(|s| *s > 0.0).collect();
        sorted.sort_by(f64::total_cmp);
        let uniform = || RotationSupport {
            rate: vec![1.0; n],
            passes: rings,
        };
        if sorted.is_empty() || rings == 0 {
            return uniform();
        }
        let typical = sorted[sorted.len() / 2];
        // the finest parts (the first percentile) set the passes; a mesh whose fine
        // triangles are within twice the typical area keeps the plain rings
        let fine = sorted[sorted.len() / 100];
        let finer = (typical / fine).powi(2);
        if finer <= 2.0 {
            return uniform();
        }
        let per_ring = (finer.ceil() as usize).min(MAX_PASSES_PER_RING);
        let rate = size
            .iter()
            .map(|&s| {
                if s > 0.0 {
                    ((typical / s).powi(2) / per_ring as f64).min(1.0)
                } else {
                    1.0
                }
            })
            .collect();
        RotationSupport {
            rate,
            passes: rings * per_ring,
        }
    }

    /// Averages #V values over each vertex's support (itself counted twice per pass).
    fn smooth<T>(&self, lap: &Laplacian, values: Vec<T>) -> Vec<T>
    where
        T: Copy
            + Send
            + Sync
            + std::ops::Add<Output = T>
            + std::ops::Mul<f64, Output = T>
            + std::ops::Div<f64, Output = T>,
    {
        let (ip, idx) = (lap.weights.indptr(), lap.weights.indices());
        let ip = ip.raw_storage();
        let mut m = values;
        for _ in 0..self.passes {
            m = (0..m.len())
                .into_par_iter()
                .with_min_len(1024)
                .map(|i| {
                    let mut a = m[i] * 2.0;
                    for k in ip[i]..ip[i + 1] {
                        a = a + m[idx[k]];
                    }
                    let mean = a / (2.0 + (ip[i + 1] - ip[i]) as f64);
                    let r = self.rate[i];
                    m[i] * (1.0 - r) + mean * r
                })
                .collect();
        }
        m
    }
}

/// Per-vertex best-fit rotations of the rest edges onto the current edges (the local
/// step of as-rigid-as-possible), smoothed by averaging each vertex's covariance over
/// its `support` before extracting the rotation: a lone noisy vertex cannot twist, and a
/// rotation seen in one place (a landmark, a feature) spreads quickly.
///
/// - `rest`, `cur`: #V positions; `rot`: #V rotations, warm start in and result out
/// - `scale`: optional #V local scales (out) and their limit, for as-similar-as-possible
pub fn fit_rotations(
    lap: &Laplacian,
    rest: &[V3],
    cur: &[V3],
    support: &RotationSupport,
    rot: &mut [UnitQuaternion<f64>],
    scale: Option<(&mut [f64], &[f64], f64)>,
) {
    let (ip, idx, w) = (
        lap.weights.indptr(),
        lap.weights.indices(),
        lap.weights.data(),
    );
    let ip = ip.raw_storage();
    let n = rest.len();
    let cov: Vec<Matrix3<f64>> = (0..n)
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            let mut a = Matrix3::zeros();
            for k in ip[i]..ip[i + 1] {
                let j = idx[k];
                a += (cur[i] - cur[j]) * (rest[i] - rest[j]).transpose() * w[k];
            }
            a
        })
        .collect();
    let cov = support.smooth(lap, cov);
    rot.par_iter_mut()
        .with_min_len(512)
        .enumerate()
        .for_each(|(i, q)| {
            *q = polar_rotation(&cov[i], *q);
        });
    // Local scale (as-similar-as-possible): s_i = tr(R_i^T A_i) / sum_j c_ij |rest edge|^2,
    // over the same smoothed neighbourhood, clamped to [1/limit, limit].
    if let Some((scale, sq, limit)) = scale {
        scale
            .par_iter_mut()
            .with_min_len(512)
            .enumerate()
            .for_each(|(i, s)| {
                let d = sq[i];
                let r = rot[i].to_rotation_matrix();
                let t = (r.matrix().transpose() * cov[i]).trace();
                *s = if d > 0.0 {
                    (t / d).clamp(1.0 / limit, limit)
                } else {
                    1.0
                };
            });
    }
}

/// Per vertex, `sum_j c_ij |rest_i - rest_j|^2` averaged over the `support` as
/// `fit_rotations` averages covariances: the denominator of the local scale. Depends on
/// the rest shape only, so it is computed once per conformation.
pub fn smoothed_rest_norms(lap: &Laplacian, rest: &[V3], support: &RotationSupport) -> Vec<f64> {
    let (ip, idx, w) = (
        lap.weights.indptr(),
        lap.weights.indices(),
        lap.weights.data(),
    );
    let ip = ip.raw_storage();
    let n = rest.len();
    let sq: Vec<f64> = (0..n)
        .map(|i| {
            (ip[i]..ip[i + 1])
                .map(|k| w[k] * (rest[i] - rest[idx[k]]).norm_squared())
                .sum()
        })
        .collect();
    support.smooth(lap, sq)
}

/// The rotation closest to `a` (maximising `tr(R^T a)`), by the iterative method of
/// Müller et al. 2016 warm-started from `q`: a few cheap steps instead of an SVD.
pub fn polar_rotation(a: &Matrix3<f64>, mut q: UnitQuaternion<f64>) -> UnitQuaternion<f64> {
    let scale = a.norm();
    if !(scale > 0.0) || !scale.is_finite() {
        return q;
    }
    let a = a / scale;
    for _ in 0..30 {
        let r = q.to_rotation_matrix();
        let r = r.matrix();
        let num = r.column(0).cross(&a.column(0))
            + r.column(1).cross(&a.column(1))
            + r.column(2).cross(&a.column(2));
        let den = (r.column(0).dot(&a.column(0))
            + r.column(1).dot(&a.column(1))
            + r.column(2).dot(&a.column(2)))
        .abs()
            + 1e-9;
        let omega: V3 = num / den;
        let angle = omega.norm();
        // 1e-4 rad (0.006 degrees): measured to change no result figure, and warm
        // starts reach it in a step or two
        if angle < 1e-4 {
            break;
        }
        q = if angle < 0.1 {
            // small step: the first-order quaternion of the rotation by omega, renormalised,
            // is the same step to 1e-4 relative and needs no sine or cosine
            let dq = nalgebra::Quaternion::new(1.0, 0.5 * omega.x, 0.5 * omega.y, 0.5 * omega.z);
            UnitQuaternion::new_normalize(dq * q.into_inner())
        } else {
            UnitQuaternion::from_scaled_axis(omega.normalize() * angle.min(1.0)) * q
        };
    }
    q
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polar_rotation_recovers_a_rotation_from_a_stretched_one() {
        let r = UnitQuaternion::from_euler_angles(0.4, -1.1, 2.0);
        let s = Matrix3::new(2.0, 0.1, 0.0, 0.1, 1.0, 0.0, 0.0, 0.0, 0.5);
        let a = r.to_rotation_matrix().matrix() * s;
        let got = polar_rotation(&a, UnitQuaternion::identity());
        assert!(got.angle_to(&r) < 1e-3, "{}", got.angle_to(&r));
    }

    #[test]
    fn pcg_solves_a_path_graph() {
        let v: Vec<V3> = (0..50).map(|i| V3::new(i as f64, 0., 0.)).collect();
        let tris: Vec<[u32; 3]> = (0..48).map(|i| [i, i + 1, i + 2]).collect();
        let lap = laplacian(&v, &tris, false, &vec![1.0; 50], &[]);
        let d: Vec<f64> = (0..50)
            .map(|i| if i % 7 == 0 { 1.0 } else { 0.0 })
            .collect();
        let truth: Vec<V3> = (0..50)
            .map(|i| V3::new((i as f64).sin(), 1.0, i as f64))
            .collect();
        let lt = lap.apply(&truth);
        let b: Vec<V3> = (0..50).map(|i| lt[i] * 0.3 + truth[i] * d[i]).collect();
        let mut x = vec![V3::zeros(); 50];
        let st = pcg(&lap, 0.3, &d, &b, &mut x, 1e-12, 2000);
        assert!(st.relative_residual < 1e-10);
        for (a, t) in x.iter().zip(&truth) {
            assert!((a - t).norm() < 1e-6);
        }
    }
}
