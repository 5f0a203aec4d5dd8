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

/// One pod's rendered pair matched over its whole images with `o`, the pod's report
/// thrown away: the depth grid alone.
pub fn whole_pod_grid(
    rectifier: &conformd::stereo::reconstruct::PodRectifier,
    left: &[u8],
    right: &[u8],
    o: &conformd::stereo::disparity::SgbmOptions,
) -> conformd::stereo::reconstruct::DepthGrid {
    conformd::stereo::reconstruct::pod_grid(
        rectifier,
        left,
        right,
        o,
        None,
        &mut Default::default(),
    )
    .expect("the pod's pair matches")
}

/// A port on 127.0.0.1 nothing listens on now.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}
