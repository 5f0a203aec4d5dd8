//! A virtual rig: stereo pods around a crate or booth, each with a speckle projector, that
//! render what their cameras would see of a subject mesh: the projected random-speckle
//! texture on the surface, simple shading, the lens distortion of the rig file, and sensor
//! noise. Every surface point carries the same speckle in both cameras of a pod, as a real
//! projector's pattern does, so the images are fit for stereo matching; ground truth comes
//! from the mesh.

use crate::mesh::{Mesh, V3};
use crate::stereo::calib::{Intrinsics, Pod, Pose};
use crate::stereo::rig::{PodSpec, RigFile};
use nalgebra::Vector2;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

/// One rendered camera image (8-bit grey), and for ground truth the surface point each
/// pixel sees.
pub struct Rendered {
    pub pod: String,
    pub side: &'static str,
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<u8>,
    pub points: Vec<Option<V3>>,
}

/// Smooth random speckle: value noise over a lattice, sharpened into blobs.
fn speckle_value(u: f64, v: f64, seed: u64) -> f64 {
    let hash = |i: i64, j: i64| -> f64 {
        let mut h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ seed;
        h ^= h >> 31;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 29;
        (h >> 11) as f64 / (1u64 << 53) as f64
    };
    let (i, j) = (u.floor() as i64, v.floor() as i64);
    let (fu, fv) = (u - u.floor(), v - v.floor());
    let s = |t: f64| t * t * (3.0 - 2.0 * t);
    let (a, b, c, d) = (
        hash(i, j),
        hash(i + 1, j),
        hash(i, j + 1),
        hash(i + 1, j + 1),
    );
    let x = a + (b - a) * s(fu) + (c - a) * s(fv) + (a - b - c + d) * s(fu) * s(fv);
    ((x - 0.5) * 4.0).tanh() * 0.5 + 0.5
}

/// Renders one camera of `pod` seeing `subject`, lit by the pod's projector (a pinhole
/// midway between the cameras, looking where the left camera looks).
pub fn render_camera(
    pod: &Pod,
    spec: &PodSpec,
    right: bool,
    subject: &Mesh,
    noise: f64,
    seed: u64,
) -> Rendered {
    let (k, pose): (Intrinsics, _) = pod.camera(right);
    let (w, h) = (k.width as usize, k.height as usize);
    // an undistorted canvas with a margin: barrel distortion shows more than the pinhole
    let margin = 0.3;
    let (mw, mh) = ((w as f64 * margin) as usize, (h as f64 * margin) as usize);
    let (cw, ch) = (w + 2 * mw, h + 2 * mh);
    let cam: Vec<V3> = subject.vertices.iter().map(|p| pose.to_camera(p)).collect();
    // perspective: -1/z is linear in screen space and smaller when nearer
    let screen: Vec<V3> = cam
        .iter()
        .map(|c| {
            V3::new(
                k.fx * c.x / c.z + k.cx + mw as f64,
                k.fy * c.y / c.z + k.cy + mh as f64,
                -1.0 / c.z,
            )
        })
        .collect();
    let hit = crate::render::raster::rasterize(&screen, &subject.triangles, cw, ch, |t| {
        subject.triangles[t]
            .iter()
            .all(|&i| cam[i as usize].z > 1e-6)
    });
    // the projector
    let centre = (pod.left_pose.centre() + pod.right_pose().centre()) / 2.0;
    let proj = Pose::look_at(centre, V3::from(spec.look_at), V3::from(spec.up));
    let scale = spec.focal_px / spec.speckle_px;
    let pattern_seed = seed_of(&pod.id);
    // the surface point a ray through image point (u, v) meets, and its triangle: the
    // triangle from the z-buffer, the point where the ray crosses that triangle's plane
    let rt = pose.r.transpose();
    let surface_at = |u: f64, v: f64| -> Option<(V3, u32)> {
        let n = k.undistort(Vector2::new((u - k.cx) / k.fx, (v - k.cy) / k.fy));
        let (x, y) = (k.fx * n.x + k.cx + mw as f64, k.fy * n.y + k.cy + mh as f64);
        if x < 0.0 || y < 0.0 || x >= cw as f64 || y >= ch as f64 {
            return None;
        }
        let t = hit[y as usize * cw + x as usize]?.triangle;
        let [a, b, c] = subject.triangles[t as usize].map(|i| cam[i as usize]);
        let normal = (b - a).cross(&(c - a));
        let dir = V3::new(n.x, n.y, 1.0);
        let s = normal.dot(&a) / normal.dot(&dir);
        (s.is_finite() && s > 0.0).then(|| (rt * (dir * s - pose.t), t))
    };
    let value = |p: &V3, t: u32| -> f64 {
        let n = subject.face_normal_scaled(t as usize).normalize();
        let pc = proj.to_camera(p);
        let lit = n.dot(&(centre - p).normalize()).abs();
        let s = if !spec.projector {
            // bare skin: a faint, smooth texture of its own
            0.5 + 0.02 * (p.x * 40.0).sin() * (p.y * 37.0).cos()
        } else if pc.z > 0.0 {
            speckle_value(pc.x / pc.z * scale, pc.y / pc.z * scale, pattern_seed)
        } else {
            0.0
        };
        25.0 + 200.0 * lit * (0.25 + 0.75 * s)
    };
    // per output pixel (OpenCV's convention: pixel (x, y) is centred on image point
    // (x, y)): the surface point at its centre, and its grey level averaged over 2x2
    // samples, as a sensor integrates light over a pixel (point samples of a sharp
    // speckle alias, which no camera shows)
    let rendered: Vec<(Option<V3>, f64)> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            let truth = surface_at(u, v).map(|(p, _)| p);
            let grey = [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)]
                .iter()
                .map(|(du, dv)| match surface_at(u + du, v + dv) {
                    Some((p, t)) => value(&p, t),
                    None => 12.0,
                })
                .sum::<f64>()
                / 4.0;
            (truth, grey)
        })
        .collect();
    let mut rng =
        ChaCha8Rng::seed_from_u64(seed ^ if right { 0x5a5a } else { 0xa5a5 } ^ pattern_seed);
    let gauss = Normal::new(0.0, noise.max(0.0)).expect("valid sigma");
    let pixels = rendered
        .iter()
        .map(|(_, g)| (g + gauss.sample(&mut rng)).round().clamp(0.0, 255.0) as u8)
        .collect();
    let points = rendered.into_iter().map(|(p, _)| p).collect();
    Rendered {
        pod: pod.id.clone(),
        side: if right { "right" } else { "left" },
        width: k.width,
        height: k.height,
        pixels,
        points,
    }
}

fn seed_of(id: &str) -> u64 {
    id.bytes().fold(0xcbf29ce484222325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x100000001b3)
    })
}

/// Renders every camera of the rig.
pub fn render_rig(rig: &RigFile, subject: &Mesh, noise: f64, seed: u64) -> Vec<Rendered> {
    let pods = rig.pods();
    let mut out = Vec::new();
    for (pod, spec) in pods.iter().zip(&rig.pods) {
        for right in [false, true] {
            out.push(render_camera(pod, spec, right, subject, noise, seed));
        }
    }
    out
}

/// A chessboard for calibration: `cols` x `rows` inner corners, squares of `square` m,
/// one white square of margin around; its own frame has the inner corners at
/// (i * square, j * square, 0) for i in 1..=cols, j in 1..=rows.
#[derive(Debug, Clone, Copy)]
pub struct Chessboard {
    pub cols: u32,
    pub rows: u32,
    pub square: f64,
}

/// Renders a chessboard at `board` (board frame to rig frame) as one camera of `pod`
/// sees it: 2x2 supersampled, lens distortion and noise as for subjects.
pub fn render_chessboard(
    pod: &Pod,
    right: bool,
    cb: &Chessboard,
    board: &Pose,
    noise: f64,
    seed: u64,
) -> Vec<u8> {
    let (k, pose): (Intrinsics, _) = pod.camera(right);
    let (w, h) = (k.width as usize, k.height as usize);
    // board pose as x_board = B x_rig + b; camera ray in the rig frame
    let (cr, centre) = (pose.r.transpose(), pose.centre());
    let shade = |u: f64, v: f64| -> f64 {
        let n = k.undistort(Vector2::new((u - k.cx) / k.fx, (v - k.cy) / k.fy));
        let dir = cr * V3::new(n.x, n.y, 1.0);
        let (o, d) = (board.to_camera(&centre), board.r * dir);
        if d.z.abs() < 1e-12 {
            return 40.0;
        }
        let s = -o.z / d.z;
        if s <= 0.0 {
            return 40.0;
        }
        let p = o + d * s;
        let (a, b) = (
            (p.x / cb.square).floor() as i64,
            (p.y / cb.square).floor() as i64,
        );
        let inside = a >= -1 && b >= -1 && a <= cb.cols as i64 + 1 && b <= cb.rows as i64 + 1;
        if !inside {
            return 40.0;
        }
        let on_margin = a == -1 || b == -1 || a == cb.cols as i64 + 1 || b == cb.rows as i64 + 1;
        if on_margin || (a + b).rem_euclid(2) == 1 {
            220.0
        } else {
            25.0
        }
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ if right { 77 } else { 11 });
    let gauss = Normal::new(0.0, noise.max(0.0)).expect("valid sigma");
    let vals: Vec<f64> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            // pixel (x, y) centred on image point (x, y), as in OpenCV
            let (u, v) = ((i % w) as f64, (i / w) as f64);
            [(-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)]
                .iter()
                .map(|(du, dv)| shade(u + du, v + dv))
                .sum::<f64>()
                / 4.0
        })
        .collect();
    vals.into_iter()
        .map(|v| (v + gauss.sample(&mut rng)).round().clamp(0.0, 255.0) as u8)
        .collect()
}

/// Board poses for calibration views of one pod: in front of the left camera at 0.6 to
/// 1.0 of its look-at distance, spread over the image, tilted up to 35 degrees.
pub fn chessboard_poses(
    pod: &Pod,
    spec: &PodSpec,
    cb: &Chessboard,
    views: usize,
    seed: u64,
) -> Vec<Pose> {
    use rand::Rng;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let centre = pod.left_pose.centre();
    let dist = (V3::from(spec.look_at) - centre).norm();
    let (bw, bh) = (
        (cb.cols + 1) as f64 * cb.square,
        (cb.rows + 1) as f64 * cb.square,
    );
    (0..views)
        .map(|_| {
            let d = dist * rng.random_range(0.55..0.9);
            let half_w = d * (pod.left.width as f64 / 2.0) / pod.left.fx;
            let half_h = d * (pod.left.height as f64 / 2.0) / pod.left.fy;
            let cx = rng.random_range(-0.5..0.5) * (2.0 * half_w - bw).max(0.0);
            let cy = rng.random_range(-0.5..0.5) * (2.0 * half_h - bh).max(0.0);
            // board centre in camera coordinates, facing the camera, then tilted
            let tilt = nalgebra::Rotation3::from_euler_angles(
                rng.random_range(-35.0f64..35.0).to_radians(),
                rng.random_range(-35.0f64..35.0).to_radians(),
                rng.random_range(-20.0f64..20.0).to_radians(),
            );
            // board frame in camera coordinates: x right, y down, z away from the camera
            let r_cam = *tilt.matrix();
            let origin_cam = V3::new(cx, cy, d) - r_cam * V3::new(bw / 2.0, bh / 2.0, 0.0);
            // rig -> board: x_board = R_cam^T (R x_rig + t - origin)
            let r = r_cam.transpose() * pod.left_pose.r;
            let t = r_cam.transpose() * (pod.left_pose.t - origin_cam);
            Pose { r, t }
        })
        .collect()
}

/// Where `simulate --placement` lays the board: face up on the floor (z = 0), centred
/// under the working volume (or the rig origin), its long side turned `yaw` degrees from
/// the rig's x.
pub fn placement_board(
    rig: &RigFile,
    cb: &Chessboard,
    yaw: f64,
) -> crate::stereo::calibrate::BoardPlacement {
    let centre = rig
        .working_volume
        .map(|[lo, hi]| V3::new((lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, 0.0))
        .unwrap_or_else(V3::zeros);
    // the board centre is half its size along its x and y axes from the origin
    let centred = crate::stereo::calibrate::BoardPlacement {
        origin: [0.0; 3],
        yaw,
    };
    let b = centred.board_from_rig().r;
    let half = V3::new(
        (cb.cols + 1) as f64 * cb.square / 2.0,
        (cb.rows + 1) as f64 * cb.square / 2.0,
        0.0,
    );
    let origin = centre - b.transpose() * half;
    crate::stereo::calibrate::BoardPlacement {
        origin: [origin.x, origin.y, origin.z],
        yaw,
    }
}
