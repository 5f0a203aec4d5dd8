//! Helpers shared by the integration tests.
#![allow(dead_code)]

use conformd::conform::{ConformOptions, Conformed, conform};
use conformd::synth::cases::Case;

/// Runs one case with landmarks (or without) and returns the result.
pub fn run(case: &Case, opts: &ConformOptions, landmarks: bool) -> Conformed {
    let lm = landmarks.then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
    conform(&case.template, &case.scan, lm, opts, &mut |_| {}).expect("conformation runs")
}
