//! What a user can do from the CLI (its commands), as library calls, one file per stage:
//! conformation (`conformation`), templates, previews and shape models (`shapes`), captures
//! with the station's devices (`capture`),
//! simulation, calibration and reconstruction (`stereo`). The CLI, the tests and the
//! daemon call exactly these.

mod capture;
mod conformation;
mod demo;
mod measure;
mod shapes;
mod station;
mod stereo;

pub use capture::*;
pub use conformation::*;
pub use demo::*;
pub use measure::*;
pub use shapes::*;
pub use station::*;
pub use stereo::*;

use crate::files::write_atomic;
use crate::mesh;
use std::path::Path;

/// Why a job failed: the typed error of the stage that failed, or a sentence about the
/// request itself (`Usage`).
#[derive(Debug, thiserror::Error)]
pub enum CommandError {
    #[error(transparent)]
    File(#[from] mesh::FileError),
    /// a mesh read well whose contents are unfit (an index out of range, a NaN)
    #[error(transparent)]
    Mesh(#[from] mesh::MeshError),
    #[error("{path}: {msg}")]
    Config { path: String, msg: String },
    #[error(transparent)]
    Station(#[from] crate::station::ConfigError),
    #[error("{0}")]
    Conform(#[from] crate::conform::ConformError),
    #[error(transparent)]
    CaptureSet(#[from] crate::devices::capture_set::CaptureSetError),
    #[error(transparent)]
    Capture(#[from] crate::devices::capture::CaptureError),
    #[error(transparent)]
    Rig(#[from] crate::devices::setup::StationError),
    #[error(transparent)]
    Daemon(#[from] crate::daemon::DaemonError),
    #[error(transparent)]
    StereoRig(#[from] crate::stereo::rig::RigError),
    /// a recorded pair's calibration file that could not be read
    #[error("{path}: {source}")]
    RecordedCalibration {
        path: String,
        source: crate::stereo::recorded::RecordedCalibrationError,
    },
    /// a rig file made by a command that would not be valid
    #[error(transparent)]
    RigFile(#[from] crate::stereo::rig::RigFileError),
    #[error(transparent)]
    Calibration(#[from] crate::stereo::calibrate::CalibrationError),
    #[error(transparent)]
    Truth(#[from] crate::stereo::truth::TruthError),
    #[error(transparent)]
    Disparity(#[from] crate::stereo::disparity::DisparityError),
    /// a truth read well that the result could not be scored against
    #[error("{path}: {source}")]
    Scoring {
        path: String,
        source: crate::stereo::truth::TruthError,
    },
    #[error("{0}")]
    Reconstruct(String),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    #[error(transparent)]
    Pipeline(#[from] crate::station::PipelineError),
    #[error(transparent)]
    Stage(#[from] crate::station::StageError),
    /// a mesh that could not be measured
    #[error("{mesh}: {source}")]
    Measure {
        mesh: String,
        source: crate::measure::MeasureError,
    },
    /// a template named wrongly or given parameters it does not have
    #[error(transparent)]
    Template(#[from] crate::template::TemplateError),
    /// a flag given wrongly or a combination of flags that does not make sense
    #[error("{0}")]
    Usage(String),
    /// a file given that cannot be used for what was asked (a point cloud to render,
    /// two meshes of different topology, a pair of two sizes); names the file
    #[error("{path}: {msg}")]
    Input { path: String, msg: String },
    /// an image file that could not be decoded
    #[error("{path}: not a readable image: {msg}")]
    Image { path: String, msg: String },
    /// a scan that cannot be searched (too few points, NaN, ...)
    #[error("{path}: {source}")]
    Scan {
        path: String,
        source: crate::conform::correspond::ScanError,
    },
    /// measurement definitions that do not fit the template
    #[error(transparent)]
    Definitions(crate::measure::MeasureError),
    /// a weight model that could not be fitted to the samples
    #[error(transparent)]
    Weight(#[from] crate::measure::weight::WeightError),
    /// the station demo could not run to its end
    #[error("demo: {0}")]
    Demo(String),
    /// the demo's simulated trigger box got no pseudo-terminal
    #[error("demo: no pseudo-terminal for the trigger box: {0}")]
    Terminal(#[from] serialport::Error),
    /// the operator's landmarks file of the capture being processed: a file that is
    /// not one (a pipe, garbled lines) is the capture's fault, not the machine's
    #[error("{0}")]
    Landmarks(mesh::FileError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

impl CommandError {
    /// A truth read from `path` that a result could not be scored against.
    fn scoring(path: &Path) -> impl FnOnce(crate::stereo::truth::TruthError) -> CommandError {
        let path = path.display().to_string();
        move |source| CommandError::Scoring { path, source }
    }
}

/// Largest options file read: a page of settings, with room to spare.
const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Reads a TOML file into a table; errors name the file.
fn read_toml(path: &Path) -> Result<toml::Table, CommandError> {
    let name = path.display().to_string();
    let text = crate::files::read_text_limited(path, MAX_CONFIG_BYTES)?;
    toml::from_str(&text).map_err(|e| CommandError::Config {
        path: name,
        msg: e.to_string(),
    })
}

fn write_report<T: serde::Serialize>(path: &Path, report: &T) -> Result<(), CommandError> {
    let json = serde_json::to_string_pretty(report).expect("reports serialise");
    write_atomic(path, json.as_bytes())?;
    Ok(())
}

/// Parses `9x6` (inner corners).
pub fn parse_board(s: &str) -> Result<(u32, u32), CommandError> {
    let bad = || {
        CommandError::Usage(format!(
            "board '{s}': expected COLSxROWS inner corners, e.g. 9x6"
        ))
    };
    let (a, b) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (c, r): (u32, u32) = (a.parse().map_err(|_| bad())?, b.parse().map_err(|_| bad())?);
    if c < 3 || r < 3 {
        return Err(bad());
    }
    Ok((c, r))
}
