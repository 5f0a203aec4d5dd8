//! `conformd capture`: one capture set from the station's cameras and trigger.

use crate::cli::args::CaptureArgs;
use conformd::commands;

pub fn run(a: CaptureArgs) -> Result<(), commands::CommandError> {
    let CaptureArgs { config, subject } = a;
    println!("{}", commands::capture(&config, subject.as_deref())?);
    Ok(())
}
