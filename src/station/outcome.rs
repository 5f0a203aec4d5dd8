//! The protocol between the daemon (or `conformd worker`) and the child process that runs
//! one job (`conformd process --json --stage`): the one JSON line the child prints on
//! stdout, typed here so both ends share it.

use super::pipeline::{ProcessReport, Stage, StageError, StageSeconds};
use std::path::PathBuf;

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
    pub seconds: Option<StageSeconds>,
    /// the mean distance to the scan, relative to the diagonal, and the filled share
    pub mean_distance_relative: Option<f64>,
    pub filled: Option<usize>,
    /// the names of the operator's landmarks the fit used (comma-separated)
    #[serde(default)]
    pub landmarks: Option<String>,
    /// the failed stage (`setup` when the station file or its template could not be
    /// loaded)
    pub stage: Option<Stage>,
    /// the capture is at fault: do not retry
    pub permanent: bool,
    pub error: Option<String>,
}

impl ProcessOutcome {
    /// A capture processed: its result in `dir` (hidden there when `staged`).
    pub fn done(dir: PathBuf, report: &ProcessReport, staged: bool) -> ProcessOutcome {
        ProcessOutcome {
            ok: true,
            capture: Some(report.capture.clone()),
            result: Some(dir),
            staged,
            seconds: Some(report.seconds.clone()),
            mean_distance_relative: Some(report.conformation.mean_distance_relative),
            filled: Some(report.conformation.filled),
            landmarks: report.manual_landmarks.as_ref().map(|l| {
                l.iter()
                    .map(|l| l.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            }),
            stage: None,
            permanent: false,
            error: None,
        }
    }

    /// A capture's stage failed.
    pub fn failed(e: &StageError) -> ProcessOutcome {
        Self::failed_at(Some(e.capture.clone()), e.stage, e.permanent, e.to_string())
    }

    /// Processing failed at `stage` (of `capture` when it was known).
    pub fn failed_at(
        capture: Option<String>,
        stage: Stage,
        permanent: bool,
        error: String,
    ) -> ProcessOutcome {
        ProcessOutcome {
            ok: false,
            capture,
            result: None,
            staged: false,
            seconds: None,
            mean_distance_relative: None,
            filled: None,
            landmarks: None,
            stage: Some(stage),
            permanent,
            error: Some(error),
        }
    }
}
