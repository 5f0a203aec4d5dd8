//! Progress bars for long CLI work (conformation iterations, pipeline stages).

use conformd::conform::IterationReport;
use conformd::station::pipeline::Progress;
use indicatif::{ProgressBar, ProgressStyle};

/// A bar over `len` iterations, labelled `what`.
pub fn iterations(len: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(
        ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} iterations {msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    pb.set_prefix(what.to_string());
    pb
}

/// Moves a bar to an iteration's report.
pub fn tick(pb: &ProgressBar, it: &IterationReport) {
    // the full-resolution iterations after a decimated level's run past max_iterations
    if pb.length().is_some_and(|l| it.iteration as u64 > l) {
        pb.set_length(it.iteration as u64);
    }
    pb.set_position(it.iteration as u64);
    pb.set_message(format!(
        "{} vertices, matched {} filled {} update {:.2e}",
        it.vertices, it.matched, it.filled, it.max_update_relative
    ));
}

/// A bar for one capture through the pipeline: the stage as its prefix, conformation
/// iterations as its position.
pub fn pipeline(max_iterations: usize) -> (ProgressBar, impl FnMut(Progress)) {
    let pb = iterations(max_iterations, "read");
    let bar = pb.clone();
    let f = move |p: Progress| match p {
        Progress::Stage(s) => bar.set_prefix(s.to_string()),
        Progress::Iteration(it) => tick(&bar, it),
    };
    (pb, f)
}
