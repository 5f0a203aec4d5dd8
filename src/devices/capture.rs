//! Capture sessions: arm every camera, fire (the trigger box or a software trigger),
//! collect one frame per camera within a window, check that the sensor timestamps agree,
//! and write the capture set atomically: `captures/.<id>.partial/`, every file synced,
//! `manifest.json` last, then renamed to `captures/<id>/`. A failure removes the partial
//! set (or moves it to `captures/failed/<id>/` with the reason); there is never a set
//! without a manifest under `captures/`.

use super::camera::{Camera, CameraError, CameraSettings, Frame};
pub use super::capture_set::{CameraRecord, Manifest, TriggerRecord, utc_stamp};
use super::capture_set::{id_taken, write_capture_set};
use super::trigger::{BoxEvent, TriggerBox, TriggerError, TriggerLink};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

/// Fires the cameras.
pub trait Trigger {
    fn kind(&self) -> &'static str;
    fn arm(&mut self, seq: u32) -> Result<(), TriggerError>;
    /// Fires; returns the box's timestamp of the pulse when there is a box.
    fn fire(&mut self, seq: u32, exposure_us: u32) -> Result<Option<u64>, TriggerError>;
    /// Operator button presses and tag reads the box reported, waiting up to `wait`.
    fn poll_events(&mut self, _wait: Duration) -> Result<Vec<BoxEvent>, TriggerError> {
        Ok(Vec::new())
    }
    /// Whether the trigger's link is up (a software trigger always is).
    fn connected(&self) -> bool {
        true
    }
}

/// No box: cameras free-run and the next frame of each is taken.
pub struct SoftwareTrigger;

impl Trigger for SoftwareTrigger {
    fn kind(&self) -> &'static str {
        "software"
    }
    fn arm(&mut self, _: u32) -> Result<(), TriggerError> {
        Ok(())
    }
    fn fire(&mut self, _: u32, _: u32) -> Result<Option<u64>, TriggerError> {
        Ok(None)
    }
}

impl<P: Read + Write> Trigger for TriggerBox<P> {
    fn kind(&self) -> &'static str {
        "serial"
    }
    fn arm(&mut self, seq: u32) -> Result<(), TriggerError> {
        TriggerBox::arm(self, seq)
    }
    fn fire(&mut self, seq: u32, exposure_us: u32) -> Result<Option<u64>, TriggerError> {
        TriggerBox::fire(self, seq, exposure_us).map(Some)
    }
}

impl Trigger for TriggerLink {
    fn kind(&self) -> &'static str {
        "serial"
    }
    fn poll_events(&mut self, wait: Duration) -> Result<Vec<BoxEvent>, TriggerError> {
        self.with(|b| b.poll_events(wait))
    }
    fn connected(&self) -> bool {
        self.is_connected()
    }
    fn arm(&mut self, seq: u32) -> Result<(), TriggerError> {
        self.with(|b| b.arm(seq))
    }
    fn fire(&mut self, seq: u32, exposure_us: u32) -> Result<Option<u64>, TriggerError> {
        self.with(|b| b.fire(seq, exposure_us)).map(Some)
    }
}

/// Options of a capture session (the `[capture]` part of a station config).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CaptureOptions {
    pub station: String,
    /// every camera's frame must arrive within this window after the trigger
    pub window_ms: u64,
    /// largest spread of the cameras' sensor timestamps
    pub max_skew_ms: f64,
    /// attempts after the first when a capture fails
    pub retries: u32,
    /// keep failed sets under `failed/<id>/` with the reason, instead of removing them
    pub keep_failed: bool,
    pub exposure_us: u32,
}

impl Default for CaptureOptions {
    fn default() -> Self {
        CaptureOptions {
            station: "station".into(),
            window_ms: 2000,
            max_skew_ms: 5.0,
            retries: 1,
            keep_failed: false,
            exposure_us: 8000,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error(transparent)]
    Trigger(#[from] TriggerError),
    #[error("sensor timestamps spread {spread_ms:.2} ms (at most {max_ms} ms): {detail}")]
    Skew {
        spread_ms: f64,
        max_ms: f64,
        detail: String,
    },
    #[error("writing {path}: {msg}")]
    Write { path: String, msg: String },
    #[error("{0}")]
    Subject(String),
    #[error("{0}")]
    IdTaken(String),
    #[error("capture failed {attempts} times; last: {last}")]
    GaveUp {
        attempts: u32,
        last: Box<CaptureError>,
    },
}

/// A capture station's cameras, trigger and capture directory.
pub struct Session {
    pub cameras: Vec<Box<dyn Camera>>,
    pub trigger: Box<dyn Trigger + Send>,
    /// the `captures/` directory
    pub root: PathBuf,
    pub options: CaptureOptions,
    pub settings: CameraSettings,
    sequence: u32,
    last_stamp: String,
    counter: u32,
}

/// What a successful capture wrote.
#[derive(Debug, Clone)]
pub struct CaptureSet {
    pub id: String,
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub attempts: u32,
}

impl std::fmt::Display for CaptureSet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "captured {} ({} cameras, {} attempt{})\nwrote {}",
            self.id,
            self.manifest.cameras.len(),
            self.attempts,
            if self.attempts == 1 { "" } else { "s" },
            self.dir.display()
        )
    }
}

impl Session {
    pub fn new(
        cameras: Vec<Box<dyn Camera>>,
        trigger: Box<dyn Trigger + Send>,
        root: &Path,
        options: CaptureOptions,
        settings: CameraSettings,
    ) -> Self {
        Session {
            cameras,
            trigger,
            root: root.to_path_buf(),
            options,
            settings,
            sequence: 0,
            last_stamp: String::new(),
            counter: 0,
        }
    }

    /// Configures every camera once.
    pub fn configure(&mut self) -> Result<(), CaptureError> {
        for c in &mut self.cameras {
            c.configure(&self.settings)?;
        }
        Ok(())
    }

    /// A new capture id: UTC time to the millisecond, a counter within the millisecond
    /// (this session's ids sort in the order taken), then 6 random hex digits
    /// (`20261122T045012.345Z-000-3f9c02`), so that two processes, or two stations sharing
    /// one `captures/` folder, do not pick one id by chance; the writer's exclusive create
    /// and no-replace rename make sure of it.
    pub fn next_id(&mut self) -> String {
        let stamp = utc_stamp(SystemTime::now());
        self.counter = if stamp == self.last_stamp {
            self.counter + 1
        } else {
            0
        };
        self.last_stamp = stamp.clone();
        loop {
            let id = format!(
                "{stamp}-{:03}-{:06x}",
                self.counter,
                rand::random::<u32>() & 0xff_ffff
            );
            if !self.root.join(&id).exists() && !self.root.join("failed").join(&id).exists() {
                return id;
            }
            self.counter += 1;
        }
    }

    /// Captures one set, retrying as configured.
    pub fn capture(&mut self, subject: Option<&str>) -> Result<CaptureSet, CaptureError> {
        // the subject goes into the manifest, the journal, page links and CSV exports
        if let Some(s) = subject {
            crate::paths::check_plain_name("subject", s)
                .map_err(|e| CaptureError::Subject(e.to_string()))?;
        }
        let mut last = None;
        let attempts = self.options.retries + 1;
        for attempt in 1..=attempts {
            match self.attempt(subject) {
                Ok(mut set) => {
                    set.attempts = attempt;
                    return Ok(set);
                }
                Err(e) => last = Some(e),
            }
        }
        let last = last.expect("at least one attempt");
        if attempts == 1 {
            return Err(last);
        }
        Err(CaptureError::GaveUp {
            attempts,
            last: Box::new(last),
        })
    }

    fn attempt(&mut self, subject: Option<&str>) -> Result<CaptureSet, CaptureError> {
        let mut id = self.next_id();
        let started = SystemTime::now();
        let frames = self.collect();
        for c in &mut self.cameras {
            c.close();
        }
        let result = frames.and_then(|(frames, box_time)| {
            check_skew(&frames, self.options.max_skew_ms)?;
            // an id another writer took in the meantime: the same frames under a new one
            let mut retries = 0;
            loop {
                match self.write(&id, subject, started, &frames, box_time) {
                    Err(CaptureError::IdTaken(_)) if retries < 8 => {
                        retries += 1;
                        id = self.next_id();
                    }
                    r => return r,
                }
            }
        });
        match &result {
            // the partial folder of that id is the other writer's
            Err(CaptureError::IdTaken(_)) | Ok(_) => {}
            Err(e) => self.discard(&id, e),
        }
        result
    }

    /// Arms, fires and collects one frame per camera.
    fn collect(&mut self) -> Result<(Vec<Frame>, Option<u64>), CaptureError> {
        self.sequence += 1;
        let seq = self.sequence;
        for c in &mut self.cameras {
            c.arm()?;
        }
        self.trigger.arm(seq)?;
        // taken before the pulse: a frame stamped earlier was exposed before it
        let fired_at = super::camera::monotonic_now();
        let box_time = self.trigger.fire(seq, self.options.exposure_us)?;
        let deadline = Instant::now() + Duration::from_millis(self.options.window_ms);
        let mut frames = Vec::with_capacity(self.cameras.len());
        for c in &mut self.cameras {
            frames.push(c.grab(fired_at, deadline)?);
        }
        Ok((frames, box_time))
    }

    fn write(
        &self,
        id: &str,
        subject: Option<&str>,
        started: SystemTime,
        frames: &[Frame],
        box_time: Option<u64>,
    ) -> Result<CaptureSet, CaptureError> {
        let mut cameras = Vec::new();
        let mut files = Vec::new();
        for (f, c) in frames.iter().zip(&self.cameras) {
            let info = c.info();
            let file = format!("{}.{}", info.id, f.extension());
            let bytes = f.encode().map_err(|e| CaptureError::Write {
                path: self.root.join(id).join(&file).display().to_string(),
                msg: e.to_string(),
            })?;
            files.push((file.clone(), bytes));
            cameras.push(CameraRecord {
                id: info.id.clone(),
                pod: info.pod.clone(),
                side: info.side.clone(),
                file,
                width: f.width,
                height: f.height,
                sensor_timestamp_us: f.sensor_time.as_micros() as u64,
                sequence: f.sequence,
                exposure_us: f.exposure_us,
            });
        }
        let manifest = Manifest {
            format: Manifest::FORMAT.into(),
            version: Manifest::VERSION,
            id: id.into(),
            station: self.options.station.clone(),
            subject: subject.map(str::to_string),
            started_utc: utc_stamp(started),
            finished_utc: utc_stamp(SystemTime::now()),
            trigger: TriggerRecord {
                kind: self.trigger.kind().into(),
                sequence: self.sequence,
                box_time_us: box_time,
            },
            cameras,
        };
        let dir = write_capture_set(&self.root, &manifest, &files).map_err(|e| {
            if id_taken(&e) {
                CaptureError::IdTaken(e.to_string())
            } else {
                CaptureError::Write {
                    path: e.path().to_string(),
                    msg: e.to_string(),
                }
            }
        })?;
        Ok(CaptureSet {
            id: id.into(),
            dir,
            manifest,
            attempts: 1,
        })
    }

    /// Removes a failed attempt's partial set, or keeps it under `failed/<id>/` with
    /// `reason.txt`.
    fn discard(&self, id: &str, why: &CaptureError) {
        let partial = self.root.join(format!(".{id}.partial"));
        if self.options.keep_failed {
            let failed = self.root.join("failed").join(id);
            if std::fs::create_dir_all(self.root.join("failed")).is_ok() {
                if !partial.exists() {
                    let _ = std::fs::create_dir_all(&partial);
                }
                let _ = std::fs::write(partial.join("reason.txt"), format!("{why}\n"));
                if crate::files::rename_no_replace(&partial, &failed).is_ok() {
                    return;
                }
            }
        }
        let _ = std::fs::remove_dir_all(&partial);
    }
}

fn check_skew(frames: &[Frame], max_ms: f64) -> Result<(), CaptureError> {
    let (Some(lo), Some(hi)) = (
        frames.iter().min_by_key(|f| f.sensor_time),
        frames.iter().max_by_key(|f| f.sensor_time),
    ) else {
        return Ok(());
    };
    let spread_ms = (hi.sensor_time - lo.sensor_time).as_secs_f64() * 1000.0;
    if spread_ms > max_ms {
        return Err(CaptureError::Skew {
            spread_ms,
            max_ms,
            detail: format!("{} is {spread_ms:.2} ms after {}", hi.camera, lo.camera),
        });
    }
    Ok(())
}
