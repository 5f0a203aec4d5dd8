//! Capture sessions with replay cameras: a good capture writes a complete set with a
//! valid manifest; each injected fault (timeout, lost frame, skew, box error, unwritable
//! directory) leaves no visible partial set and reports the reason; 100 captures in a
//! row leave exactly 100 sets. Cameras on simulated V4L2 drivers (triggered and
//! free-running) show that arming starts streaming and that no frame from before the
//! trigger is taken.
use crate::common;
use common::{CHILD_LIMIT, Deadline};

use conformd::devices::camera::{Camera, CameraInfo, CameraSettings, PixelFormat};
use conformd::devices::capture::{
    CaptureError, CaptureOptions, Manifest, Session, SoftwareTrigger, Trigger,
};
use conformd::devices::replay::{Fault, ReplayCamera};
use conformd::devices::trigger::TriggerError;
use conformd::devices::v4l2::V4l2Camera;
use conformd::synth::v4l2_driver::{Mode, SimulatedDriver, SimulatedTrigger};
use std::path::Path;
use std::time::Duration;

fn cameras(faults: &[(usize, usize, Fault)]) -> Vec<Box<dyn Camera>> {
    let mut out: Vec<Box<dyn Camera>> = Vec::new();
    for (k, (pod, side)) in [
        ("pod1", "left"),
        ("pod1", "right"),
        ("pod2", "left"),
        ("pod2", "right"),
    ]
    .iter()
    .enumerate()
    {
        let info = CameraInfo {
            id: format!("{pod}-{side}"),
            pod: pod.to_string(),
            side: side.to_string(),
        };
        let mut cam = ReplayCamera::synthetic(info, 64, 48);
        for (c, at, f) in faults {
            if *c == k {
                cam = cam.fault_at(*at, f.clone());
            }
        }
        out.push(Box::new(cam));
    }
    out
}

fn settings() -> CameraSettings {
    CameraSettings {
        format: PixelFormat::Grey,
        width: 64,
        height: 48,
        exposure_us: Some(8000),
        ..Default::default()
    }
}

fn session(
    root: &Path,
    cams: Vec<Box<dyn Camera>>,
    trigger: Box<dyn Trigger + Send>,
    opts: CaptureOptions,
) -> Session {
    let mut s = Session::new(cams, trigger, root, opts, settings());
    s.configure().unwrap();
    s
}

/// A short window; a skew limit loose enough that a loaded test machine pausing between
/// arming two replay cameras is not taken for a skewed rig.
fn quick() -> CaptureOptions {
    CaptureOptions {
        window_ms: 150,
        retries: 0,
        max_skew_ms: 50.0,
        ..Default::default()
    }
}

/// Nothing half-written is visible: every entry of `captures/` is a set with a manifest
/// (or the `failed/` folder), no `.partial` folder remains.
fn only_complete_sets(root: &Path) -> usize {
    let mut n = 0;
    for e in std::fs::read_dir(root).unwrap().filter_map(|e| e.ok()) {
        let name = e.file_name().to_string_lossy().to_string();
        assert!(
            !name.ends_with(".partial"),
            "partial set {name} left behind"
        );
        if name == "failed" {
            continue;
        }
        assert!(
            e.path().join("manifest.json").exists(),
            "{name} has no manifest"
        );
        n += 1;
    }
    n
}

#[test]
fn a_good_capture_writes_a_complete_set() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = session(dir.path(), cameras(&[]), Box::new(SoftwareTrigger), quick());
    let set = s.capture(Some("sow-412")).expect("captures");
    let m = Manifest::read(&set.dir).unwrap();
    assert_eq!(m.id, set.id);
    assert_eq!(m.subject.as_deref(), Some("sow-412"));
    assert_eq!(m.cameras.len(), 4);
    assert_eq!(m.trigger.kind, "software");
    for c in &m.cameras {
        let img = image::open(set.dir.join(&c.file)).expect("the image reads back");
        assert_eq!(
            (img.width(), img.height(), c.exposure_us),
            (64, 48, Some(8000))
        );
    }
    assert_eq!(only_complete_sets(dir.path()), 1);
    // the set replays: a replay camera serves the recorded image
    let info = CameraInfo {
        id: "pod2-left".into(),
        pod: "pod2".into(),
        side: "left".into(),
    };
    let mut r = ReplayCamera::from_capture_sets(info, &[&set.dir]).unwrap();
    r.arm().unwrap();
    let f = r
        .grab(
            conformd::devices::camera::monotonic_now(),
            std::time::Instant::now() + Duration::from_millis(100),
        )
        .unwrap();
    assert_eq!((f.width, f.height), (64, 48));
}

struct RefusingBox;
impl Trigger for RefusingBox {
    fn kind(&self) -> &'static str {
        "serial"
    }
    fn arm(&mut self, _: u32) -> Result<(), TriggerError> {
        Ok(())
    }
    fn fire(&mut self, seq: u32, _: u32) -> Result<Option<u64>, TriggerError> {
        Err(TriggerError::Refused {
            port: "sim".into(),
            command: format!("FIRE {seq}"),
            code: "E_FLASH".into(),
            text: "flash not charged".into(),
        })
    }
}

#[test]
fn every_fault_leaves_nothing_half_written_and_says_why() {
    // (name, faults as (camera, capture, fault), expected words)
    type Case = (&'static str, Vec<(usize, usize, Fault)>, &'static str);
    let cases: Vec<Case> = vec![
        (
            "timeout",
            vec![(2, 0, Fault::Timeout)],
            "camera pod2-left: no frame within",
        ),
        (
            "lost frame",
            vec![(1, 0, Fault::LostFrame)],
            "camera pod1-right: frame 0 was lost",
        ),
        (
            "skew",
            vec![(3, 0, Fault::Skew(Duration::from_millis(120)))],
            "(at most 50 ms): pod2-right is 1",
        ),
        (
            "unplugged",
            vec![(0, 0, Fault::Device("device disconnected".into()))],
            "camera pod1-left: device disconnected",
        ),
    ];
    for (what, faults, reason) in cases {
        let dir = tempfile::tempdir().unwrap();
        let mut s = session(
            dir.path(),
            cameras(&faults),
            Box::new(SoftwareTrigger),
            quick(),
        );
        let e = s.capture(None).expect_err(what).to_string();
        assert!(e.contains(reason), "{what}: {e}");
        assert_eq!(only_complete_sets(dir.path()), 0, "{what}");
    }
    // the box refuses to fire
    let dir = tempfile::tempdir().unwrap();
    let mut s = session(dir.path(), cameras(&[]), Box::new(RefusingBox), quick());
    let e = s.capture(None).unwrap_err().to_string();
    assert!(
        e.contains("refused FIRE 1: E_FLASH flash not charged"),
        "{e}"
    );
    assert_eq!(only_complete_sets(dir.path()), 0);
    // the capture folder cannot be written (a file stands where a folder should)
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("captures"), b"not a folder").unwrap();
    let root = dir.path().join("captures").join("sets");
    let mut s = session(&root, cameras(&[]), Box::new(SoftwareTrigger), quick());
    let e = s.capture(None).unwrap_err();
    assert!(matches!(e, CaptureError::Write { .. }), "{e}");
    assert!(
        e.to_string().contains("captures/sets") && e.to_string().contains("Not a directory"),
        "{e}"
    );
}

#[test]
fn failed_sets_can_be_kept_with_their_reason_and_retries_recover() {
    let dir = tempfile::tempdir().unwrap();
    let opts = CaptureOptions {
        keep_failed: true,
        ..quick()
    };
    let mut s = session(
        dir.path(),
        cameras(&[(0, 0, Fault::Skew(Duration::from_millis(90)))]),
        Box::new(SoftwareTrigger),
        opts,
    );
    let e = s.capture(None).unwrap_err().to_string();
    let failed: Vec<_> = std::fs::read_dir(dir.path().join("failed"))
        .unwrap()
        .filter_map(|e| e.ok())
        .collect();
    assert_eq!(failed.len(), 1);
    let reason = std::fs::read_to_string(failed[0].path().join("reason.txt")).unwrap();
    assert!(
        reason.contains("sensor timestamps spread 9")
            && reason.contains("(at most 50 ms)")
            && e.contains("at most 50 ms"),
        "{reason}"
    );
    assert_eq!(only_complete_sets(dir.path()), 0);

    // one retry: the first attempt times out, the second succeeds
    let dir = tempfile::tempdir().unwrap();
    let opts = CaptureOptions {
        retries: 1,
        ..quick()
    };
    let mut s = session(
        dir.path(),
        cameras(&[(1, 0, Fault::Timeout)]),
        Box::new(SoftwareTrigger),
        opts,
    );
    let set = s.capture(None).expect("the retry succeeds");
    assert_eq!(set.attempts, 2);
    assert_eq!(only_complete_sets(dir.path()), 1);
}

#[test]
fn a_hundred_captures_leave_a_hundred_sets() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = session(dir.path(), cameras(&[]), Box::new(SoftwareTrigger), quick());
    let mut ids = Vec::new();
    for _ in 0..100 {
        ids.push(s.capture(None).expect("captures").id);
    }
    assert_eq!(only_complete_sets(dir.path()), 100);
    let mut sorted = ids.clone();
    sorted.sort();
    assert_eq!(sorted, ids, "ids are time-ordered");
    sorted.dedup();
    assert_eq!(sorted.len(), 100, "ids are unique");
    assert!(
        ids.iter().all(|i| i
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '.')),
        "ids are safe file names"
    );
}

#[test]
fn capture_from_a_station_config() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = common::synthetic_station(dir.path(), None);
    let out = common::succeeded(
        std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
            .args([
                "capture",
                "--config",
                cfg.to_str().unwrap(),
                "--subject",
                "pig-7",
            ])
            .output_within(CHILD_LIMIT),
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("captured") && text.contains("2 cameras"),
        "{text}"
    );
    assert_eq!(only_complete_sets(&dir.path().join("captures")), 1);
    std::fs::write(&cfg, "[capture]\nroot = \"c\"\n").unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
        .args(["capture", "--config", cfg.to_str().unwrap()])
        .output_within(CHILD_LIMIT);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("station.toml"),
        "{err}"
    );
}

/// Four cameras on simulated V4L2 drivers (8x6 GREY), behind the real camera's frame
/// logic, and a trigger box wired to them.
fn driven_rig(
    mode: Mode,
    arm_delay: Duration,
) -> (
    Vec<Box<dyn Camera>>,
    SimulatedTrigger,
    Vec<conformd::synth::v4l2_driver::TriggerLine>,
) {
    let mut cams: Vec<Box<dyn Camera>> = Vec::new();
    let mut lines = Vec::new();
    for (pod, side) in [
        ("pod1", "left"),
        ("pod1", "right"),
        ("pod2", "left"),
        ("pod2", "right"),
    ] {
        let driver = SimulatedDriver::new(mode, vec![90; 48]);
        lines.push(driver.line());
        let info = CameraInfo {
            id: format!("{pod}-{side}"),
            pod: pod.into(),
            side: side.into(),
        };
        cams.push(Box::new(V4l2Camera::with_queue(
            info,
            format!("/dev/sim-{pod}-{side}").into(),
            Box::new(driver),
            PixelFormat::Grey,
            8,
            6,
        )));
    }
    let trigger = SimulatedTrigger {
        lines: lines.clone(),
        arm_delay,
        fired: Default::default(),
    };
    (cams, trigger, lines)
}

fn driven_settings() -> CameraSettings {
    CameraSettings {
        width: 8,
        height: 6,
        external_trigger: true,
        ..settings()
    }
}

/// Externally triggered cameras make a frame only for a pulse that comes while they
/// stream: arming must have started streaming (fails with a time-out otherwise), the
/// frame taken is the triggered one (sequence 0 of a fresh stream, stamped at the pulse),
/// and streaming stops after the set. A stray pulse before arming makes nothing.
#[test]
fn arming_starts_streaming_so_the_triggered_frame_is_taken() {
    let dir = tempfile::tempdir().unwrap();
    let (cams, trigger, lines) = driven_rig(Mode::Triggered, Duration::ZERO);
    let fired = trigger.fired.clone();
    for l in &lines {
        l.pulse(); // before any arming: lost, as on a device not streaming
    }
    let mut s = Session::new(
        cams,
        Box::new(trigger),
        dir.path(),
        quick(),
        driven_settings(),
    );
    s.configure().unwrap();
    for round in 0..3 {
        let set = s
            .capture(None)
            .unwrap_or_else(|e| panic!("round {round}: {e}"));
        let pulse = *fired.lock().unwrap().last().unwrap();
        for c in &set.manifest.cameras {
            let t = Duration::from_micros(c.sensor_timestamp_us);
            assert_eq!(c.sequence, 0, "round {round}, {}: a fresh stream", c.id);
            assert!(
                t >= pulse - Duration::from_micros(1) && t < pulse + Duration::from_millis(100),
                "round {round}, {}: stamped {t:?}, the pulse was at {pulse:?}",
                c.id
            );
            assert_eq!((c.width, c.height), (8, 6));
        }
    }
    for l in &lines {
        let n = l.counts();
        assert_eq!((n.starts, n.pulses_lost, n.dequeued), (3, 1, 3), "{n:?}");
        assert!(!l.streaming(), "streaming stopped after the set");
    }
    assert_eq!(only_complete_sets(dir.path()), 3);
}

/// Free-running cameras stream from arming on; with a trigger box that takes 30 ms to arm
/// (a serial round trip), every buffer holds a frame from before the pulse when it fires.
/// None of those may be taken: each camera's frame is the first exposed after the pulse.
#[test]
fn a_frame_from_before_the_trigger_is_never_taken() {
    let dir = tempfile::tempdir().unwrap();
    let period = Duration::from_millis(3);
    let (cams, trigger, lines) =
        driven_rig(Mode::FreeRunning { period }, Duration::from_millis(30));
    let fired = trigger.fired.clone();
    // free-running cameras are not in step with each other: the spread is not this test's
    let opts = CaptureOptions {
        window_ms: 500,
        max_skew_ms: 1000.0,
        ..quick()
    };
    let mut s = Session::new(cams, Box::new(trigger), dir.path(), opts, driven_settings());
    s.configure().unwrap();
    for round in 0..3 {
        let set = s
            .capture(None)
            .unwrap_or_else(|e| panic!("round {round}: {e}"));
        let pulse = *fired.lock().unwrap().last().unwrap();
        for c in &set.manifest.cameras {
            let t = Duration::from_micros(c.sensor_timestamp_us);
            assert!(
                t >= pulse,
                "round {round}, {}: frame {} exposed {:.2} ms before the trigger was taken",
                c.id,
                c.sequence,
                (pulse - t).as_secs_f64() * 1e3
            );
            // frames came and were passed over: about 10 in the 30 ms before the pulse
            assert!(c.sequence >= 5, "round {round}, {}: {}", c.id, c.sequence);
        }
    }
    for l in &lines {
        assert!(
            l.counts().dropped > 0,
            "the buffers filled before the pulse"
        );
    }
}

/// Two `conformd capture` runs at once into one `captures/` folder (two stations sharing
/// it, or a script and the daemon), 40 times: 80 sets, each with its own subject and
/// its own images, none overwritten or mixed.
#[test]
fn concurrent_captures_into_one_folder_never_share_an_id() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = common::synthetic_station(dir.path(), None);
    let run = |subject: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
            .args([
                "capture",
                "--config",
                cfg.to_str().unwrap(),
                "--subject",
                subject,
            ])
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap()
    };
    let mut subjects = std::collections::BTreeSet::new();
    for round in 0..40 {
        let (a, b) = (format!("pig-{round}a"), format!("pig-{round}b"));
        let (pa, pb) = (run(&a), run(&b));
        for (p, s) in [(pa, &a), (pb, &b)] {
            let out = common::deadline::output_of(p, &format!("capture {s}"), CHILD_LIMIT);
            assert!(
                out.status.success(),
                "round {round}, {s}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        subjects.insert(a);
        subjects.insert(b);
    }
    let root = dir.path().join("captures");
    assert_eq!(only_complete_sets(&root), 80);
    let mut on_sets = std::collections::BTreeSet::new();
    for e in std::fs::read_dir(&root).unwrap().flatten() {
        let m = Manifest::read(&e.path()).unwrap();
        assert_eq!(
            m.id,
            e.file_name().to_string_lossy(),
            "the folder is its id"
        );
        let files: std::collections::BTreeSet<String> = std::fs::read_dir(e.path())
            .unwrap()
            .flatten()
            .map(|f| f.file_name().to_string_lossy().to_string())
            .collect();
        let listed: std::collections::BTreeSet<String> = m
            .cameras
            .iter()
            .map(|c| c.file.clone())
            .chain(["manifest.json".to_string()])
            .collect();
        assert_eq!(files, listed, "{}: only its own files", m.id);
        assert!(
            on_sets.insert(m.subject.clone().unwrap()),
            "two sets carry {:?}",
            m.subject
        );
    }
    assert_eq!(on_sets, subjects, "every subject on exactly one set");
}
