//! Helpers shared by the integration tests.
#![allow(dead_code)]

pub mod deadline;

use conformd::conform::{ConformOptions, Conformed, conform};
use conformd::synth::cases::Case;
#[allow(unused_imports)]
pub use deadline::{CHILD_LIMIT, Deadline};

/// Runs one case with landmarks (or without) and returns the result.
pub fn run(case: &Case, opts: &ConformOptions, landmarks: bool) -> Conformed {
    let lm = landmarks.then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
    conform(&case.template, &case.scan, lm, opts, &mut |_| {}).expect("conformation runs")
}
