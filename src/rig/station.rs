//! A station's rig from its config: the `[capture]` options, the optional `[trigger]`
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
    /// the `captures/` directory (relative to the config file)
    pub root: PathBuf,
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

/// The rig part of a station config.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct RigConfig {
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
    /// Reads the rig sections of a station config; paths are made absolute against the
    /// config's folder.
    pub fn load(path: &Path) -> Result<RigConfig, StationError> {
        let name = path.display().to_string();
        let err = |msg: String| StationError::Config {
            path: name.clone(),
            msg,
        };
        let text = std::fs::read_to_string(path).map_err(|e| err(e.to_string()))?;
        let table: toml::Table = toml::from_str(&text).map_err(|e| err(e.to_string()))?;
        let pick = |k: &str| table.get(k).cloned();
        let mut sub = toml::Table::new();
        for k in ["capture", "trigger", "cameras"] {
            if let Some(v) = pick(k) {
                sub.insert(k.into(), v);
            }
        }
        let mut cfg: RigConfig = sub
            .try_into()
            .map_err(|e: toml::de::Error| err(e.to_string()))?;
        if cfg.cameras.is_empty() {
            return Err(err("[[cameras]]: no camera is configured".into()));
        }
        let base = path.parent().unwrap_or(Path::new("."));
        let abs = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        abs(&mut cfg.capture.root);
        for c in &mut cfg.cameras {
            let kinds = c.device.is_some() as u8 + c.replay.is_some() as u8 + c.synthetic as u8;
            if kinds != 1 {
                return Err(err(format!(
                    "camera '{}': give exactly one of device, replay or synthetic",
                    c.id
                )));
            }
            for r in c.replay.iter_mut().flatten() {
                abs(r);
            }
        }
        let mut ids: Vec<&str> = cfg.cameras.iter().map(|c| c.id.as_str()).collect();
        ids.sort_unstable();
        if ids.windows(2).any(|w| w[0] == w[1]) {
            return Err(err("two cameras have the same id".into()));
        }
        Ok(cfg)
    }

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
            &self.capture.root,
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
