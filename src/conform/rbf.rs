//! Global mapping by landmarks (Ju et al. 2004, equation 1): a radial basis function with
//! the biharmonic kernel phi(r) = r plus an affine part, interpolating template landmarks
//! onto scan landmarks.

use crate::mesh::V3;
use nalgebra::{DMatrix, DVector, Matrix3};

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RbfError {
    #[error(
        "{0} landmark pairs; the global mapping needs at least 4 that are not all in one plane"
    )]
    TooFew(usize),
    #[error("landmark '{0}' has a non-finite coordinate")]
    NotFinite(String),
    #[error("landmarks '{0}' and '{1}' are at the same place on the {2}")]
    Duplicate(String, String, &'static str),
    #[error(
        "the {0} landmarks all lie in one plane (or on a line), so the mapping is undetermined; add a landmark off that plane"
    )]
    Coplanar(&'static str),
    #[error("the landmark system could not be solved (the landmarks are degenerate)")]
    Singular,
}

/// `g(x) = A x + c + sum_i lambda_i |x - a_i|`, evaluated in normalised coordinates.
#[derive(Debug, Clone)]
pub struct RbfMap {
    centres: Vec<V3>,
    lambdas: Vec<V3>,
    linear: Matrix3<f64>,
    offset: V3,
    /// normalisation of the source space: x' = (x - origin) / scale
    origin: V3,
    scale: f64,
}

/// Relative flatness below which a landmark set counts as planar.
const PLANAR: f64 = 1e-3;

/// Fits the RBF mapping from landmark pairs.
///
/// - `names`: #N landmark names, for errors
/// - `src`: #N template landmark positions; `dst`: #N scan landmark positions
/// - `smoothing`: relative regularisation added to the kernel diagonal (0 interpolates
///   exactly); near-degenerate sets are also solved by a truncated SVD so they stay finite
///
/// Errors: fewer than 4 pairs, non-finite, duplicate or coplanar landmarks.
/// See also: `tests/landmarks.rs`.
pub fn fit(names: &[String], src: &[V3], dst: &[V3], smoothing: f64) -> Result<RbfMap, RbfError> {
    let n = src.len();
    if n < 4 || dst.len() != n {
        return Err(RbfError::TooFew(n.min(dst.len())));
    }
    for (i, (a, b)) in src.iter().zip(dst).enumerate() {
        if !a.iter().chain(b.iter()).all(|c| c.is_finite()) {
            return Err(RbfError::NotFinite(names[i].clone()));
        }
    }
    check_spread(names, src, "template")?;
    check_spread(names, dst, "scan")?;

    let origin = src.iter().sum::<V3>() / n as f64;
    let scale = (src.iter().map(|p| (p - origin).norm_squared()).sum::<f64>() / n as f64).sqrt();
    let c: Vec<V3> = src.iter().map(|p| (p - origin) / scale).collect();
    let m = n + 4;
    let mut a = DMatrix::<f64>::zeros(m, m);
    for i in 0..n {
        for j in 0..n {
            a[(i, j)] = (c[i] - c[j]).norm();
        }
        a[(i, i)] += smoothing;
        a[(i, n)] = 1.0;
        a[(n, i)] = 1.0;
        for k in 0..3 {
            a[(i, n + 1 + k)] = c[i][k];
            a[(n + 1 + k, i)] = c[i][k];
        }
    }
    let svd = a.svd(true, true);
    let smax = svd.singular_values.max();
    let mut sol = DMatrix::<f64>::zeros(m, 3);
    for k in 0..3 {
        let mut rhs = DVector::<f64>::zeros(m);
        for (r, d) in rhs.iter_mut().zip(dst) {
            *r = d[k];
        }
        let x = svd
            .solve(&rhs, smax * 1e-10)
            .map_err(|_| RbfError::Singular)?;
        sol.set_column(k, &x);
    }
    if !sol.iter().all(|v| v.is_finite()) {
        return Err(RbfError::Singular);
    }
    let lambdas = (0..n)
        .map(|i| V3::new(sol[(i, 0)], sol[(i, 1)], sol[(i, 2)]))
        .collect();
    let offset = V3::new(sol[(n, 0)], sol[(n, 1)], sol[(n, 2)]);
    let linear = Matrix3::from_fn(|r, col| sol[(n + 1 + col, r)]);
    Ok(RbfMap {
        centres: c,
        lambdas,
        linear,
        offset,
        origin,
        scale,
    })
}

fn check_spread(names: &[String], p: &[V3], what: &'static str) -> Result<(), RbfError> {
    let n = p.len();
    let centroid = p.iter().sum::<V3>() / n as f64;
    let extent = p.iter().map(|q| (q - centroid).norm()).fold(0.0, f64::max);
    if extent == 0.0 {
        return Err(RbfError::Duplicate(
            names[0].clone(),
            names[1].clone(),
            what,
        ));
    }
    for i in 0..n {
        for j in i + 1..n {
            if (p[i] - p[j]).norm() <= 1e-9 * extent {
                return Err(RbfError::Duplicate(
                    names[i].clone(),
                    names[j].clone(),
                    what,
                ));
            }
        }
    }
    let cov = p.iter().fold(Matrix3::zeros(), |m, q| {
        m + (q - centroid) * (q - centroid).transpose()
    });
    let ev = cov.symmetric_eigenvalues();
    let (lo, hi) = (ev.min().max(0.0).sqrt(), ev.max().sqrt());
    if lo <= PLANAR * hi {
        return Err(RbfError::Coplanar(what));
    }
    Ok(())
}

impl RbfMap {
    /// Maps one point.
    pub fn apply(&self, x: &V3) -> V3 {
        let y = (x - self.origin) / self.scale;
        let mut out = self.linear * y + self.offset;
        for (c, l) in self.centres.iter().zip(&self.lambdas) {
            out += l * (y - c).norm();
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("l{i}")).collect()
    }

    #[test]
    fn interpolates_landmarks_and_reproduces_affine_maps() {
        let src = vec![
            V3::new(0., 0., 0.),
            V3::new(1., 0., 0.),
            V3::new(0., 1., 0.),
            V3::new(0., 0., 1.),
            V3::new(1., 1., 1.),
            V3::new(0.3, 0.7, 0.2),
        ];
        let aff =
            |p: &V3| Matrix3::new(2., 0.1, 0., 0., 1.5, 0., 0.2, 0., 0.8) * p + V3::new(1., 2., 3.);
        let dst: Vec<V3> = src.iter().map(aff).collect();
        let m = fit(&names(6), &src, &dst, 0.0).unwrap();
        let probe = V3::new(0.5, 0.2, 0.9);
        assert!((m.apply(&probe) - aff(&probe)).norm() < 1e-8);
        let mut bent = dst.clone();
        bent[5] += V3::new(0.1, 0., 0.);
        let m = fit(&names(6), &src, &bent, 0.0).unwrap();
        for (s, d) in src.iter().zip(&bent) {
            assert!((m.apply(s) - d).norm() < 1e-8);
        }
    }
}
