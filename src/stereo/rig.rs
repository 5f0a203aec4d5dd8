//! Rig geometry: the rig file (`config/rig.example.toml`) with its stereo pods, their
//! lenses and poses in the rig frame, the working volume, and the rig's reconstruction
//! settings. Both the station's reconstruction and the virtual rig read it.

use crate::mesh::{FileError, V3};
use crate::stereo::calib::{Intrinsics, Pod, Pose};
use nalgebra::Matrix3;
use std::path::Path;

/// One pod in a rig file.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PodSpec {
    pub id: String,
    /// image width and height, pixels
    pub image: [u32; 2],
    pub focal_px: f64,
    /// principal point (default: the image centre)
    pub principal: Option<[f64; 2]>,
    /// k1 k2 p1 p2 k3
    #[serde(default)]
    pub distortion: [f64; 5],
    /// distance between the two cameras' centres, along the left camera's x axis (m)
    pub baseline: f64,
    /// the left camera's centre in the rig frame (m)
    pub position: [f64; 3],
    pub look_at: [f64; 3],
    #[serde(default = "up")]
    pub up: [f64; 3],
    /// the left camera's measured orientation (`calibrate --placement`), rows: its x, y, z
    /// axes in the rig frame; replaces look_at/up for the camera (the projector still
    /// aims at look_at)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation: Option<[[f64; 3]; 3]>,
    /// a speckle projector lights the subject (textureless skin matches poorly without)
    #[serde(default = "yes")]
    pub projector: bool,
    /// size of a projected speckle, in image pixels at the look-at distance
    #[serde(default = "speckle")]
    pub speckle_px: f64,
}

fn up() -> [f64; 3] {
    [0.0, 0.0, 1.0]
}
fn speckle() -> f64 {
    3.0
}
fn yes() -> bool {
    true
}

/// A rig file (`config/rig.example.toml`).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RigFile {
    pub name: String,
    pub pods: Vec<PodSpec>,
    /// the part of the rig frame scans are cropped to: [min, max] corners (m)
    pub working_volume: Option<[[f64; 3]; 2]>,
    /// reconstruction settings for this rig (`[reconstruct]`, `[reconstruct.sgbm]`,
    /// `[reconstruct.mesh]`); the defaults when absent
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reconstruct: Option<crate::stereo::reconstruct::ReconstructOptions>,
}

impl RigFile {
    /// Reads and checks a rig file; errors name the file and the pod.
    pub fn load(path: &Path) -> Result<RigFile, FileError> {
        let text = crate::files::read_text_limited(path, 1 << 20)?;
        RigFile::parse(&path.display().to_string(), &text)
    }

    /// Reads and checks a rig file's text; `name` labels the errors.
    pub fn parse(name: &str, text: &str) -> Result<RigFile, FileError> {
        let rig: RigFile =
            toml::from_str(text).map_err(|e| FileError::content(name, e.to_string()))?;
        rig.check()
            .map_err(|e| FileError::content(name, e.to_string()))?;
        Ok(rig)
    }

    /// Checks what the types cannot: pods present, ids plain and distinct, finite
    /// positive optics, rotations that are rotations, a working volume with min < max.
    pub fn check(&self) -> Result<(), RigFileError> {
        if self.pods.is_empty() {
            return Err(RigFileError::NoPods);
        }
        if let Some(o) = &self.reconstruct {
            o.sgbm.validate()?;
        }
        if let Some([lo, hi]) = self.working_volume
            && !(0..3).all(|i| lo[i].is_finite() && hi[i].is_finite() && lo[i] < hi[i])
        {
            return Err(RigFileError::WorkingVolume(lo, hi));
        }
        let mut ids = std::collections::BTreeSet::new();
        for p in &self.pods {
            crate::paths::check_plain_name("pod id", &p.id)?;
            if !ids.insert(p.id.as_str()) {
                return Err(RigFileError::TwoPods(p.id.clone()));
            }
            let bad = |what: PodFault| Err(RigFileError::Pod(p.id.clone(), what));
            if let Some(rows) = p.rotation {
                let r = Matrix3::from_fn(|i, j| rows[i][j]);
                if !r.iter().all(|v| v.is_finite())
                    || (r * r.transpose() - Matrix3::identity()).norm() > 1e-6
                    || r.determinant() < 0.0
                {
                    return bad(PodFault::NotARotation);
                }
            }
            if !(p.baseline > 0.0
                && p.baseline.is_finite()
                && p.focal_px > 0.0
                && p.focal_px.is_finite()
                && (16..=20_000).contains(&p.image[0])
                && (16..=20_000).contains(&p.image[1]))
            {
                return bad(PodFault::Optics);
            }
            let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
            if !finite(&p.position)
                || !finite(&p.look_at)
                || !finite(&p.up)
                || !finite(&p.distortion)
            {
                return bad(PodFault::NotFinite);
            }
            if p.rotation.is_none() {
                let (eye, at, up) = (V3::from(p.position), V3::from(p.look_at), V3::from(p.up));
                let dir = at - eye;
                if dir.norm() < 1e-9
                    || dir.cross(&up).norm() < 1e-9 * dir.norm() * up.norm().max(1e-300)
                {
                    return bad(PodFault::LookAt);
                }
            }
        }
        Ok(())
    }

    /// The pods as cameras: the right camera parallel to the left, `baseline` along its x.
    pub fn pods(&self) -> Vec<Pod> {
        self.pods
            .iter()
            .map(|s| {
                let [w, h] = s.image;
                let [cx, cy] = s.principal.unwrap_or([w as f64 / 2.0, h as f64 / 2.0]);
                let k = Intrinsics {
                    width: w,
                    height: h,
                    fx: s.focal_px,
                    fy: s.focal_px,
                    cx,
                    cy,
                    dist: s.distortion,
                };
                let left_pose = match s.rotation {
                    Some(rows) => {
                        let r = Matrix3::from_fn(|i, j| rows[i][j]);
                        Pose {
                            r,
                            t: -(r * V3::from(s.position)),
                        }
                    }
                    None => {
                        Pose::look_at(V3::from(s.position), V3::from(s.look_at), V3::from(s.up))
                    }
                };
                Pod {
                    id: s.id.clone(),
                    left: k,
                    right: k,
                    left_pose,
                    r: Matrix3::identity(),
                    t: V3::new(-s.baseline, 0.0, 0.0),
                }
            })
            .collect()
    }
}

/// What is wrong in a rig file that parsed (what the types cannot say).
#[derive(Debug, thiserror::Error)]
pub enum RigFileError {
    #[error("no [[pods]]")]
    NoPods,
    #[error("[reconstruct.sgbm]: {0}")]
    Sgbm(#[from] crate::stereo::disparity::DisparityError),
    #[error("working_volume {0:?} .. {1:?}: every minimum must be below its maximum")]
    WorkingVolume([f64; 3], [f64; 3]),
    #[error(transparent)]
    Name(#[from] crate::paths::NameError),
    #[error("two pods have the id '{0}'")]
    TwoPods(String),
    #[error("pod {0}: {1}")]
    Pod(String, PodFault),
}

/// What is wrong with one pod of a rig file.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum PodFault {
    #[error("rotation is not a rotation matrix (orthonormal rows, determinant 1)")]
    NotARotation,
    #[error("baseline and focal_px must be positive and finite, image 16 to 20000 pixels a side")]
    Optics,
    #[error("position, look_at, up and distortion must be finite")]
    NotFinite,
    #[error("look_at must differ from position and not lie along up")]
    LookAt,
}

/// Why a rig's reconstruction set-up could not be loaded; names the file.
#[derive(Debug, thiserror::Error)]
pub enum RigError {
    #[error(transparent)]
    File(#[from] FileError),
    #[error("{path}: {msg}")]
    Calibration { path: String, msg: String },
}

/// A station's reconstruction set-up: the rig file, its pods with their calibrations
/// (checked to belong to this rig), the options, and the rectification maps, built on the
/// first capture and reused for every later one. A station pipeline keeps one for its
/// life; the CLI makes one per call.
pub struct Reconstruction {
    pub rig: RigFile,
    pub pods: Vec<Pod>,
    pub options: crate::stereo::reconstruct::ReconstructOptions,
    cache: crate::stereo::reconstruct::RectifierCache,
}

impl Reconstruction {
    /// Loads the rig file and, from `calibration` when given, every pod's `<pod>.yml`
    /// (OpenCV YAML), which replaces the rig file's lenses and pair geometry. A
    /// calibration that names another rig or pod, was made for another image size, or
    /// whose baseline is more than 25% off the rig file's is refused.
    pub fn load(rig_path: &Path, calibration: Option<&Path>) -> Result<Reconstruction, RigError> {
        let rig = RigFile::load(rig_path)?;
        let mut pods = Vec::new();
        for pod in rig.pods() {
            let Some(dir) = calibration else {
                pods.push(pod);
                continue;
            };
            let f = dir.join(format!("{}.yml", pod.id));
            let refuse = |msg: String| RigError::Calibration {
                path: f.display().to_string(),
                msg,
            };
            match std::fs::metadata(&f) {
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    return Err(refuse(format!("no calibration for pod {}", pod.id)));
                }
                // what else stands there is named by the reader (a pipe, a folder, ...)
                _ => {}
            }
            let (cal, origin) = crate::stereo::calibrate::read_yaml(
                &f,
                &pod.id,
                pod.left_pose,
                pod.left.width,
                pod.left.height,
            )
            .map_err(|e| {
                let msg = match e {
                    crate::stereo::calibrate::CalibrationError::File { msg, .. } => msg,
                    // the reader's own message names the file
                    other => {
                        let msg = other.to_string();
                        msg.strip_prefix(&format!("{}: ", f.display()))
                            .map_or(msg.clone(), str::to_string)
                    }
                };
                RigError::Calibration {
                    path: f.display().to_string(),
                    msg,
                }
            })?;
            let other = |why: String| {
                refuse(format!(
                    "{why}; is it a calibration from another rig? (rig file {})",
                    rig_path.display()
                ))
            };
            if let Some(r) = origin.rig.as_ref().filter(|r| **r != rig.name) {
                return Err(other(format!(
                    "made for rig '{r}', this rig is '{}'",
                    rig.name
                )));
            }
            if let Some(p) = origin.pod.as_ref().filter(|p| **p != pod.id) {
                return Err(other(format!("made for pod '{p}', not '{}'", pod.id)));
            }
            if let Some((w, h)) = origin
                .image
                .filter(|s| *s != (pod.left.width, pod.left.height))
            {
                return Err(other(format!(
                    "made for {w}x{h} images, pod {}'s cameras give {}x{}",
                    pod.id, pod.left.width, pod.left.height
                )));
            }
            let ratio = cal.baseline() / pod.baseline();
            if !(0.75..=1.25).contains(&ratio) {
                return Err(other(format!(
                    "its baseline is {:.4} m, the rig file gives pod {} {:.4} m",
                    cal.baseline(),
                    pod.id,
                    pod.baseline()
                )));
            }
            pods.push(cal);
        }
        let mut options = rig.reconstruct.clone().unwrap_or_default();
        options.working_volume = options.working_volume.or(rig.working_volume);
        Ok(Reconstruction {
            rig,
            pods,
            options,
            cache: Default::default(),
        })
    }

    /// Reconstructs one capture from every pod's (left, right) grey pixels, in the order
    /// of [`Reconstruction::pods`], each of the pod's image size: a fused point cloud with
    /// normals, or (`as_mesh`) every pod's triangulated depth grid in one mesh with holes.
    /// See [`crate::stereo::reconstruct::reconstruct`].
    pub fn run(
        &mut self,
        images: &[(Vec<u8>, Vec<u8>)],
        as_mesh: bool,
    ) -> Result<
        (
            crate::mesh::Mesh,
            crate::stereo::reconstruct::ReconstructReport,
        ),
        crate::stereo::reconstruct::ReconstructError,
    > {
        use crate::stereo::reconstruct::{self as rc, PodImages};
        let inputs: Vec<PodImages> = self
            .pods
            .iter()
            .zip(images)
            .map(|(pod, (l, r))| PodImages {
                pod,
                left: l,
                right: r,
            })
            .collect();
        let mut report = rc::ReconstructReport::default();
        let scan = rc::reconstruct(
            &inputs,
            &mut self.cache,
            &self.options,
            as_mesh,
            &mut report,
        )?;
        Ok((scan, report))
    }
}
