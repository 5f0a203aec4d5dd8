//! `conformd capture`: one capture set from the station's cameras and trigger.

use crate::cli::args::CaptureArgs;
use conformd::jobs;

pub fn run(a: CaptureArgs) -> Result<(), jobs::JobError> {
    let CaptureArgs { config, subject } = a;
    println!("{}", jobs::capture(&config, subject.as_deref())?);
    Ok(())
}
