//! `conformd measure`: measurements of conformed meshes, raw and posture-free, or their repeatability.

use crate::cli::args::MeasureArgs;
use conformd::commands;
use conformd::template::TemplateSource;

pub fn run(a: MeasureArgs) -> Result<(), commands::CommandError> {
    let MeasureArgs {
        meshes,
        template,
        vertices,
        template_landmarks,
        template_groups,
        definitions,
        model,
        normalise_posture,
        csv,
        repeatability,
    } = a;
    let mut source =
        TemplateSource::named(&template, template_groups).map_err(commands::CommandError::from)?;
    if template_landmarks.is_some() {
        source.landmarks = template_landmarks;
    }
    if source.generic.is_some() {
        source.vertices = vertices;
    }
    let resolved = commands::resolve_measurements(&source, definitions.as_deref())?;
    let posture = normalise_posture
        .then(|| commands::posture_removal(&source, model.as_deref(), &resolved))
        .transpose()?;
    let reports = meshes
        .iter()
        .map(|m| commands::measure(m, &resolved, posture.as_ref()))
        .collect::<Result<Vec<_>, _>>()?;
    if repeatability {
        print!("{}", commands::repeatability(&reports)?);
    } else {
        println!(
            "{}",
            serde_json::to_string_pretty(&reports).expect("serialises")
        );
    }
    if let Some(p) = csv {
        conformd::files::write_atomic(&p, commands::measurements_csv(&reports).as_bytes())?;
        eprintln!("wrote {}", p.display());
    }
    Ok(())
}
