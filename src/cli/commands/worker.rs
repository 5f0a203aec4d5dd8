//! `conformd worker`: jobs of a shared journal run on this machine.

use crate::cli::args::WorkerArgs;
use conformd::commands;

pub fn run(a: WorkerArgs) -> Result<(), commands::CommandError> {
    let WorkerArgs { config } = a;
    let cfg = commands::check(&config)?;
    conformd::daemon::worker::run(cfg)?;
    Ok(())
}
