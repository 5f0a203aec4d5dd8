//! Rig jobs: one capture with the station config's cameras and trigger.

use super::*;
use std::path::Path;

/// Captures one set with the station config's rig; the result names the set's folder.
pub fn capture(
    config: &Path,
    subject: Option<&str>,
) -> Result<crate::rig::capture::CaptureSet, JobError> {
    let rig =
        crate::rig::station::RigConfig::load(config).map_err(|e| JobError::Usage(e.to_string()))?;
    std::fs::create_dir_all(&rig.capture.root).map_err(|source| JobError::Io {
        path: rig.capture.root.display().to_string(),
        source,
    })?;
    let mut session = rig.open().map_err(|e| JobError::Usage(e.to_string()))?;
    session
        .capture(subject)
        .map_err(|e| JobError::Usage(e.to_string()))
}
