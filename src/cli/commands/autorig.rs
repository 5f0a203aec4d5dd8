//! `conformd autorig`: an automatic rig for a template mesh.

use crate::cli::args::AutorigArgs;
use conformd::jobs;

pub fn run(a: AutorigArgs) -> Result<(), jobs::JobError> {
    let AutorigArgs {
        mesh,
        limbs,
        out,
        preview,
    } = a;
    let out = out.unwrap_or_else(|| mesh.with_extension("rig.json"));
    println!("{}", jobs::autorig(&mesh, limbs, &out, preview.as_deref())?);
    Ok(())
}
