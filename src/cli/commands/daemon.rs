//! `conformd daemon`: the station.

use crate::cli::args::DaemonArgs;
use conformd::commands;

pub fn run(a: DaemonArgs) -> Result<(), commands::CommandError> {
    let DaemonArgs { config } = a;
    let cfg = commands::check(&config)?;
    conformd::daemon::run(cfg)?;
    Ok(())
}
