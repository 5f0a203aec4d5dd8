//! The capture command: one capture with the station file's cameras and trigger.

use super::*;
use std::path::Path;

/// Captures one set with the station file's rig; the result names the set's folder.
pub fn capture(
    config: &Path,
    subject: Option<&str>,
) -> Result<crate::devices::capture::CaptureSet, CommandError> {
    let cfg = crate::station::StationConfig::load(config)?;
    let rig = cfg.rig_config()?;
    std::fs::create_dir_all(&rig.root).map_err(|source| CommandError::Io {
        path: rig.root.display().to_string(),
        source,
    })?;
    let mut session = rig.open()?;
    Ok(session.capture(subject)?)
}
