//! `conformd template`: a generic template written out.

use crate::cli::args::TemplateArgs;
use conformd::jobs;

pub fn run(a: TemplateArgs) -> Result<(), jobs::JobError> {
    let TemplateArgs {
        kind,
        vertices,
        pose,
        shape,
        out,
    } = a;
    let s = jobs::template(kind, vertices, &pose, &shape, &out)?;
    println!("{kind:?} template: {s}");
    Ok(())
}
