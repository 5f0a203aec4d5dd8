//! The pinhole camera with Brown-Conrady distortion, a stereo pod (two cameras, the
//! right one's pose relative to the left), and calibration files in OpenCV's
//! `cv::FileStorage` YAML form (`M1 D1 M2 D2 R T` per pod).

use crate::mesh::V3;
use nalgebra::{Matrix3, Vector2};

/// Intrinsics: focal lengths and principal point in pixels, distortion (k1 k2 p1 p2 k3).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub dist: [f64; 5],
}

impl Intrinsics {
    /// Distorts normalised image coordinates.
    pub fn distort(&self, p: Vector2<f64>) -> Vector2<f64> {
        let [k1, k2, p1, p2, k3] = self.dist;
        let (x, y) = (p.x, p.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
        Vector2::new(
            x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
        )
    }

    /// Undistorts normalised coordinates by fixed-point iteration (as OpenCV does).
    pub fn undistort(&self, d: Vector2<f64>) -> Vector2<f64> {
        let mut p = d;
        for _ in 0..20 {
            let e = self.distort(p) - d;
            p -= e;
            if e.norm() < 1e-12 {
                break;
            }
        }
        p
    }

    /// A point in camera coordinates to (distorted) pixel coordinates; None behind.
    pub fn project(&self, c: &V3) -> Option<Vector2<f64>> {
        if c.z <= 1e-9 {
            return None;
        }
        let d = self.distort(Vector2::new(c.x / c.z, c.y / c.z));
        Some(Vector2::new(
            self.fx * d.x + self.cx,
            self.fy * d.y + self.cy,
        ))
    }

    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }
}

/// A camera's pose: `x_cam = R x_world + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub r: Matrix3<f64>,
    pub t: V3,
}

impl Pose {
    /// A camera at `eye` looking at `target`, image up along `up` (camera y points down).
    pub fn look_at(eye: V3, target: V3, up: V3) -> Pose {
        let z = (target - eye).normalize();
        let x = z.cross(&up).normalize();
        let y = z.cross(&x);
        let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        Pose { r, t: -(r * eye) }
    }
    pub fn to_camera(&self, p: &V3) -> V3 {
        self.r * p + self.t
    }
    pub fn centre(&self) -> V3 {
        -(self.r.transpose() * self.t)
    }
}

/// A stereo pod: left and right intrinsics, the left camera's pose in the rig frame, and
/// the right camera relative to the left (`x_right = R x_left + T`, OpenCV's convention).
#[derive(Debug, Clone, PartialEq)]
pub struct Pod {
    pub id: String,
    pub left: Intrinsics,
    pub right: Intrinsics,
    pub left_pose: Pose,
    pub r: Matrix3<f64>,
    pub t: V3,
}

impl Pod {
    pub fn right_pose(&self) -> Pose {
        Pose {
            r: self.r * self.left_pose.r,
            t: self.r * self.left_pose.t + self.t,
        }
    }
    pub fn baseline(&self) -> f64 {
        self.t.norm()
    }

    /// One of the pod's cameras: its intrinsics and its pose in the rig.
    pub fn camera(&self, right: bool) -> (Intrinsics, Pose) {
        if right {
            (self.right, self.right_pose())
        } else {
            (self.left, self.left_pose)
        }
    }

    /// The pod's calibration in OpenCV's FileStorage YAML (M1 D1 M2 D2 R T).
    pub fn opencv_yaml(&self) -> String {
        self.opencv_yaml_of(None)
    }

    /// As [`Pod::opencv_yaml`], naming the rig the pod belongs to, so that a calibration
    /// copied to another rig is recognised there.
    pub fn opencv_yaml_of(&self, rig: Option<&str>) -> String {
        fn mat(name: &str, rows: usize, cols: usize, data: &[f64]) -> String {
            let d: Vec<String> = data.iter().map(|v| format!("{v:.10e}")).collect();
            format!(
                "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
                d.join(", ")
            )
        }
        let m = |k: &Intrinsics| k.matrix().transpose().iter().copied().collect::<Vec<_>>();
        let r: Vec<f64> = self.r.transpose().iter().copied().collect();
        let mut s = String::from("%YAML:1.0\n---\n");
        // names are written only when YAML can carry them unquoted-safe
        let plain = |n: &str| {
            n.chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
        };
        if let Some(r) = rig.filter(|r| plain(r)) {
            s.push_str(&format!("rig: \"{r}\"\n"));
        }
        if plain(&self.id) {
            s.push_str(&format!("pod: \"{}\"\n", self.id));
        }
        s.push_str(&format!(
            "image_width: {}\nimage_height: {}\n",
            self.left.width, self.left.height
        ));
        s.push_str(&mat("M1", 3, 3, &m(&self.left)));
        s.push_str(&mat("D1", 1, 5, &self.left.dist));
        s.push_str(&mat("M2", 3, 3, &m(&self.right)));
        s.push_str(&mat("D2", 1, 5, &self.right.dist));
        s.push_str(&mat("R", 3, 3, &r));
        s.push_str(&mat("T", 3, 1, &[self.t.x, self.t.y, self.t.z]));
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_round_trips_and_projection_is_consistent() {
        let k = Intrinsics {
            width: 640,
            height: 480,
            fx: 700.0,
            fy: 700.0,
            cx: 320.0,
            cy: 240.0,
            dist: [-0.2, 0.05, 0.001, -0.001, 0.0],
        };
        let p = Vector2::new(0.3, -0.2);
        assert!((k.undistort(k.distort(p)) - p).norm() < 1e-10);
        let pose = Pose::look_at(V3::new(0., -2., 1.), V3::new(0., 0., 1.), V3::z());
        let c = pose.to_camera(&V3::new(0., 0., 1.));
        assert!(
            c.x.abs() < 1e-12 && c.y.abs() < 1e-12 && (c.z - 2.0).abs() < 1e-12,
            "the target is on the optical axis"
        );
        assert!((pose.centre() - V3::new(0., -2., 1.)).norm() < 1e-12);
        // image up is world up: a point above the target projects above the centre
        let above = k.project(&pose.to_camera(&V3::new(0., 0., 1.2))).unwrap();
        assert!(above.y < 240.0);
        let yaml = Pod {
            id: "p".into(),
            left: k,
            right: k,
            left_pose: pose,
            r: Matrix3::identity(),
            t: V3::new(-0.12, 0., 0.),
        }
        .opencv_yaml();
        assert!(
            yaml.starts_with("%YAML:1.0")
                && yaml.contains("M1: !!opencv-matrix")
                && yaml.contains("T: !!opencv-matrix\n   rows: 3\n   cols: 1")
        );
    }
}
