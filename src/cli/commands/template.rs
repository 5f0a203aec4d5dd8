//! `conformd template`: a generic template written out.

use crate::cli::args::TemplateArgs;
use conformd::commands;

pub fn run(a: TemplateArgs) -> Result<(), commands::CommandError> {
    let TemplateArgs {
        kind,
        vertices,
        pose,
        shape,
        out,
    } = a;
    let s = commands::template(kind, vertices, &pose, &shape, &out)?;
    println!("{kind:?} template: {s}");
    Ok(())
}
