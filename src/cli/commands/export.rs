//! `conformd export`: every result as CSV, and each subject's repeatability.

use crate::cli::args::ExportArgs;
use conformd::commands;

pub fn run(a: ExportArgs) -> Result<(), commands::CommandError> {
    let ExportArgs {
        results,
        out,
        repeatability,
    } = a;
    for p in out.iter().chain(&repeatability) {
        conformd::files::refuse_inside(p, &results, "the results folder")?;
    }
    let export = commands::export_csv(&results)?;
    for (file, why) in &export.skipped {
        eprintln!("warning: {file} left out: {why}");
    }
    if !export.rejected.is_empty() {
        eprintln!(
            "{} rejected result(s) left out (review.json)",
            export.rejected.len()
        );
    }
    if let Some(p) = &repeatability {
        let csv = conformd::station::export::spreads_csv(&export.subjects);
        conformd::files::write_atomic(p, csv.as_bytes())?;
        eprintln!(
            "wrote {} ({} subject(s) with two results or more)",
            p.display(),
            export.subjects.len()
        );
    }
    let csv = export.csv;
    match out {
        Some(p) => {
            conformd::files::write_atomic(&p, csv.as_bytes())?;
            eprintln!("wrote {}", p.display());
        }
        None => print!("{csv}"),
    }
    Ok(())
}
