//! `conformd conform`: one template conformed onto one scan, with a progress bar.

use crate::cli::args::ConformArgs;
use crate::cli::progress;
use conformd::commands;
use conformd::template::TemplateSource;

pub fn run(a: ConformArgs) -> Result<(), commands::CommandError> {
    let ConformArgs {
        template,
        template_groups,
        template_rig,
        scan,
        template_landmarks,
        scan_landmarks,
        config,
        method,
        out,
        report,
    } = a;
    let opts = commands::conform_options(config.as_deref(), method.map(Into::into))?;
    let mut template = match (template, &config) {
        (Some(t), _) => {
            TemplateSource::named(&t, template_groups).map_err(commands::CommandError::from)?
        }
        (None, Some(c)) => commands::template_from_config(c)?,
        (None, None) => {
            return Err(commands::CommandError::Usage(
                "--template is needed (or a --config with a [template] table)".into(),
            ));
        }
    };
    if template_rig.is_some() {
        if template.generic.is_some() {
            return Err(commands::CommandError::Usage(
                "--template-rig is for a template mesh: a generic template brings its own rig"
                    .into(),
            ));
        }
        template.rig = template_rig;
    }
    let files = commands::ConformFiles {
        template,
        scan,
        template_landmarks,
        scan_landmarks,
        out: out.clone(),
        report: report.clone(),
    };
    let pb = progress::iterations(opts.max_iterations, "conform");
    let r = commands::conform_files(&files, &opts, &mut |it| progress::tick(&pb, it));
    pb.finish_and_clear();
    println!("{}\nwrote {}", r?, out.display());
    if let Some(p) = report {
        println!("wrote {}", p.display());
    }
    Ok(())
}
