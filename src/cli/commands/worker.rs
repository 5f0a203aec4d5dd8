//! `conformd worker`: jobs of a shared journal run on this machine.

use crate::cli::args::WorkerArgs;
use conformd::jobs;

pub fn run(a: WorkerArgs) -> Result<(), jobs::JobError> {
    let WorkerArgs { config } = a;
    let cfg = jobs::check(&config)?;
    conformd::daemon::worker::run(cfg)?;
    Ok(())
}
