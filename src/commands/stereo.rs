//! Stereo jobs: simulated capture sets and chessboard views, calibration, disparity,
//! reconstruction.

use super::*;
use crate::devices::capture_set::CaptureSetDir;
use crate::stereo::rig::Reconstruction;
use std::path::{Path, PathBuf};

/// Renders capture sets of a subject (a mesh file, or a generic `pig`/`body` posed with
/// `pose`) seen by the rig's cameras, written as standard capture sets under `out`, each
/// with the ground-truth mesh beside its images (`truth.ply`), and every pod's
/// calibration as OpenCV YAML under `out/calibration/`. All or nothing: when any write
/// fails (a full disk), what this call wrote is removed again.
pub fn simulate(
    rig_path: &Path,
    subject: &str,
    pose: &str,
    captures: usize,
    noise: f64,
    out: &Path,
) -> Result<Vec<PathBuf>, CommandError> {
    let out_existed = out.exists();
    let calib_existed = out.join("calibration").exists();
    let mut written: Vec<PathBuf> = Vec::new();
    let result = simulate_into(rig_path, subject, pose, captures, noise, out, &mut written);
    if result.is_err() {
        if !out_existed {
            let _ = std::fs::remove_dir_all(out);
        } else {
            for p in written.iter().rev() {
                let _ = if p.is_dir() {
                    std::fs::remove_dir_all(p)
                } else {
                    std::fs::remove_file(p)
                };
            }
            if !calib_existed {
                let _ = std::fs::remove_dir(out.join("calibration"));
            }
        }
    }
    result
}

/// Sensor noise in grey levels: 0 to 100 (beyond that an image is noise alone).
fn check_noise(noise: f64) -> Result<(), CommandError> {
    if !(0.0..=100.0).contains(&noise) {
        return Err(CommandError::Usage(format!(
            "--noise {noise}: sensor noise must be 0 to 100 grey levels"
        )));
    }
    Ok(())
}

/// [`simulate`]'s work; records each file and set folder it wrote in `written`.
fn simulate_into(
    rig_path: &Path,
    subject: &str,
    pose: &str,
    captures: usize,
    noise: f64,
    out: &Path,
    written: &mut Vec<PathBuf>,
) -> Result<Vec<PathBuf>, CommandError> {
    use crate::template as templates;
    check_noise(noise)?;
    let rig = crate::stereo::rig::RigFile::load(rig_path)?;
    let mesh = match subject.parse::<templates::Kind>() {
        Ok(kind) if !Path::new(subject).exists() => {
            let names: Vec<&str> = templates::pose_parameters(kind)
                .iter()
                .map(|p| p.0)
                .collect();
            let params = templates::parse_parameters(pose, &names, "pose")?;
            let fig = templates::build(kind, 20_000);
            templates::subject(
                &fig,
                kind,
                &std::collections::BTreeMap::new(),
                &templates::pose(kind, &params),
            )?
        }
        _ => mesh::read_mesh(Path::new(subject))?,
    };
    let io = |p: &Path, source| CommandError::Io {
        path: p.display().to_string(),
        source,
    };
    let calib = out.join("calibration");
    std::fs::create_dir_all(&calib).map_err(|e| io(&calib, e))?;
    for pod in rig.pods() {
        let file = calib.join(format!("{}.yml", pod.id));
        // a file this call replaces is the new calibration either way; only new ones go
        let new = !file.exists();
        write_atomic(&file, pod.opencv_yaml_of(Some(&rig.name)).as_bytes())?;
        if new {
            written.push(file);
        }
    }
    let mut dirs = Vec::new();
    for n in 0..captures {
        let images = crate::synth::virtual_rig::render_rig(&rig, &mesh, noise, n as u64)
            .into_iter()
            .map(|r| (r.pod, r.side, r.width, r.height, r.pixels))
            .collect();
        let truth = mesh::io::ply_bytes(&mesh, mesh::io::PlyEncoding::BinaryLittleEndian);
        let set = write_simulated_set(out, n, &rig.name, subject, images, &[("truth.ply", truth)])?;
        written.push(set.clone());
        dirs.push(set);
    }
    Ok(dirs)
}

/// One rendered camera image: pod, side, width, height, grey pixels.
type SimImage = (String, &'static str, u32, u32, Vec<u8>);

/// Writes a simulated capture set under `out` through the one capture-set writer, with
/// `extra` files (ground truth) beside the images; returns its folder.
/// A simulated set's subject as a plain name (a mesh path's file stem, other characters
/// as `-`): manifests hold plain subjects only.
fn plain_subject(subject: &str) -> String {
    let stem = Path::new(subject)
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default();
    let plain: String = stem
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '-'
            }
        })
        .take(crate::paths::MAX_NAME)
        .collect();
    let plain = plain.trim_start_matches('.').to_string();
    if plain.is_empty() {
        "subject".into()
    } else {
        plain
    }
}

fn write_simulated_set(
    out: &Path,
    n: usize,
    station: &str,
    subject: &str,
    images: Vec<SimImage>,
    extra: &[(&str, Vec<u8>)],
) -> Result<PathBuf, CommandError> {
    write_set(
        out,
        ("simulated", "sim"),
        n,
        station,
        subject,
        images,
        extra,
    )
}

/// Writes a capture set not taken by a rig (`trigger`: the manifest's trigger kind and
/// the id's tag) under `out`; see [`write_simulated_set`].
fn write_set(
    out: &Path,
    (trigger, tag): (&str, &str),
    n: usize,
    station: &str,
    subject: &str,
    images: Vec<SimImage>,
    extra: &[(&str, Vec<u8>)],
) -> Result<PathBuf, CommandError> {
    use crate::devices::capture::{CameraRecord, Manifest, TriggerRecord, utc_stamp};
    let id = format!("{}-{tag}{n:03}", utc_stamp(std::time::SystemTime::now()));
    let mut cameras = Vec::new();
    let mut files = Vec::new();
    for (pod, side, width, height, pixels) in images {
        let file = format!("{pod}-{side}.png");
        let img = image::GrayImage::from_raw(width, height, pixels).expect("sized");
        files.push((file.clone(), crate::render::png_bytes(&img)));
        cameras.push(CameraRecord {
            id: format!("{pod}-{side}"),
            pod,
            side: side.into(),
            file,
            width,
            height,
            sensor_timestamp_us: n as u64 * 1_000_000,
            sequence: n as u32,
            exposure_us: None,
        });
    }
    files.extend(
        extra
            .iter()
            .map(|(name, bytes)| (name.to_string(), bytes.clone())),
    );
    let now = utc_stamp(std::time::SystemTime::now());
    let manifest = Manifest {
        format: Manifest::FORMAT.into(),
        version: Manifest::VERSION,
        id,
        station: station.into(),
        subject: Some(plain_subject(subject)),
        started_utc: now.clone(),
        finished_utc: now,
        trigger: TriggerRecord {
            kind: trigger.into(),
            sequence: n as u32,
            box_time_us: None,
        },
        cameras,
    };
    std::fs::create_dir_all(out).map_err(|source| CommandError::Io {
        path: out.display().to_string(),
        source,
    })?;
    Ok(crate::devices::capture_set::write_capture_set(
        out, &manifest, &files,
    )?)
}

/// Renders one capture set of a chessboard lying face up on the rig's floor, its long
/// side turned `yaw` degrees from the rig's x, seen by every pod, for `calibrate
/// --placement`; where the board lies is written beside the images (`placement.toml`:
/// `board`, `square`, `origin`, `yaw`).
pub fn simulate_placement(
    rig_path: &Path,
    board: &str,
    square: f64,
    yaw: f64,
    noise: f64,
    out: &Path,
) -> Result<PathBuf, CommandError> {
    use crate::stereo::rig::RigFile;
    use crate::synth::virtual_rig::{Chessboard, placement_board, render_chessboard};
    check_noise(noise)?;
    let (cols, rows) = parse_board(board)?;
    let rig = RigFile::load(rig_path)?;
    let cb = Chessboard { cols, rows, square };
    let placement = placement_board(&rig, &cb, yaw);
    let pose = placement.board_from_rig();
    let mut images = Vec::new();
    for pod in rig.pods() {
        for (right, side) in [(false, "left"), (true, "right")] {
            let k = if right { pod.right } else { pod.left };
            let px = render_chessboard(&pod, right, &cb, &pose, noise, 5);
            images.push((pod.id.clone(), side, k.width, k.height, px));
        }
    }
    let [x, y, z] = placement.origin;
    let text = format!(
        "board = \"{cols}x{rows}\"\nsquare = {square}\norigin = [{x}, {y}, {z}]\nyaw = {yaw}\n"
    );
    write_simulated_set(
        out,
        0,
        &rig.name,
        "placement-board",
        images,
        &[("placement.toml", text.into_bytes())],
    )
}

/// One pod's pose found by `calibrate --placement`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PodPlacement {
    pub pod: String,
    /// the left camera's centre in the rig frame (m)
    pub position: [f64; 3],
    /// rows: the left camera's axes in the rig frame
    pub rotation: [[f64; 3]; 3],
    /// corner reprojection RMS of the left and right camera, pixels
    pub rms_left: f64,
    pub rms_right: f64,
    /// the left camera's pose found from the right camera's view through the pod's
    /// calibration, against the one from its own view: a check of the calibration
    pub left_right_mm: f64,
    pub left_right_deg: f64,
}

impl std::fmt::Display for PodPlacement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "pod {}: left camera at ({:.4}, {:.4}, {:.4}) m; corner RMS {:.3} / {:.3} px; left-right check {:.2} mm, {:.3} deg",
            self.pod,
            self.position[0],
            self.position[1],
            self.position[2],
            self.rms_left,
            self.rms_right,
            self.left_right_mm,
            self.left_right_deg
        )
    }
}

/// Finds every pod's pose in the rig frame from one capture set of a chessboard that
/// all pods see, and writes
/// the rig file with the measured `position` and `rotation` of every pod to `out`.
/// Lenses come from `calibration/<pod>.yml` when given, else from the rig file.
/// The board lies face up as `placement` says: its long side (the `cols` inner corners)
/// turned `yaw` degrees from the rig's x, its origin (the outer corner of the dark corner
/// square from which the long side runs along the yaw direction and the short side to its
/// right, seen from above) at `origin` (see `stereo::calibrate::board_pose`).
///
/// Example: `conformd calibrate --placement captures/<id> --rig rig.toml --calibration cal
/// --board 9x6 --square 0.08 --out rig-measured.toml`; see `tests/calibration.rs`.
pub fn calibrate_placement(
    capture: &Path,
    rig_path: &Path,
    calibration: Option<&Path>,
    board: &str,
    square: f64,
    placement: &crate::stereo::calibrate::BoardPlacement,
    out: &Path,
) -> Result<Vec<PodPlacement>, CommandError> {
    use crate::stereo::calib::Pose;
    let (cols, rows) = parse_board(board)?;
    let station = Reconstruction::load(rig_path, calibration)?;
    let set = CaptureSetDir::open(capture)?;
    let board = placement.board_from_rig();
    let mut rig = station.rig.clone();
    let mut found = Vec::new();
    for (pod, spec) in station.pods.iter().zip(&mut rig.pods) {
        let mut views = Vec::new();
        for (side, k) in [("left", &pod.left), ("right", &pod.right)] {
            let img = set.grey_image(&pod.id, side, (k.width, k.height))?;
            let cam = set.camera(&pod.id, side)?;
            let named = |what: String| CommandError::Input {
                path: capture.join(&cam.file).display().to_string(),
                msg: format!("camera {}: {what}", cam.id),
            };
            let view = crate::stereo::calibrate::board_pose(k, img.as_raw(), cols, rows, square)
                .map_err(|e| named(e.to_string()))?
                .ok_or_else(|| {
                    named(format!(
                        "the {cols}x{rows} board is not in view; every pod must see the whole board"
                    ))
                })?;
            // rig -> board -> camera
            views.push((
                Pose {
                    r: view.pose.r * board.r,
                    t: view.pose.r * board.t + view.pose.t,
                },
                view.rms,
            ));
        }
        let ((left, rms_left), (right, rms_right)) = (views[0], views[1]);
        // the left camera again, from the right one: x_left = R^T (x_right - T)
        let rt = pod.r.transpose();
        let via_right = Pose {
            r: rt * right.r,
            t: rt * (right.t - pod.t),
        };
        let angle = crate::mesh::transform::rotation_angle(
            &nalgebra::Rotation3::from_matrix_unchecked(left.r * via_right.r.transpose()),
        )
        .to_degrees();
        let rotation = [0, 1, 2].map(|i| [0, 1, 2].map(|j| left.r[(i, j)]));
        let position = left.centre();
        spec.position = [position.x, position.y, position.z];
        spec.rotation = Some(rotation);
        found.push(PodPlacement {
            pod: pod.id.clone(),
            position: spec.position,
            rotation,
            rms_left,
            rms_right,
            left_right_mm: (left.centre() - via_right.centre()).norm() * 1000.0,
            left_right_deg: angle,
        });
    }
    let text = format!(
        "# {}: pod poses measured by `conformd calibrate --placement {}`\n{}",
        rig.name,
        capture.display(),
        toml::to_string(&rig).expect("a rig file serialises")
    );
    write_atomic(out, text.as_bytes())?;
    Ok(found)
}

/// Reconstructs the capture set in `capture` with a loaded rig (its rectification maps
/// cached across calls) and writes the scan and, if asked, the JSON report.
pub fn reconstruct_with(
    station: &mut Reconstruction,
    capture: &Path,
    out: &Path,
    report_path: Option<&Path>,
    as_mesh: bool,
) -> Result<crate::stereo::reconstruct::ReconstructReport, CommandError> {
    Ok(reconstruct_scan(station, capture, out, report_path, as_mesh)?.1)
}

/// As [`reconstruct_with`], also handing back the scan it wrote (for `--truth`).
pub fn reconstruct_scan(
    station: &mut Reconstruction,
    capture: &Path,
    out: &Path,
    report_path: Option<&Path>,
    as_mesh: bool,
) -> Result<(mesh::Mesh, crate::stereo::reconstruct::ReconstructReport), CommandError> {
    let (scan, report) = reconstruct_in_memory(station, capture, as_mesh)?;
    write_scan(out, report_path, &scan, &report)?;
    Ok((scan, report))
}

/// A ground truth for `reconstruct --truth`: the disparity file, its scale and the pod
/// whose left image it belongs to (None: the rig's first).
pub struct ScanTruth<'a> {
    pub file: &'a Path,
    pub scale: Option<f64>,
    pub pod: Option<&'a str>,
}

/// `reconstruct`, scored against a truth when one is given: the scan is scored before
/// it is written, so a truth that cannot be read or used leaves no scan behind.
pub fn reconstruct_scored(
    station: &mut Reconstruction,
    capture: &Path,
    out: &Path,
    report_path: Option<&Path>,
    as_mesh: bool,
    truth: Option<ScanTruth>,
) -> Result<
    (
        crate::stereo::reconstruct::ReconstructReport,
        Option<crate::stereo::truth::DepthScore>,
    ),
    CommandError,
> {
    let (scan, report) = reconstruct_in_memory(station, capture, as_mesh)?;
    let score = truth
        .map(|t| score_scan(&scan, station, t.pod, t.file, t.scale))
        .transpose()?;
    write_scan(out, report_path, &scan, &report)?;
    Ok((report, score))
}

fn reconstruct_in_memory(
    station: &mut Reconstruction,
    capture: &Path,
    as_mesh: bool,
) -> Result<(mesh::Mesh, crate::stereo::reconstruct::ReconstructReport), CommandError> {
    let set = CaptureSetDir::open(capture)?;
    let images = crate::station::pipeline::read_pod_images(&set, &station.pods)?;
    station
        .run(&images.pixels, as_mesh)
        .map_err(|e| CommandError::Reconstruct(format!("{e}; images: {}", images.named(e.pod()))))
}

fn write_scan(
    out: &Path,
    report_path: Option<&Path>,
    scan: &mesh::Mesh,
    report: &crate::stereo::reconstruct::ReconstructReport,
) -> Result<(), CommandError> {
    mesh::write_mesh(out, scan)?;
    if let Some(p) = report_path {
        write_report(p, report)?;
    }
    Ok(())
}

/// Reconstructs a capture set into a scan in the rig frame: every pod of the rig file
/// (cameras found by the manifest's pod and side) is rectified, matched and reprojected;
/// then the points are fused into a PLY point cloud with normals, or, `as_mesh`, each
/// pod's depth grid is triangulated with a cut at depth jumps into one mesh with holes.
/// Writes the scan and, if asked, a JSON report. Images are checked before any work:
/// a missing, unreadable or wrongly sized image is named with its camera and file.
///
/// Example: `conformd reconstruct sim/<id> --rig config/rig.example.toml --out scan.ply`;
/// see `tests/stereo.rs`.
pub fn reconstruct(
    capture: &Path,
    rig_path: &Path,
    calibration: Option<&Path>,
    out: &Path,
    report_path: Option<&Path>,
    as_mesh: bool,
) -> Result<crate::stereo::reconstruct::ReconstructReport, CommandError> {
    let mut station = Reconstruction::load(rig_path, calibration)?;
    reconstruct_with(&mut station, capture, out, report_path, as_mesh)
}

/// An image file in grey (a regular file of at most [`crate::files::MAX_IMAGE_BYTES`]),
/// refused naming the file.
fn read_grey(p: &Path) -> Result<image::GrayImage, CommandError> {
    let bytes = crate::files::read_limited(p, crate::files::MAX_IMAGE_BYTES)?;
    Ok(image::load_from_memory(&bytes)
        .map_err(|e| CommandError::Image {
            path: p.display().to_string(),
            msg: e.to_string(),
        })?
        .to_luma8())
}

/// A rectified pair's two images in grey, refused naming the file if one cannot be read
/// or the two differ in size.
fn read_rectified_pair(
    left: &Path,
    right: &Path,
) -> Result<(image::GrayImage, image::GrayImage), CommandError> {
    let (l, r) = (read_grey(left)?, read_grey(right)?);
    if l.dimensions() != r.dimensions() {
        return Err(CommandError::Input {
            path: right.display().to_string(),
            msg: format!(
                "{:?}, but {} is {:?}: a rectified pair has one size",
                r.dimensions(),
                left.display(),
                l.dimensions()
            ),
        });
    }
    Ok((l, r))
}

/// Disparity of an already-rectified pair, written as PFM (or 16-bit PNG x16 for .png).
pub fn disparity(
    left: &Path,
    right: &Path,
    opts: &crate::stereo::disparity::SgbmOptions,
    out: &Path,
) -> Result<crate::stereo::disparity::Disparity, CommandError> {
    disparity_scored(left, right, opts, out, None, None).map(|(d, _)| d)
}

/// A ground truth to score a disparity map against: the file, its scale (None: the file
/// type's own) and the first column scored.
pub struct TruthArgs<'a> {
    pub file: &'a Path,
    pub scale: Option<f64>,
    pub min_x: u32,
}

/// [`disparity`] scored against a truth: the truth is read first and the map written
/// only once it is scored, so a bad truth leaves no map behind. With `confidence_out`,
/// each pixel's confidence in its match (0 to 1, 0 where none is kept) is written there
/// as PFM too.
pub fn disparity_scored(
    left: &Path,
    right: &Path,
    opts: &crate::stereo::disparity::SgbmOptions,
    out: &Path,
    truth: Option<TruthArgs>,
    confidence_out: Option<&Path>,
) -> Result<
    (
        crate::stereo::disparity::Disparity,
        Option<crate::stereo::truth::TruthScore>,
    ),
    CommandError,
> {
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext != "pfm" && ext != "png" {
        return Err(CommandError::Usage(format!(
            "{}: a disparity map is written as .pfm (float) or .png (16-bit, x16)",
            out.display()
        )));
    }
    opts.validate()?;
    let truth = truth
        .map(|t| {
            crate::stereo::truth::read_truth(t.file, t.scale)
                .map(|read| (t, read))
                .map_err(CommandError::from)
        })
        .transpose()?;
    let (l, r) = read_rectified_pair(left, right)?;
    if opts.num_disparities as u32 >= l.width() {
        return Err(CommandError::Usage(format!(
            "{} disparities cannot be searched in an image {} pixels wide",
            opts.num_disparities,
            l.width()
        )));
    }
    if let Some(c) = confidence_out
        && !c.extension().is_some_and(|e| e.eq_ignore_ascii_case("pfm"))
    {
        return Err(CommandError::Usage(format!(
            "{}: a confidence map is written as .pfm (float, 0 to 1)",
            c.display()
        )));
    }
    let (d, confidence) = crate::stereo::disparity::disparity_with_confidence(
        l.as_raw(),
        r.as_raw(),
        l.width(),
        l.height(),
        opts,
    )?;
    if d.valid_share() == 0.0 {
        return Err(CommandError::Input {
            path: left.display().to_string(),
            msg: format!(
                "no pixel found its match in {}: the pair has no texture to match (or is not a rectified pair)",
                right.display()
            ),
        });
    }
    let bytes = if ext == "png" {
        let px: Vec<u16> = d
            .values
            .iter()
            .map(|v| {
                if v.is_finite() {
                    (v * 16.0).round().clamp(0.0, 65535.0) as u16
                } else {
                    0
                }
            })
            .collect();
        let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(d.width, d.height, px)
            .expect("sized");
        crate::render::png_bytes(&img)
    } else {
        d.pfm()
    };
    let score = truth
        .map(|(t, read)| {
            crate::stereo::truth::score(&d, &read, t.min_x).map_err(CommandError::scoring(t.file))
        })
        .transpose()?;
    write_atomic(out, &bytes)?;
    if let Some(c) = confidence_out {
        write_atomic(
            c,
            &crate::stereo::disparity::pfm_bytes(d.width, d.height, &confidence),
        )?;
    }
    Ok((d, score))
}

/// How a disparity map compares with a ground truth (`--truth`): the truth file, its
/// scale (None: the file type's own) and the first column scored.
pub fn score_disparity(
    d: &crate::stereo::disparity::Disparity,
    truth: &Path,
    scale: Option<f64>,
    min_x: u32,
) -> Result<crate::stereo::truth::TruthScore, CommandError> {
    let t = crate::stereo::truth::read_truth(truth, scale)?;
    crate::stereo::truth::score(d, &t, min_x).map_err(CommandError::scoring(truth))
}

/// What `import-pair` wrote: the rig file, the calibration folder and the capture set.
#[derive(Debug, Clone)]
pub struct ImportedPair {
    pub rig: PathBuf,
    pub calibration: PathBuf,
    pub capture: PathBuf,
    /// the truth's copy inside the capture set, if one was given
    pub truth: Option<PathBuf>,
}

/// The pod id of an imported pair.
pub const IMPORTED_POD: &str = "pair";

/// Turns a recorded, rectified pair and its calibration (Middlebury or KITTI
/// `calib.txt`) into what a station would have: `out/rig.toml` (one pod, the
/// natural-texture profile over `num_disparities`, or the file's `ndisp` rounded up to
/// a multiple of 16, else 128; every point kept), `out/calibration/pair.yml` and a
/// capture set under `out/captures/` holding the images, the calibration file and the
/// truth, if given, as it was (`truth.<ext>`). Then `reconstruct` and `process` run on
/// it, and `reconstruct --truth` scores the scan in depth.
pub fn import_pair(
    left: &Path,
    right: &Path,
    calib: &Path,
    truth: Option<&Path>,
    num_disparities: Option<i32>,
    out: &Path,
) -> Result<ImportedPair, CommandError> {
    let (l, r) = read_rectified_pair(left, right)?;
    let calib_text = crate::files::read_limited(calib, 1 << 20)?;
    let cal = crate::stereo::recorded::parse_calibration(&String::from_utf8_lossy(&calib_text))
        .map_err(|source| CommandError::RecordedCalibration {
            path: calib.display().to_string(),
            source,
        })?;
    let ndisp = num_disparities.unwrap_or_else(|| match cal.ndisp {
        Some(n) => (n as i32 + 15) / 16 * 16,
        None => 128,
    });
    let (w, h) = l.dimensions();
    if let Some((cw, ch)) = cal.size
        && (cw, ch) != (w, h)
    {
        return Err(CommandError::Input {
            path: calib.display().to_string(),
            msg: format!(
                "the calibration is for {cw}x{ch} images, {} is {w}x{h}",
                left.display()
            ),
        });
    }
    // the truth is kept under one name whatever it was called, its type kept
    let truth_file = truth.map(|t| {
        let ext = t.extension().and_then(|e| e.to_str()).unwrap_or("png");
        format!("truth.{}", ext.to_ascii_lowercase())
    });
    let mut extra: Vec<(&str, Vec<u8>)> = vec![("calib.txt", calib_text)];
    if let (Some(t), Some(file)) = (truth, &truth_file) {
        // parsed now, so that a truth of the wrong size is refused before anything is
        // written; copied as it was
        let bytes = crate::files::read_limited(t, crate::files::MAX_IMAGE_BYTES)?;
        let parsed = crate::stereo::truth::parse_truth(t, &bytes, None)?;
        if (parsed.width, parsed.height) != (w, h) {
            return Err(CommandError::Input {
                path: t.display().to_string(),
                msg: format!(
                    "the truth is {} x {}, the images {w} x {h}",
                    parsed.width, parsed.height
                ),
            });
        }
        extra.push((file, bytes));
    }
    let stem = left
        .parent()
        .and_then(|p| p.file_name())
        .and_then(|n| n.to_str())
        .filter(|n| crate::paths::check_plain_name("rig name", n).is_ok())
        .unwrap_or("recorded");
    let name = format!("replay-{stem}");
    let rig = cal.rig_file(&name, IMPORTED_POD, (w, h), ndisp);
    rig.check()?;
    let rig_path = out.join("rig.toml");
    let cal_dir = out.join("calibration");
    std::fs::create_dir_all(&cal_dir).map_err(|source| CommandError::Io {
        path: cal_dir.display().to_string(),
        source,
    })?;
    let text = format!(
        "# {name}: the recorded pair {} / {} ({}), replayed by `conformd import-pair`\n{}",
        left.display(),
        right.display(),
        calib.display(),
        toml::to_string(&rig).expect("a rig file serialises")
    );
    write_atomic(&rig_path, text.as_bytes())?;
    let pod = cal.pod(IMPORTED_POD, w, h);
    write_atomic(
        &cal_dir.join(format!("{IMPORTED_POD}.yml")),
        pod.opencv_yaml_of(Some(&name)).as_bytes(),
    )?;
    let images = vec![
        (IMPORTED_POD.to_string(), "left", w, h, l.into_raw()),
        (IMPORTED_POD.to_string(), "right", w, h, r.into_raw()),
    ];
    let capture = write_set(
        &out.join("captures"),
        ("recorded", "replay"),
        0,
        &name,
        &format!("{}", left.display()),
        images,
        &extra,
    )?;
    let truth = truth_file.map(|n| capture.join(n));
    Ok(ImportedPair {
        rig: rig_path,
        calibration: cal_dir,
        capture,
        truth,
    })
}

/// Scores a reconstructed scan against a truth disparity of one pod's left image
/// (`pod`, else the rig's first), as depth ([`crate::stereo::truth::score_depth`]).
pub fn score_scan(
    scan: &crate::mesh::Mesh,
    station: &Reconstruction,
    pod: Option<&str>,
    truth: &Path,
    scale: Option<f64>,
) -> Result<crate::stereo::truth::DepthScore, CommandError> {
    let p = match pod {
        Some(id) => station.pods.iter().find(|p| p.id == id).ok_or_else(|| {
            CommandError::Usage(format!("--truth-pod {id}: the rig has no such pod"))
        })?,
        None => &station.pods[0],
    };
    let t = crate::stereo::truth::read_truth(truth, scale)?;
    crate::stereo::truth::score_depth(&scan.vertices, p, &t).map_err(CommandError::scoring(truth))
}

/// Renders chessboard calibration views for every pod of the rig: `out/<pod>/leftNN.png`
/// and `rightNN.png`, and the pod's true calibration beside them (`truth.yml`).
pub fn simulate_chessboard(
    rig_path: &Path,
    board: &str,
    square: f64,
    views: usize,
    out: &Path,
) -> Result<Vec<PathBuf>, CommandError> {
    use crate::stereo::rig::RigFile;
    use crate::synth::virtual_rig::{Chessboard, chessboard_poses, render_chessboard};
    let (cols, rows) = parse_board(board)?;
    if !(square > 0.0) {
        return Err(CommandError::Usage(format!(
            "the chessboard's square size must be positive, got {square}"
        )));
    }
    let rig = RigFile::load(rig_path)?;
    let cb = Chessboard { cols, rows, square };
    let mut dirs = Vec::new();
    for (pod, spec) in rig.pods().iter().zip(&rig.pods) {
        let dir = out.join(&pod.id);
        std::fs::create_dir_all(&dir).map_err(|source| CommandError::Io {
            path: dir.display().to_string(),
            source,
        })?;
        for (k, b) in chessboard_poses(pod, spec, &cb, views, 7)
            .iter()
            .enumerate()
        {
            for (right, name) in [(false, "left"), (true, "right")] {
                let px = render_chessboard(pod, right, &cb, b, 1.0, k as u64);
                let img =
                    image::GrayImage::from_raw(pod.left.width, pod.left.height, px).expect("sized");
                crate::render::save_png(&img, &dir.join(format!("{name}{k:02}.png")))?;
            }
        }
        write_atomic(&dir.join("truth.yml"), pod.opencv_yaml().as_bytes())?;
        dirs.push(dir);
    }
    Ok(dirs)
}

/// Calibrates one pod from chessboard pairs in `images` (`leftNN.*` with `rightNN.*`, or
/// folders `left/` and `right/` with matching names) and writes OpenCV YAML.
pub fn calibrate(
    images: &Path,
    board: &str,
    square: f64,
    out: &Path,
) -> Result<crate::stereo::calibrate::CalibrationReport, CommandError> {
    let (cols, rows) = parse_board(board)?;
    let list = |dir: &Path, prefix: &str| -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .map(|e| e.path())
                    .filter(|p| {
                        p.file_name()
                            .is_some_and(|n| n.to_string_lossy().starts_with(prefix))
                    })
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    };
    let (lefts, rights) = if images.join("left").is_dir() {
        (
            list(&images.join("left"), ""),
            list(&images.join("right"), ""),
        )
    } else {
        (list(images, "left"), list(images, "right"))
    };
    if lefts.is_empty() || lefts.len() != rights.len() {
        return Err(CommandError::Usage(format!(
            "{}: found {} left and {} right images; expected pairs leftNN/rightNN (or folders left/ and right/)",
            images.display(),
            lefts.len(),
            rights.len()
        )));
    }
    let mut size = None;
    let mut pairs = Vec::new();
    for (l, r) in lefts.iter().zip(&rights) {
        let (a, b) = (read_grey(l)?, read_grey(r)?);
        let dims = a.dimensions();
        if b.dimensions() != dims || size.is_some_and(|s| s != dims) {
            return Err(CommandError::Usage(format!(
                "{}: its size differs from the other views",
                r.display()
            )));
        }
        size = Some(dims);
        pairs.push((a.into_raw(), b.into_raw()));
    }
    let (w, h) = size.expect("at least one pair");
    let id = images
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "pod".into());
    let (pod, report) = crate::stereo::calibrate::calibrate(&pairs, w, h, cols, rows, square, &id)?;
    let yaml = crate::stereo::calibrate::full_yaml(&pod, None)?;
    write_atomic(out, yaml.as_bytes())?;
    Ok(report)
}
