//! `conformd daemon`: the station.

use crate::cli::args::DaemonArgs;
use conformd::jobs;

pub fn run(a: DaemonArgs) -> Result<(), jobs::JobError> {
    let DaemonArgs { config } = a;
    let cfg = jobs::check(&config)?;
    conformd::daemon::run(cfg)?;
    Ok(())
}
