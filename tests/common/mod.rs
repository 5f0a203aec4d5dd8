//! Helpers shared by the integration tests.
#![allow(dead_code)]

pub mod deadline;
pub mod postgres;
pub mod stereo_pairs;

use conformd::conform::{ConformOptions, Conformed, conform};
use conformd::synth::cases::Case;
#[allow(unused_imports)]
pub use deadline::{CHILD_LIMIT, Deadline};

/// A program the test started, killed when the test ends, passing or failing, with its
/// process group when it leads one (`process_group(0)`), so no worker, daemon or job of
/// theirs outlives the test.
pub struct GroupChild(Option<std::process::Child>);

impl GroupChild {
    pub fn new(child: std::process::Child) -> Self {
        GroupChild(Some(child))
    }

    /// The child itself, no longer killed on drop (for a caller that waits it out
    /// within its own deadline).
    pub fn into_inner(mut self) -> std::process::Child {
        self.0.take().expect("a child")
    }
}

impl std::ops::Deref for GroupChild {
    type Target = std::process::Child;
    fn deref(&self) -> &Self::Target {
        self.0.as_ref().expect("a child")
    }
}

impl std::ops::DerefMut for GroupChild {
    fn deref_mut(&mut self) -> &mut Self::Target {
        self.0.as_mut().expect("a child")
    }
}

impl Drop for GroupChild {
    fn drop(&mut self) {
        let Some(child) = self.0.as_mut() else {
            return;
        };
        // the group may outlive its leader (a job of a killed worker); a program in
        // the test's own group has none of its own, and is killed alone
        let _ = std::process::Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", child.id())])
            .stderr(std::process::Stdio::null())
            .status();
        let _ = child.kill();
        let _ = child.wait();
    }
}

/// `out`, when its command succeeded; otherwise the test fails with the command's
/// exit status and standard error (what a person reads first).
pub fn succeeded(out: std::process::Output) -> std::process::Output {
    assert!(
        out.status.success(),
        "the command failed ({}): {}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// The captures the logs `logs` say were recorded done (by a job's end, or adopted
/// from a complete result at a start), sorted, once per line that says so.
pub fn recorded_done(logs: &[std::path::PathBuf]) -> Vec<String> {
    let mut ids: Vec<String> = logs
        .iter()
        .flat_map(|l| {
            std::fs::read_to_string(l)
                .unwrap()
                .lines()
                .filter(|line| line.contains(" done"))
                .filter_map(|line| {
                    line.split_whitespace()
                        .find_map(|w| w.strip_prefix("capture="))
                        .map(str::to_string)
                })
                .collect::<Vec<_>>()
        })
        .collect();
    ids.sort();
    ids
}

/// Runs the `conformd` binary with `args` in `dir`, within the children's deadline.
pub fn conformd(args: &[&str], dir: &std::path::Path) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
        .args(args)
        .current_dir(dir)
        .output_within(CHILD_LIMIT)
}

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

/// A station file with two synthetic cameras writing to `captures/` beside it; with
/// `trigger`, fired through the trigger box at that device (their frames then wait for
/// its pulse).
pub fn synthetic_station(
    dir: &std::path::Path,
    trigger: Option<&std::path::Path>,
) -> std::path::PathBuf {
    let cfg = dir.join("station.toml");
    let trigger = trigger.map_or(String::new(), |d| {
        format!(
            "[trigger]\ndevice = \"{}\"\nbaud = 115200\nreply_timeout_ms = 500\n",
            d.display()
        )
    });
    std::fs::write(
        &cfg,
        format!(
            r#"
[capture]
root = "captures"
station = "crate-1"
window_ms = 500
[capture.camera_settings]
format = "GREY"
width = 32
height = 24
external_trigger = {}

{trigger}
[[cameras]]
id = "pod1-left"
pod = "pod1"
side = "left"
synthetic = true

[[cameras]]
id = "pod1-right"
pod = "pod1"
side = "right"
synthetic = true
"#,
            !trigger.is_empty()
        ),
    )
    .unwrap();
    cfg
}
