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
    progress: &mut dyn FnMut(Progress),
) -> Result<(PathBuf, ProcessReport), JobError> {
    let cfg = StationConfig::load(config)?;
    let mut pipeline = Pipeline::from_config(&cfg)?;
    let mut control = Control {
        cancel: None,
        progress: Some(progress),
    };
    let processed = pipeline.process(capture, &mut control)?;
    let dir = processed.write(out)?;
    Ok((dir, processed.report))
}
