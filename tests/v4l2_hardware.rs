//! A real V4L2 camera: listed, opened, configured and grabbed from without hanging past
//! the deadline. It needs a camera, so it is ignored by default and counted as skipped in
//! `make test`'s closing line; `make test-hardware` runs it on a station. What runs
//! everywhere is the listing's check against `/dev`.

use conformd::devices::camera::{Camera, CameraInfo, CameraSettings, monotonic_now};
use conformd::devices::v4l2::{V4l2Camera, list_devices};
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
    // a size the device offers in a format the station reads
    let dev = v4l::Device::with_path(&d.path).expect("the device opens");
    let (format, (width, height)) = V4l2Camera::offered(&dev)
        .expect("the device lists its formats")
        .into_iter()
        .find_map(|(f, sizes)| sizes.first().map(|s| (f, *s)))
        .unwrap_or_else(|| panic!("{} offers no MJPG, YUYV or GREY size", d.path.display()));
    drop(dev);
    let info = CameraInfo {
        id: "hw".into(),
        pod: "p".into(),
        side: "left".into(),
    };
    let mut cam = V4l2Camera::open(info, d.path.to_str().unwrap()).expect("opens");
    let settings = CameraSettings {
        format,
        width,
        height,
        ..Default::default()
    };
    cam.configure(&settings).expect("configures");
    // twice: every arming starts a fresh stream, counted from 0
    for round in 0..2 {
        cam.arm().expect("arms");
        // a free-running camera: the software trigger's moment, taken after arming
        let fired_at = monotonic_now();
        let deadline = Instant::now() + Duration::from_secs(2);
        let f = cam.grab(fired_at, deadline).expect("a frame within 2 s");
        assert!(
            Instant::now() < deadline + Duration::from_millis(500),
            "grab kept its deadline"
        );
        assert_eq!((f.width, f.height), (width, height), "round {round}");
        assert_eq!(
            f.sequence, 0,
            "round {round}: the first frame of the stream"
        );
        assert!(
            f.sensor_time >= fired_at,
            "round {round}: the frame ({:?}) was exposed before the trigger ({fired_at:?})",
            f.sensor_time
        );
        assert!(
            f.sensor_time < fired_at + Duration::from_secs(2),
            "round {round}: the frame's timestamp is on another clock"
        );
        eprintln!(
            "round {round}: {} {format:?} {width}x{height}, sequence 0, {:.1} ms after the trigger",
            d.path.display(),
            (f.sensor_time - fired_at).as_secs_f64() * 1e3
        );
        cam.close();
    }
}
