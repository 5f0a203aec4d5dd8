//! A station's devices from its config: the `[capture]` options, the optional `[trigger]`
//! box, and the `[[cameras]]` (V4L2 devices, or replayed capture sets for testing and
//! demonstration), opened into a capture session.

use super::camera::{Camera, CameraError, CameraInfo, CameraSettings};
use super::capture::{CaptureOptions, Session, SoftwareTrigger, Trigger};
use super::replay::ReplayCamera;
use super::trigger::TriggerLink;
use super::v4l2::V4l2Camera;
use std::path::{Path, PathBuf};
use std::time::Duration;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CaptureSection {
    /// the `captures/` directory (relative to the config file; default: the station's)
    pub root: Option<PathBuf>,
    #[serde(flatten)]
    pub options: CaptureOptions,
    #[serde(default)]
    pub camera_settings: CameraSettings,
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TriggerSection {
    /// serial device, best a stable `/dev/serial/by-id/...` name
    pub device: PathBuf,
    #[serde(default = "default_baud")]
    pub baud: u32,
    #[serde(default = "default_reply")]
    pub reply_timeout_ms: u64,
}

fn default_baud() -> u32 {
    115_200
}
fn default_reply() -> u64 {
    500
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSection {
    pub id: String,
    pub pod: String,
    pub side: String,
    /// a V4L2 device: `/dev/videoN` or a `/dev/v4l/by-id` name
    pub device: Option<String>,
    /// or capture sets to replay (directories, relative to the config file)
    pub replay: Option<Vec<PathBuf>>,
    /// or a synthetic test image of the configured size
    #[serde(default)]
    pub synthetic: bool,
}

impl CameraSection {
    /// Plain id, pod and side (they become file names), and exactly one source.
    pub fn check(&self) -> Result<(), CameraSectionError> {
        use crate::paths::check_plain_name;
        check_plain_name("camera id", &self.id)?;
        check_plain_name(&format!("camera {}'s pod", self.id), &self.pod)?;
        check_plain_name(&format!("camera {}'s side", self.id), &self.side)?;
        let kinds =
            self.device.is_some() as u8 + self.replay.is_some() as u8 + self.synthetic as u8;
        if kinds != 1 {
            return Err(CameraSectionError::Sources(self.id.clone()));
        }
        Ok(())
    }
}

/// What is wrong with one `[[cameras]]` entry.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraSectionError {
    #[error(transparent)]
    Name(#[from] crate::paths::NameError),
    #[error("camera '{0}': give exactly one of device, replay or synthetic")]
    Sources(String),
}

/// The rig part of a station config (made by `station::StationConfig::rig_config`).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct RigConfig {
    /// where capture sets are written
    pub root: PathBuf,
    pub capture: CaptureSection,
    pub trigger: Option<TriggerSection>,
    pub cameras: Vec<CameraSection>,
}

#[derive(Debug, thiserror::Error)]
pub enum StationError {
    #[error("{path}: {msg}")]
    Config { path: String, msg: String },
    #[error(transparent)]
    Camera(#[from] CameraError),
}

impl RigConfig {
    /// Opens the cameras and the trigger into a capture session.
    pub fn open(&self) -> Result<Session, StationError> {
        let s = &self.capture.camera_settings;
        let mut cameras: Vec<Box<dyn Camera>> = Vec::new();
        for c in &self.cameras {
            let info = CameraInfo {
                id: c.id.clone(),
                pod: c.pod.clone(),
                side: c.side.clone(),
            };
            let cam: Box<dyn Camera> = if let Some(dev) = &c.device {
                Box::new(V4l2Camera::open(info, dev)?)
            } else if let Some(sets) = &c.replay {
                let paths: Vec<&Path> = sets.iter().map(PathBuf::as_path).collect();
                Box::new(ReplayCamera::from_capture_sets(info, &paths)?)
            } else {
                Box::new(ReplayCamera::synthetic(info, s.width, s.height))
            };
            cameras.push(cam);
        }
        let trigger: Box<dyn Trigger + Send> = match &self.trigger {
            Some(t) => Box::new(TriggerLink::new(
                &t.device,
                t.baud,
                Duration::from_millis(t.reply_timeout_ms),
            )),
            None => Box::new(SoftwareTrigger),
        };
        let mut session = Session::new(
            cameras,
            trigger,
            &self.root,
            self.capture.options.clone(),
            s.clone(),
        );
        session.configure().map_err(|e| StationError::Config {
            path: "cameras".into(),
            msg: e.to_string(),
        })?;
        Ok(session)
    }
}
