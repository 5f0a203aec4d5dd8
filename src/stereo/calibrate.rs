//! Stereo calibration of one pod from chessboard image pairs with OpenCV: corners found
//! and refined to sub-pixel, each camera calibrated, then the pair (R, T); views where the
//! board is not found in both images are skipped and reported. Also a pod's pose in the
//! rig frame from one board placement that every pod sees.

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

impl std::fmt::Display for CalibrationReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "RMS reprojection error {:.3} px over {} of {} views; baseline {:.4}",
            self.rms,
            self.used.len(),
            self.views,
            self.baseline
        )?;
        for (v, e) in self.used.iter().zip(&self.per_view_left) {
            write!(f, "\n  view {v:>2}: {e:.3} px")?;
        }
        if !self.skipped.is_empty() {
            write!(
                f,
                "\n  skipped (board not found in both images): {:?}",
                self.skipped
            )?;
        }
        Ok(())
    }
}

/// Fewest pixels a square spans in the searched copy for OpenCV to find the corners.
const MIN_SQUARE_PIXELS: u32 = 4;

/// What calibrating, reading or writing a pod's calibration refused.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    /// the chessboard asked for cannot be found in these images (its size, its square,
    /// its symmetry)
    #[error("{0}")]
    Board(String),
    #[error(
        "the board ({cols}x{rows} inner corners) was found in only {found} of {views} views; at least 4 are needed"
    )]
    TooFewViews {
        cols: u32,
        rows: u32,
        found: usize,
        views: usize,
    },
    /// a calibration file that is not one: its shape, a missing or malformed matrix, a
    /// value that cannot describe a camera
    #[error("{path}: {msg}")]
    File { path: String, msg: String },
    #[error("{0}")]
    Read(#[from] crate::files::FileError),
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// Refuses a board that cannot be seen in a `width` x `height` image (fewer than
/// [`MIN_SQUARE_PIXELS`] per square in the searched copy) or a square size that is not a
/// positive length, before OpenCV is asked: a huge board would have it allocate the
/// board's corners until memory runs out, and its exceptions then cannot be caught.
fn check_board(
    cols: u32,
    rows: u32,
    square: f64,
    width: u32,
    height: u32,
) -> Result<(), CalibrationError> {
    if !(square.is_finite() && square > 0.0) {
        return Err(CalibrationError::Board(format!(
            "the chessboard's square size must be a positive length in metres, got {square}"
        )));
    }
    let scale = (width as f64 / 640.0).max(1.0);
    let (w, h) = (
        (width as f64 / scale) as u64,
        (height as f64 / scale) as u64,
    );
    let fits =
        |corners: u32, pixels: u64| (corners as u64 + 1) * MIN_SQUARE_PIXELS as u64 <= pixels;
    if cols < 3 || rows < 3 || !fits(cols, w) || !fits(rows, h) {
        return Err(CalibrationError::Board(format!(
            "a {cols}x{rows} board (inner corners) cannot be found in {width}x{height} images: \
             it needs 3 or more corners each way and at least {MIN_SQUARE_PIXELS} pixels per \
             square at {w}x{h}, where the corners are searched"
        )));
    }
    Ok(())
}

fn corners(img: &Mat, cols: u32, rows: u32) -> opencv::Result<Option<Vector<Point2f>>> {
    // search a copy at most 640 pixels wide (the search's time grows with the pixels, and
    // on an image without a board it tries everything), then refine at full size
    let width = img.cols().max(1);
    let scale = (width as f64 / 640.0).max(1.0);
    let small = if scale > 1.0 {
        let mut m = Mat::default();
        imgproc::resize(
            img,
            &mut m,
            Size::new(
                (img.cols() as f64 / scale).round() as i32,
                (img.rows() as f64 / scale).round() as i32,
            ),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )?;
        Some(m)
    } else {
        None
    };
    let mut c = Vector::<Point2f>::new();
    let found = calib3d::find_chessboard_corners(
        small.as_ref().unwrap_or(img),
        Size::new(cols as i32, rows as i32),
        &mut c,
        // the fast check gives up early on an image without a board
        calib3d::CALIB_CB_ADAPTIVE_THRESH
            | calib3d::CALIB_CB_NORMALIZE_IMAGE
            | calib3d::CALIB_CB_FAST_CHECK,
    )?;
    if !found {
        return Ok(None);
    }
    if scale > 1.0 {
        let up: Vector<Point2f> = c
            .iter()
            .map(|p| {
                // pixel centres: x_full = (x_small + 0.5) * scale - 0.5
                Point2f::new(
                    ((p.x as f64 + 0.5) * scale - 0.5) as f32,
                    ((p.y as f64 + 0.5) * scale - 0.5) as f32,
                )
            })
            .collect();
        c = up;
        let crit = TermCriteria::new(core::TermCriteria_COUNT + core::TermCriteria_EPS, 50, 1e-4)?;
        let w = (3.0 * scale).ceil() as i32 + 4;
        imgproc::corner_sub_pix(img, &mut c, Size::new(w, w), Size::new(-1, -1), crit)?;
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
) -> Result<(Pod, CalibrationReport), CalibrationError> {
    check_board(cols, rows, square, width, height)?;
    let run = || -> opencv::Result<Result<(Pod, CalibrationReport), CalibrationError>> {
        let object = board_points(cols, rows, square);
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
            return Ok(Err(CalibrationError::TooFewViews {
                cols,
                rows,
                found: used.len(),
                views: pairs.len(),
            }));
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
        let per_view_left = reprojection_errors(&obj, &left, (&rv, &tv), (&m1, &d1))?;
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
    run()?
}

/// Each view's RMS reprojection error (pixels) of one camera: its board points `obj`
/// projected with the view's pose (`rv`, `tv`) and the camera (`m`, `d`), against the
/// corners seen.
fn reprojection_errors(
    obj: &Vector<Vector<Point3f>>,
    seen_corners: &Vector<Vector<Point2f>>,
    (rv, tv): (&Vector<Mat>, &Vector<Mat>),
    (m1, d1): (&Mat, &Mat),
) -> opencv::Result<Vec<f64>> {
    let mut errors = Vec::new();
    for v in 0..obj.len() {
        let mut proj = Vector::<Point2f>::new();
        calib3d::project_points_def(&obj.get(v)?, &rv.get(v)?, &tv.get(v)?, m1, d1, &mut proj)?;
        let seen = seen_corners.get(v)?;
        let e: f64 = proj
            .iter()
            .zip(seen.iter())
            .map(|(a, b)| ((a.x - b.x) as f64).powi(2) + ((a.y - b.y) as f64).powi(2))
            .sum();
        errors.push((e / proj.len() as f64).sqrt());
    }
    Ok(errors)
}

/// The pod's calibration with everything OpenCV's stereo tools read: M1 D1 M2 D2 R T,
/// the essential and fundamental matrices E F, and the rectification R1 R2 P1 P2 Q.
pub fn full_yaml(pod: &Pod, rig: Option<&str>) -> Result<String, CalibrationError> {
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
    Ok(run()?)
}

/// What a calibration file says about where it belongs, when it says it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct CalibrationOrigin {
    pub rig: Option<String>,
    pub pod: Option<String>,
    /// image width and height the calibration was made for
    pub image: Option<(u32, u32)>,
}

/// An OpenCV error about a file in an operator's words: its source path, line and
/// assertion text left out, what it says of the file kept (`line 3: Missing , between
/// the elements`; a matrix whose data does not fill its rows and columns named so).
pub fn cv_words(e: &opencv::Error) -> String {
    let m = e.message.trim();
    if m.contains("nelems == m.total()*m.channels()") {
        return "a matrix's data does not hold rows x cols values".into();
    }
    // "OpenCV(4.6.0) path:line: error: (-212:Parsing error) parseValue in function
    // '(3): Missing , between the elements'"
    let detail = m.split_once("error: (").map_or(m, |(_, rest)| rest);
    let (kind, rest) = detail.split_once(')').map_or(("", detail), |(k, r)| {
        (k.split_once(':').map_or(k, |x| x.1), r.trim())
    });
    let quoted = rest
        .rsplit_once("in function '")
        .map(|(_, q)| q.trim_end_matches('\''));
    match quoted {
        Some(q) if q.starts_with('(') => {
            let (line, what) = q[1..].split_once("):").unwrap_or(("?", q));
            format!("{} at line {line}:{what}", kind.to_lowercase())
        }
        _ => format!(
            "{} ({})",
            kind.to_lowercase(),
            rest.split(" in function").next().unwrap_or(rest)
        ),
    }
}

/// Deepest nesting of a calibration file (brackets, or block indentation in steps of
/// two): a calibration nests two levels; OpenCV's parser recurses once per level and a
/// file of 100,000 brackets overflows its stack.
const MAX_YAML_DEPTH: usize = 32;

/// Why a text is not given to OpenCV's YAML parser.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct YamlShape(String);

/// Refuses what OpenCV's YAML parser should not be given: NUL bytes (its strings end
/// there) and nesting deeper than [`MAX_YAML_DEPTH`], in brackets, indentation or a run
/// of `- ` on one line. Quoted text and comments are not counted.
pub fn check_yaml_shape(text: &str) -> Result<(), YamlShape> {
    if text.contains('\0') {
        return Err(YamlShape("holds a NUL byte: not a calibration file".into()));
    }
    let mut depth = 0usize;
    for (n, line) in text.lines().enumerate() {
        let deep = |what: &str| {
            Err(YamlShape(format!(
                "line {}: {what} nests deeper than {MAX_YAML_DEPTH} levels; a calibration file nests two",
                n + 1
            )))
        };
        let body = line.trim_start_matches(' ');
        if (line.len() - body.len()) / 2 > MAX_YAML_DEPTH {
            return deep("indentation");
        }
        let dashes = body
            .split_inclusive(' ')
            .take_while(|w| w.trim_end() == "-")
            .count();
        if dashes > MAX_YAML_DEPTH {
            return deep("a run of '- '");
        }
        let mut quote = None;
        for c in body.chars() {
            match (quote, c) {
                (None, '#') => break,
                (None, '"' | '\'') => quote = Some(c),
                (Some(q), c) if c == q => quote = None,
                (None, '[' | '{') => {
                    depth += 1;
                    if depth > MAX_YAML_DEPTH {
                        return deep("a bracket");
                    }
                }
                (None, ']' | '}') => depth = depth.saturating_sub(1),
                _ => {}
            }
        }
    }
    Ok(())
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
) -> Result<(Pod, CalibrationOrigin), CalibrationError> {
    let name = path.display().to_string();
    // read once, checked, and parsed from memory: the file OpenCV parses is the one
    // checked, and a shape its recursive parser cannot take never reaches it
    let text = crate::files::read_text_limited(path, 1 << 20)?;
    let refused = |msg: String| CalibrationError::File {
        path: name.clone(),
        msg,
    };
    check_yaml_shape(&text).map_err(|e| refused(e.to_string()))?;
    let run = || -> opencv::Result<Result<(Pod, CalibrationOrigin), CalibrationError>> {
        let fs = core::FileStorage::new(
            &text,
            core::FileStorage_Mode::READ as i32 | core::FileStorage_Mode::MEMORY as i32,
            "",
        )?;
        if !fs.is_opened()? {
            return Ok(Err(refused(
                "cannot be opened as an OpenCV calibration file".into(),
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
                return Ok(Err(refused(format!("no {key} matrix"))));
            }
            let mut f = Mat::default();
            m.convert_to(&mut f, core::CV_64F, 1.0, 0.0)?;
            mats.push(f);
        }
        let sizes = [(3, 3), (1, 5), (3, 3), (1, 5), (3, 3), (3, 1)];
        for (k, (m, (r, c))) in mats.iter().zip(sizes).enumerate() {
            if m.total() != r * c {
                return Ok(Err(refused(format!(
                    "{} has {} values, expected {}",
                    ["M1", "D1", "M2", "D2", "R", "T"][k],
                    m.total(),
                    r * c
                ))));
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
        if let Err(why) = check_pod(&pod) {
            return Ok(Err(refused(why.0)));
        }
        Ok(Ok((pod, origin)))
    };
    run().map_err(|e| {
        refused(format!(
            "not a calibration OpenCV can read: {}",
            cv_words(&e)
        ))
    })?
}

/// What makes a calibration unable to describe two cameras.
struct PodProblem(String);

/// A calibration that cannot describe two cameras is refused where it is read, naming
/// the value: otherwise a zero focal length or a broken rotation shows up much later as
/// "the disparity map is empty" and is blamed on the images.
fn check_pod(pod: &Pod) -> Result<(), PodProblem> {
    for (side, k) in [("M1 (left)", &pod.left), ("M2 (right)", &pod.right)] {
        let values = [k.fx, k.fy, k.cx, k.cy];
        if !values.iter().chain(&k.dist).all(|v| v.is_finite()) {
            return Err(PodProblem(format!(
                "{side} or its distortion holds a value that is not a number"
            )));
        }
        if !(k.fx > 0.0 && k.fy > 0.0) {
            return Err(PodProblem(format!(
                "{side}: the focal length must be positive, got fx {} fy {}",
                k.fx, k.fy
            )));
        }
        if !(0.0..=k.width as f64).contains(&k.cx) || !(0.0..=k.height as f64).contains(&k.cy) {
            return Err(PodProblem(format!(
                "{side}: the principal point ({}, {}) lies outside the {} x {} image",
                k.cx, k.cy, k.width, k.height
            )));
        }
    }
    if !pod.r.iter().chain(pod.t.iter()).all(|v| v.is_finite()) {
        return Err(PodProblem(
            "R or T holds a value that is not a number".into(),
        ));
    }
    let ortho = (pod.r.transpose() * pod.r - nalgebra::Matrix3::identity()).norm();
    if ortho > 1e-3 || pod.r.determinant() < 0.0 {
        return Err(PodProblem(format!(
            "R is not a rotation (|R^T R - I| = {ortho:.2e}, det {:.3})",
            pod.r.determinant()
        )));
    }
    if !(pod.t.norm() > 0.0) {
        return Err(PodProblem(
            "T is zero: the two cameras of a pod need a baseline".into(),
        ));
    }
    Ok(())
}

/// Where one camera sees a flat chessboard ([`board_pose`]).
#[derive(Debug, Clone, Copy)]
pub struct BoardView {
    /// board frame to camera: `x_cam = R x_board + t`
    pub pose: Pose,
    /// RMS reprojection error of the corners, pixels
    pub rms: f64,
    /// OpenCV's corner order was read another way round to match the board
    pub reordered: bool,
}

/// The board's inner corners in its own frame, in OpenCV's order (rows of `cols`):
/// `(i * square, j * square, 0)` for j in 1..=rows, i in 1..=cols. The board frame's
/// origin is the outer corner of the dark square before the first inner corner, x runs
/// along the `cols` corners, and z points into the board (away from a camera that sees
/// its printed face), as in OpenCV.
fn board_points(cols: u32, rows: u32, square: f64) -> Vector<Point3f> {
    (1..=rows)
        .flat_map(|j| {
            (1..=cols).map(move |i| {
                Point3f::new((i as f64 * square) as f32, (j as f64 * square) as f32, 0.0)
            })
        })
        .collect()
}

/// The pose of a flat chessboard seen by one camera of intrinsics `k` in an 8-bit grey
/// image (`k.width` x `k.height`): OpenCV's corners refined to sub-pixel, then
/// `solvePnP`. Seen from its far end, a board comes back with its corners listed from the
/// other end; the colouring (the origin square is dark) tells, so the board needs one odd
/// and one even side (`cols + rows` odd). `Ok(None)`: the board is not in the image, or
/// no reading of its corners matches its colouring.
pub fn board_pose(
    k: &Intrinsics,
    pixels: &[u8],
    cols: u32,
    rows: u32,
    square: f64,
) -> Result<Option<BoardView>, CalibrationError> {
    if (cols + rows).is_multiple_of(2) {
        return Err(CalibrationError::Board(format!(
            "a {cols}x{rows} board looks the same from both ends; placement needs one odd and one even count of inner corners (e.g. 9x6)"
        )));
    }
    check_board(cols, rows, square, k.width, k.height)?;
    let run = || -> opencv::Result<Option<BoardView>> {
        let img = gray_mat(pixels, k.width, k.height)?;
        let Some(found) = corners(&img, cols, rows)? else {
            return Ok(None);
        };
        let object = board_points(cols, rows, square);
        let m = Mat::from_slice_2d(&[[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])?;
        let d = Mat::from_slice(&k.dist)?.try_clone()?;
        let solve = |img_pts: &Vector<Point2f>| -> opencv::Result<(Mat, Mat, f64)> {
            let (mut rv, mut tv) = (Mat::default(), Mat::default());
            calib3d::solve_pnp(
                &object,
                img_pts,
                &m,
                &d,
                &mut rv,
                &mut tv,
                false,
                calib3d::SOLVEPNP_ITERATIVE,
            )?;
            let mut proj = Vector::<Point2f>::new();
            calib3d::project_points_def(&object, &rv, &tv, &m, &d, &mut proj)?;
            let e: f64 = proj
                .iter()
                .zip(img_pts.iter())
                .map(|(a, b)| ((a.x - b.x) as f64).powi(2) + ((a.y - b.y) as f64).powi(2))
                .sum();
            Ok((rv, tv, (e / proj.len() as f64).sqrt()))
        };
        // mean grey of the squares that should be dark, and of those that should be light
        let shades = |rv: &Mat, tv: &Mat| -> opencv::Result<(f64, f64)> {
            let centres: Vector<Point3f> = (0..=rows)
                .flat_map(|b| {
                    (0..=cols).map(move |a| {
                        Point3f::new(
                            ((a as f64 + 0.5) * square) as f32,
                            ((b as f64 + 0.5) * square) as f32,
                            0.0,
                        )
                    })
                })
                .collect();
            let mut proj = Vector::<Point2f>::new();
            calib3d::project_points_def(&centres, rv, tv, &m, &d, &mut proj)?;
            let (mut sum, mut n) = ([0.0; 2], [0usize; 2]);
            for (idx, p) in proj.iter().enumerate() {
                let (a, b) = (idx as u32 % (cols + 1), idx as u32 / (cols + 1));
                let (x, y) = (p.x.round() as i64, p.y.round() as i64);
                if x < 0 || y < 0 || x >= k.width as i64 || y >= k.height as i64 {
                    continue;
                }
                let parity = ((a + b) % 2) as usize;
                sum[parity] += pixels[y as usize * k.width as usize + x as usize] as f64;
                n[parity] += 1;
            }
            Ok((sum[0] / n[0].max(1) as f64, sum[1] / n[1].max(1) as f64))
        };
        // OpenCV lists the corners row by row, but which end and which side it starts
        // from follows the image; of the four readings of the grid, the board is the one
        // seen from its printed face (z away from the camera) with dark squares where
        // they belong
        let (c, r) = (cols as usize, rows as usize);
        let reading = |flip_rows: bool, flip_cols: bool| -> Vector<Point2f> {
            (0..r)
                .flat_map(|j| (0..c).map(move |i| (j, i)))
                .map(|(j, i)| {
                    let jj = if flip_rows { r - 1 - j } else { j };
                    let ii = if flip_cols { c - 1 - i } else { i };
                    found.get(jj * c + ii).expect("in the grid")
                })
                .collect()
        };
        let mut best: Option<BoardView> = None;
        for (flip_rows, flip_cols) in [(false, false), (true, true), (true, false), (false, true)] {
            let (rv, tv, rms) = solve(&reading(flip_rows, flip_cols))?;
            let mut rm = Mat::default();
            calib3d::rodrigues_def(&rv, &mut rm)?;
            let rot = nalgebra::Matrix3::from_row_slice(rm.data_typed::<f64>()?);
            let t = tv.data_typed::<f64>()?;
            let t = V3::new(t[0], t[1], t[2]);
            let (dark, light) = shades(&rv, &tv)?;
            if rot.column(2).dot(&t) <= 0.0 || dark >= light {
                continue;
            }
            if best.is_none_or(|b| rms < b.rms) {
                best = Some(BoardView {
                    pose: Pose { r: rot, t },
                    rms,
                    reordered: flip_rows || flip_cols,
                });
            }
        }
        Ok(best)
    };
    Ok(run()?)
}

/// Where a placement board lies in the rig: face up, its long side (the `cols` corners)
/// turned `yaw` degrees from the rig's +x towards +y, its origin at `origin` (rig frame,
/// m); the board frame of [`board_pose`] then has z pointing down into the floor.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BoardPlacement {
    pub origin: [f64; 3],
    #[serde(default)]
    pub yaw: f64,
}

impl BoardPlacement {
    /// The board's pose: `x_board = B (x_rig - origin)`.
    pub fn board_from_rig(&self) -> Pose {
        let turn = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), self.yaw.to_radians());
        // rows: the board's axes in the rig frame (x along the long side, y across it
        // away from the origin, z down)
        let b =
            nalgebra::Matrix3::from_diagonal(&V3::new(1.0, -1.0, -1.0)) * turn.matrix().transpose();
        let origin = V3::from(self.origin);
        Pose {
            r: b,
            t: -(b * origin),
        }
    }
}
