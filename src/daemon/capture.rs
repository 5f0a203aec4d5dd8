//! The daemon's capture thread: it owns the capture session (cameras and
//! trigger box), takes capture requests from the API and fires on the box's button and
//! RFID events (the tag becomes the capture's subject).

use super::{CaptureRefused, CaptureRequest, DaemonError, RigStatus, Shared};
use crate::devices::trigger::BoxEvent;
use crate::station::StationConfig;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::time::Duration;
use tracing::{info, warn};

pub type Channel = (Sender<CaptureRequest>, Receiver<CaptureRequest>);

/// The capture channel (when the station captures) and the rig's first status.
pub fn start(cfg: &StationConfig) -> Result<(Option<Channel>, RigStatus), DaemonError> {
    let mut status = RigStatus {
        cameras: cfg.cameras.iter().map(|c| c.id.clone()).collect(),
        trigger: cfg.trigger.as_ref().map(|t| t.device.display().to_string()),
        ..Default::default()
    };
    if cfg.capture.is_none() {
        return Ok((None, status));
    }
    cfg.rig_config()
        .map_err(|e| DaemonError::Config(e.to_string()))?;
    status.trigger_connected = cfg.trigger.is_none();
    Ok((Some(std::sync::mpsc::channel()), status))
}

/// Runs the capture session on its own thread until the daemon stops.
pub fn spawn_capture_thread(shared: Arc<Shared>, rx: Receiver<CaptureRequest>) {
    std::thread::spawn(move || capture_loop(shared, rx));
}

fn capture_loop(shared: Arc<Shared>, rx: Receiver<CaptureRequest>) {
    use std::sync::atomic::Ordering;
    let rig = match shared.cfg.rig_config() {
        Ok(r) => r,
        Err(e) => {
            warn!("capture disabled: {e}");
            return;
        }
    };
    if let Err(e) = std::fs::create_dir_all(&rig.root) {
        warn!("capture disabled: {}: {e}", rig.root.display());
        return;
    }
    let mut session = None;
    while !shared.stopping.load(Ordering::SeqCst) {
        if session.is_none() {
            match rig.open() {
                Ok(s) => {
                    info!("cameras open");
                    session = Some(s);
                }
                Err(e) => {
                    set_error(&shared, format!("opening the rig: {e}"));
                    // answer waiting requests, then try again a little later
                    while let Ok(req) = rx.recv_timeout(Duration::from_millis(500)) {
                        if let Some(r) = req.reply {
                            let _ = r.send(Err(CaptureRefused::RigUnavailable(e.to_string())));
                        }
                    }
                    continue;
                }
            }
        }
        let s = session.as_mut().expect("opened above");
        let request = match rx.recv_timeout(Duration::from_millis(50)) {
            Ok(req) => Some(req),
            Err(RecvTimeoutError::Disconnected) => return,
            Err(RecvTimeoutError::Timeout) => {
                let events = s.trigger.poll_events(Duration::from_millis(50));
                let connected = s.trigger.connected();
                if let Ok(mut st) = shared.rig.lock() {
                    st.trigger_connected = connected;
                }
                match events {
                    Ok(ev) => ev.into_iter().find_map(|e| match e {
                        BoxEvent::Button { .. } => Some(CaptureRequest {
                            subject: None,
                            reply: None,
                        }),
                        BoxEvent::Rfid { tag, .. } => Some(CaptureRequest {
                            subject: Some(tag),
                            reply: None,
                        }),
                        BoxEvent::Fault { code, text } => {
                            warn!("trigger box fault {code}: {text}");
                            None
                        }
                    }),
                    Err(_) => None,
                }
            }
        };
        let Some(req) = request else { continue };
        let result = s.capture(req.subject.as_deref());
        let reply = match result {
            Ok(set) => {
                info!(capture = %set.id, subject = ?req.subject, attempts = set.attempts, "captured");
                if let Ok(mut st) = shared.rig.lock() {
                    st.last_capture = Some(set.id.clone());
                    st.last_capture_error = None;
                    st.captures += 1;
                }
                shared.wake.notify_one();
                Ok(set.id)
            }
            Err(e) => {
                set_error(&shared, e.to_string());
                Err(e.into())
            }
        };
        if let Some(r) = req.reply {
            let _ = r.send(reply);
        }
    }
}

fn set_error(shared: &Shared, msg: String) {
    warn!("capture: {msg}");
    if let Ok(mut st) = shared.rig.lock() {
        st.last_capture_error = Some(msg);
    }
}
