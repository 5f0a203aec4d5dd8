//! Similarity transforms (scale, rotation, translation) and their least-squares fit to
//! point pairs (Umeyama 1991), shared by alignment and Procrustes analysis.

use super::V3;
use nalgebra::{Matrix3, Rotation3};

/// The rotation's angle in [0, pi], from the sine and cosine together: nalgebra's
/// `angle()` takes the arccosine of the trace, which is NaN when rounding puts the trace
/// a hair above 3 (a rotation composed many times close to the identity).
pub fn rotation_angle(r: &Rotation3<f64>) -> f64 {
    let m = r.matrix();
    let sin2 = V3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    )
    .norm();
    let cos2 = m[(0, 0)] + m[(1, 1)] + m[(2, 2)] - 1.0;
    sin2.atan2(cos2)
}

/// The rotation as axis times angle (radians), finite for every rotation matrix (see
/// [`rotation_angle`]); past about 170 degrees, where the skew part no longer fixes the
/// axis well, through the unit quaternion.
pub fn rotation_vector(r: &Rotation3<f64>) -> V3 {
    let m = r.matrix();
    let skew = V3::new(
        m[(2, 1)] - m[(1, 2)],
        m[(0, 2)] - m[(2, 0)],
        m[(1, 0)] - m[(0, 1)],
    );
    let angle = rotation_angle(r);
    if angle < 3.0 {
        let s = skew.norm();
        if s < 1e-300 {
            return V3::zeros();
        }
        // skew = 2 sin(angle) axis
        return skew * (angle / s);
    }
    // q and -q are the same rotation: the one with w >= 0 has its angle in [0, pi]
    let q = nalgebra::UnitQuaternion::from_rotation_matrix(r);
    let sign = if q.scalar() < 0.0 { -1.0 } else { 1.0 };
    let v = q.imag() * sign;
    let n = v.norm();
    if n < 1e-300 {
        return V3::zeros();
    }
    v * (2.0 * n.atan2(q.scalar() * sign) / n)
}

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
    fn rotation_vectors_are_finite_and_round_trip() {
        // a turn near the identity whose rounding puts the trace a hair above 3 (as
        // turns composed step after step do): nalgebra's angle() is NaN there
        let mut m = nalgebra::Matrix3::<f64>::identity() * (1.0 + 4e-16);
        m[(1, 0)] = 1e-9;
        m[(0, 1)] = -1e-9;
        let r = Rotation3::from_matrix_unchecked(m);
        assert!(r.angle().is_nan(), "the case no longer shows the rounding");
        assert!(rotation_vector(&r).iter().all(|x| x.is_finite()));
        assert!((rotation_angle(&r) - 1e-9).abs() < 1e-15);
        for angle in [0.0, 1e-12, 0.3, 1.5, 2.9, 3.05, 3.13, std::f64::consts::PI] {
            for axis in [V3::x(), V3::new(1.0, -2.0, 0.5).normalize(), -V3::z()] {
                let r = Rotation3::new(axis * angle);
                let back = rotation_vector(&r);
                assert!((rotation_angle(&r) - angle).abs() < 1e-9, "{angle}");
                assert!(
                    (Rotation3::new(back).matrix() - r.matrix()).norm() < 1e-9,
                    "{angle} {axis:?}: {back:?}"
                );
            }
        }
    }

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
