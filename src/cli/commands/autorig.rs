//! `conformd autorig`: an automatic rig for a template mesh.

use crate::cli::args::AutorigArgs;
use conformd::commands;

pub fn run(a: AutorigArgs) -> Result<(), commands::CommandError> {
    let AutorigArgs {
        mesh,
        limbs,
        out,
        preview,
    } = a;
    let out = out.unwrap_or_else(|| mesh.with_extension("rig.json"));
    println!(
        "{}",
        commands::autorig(&mesh, limbs, &out, preview.as_deref())?
    );
    Ok(())
}
