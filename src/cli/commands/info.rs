//! `conformd info`: a mesh described.

use crate::cli::args::InfoArgs;
use conformd::jobs;

pub fn run(a: InfoArgs) -> Result<(), jobs::JobError> {
    let InfoArgs { mesh, original } = a;
    let i = jobs::info(&mesh, original.as_deref())?;
    println!("{}", serde_json::to_string_pretty(&i).expect("serialises"));
    Ok(())
}
