//! What every camera does (open, configure, arm, grab one frame with a deadline, close),
//! and what a frame is: pixels (or the camera's own JPEG), the sensor's timestamp and
//! sequence number, the exposure it was taken with.

use std::path::Path;
use std::time::{Duration, Instant};

/// Where a camera sits in the rig.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraInfo {
    /// stable name in the station config (e.g. `pod1-left`)
    pub id: String,
    /// stereo pod it belongs to
    pub pod: String,
    /// `left` or `right` within the pod
    pub side: String,
}

/// Pixel formats a station uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum PixelFormat {
    Mjpg,
    Yuyv,
    Grey,
}

impl PixelFormat {
    pub fn fourcc(self) -> [u8; 4] {
        match self {
            PixelFormat::Mjpg => *b"MJPG",
            PixelFormat::Yuyv => *b"YUYV",
            PixelFormat::Grey => *b"GREY",
        }
    }
    pub fn from_fourcc(f: &[u8; 4]) -> Option<PixelFormat> {
        match f {
            b"MJPG" => Some(PixelFormat::Mjpg),
            b"YUYV" => Some(PixelFormat::Yuyv),
            b"GREY" => Some(PixelFormat::Grey),
            _ => None,
        }
    }
}

/// What a camera is asked for before a capture.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraSettings {
    pub format: PixelFormat,
    pub width: u32,
    pub height: u32,
    /// exposure in microseconds (None: the camera's automatic exposure)
    pub exposure_us: Option<u32>,
    /// analogue gain in the camera's own units
    pub gain: Option<i64>,
    /// wait for the trigger box's pulse (true) or free-run and take the next frame
    pub external_trigger: bool,
}

impl Default for CameraSettings {
    fn default() -> Self {
        CameraSettings {
            format: PixelFormat::Mjpg,
            width: 1280,
            height: 960,
            exposure_us: None,
            gain: None,
            external_trigger: false,
        }
    }
}

/// Pixels as they came.
#[derive(Debug, Clone, PartialEq)]
pub enum FrameData {
    /// the camera's own JPEG (MJPG), kept byte for byte
    Jpeg(Vec<u8>),
    Gray8(Vec<u8>),
    Rgb8(Vec<u8>),
}

/// One frame from one camera.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub camera: String,
    pub width: u32,
    pub height: u32,
    pub data: FrameData,
    /// the sensor's (driver's) timestamp: comparable between cameras of one host
    pub sensor_time: Duration,
    pub sequence: u32,
    pub exposure_us: Option<u32>,
}

impl Frame {
    /// The file extension this frame is stored with.
    pub fn extension(&self) -> &'static str {
        match self.data {
            FrameData::Jpeg(_) => "jpg",
            _ => "png",
        }
    }

    /// The bytes of the file (JPEG as delivered; PNG otherwise).
    pub fn encode(&self) -> Result<Vec<u8>, CameraError> {
        let png = |ct: image::ExtendedColorType, px: &[u8]| -> Result<Vec<u8>, CameraError> {
            let mut out = Vec::new();
            image::ImageEncoder::write_image(
                image::codecs::png::PngEncoder::new(&mut out),
                px,
                self.width,
                self.height,
                ct,
            )
            .map_err(|e| CameraError::Encode {
                camera: self.camera.clone(),
                msg: e.to_string(),
            })?;
            Ok(out)
        };
        match &self.data {
            FrameData::Jpeg(b) => Ok(b.clone()),
            FrameData::Gray8(px) => png(image::ExtendedColorType::L8, px),
            FrameData::Rgb8(px) => png(image::ExtendedColorType::Rgb8, px),
        }
    }
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    #[error("camera {camera}: no frame within {waited_ms} ms{}", stale_note(*stale))]
    Timeout {
        camera: String,
        waited_ms: u64,
        /// frames exposed before the trigger that came and were dropped
        stale: u32,
    },
    #[error("camera {camera}: frame {expected} was lost (the next one was {got})")]
    LostFrame {
        camera: String,
        expected: u32,
        got: u32,
    },
    #[error("camera {camera}: {msg}")]
    Device { camera: String, msg: String },
    #[error("camera {camera}: {msg}")]
    Settings { camera: String, msg: String },
    #[error("camera {camera}: encoding the frame: {msg}")]
    Encode { camera: String, msg: String },
}

fn stale_note(stale: u32) -> String {
    match stale {
        0 => String::new(),
        n => format!(" after the trigger ({n} from before it dropped)"),
    }
}

/// A camera of the rig.
pub trait Camera: Send {
    fn info(&self) -> &CameraInfo;
    /// Applies pixel format, size, exposure, gain and trigger mode.
    fn configure(&mut self, settings: &CameraSettings) -> Result<(), CameraError>;
    /// Gets ready for the trigger: streaming started, frames already waiting dropped, so
    /// the next frame is one the trigger made.
    fn arm(&mut self) -> Result<(), CameraError>;
    /// Returns the first frame exposed at or after `fired_at` (the trigger's moment on
    /// [`monotonic_now`]'s clock), or an error once `deadline` has passed; never blocks
    /// beyond it (an unplugged camera must not hang the station). A frame from before
    /// the trigger is never returned.
    fn grab(&mut self, fired_at: Duration, deadline: Instant) -> Result<Frame, CameraError>;
    /// Stops streaming; the camera can be armed again.
    fn close(&mut self);
}

/// Now on CLOCK_MONOTONIC, the clock V4L2 drivers stamp frames with, so a trigger's
/// moment and a frame's timestamp compare.
pub fn monotonic_now() -> Duration {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::Monotonic);
    Duration::new(
        t.tv_sec.max(0) as u64,
        t.tv_nsec.clamp(0, 999_999_999) as u32,
    )
}

/// Reads an image file into frame pixels: JPEG kept as is, anything else decoded to
/// grey or RGB.
pub fn frame_from_file(camera: &str, path: &Path) -> Result<(u32, u32, FrameData), CameraError> {
    let err = |msg: String| CameraError::Device {
        camera: camera.into(),
        msg,
    };
    let bytes = crate::files::read_limited(path, crate::files::MAX_IMAGE_BYTES)
        .map_err(|e| err(e.to_string()))?;
    let img = image::load_from_memory(&bytes)
        .map_err(|e| err(format!("{}: not a readable image: {e}", path.display())))?;
    let (w, h) = (img.width(), img.height());
    let is_jpeg = bytes.starts_with(&[0xff, 0xd8]);
    let data = if is_jpeg {
        FrameData::Jpeg(bytes)
    } else if img.color().channel_count() == 1 {
        FrameData::Gray8(img.to_luma8().into_raw())
    } else {
        FrameData::Rgb8(img.to_rgb8().into_raw())
    };
    Ok((w, h, data))
}
