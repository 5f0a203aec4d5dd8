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
use v4l::io::traits::{CaptureStream, Stream as StreamControl};
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
) -> Result<(PixelFormat, u32, u32), FormatError> {
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
    Err(FormatError::NotOffered {
        width: want.width,
        height: want.height,
        has: if list.is_empty() {
            "nothing the station reads".into()
        } else {
            list.join("; ")
        },
    })
}

/// Why a camera's format cannot be set or a buffer read as a frame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FormatError {
    #[error("{width}x{height} is not offered (the device has: {has})")]
    NotOffered {
        width: u32,
        height: u32,
        has: String,
    },
    #[error("MJPG buffer is not a JPEG")]
    NotJpeg,
    #[error("{format} frame of {got} bytes, {need} expected")]
    Short {
        format: &'static str,
        got: usize,
        need: usize,
    },
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
pub fn yuyv_to_rgb(data: &[u8], width: u32, height: u32) -> Result<Vec<u8>, FormatError> {
    let need = (width * height * 2) as usize;
    if data.len() < need {
        return Err(FormatError::Short {
            format: "YUYV",
            got: data.len(),
            need,
        });
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
) -> Result<FrameData, FormatError> {
    match format {
        PixelFormat::Mjpg => {
            if data.len() < 4 || data[0] != 0xff || data[1] != 0xd8 {
                return Err(FormatError::NotJpeg);
            }
            Ok(FrameData::Jpeg(data.to_vec()))
        }
        PixelFormat::Yuyv => yuyv_to_rgb(data, width, height).map(FrameData::Rgb8),
        PixelFormat::Grey => {
            let need = (width * height) as usize;
            if data.len() < need {
                return Err(FormatError::Short {
                    format: "GREY",
                    got: data.len(),
                    need,
                });
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

/// What the camera needs of a device's capture queue, as a V4L2 driver behaves: `start`
/// requests the buffers, queues them and turns streaming on (VIDIOC_STREAMON), so a
/// trigger pulse after it fills a buffer and one before it is lost; sequence numbers count
/// from 0 at `start`; `next` dequeues the next filled buffer within a time limit; `stop`
/// turns streaming off and frees the buffers. The real one is the `v4l` crate's mmap
/// stream; `synth::v4l2_driver` simulates a driver (triggered or free-running) for tests.
pub trait CaptureQueue: Send {
    /// Streaming is on when this returns.
    fn start(&mut self) -> std::io::Result<()>;
    /// the next buffer's bytes in use and its driver metadata; `TimedOut` when none
    /// was filled within `timeout` (zero: only one already waiting)
    fn next(&mut self, timeout: Duration) -> std::io::Result<(Vec<u8>, BufferMeta)>;
    fn stop(&mut self);
}

/// The driver's metadata of one dequeued buffer.
#[derive(Debug, Clone, Copy)]
pub struct BufferMeta {
    pub sequence: u32,
    pub sec: i64,
    pub usec: i64,
    /// the timestamp is CLOCK_MONOTONIC's (V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC), so it
    /// compares with the trigger's moment
    pub monotonic: bool,
}

/// Buffers asked of the driver at each start.
const BUFFERS: u32 = 5;
/// `POLLIN` of poll(2)
const POLLIN: i16 = 0x001;
/// V4L2_BUF_FLAG_TIMESTAMP_MASK and _MONOTONIC
const TIMESTAMP_MASK: u32 = 0xe000;
const TIMESTAMP_MONOTONIC: u32 = 0x2000;

/// A device's mmap buffers, made and streamed at each start.
struct MmapQueue {
    dev: std::sync::Arc<Device>,
    stream: Option<MmapStream<'static>>,
}

impl CaptureQueue for MmapQueue {
    fn start(&mut self) -> std::io::Result<()> {
        self.stop();
        let mut stream = MmapStream::with_buffers(&self.dev, Type::VideoCapture, BUFFERS)?;
        // The crate's `next` queues the buffer it handed out last before dequeuing, and
        // takes buffer 0 for that one once streaming is on: buffer 0 waits outside the
        // queue until the first frame is taken, every other one is queued now.
        for index in 1..BUFFERS as usize {
            CaptureStream::queue(&mut stream, index)?;
        }
        // VIDIOC_STREAMON: from here a trigger pulse fills a buffer
        StreamControl::start(&mut stream)?;
        self.stream = Some(stream);
        Ok(())
    }

    fn next(&mut self, timeout: Duration) -> std::io::Result<(Vec<u8>, BufferMeta)> {
        let stream = self
            .stream
            .as_mut()
            .ok_or_else(|| std::io::Error::other("grab before arm"))?;
        // Wait here, not inside the crate's `next`: a time-out there leaves the buffer it
        // queued counted as handed out, and the next call would queue it twice.
        let ms = timeout.as_millis().min(i32::MAX as u128) as i32;
        if stream.handle().poll(POLLIN, ms)? == 0 {
            return Err(std::io::ErrorKind::TimedOut.into());
        }
        stream.set_timeout(timeout.max(Duration::from_millis(1)));
        let taken = stream.next().map(|(buf, meta)| {
            let used = (meta.bytesused as usize).min(buf.len());
            (
                buf[..used].to_vec(),
                BufferMeta {
                    sequence: meta.sequence,
                    sec: meta.timestamp.sec,
                    usec: meta.timestamp.usec,
                    monotonic: meta.flags.bits() & TIMESTAMP_MASK == TIMESTAMP_MONOTONIC,
                },
            )
        });
        if taken.is_err() {
            // the queue's state is unknown after a failed dequeue: arming starts afresh
            self.stop();
        }
        taken
    }

    fn stop(&mut self) {
        // dropping the stream turns streaming off (VIDIOC_STREAMOFF) and unmaps
        self.stream = None;
    }
}

/// A V4L2 camera.
pub struct V4l2Camera {
    info: CameraInfo,
    path: PathBuf,
    /// shared with the capture queue, which streams from it; none for a camera over a
    /// simulated driver, whose format is fixed
    dev: Option<std::sync::Arc<Device>>,
    frames: FrameStream,
}

/// Frames the queue may hold at arming, dropped then (more means a camera faster than
/// the station can drain: the rest are dropped by the trigger time check).
const DRAIN_AT_MOST: u32 = 4 * BUFFERS;

/// The part of a camera that turns dequeued buffers into frames: streaming started at
/// arming, frames from before the trigger dropped (by the driver's timestamp), decoding,
/// and the sequence check (a frame lost since arming, or between two grabs of one arming,
/// is an error, not a silently later frame).
struct FrameStream {
    camera: String,
    queue: Box<dyn CaptureQueue>,
    armed: bool,
    format: (PixelFormat, u32, u32),
    exposure_us: Option<u32>,
    /// the sequence number the next frame must carry; none after frames from before the
    /// trigger were dropped (a frame lost then was nobody's)
    expected: Option<u32>,
    /// frames from before the trigger dropped since arming
    stale: u32,
}

impl FrameStream {
    fn arm(&mut self) -> std::io::Result<()> {
        self.armed = false;
        self.queue.start()?;
        self.expected = Some(0);
        self.stale = 0;
        // anything a free-running camera filled since STREAMON is from before the trigger
        while self.stale < DRAIN_AT_MOST {
            match self.queue.next(Duration::ZERO) {
                Ok(_) => {
                    self.stale += 1;
                    self.expected = None;
                }
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => break,
                Err(e) => return Err(e),
            }
        }
        self.armed = true;
        Ok(())
    }

    fn grab(
        &mut self,
        fired_at: Duration,
        deadline: Instant,
        path: &Path,
    ) -> Result<Frame, CameraError> {
        let start = Instant::now();
        let (f, w, h) = self.format;
        let camera = self.camera.clone();
        let device = |msg: String| CameraError::Device {
            camera: camera.clone(),
            msg: format!("{}: {msg}", path.display()),
        };
        if !self.armed {
            return Err(device("grab before arm".into()));
        }
        let timeout = |stale| CameraError::Timeout {
            camera: camera.clone(),
            waited_ms: start.elapsed().as_millis() as u64,
            stale,
        };
        // drivers stamp in whole microseconds: a frame of the trigger's own microsecond is its
        let fired_at = Duration::from_micros(fired_at.as_micros() as u64);
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let (bytes, meta) = match self.queue.next(left.max(Duration::from_millis(1))) {
                Ok(x) => x,
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                    return Err(timeout(self.stale));
                }
                Err(e) => return Err(device(e.to_string())),
            };
            if !meta.monotonic {
                return Err(device(
                    "the driver's frame timestamps are not CLOCK_MONOTONIC's, so a frame cannot be told from one taken before the trigger".into(),
                ));
            }
            let sensor_time = timestamp(meta.sec, meta.usec);
            let sequence = meta.sequence;
            if sensor_time < fired_at {
                self.stale += 1;
                self.expected = None;
                if Instant::now() >= deadline {
                    return Err(timeout(self.stale));
                }
                continue;
            }
            let expected = self.expected;
            self.expected = Some(sequence.wrapping_add(1));
            if let Some(expected) = expected
                && sequence != expected
            {
                return Err(CameraError::LostFrame {
                    camera,
                    expected,
                    got: sequence,
                });
            }
            let data = decode(f, &bytes, w, h).map_err(|e| device(e.to_string()))?;
            return Ok(Frame {
                camera,
                width: w,
                height: h,
                data,
                sensor_time,
                sequence,
                exposure_us: self.exposure_us,
            });
        }
    }
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
        let dev = std::sync::Arc::new(dev);
        let queue = MmapQueue {
            dev: dev.clone(),
            stream: None,
        };
        let mut camera =
            V4l2Camera::with_queue(info, path, Box::new(queue), PixelFormat::Mjpg, 0, 0);
        camera.dev = Some(dev);
        Ok(camera)
    }

    /// A camera over another capture queue (a simulated driver in the tests) whose
    /// frames are `format` at `width` x `height`; `path` names it in errors.
    pub fn with_queue(
        info: CameraInfo,
        path: PathBuf,
        queue: Box<dyn CaptureQueue>,
        format: PixelFormat,
        width: u32,
        height: u32,
    ) -> Self {
        V4l2Camera {
            frames: FrameStream {
                camera: info.id.clone(),
                queue,
                armed: false,
                format: (format, width, height),
                exposure_us: None,
                expected: Some(0),
                stale: 0,
            },
            info,
            path,
            dev: None,
        }
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
        let Some(dev) = self.dev.clone() else {
            // a queue of fixed format: the settings must ask for it
            let (f, w, h) = self.frames.format;
            if (s.width, s.height) != (w, h) {
                return Err(CameraError::Settings {
                    camera: self.info.id.clone(),
                    msg: format!(
                        "{}x{} was asked for; the queue gives {f:?} {w}x{h}",
                        s.width, s.height
                    ),
                });
            }
            self.frames.exposure_us = s.exposure_us;
            return Ok(());
        };
        let offered = Self::offered(&dev).map_err(|e| self.err(e))?;
        let (f, w, h) = choose_format(&offered, s).map_err(|e| CameraError::Settings {
            camera: self.info.id.clone(),
            msg: e.to_string(),
        })?;
        let mut fmt = dev.format().map_err(|e| self.err(e))?;
        fmt.width = w;
        fmt.height = h;
        fmt.fourcc = FourCC::new(&f.fourcc());
        let got = dev.set_format(&fmt).map_err(|e| self.err(e))?;
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
            let _ = dev.set_control(v4l::Control {
                id,
                value: v4l::control::Value::Integer(value),
            });
        }
        self.frames.format = (f, w, h);
        self.frames.exposure_us = s.exposure_us;
        Ok(())
    }

    fn arm(&mut self) -> Result<(), CameraError> {
        self.frames.arm().map_err(|e| self.err(e))
    }

    fn grab(&mut self, fired_at: Duration, deadline: Instant) -> Result<Frame, CameraError> {
        self.frames.grab(fired_at, deadline, &self.path)
    }

    fn close(&mut self) {
        self.frames.queue.stop();
        self.frames.armed = false;
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
    list_all().0
}

/// [`list_devices`], and the video device nodes that could not be queried, each with
/// why (a node the station's user may not open, one that is not a V4L2 device).
pub fn list_all() -> (Vec<DeviceListing>, Vec<(PathBuf, String)>) {
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
    let mut unusable = Vec::new();
    for node in v4l::context::enum_devices() {
        let path = node.path().to_path_buf();
        let dev = match Device::with_path(&path) {
            Ok(d) => d,
            Err(e) => {
                let hint = if e.kind() == std::io::ErrorKind::PermissionDenied {
                    " (the station's user must be in the device's group, usually video)"
                } else {
                    ""
                };
                unusable.push((path, format!("cannot be opened: {e}{hint}")));
                continue;
            }
        };
        let caps = match dev.query_caps() {
            Ok(c) => c,
            Err(e) => {
                unusable.push((path, format!("is not a V4L2 device that answers: {e}")));
                continue;
            }
        };
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
    (out, unusable)
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
        let e = choose_format(&offered, &want(PixelFormat::Mjpg, 800, 600))
            .unwrap_err()
            .to_string();
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

    /// The device layer faked: buffers with chosen sequence numbers and times, timeouts,
    /// errors. Buffers before a `None` are what the queue holds when it starts (a
    /// free-running camera's frames since STREAMON); the rest come one per `next`.
    struct FakeQueue {
        at_start: usize,
        buffers: std::collections::VecDeque<std::io::Result<(Vec<u8>, BufferMeta)>>,
        streaming: bool,
    }

    impl CaptureQueue for FakeQueue {
        fn start(&mut self) -> std::io::Result<()> {
            self.streaming = true;
            Ok(())
        }
        fn next(&mut self, timeout: Duration) -> std::io::Result<(Vec<u8>, BufferMeta)> {
            if !self.streaming {
                return Err(std::io::ErrorKind::TimedOut.into());
            }
            if timeout.is_zero() {
                // only what was already waiting
                if self.at_start == 0 {
                    return Err(std::io::ErrorKind::TimedOut.into());
                }
                self.at_start -= 1;
            } else {
                self.at_start = self.at_start.saturating_sub(1);
            }
            self.buffers
                .pop_front()
                .unwrap_or_else(|| Err(std::io::ErrorKind::TimedOut.into()))
        }
        fn stop(&mut self) {
            self.streaming = false;
        }
    }

    /// A 2x2 grey frame exposed at `at` seconds.
    fn grey_at(sequence: u32, at: f64) -> std::io::Result<(Vec<u8>, BufferMeta)> {
        Ok((
            vec![7; 4],
            BufferMeta {
                sequence,
                sec: at.trunc() as i64,
                usec: (at.fract() * 1e6).round() as i64,
                monotonic: true,
            },
        ))
    }

    fn grey(sequence: u32) -> std::io::Result<(Vec<u8>, BufferMeta)> {
        grey_at(sequence, 100.5)
    }

    fn stream_holding(
        at_start: usize,
        buffers: Vec<std::io::Result<(Vec<u8>, BufferMeta)>>,
    ) -> FrameStream {
        FrameStream {
            camera: "cam0".into(),
            queue: Box::new(FakeQueue {
                at_start,
                buffers: buffers.into(),
                streaming: false,
            }),
            armed: false,
            format: (PixelFormat::Grey, 2, 2),
            exposure_us: Some(800),
            expected: Some(0),
            stale: 0,
        }
    }

    fn stream(buffers: Vec<std::io::Result<(Vec<u8>, BufferMeta)>>) -> FrameStream {
        stream_holding(0, buffers)
    }

    /// The trigger's moment in these tests: 100 s on the monotonic clock.
    const FIRED: Duration = Duration::from_secs(100);

    #[test]
    fn a_frame_lost_on_the_device_is_an_error() {
        let path = Path::new("/dev/video9");
        let soon = || Instant::now() + Duration::from_millis(50);
        // one arming, several grabs: 0 and 1 arrive, 2 is lost
        let mut s = stream(vec![grey(0), grey(1), grey(3), grey(4)]);
        assert!(
            s.grab(FIRED, soon(), path)
                .unwrap_err()
                .to_string()
                .contains("grab before arm")
        );
        s.arm().unwrap();
        let f = s.grab(FIRED, soon(), path).unwrap();
        assert_eq!((f.sequence, f.width, f.exposure_us), (0, 2, Some(800)));
        assert_eq!(f.sensor_time, Duration::from_millis(100_500));
        assert!(matches!(f.data, FrameData::Gray8(ref p) if p == &vec![7; 4]));
        assert_eq!(s.grab(FIRED, soon(), path).unwrap().sequence, 1);
        match s.grab(FIRED, soon(), path) {
            Err(CameraError::LostFrame {
                expected: 2,
                got: 3,
                ..
            }) => {}
            other => panic!("expected a lost frame, got {other:?}"),
        }
        // counting goes on from the frame that came
        assert_eq!(s.grab(FIRED, soon(), path).unwrap().sequence, 4);

        // the case a session meets on hardware (arm, one grab): the triggered frame was
        // dropped and a later one came; a fresh arming counts from 0 again
        let mut s = stream(vec![grey(2), grey(0)]);
        s.arm().unwrap();
        match s.grab(FIRED, soon(), path) {
            Err(CameraError::LostFrame {
                expected: 0,
                got: 2,
                ..
            }) => {}
            other => panic!("expected a lost frame, got {other:?}"),
        }
        s.arm().unwrap();
        assert_eq!(s.grab(FIRED, soon(), path).unwrap().sequence, 0);
    }

    #[test]
    fn frames_from_before_the_trigger_are_dropped() {
        let path = Path::new("/dev/video9");
        let soon = || Instant::now() + Duration::from_millis(50);
        // a free-running camera: frames 0-2 filled between STREAMON and the drain, 3-4
        // between arming and the trigger, 6 the first after it (5 dropped, the buffers
        // being full: nobody's frame)
        let mut s = stream_holding(
            3,
            vec![
                grey_at(0, 99.90),
                grey_at(1, 99.93),
                grey_at(2, 99.96),
                grey_at(3, 99.97),
                grey_at(4, 99.99),
                grey_at(6, 100.02),
                grey_at(7, 100.05),
            ],
        );
        s.arm().unwrap();
        assert_eq!(s.stale, 3, "the drain at arming took what was waiting");
        let f = s.grab(FIRED, soon(), path).unwrap();
        assert_eq!(
            (f.sequence, f.sensor_time),
            (6, Duration::from_millis(100_020))
        );
        assert_eq!(s.stale, 5);
        // and from there on every frame must follow
        assert_eq!(s.grab(FIRED, soon(), path).unwrap().sequence, 7);

        // only frames from before the trigger: none is taken, the time-out says so
        let mut s = stream(vec![grey_at(0, 99.0), grey_at(1, 99.5)]);
        s.arm().unwrap();
        let e = s.grab(FIRED, soon(), path).unwrap_err();
        assert!(matches!(e, CameraError::Timeout { stale: 2, .. }), "{e:?}");
        assert!(e.to_string().contains("2 from before it dropped"), "{e}");

        // a driver whose timestamps are not on the monotonic clock cannot be trusted
        let mut wall = grey(0).unwrap();
        wall.1.monotonic = false;
        let mut s = stream(vec![Ok(wall)]);
        s.arm().unwrap();
        let e = s.grab(FIRED, soon(), path).unwrap_err().to_string();
        assert!(
            e.contains("CLOCK_MONOTONIC") && e.contains("/dev/video9"),
            "{e}"
        );
    }

    #[test]
    fn device_faults_are_named() {
        let path = Path::new("/dev/video9");
        let soon = || Instant::now() + Duration::from_millis(50);
        let mut s = stream(vec![
            Err(std::io::Error::other("No such device")),
            Ok((
                vec![1, 2],
                BufferMeta {
                    sequence: 0,
                    sec: 100,
                    usec: 0,
                    monotonic: true,
                },
            )),
        ]);
        s.arm().unwrap();
        let e = s.grab(FIRED, soon(), path).unwrap_err().to_string();
        assert!(
            e.contains("cam0") && e.contains("/dev/video9") && e.contains("No such device"),
            "{e}"
        );
        // a short buffer is the device's fault, named, not a panic
        let e = s.grab(FIRED, soon(), path).unwrap_err().to_string();
        assert!(e.contains("/dev/video9"), "{e}");
        // nothing more queued: the time limit, not a hang
        assert!(matches!(
            s.grab(FIRED, soon(), path),
            Err(CameraError::Timeout { .. })
        ));
    }

    #[test]
    fn decoding() {
        // two pixels, grey-ish: Y=128, U=V=128 -> R=G=B
        let rgb = yuyv_to_rgb(&[128, 128, 128, 128], 2, 1).unwrap();
        assert_eq!(rgb.len(), 6);
        assert!(rgb.iter().all(|&c| c == rgb[0]));
        assert_eq!(
            yuyv_to_rgb(&[1, 2, 3], 2, 1).unwrap_err(),
            FormatError::Short {
                format: "YUYV",
                got: 3,
                need: 4
            }
        );
        assert!(matches!(
            decode(PixelFormat::Mjpg, &[0xff, 0xd8, 0, 0], 1, 1),
            Ok(FrameData::Jpeg(_))
        ));
        assert!(matches!(
            decode(PixelFormat::Mjpg, &[0, 0, 0, 0], 1, 1),
            Err(FormatError::NotJpeg)
        ));
        assert!(decode(PixelFormat::Grey, &[1, 2], 2, 2).is_err());
        assert_eq!(
            resolve("usb-cam0-video-index0"),
            PathBuf::from("/dev/v4l/by-id/usb-cam0-video-index0")
        );
        assert_eq!(resolve("/dev/video2"), PathBuf::from("/dev/video2"));
    }
}
