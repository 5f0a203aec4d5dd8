//! Disparity by OpenCV's semi-global block matching on a rectified pair, with tuned
//! defaults (P1/P2 from the block size, uniqueness, speckle filtering, OpenCV's
//! left-right check), then a sub-pixel refinement; written as PFM (Middlebury
//! convention, invalid = inf).

use opencv::calib3d::{StereoSGBM, StereoSGBM_MODE_SGBM_3WAY};
use opencv::core::{self, CV_8UC1, CV_32F, Mat, Point, Size};
use opencv::imgproc;
use opencv::prelude::*;

/// What the cameras see, which decides the defaults of the other settings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    /// a projected speckle pattern on the subject (the virtual rig, an active rig): a
    /// contrast mask drops the unlit background, and a sub-pixel step lowers depth noise
    #[default]
    Speckle,
    /// natural texture (passive cameras, recorded benchmark pairs): smooth surfaces are
    /// matched by SGBM's smoothness, so no contrast mask, and no sub-pixel step (it
    /// moves more pixels past 1 px than it brings closer)
    Natural,
}

/// SGBM settings; `p1`/`p2` are 8 and 32 x block size squared (one channel). Read from
/// a rig file, `profile` picks the defaults and every other key given overrides them.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(from = "SgbmKeys")]
pub struct SgbmOptions {
    pub profile: Profile,
    pub min_disparity: i32,
    /// a multiple of 16
    pub num_disparities: i32,
    /// odd, 3 to 11
    pub block_size: i32,
    pub uniqueness_ratio: i32,
    pub speckle_window_size: i32,
    pub speckle_range: i32,
    /// left-right consistency, pixels (negative: off)
    pub disp12_max_diff: i32,
    pub pre_filter_cap: i32,
    /// pixels whose neighbourhood (`contrast_window` a side) varies less than this (grey
    /// levels, standard deviation) carry no texture to match: they are left out, not
    /// guessed; 0 keeps them
    pub min_contrast: f64,
    /// side of that neighbourhood, pixels (odd)
    pub contrast_window: i32,
    /// valid pixels this close (pixels) to an unmatched pixel or to a disparity jump of
    /// over `max_jump` are dropped: block matching smears the nearer surface across such
    /// edges ("edge fattening"); 0 keeps them
    pub edge_margin: i32,
    /// disparity step (pixels) within the margin's window taken as a jump between surfaces
    pub max_jump: f64,
    /// sub-pixel refinement after SGBM (see [`refine_subpixel`]): Gauss-Newton steps, and
    /// the window (pixels, odd) they compare; 0 steps keeps SGBM's own interpolation
    pub subpixel_steps: u32,
    pub subpixel_window: i32,
    /// a full left-right check: the mirrored pair is matched too, and a left pixel is kept
    /// only if the right pixel it lands on agrees within this many pixels (or has no
    /// match of its own); 0: off (SGBM's `disp12_max_diff` still applies). Costs a second
    /// SGBM run; catches the occluded pixels SGBM's own check passes (edge fattening).
    pub cross_check: f64,
    /// pixels this close (pixels, to the right) to one the full check dropped are dropped
    /// too: the first columns of a surface after an occlusion carry its smeared edge
    pub occlusion_margin: i32,
    /// pixels whose confidence in their match (0 to 1, [`Matched::confidence`]) is
    /// below this are dropped: the knob that trades coverage for fewer wrong matches;
    /// 0 keeps them all
    pub min_confidence: f64,
}

impl Default for SgbmOptions {
    fn default() -> Self {
        SgbmOptions::for_profile(Profile::Speckle)
    }
}

/// The keys of `[reconstruct.sgbm]` as written: any may be left out.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct SgbmKeys {
    profile: Option<Profile>,
    min_disparity: Option<i32>,
    num_disparities: Option<i32>,
    block_size: Option<i32>,
    uniqueness_ratio: Option<i32>,
    speckle_window_size: Option<i32>,
    speckle_range: Option<i32>,
    disp12_max_diff: Option<i32>,
    pre_filter_cap: Option<i32>,
    min_contrast: Option<f64>,
    contrast_window: Option<i32>,
    edge_margin: Option<i32>,
    max_jump: Option<f64>,
    subpixel_steps: Option<u32>,
    subpixel_window: Option<i32>,
    cross_check: Option<f64>,
    occlusion_margin: Option<i32>,
    min_confidence: Option<f64>,
}

impl From<SgbmKeys> for SgbmOptions {
    fn from(k: SgbmKeys) -> SgbmOptions {
        let mut o = SgbmOptions::for_profile(k.profile.unwrap_or_default());
        macro_rules! given {
            ($($f:ident),*) => {$(if let Some(v) = k.$f { o.$f = v; })*};
        }
        given!(
            min_disparity,
            num_disparities,
            block_size,
            uniqueness_ratio,
            speckle_window_size,
            speckle_range,
            disp12_max_diff,
            pre_filter_cap,
            min_contrast,
            contrast_window,
            edge_margin,
            max_jump,
            subpixel_steps,
            subpixel_window,
            cross_check,
            occlusion_margin,
            min_confidence
        );
        o
    }
}

/// Why a disparity map could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum DisparityError {
    /// a matcher setting out of its range, in words naming it
    #[error("{0}")]
    Options(String),
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

impl SgbmOptions {
    /// The defaults for what the cameras see.
    pub fn for_profile(profile: Profile) -> SgbmOptions {
        let speckle = SgbmOptions::speckle();
        match profile {
            Profile::Speckle => speckle,
            // chosen on the recorded pairs of tests/data/stereo (benches/stereo_real.rs):
            // SGBM's smoothness carries matches across plain surfaces from their textured
            // edges, so only what is flat over a 21x21 window is left out; the sub-pixel
            // step moves more pixels past 1 px than it brings closer; occlusions are
            // found by the full left-right check instead of the edge margin, which cost
            // KITTI's thin poles and car edges their coverage. A looser uniqueness ratio
            // with the least confident matches dropped keeps fewer wrong ones than the
            // strict ratio alone, at stock SGBM's coverage or more (cones 4.66 -> 4.22%
            // bad, teddy 7.19 -> 6.81%, KITTI 7.17 -> 6.90%)
            Profile::Natural => SgbmOptions {
                profile,
                uniqueness_ratio: 5,
                min_confidence: 0.1,
                min_contrast: 1.0,
                contrast_window: 21,
                subpixel_steps: 0,
                edge_margin: 0,
                cross_check: 1.0,
                occlusion_margin: 1,
                ..speckle
            },
        }
    }

    fn speckle() -> Self {
        // Wrong matches are worse than holes for a scanner: a strict uniqueness ratio,
        // speckle filtering and the left-right check drop doubtful pixels.
        SgbmOptions {
            profile: Profile::Speckle,
            min_disparity: 0,
            num_disparities: 128,
            block_size: 5,
            uniqueness_ratio: 12,
            speckle_window_size: 120,
            speckle_range: 2,
            disp12_max_diff: 1,
            pre_filter_cap: 31,
            min_contrast: 6.0,
            contrast_window: 5,
            edge_margin: 2,
            max_jump: 2.0,
            subpixel_steps: 1,
            subpixel_window: 7,
            cross_check: 0.0,
            occlusion_margin: 0,
            min_confidence: 0.0,
        }
    }
}

impl SgbmOptions {
    pub fn validate(&self) -> Result<(), DisparityError> {
        if self.num_disparities <= 0
            || self.num_disparities % 16 != 0
            || self.num_disparities > 1024
        {
            return Err(DisparityError::Options(format!(
                "num_disparities must be a multiple of 16 from 16 to 1024, got {}",
                self.num_disparities
            )));
        }
        if self.block_size < 1 || self.block_size % 2 == 0 || self.block_size > 21 {
            return Err(DisparityError::Options(format!(
                "block_size must be odd, 1 to 21, got {}",
                self.block_size
            )));
        }
        if !(self.cross_check >= 0.0 && self.cross_check.is_finite()) {
            return Err(DisparityError::Options(format!(
                "cross_check must be 0 (off) or a tolerance in pixels, got {}",
                self.cross_check
            )));
        }
        if !(0.0..=1.0).contains(&self.min_confidence) {
            return Err(DisparityError::Options(format!(
                "min_confidence must be 0 to 1, got {}",
                self.min_confidence
            )));
        }
        if self.edge_margin < 0 || self.occlusion_margin < 0 {
            return Err(DisparityError::Options(format!(
                "edge_margin and occlusion_margin are pixels, 0 or more, got {} and {}",
                self.edge_margin, self.occlusion_margin
            )));
        }
        if self.contrast_window < 3 || self.contrast_window % 2 == 0 || self.contrast_window > 63 {
            return Err(DisparityError::Options(format!(
                "contrast_window must be odd, 3 to 63, got {}",
                self.contrast_window
            )));
        }
        if self.subpixel_window < 3 || self.subpixel_window % 2 == 0 || self.subpixel_window > 31 {
            return Err(DisparityError::Options(format!(
                "subpixel_window must be odd, 3 to 31, got {}",
                self.subpixel_window
            )));
        }
        Ok(())
    }
}

/// A disparity map in pixels, row-major; invalid pixels are infinite.
#[derive(Debug, Clone)]
pub struct Disparity {
    pub width: u32,
    pub height: u32,
    pub values: Vec<f32>,
}

impl Disparity {
    pub fn valid_share(&self) -> f64 {
        self.values.iter().filter(|v| v.is_finite()).count() as f64
            / self.values.len().max(1) as f64
    }

    /// PFM bytes ([`pfm_bytes`]).
    pub fn pfm(&self) -> Vec<u8> {
        pfm_bytes(self.width, self.height, &self.values)
    }
}

/// PFM bytes of a one-channel float image (`values` row-major, top row first): `Pf`,
/// size, scale -1 (little-endian), rows bottom to top.
pub fn pfm_bytes(width: u32, height: u32, values: &[f32]) -> Vec<u8> {
    let mut out = format!("Pf\n{width} {height}\n-1\n").into_bytes();
    for y in (0..height as usize).rev() {
        for v in &values[y * width as usize..(y + 1) * width as usize] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

pub(crate) fn gray_mat(pixels: &[u8], width: u32, height: u32) -> opencv::Result<Mat> {
    let m = Mat::new_rows_cols_with_data(height as i32, width as i32, pixels)?;
    let owned = m.try_clone()?;
    debug_assert_eq!(owned.typ(), CV_8UC1);
    Ok(owned)
}

/// Disparity of a rectified pair of 8-bit grey images (same size).
pub fn disparity_mats(left: &Mat, right: &Mat, o: &SgbmOptions) -> opencv::Result<Mat> {
    let bs = o.block_size;
    let mut sgbm = StereoSGBM::create(
        o.min_disparity,
        o.num_disparities,
        bs,
        8 * bs * bs,
        32 * bs * bs,
        o.disp12_max_diff,
        o.pre_filter_cap,
        o.uniqueness_ratio,
        o.speckle_window_size,
        o.speckle_range,
        StereoSGBM_MODE_SGBM_3WAY,
    )?;
    // SGBM leaves the first min + num columns without a disparity (their match could lie
    // left of the right image); padding both images on the left by as much gives every
    // original column its full search, and the padding is cut off again
    let pad = (o.min_disparity + o.num_disparities).max(0);
    let padded = |m: &Mat| -> opencv::Result<Mat> {
        let mut out = Mat::default();
        core::copy_make_border(
            m,
            &mut out,
            0,
            0,
            pad,
            0,
            core::BORDER_CONSTANT,
            core::Scalar::all(0.0),
        )?;
        Ok(out)
    };
    let mut disp = Mat::default();
    sgbm.compute(&padded(left)?, &padded(right)?, &mut disp)?;
    Mat::roi(&disp, core::Rect::new(pad, 0, left.cols(), left.rows()))?.try_clone()
}

/// Stock OpenCV SGBM_3WAY with the ordinary settings of OpenCV's own sample (block 5,
/// P1 200, P2 800, left-right 1, pre-filter cap 63, uniqueness 10, speckle 100 / 32), no
/// padding and no filter of ours: the floor the profiles are measured against.
pub fn stock_sgbm(
    left: &[u8],
    right: &[u8],
    width: u32,
    height: u32,
    num_disparities: i32,
) -> Result<Disparity, DisparityError> {
    let run = || -> opencv::Result<Disparity> {
        let (l, r) = (
            gray_mat(left, width, height)?,
            gray_mat(right, width, height)?,
        );
        let mut sgbm = StereoSGBM::create(
            0,
            num_disparities,
            5,
            200,
            800,
            1,
            63,
            10,
            100,
            32,
            StereoSGBM_MODE_SGBM_3WAY,
        )?;
        let mut d = Mat::default();
        sgbm.compute(&l, &r, &mut d)?;
        to_pixels(&d, 0)
    };
    Ok(run()?)
}

/// Converts OpenCV's fixed-point disparity (16 x pixels, CV_16S) to pixels, invalid = inf.
pub fn to_pixels(disp: &Mat, min_disparity: i32) -> opencv::Result<Disparity> {
    let raw = disp.data_typed::<i16>()?;
    let invalid = (min_disparity - 1) * 16;
    Ok(Disparity {
        width: disp.cols() as u32,
        height: disp.rows() as u32,
        values: raw
            .iter()
            .map(|&d| {
                if (d as i32) <= invalid {
                    f32::INFINITY
                } else {
                    d as f32 / 16.0
                }
            })
            .collect(),
    })
}

/// A rectified pair matched: what conformd's filters keep of SGBM's disparity.
pub struct Matched {
    /// the kept disparity, refined where `subpixel_steps` > 0, row-major, invalid = inf
    pub values: Vec<f32>,
    /// each kept pixel's confidence, 0 to 1 ([`pixel_confidence`]); 0 where none is kept;
    /// empty unless asked for or cut by (`min_confidence`)
    pub confidence: Vec<f32>,
    /// pixels SGBM matched, before conformd's filters
    pub sgbm_matched: usize,
    /// seconds spent in conformd's own loops (the rest is OpenCV's)
    pub seconds_own: f64,
}

/// Matches a rectified pair of 8-bit grey images and applies every filter of `o`: the
/// one path of `disparity` and `reconstruct`, so both report the same pixels. In order:
/// SGBM; the sub-pixel step (a pixel it would move by over a pixel is dropped); the
/// texture mask (`min_contrast`); the edge margin (a jump of over `max_jump`, or an
/// unmatched pixel, within `edge_margin`); the full left-right check (`cross_check`) and
/// the `occlusion_margin` beside what it dropped; the confidence cut (`min_confidence`).
/// `grids`: [`pixel_grids`] of the pair's size, if the caller keeps them; `want_confidence`:
/// whether the caller wants each pixel's confidence (it costs about 0.04 s a 1280x960
/// pair, so a station whose rig file does not cut by it does not pay for it).
pub fn match_pair(
    left: &Mat,
    right: &Mat,
    grids: Option<&(Mat, Mat)>,
    o: &SgbmOptions,
    want_confidence: bool,
) -> opencv::Result<Matched> {
    let (w, h) = (left.cols() as usize, left.rows() as usize);
    let d16 = disparity_mats(left, right, o)?;
    let mut sgbm = Mat::default();
    d16.convert_to(&mut sgbm, CV_32F, 1.0 / 16.0, 0.0)?;
    let unmatched = (o.min_disparity - 1) as f32;
    let raw = sgbm.data_typed::<f32>()?;
    let refined_own;
    let refined = if o.subpixel_steps > 0 {
        let own_grids;
        let g = match grids {
            Some(g) => g,
            None => {
                own_grids = pixel_grids(w as i32, h as i32)?;
                &own_grids
            }
        };
        refined_own = refine_subpixel(left, right, &sgbm, g, o)?;
        Some(refined_own.data_typed::<f32>()?)
    } else {
        None
    };
    let moments = if o.min_contrast > 0.0 {
        Some(local_moments(left, o.contrast_window)?)
    } else {
        None
    };
    let spread = if o.edge_margin > 0 {
        Some(disparity_spread(&sgbm, o)?)
    } else {
        None
    };
    let mirrored = if o.cross_check > 0.0 {
        let flip = |m: &Mat| -> opencv::Result<Mat> {
            let mut out = Mat::default();
            core::flip(m, &mut out, 1)?;
            Ok(out)
        };
        // the right image as reference: the mirrored right image is the left of a pair
        let d = disparity_mats(&flip(right)?, &flip(left)?, o)?;
        let mut f = Mat::default();
        d.convert_to(&mut f, CV_32F, 1.0 / 16.0, 0.0)?;
        Some(f)
    } else {
        None
    };
    let moments = match &moments {
        Some((m, m2)) => Some((m.data_typed::<f32>()?, m2.data_typed::<f32>()?)),
        None => None,
    };
    let spread = match &spread {
        Some(s) => Some(s.data_typed::<f32>()?),
        None => None,
    };
    let own = std::time::Instant::now();
    let mut sgbm_matched = 0;
    let min_var = (o.min_contrast * o.min_contrast) as f32;
    let mut values: Vec<f32> = raw
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            if d <= unmatched {
                return f32::INFINITY;
            }
            sgbm_matched += 1;
            let v = match refined {
                // a pixel that moved over a pixel in all was not refined but lost
                Some(r) if (r[i] - d).abs() > 1.0 => return f32::INFINITY,
                Some(r) => r[i],
                None => d,
            };
            if let Some((m, m2)) = moments
                && m2[i] - m[i] * m[i] < min_var
            {
                // no match where the left image has no texture to match
                return f32::INFINITY;
            }
            if spread.is_some_and(|s| s[i] > o.max_jump as f32) {
                return f32::INFINITY;
            }
            v
        })
        .collect();
    let mut lr = vec![f32::NAN; values.len()];
    if let Some(m) = &mirrored {
        cross_check(
            &mut values,
            &mut lr,
            raw,
            m.data_typed::<f32>()?,
            w,
            unmatched,
            o,
        );
    }
    let mut confidence = if want_confidence || o.min_confidence > 0.0 {
        pixel_confidence(&values, &lr, w, h)?
    } else {
        Vec::new()
    };
    if o.min_confidence > 0.0 {
        for (v, c) in values.iter_mut().zip(confidence.iter_mut()) {
            if *c < o.min_confidence as f32 {
                (*v, *c) = (f32::INFINITY, 0.0);
            }
        }
    }
    Ok(Matched {
        values,
        confidence,
        sgbm_matched,
        seconds_own: own.elapsed().as_secs_f64(),
    })
}

/// The full left-right check on `values` (row-major, `w` wide) against the mirrored
/// pair's disparity `right` (its column `w - 1 - x` is the right image's column x), then
/// the occlusion margin beside the pixels it dropped. `raw`: SGBM's left disparity.
fn cross_check(
    values: &mut [f32],
    lr: &mut [f32],
    raw: &[f32],
    right: &[f32],
    w: usize,
    unmatched: f32,
    o: &SgbmOptions,
) {
    let tol = o.cross_check as f32;
    let mut dropped = vec![false; values.len()];
    for (i, v) in values.iter_mut().enumerate() {
        if !v.is_finite() {
            continue;
        }
        let (row, x) = (i - i % w, (i % w) as f32);
        let at = x - raw[i];
        if at < 0.0 {
            // its match would lie left of the right image
            (*v, dropped[i]) = (f32::INFINITY, true);
            continue;
        }
        // the two right columns about the sub-pixel match
        let (mut seen, mut agrees) = (false, false);
        for c in [at.floor() as usize, at.ceil() as usize] {
            if c >= w {
                continue;
            }
            let q = right[row + w - 1 - c];
            if q > unmatched {
                seen = true;
                agrees |= (q - raw[i]).abs() <= tol;
                lr[i] = lr[i].min((q - raw[i]).abs());
            }
        }
        // a right pixel without a match of its own says nothing against this one
        if seen && !agrees {
            (*v, dropped[i]) = (f32::INFINITY, true);
        }
    }
    let m = o.occlusion_margin as usize;
    if m == 0 {
        return;
    }
    for i in 0..values.len() {
        let x = i % w;
        if values[i].is_finite() && (1..=m.min(x)).any(|k| dropped[i - k]) {
            values[i] = f32::INFINITY;
        }
    }
}

/// Side of the window the confidence reads the disparity's local spread over.
const CONFIDENCE_SMOOTH_WINDOW: i32 = 5;

/// Each kept pixel's confidence in its match, 0 to 1: the product of two agreements, each
/// 1 when perfect and 1/2 at its scale: the left-right check's disagreement (without the
/// full check, or where the mirrored pair has no match, 1/2), and how smooth the kept
/// disparity is over a 5x5 window (its standard deviation): a wrong match is most often a
/// lone one that the other view disputes. (The left image's texture ranked worse than
/// no order at all on the recorded pairs: the most textured pixels are the edges, where
/// occlusions are.)
fn pixel_confidence(values: &[f32], lr: &[f32], w: usize, h: usize) -> opencv::Result<Vec<f32>> {
    let kept: Vec<f32> = values.iter().map(|v| v.is_finite() as u8 as f32).collect();
    let d: Vec<f32> = values
        .iter()
        .map(|v| if v.is_finite() { *v } else { 0.0 })
        .collect();
    let d2: Vec<f32> = d.iter().map(|v| v * v).collect();
    let side = core::Size::new(CONFIDENCE_SMOOTH_WINDOW, CONFIDENCE_SMOOTH_WINDOW);
    let blurred = |v: &[f32]| -> opencv::Result<Vec<f32>> {
        let m = Mat::new_rows_cols_with_data(h as i32, w as i32, v)?;
        let mut out = Mat::default();
        imgproc::blur(&m, &mut out, side, Point::new(-1, -1), core::BORDER_REFLECT)?;
        Ok(out.data_typed::<f32>()?.to_vec())
    };
    let (k, s1, s2) = (blurred(&kept)?, blurred(&d)?, blurred(&d2)?);
    Ok((0..values.len())
        .map(|i| {
            if !values[i].is_finite() {
                return 0.0;
            }
            let c_lr = if lr[i].is_nan() {
                0.5
            } else {
                1.0 / (1.0 + (lr[i] / CONFIDENCE_LR_SCALE).powi(2))
            };
            let mu = s1[i] / k[i];
            let sd = (s2[i] / k[i] - mu * mu).max(0.0).sqrt();
            let c_smooth = 1.0 / (1.0 + (sd / CONFIDENCE_SMOOTH_SCALE).powi(2));
            c_lr * c_smooth
        })
        .collect())
}

/// The left-right disagreement (pixels) and the disparity's local standard deviation
/// (pixels) at which each halves the confidence.
const CONFIDENCE_LR_SCALE: f32 = 0.5;
const CONFIDENCE_SMOOTH_SCALE: f32 = 1.0;

/// The spread (largest minus smallest) of SGBM's disparity over each pixel's
/// `edge_margin` window, unmatched pixels counting as 0: over `max_jump` marks a pixel
/// beside a depth jump or a hole, where block matching smears the nearer surface.
fn disparity_spread(sgbm: &Mat, o: &SgbmOptions) -> opencv::Result<Mat> {
    let side = 2 * o.edge_margin + 1;
    let anchor = Point::new(-1, -1);
    let kernel =
        imgproc::get_structuring_element(imgproc::MORPH_RECT, Size::new(side, side), anchor)?;
    let mut d0 = Mat::default();
    imgproc::threshold(
        sgbm,
        &mut d0,
        o.min_disparity as f64,
        0.0,
        imgproc::THRESH_TOZERO,
    )?;
    let (mut hi, mut lo) = (Mat::default(), Mat::default());
    let border = imgproc::morphology_default_border_value()?;
    imgproc::dilate(
        &d0,
        &mut hi,
        &kernel,
        anchor,
        1,
        core::BORDER_CONSTANT,
        border,
    )?;
    imgproc::erode(
        &d0,
        &mut lo,
        &kernel,
        anchor,
        1,
        core::BORDER_REPLICATE,
        border,
    )?;
    let mut spread = Mat::default();
    core::subtract(&hi, &lo, &mut spread, &core::no_array(), -1)?;
    Ok(spread)
}

/// Disparity of a rectified pair given as grey pixels, with every filter of `o`
/// ([`match_pair`]).
pub fn disparity(
    left: &[u8],
    right: &[u8],
    width: u32,
    height: u32,
    o: &SgbmOptions,
) -> Result<Disparity, DisparityError> {
    Ok(disparity_with_confidence(left, right, width, height, o)?.0)
}

/// [`disparity`] and each pixel's confidence in its match (0 to 1, 0 where none is kept;
/// [`Matched::confidence`]), row-major.
pub fn disparity_with_confidence(
    left: &[u8],
    right: &[u8],
    width: u32,
    height: u32,
    o: &SgbmOptions,
) -> Result<(Disparity, Vec<f32>), DisparityError> {
    o.validate()?;
    let run = || -> opencv::Result<(Disparity, Vec<f32>)> {
        let (l, r) = (
            gray_mat(left, width, height)?,
            gray_mat(right, width, height)?,
        );
        let m = match_pair(&l, &r, None, o, true)?;
        Ok((
            Disparity {
                width,
                height,
                values: m.values,
            },
            m.confidence,
        ))
    };
    Ok(run()?)
}

/// Local mean and mean of squares of a grey image over `side` x `side` windows (CV_32F),
/// whose difference of squares is the local variance the texture mask reads.
pub fn local_moments(img: &Mat, side: i32) -> opencv::Result<(Mat, Mat)> {
    let mut f = Mat::default();
    img.convert_to(&mut f, CV_32F, 1.0, 0.0)?;
    let mut sq = Mat::default();
    core::multiply(&f, &f, &mut sq, 1.0, -1)?;
    let (mut mean, mut mean_sq) = (Mat::default(), Mat::default());
    let k = core::Size::new(side, side);
    let anchor = core::Point::new(-1, -1);
    imgproc::blur(&f, &mut mean, k, anchor, core::BORDER_REFLECT)?;
    imgproc::blur(&sq, &mut mean_sq, k, anchor, core::BORDER_REFLECT)?;
    Ok((mean, mean_sq))
}

/// Each pixel's x and y coordinate as two CV_32F images of `width` x `height`.
pub fn pixel_grids(width: i32, height: i32) -> opencv::Result<(Mat, Mat)> {
    let xs: Vec<f32> = (0..height)
        .flat_map(|_| (0..width).map(|x| x as f32))
        .collect();
    let ys: Vec<f32> = (0..height)
        .flat_map(|y| (0..width).map(move |_| y as f32))
        .collect();
    Ok((
        Mat::new_rows_cols_with_data(height, width, &xs)?.try_clone()?,
        Mat::new_rows_cols_with_data(height, width, &ys)?.try_clone()?,
    ))
}

/// Refines a disparity map to sub-pixel precision: SGBM's parabola fit between whole-pixel
/// costs leans towards whole pixels ("pixel locking"), which shows as ripples of a few mm
/// on a scanned surface. Each step warps the right image by the disparity and takes the
/// Gauss-Newton step that best aligns it with the left image over a window, with the
/// window's mean brightness removed (one-dimensional Lucas-Kanade); every operation is an
/// OpenCV call over the whole image.
///
/// In: rectified 8-bit left and right images, disparity in pixels (CV_32F, same size).
/// Out: the refined disparity (CV_32F); pixels the caller takes as unmatched stay so.
/// `grids`: each pixel's x and y coordinate ([`pixel_grids`]), kept by callers that
/// refine many maps of one size.
pub fn refine_subpixel(
    left: &Mat,
    right: &Mat,
    disp: &Mat,
    grids: &(Mat, Mat),
    o: &SgbmOptions,
) -> opencv::Result<Mat> {
    let (w, h) = (disp.cols(), disp.rows());
    let (xg, yg) = grids;
    let (mut l, mut r, mut g) = (Mat::default(), Mat::default(), Mat::default());
    left.convert_to(&mut l, CV_32F, 1.0, 0.0)?;
    right.convert_to(&mut r, CV_32F, 1.0, 0.0)?;
    imgproc::sobel(
        &r,
        &mut g,
        CV_32F,
        1,
        0,
        3,
        0.125,
        0.0,
        core::BORDER_REPLICATE,
    )?;
    let win = Size::new(o.subpixel_window, o.subpixel_window);
    let mean = |m: &Mat| -> opencv::Result<Mat> {
        let mut out = Mat::default();
        imgproc::box_filter(
            m,
            &mut out,
            -1,
            win,
            Point::new(-1, -1),
            true,
            core::BORDER_REFLECT,
        )?;
        Ok(out)
    };
    let mul = |a: &Mat, b: &Mat| -> opencv::Result<Mat> {
        let mut out = Mat::default();
        core::multiply(a, b, &mut out, 1.0, -1)?;
        Ok(out)
    };
    let sub = |a: &Mat, b: &Mat| -> opencv::Result<Mat> {
        let mut out = Mat::default();
        core::subtract(a, b, &mut out, &core::no_array(), -1)?;
        Ok(out)
    };
    let warp = |m: &Mat, mapx: &Mat| -> opencv::Result<Mat> {
        let mut out = Mat::default();
        imgproc::remap(
            m,
            &mut out,
            mapx,
            yg,
            imgproc::INTER_LINEAR,
            core::BORDER_REPLICATE,
            core::Scalar::all(0.0),
        )?;
        Ok(out)
    };
    let mut d = disp.try_clone()?;
    for _ in 0..o.subpixel_steps {
        let mapx = sub(xg, &d)?;
        let (rw, gw) = (warp(&r, &mapx)?, warp(&g, &mapx)?);
        let e = sub(&rw, &l)?;
        let (me, mg) = (mean(&e)?, mean(&gw)?);
        // cov(e, g) / var(g) over the window
        let num = sub(&mean(&mul(&e, &gw)?)?, &mul(&me, &mg)?)?;
        let den = sub(&mean(&mul(&gw, &gw)?)?, &mul(&mg, &mg)?)?;
        let mut step = Mat::default();
        core::divide2(&num, &den, &mut step, 1.0, -1)?;
        // a step of over half a pixel is not a refinement: bounded, and the caller drops
        // pixels that moved more than a pixel in all
        let (mut hi, mut lo) = (Mat::default(), Mat::default());
        core::min(
            &step,
            &Mat::new_rows_cols_with_default(h, w, core::CV_32F, core::Scalar::all(0.5))?,
            &mut hi,
        )?;
        core::max(
            &hi,
            &Mat::new_rows_cols_with_default(h, w, core::CV_32F, core::Scalar::all(-0.5))?,
            &mut lo,
        )?;
        let mut next = Mat::default();
        core::add(&d, &lo, &mut next, &core::no_array(), -1)?;
        d = next;
    }
    Ok(d)
}
