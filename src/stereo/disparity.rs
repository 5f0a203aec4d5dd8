//! Disparity by OpenCV's semi-global block matching on a rectified pair, with tuned
//! defaults (P1/P2 from the block size, uniqueness, speckle filtering, OpenCV's
//! left-right check); written as PFM (Middlebury convention, invalid = inf).

use opencv::calib3d::{StereoSGBM, StereoSGBM_MODE_SGBM_3WAY};
use opencv::core::{CV_8UC1, Mat};
use opencv::prelude::*;

/// SGBM settings; `p1`/`p2` default to 8 and 32 x block size squared (one channel).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SgbmOptions {
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
    /// pixels whose 5x5 neighbourhood varies less than this (grey levels, standard
    /// deviation) carry no texture to match: they are left out, not guessed
    pub min_contrast: f64,
    /// valid pixels this close (pixels) to an unmatched pixel or to a disparity jump of
    /// over `max_jump` are dropped: block matching smears the nearer surface across such
    /// edges ("edge fattening"); 0 keeps them
    pub edge_margin: i32,
    /// disparity step (pixels) within the margin's window taken as a jump between surfaces
    pub max_jump: f64,
}

impl Default for SgbmOptions {
    fn default() -> Self {
        // Wrong matches are worse than holes for a scanner: a strict uniqueness ratio,
        // speckle filtering and the left-right check drop doubtful pixels.
        SgbmOptions {
            min_disparity: 0,
            num_disparities: 128,
            block_size: 5,
            uniqueness_ratio: 12,
            speckle_window_size: 120,
            speckle_range: 2,
            disp12_max_diff: 1,
            pre_filter_cap: 31,
            min_contrast: 6.0,
            edge_margin: 2,
            max_jump: 2.0,
        }
    }
}

impl SgbmOptions {
    pub fn validate(&self) -> Result<(), String> {
        if self.num_disparities <= 0 || self.num_disparities % 16 != 0 {
            return Err(format!(
                "num_disparities must be a positive multiple of 16, got {}",
                self.num_disparities
            ));
        }
        if self.block_size < 1 || self.block_size % 2 == 0 || self.block_size > 21 {
            return Err(format!(
                "block_size must be odd, 1 to 21, got {}",
                self.block_size
            ));
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

    /// PFM bytes: `Pf`, size, scale -1 (little-endian), rows bottom to top.
    pub fn pfm(&self) -> Vec<u8> {
        let mut out = format!("Pf\n{} {}\n-1\n", self.width, self.height).into_bytes();
        for y in (0..self.height as usize).rev() {
            for v in &self.values[y * self.width as usize..(y + 1) * self.width as usize] {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        out
    }
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
    let mut disp = Mat::default();
    sgbm.compute(left, right, &mut disp)?;
    Ok(disp)
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

/// Disparity of a rectified pair given as grey pixels.
pub fn disparity(
    left: &[u8],
    right: &[u8],
    width: u32,
    height: u32,
    o: &SgbmOptions,
) -> Result<Disparity, String> {
    o.validate()?;
    let run = || -> opencv::Result<Disparity> {
        let d = disparity_mats(
            &gray_mat(left, width, height)?,
            &gray_mat(right, width, height)?,
            o,
        )?;
        to_pixels(&d, o.min_disparity)
    };
    run().map_err(|e| format!("OpenCV: {e}"))
}
