//! `conformd render`: a shaded preview of a mesh.

use crate::cli::args::RenderArgs;
use conformd::jobs;

pub fn run(a: RenderArgs) -> Result<(), jobs::JobError> {
    let RenderArgs {
        mesh,
        colour_by,
        views,
        width,
        height,
        out,
    } = a;
    jobs::render(&mesh, &colour_by, &views, width, height, &out)?;
    println!("wrote {}", out.display());
    Ok(())
}
