//! Calibrations of recorded benchmark pairs (Middlebury `calib.txt`, KITTI `calib.txt`)
//! read into a pod and a rig file, so a recorded, rectified pair can be replayed as a
//! capture set through `reconstruct` and `process` (`conformd import-pair`).

use super::calib::{Intrinsics, Pod, Pose};
use super::rig::{PodSpec, RigFile};
use crate::mesh::V3;
use nalgebra::Matrix3;

/// A rectified pair's calibration: one focal length and row of principal points, the
/// right camera's principal point (Middlebury's `doffs` is its difference), the baseline
/// and, if the file says, the disparities to search.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RecordedCalibration {
    pub focal: f64,
    pub cx_left: f64,
    pub cx_right: f64,
    pub cy: f64,
    /// metres
    pub baseline: f64,
    pub ndisp: Option<u32>,
    /// the image size the file states (Middlebury's `width=` and `height=`), to be
    /// checked against the images
    pub size: Option<(u32, u32)>,
}

/// Reads a Middlebury 2014 `calib.txt` (`cam0=[f 0 cx; 0 f cy; 0 0 1]`, `cam1=`,
/// `baseline=` in mm, `ndisp=`) or a KITTI one (`P0:` and `P1:`, 3x4 projections of the
/// rectified grey cameras, `P1`'s fourth entry `-f B` in metres).
pub fn parse_calibration(text: &str) -> Result<RecordedCalibration, RecordedCalibrationError> {
    // a key given twice has two values, and which one counts would be a guess
    let mut seen = std::collections::BTreeMap::new();
    for (n, l) in text.lines().enumerate() {
        let Some(k) = l
            .split(['=', ':'])
            .next()
            .map(str::trim)
            .filter(|_| l.contains(['=', ':']))
        else {
            continue;
        };
        if let Some(first) = seen.insert(k.to_string(), n + 1) {
            return Err(RecordedCalibrationError::Twice {
                key: k.escape_default().to_string(),
                first,
                second: n + 1,
            });
        }
    }
    let value = |key: &str, sep: char| -> Option<&str> {
        text.lines().find_map(|l| {
            let (k, v) = l.split_once(sep)?;
            (k.trim() == key).then_some(v.trim())
        })
    };
    let numbers = |v: &str, what: &'static str| -> Result<Vec<f64>, RecordedCalibrationError> {
        v.split(|c: char| c.is_whitespace() || matches!(c, '[' | ']' | ';'))
            .filter(|s| !s.is_empty())
            .map(|s| {
                s.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| RecordedCalibrationError::NotANumber {
                        what,
                        value: s.to_string(),
                    })
            })
            .collect()
    };
    let c = if let (Some(c0), Some(c1)) = (value("cam0", '='), value("cam1", '=')) {
        let (k0, k1) = (numbers(c0, "cam0")?, numbers(c1, "cam1")?);
        if k0.len() != 9 || k1.len() != 9 {
            return Err(RecordedCalibrationError::Cameras);
        }
        let b = value("baseline", '=').ok_or(RecordedCalibrationError::NoBaseline)?;
        let b = numbers(b, "baseline")?;
        let count = |key: &'static str| -> Result<Option<u32>, RecordedCalibrationError> {
            value(key, '=')
                .map(|v| {
                    v.parse::<u32>()
                        .map_err(|_| RecordedCalibrationError::NotACount {
                            key,
                            value: v.to_string(),
                        })
                })
                .transpose()
        };
        let ndisp = count("ndisp")?;
        let size = match (count("width")?, count("height")?) {
            (Some(w), Some(h)) => Some((w, h)),
            (None, None) => None,
            _ => return Err(RecordedCalibrationError::HalfSize),
        };
        // doffs is cam1's cx less cam0's: a file where they disagree is not one pair's
        if let Some(d) = value("doffs", '=') {
            let d = numbers(d, "doffs")?;
            let want = k1[2] - k0[2];
            if d.len() != 1 || (d[0] - want).abs() > 0.5 + 1e-3 * want.abs() {
                return Err(RecordedCalibrationError::Doffs { given: d, want });
            }
        }
        RecordedCalibration {
            focal: k0[0],
            cx_left: k0[2],
            cx_right: k1[2],
            cy: k0[5],
            baseline: b.first().copied().unwrap_or(f64::NAN) / 1000.0,
            ndisp,
            size,
        }
    } else if let (Some(p0), Some(p1)) = (value("P0", ':'), value("P1", ':')) {
        let (p0, p1) = (numbers(p0, "P0")?, numbers(p1, "P1")?);
        if p0.len() != 12 || p1.len() != 12 {
            return Err(RecordedCalibrationError::Projections);
        }
        RecordedCalibration {
            focal: p0[0],
            cx_left: p0[2],
            cx_right: p1[2],
            cy: p0[6],
            baseline: -p1[3] / p1[0],
            ndisp: None,
            size: None,
        }
    } else {
        return Err(RecordedCalibrationError::Neither);
    };
    if !(c.focal > 0.0 && c.baseline > 0.0 && c.baseline.is_finite()) {
        return Err(RecordedCalibrationError::NotPositive {
            focal: c.focal,
            baseline: c.baseline,
        });
    }
    Ok(c)
}

/// Why a recorded pair's calibration file could not be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RecordedCalibrationError {
    #[error("'{key}' is given twice (lines {first} and {second})")]
    Twice {
        key: String,
        first: usize,
        second: usize,
    },
    #[error("{what}: '{value}' is not a number")]
    NotANumber { what: &'static str, value: String },
    #[error("cam0 and cam1 must be 3x3 matrices [f 0 cx; 0 f cy; 0 0 1]")]
    Cameras,
    #[error("no baseline= (mm)")]
    NoBaseline,
    #[error("{key}: '{value}' is not a count")]
    NotACount { key: &'static str, value: String },
    #[error("width= and height= come together")]
    HalfSize,
    #[error("doffs {given:?} is not cam1's cx less cam0's ({want})")]
    Doffs { given: Vec<f64>, want: f64 },
    #[error("P0 and P1 must be 3x4 projection matrices (12 numbers)")]
    Projections,
    #[error(
        "neither a Middlebury calibration (cam0=, cam1=, baseline=) nor a KITTI one (P0:, P1:)"
    )]
    Neither,
    #[error("focal length {focal} px and baseline {baseline} m must be positive")]
    NotPositive { focal: f64, baseline: f64 },
}

impl RecordedCalibration {
    /// The pair as a pod `id` whose left camera is the rig frame (x right, y down, z
    /// forward), for images of `width` x `height`.
    pub fn pod(&self, id: &str, width: u32, height: u32) -> Pod {
        let k = |cx| Intrinsics {
            width,
            height,
            fx: self.focal,
            fy: self.focal,
            cx,
            cy: self.cy,
            dist: [0.0; 5],
        };
        Pod {
            id: id.into(),
            left: k(self.cx_left),
            right: k(self.cx_right),
            left_pose: Pose {
                r: Matrix3::identity(),
                t: V3::zeros(),
            },
            r: Matrix3::identity(),
            t: V3::new(-self.baseline, 0.0, 0.0),
        }
    }

    /// A rig file of the one pod, matched with the natural-texture profile over
    /// `num_disparities` (a multiple of 16), every point kept (no voxel grid, no outlier
    /// removal, no working volume): a replay is scored pixel by pixel.
    pub fn rig_file(
        &self,
        name: &str,
        pod: &str,
        size: (u32, u32),
        num_disparities: i32,
    ) -> RigFile {
        use super::disparity::{Profile, SgbmOptions};
        use super::reconstruct::ReconstructOptions;
        RigFile {
            name: name.into(),
            pods: vec![PodSpec {
                id: pod.into(),
                image: [size.0, size.1],
                focal_px: self.focal,
                principal: Some([self.cx_left, self.cy]),
                distortion: [0.0; 5],
                baseline: self.baseline,
                position: [0.0; 3],
                look_at: [0.0, 0.0, 1.0],
                up: [0.0, -1.0, 0.0],
                rotation: Some([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
                projector: false,
                speckle_px: 3.0,
            }],
            working_volume: None,
            reconstruct: Some(ReconstructOptions {
                sgbm: SgbmOptions {
                    num_disparities,
                    ..SgbmOptions::for_profile(Profile::Natural)
                },
                voxel: 0.0,
                outlier_k: 0,
                auto_disparity_range: false,
                ..Default::default()
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn middlebury_and_kitti_calibrations_read() {
        let m = parse_calibration(
            "cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]\ncam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]\ndoffs=131.111\nbaseline=193.001\nwidth=2964\nheight=1988\nndisp=280\n",
        )
        .unwrap();
        assert_eq!(m.ndisp, Some(280));
        assert!((m.baseline - 0.193001).abs() < 1e-9);
        assert!((m.cx_right - m.cx_left - 131.111).abs() < 1e-9);
        let k = parse_calibration(
            "P0: 7.188560e+02 0 6.071928e+02 0 0 7.188560e+02 1.852157e+02 0 0 0 1 0\nP1: 7.188560e+02 0 6.071928e+02 -3.861448e+02 0 7.188560e+02 1.852157e+02 0 0 0 1 0\n",
        )
        .unwrap();
        assert!((k.baseline - 0.537165).abs() < 1e-5 && k.cx_left == k.cx_right);
        let pod = k.pod("p", 1226, 370);
        assert!((pod.baseline() - k.baseline).abs() < 1e-12);
        assert!(
            parse_calibration("cam0=[1 0 2; 0 1 2; 0 0 1]\ncam1=[1 0 x; 0 1 2; 0 0 1]\nbaseline=1")
                .unwrap_err()
                .to_string()
                .contains("'x'")
        );
        assert!(parse_calibration("hello").unwrap_err() == RecordedCalibrationError::Neither);
        assert_eq!(m.size, Some((2964, 1988)));
        // careless files: a key twice, doffs that is not the cx difference or not a
        // number, half a size
        let mb = |extra: &str| {
            parse_calibration(&format!(
                "cam0=[3997.684 0 1176.728; 0 3997.684 1011.728; 0 0 1]\ncam1=[3997.684 0 1307.839; 0 3997.684 1011.728; 0 0 1]\nbaseline=193.001\n{extra}"
            ))
        };
        assert!(mb("doffs=131.111\n").is_ok());
        let e = mb("baseline=19.3\n").unwrap_err().to_string();
        assert!(
            e.contains("'baseline' is given twice (lines 3 and 4)"),
            "{e}"
        );
        assert!(
            mb("doffs=inf\n")
                .unwrap_err()
                .to_string()
                .contains("'inf' is not a number")
        );
        assert!(
            mb("doffs=12\n")
                .unwrap_err()
                .to_string()
                .contains("cam1's cx less cam0's")
        );
        assert_eq!(
            mb("width=100\n").unwrap_err(),
            RecordedCalibrationError::HalfSize
        );
        assert!(
            parse_calibration("P0: 1 0 0 0 0 1 0 0 0 0 1 0\nP1: 1 0 0 5 0 1 0 0 0 0 1 0")
                .unwrap_err()
                .to_string()
                .contains("positive")
        );
    }
}
