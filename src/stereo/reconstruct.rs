//! A capture set to a scan: per pod, rectify (maps built once per calibration and
//! cached), disparity, reproject into the rig frame; then either fuse all pods' points
//! (crop to the working volume, voxel-downsample, remove outliers, normals turned towards
//! the camera that saw each point) or triangulate each pod's depth grid with a cut at
//! depth discontinuities into one mesh with holes.

use super::calib::Pod;
use super::disparity::{SgbmOptions, gray_mat, match_pair, pixel_grids};
use crate::mesh::{Mesh, V3, keep_triangles, topology};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use opencv::calib3d;
use opencv::core::{self, Mat, Rect, Size};
use opencv::imgproc;
use opencv::prelude::*;
use rayon::prelude::*;
use std::collections::HashMap;
use std::num::NonZero;
use std::time::Instant;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReconstructOptions {
    pub sgbm: SgbmOptions,
    /// voxel edge for downsampling (m); 0 keeps every point
    pub voxel: f64,
    /// outlier removal: neighbours considered (0: no removal), and how many standard
    /// deviations above the mean neighbour distance a point may be
    pub outlier_k: usize,
    pub outlier_sigma: f64,
    /// [min, max] corners of the rig's working volume (m)
    pub working_volume: Option<[[f64; 3]; 2]>,
    /// triangulation of the depth grids (`reconstruct --mesh`)
    pub mesh: GridMeshOptions,
    /// with a working volume, each pod searches only the disparities the volume can
    /// produce (from its nearest to its farthest corner), in place of
    /// `sgbm.min_disparity` and `sgbm.num_disparities`: no match outside the volume, a
    /// near booth not cut off at 128 pixels, and less work for a far one
    pub auto_disparity_range: bool,
    /// with a working volume, each pod matches only the window of its images the volume
    /// can appear in (pixels outside it lie outside the volume, which the fusion crops)
    pub volume_window: bool,
}

/// Pixels around a working volume's projected corners that a pod still matches.
const VOLUME_WINDOW_MARGIN: f64 = 24.0;

/// How a pod's depth grid becomes a mesh ([`DepthGrid::mesh`]).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GridMeshOptions {
    /// grid spacing, pixels
    pub step: usize,
    /// neighbours further apart in depth than this many times the lateral grid spacing
    /// are not joined (a surface steeper than atan(depth_cut) to the image plane)
    pub depth_cut: f64,
    /// smallest connected piece kept, triangles
    pub min_component: usize,
}

impl Default for GridMeshOptions {
    fn default() -> Self {
        GridMeshOptions {
            step: 3,
            depth_cut: 4.0,
            min_component: 200,
        }
    }
}

impl Default for ReconstructOptions {
    fn default() -> Self {
        ReconstructOptions {
            sgbm: SgbmOptions::default(),
            voxel: 0.004,
            outlier_k: 8,
            outlier_sigma: 2.0,
            working_volume: None,
            mesh: GridMeshOptions::default(),
            auto_disparity_range: true,
            volume_window: true,
        }
    }
}

/// Per-pod and per-stage figures.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ReconstructReport {
    pub pods: Vec<PodReport>,
    pub fused_points: usize,
    pub after_crop: usize,
    pub after_voxel: usize,
    pub after_outliers: usize,
    /// triangles of the scan (`--mesh`; 0 for a point cloud)
    pub triangles: usize,
    pub seconds_fuse: f64,
    pub seconds_total: f64,
}

#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct PodReport {
    pub pod: String,
    pub points: usize,
    pub valid_disparity_share: f64,
    /// the rectification maps came from the cache (built for an earlier capture)
    pub maps_reused: bool,
    /// the disparities searched, [first, past the last], pixels
    pub disparities: [i32; 2],
    /// the window of the rectified image matched ([x, y, width, height], pixels), when
    /// not the whole image
    pub window: Option<[i32; 4]>,
    pub seconds_rectify: f64,
    pub seconds_disparity: f64,
    pub seconds_reproject: f64,
    /// time in conformd's own code (image copies, masking, frame changes), the rest of
    /// the pod's time being OpenCV's
    pub seconds_own: f64,
}

fn mat3(m: &nalgebra::Matrix3<f64>) -> opencv::Result<Mat> {
    Mat::from_slice_2d(&[
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ])
}

/// A pod's calibration as OpenCV matrices, and its rectification (R1 R2 P1 P2 Q).
pub struct Rectification {
    pub m1: Mat,
    pub d1: Mat,
    pub m2: Mat,
    pub d2: Mat,
    pub r1: Mat,
    pub r2: Mat,
    pub p1: Mat,
    pub p2: Mat,
    pub q: Mat,
}

/// Rectifies a pod (`stereoRectify`, zero disparity at infinity, no scaling).
pub fn rectification(pod: &Pod) -> opencv::Result<Rectification> {
    let size = Size::new(pod.left.width as i32, pod.left.height as i32);
    let (m1, m2) = (mat3(&pod.left.matrix())?, mat3(&pod.right.matrix())?);
    let (d1, d2) = (
        Mat::from_slice(&pod.left.dist)?.try_clone()?,
        Mat::from_slice(&pod.right.dist)?.try_clone()?,
    );
    let t = Mat::from_slice_2d(&[[pod.t.x], [pod.t.y], [pod.t.z]])?;
    let mut out = Rectification {
        m1,
        d1,
        m2,
        d2,
        r1: Mat::default(),
        r2: Mat::default(),
        p1: Mat::default(),
        p2: Mat::default(),
        q: Mat::default(),
    };
    let (mut roi1, mut roi2) = (Rect::default(), Rect::default());
    let Rectification {
        m1,
        d1,
        m2,
        d2,
        r1,
        r2,
        p1,
        p2,
        q,
    } = &mut out;
    calib3d::stereo_rectify(
        m1,
        d1,
        m2,
        d2,
        size,
        &mat3(&pod.r)?,
        &t,
        r1,
        r2,
        p1,
        p2,
        q,
        calib3d::CALIB_ZERO_DISPARITY,
        0.0,
        size,
        &mut roi1,
        &mut roi2,
    )?;
    Ok(out)
}

/// A pod ready to reconstruct: its calibration, its rectification and both cameras'
/// undistort-rectify maps (fixed-point, for a fast `remap`). Building the maps is most of
/// a rectification's cost, so a station builds them once per calibration
/// ([`RectifierCache`]) and reuses them for every capture.
pub struct PodRectifier {
    pub pod: Pod,
    pub rect: Rectification,
    maps: [(Mat, Mat); 2],
    /// rectified-left camera coordinates to the rig frame: `x_rig = rot * x + shift`
    rot: nalgebra::Matrix3<f64>,
    shift: V3,
    /// focal length of the rectified cameras, pixels
    focal: f64,
    /// each pixel's x and y, for the sub-pixel refinement's warps
    grids: (Mat, Mat),
}

impl PodRectifier {
    pub fn new(pod: &Pod) -> opencv::Result<PodRectifier> {
        let size = Size::new(pod.left.width as i32, pod.left.height as i32);
        let rect = rectification(pod)?;
        let map = |m: &Mat, d: &Mat, r: &Mat, p: &Mat| -> opencv::Result<(Mat, Mat)> {
            let (mut m1, mut m2) = (Mat::default(), Mat::default());
            calib3d::init_undistort_rectify_map(
                m,
                d,
                r,
                p,
                size,
                core::CV_16SC2,
                &mut m1,
                &mut m2,
            )?;
            Ok((m1, m2))
        };
        let maps = [
            map(&rect.m1, &rect.d1, &rect.r1, &rect.p1)?,
            map(&rect.m2, &rect.d2, &rect.r2, &rect.p2)?,
        ];
        // rectified left -> left camera (R1^T) -> rig (pose inverse)
        let r1 = nalgebra::Matrix3::from_row_slice(rect.r1.data_typed::<f64>()?);
        let rt = pod.left_pose.r.transpose();
        let focal = *rect.p1.at_2d::<f64>(0, 0)?;
        Ok(PodRectifier {
            pod: pod.clone(),
            rot: rt * r1.transpose(),
            shift: -(rt * pod.left_pose.t),
            focal,
            rect,
            maps,
            grids: pixel_grids(size.width, size.height)?,
        })
    }

    /// The disparities (minimum, count as SGBM takes them: a multiple of 16) under
    /// which this pod sees every point of the box `volume` ([min, max] corners, rig
    /// frame), with 2 pixels to spare; None when the box is not in front of the pod.
    pub fn disparity_range(&self, volume: [[f64; 3]; 2]) -> Option<(i32, i32)> {
        let [lo, hi] = volume;
        let depths: Vec<f64> = (0..8)
            .map(|c| {
                let p = V3::new(
                    if c & 1 == 0 { lo[0] } else { hi[0] },
                    if c & 2 == 0 { lo[1] } else { hi[1] },
                    if c & 4 == 0 { lo[2] } else { hi[2] },
                );
                (self.rot.transpose() * (p - self.shift)).z
            })
            .collect();
        let far = depths.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        if far <= 0.0 {
            return None;
        }
        // a corner behind or beside the camera bounds nothing: the near side then is
        // as near as a tenth of the far corner
        let near = depths
            .iter()
            .cloned()
            .fold(f64::INFINITY, f64::min)
            .max(far * 0.1);
        let fb = self.focal * self.pod.baseline();
        let min = ((fb / far).floor() as i32 - 2).max(0);
        let count = ((fb / near + 2.0 - min as f64) / 16.0).ceil() as i32 * 16;
        Some((min, count.clamp(16, 1024)))
    }

    /// The rectified left image's window (x, y, width, height) over which this pod can
    /// see the box `volume` at disparities from `min` to `min + count`: the box's
    /// corners projected, with a margin, widened on the left by the disparities (the
    /// right image's part a match there reaches). None when the box does not lie wholly
    /// in front of the camera, or the window is most of the image.
    pub fn volume_window(
        &self,
        volume: [[f64; 3]; 2],
        min: i32,
        count: i32,
    ) -> Option<(i32, i32, i32, i32)> {
        let (w, h) = (self.pod.left.width as f64, self.pod.left.height as f64);
        let cx = *self.rect.p1.at_2d::<f64>(0, 2).ok()?;
        let cy = *self.rect.p1.at_2d::<f64>(1, 2).ok()?;
        let [lo, hi] = volume;
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for c in 0..8 {
            let p = V3::new(
                if c & 1 == 0 { lo[0] } else { hi[0] },
                if c & 2 == 0 { lo[1] } else { hi[1] },
                if c & 4 == 0 { lo[2] } else { hi[2] },
            );
            let q = self.rot.transpose() * (p - self.shift);
            if q.z <= 1e-9 {
                return None;
            }
            let (u, v) = (self.focal * q.x / q.z + cx, self.focal * q.y / q.z + cy);
            (x0, y0, x1, y1) = (x0.min(u), y0.min(v), x1.max(u), y1.max(v));
        }
        let margin = VOLUME_WINDOW_MARGIN;
        let left = (x0 - margin - (min + count) as f64).floor().max(0.0);
        let top = (y0 - margin).floor().max(0.0);
        let right = (x1 + margin).ceil().min(w);
        let bottom = (y1 + margin).ceil().min(h);
        if right - left < 32.0 || bottom - top < 32.0 {
            return None;
        }
        let share = (right - left) * (bottom - top) / (w * h);
        (share < 0.9).then_some((
            left as i32,
            top as i32,
            (right - left) as i32,
            (bottom - top) as i32,
        ))
    }

    fn remap(&self, right: bool, img: &Mat) -> opencv::Result<Mat> {
        let (m1, m2) = &self.maps[right as usize];
        let mut out = Mat::default();
        imgproc::remap(
            img,
            &mut out,
            m1,
            m2,
            imgproc::INTER_LINEAR,
            core::BORDER_CONSTANT,
            core::Scalar::all(0.0),
        )?;
        Ok(out)
    }
}

/// Rectifiers keyed by a fingerprint of the pod's calibration and pose: a new
/// calibration gets new maps, an unchanged one reuses its maps.
#[derive(Default)]
pub struct RectifierCache {
    entries: HashMap<u64, PodRectifier>,
    /// how many rectifiers were built, and how many lookups found one ready
    pub built: usize,
    pub reused: usize,
}

impl RectifierCache {
    /// The pod's rectifier, and whether it was ready (built for an earlier capture).
    pub fn get(&mut self, pod: &Pod) -> Result<(&PodRectifier, bool), ReconstructError> {
        Ok(self.prepare(&[pod])?.remove(0))
    }

    /// Every pod's rectifier, those this cache lacks built at once, each with whether it
    /// was ready before.
    pub fn prepare(
        &mut self,
        pods: &[&Pod],
    ) -> Result<Vec<(&PodRectifier, bool)>, ReconstructError> {
        let keys: Vec<u64> = pods.iter().map(|p| pod_fingerprint(p)).collect();
        let ready: Vec<bool> = keys.iter().map(|k| self.entries.contains_key(k)).collect();
        let built: Vec<Result<(u64, PodRectifier), ReconstructError>> = pods
            .par_iter()
            .zip(&keys)
            .zip(&ready)
            .filter(|(_, r)| !**r)
            .map(|((p, k), _)| {
                PodRectifier::new(p)
                    .map(|r| (*k, r))
                    .map_err(|source| ReconstructError::OpenCv {
                        pod: p.id.clone(),
                        source,
                    })
            })
            .collect();
        for b in built {
            let (k, r) = b?;
            self.entries.insert(k, r);
            self.built += 1;
        }
        self.reused += ready.iter().filter(|r| **r).count();
        Ok(keys.iter().map(|k| &self.entries[k]).zip(ready).collect())
    }
}

/// A hash of the pod's id and every number of its calibration and pose (a key for this
/// process's cache, not stored anywhere).
fn pod_fingerprint(pod: &Pod) -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::hash::DefaultHasher::new();
    pod.id.hash(&mut h);
    for k in [&pod.left, &pod.right] {
        (k.width, k.height).hash(&mut h);
        for v in [k.fx, k.fy, k.cx, k.cy].iter().chain(&k.dist) {
            v.to_bits().hash(&mut h);
        }
    }
    let nums = pod
        .r
        .iter()
        .chain(pod.t.iter())
        .chain(pod.left_pose.r.iter())
        .chain(pod.left_pose.t.iter());
    for v in nums {
        v.to_bits().hash(&mut h);
    }
    h.finish()
}

/// What one pod saw: a point in the rig frame for every pixel of the rectified left
/// image where the disparity is valid (NaN elsewhere), row-major, `width` x `height`.
pub struct DepthGrid {
    pub pod: String,
    pub width: usize,
    pub height: usize,
    pub points: Vec<[f32; 3]>,
    /// the left camera's centre in the rig frame
    pub camera: V3,
    /// focal length of the rectified image, pixels
    pub focal: f64,
}

impl DepthGrid {
    fn at(&self, i: usize) -> Option<V3> {
        let p = self.points[i];
        p[0].is_finite()
            .then(|| V3::new(p[0] as f64, p[1] as f64, p[2] as f64))
    }

    /// The valid points.
    pub fn valid(&self) -> impl Iterator<Item = V3> + '_ {
        (0..self.points.len()).filter_map(|i| self.at(i))
    }

    /// Triangulates the grid every `o.step` pixels into a mesh with holes: a cell's two
    /// triangles are kept when all three corners are valid, inside `volume`, and no two
    /// differ in distance from the camera by more than `o.depth_cut` times the grid's
    /// lateral spacing there (a steeper "surface" is a jump between two surfaces, e.g. a
    /// leg in front of the body, and is cut). Triangles face the camera; components of
    /// fewer than `o.min_component` triangles (matching noise) are dropped.
    ///
    /// Out: vertices (#V, rig frame), triangles (#F), vertex normals; the pod's vertices only.
    pub fn mesh(&self, o: &GridMeshOptions, volume: Option<[[f64; 3]; 2]>) -> Mesh {
        let s = o.step.max(1);
        let (gw, gh) = ((self.width - 1) / s + 1, (self.height - 1) / s + 1);
        let mut index = vec![u32::MAX; gw * gh];
        let mut vertices = Vec::new();
        let mut dist = Vec::new();
        for gy in 0..gh {
            for gx in 0..gw {
                let Some(p) = self.at(gy * s * self.width + gx * s) else {
                    continue;
                };
                if let Some([lo, hi]) = volume
                    && !(0..3).all(|k| p[k] >= lo[k] && p[k] <= hi[k])
                {
                    continue;
                }
                index[gy * gw + gx] = vertices.len() as u32;
                dist.push((p - self.camera).norm());
                vertices.push(p);
            }
        }
        let lateral = s as f64 / self.focal;
        let mut triangles = Vec::new();
        let mut add = |t: [u32; 3]| {
            if t.contains(&u32::MAX) {
                return;
            }
            let d = t.map(|i| dist[i as usize]);
            let (lo, hi) = (d[0].min(d[1]).min(d[2]), d[0].max(d[1]).max(d[2]));
            if hi - lo > o.depth_cut * lo * lateral {
                return;
            }
            let [a, b, c] = t.map(|i| vertices[i as usize]);
            let n = (b - a).cross(&(c - a));
            triangles.push(if n.dot(&(self.camera - a)) >= 0.0 {
                t
            } else {
                [t[0], t[2], t[1]]
            });
        };
        for gy in 0..gh.saturating_sub(1) {
            for gx in 0..gw.saturating_sub(1) {
                let at = |x: usize, y: usize| index[y * gw + x];
                let (a, b, c, d) = (
                    at(gx, gy),
                    at(gx + 1, gy),
                    at(gx, gy + 1),
                    at(gx + 1, gy + 1),
                );
                add([a, c, b]);
                add([b, c, d]);
            }
        }
        let (labels, count) = topology::components(vertices.len(), &triangles);
        let mut size = vec![0usize; count];
        for t in &triangles {
            size[labels[t[0] as usize] as usize] += 1;
        }
        let raw = Mesh::new(vertices, triangles);
        let (mut mesh, _) = keep_triangles(&raw, |t| {
            size[labels[raw.triangles[t][0] as usize] as usize] >= o.min_component
        });
        mesh.normals = Some(mesh.vertex_normals());
        mesh
    }
}

/// Rectifies one pod's image pair with its cached maps, matches it with every filter of
/// `o` ([`match_pair`], the same path as `disparity`), and reprojects every kept pixel
/// into the rig frame.
///
/// In: 8-bit grey left and right pixels of the calibration's size (row-major).
/// Out: the pod's depth grid; `report` gets the pod's counts and seconds per stage.
pub fn pod_grid(
    rectifier: &PodRectifier,
    left: &[u8],
    right: &[u8],
    o: &SgbmOptions,
    window: Option<(i32, i32, i32, i32)>,
    report: &mut PodReport,
) -> opencv::Result<DepthGrid> {
    let pod = &rectifier.pod;
    let (w, h) = (pod.left.width, pod.left.height);
    let t0 = Instant::now();
    let tc = Instant::now();
    let (lm, rm) = (gray_mat(left, w, h)?, gray_mat(right, w, h)?);
    let own_copies = tc.elapsed().as_secs_f64();
    let (lr, rr) = (rectifier.remap(false, &lm)?, rectifier.remap(true, &rm)?);
    report.seconds_rectify = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    // matched only over the window (rows are epipolar lines, so a band of rows is
    // matched as in the whole image); the rest has no match
    let matched = match window {
        None => match_pair(&lr, &rr, Some(&rectifier.grids), o, false)?,
        Some((x, y, ww, wh)) => {
            let rect = core::Rect::new(x, y, ww, wh);
            let crop = |m: &Mat| -> opencv::Result<Mat> { Mat::roi(m, rect)?.try_clone() };
            let mut m = match_pair(&crop(&lr)?, &crop(&rr)?, None, o, false)?;
            let mut full = vec![f32::INFINITY; (w * h) as usize];
            for (r, row) in m.values.chunks(ww as usize).enumerate() {
                let at = (y as usize + r) * w as usize + x as usize;
                full[at..at + ww as usize].copy_from_slice(row);
            }
            m.values = full;
            // (of the window's pixels only; the scan does not read it)
            m.confidence = Vec::new();
            m
        }
    };
    report.window = window.map(|(x, y, ww, wh)| [x, y, ww, wh]);
    report.seconds_disparity = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let kept = Mat::new_rows_cols_with_data(h as i32, w as i32, &matched.values)?;
    let mut xyz = Mat::default();
    calib3d::reproject_image_to_3d(&kept, &mut xyz, &rectifier.rect.q, false, core::CV_32F)?;
    let pts = xyz.data_typed::<core::Vec3f>()?;
    // from here on the work is conformd's own
    let own_start = Instant::now();
    let (rot, shift) = (rectifier.rot, rectifier.shift);
    let invalid = [f32::NAN; 3];
    let mut count = 0;
    // a match at the first disparity searched may be one whose truth lies below it
    let first = o.min_disparity as f32;
    let points: Vec<[f32; 3]> = pts
        .iter()
        .zip(&matched.values)
        .map(|(p, &d)| {
            if !(d > first) {
                return invalid;
            }
            let c = V3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if !c.iter().all(|v| v.is_finite()) || c.z <= 0.0 || c.z > 1e4 {
                return invalid;
            }
            count += 1;
            let r = rot * c + shift;
            [r.x as f32, r.y as f32, r.z as f32]
        })
        .collect();
    report.points = count;
    report.valid_disparity_share = matched.sgbm_matched as f64 / pts.len().max(1) as f64;
    report.seconds_own = own_start.elapsed().as_secs_f64() + own_copies + matched.seconds_own;
    report.seconds_reproject = t2.elapsed().as_secs_f64();
    Ok(DepthGrid {
        pod: pod.id.clone(),
        width: w as usize,
        height: h as usize,
        points,
        camera: pod.left_pose.centre(),
        focal: rectifier.focal,
    })
}

/// One pod's pixels, for [`reconstruct`].
pub struct PodImages<'a> {
    pub pod: &'a Pod,
    pub left: &'a [u8],
    pub right: &'a [u8],
}

/// Why a reconstruction failed; the caller adds camera names and files.
#[derive(Debug, thiserror::Error)]
pub enum ReconstructError {
    #[error("pod {pod}: OpenCV: {source}")]
    OpenCv { pod: String, source: opencv::Error },
    #[error("pod {pod}: the disparity map is empty (no surface matched)")]
    EmptyDisparity { pod: String },
    #[error("pod {pod}: {msg}")]
    Input { pod: String, msg: String },
}

impl ReconstructError {
    /// The pod whose images failed.
    pub fn pod(&self) -> &str {
        match self {
            ReconstructError::OpenCv { pod, .. }
            | ReconstructError::EmptyDisparity { pod }
            | ReconstructError::Input { pod, .. } => pod,
        }
    }
}

/// One pod's depth grid and its report.
fn pod_scan(
    p: &PodImages,
    rectifier: &PodRectifier,
    o: &ReconstructOptions,
    maps_reused: bool,
) -> Result<(DepthGrid, PodReport), ReconstructError> {
    let id = p.pod.id.clone();
    let ocv = |source| ReconstructError::OpenCv {
        pod: id.clone(),
        source,
    };
    let mut pr = PodReport {
        pod: id.clone(),
        maps_reused,
        ..Default::default()
    };
    let mut sgbm = o.sgbm.clone();
    if let (true, Some(v)) = (o.auto_disparity_range, o.working_volume)
        && let Some((min, count)) = rectifier.disparity_range(v)
    {
        (sgbm.min_disparity, sgbm.num_disparities) = (min, count);
    }
    pr.disparities = [
        sgbm.min_disparity,
        sgbm.min_disparity + sgbm.num_disparities,
    ];
    let window = o
        .working_volume
        .filter(|_| o.volume_window)
        .and_then(|v| rectifier.volume_window(v, sgbm.min_disparity, sgbm.num_disparities));
    let grid = pod_grid(rectifier, p.left, p.right, &sgbm, window, &mut pr).map_err(ocv)?;
    if pr.points == 0 {
        return Err(ReconstructError::EmptyDisparity { pod: id });
    }
    Ok((grid, pr))
}

/// A capture's pods to one scan in the rig frame: a point cloud with normals ([`fuse`]),
/// or (`as_mesh`) every pod's triangulated depth grid in one mesh with holes
/// ([`fuse_meshes`]). Each pod's rectification comes from `cache`; with a working volume
/// and `o.auto_disparity_range`, each pod searches only the volume's disparities.
pub fn reconstruct(
    pods: &[PodImages],
    cache: &mut RectifierCache,
    o: &ReconstructOptions,
    as_mesh: bool,
    report: &mut ReconstructReport,
) -> Result<Mesh, ReconstructError> {
    let t = Instant::now();
    for p in pods {
        let n = (p.pod.left.width * p.pod.left.height) as usize;
        if p.left.len() != n || p.right.len() != n {
            return Err(ReconstructError::Input {
                pod: p.pod.id.clone(),
                msg: format!(
                    "images of {} and {} pixels, the calibration is for {}x{}",
                    p.left.len(),
                    p.right.len(),
                    p.pod.left.width,
                    p.pod.left.height
                ),
            });
        }
    }
    // every pod's rectifier first (the cache is the pods' only shared state), then the
    // pods matched at once: OpenCV's matcher leaves cores idle between its passes
    let rectifiers = cache.prepare(&pods.iter().map(|p| p.pod).collect::<Vec<_>>())?;
    let matched: Vec<Result<(DepthGrid, PodReport), ReconstructError>> = pods
        .par_iter()
        .zip(rectifiers)
        .map(|(p, (rectifier, maps_reused))| pod_scan(p, rectifier, o, maps_reused))
        .collect();
    let mut grids = Vec::new();
    for m in matched {
        let (grid, pr) = m?;
        report.pods.push(pr);
        grids.push(grid);
    }
    let scan = if as_mesh {
        fuse_meshes(&grids, o, report)
    } else {
        let points = grids
            .iter()
            .flat_map(|g| g.valid().map(move |p| (p, g.camera)))
            .collect();
        fuse(points, o, report)
    };
    report.seconds_total = t.elapsed().as_secs_f64();
    Ok(scan)
}

/// Every pod's depth grid triangulated ([`DepthGrid::mesh`]) and gathered into one mesh.
pub fn fuse_meshes(
    grids: &[DepthGrid],
    o: &ReconstructOptions,
    report: &mut ReconstructReport,
) -> Mesh {
    let t = Instant::now();
    let mut out = Mesh::default();
    let mut normals = Vec::new();
    for g in grids {
        let m = g.mesh(&o.mesh, o.working_volume);
        let base = out.vertices.len() as u32;
        out.vertices.extend(&m.vertices);
        normals.extend(m.normals.unwrap_or_default());
        out.triangles
            .extend(m.triangles.iter().map(|t| t.map(|i| i + base)));
    }
    out.normals = Some(normals);
    report.fused_points = out.vertices.len();
    report.triangles = out.triangles.len();
    report.seconds_fuse = t.elapsed().as_secs_f64();
    out
}

/// Points a fused scan's normal is fitted to (the point itself among them).
const NORMAL_NEIGHBOURS: usize = 12;

/// Fuses pods' points into one scan with normals.
pub fn fuse(points: Vec<(V3, V3)>, o: &ReconstructOptions, report: &mut ReconstructReport) -> Mesh {
    let t = Instant::now();
    report.fused_points = points.len();
    let mut pts: Vec<(V3, V3)> = match o.working_volume {
        Some([lo, hi]) => points
            .into_iter()
            .filter(|(p, _)| (0..3).all(|k| p[k] >= lo[k] && p[k] <= hi[k]))
            .collect(),
        None => points,
    };
    report.after_crop = pts.len();
    if o.voxel > 0.0 {
        pts = voxel_average(&pts, o.voxel);
    }
    report.after_voxel = pts.len();
    // each kept point's nearest neighbours (itself first, indices after the removal)
    // from the outlier search, where none of them was removed: its normal needs no
    // search of its own
    let mut near: Vec<Option<Vec<u32>>> = Vec::new();
    if o.outlier_k > 0 && pts.len() > o.outlier_k + 1 {
        (pts, near) = remove_outliers(pts, o);
    }
    report.after_outliers = pts.len();
    let mut mesh = Mesh::new(pts.iter().map(|(p, _)| *p).collect(), vec![]);
    mesh.normals = fused_normals(&pts, &mesh.vertices, &near);
    report.seconds_fuse = t.elapsed().as_secs_f64();
    mesh
}

/// Each voxel's points averaged (position and camera), voxels in key order: the points
/// sorted by their voxel (stably, so each voxel sums in the points' order), then each
/// run summed.
fn voxel_average(pts: &[(V3, V3)], voxel: f64) -> Vec<(V3, V3)> {
    let mut keyed: Vec<([i64; 3], usize)> = pts
        .par_iter()
        .enumerate()
        .map(|(i, (p, _))| {
            let key = [
                (p.x / voxel).floor() as i64,
                (p.y / voxel).floor() as i64,
                (p.z / voxel).floor() as i64,
            ];
            (key, i)
        })
        .collect();
    keyed.par_sort_by_key(|(k, _)| *k);
    keyed
        .chunk_by(|a, b| a.0 == b.0)
        .map(|run| {
            let (p, c) = run
                .iter()
                .fold((V3::zeros(), V3::zeros()), |(p, c), &(_, i)| {
                    (p + pts[i].0, c + pts[i].1)
                });
            (p / run.len() as f64, c / run.len() as f64)
        })
        .collect()
}

/// Points whose mean distance to their `outlier_k` nearest is more than `outlier_sigma`
/// standard deviations above the mean removed. Also, per kept point, its nearest
/// neighbours (itself first, indices after the removal) where none of them was
/// removed: its normal then needs no search of its own.
#[allow(clippy::type_complexity)]
fn remove_outliers(
    pts: Vec<(V3, V3)>,
    o: &ReconstructOptions,
) -> (Vec<(V3, V3)>, Vec<Option<Vec<u32>>>) {
    let arr: Vec<[f64; 3]> = pts.iter().map(|(p, _)| [p.x, p.y, p.z]).collect();
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
    let k = NonZero::new((o.outlier_k + 1).max(NORMAL_NEIGHBOURS)).unwrap();
    let found: Vec<(f64, Vec<u32>)> = arr
        .par_iter()
        .map(|q| {
            let nb = tree.nearest_n::<SquaredEuclidean>(q, k);
            let mean = nb
                .iter()
                .skip(1)
                .take(o.outlier_k)
                .map(|m| m.distance.sqrt())
                .sum::<f64>()
                / o.outlier_k as f64;
            let ids = nb
                .iter()
                .take(NORMAL_NEIGHBOURS)
                .map(|m| m.item as u32)
                .collect();
            (mean, ids)
        })
        .collect();
    let n = found.len() as f64;
    let mu = found.iter().map(|f| f.0).sum::<f64>() / n;
    let sd = (found.iter().map(|f| (f.0 - mu).powi(2)).sum::<f64>() / n).sqrt();
    let keep: Vec<bool> = found
        .iter()
        .map(|f| f.0 <= mu + o.outlier_sigma * sd)
        .collect();
    let mut renumber = vec![u32::MAX; keep.len()];
    let mut next = 0;
    for (i, &k) in keep.iter().enumerate() {
        if k {
            renumber[i] = next;
            next += 1;
        }
    }
    let near = found
        .into_iter()
        .zip(&keep)
        .filter(|(_, k)| **k)
        .map(|((_, ids), _)| {
            let ids: Vec<u32> = ids.iter().map(|&j| renumber[j as usize]).collect();
            (ids.len() == NORMAL_NEIGHBOURS && !ids.contains(&u32::MAX)).then_some(ids)
        })
        .collect();
    let pts = pts
        .into_iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(p, _)| p)
        .collect();
    (pts, near)
}

/// Normals from 12 neighbours (those in `near`, else searched), turned towards the
/// camera that saw the point; `None` for too few points.
fn fused_normals(pts: &[(V3, V3)], vertices: &[V3], near: &[Option<Vec<u32>>]) -> Option<Vec<V3>> {
    let arr: Vec<[f64; 3]> = pts.iter().map(|(p, _)| [p.x, p.y, p.z]).collect();
    if arr.len() <= NORMAL_NEIGHBOURS {
        return None;
    }
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
    let normals: Vec<V3> = pts
        .par_iter()
        .enumerate()
        .map(|(i, (p, cam))| {
            let searched;
            let nb: &[u32] = match near.get(i) {
                Some(Some(ids)) => ids,
                _ => {
                    searched = tree
                        .nearest_n::<SquaredEuclidean>(
                            &[p.x, p.y, p.z],
                            NonZero::new(NORMAL_NEIGHBOURS).unwrap(),
                        )
                        .iter()
                        .map(|m| m.item as u32)
                        .collect::<Vec<u32>>();
                    &searched
                }
            };
            let n = crate::mesh::plane_normal(nb.iter().map(|&j| vertices[j as usize]));
            if n.dot(&(cam - p)) < 0.0 { -n } else { n }
        })
        .collect();
    Some(normals)
}

impl std::fmt::Display for ReconstructReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for p in &self.pods {
            writeln!(
                f,
                "pod {}: {} points, {:.0}% valid disparity (rectify {:.2} s, disparity {:.2} s, reproject {:.2} s)",
                p.pod,
                p.points,
                p.valid_disparity_share * 100.0,
                p.seconds_rectify,
                p.seconds_disparity,
                p.seconds_reproject
            )?;
        }
        if self.triangles > 0 {
            write!(
                f,
                "mesh of {} vertices, {} triangles; {:.2} s",
                self.fused_points, self.triangles, self.seconds_total
            )
        } else {
            write!(
                f,
                "fused {} points, {} in the working volume, {} after voxels, {} after outliers; {:.2} s",
                self.fused_points,
                self.after_crop,
                self.after_voxel,
                self.after_outliers,
                self.seconds_total
            )
        }
    }
}
