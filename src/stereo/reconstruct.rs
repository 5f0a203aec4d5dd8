//! A capture set to a scan: per pod, rectify (maps from the calibration), disparity,
//! reproject into the left camera, then into the rig frame; fuse all pods, crop to the
//! working volume, voxel-downsample, remove outliers, and estimate normals turned towards
//! the camera that saw each point.

use super::calib::Pod;
use super::disparity::{SgbmOptions, disparity_mats, gray_mat, to_pixels};
use crate::mesh::{Mesh, V3};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use opencv::calib3d;
use opencv::core::{self, Mat, Rect, Size};
use opencv::imgproc;
use opencv::prelude::*;
use std::collections::HashMap;
use std::num::NonZero;
use std::time::Instant;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReconstructOptions {
    pub sgbm: SgbmOptions,
    /// voxel edge for downsampling (m); 0 keeps every point
    pub voxel: f64,
    /// outlier removal: neighbours considered, and how many standard deviations above
    /// the mean neighbour distance a point may be
    pub outlier_k: usize,
    pub outlier_sigma: f64,
    /// [min, max] corners of the rig's working volume (m)
    pub working_volume: Option<[[f64; 3]; 2]>,
}

impl Default for ReconstructOptions {
    fn default() -> Self {
        ReconstructOptions {
            sgbm: SgbmOptions::default(),
            voxel: 0.004,
            outlier_k: 8,
            outlier_sigma: 2.0,
            working_volume: None,
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
    pub seconds_fuse: f64,
    pub seconds_total: f64,
}

#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct PodReport {
    pub pod: String,
    pub points: usize,
    pub valid_disparity_share: f64,
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

/// Points (rig frame) and their viewing camera centre, from one pod's image pair.
pub fn pod_points(
    pod: &Pod,
    left: &[u8],
    right: &[u8],
    o: &SgbmOptions,
    report: &mut PodReport,
) -> opencv::Result<Vec<(V3, V3)>> {
    let (w, h) = (pod.left.width, pod.left.height);
    let size = Size::new(w as i32, h as i32);
    let t0 = Instant::now();
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
    } = rectification(pod)?;
    let tc = Instant::now();
    let (lm, rm) = (gray_mat(left, w, h)?, gray_mat(right, w, h)?);
    let own_copies = tc.elapsed().as_secs_f64();
    let rectify = |m: &Mat, d: &Mat, rr: &Mat, pp: &Mat, img: &Mat| -> opencv::Result<Mat> {
        let (mut map1, mut map2) = (Mat::default(), Mat::default());
        calib3d::init_undistort_rectify_map(
            m,
            d,
            rr,
            pp,
            size,
            core::CV_32FC1,
            &mut map1,
            &mut map2,
        )?;
        let mut out = Mat::default();
        imgproc::remap(
            img,
            &mut out,
            &map1,
            &map2,
            imgproc::INTER_LINEAR,
            core::BORDER_CONSTANT,
            core::Scalar::all(0.0),
        )?;
        Ok(out)
    };
    let (lr, rr) = (
        rectify(&m1, &d1, &r1, &p1, &lm)?,
        rectify(&m2, &d2, &r2, &p2, &rm)?,
    );
    report.seconds_rectify = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let disp = disparity_mats(&lr, &rr, o)?;
    report.seconds_disparity = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let px = to_pixels(&disp, o.min_disparity)?;
    report.valid_disparity_share = px.valid_share();
    let mut dispf = Mat::default();
    disp.convert_to(&mut dispf, core::CV_32F, 1.0 / 16.0, 0.0)?;
    let mut xyz = Mat::default();
    calib3d::reproject_image_to_3d(&dispf, &mut xyz, &q, true, core::CV_32F)?;
    let pts = xyz.data_typed::<core::Vec3f>()?;
    // texture mask: local standard deviation of the rectified left image
    let mut lf = Mat::default();
    lr.convert_to(&mut lf, core::CV_32F, 1.0, 0.0)?;
    let mut sq = Mat::default();
    core::multiply(&lf, &lf, &mut sq, 1.0, -1)?;
    let (mut mean, mut mean_sq) = (Mat::default(), Mat::default());
    let k = Size::new(5, 5);
    imgproc::blur(
        &lf,
        &mut mean,
        k,
        core::Point::new(-1, -1),
        core::BORDER_REFLECT,
    )?;
    imgproc::blur(
        &sq,
        &mut mean_sq,
        k,
        core::Point::new(-1, -1),
        core::BORDER_REFLECT,
    )?;
    // from here on the work is conformd's own
    let own_start = Instant::now();
    let (m, m2) = (mean.data_typed::<f32>()?, mean_sq.data_typed::<f32>()?);
    let min_var = (o.min_contrast * o.min_contrast) as f32;
    // rectified left camera -> left camera -> rig frame
    let r1m = nalgebra::Matrix3::from_row_slice(r1.data_typed::<f64>()?);
    let to_cam = r1m.transpose();
    let pose = pod.left_pose;
    let rt = pose.r.transpose();
    let centre = pose.centre();
    let mut out = Vec::new();
    for (i, p) in pts.iter().enumerate() {
        if !px.values[i].is_finite()
            || px.values[i] <= o.min_disparity as f32
            || m2[i] - m[i] * m[i] < min_var
        {
            continue;
        }
        let c = V3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        if !c.iter().all(|v| v.is_finite()) || c.z <= 0.0 || c.z > 1e4 {
            continue;
        }
        let cam = to_cam * c;
        out.push((rt * (cam - pose.t), centre));
    }
    report.points = out.len();
    report.seconds_own = own_start.elapsed().as_secs_f64() + own_copies;
    report.seconds_reproject = t2.elapsed().as_secs_f64();
    Ok(out)
}

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
        let mut cells: HashMap<[i64; 3], (V3, V3, usize)> = HashMap::new();
        for (p, c) in pts {
            let key = [
                (p.x / o.voxel).floor() as i64,
                (p.y / o.voxel).floor() as i64,
                (p.z / o.voxel).floor() as i64,
            ];
            let e = cells.entry(key).or_insert((V3::zeros(), V3::zeros(), 0));
            e.0 += p;
            e.1 += c;
            e.2 += 1;
        }
        let mut v: Vec<_> = cells.into_iter().collect();
        v.sort_by_key(|(k, _)| *k);
        pts = v
            .into_iter()
            .map(|(_, (p, c, n))| (p / n as f64, c / n as f64))
            .collect();
    }
    report.after_voxel = pts.len();
    if pts.len() > o.outlier_k + 1 {
        let arr: Vec<[f64; 3]> = pts.iter().map(|(p, _)| [p.x, p.y, p.z]).collect();
        let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
        let k = NonZero::new(o.outlier_k + 1).unwrap();
        let mean_d: Vec<f64> = arr
            .iter()
            .map(|q| {
                tree.nearest_n::<SquaredEuclidean>(q, k)
                    .iter()
                    .skip(1)
                    .map(|m| m.distance.sqrt())
                    .sum::<f64>()
                    / o.outlier_k as f64
            })
            .collect();
        let mu = mean_d.iter().sum::<f64>() / mean_d.len() as f64;
        let sd =
            (mean_d.iter().map(|d| (d - mu).powi(2)).sum::<f64>() / mean_d.len() as f64).sqrt();
        let keep: Vec<bool> = mean_d
            .iter()
            .map(|d| *d <= mu + o.outlier_sigma * sd)
            .collect();
        pts = pts
            .into_iter()
            .zip(keep)
            .filter(|(_, k)| *k)
            .map(|(p, _)| p)
            .collect();
    }
    report.after_outliers = pts.len();
    // normals from 12 neighbours, turned towards the camera that saw the point
    let arr: Vec<[f64; 3]> = pts.iter().map(|(p, _)| [p.x, p.y, p.z]).collect();
    let mut mesh = Mesh::new(pts.iter().map(|(p, _)| *p).collect(), vec![]);
    if arr.len() >= 13 {
        let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
        let normals = pts
            .iter()
            .map(|(p, cam)| {
                let nb =
                    tree.nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], NonZero::new(12).unwrap());
                let c = nb
                    .iter()
                    .map(|m| mesh.vertices[m.item as usize])
                    .sum::<V3>()
                    / nb.len() as f64;
                let cov = nb.iter().fold(nalgebra::Matrix3::zeros(), |a, m| {
                    let d = mesh.vertices[m.item as usize] - c;
                    a + d * d.transpose()
                });
                let e = cov.symmetric_eigen();
                let n: V3 = e.eigenvectors.column(e.eigenvalues.imin()).into();
                if n.dot(&(cam - p)) < 0.0 { -n } else { n }
            })
            .collect();
        mesh.normals = Some(normals);
    }
    report.seconds_fuse = t.elapsed().as_secs_f64();
    mesh
}
