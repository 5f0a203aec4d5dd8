//! A real V4L2 camera, when this machine has one: listed, opened, configured and grabbed
//! from without hanging past the deadline. Without `/dev/video*` the test says so plainly
//! and checks only that listing finds nothing.

use conformd::rig::camera::{Camera, CameraInfo, CameraSettings};
use conformd::rig::v4l2::{V4l2Camera, list_devices};
use std::time::{Duration, Instant};

#[test]
fn a_real_camera_if_there_is_one() {
    let devices: Vec<_> = std::fs::read_dir("/dev")
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter(|e| e.file_name().to_string_lossy().starts_with("video"))
                .collect()
        })
        .unwrap_or_default();
    let listed = list_devices();
    if devices.is_empty() {
        eprintln!(
            "SKIPPED: no /dev/video* device on this machine; the V4L2 backend was only unit-tested"
        );
        assert!(listed.is_empty());
        return;
    }
    let Some(d) = listed.first() else {
        eprintln!("SKIPPED: /dev/video* exists but none can be queried as a capture device");
        return;
    };
    let info = CameraInfo {
        id: "hw".into(),
        pod: "p".into(),
        side: "left".into(),
    };
    let mut cam = V4l2Camera::open(info, d.path.to_str().unwrap()).expect("opens");
    let offered = format!("{:?}", d.formats);
    let settings = CameraSettings {
        width: 640,
        height: 480,
        ..Default::default()
    };
    match cam.configure(&settings) {
        Ok(()) => {
            cam.arm().expect("arms");
            let deadline = Instant::now() + Duration::from_secs(2);
            let r = cam.grab(deadline);
            assert!(
                Instant::now() < deadline + Duration::from_millis(500),
                "grab kept its deadline"
            );
            eprintln!(
                "grab from {}: {:?}",
                d.path.display(),
                r.map(|f| (f.width, f.height, f.sequence))
            );
        }
        Err(e) => eprintln!("{} cannot give 640x480 ({offered}): {e}", d.path.display()),
    }
}
