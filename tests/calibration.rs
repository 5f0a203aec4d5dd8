//! Stereo calibration from simulated chessboard views (release builds): focal lengths and
//! baseline recovered within 0.5%, RMS reprojection error below 0.3 px.

use conformd::synth::rig::{Chessboard, RigFile, chessboard_poses, render_chessboard};

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: runs in release builds")]
fn calibration_recovers_focal_length_and_baseline() {
    let mut rig: RigFile = toml::from_str(
        &std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/rig.example.toml"
        ))
        .unwrap(),
    )
    .unwrap();
    rig.pods[0].image = [960, 720];
    rig.pods[0].focal_px = 825.0;
    let pod = &rig.pods()[0];
    let cb = Chessboard {
        cols: 9,
        rows: 6,
        square: 0.04,
    };
    let poses = chessboard_poses(pod, &rig.pods[0], &cb, 15, 3);
    let pairs: Vec<(Vec<u8>, Vec<u8>)> = poses
        .iter()
        .enumerate()
        .map(|(k, b)| {
            (
                render_chessboard(pod, false, &cb, b, 1.0, k as u64),
                render_chessboard(pod, true, &cb, b, 1.0, k as u64),
            )
        })
        .collect();
    let (got, report) =
        conformd::stereo::calibrate::calibrate(&pairs, 960, 720, 9, 6, 0.04, "pod1")
            .expect("calibrates");
    let rel = |a: f64, b: f64| (a - b).abs() / b;
    eprintln!(
        "calibration: {} of {} views used (skipped {:?}), RMS {:.3} px; fx {:.2} / {:.2} (true {:.2}), fy {:.2}, baseline {:.4} m (true {:.4}); per-view left RMS max {:.3}",
        report.used.len(),
        report.views,
        report.skipped,
        report.rms,
        got.left.fx,
        got.right.fx,
        pod.left.fx,
        got.left.fy,
        got.baseline(),
        pod.baseline(),
        report.per_view_left.iter().cloned().fold(0.0, f64::max)
    );
    assert!(report.used.len() >= 10);
    assert!(report.rms < 0.3, "RMS {:.3} px", report.rms);
    for f in [got.left.fx, got.left.fy, got.right.fx, got.right.fy] {
        assert!(
            rel(f, pod.left.fx) < 0.005,
            "focal {f:.2} vs {:.2}",
            pod.left.fx
        );
    }
    assert!(
        rel(got.baseline(), pod.baseline()) < 0.005,
        "baseline {:.4} vs {:.4}",
        got.baseline(),
        pod.baseline()
    );
}
