//! `conformd render`: a shaded preview of a mesh.

use crate::cli::args::RenderArgs;
use conformd::commands;

pub fn run(a: RenderArgs) -> Result<(), commands::CommandError> {
    let RenderArgs {
        mesh,
        colour_by,
        views,
        width,
        height,
        out,
    } = a;
    commands::render(&mesh, &colour_by, &views, width, height, &out)?;
    println!("wrote {}", out.display());
    Ok(())
}
