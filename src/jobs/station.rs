//! Station jobs: checking a station file, and processing one capture set by hand through
//! the same pipeline the daemon runs.

use super::*;
use crate::station::StationConfig;
use crate::station::pipeline::{Control, Pipeline, ProcessReport, Progress};
use std::path::{Path, PathBuf};

/// Reads and checks a station file; the error lists every problem with its line.
///
/// Example: `conformd check config/station.example.toml`; see `tests/pipeline.rs`.
pub fn check(config: &Path) -> Result<StationConfig, JobError> {
    Ok(StationConfig::load(config)?)
}

/// Processes one capture set with the station file's pipeline and writes
/// `out/<capture id>/` (scan, conformed mesh, report, preview) atomically.
///
/// Example: `conformd process captures/<id> --config station.toml --out results`; see
/// `tests/pipeline.rs`.
pub fn process(
    capture: &Path,
    config: &Path,
    out: &Path,
    write: Write,
    progress: &mut (dyn FnMut(Progress) + Send),
) -> Result<(PathBuf, ProcessReport), JobError> {
    let cfg = StationConfig::load(config)?;
    let mut pipeline = Pipeline::from_config(&cfg)?;
    let mut control = Control {
        cancel: None,
        progress: Some(progress),
    };
    let processed = pipeline.process(capture, &mut control)?;
    let dir = match write {
        Write::Publish => processed.write(out)?,
        Write::Stage => processed.stage(out)?,
    };
    Ok((dir, processed.report))
}

/// What [`process`] does with its result.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Write {
    /// renamed into place as `out/<id>`
    Publish,
    /// left complete under a hidden name in `out`, for a worker to publish once the
    /// journal says the job is still its own (`crate::station::pipeline::publish`)
    Stage,
}

/// What `conformd process --json` prints as its one line on stdout: how a worker process
/// tells the daemon what happened to its capture.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ProcessOutcome {
    pub ok: bool,
    pub capture: Option<String>,
    /// the result folder, or with `staged` the hidden folder it waits in
    pub result: Option<PathBuf>,
    #[serde(default)]
    pub staged: bool,
    /// seconds per stage
    pub seconds: Option<serde_json::Value>,
    /// the mean distance to the scan, relative to the diagonal, and the filled share
    pub mean_distance_relative: Option<f64>,
    pub filled: Option<usize>,
    /// the failed stage (`read`, `reconstruct`, `conform`, `score`, `write`, or `setup`
    /// when the station file or its template could not be loaded)
    pub stage: Option<String>,
    /// the capture is at fault: do not retry
    pub permanent: bool,
    pub error: Option<String>,
}

impl ProcessOutcome {
    pub fn of(r: &Result<(PathBuf, ProcessReport), JobError>, write: Write) -> ProcessOutcome {
        match r {
            Ok((dir, report)) => ProcessOutcome {
                ok: true,
                capture: Some(report.capture.clone()),
                result: Some(dir.clone()),
                staged: write == Write::Stage,
                seconds: serde_json::to_value(&report.seconds).ok(),
                mean_distance_relative: Some(report.conformation.mean_distance_relative),
                filled: Some(report.conformation.filled),
                stage: None,
                permanent: false,
                error: None,
            },
            Err(e) => {
                let (capture, stage, permanent) = match e {
                    JobError::Stage(s) => {
                        (Some(s.capture.clone()), s.stage.to_string(), s.permanent)
                    }
                    _ => (None, "setup".to_string(), false),
                };
                ProcessOutcome {
                    ok: false,
                    capture,
                    result: None,
                    staged: false,
                    seconds: None,
                    mean_distance_relative: None,
                    filled: None,
                    stage: Some(stage),
                    permanent,
                    error: Some(e.to_string()),
                }
            }
        }
    }
}
