//! A real V4L2 camera: listed, opened, configured and grabbed from without hanging past
//! the deadline. It needs a camera, so it is ignored by default and counted as skipped in
//! `make test`'s closing line; `make test-hardware` runs it on a station. What runs
//! everywhere is the listing's check against `/dev`.

use conformd::rig::camera::{Camera, CameraInfo, CameraSettings};
use conformd::rig::v4l2::{V4l2Camera, list_devices};
use std::time::{Duration, Instant};

fn video_nodes() -> Vec<std::fs::DirEntry> {
    std::fs::read_dir("/dev")
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter(|e| e.file_name().to_string_lossy().starts_with("video"))
                .collect()
        })
        .unwrap_or_default()
}

#[test]
fn listing_finds_no_camera_where_dev_has_none() {
    // every listed device is a /dev/video* node; none listed where there is none
    let nodes: Vec<String> = video_nodes()
        .iter()
        .map(|e| e.path().display().to_string())
        .collect();
    for d in list_devices() {
        assert!(
            nodes.contains(&d.path.display().to_string()),
            "{} is not a /dev/video* node",
            d.path.display()
        );
    }
}

#[test]
#[ignore = "needs a V4L2 capture device: make test-hardware"]
fn a_real_camera() {
    assert!(
        !video_nodes().is_empty(),
        "no /dev/video* device on this machine"
    );
    let listed = list_devices();
    let d = listed
        .first()
        .expect("a /dev/video* device that can be queried as a capture device");
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
