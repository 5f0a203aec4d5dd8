//! Stereo calibration of one pod from chessboard image pairs with OpenCV: corners found
//! and refined to sub-pixel, each camera calibrated, then the pair (R, T); views where the
//! board is not found in both images are skipped and reported.

use super::calib::{Intrinsics, Pod, Pose};
use super::disparity::gray_mat;
use crate::mesh::V3;
use opencv::calib3d;
use opencv::core::{self, Mat, Point2f, Point3f, Size, TermCriteria, Vector};
use opencv::imgproc;
use opencv::prelude::*;

/// What a calibration found.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CalibrationReport {
    pub views: usize,
    pub used: Vec<usize>,
    /// views where the board was not found in both images
    pub skipped: Vec<usize>,
    /// RMS reprojection error of the stereo calibration, pixels
    pub rms: f64,
    /// per used view: RMS reprojection error of the left camera, pixels
    pub per_view_left: Vec<f64>,
    pub baseline: f64,
}

fn corners(img: &Mat, cols: u32, rows: u32) -> opencv::Result<Option<Vector<Point2f>>> {
    let mut c = Vector::<Point2f>::new();
    let found = calib3d::find_chessboard_corners(
        img,
        Size::new(cols as i32, rows as i32),
        &mut c,
        calib3d::CALIB_CB_ADAPTIVE_THRESH | calib3d::CALIB_CB_NORMALIZE_IMAGE,
    )?;
    if !found {
        return Ok(None);
    }
    let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 50, 1e-4)?;
    imgproc::corner_sub_pix(img, &mut c, Size::new(7, 7), Size::new(-1, -1), crit)?;
    Ok(Some(c))
}

fn to_intrinsics(m: &Mat, d: &Mat, w: u32, h: u32) -> opencv::Result<Intrinsics> {
    let md = m.data_typed::<f64>()?;
    let dd = d.data_typed::<f64>()?;
    let mut dist = [0.0; 5];
    for (k, v) in dd.iter().take(5).enumerate() {
        dist[k] = *v;
    }
    Ok(Intrinsics {
        width: w,
        height: h,
        fx: md[0],
        fy: md[4],
        cx: md[2],
        cy: md[5],
        dist,
    })
}

/// Calibrates a pod from (left, right) grey image pairs of `width` x `height`.
pub fn calibrate(
    pairs: &[(Vec<u8>, Vec<u8>)],
    width: u32,
    height: u32,
    cols: u32,
    rows: u32,
    square: f64,
    id: &str,
) -> Result<(Pod, CalibrationReport), String> {
    let run = || -> opencv::Result<Result<(Pod, CalibrationReport), String>> {
        let object: Vector<Point3f> = (1..=rows)
            .flat_map(|j| {
                (1..=cols).map(move |i| {
                    Point3f::new((i as f64 * square) as f32, (j as f64 * square) as f32, 0.0)
                })
            })
            .collect();
        let (mut obj, mut left, mut right) = (
            Vector::<Vector<Point3f>>::new(),
            Vector::<Vector<Point2f>>::new(),
            Vector::<Vector<Point2f>>::new(),
        );
        let (mut used, mut skipped) = (Vec::new(), Vec::new());
        for (k, (l, r)) in pairs.iter().enumerate() {
            let (lm, rm) = (gray_mat(l, width, height)?, gray_mat(r, width, height)?);
            match (corners(&lm, cols, rows)?, corners(&rm, cols, rows)?) {
                (Some(a), Some(b)) => {
                    obj.push(object.clone());
                    left.push(a);
                    right.push(b);
                    used.push(k);
                }
                _ => skipped.push(k),
            }
        }
        if used.len() < 4 {
            return Ok(Err(format!(
                "the board ({cols}x{rows} inner corners) was found in only {} of {} views; at least 4 are needed",
                used.len(),
                pairs.len()
            )));
        }
        let size = Size::new(width as i32, height as i32);
        let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 100, 1e-9)?;
        let flags = calib3d::CALIB_FIX_K3;
        let (mut m1, mut d1, mut m2, mut d2) = (
            Mat::default(),
            Mat::default(),
            Mat::default(),
            Mat::default(),
        );
        let (mut rv, mut tv) = (Vector::<Mat>::new(), Vector::<Mat>::new());
        calib3d::calibrate_camera(
            &obj, &left, size, &mut m1, &mut d1, &mut rv, &mut tv, flags, crit,
        )?;
        // per-view errors of the left camera
        let mut per_view_left = Vec::new();
        for v in 0..obj.len() {
            let mut proj = Vector::<Point2f>::new();
            calib3d::project_points_def(
                &obj.get(v)?,
                &rv.get(v)?,
                &tv.get(v)?,
                &m1,
                &d1,
                &mut proj,
            )?;
            let seen = left.get(v)?;
            let e: f64 = proj
                .iter()
                .zip(seen.iter())
                .map(|(a, b)| ((a.x - b.x) as f64).powi(2) + ((a.y - b.y) as f64).powi(2))
                .sum();
            per_view_left.push((e / proj.len() as f64).sqrt());
        }
        let (mut rv2, mut tv2) = (Vector::<Mat>::new(), Vector::<Mat>::new());
        calib3d::calibrate_camera(
            &obj, &right, size, &mut m2, &mut d2, &mut rv2, &mut tv2, flags, crit,
        )?;
        let (mut r, mut t, mut e, mut f) = (
            Mat::default(),
            Mat::default(),
            Mat::default(),
            Mat::default(),
        );
        let rms = calib3d::stereo_calibrate(
            &obj,
            &left,
            &right,
            &mut m1,
            &mut d1,
            &mut m2,
            &mut d2,
            size,
            &mut r,
            &mut t,
            &mut e,
            &mut f,
            calib3d::CALIB_USE_INTRINSIC_GUESS | flags,
            crit,
        )?;
        let rd = r.data_typed::<f64>()?;
        let td = t.data_typed::<f64>()?;
        let pod = Pod {
            id: id.into(),
            left: to_intrinsics(&m1, &d1, width, height)?,
            right: to_intrinsics(&m2, &d2, width, height)?,
            left_pose: Pose {
                r: nalgebra::Matrix3::identity(),
                t: V3::zeros(),
            },
            r: nalgebra::Matrix3::from_row_slice(rd),
            t: V3::new(td[0], td[1], td[2]),
        };
        let report = CalibrationReport {
            views: pairs.len(),
            used,
            skipped,
            rms,
            per_view_left,
            baseline: pod.baseline(),
        };
        Ok(Ok((pod, report)))
    };
    run().map_err(|e| format!("OpenCV: {e}"))?
}

/// The pod's calibration with everything OpenCV's stereo tools read: M1 D1 M2 D2 R T,
/// the essential and fundamental matrices E F, and the rectification R1 R2 P1 P2 Q.
pub fn full_yaml(pod: &Pod, rig: Option<&str>) -> Result<String, String> {
    let run = || -> opencv::Result<String> {
        let rect = super::reconstruct::rectification(pod)?;
        let (r1, r2, p1, p2, q) = (rect.r1, rect.r2, rect.p1, rect.p2, rect.q);
        // E = [T]x R, F = M2^-T E M1^-1
        let tx = nalgebra::Matrix3::new(
            0.0, -pod.t.z, pod.t.y, pod.t.z, 0.0, -pod.t.x, -pod.t.y, pod.t.x, 0.0,
        );
        let e = tx * pod.r;
        let f = pod
            .right
            .matrix()
            .try_inverse()
            .unwrap_or_default()
            .transpose()
            * e
            * pod.left.matrix().try_inverse().unwrap_or_default();
        let mut s = pod.opencv_yaml_of(rig);
        let block = |name: &str, rows: usize, cols: usize, data: &[f64]| {
            let d: Vec<String> = data.iter().map(|v| format!("{v:.10e}")).collect();
            format!(
                "{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n",
                d.join(", ")
            )
        };
        let rows = |x: &nalgebra::Matrix3<f64>| x.transpose().iter().copied().collect::<Vec<f64>>();
        s.push_str(&block("E", 3, 3, &rows(&e)));
        s.push_str(&block("F", 3, 3, &rows(&f)));
        for (name, mat, r, c) in [
            ("R1", &r1, 3, 3),
            ("R2", &r2, 3, 3),
            ("P1", &p1, 3, 4),
            ("P2", &p2, 3, 4),
            ("Q", &q, 4, 4),
        ] {
            s.push_str(&block(name, r, c, mat.data_typed::<f64>()?));
        }
        Ok(s)
    };
    run().map_err(|e| format!("OpenCV: {e}"))
}

/// What a calibration file says about where it belongs, when it says it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CalibrationOrigin {
    pub rig: Option<String>,
    pub pod: Option<String>,
    /// image width and height the calibration was made for
    pub image: Option<(u32, u32)>,
}

/// Reads a pod's calibration (M1 D1 M2 D2 R T, as written by `calibrate` or `simulate`)
/// through OpenCV's FileStorage, with the rig, pod and image size it names; the pose in
/// the rig frame is the caller's. `width` x `height` apply when the file names no size.
pub fn read_yaml(
    path: &std::path::Path,
    id: &str,
    left_pose: Pose,
    width: u32,
    height: u32,
) -> Result<(Pod, CalibrationOrigin), String> {
    let name = path.display().to_string();
    let run = || -> opencv::Result<Result<(Pod, CalibrationOrigin), String>> {
        let fs = core::FileStorage::new(&name, core::FileStorage_Mode::READ as i32, "")?;
        if !fs.is_opened()? {
            return Ok(Err(format!(
                "{name}: cannot be opened as an OpenCV calibration file"
            )));
        }
        let text = |key: &str| -> opencv::Result<Option<String>> {
            let n = fs.get(key)?;
            Ok(if n.is_string()? {
                Some(n.string()?)
            } else {
                None
            })
        };
        let int = |key: &str| -> opencv::Result<Option<u32>> {
            let n = fs.get(key)?;
            Ok(if n.is_int()? {
                u32::try_from(n.to_i32()?).ok()
            } else {
                None
            })
        };
        let origin = CalibrationOrigin {
            rig: text("rig")?,
            pod: text("pod")?,
            image: int("image_width")?.zip(int("image_height")?),
        };
        let (width, height) = origin.image.unwrap_or((width, height));
        let mut mats = Vec::new();
        for key in ["M1", "D1", "M2", "D2", "R", "T"] {
            let m = fs.get(key)?.mat()?;
            if m.empty() {
                return Ok(Err(format!("{name}: no {key} matrix")));
            }
            let mut f = Mat::default();
            m.convert_to(&mut f, core::CV_64F, 1.0, 0.0)?;
            mats.push(f);
        }
        let sizes = [(3, 3), (1, 5), (3, 3), (1, 5), (3, 3), (3, 1)];
        for (k, (m, (r, c))) in mats.iter().zip(sizes).enumerate() {
            if m.total() != r * c {
                return Ok(Err(format!(
                    "{name}: {} has {} values, expected {}",
                    ["M1", "D1", "M2", "D2", "R", "T"][k],
                    m.total(),
                    r * c
                )));
            }
        }
        let t = mats[5].data_typed::<f64>()?;
        let pod = Pod {
            id: id.into(),
            left: to_intrinsics(&mats[0], &mats[1], width, height)?,
            right: to_intrinsics(&mats[2], &mats[3], width, height)?,
            left_pose,
            r: nalgebra::Matrix3::from_row_slice(mats[4].data_typed::<f64>()?),
            t: V3::new(t[0], t[1], t[2]),
        };
        Ok(Ok((pod, origin)))
    };
    run().map_err(|e| format!("{name}: OpenCV: {e}"))?
}
