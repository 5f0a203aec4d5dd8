//! Station jobs: checking a station file, and processing one capture set by hand through
//! the same pipeline the daemon runs.

use super::*;
use crate::station::StationConfig;
use crate::station::outcome::ProcessOutcome;
use crate::station::pipeline::{Control, Pipeline, ProcessReport, Progress, Stage};
use std::path::{Path, PathBuf};

/// Reads and checks a station file; the error lists every problem with its line.
///
/// Example: `conformd check config/station.example.toml`; see `tests/pipeline.rs`.
pub fn check(config: &Path) -> Result<StationConfig, CommandError> {
    let cfg = StationConfig::load(config)?;
    check_files(&cfg)?;
    Ok(cfg)
}

/// Loads every file the station file names with the reader the daemon and its workers
/// use (template, landmarks, groups, rig, calibrations, measurement definitions, posture
/// model, weights, shape model), and checks the replay folders and the worker program,
/// so a station that passes `check` does not fail on its first capture.
fn check_files(cfg: &StationConfig) -> Result<(), CommandError> {
    let name = cfg.file.display().to_string();
    let fail = |msg: String| CommandError::Config {
        path: name.clone(),
        msg,
    };
    // a worker whose program stands in for the pipeline may lack one of the two
    match (&cfg.rig, &cfg.template) {
        (Some(_), Some(_)) => {
            Pipeline::from_config(cfg)?;
        }
        (Some(rig), None) => {
            crate::stereo::rig::Reconstruction::load(&rig.file, rig.calibration.as_deref())?;
        }
        (None, Some(t)) => {
            if t.figure()?.is_none() {
                let (mesh, _) = t.load()?;
                t.rig_file(&mesh)?;
            }
        }
        (None, None) => {}
    }
    for c in &cfg.cameras {
        for d in c.replay.iter().flatten() {
            if !d.is_dir() {
                return Err(fail(format!(
                    "[[cameras]] '{}': replay {} is not a folder of capture sets",
                    c.id,
                    d.display()
                )));
            }
        }
    }
    if let Some(p) = &cfg.worker.program {
        use std::os::unix::fs::PermissionsExt;
        let ok =
            std::fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0);
        if !ok {
            return Err(fail(format!(
                "[worker]: program {} is not an executable file",
                p.display()
            )));
        }
    }
    // what the daemon makes in the data folder must be what it would make, or absent
    let s = &cfg.station;
    let captures = cfg
        .capture
        .as_ref()
        .and_then(|c| c.root.clone())
        .unwrap_or_else(|| s.captures());
    for (what, dir) in [
        ("data", s.data.clone()),
        ("captures", captures),
        ("incoming", s.incoming()),
        ("results", s.results()),
        ("landmarks", s.landmarks()),
    ] {
        if let Ok(m) = std::fs::metadata(&dir)
            && !m.is_dir()
        {
            return Err(fail(format!(
                "[station]: {what} {} is a {}, not a folder",
                dir.display(),
                crate::files::kind_of(&m)
            )));
        }
    }
    let sqlite = s.data.join("journal.sqlite");
    if cfg.journal.url.is_none()
        && let Ok(m) = std::fs::metadata(&sqlite)
        && !m.is_file()
    {
        return Err(fail(format!(
            "[station]: the journal {} is a {}, not a file",
            sqlite.display(),
            crate::files::kind_of(&m)
        )));
    }
    Ok(())
}

/// Processes one capture set with the station file's pipeline and writes
/// `out/<capture id>/` (scan, conformed mesh, report, preview) atomically; `landmarks`
/// names a file of scan landmarks (`name x y z`) an operator placed, to fit by;
/// `template_cache` a folder where a generic template is kept between processes.
///
/// Example: `conformd process captures/<id> --config station.toml --out results`; see
/// `tests/pipeline.rs`.
pub fn process(
    capture: &Path,
    config: &Path,
    out: &Path,
    landmarks: Option<&Path>,
    write: Write,
    template_cache: Option<&Path>,
    progress: &mut (dyn FnMut(Progress) + Send),
) -> Result<(PathBuf, ProcessReport), CommandError> {
    crate::files::refuse_inside(out, capture, "the capture set")?;
    let landmarks = landmarks
        .map(crate::mesh::read_landmarks)
        .transpose()
        .map_err(CommandError::Landmarks)?;
    let cfg = StationConfig::load(config)?;
    let mut pipeline = Pipeline::from_config_cached(&cfg, template_cache)?;
    let mut control = Control {
        cancel: None,
        progress: Some(progress),
    };
    let processed = pipeline.process(capture, landmarks.as_deref(), &mut control)?;
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

/// The outcome line `conformd process --json` prints for `r`.
pub fn process_outcome(
    r: &Result<(PathBuf, ProcessReport), CommandError>,
    write: Write,
) -> ProcessOutcome {
    match r {
        Ok((dir, report)) => ProcessOutcome::done(dir.clone(), report, write == Write::Stage),
        Err(CommandError::Stage(s)) => ProcessOutcome::failed(s),
        // retried only when reading failed (the file may come back whole); its content
        // or kind stays wrong however often it is read
        Err(CommandError::Landmarks(e)) => ProcessOutcome::failed_at(
            None,
            Stage::Setup,
            !matches!(e, crate::mesh::FileError::Io { .. }),
            e.to_string(),
        ),
        Err(e) => ProcessOutcome::failed_at(None, Stage::Setup, false, e.to_string()),
    }
}
