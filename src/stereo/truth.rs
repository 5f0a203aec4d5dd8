//! Ground-truth disparity of recorded stereo pairs (Middlebury PFM and quarter-size PNG,
//! KITTI 16-bit PNG) and the figures a disparity map is judged by against it: the share
//! of bad pixels (more than 1 px off) among the valid ones, and the coverage; and the
//! same truth as depth, to judge a reconstructed scan by ([`score_depth`]).

use super::calib::Pod;
use super::disparity::Disparity;
use crate::mesh::V3;
use std::path::Path;

/// A ground-truth disparity map; NaN where the truth is unknown.
#[derive(Debug, Clone)]
pub struct Truth {
    pub width: u32,
    pub height: u32,
    pub values: Vec<f32>,
}

/// How a disparity map compares with the truth, over the pixels whose truth is known
/// (and at column `min_x` or beyond).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TruthScore {
    /// pixels with a known truth
    pub known: usize,
    /// of those, the share the map gives a disparity
    pub coverage: f64,
    /// of the given ones, the share more than 1 px (and 2 px) off
    pub bad1: f64,
    pub bad2: f64,
    /// mean absolute error of the given ones, pixels
    pub mean_abs: f64,
    /// the median ratio of the map to the truth, when far from 1 ([`scale_mismatch`])
    pub scale_mismatch: Option<f64>,
}

impl std::fmt::Display for TruthScore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "against the truth: {:.2}% of valid pixels more than 1 px off ({:.2}% more than 2 px), mean error {:.3} px, coverage {:.1}% of {} pixels with a known truth",
            self.bad1 * 100.0,
            self.bad2 * 100.0,
            self.mean_abs,
            self.coverage * 100.0,
            self.known
        )?;
        if let Some(r) = self.scale_mismatch {
            write!(
                f,
                "\nwarning: the map's disparities are {r:.2} times the truth's (median): is the truth's scale right? An 8-bit PNG is read as disparity x 4 (Middlebury's quarter-size sets), a 16-bit one as x 256 (KITTI); --truth-scale 1 reads a truth stored in pixels"
            )?;
        }
        Ok(())
    }
}

/// How a reconstructed scan compares with the truth seen as depth from the pod's left
/// camera: each known pixel takes the nearest scan point that projects into it.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DepthScore {
    /// pixels with a known truth
    pub known: usize,
    /// of those, the share some scan point projects into
    pub coverage: f64,
    /// depth error of the covered pixels, metres: mean, 95th percentile
    pub mean_depth: f64,
    pub p95_depth: f64,
    /// the same, relative to the true depth
    pub mean_relative: f64,
    /// the scan's depth taken back to disparity: the share of covered pixels more than
    /// 1 px (and 2 px) off, as `disparity --truth` counts them
    pub bad1: f64,
    pub bad2: f64,
}

impl std::fmt::Display for DepthScore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "against the truth: depth error mean {:.4} m ({:.2}% of the depth), 95th percentile {:.4} m; {:.2}% of covered pixels more than 1 px of disparity off ({:.2}% more than 2 px); coverage {:.1}% of {} pixels with a known truth",
            self.mean_depth,
            self.mean_relative * 100.0,
            self.p95_depth,
            self.bad1 * 100.0,
            self.bad2 * 100.0,
            self.coverage * 100.0,
            self.known
        )
    }
}

/// Why a ground truth could not be read or scored against.
#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    #[error(transparent)]
    Read(#[from] crate::files::FileError),
    /// a file that is not a ground truth conformd reads
    #[error("{path}: {msg}")]
    Format { path: String, msg: String },
    #[error("the truth is {} x {} but pod {pod}'s left camera gives {} x {}", truth.0, truth.1, camera.0, camera.1)]
    PodSize {
        truth: (u32, u32),
        pod: String,
        camera: (u32, u32),
    },
    #[error("the disparity map is {} x {} but the truth {} x {}", map.0, map.1, truth.0, truth.1)]
    MapSize { map: (u32, u32), truth: (u32, u32) },
    #[error("{got} confidences for {pixels} pixels")]
    Confidences { got: usize, pixels: usize },
    #[error("the truth has no known pixels in front of the camera; nothing to score")]
    NothingInFront,
    #[error("the scan covers none of the truth's {known} known pixels; nothing to score")]
    NotCovered { known: usize },
    #[error("the truth has no known pixels{}; nothing to score", from_column.map(|(x, w)| format!(" from column {x} on (the images are {w} wide)")).unwrap_or_default())]
    NoKnownPixels { from_column: Option<(u32, u32)> },
    #[error(
        "the disparity map has no valid pixel where the truth's {known} are known; nothing to score"
    )]
    NoValidPixel { known: usize },
}

/// Scores scan points (rig frame) against a truth disparity of `pod`'s left image. The
/// truth's depth is `f B / (d + doffs)`, `doffs` the right camera's principal point
/// less the left's (Middlebury's convention; 0 for KITTI); lens distortion is applied
/// when projecting, so the truth is taken to be of the image as recorded.
pub fn score_depth(points: &[V3], pod: &Pod, truth: &Truth) -> Result<DepthScore, TruthError> {
    let k = &pod.left;
    if (k.width, k.height) != (truth.width, truth.height) {
        return Err(TruthError::PodSize {
            truth: (truth.width, truth.height),
            pod: pod.id.clone(),
            camera: (k.width, k.height),
        });
    }
    let (fb, doffs) = (k.fx * pod.baseline(), pod.right.cx - k.cx);
    let w = k.width as usize;
    // the nearest point per pixel: the surface that pixel sees
    let mut nearest = vec![f64::INFINITY; truth.values.len()];
    for p in points {
        let c = pod.left_pose.to_camera(p);
        let Some(px) = k.project(&c) else { continue };
        let (x, y) = (px.x.round(), px.y.round());
        if x >= 0.0 && y >= 0.0 && (x as u32) < k.width && (y as u32) < k.height {
            let i = y as usize * w + x as usize;
            nearest[i] = nearest[i].min(c.z);
        }
    }
    let (mut known, mut errors, mut rel, mut bad1, mut bad2) = (0, Vec::new(), 0.0, 0, 0);
    for (&t, &z) in truth.values.iter().zip(&nearest) {
        if t.is_nan() || !(t as f64 + doffs > 0.0) {
            continue;
        }
        known += 1;
        if z.is_finite() {
            let zt = fb / (t as f64 + doffs);
            errors.push((z - zt).abs());
            rel += (z - zt).abs() / zt;
            let e = (fb / z - doffs - t as f64).abs();
            bad1 += (e > 1.0) as usize;
            bad2 += (e > 2.0) as usize;
        }
    }
    let n = errors.len();
    if known == 0 {
        return Err(TruthError::NothingInFront);
    }
    if n == 0 {
        return Err(TruthError::NotCovered { known });
    }
    let share = |a: usize, of: usize| if of > 0 { a as f64 / of as f64 } else { 0.0 };
    errors.sort_by(f64::total_cmp);
    Ok(DepthScore {
        known,
        coverage: share(n, known),
        mean_depth: if n > 0 {
            errors.iter().sum::<f64>() / n as f64
        } else {
            0.0
        },
        p95_depth: if n > 0 {
            errors[(n * 95 / 100).min(n - 1)]
        } else {
            0.0
        },
        mean_relative: if n > 0 { rel / n as f64 } else { 0.0 },
        bad1: share(bad1, n),
        bad2: share(bad2, n),
    })
}

/// Reads a ground truth: `.pfm` (Middlebury 2014: float, rows bottom-up, inf unknown), or
/// `.png`, 0 unknown, divided by `scale`: by default 256 for a 16-bit PNG (KITTI) and 4
/// for an 8-bit one (Middlebury 2001-2006 quarter-size sets).
pub fn read_truth(path: &Path, scale: Option<f64>) -> Result<Truth, TruthError> {
    let bytes = crate::files::read_limited(path, crate::files::MAX_IMAGE_BYTES)?;
    parse_truth(path, &bytes, scale)
}

/// [`read_truth`] of a file's bytes already read; `path` gives its type and its name in
/// errors.
pub fn parse_truth(path: &Path, bytes: &[u8], scale: Option<f64>) -> Result<Truth, TruthError> {
    let bad = |msg: String| TruthError::Format {
        path: path.display().to_string(),
        msg,
    };
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "pfm" => parse_pfm(bytes).map_err(|e| bad(e.to_string())),
        "png" => {
            let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
                .map_err(|e| bad(e.to_string()))?;
            let sixteen = matches!(
                img.color(),
                image::ColorType::L16 | image::ColorType::La16 | image::ColorType::Rgb16
            );
            let scale = scale.unwrap_or(if sixteen { 256.0 } else { 4.0 });
            if !(scale > 0.0 && scale.is_finite()) {
                return Err(bad("the truth scale must be positive".into()));
            }
            let g = img.to_luma16();
            // to_luma16 stretches 8-bit values by 257: back to the file's own numbers
            let unit = if sixteen { 1.0 } else { 257.0 };
            Ok(Truth {
                width: g.width(),
                height: g.height(),
                values: g
                    .as_raw()
                    .iter()
                    .map(|&v| {
                        if v == 0 {
                            f32::NAN
                        } else {
                            (v as f64 / unit / scale) as f32
                        }
                    })
                    .collect(),
            })
        }
        _ => Err(bad(
            "a ground truth is read from .pfm or .png (16-bit /256, 8-bit /4)".into(),
        )),
    }
}

/// Why a file is not a one-channel PFM conformd reads.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum PfmError {
    #[error("not a one-channel PFM (header 'Pf')")]
    NotPfm,
    #[error("bad PFM header '{0}'")]
    Header(String),
    #[error("PFM size {0} x {1} out of range")]
    Size(f64, f64),
    #[error(
        "PFM scale '{0}' must be a non-zero number (negative: little-endian, positive: big-endian)"
    )]
    Scale(String),
    #[error("PFM data is truncated: {bytes} bytes for {width} x {height}")]
    Truncated {
        bytes: usize,
        width: usize,
        height: usize,
    },
}

fn parse_pfm(bytes: &[u8]) -> Result<Truth, PfmError> {
    // header: "Pf", width height, scale (negative: little-endian), each on its line
    let mut fields = Vec::new();
    let mut start = 0;
    let mut i = 0;
    while fields.len() < 4 && i < bytes.len().min(256) {
        if bytes[i].is_ascii_whitespace() {
            if i > start {
                fields.push(String::from_utf8_lossy(&bytes[start..i]).to_string());
            }
            start = i + 1;
        }
        i += 1;
    }
    if fields.len() < 4 || fields[0] != "Pf" {
        return Err(PfmError::NotPfm);
    }
    let num = |s: &str| {
        s.parse::<f64>()
            .map_err(|_| PfmError::Header(s.to_string()))
    };
    let (w, h, scale) = (num(&fields[1])?, num(&fields[2])?, num(&fields[3])?);
    if !(w >= 1.0 && h >= 1.0 && w * h <= 1e8) {
        return Err(PfmError::Size(w, h));
    }
    // the scale's sign gives the byte order; 0 or NaN gives none
    if !(scale.is_finite() && scale != 0.0) {
        return Err(PfmError::Scale(fields[3].clone()));
    }
    let (w, h) = (w as usize, h as usize);
    let data = &bytes[start..];
    if data.len() < w * h * 4 {
        return Err(PfmError::Truncated {
            bytes: data.len(),
            width: w,
            height: h,
        });
    }
    let mut values = vec![f32::NAN; w * h];
    for (k, c) in data.chunks_exact(4).take(w * h).enumerate() {
        let b = [c[0], c[1], c[2], c[3]];
        let v = if scale < 0.0 {
            f32::from_le_bytes(b)
        } else {
            f32::from_be_bytes(b)
        };
        // rows bottom-up in the file
        let (x, y) = (k % w, h - 1 - k / w);
        values[y * w + x] = if v.is_finite() { v } else { f32::NAN };
    }
    Ok(Truth {
        width: w as u32,
        height: h as u32,
        values,
    })
}

/// Scores `d` against `truth` over the known pixels at column `min_x` or beyond.
pub fn score(d: &Disparity, truth: &Truth, min_x: u32) -> Result<TruthScore, TruthError> {
    if (d.width, d.height) != (truth.width, truth.height) {
        return Err(TruthError::MapSize {
            map: (d.width, d.height),
            truth: (truth.width, truth.height),
        });
    }
    let (mut known, mut valid, mut bad1, mut bad2, mut abs) = (0usize, 0usize, 0usize, 0usize, 0.0);
    for (k, (&v, &t)) in d.values.iter().zip(&truth.values).enumerate() {
        if (k as u32 % d.width) < min_x || t.is_nan() {
            continue;
        }
        known += 1;
        if v.is_finite() {
            valid += 1;
            let e = (v - t).abs() as f64;
            abs += e;
            bad1 += (e > 1.0) as usize;
            bad2 += (e > 2.0) as usize;
        }
    }
    if known == 0 {
        return Err(TruthError::NoKnownPixels {
            from_column: (min_x > 0).then_some((min_x, d.width)),
        });
    }
    if valid == 0 {
        return Err(TruthError::NoValidPixel { known });
    }
    let share = |n: usize, of: usize| if of > 0 { n as f64 / of as f64 } else { 0.0 };
    Ok(TruthScore {
        known,
        coverage: share(valid, known),
        bad1: share(bad1, valid),
        bad2: share(bad2, valid),
        mean_abs: if valid > 0 { abs / valid as f64 } else { 0.0 },
        scale_mismatch: scale_mismatch(d, truth),
    })
}

/// [`score`] of the most confident pixels of `d` only, up to `coverage` (a share of the
/// known pixels at column `min_x` or beyond): how many wrong matches a map has at another
/// map's coverage. `confidence`: per pixel, higher is surer.
pub fn score_at_coverage(
    d: &Disparity,
    confidence: &[f32],
    truth: &Truth,
    min_x: u32,
    coverage: f64,
) -> Result<TruthScore, TruthError> {
    if confidence.len() != d.values.len() {
        return Err(TruthError::Confidences {
            got: confidence.len(),
            pixels: d.values.len(),
        });
    }
    let counted = |k: usize| (k as u32 % d.width) >= min_x && !truth.values[k].is_nan();
    let known = (0..d.values.len()).filter(|&k| counted(k)).count();
    let mut order: Vec<usize> = (0..d.values.len())
        .filter(|&k| counted(k) && d.values[k].is_finite())
        .collect();
    order.sort_by(|&a, &b| confidence[b].total_cmp(&confidence[a]));
    order.truncate((coverage * known as f64).round() as usize);
    let mut top = Disparity {
        width: d.width,
        height: d.height,
        values: vec![f32::INFINITY; d.values.len()],
    };
    for k in order {
        top.values[k] = d.values[k];
    }
    score(&top, truth, min_x)
}

/// The median ratio of the map's disparities to the truth's where both are known, when
/// it is far from 1 (outside 0.8-1.25): a truth read with the wrong scale, which would
/// make every figure meaningless. None when they agree or too few pixels overlap.
pub fn scale_mismatch(d: &Disparity, truth: &Truth) -> Option<f64> {
    let mut ratios: Vec<f32> = d
        .values
        .iter()
        .zip(&truth.values)
        .filter(|(v, t)| v.is_finite() && **v > 0.5 && t.is_finite() && **t > 0.5)
        .map(|(v, t)| v / t)
        .collect();
    if ratios.len() < 100 {
        return None;
    }
    let mid = ratios.len() / 2;
    let (_, m, _) = ratios.select_nth_unstable_by(mid, f32::total_cmp);
    let m = *m as f64;
    (!(0.8..=1.25).contains(&m)).then_some(m)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pfm_reads_back_upright_and_scores_what_it_was_given() {
        let d = Disparity {
            width: 3,
            height: 2,
            values: vec![1.0, 2.0, f32::INFINITY, 4.0, 5.5, 6.0],
        };
        let t = parse_pfm(&d.pfm()).unwrap();
        assert_eq!((t.width, t.height), (3, 2));
        assert_eq!(t.values[..2], [1.0, 2.0]);
        assert!(t.values[2].is_nan());
        let mut guess = d.clone();
        guess.values[4] = 7.0; // 1.5 px off
        guess.values[5] = f32::INFINITY; // not given
        let s = score(&guess, &t, 0).unwrap();
        assert_eq!(s.known, 5);
        assert!((s.coverage - 0.8).abs() < 1e-12);
        assert!((s.bad1 - 0.25).abs() < 1e-12 && s.bad2 == 0.0);
        assert_eq!(parse_pfm(b"P5\n1 1\n255\n").unwrap_err(), PfmError::NotPfm);
        // a truth read at a quarter of its scale is noticed
        let big = Disparity {
            width: 200,
            height: 1,
            values: (0..200).map(|i| 10.0 + i as f32 * 0.1).collect(),
        };
        let quarter = Truth {
            width: 200,
            height: 1,
            values: big.values.iter().map(|v| v / 4.0).collect(),
        };
        assert!(scale_mismatch(&big, &quarter).is_some_and(|r| (r - 4.0).abs() < 1e-3));
        let same = Truth {
            width: 200,
            height: 1,
            values: big.values.clone(),
        };
        assert_eq!(scale_mismatch(&big, &same), None);
        assert_eq!(
            parse_pfm(b"Pf\n4 4\n-1\n\0\0").unwrap_err(),
            PfmError::Truncated {
                bytes: 2,
                width: 4,
                height: 4
            }
        );
    }
}
