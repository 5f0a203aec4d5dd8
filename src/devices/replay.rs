//! A camera that serves frames from recorded or simulated capture sets (or from images in
//! memory), with injectable latency, timeouts, lost frames, skew and device failures, so
//! every failure path of a capture session can be tested without hardware.

use super::camera::{
    Camera, CameraError, CameraInfo, CameraSettings, Frame, FrameData, frame_from_file,
};
use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

/// Something going wrong at one grab.
#[derive(Debug, Clone, PartialEq)]
pub enum Fault {
    /// no frame comes: the grab waits until the deadline
    Timeout,
    /// the frame comes with a sequence gap (a frame was dropped)
    LostFrame,
    /// the frame's sensor timestamp is off by this much
    Skew(Duration),
    /// the device fails (unplugged)
    Device(String),
}

/// Frames served in turn, looping.
pub struct ReplayCamera {
    info: CameraInfo,
    frames: Vec<(u32, u32, FrameData)>,
    next: usize,
    sequence: u32,
    armed: bool,
    pub latency: Duration,
    /// faults by grab number (0-based, counting every grab)
    pub faults: BTreeMap<usize, Fault>,
    grabs: usize,
    exposure_us: Option<u32>,
}

impl ReplayCamera {
    pub fn new(info: CameraInfo, frames: Vec<(u32, u32, FrameData)>) -> Self {
        ReplayCamera {
            info,
            frames,
            next: 0,
            sequence: 0,
            armed: false,
            latency: Duration::ZERO,
            faults: BTreeMap::new(),
            grabs: 0,
            exposure_us: None,
        }
    }

    /// A camera showing a flat grey test image.
    pub fn synthetic(info: CameraInfo, width: u32, height: u32) -> Self {
        let px: Vec<u8> = (0..width * height)
            .map(|i| ((i % width) * 255 / width.max(1)) as u8)
            .collect();
        ReplayCamera::new(info, vec![(width, height, FrameData::Gray8(px))])
    }

    /// Serves this camera's image from each capture set in `sets` (directories with a
    /// `manifest.json`), in order.
    pub fn from_capture_sets(info: CameraInfo, sets: &[&Path]) -> Result<Self, CameraError> {
        let mut frames = Vec::new();
        for dir in sets {
            let m = super::capture::Manifest::read(dir).map_err(|e| CameraError::Device {
                camera: info.id.clone(),
                msg: e.to_string(),
            })?;
            let entry =
                m.cameras
                    .iter()
                    .find(|c| c.id == info.id)
                    .ok_or_else(|| CameraError::Device {
                        camera: info.id.clone(),
                        msg: format!(
                            "{}: the capture set has no image from this camera",
                            dir.display()
                        ),
                    })?;
            frames.push(frame_from_file(&info.id, &dir.join(&entry.file))?);
        }
        Ok(ReplayCamera::new(info, frames))
    }

    /// Adds a fault at grab `n`.
    pub fn fault_at(mut self, n: usize, f: Fault) -> Self {
        self.faults.insert(n, f);
        self
    }
}

impl Camera for ReplayCamera {
    fn info(&self) -> &CameraInfo {
        &self.info
    }

    fn configure(&mut self, s: &CameraSettings) -> Result<(), CameraError> {
        if let Some((w, h, _)) = self.frames.first()
            && (s.width, s.height) != (*w, *h)
        {
            return Err(CameraError::Settings {
                camera: self.info.id.clone(),
                msg: format!(
                    "{}x{} was asked for; the recorded frames are {w}x{h}",
                    s.width, s.height
                ),
            });
        }
        self.exposure_us = s.exposure_us;
        Ok(())
    }

    fn arm(&mut self) -> Result<(), CameraError> {
        if self.frames.is_empty() {
            return Err(CameraError::Device {
                camera: self.info.id.clone(),
                msg: "no frames to replay".into(),
            });
        }
        self.armed = true;
        Ok(())
    }

    fn grab(&mut self, fired_at: Duration, deadline: Instant) -> Result<Frame, CameraError> {
        let n = self.grabs;
        self.grabs += 1;
        if !self.armed {
            return Err(CameraError::Device {
                camera: self.info.id.clone(),
                msg: "grab before arm".into(),
            });
        }
        let fault = self.faults.get(&n).cloned();
        let start = Instant::now();
        let ready = start + self.latency;
        if matches!(fault, Some(Fault::Timeout)) || ready > deadline {
            std::thread::sleep(deadline.saturating_duration_since(Instant::now()));
            return Err(CameraError::Timeout {
                camera: self.info.id.clone(),
                waited_ms: deadline.saturating_duration_since(start).as_millis() as u64,
                stale: 0,
            });
        }
        std::thread::sleep(ready.saturating_duration_since(Instant::now()));
        if let Some(Fault::Device(msg)) = &fault {
            self.armed = false;
            return Err(CameraError::Device {
                camera: self.info.id.clone(),
                msg: msg.clone(),
            });
        }
        let expected = self.sequence;
        self.sequence += if matches!(fault, Some(Fault::LostFrame)) {
            2
        } else {
            1
        };
        if matches!(fault, Some(Fault::LostFrame)) {
            return Err(CameraError::LostFrame {
                camera: self.info.id.clone(),
                expected,
                got: expected + 1,
            });
        }
        let (w, h, data) = self.frames[self.next % self.frames.len()].clone();
        self.next += 1;
        let skew = if let Some(Fault::Skew(d)) = fault {
            d
        } else {
            Duration::ZERO
        };
        Ok(Frame {
            camera: self.info.id.clone(),
            width: w,
            height: h,
            data,
            // exposed at the trigger, on every camera of the rig alike
            sensor_time: fired_at + skew,
            sequence: expected,
            exposure_us: self.exposure_us,
        })
    }

    fn close(&mut self) {
        self.armed = false;
    }
}
