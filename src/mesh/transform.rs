//! Similarity transforms (scale, rotation, translation) and their least-squares fit to
//! point pairs (Umeyama 1991), shared by alignment and Procrustes analysis.

use super::V3;
use nalgebra::{Matrix3, Rotation3};

/// `x -> s R x + t`
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    pub scale: f64,
    pub rotation: Rotation3<f64>,
    pub translation: V3,
}

impl Default for Similarity {
    fn default() -> Self {
        Similarity {
            scale: 1.0,
            rotation: Rotation3::identity(),
            translation: V3::zeros(),
        }
    }
}

impl Similarity {
    pub fn apply(&self, x: &V3) -> V3 {
        self.rotation * x * self.scale + self.translation
    }
    pub fn inverse(&self) -> Similarity {
        let r = self.rotation.inverse();
        Similarity {
            scale: 1.0 / self.scale,
            rotation: r,
            translation: -(r * self.translation) / self.scale,
        }
    }
    /// `self` after `first`: x -> self(first(x))
    pub fn compose(&self, first: &Similarity) -> Similarity {
        Similarity {
            scale: self.scale * first.scale,
            rotation: self.rotation * first.rotation,
            translation: self.apply(&first.translation),
        }
    }
}

/// Least-squares similarity taking `src[i]` to `dst[i]` with weights `w` (all 1 if
/// `None`). With `allow_scale` false the scale stays 1 (a rigid fit). Returns the
/// identity for fewer than 3 pairs or zero total weight.
pub fn fit_similarity(src: &[V3], dst: &[V3], w: Option<&[f64]>, allow_scale: bool) -> Similarity {
    let wt = |i: usize| w.map_or(1.0, |w| w[i]);
    let total: f64 = (0..src.len()).map(wt).sum();
    if src.len() < 3 || !(total > 0.0) {
        return Similarity::default();
    }
    let cs = (0..src.len()).map(|i| src[i] * wt(i)).sum::<V3>() / total;
    let cd = (0..src.len()).map(|i| dst[i] * wt(i)).sum::<V3>() / total;
    let mut cov = Matrix3::zeros();
    let mut var_s = 0.0;
    for i in 0..src.len() {
        let (a, b) = (src[i] - cs, dst[i] - cd);
        cov += b * a.transpose() * wt(i);
        var_s += a.norm_squared() * wt(i);
    }
    let svd = cov.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * vt;
    let scale = if allow_scale && var_s > 0.0 {
        (svd.singular_values.component_mul(&d.diagonal())).sum() / var_s
    } else {
        1.0
    };
    let rotation = Rotation3::from_matrix_unchecked(r);
    Similarity {
        scale,
        rotation,
        translation: cd - rotation * cs * scale,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_known_similarity() {
        let src: Vec<V3> = (0..20)
            .map(|i| V3::new((i as f64).sin(), (i as f64 * 0.7).cos(), i as f64 * 0.1))
            .collect();
        let t = Similarity {
            scale: 1.7,
            rotation: Rotation3::from_euler_angles(0.3, -0.5, 1.2),
            translation: V3::new(1., -2., 0.5),
        };
        let dst: Vec<V3> = src.iter().map(|p| t.apply(p)).collect();
        let f = fit_similarity(&src, &dst, None, true);
        assert!((f.scale - 1.7).abs() < 1e-9);
        assert!((f.rotation.matrix() - t.rotation.matrix()).norm() < 1e-9);
        let back = f.inverse().apply(&dst[3]);
        assert!((back - src[3]).norm() < 1e-9);
    }
}
