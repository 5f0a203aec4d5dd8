//! `conformd info`: a mesh described.

use crate::cli::args::InfoArgs;
use conformd::commands;

pub fn run(a: InfoArgs) -> Result<(), commands::CommandError> {
    let InfoArgs { mesh, original } = a;
    let i = commands::info(&mesh, original.as_deref())?;
    println!("{}", serde_json::to_string_pretty(&i).expect("serialises"));
    Ok(())
}
