//! V4L2 cameras through the `v4l` crate: open by path or by the stable `/dev/v4l/by-id`
//! name, negotiate pixel format and size, set exposure and gain, stream through mmap
//! buffers and dequeue with a timeout (an unplugged camera never blocks forever), decode
//! to pixels (MJPG kept as the camera's JPEG), keep the driver's timestamp and sequence.
//! The parts that need no device (negotiation, controls, timestamps, decoding) are plain
//! functions, unit-tested without hardware.

use super::camera::{
    Camera, CameraError, CameraInfo, CameraSettings, Frame, FrameData, PixelFormat,
};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use v4l::buffer::Type;
use v4l::io::mmap::Stream as MmapStream;
use v4l::io::traits::CaptureStream;
use v4l::video::Capture;
use v4l::{Device, FourCC};

/// V4L2 control ids (linux/v4l2-controls.h).
pub const CID_GAIN: u32 = 0x0098_0913;
pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
/// `V4L2_EXPOSURE_MANUAL` and `V4L2_EXPOSURE_APERTURE_PRIORITY` of the auto-exposure menu
pub const EXPOSURE_MANUAL: i64 = 1;
pub const EXPOSURE_APERTURE_PRIORITY: i64 = 3;

/// Picks the format and size to ask for: the wanted format at the wanted size if the
/// device has it, else the wanted size in another format the station reads (MJPG, YUYV,
/// GREY, in that order), else an error listing what the device offers.
///
/// - `offered`: (format, sizes) pairs the device advertises
pub fn choose_format(
    offered: &[(PixelFormat, Vec<(u32, u32)>)],
    want: &CameraSettings,
) -> Result<(PixelFormat, u32, u32), String> {
    let has = |f: PixelFormat| {
        offered
            .iter()
            .any(|(g, sizes)| *g == f && sizes.contains(&(want.width, want.height)))
    };
    if has(want.format) {
        return Ok((want.format, want.width, want.height));
    }
    for f in [PixelFormat::Mjpg, PixelFormat::Yuyv, PixelFormat::Grey] {
        if has(f) {
            return Ok((f, want.width, want.height));
        }
    }
    let list: Vec<String> = offered
        .iter()
        .map(|(f, s)| {
            format!(
                "{f:?} {}",
                s.iter()
                    .map(|(w, h)| format!("{w}x{h}"))
                    .collect::<Vec<_>>()
                    .join(" ")
            )
        })
        .collect();
    Err(format!(
        "{}x{} is not offered (the device has: {})",
        want.width,
        want.height,
        if list.is_empty() {
            "nothing the station reads".into()
        } else {
            list.join("; ")
        }
    ))
}

/// The control writes for the settings: manual exposure in the driver's units of 100 us,
/// or aperture-priority automatic exposure; gain when asked.
pub fn control_writes(s: &CameraSettings) -> Vec<(u32, i64)> {
    let mut w = Vec::new();
    match s.exposure_us {
        Some(us) => {
            w.push((CID_EXPOSURE_AUTO, EXPOSURE_MANUAL));
            w.push((CID_EXPOSURE_ABSOLUTE, (us as i64 / 100).max(1)));
        }
        None => w.push((CID_EXPOSURE_AUTO, EXPOSURE_APERTURE_PRIORITY)),
    }
    if let Some(g) = s.gain {
        w.push((CID_GAIN, g));
    }
    w
}

/// A driver timestamp (seconds, microseconds of CLOCK_MONOTONIC) as a duration.
pub fn timestamp(sec: i64, usec: i64) -> Duration {
    if sec < 0 || usec < 0 {
        return Duration::ZERO;
    }
    Duration::from_secs(sec as u64) + Duration::from_micros(usec as u64)
}

/// YUYV 4:2:2 to RGB (BT.601, limited range).
pub fn yuyv_to_rgb(data: &[u8], width: u32, height: u32) -> Result<Vec<u8>, String> {
    let need = (width * height * 2) as usize;
    if data.len() < need {
        return Err(format!(
            "YUYV frame of {} bytes, {need} expected",
            data.len()
        ));
    }
    let mut out = Vec::with_capacity((width * height * 3) as usize);
    for px in data[..need].chunks_exact(4) {
        let (y0, u, y1, v) = (
            px[0] as f32,
            px[1] as f32 - 128.0,
            px[2] as f32,
            px[3] as f32 - 128.0,
        );
        for y in [y0, y1] {
            let c = 1.164 * (y - 16.0);
            out.push((c + 1.596 * v).round().clamp(0.0, 255.0) as u8);
            out.push((c - 0.392 * u - 0.813 * v).round().clamp(0.0, 255.0) as u8);
            out.push((c + 2.017 * u).round().clamp(0.0, 255.0) as u8);
        }
    }
    Ok(out)
}

/// A dequeued buffer as frame pixels.
pub fn decode(
    format: PixelFormat,
    data: &[u8],
    width: u32,
    height: u32,
) -> Result<FrameData, String> {
    match format {
        PixelFormat::Mjpg => {
            if data.len() < 4 || data[0] != 0xff || data[1] != 0xd8 {
                return Err("MJPG buffer is not a JPEG".into());
            }
            Ok(FrameData::Jpeg(data.to_vec()))
        }
        PixelFormat::Yuyv => yuyv_to_rgb(data, width, height).map(FrameData::Rgb8),
        PixelFormat::Grey => {
            let need = (width * height) as usize;
            if data.len() < need {
                return Err(format!(
                    "GREY frame of {} bytes, {need} expected",
                    data.len()
                ));
            }
            Ok(FrameData::Gray8(data[..need].to_vec()))
        }
    }
}

/// Resolves a camera name: a path as it is, or a name under `/dev/v4l/by-id/`.
pub fn resolve(name: &str) -> PathBuf {
    let p = Path::new(name);
    if p.is_absolute() || name.starts_with('.') {
        p.to_path_buf()
    } else {
        Path::new("/dev/v4l/by-id").join(name)
    }
}

/// A V4L2 camera.
pub struct V4l2Camera {
    info: CameraInfo,
    path: PathBuf,
    dev: Device,
    stream: Option<MmapStream<'static>>,
    format: (PixelFormat, u32, u32),
    exposure_us: Option<u32>,
    last_sequence: Option<u32>,
}

/// Frame sizes (width, height) a camera offers for one format.
pub type Sizes = Vec<(u32, u32)>;

impl V4l2Camera {
    /// Opens `/dev/videoN`, another path, or a `/dev/v4l/by-id` name.
    pub fn open(info: CameraInfo, name: &str) -> Result<Self, CameraError> {
        let path = resolve(name);
        let dev = Device::with_path(&path).map_err(|e| CameraError::Device {
            camera: info.id.clone(),
            msg: format!("{}: {e}", path.display()),
        })?;
        Ok(V4l2Camera {
            info,
            path,
            dev,
            stream: None,
            format: (PixelFormat::Mjpg, 0, 0),
            exposure_us: None,
            last_sequence: None,
        })
    }

    fn err(&self, msg: impl std::fmt::Display) -> CameraError {
        CameraError::Device {
            camera: self.info.id.clone(),
            msg: format!("{}: {msg}", self.path.display()),
        }
    }

    /// What the device offers in the formats the station reads.
    pub fn offered(dev: &Device) -> std::io::Result<Vec<(PixelFormat, Sizes)>> {
        let mut out = Vec::new();
        for d in dev.enum_formats()? {
            let Some(f) = PixelFormat::from_fourcc(&d.fourcc.repr) else {
                continue;
            };
            let mut sizes = Vec::new();
            for s in dev.enum_framesizes(d.fourcc).unwrap_or_default() {
                sizes.extend(
                    s.size
                        .to_discrete()
                        .into_iter()
                        .map(|d| (d.width, d.height)),
                );
            }
            out.push((f, sizes));
        }
        Ok(out)
    }
}

impl Camera for V4l2Camera {
    fn info(&self) -> &CameraInfo {
        &self.info
    }

    fn configure(&mut self, s: &CameraSettings) -> Result<(), CameraError> {
        let offered = Self::offered(&self.dev).map_err(|e| self.err(e))?;
        let (f, w, h) = choose_format(&offered, s).map_err(|m| CameraError::Settings {
            camera: self.info.id.clone(),
            msg: m,
        })?;
        let mut fmt = self.dev.format().map_err(|e| self.err(e))?;
        fmt.width = w;
        fmt.height = h;
        fmt.fourcc = FourCC::new(&f.fourcc());
        let got = self.dev.set_format(&fmt).map_err(|e| self.err(e))?;
        if (got.width, got.height) != (w, h) || got.fourcc.repr != f.fourcc() {
            return Err(CameraError::Settings {
                camera: self.info.id.clone(),
                msg: format!(
                    "asked for {f:?} {w}x{h}, the driver gave {} {}x{}",
                    got.fourcc, got.width, got.height
                ),
            });
        }
        for (id, value) in control_writes(s) {
            // cameras without a control (no gain, fixed exposure) are not an error
            let _ = self.dev.set_control(v4l::Control {
                id,
                value: v4l::control::Value::Integer(value),
            });
        }
        self.format = (f, w, h);
        self.exposure_us = s.exposure_us;
        Ok(())
    }

    fn arm(&mut self) -> Result<(), CameraError> {
        // a fresh stream: no stale frame from before the trigger is taken
        self.stream = None;
        let stream =
            MmapStream::with_buffers(&self.dev, Type::VideoCapture, 4).map_err(|e| self.err(e))?;
        self.stream = Some(stream);
        self.last_sequence = None;
        Ok(())
    }

    fn grab(&mut self, deadline: Instant) -> Result<Frame, CameraError> {
        let start = Instant::now();
        let left = deadline.saturating_duration_since(start);
        let (f, w, h) = self.format;
        let camera = self.info.id.clone();
        let stream = self.stream.as_mut().ok_or_else(|| CameraError::Device {
            camera: camera.clone(),
            msg: "grab before arm".into(),
        })?;
        stream.set_timeout(left.max(Duration::from_millis(1)));
        let (buf, meta) = match stream.next() {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                return Err(CameraError::Timeout {
                    camera,
                    waited_ms: start.elapsed().as_millis() as u64,
                });
            }
            Err(e) => {
                return Err(CameraError::Device {
                    camera,
                    msg: e.to_string(),
                });
            }
        };
        let used = (meta.bytesused as usize).min(buf.len());
        let data = decode(f, &buf[..used], w, h).map_err(|m| CameraError::Device {
            camera: camera.clone(),
            msg: m,
        })?;
        let sequence = meta.sequence;
        if let Some(prev) = self.last_sequence
            && sequence != prev.wrapping_add(1)
        {
            self.last_sequence = Some(sequence);
            return Err(CameraError::LostFrame {
                camera,
                expected: prev.wrapping_add(1),
                got: sequence,
            });
        }
        self.last_sequence = Some(sequence);
        Ok(Frame {
            camera,
            width: w,
            height: h,
            data,
            sensor_time: timestamp(meta.timestamp.sec, meta.timestamp.usec),
            sequence,
            exposure_us: self.exposure_us,
        })
    }

    fn close(&mut self) {
        self.stream = None;
    }
}

/// One V4L2 device as `conformd cameras` lists it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DeviceListing {
    pub path: PathBuf,
    pub by_id: Vec<String>,
    pub name: String,
    pub driver: String,
    pub formats: Vec<String>,
    pub controls: Vec<String>,
}

impl std::fmt::Display for DeviceListing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} ({}, driver {})",
            self.path.display(),
            self.name,
            self.driver
        )?;
        for b in &self.by_id {
            write!(f, "\n  by-id: /dev/v4l/by-id/{b}")?;
        }
        for x in &self.formats {
            write!(f, "\n  format {x}")?;
        }
        for c in &self.controls {
            write!(f, "\n  control {c}")?;
        }
        Ok(())
    }
}

/// Lists V4L2 capture devices with their stable names, formats, sizes and controls.
pub fn list_devices() -> Vec<DeviceListing> {
    let by_id: Vec<(PathBuf, String)> = std::fs::read_dir("/dev/v4l/by-id")
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    std::fs::canonicalize(e.path())
                        .ok()
                        .map(|t| (t, e.file_name().to_string_lossy().to_string()))
                })
                .collect()
        })
        .unwrap_or_default();
    let mut out = Vec::new();
    for node in v4l::context::enum_devices() {
        let path = node.path().to_path_buf();
        let Ok(dev) = Device::with_path(&path) else {
            continue;
        };
        let Ok(caps) = dev.query_caps() else { continue };
        let mut formats = Vec::new();
        for d in dev.enum_formats().unwrap_or_default() {
            let sizes: Vec<String> = dev
                .enum_framesizes(d.fourcc)
                .unwrap_or_default()
                .into_iter()
                .flat_map(|s| {
                    s.size
                        .to_discrete()
                        .into_iter()
                        .map(|x| format!("{}x{}", x.width, x.height))
                        .collect::<Vec<_>>()
                })
                .collect();
            formats.push(format!(
                "{} ({}): {}",
                d.fourcc,
                d.description,
                sizes.join(" ")
            ));
        }
        let controls = dev
            .query_controls()
            .unwrap_or_default()
            .into_iter()
            .map(|c| {
                format!(
                    "{} [{}..{}, default {}]",
                    c.name, c.minimum, c.maximum, c.default
                )
            })
            .collect();
        let canon = std::fs::canonicalize(&path).unwrap_or(path.clone());
        out.push(DeviceListing {
            by_id: by_id
                .iter()
                .filter(|(t, _)| *t == canon)
                .map(|(_, n)| n.clone())
                .collect(),
            path,
            name: caps.card,
            driver: caps.driver,
            formats,
            controls,
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn want(f: PixelFormat, w: u32, h: u32) -> CameraSettings {
        CameraSettings {
            format: f,
            width: w,
            height: h,
            ..Default::default()
        }
    }

    #[test]
    fn format_negotiation() {
        let offered = vec![
            (PixelFormat::Yuyv, vec![(640, 480), (1280, 960)]),
            (PixelFormat::Mjpg, vec![(1280, 960), (1920, 1080)]),
        ];
        assert_eq!(
            choose_format(&offered, &want(PixelFormat::Yuyv, 1280, 960)),
            Ok((PixelFormat::Yuyv, 1280, 960))
        );
        assert_eq!(
            choose_format(&offered, &want(PixelFormat::Grey, 1280, 960)),
            Ok((PixelFormat::Mjpg, 1280, 960))
        );
        assert_eq!(
            choose_format(&offered, &want(PixelFormat::Mjpg, 640, 480)),
            Ok((PixelFormat::Yuyv, 640, 480))
        );
        let e = choose_format(&offered, &want(PixelFormat::Mjpg, 800, 600)).unwrap_err();
        assert!(
            e.contains("800x600 is not offered") && e.contains("Mjpg 1280x960 1920x1080"),
            "{e}"
        );
    }

    #[test]
    fn controls_and_timestamps() {
        let s = CameraSettings {
            exposure_us: Some(8000),
            gain: Some(4),
            ..Default::default()
        };
        assert_eq!(
            control_writes(&s),
            vec![
                (CID_EXPOSURE_AUTO, 1),
                (CID_EXPOSURE_ABSOLUTE, 80),
                (CID_GAIN, 4)
            ]
        );
        assert_eq!(
            control_writes(&CameraSettings::default()),
            vec![(CID_EXPOSURE_AUTO, 3)]
        );
        assert_eq!(timestamp(12, 345_678), Duration::from_micros(12_345_678));
        assert_eq!(timestamp(-1, 0), Duration::ZERO);
    }

    #[test]
    fn decoding() {
        // two pixels, grey-ish: Y=128, U=V=128 -> R=G=B
        let rgb = yuyv_to_rgb(&[128, 128, 128, 128], 2, 1).unwrap();
        assert_eq!(rgb.len(), 6);
        assert!(rgb.iter().all(|&c| c == rgb[0]));
        assert!(
            yuyv_to_rgb(&[1, 2, 3], 2, 1)
                .unwrap_err()
                .contains("3 bytes")
        );
        assert!(matches!(
            decode(PixelFormat::Mjpg, &[0xff, 0xd8, 0, 0], 1, 1),
            Ok(FrameData::Jpeg(_))
        ));
        assert!(
            decode(PixelFormat::Mjpg, &[0, 0, 0, 0], 1, 1)
                .unwrap_err()
                .contains("not a JPEG")
        );
        assert!(decode(PixelFormat::Grey, &[1, 2], 2, 2).is_err());
        assert_eq!(
            resolve("usb-cam0-video-index0"),
            PathBuf::from("/dev/v4l/by-id/usb-cam0-video-index0")
        );
        assert_eq!(resolve("/dev/video2"), PathBuf::from("/dev/video2"));
    }
}
