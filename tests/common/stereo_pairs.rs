//! The recorded stereo pairs with ground truth in `tests/data/stereo`, one list for the
//! stereo tests and `benches/stereo_real.rs`.

/// A recorded pair: its folder, a name to print, the left and right images and the
/// truth (paths under `tests/data/stereo`), the disparity range, the truth's scale
/// (`None`: its format's), and whether it is in the validation part.
pub struct RecordedPair {
    pub dir: &'static str,
    pub name: String,
    pub left: String,
    pub right: String,
    pub truth: String,
    pub disparities: i32,
    pub truth_scale: Option<f64>,
    pub validation: bool,
}

/// The development pairs (the profiles were chosen on Middlebury 2003's quarter-size
/// cones and teddy and KITTI #70; Middlebury 2005's art, dolls and moebius joined
/// later), then the validation pairs (Middlebury 2005's books, laundry and reindeer, on
/// which no setting was chosen). Middlebury 2005's are third size: views 1 and 5, the
/// truth x 3, disparities under 80.
pub fn recorded_pairs() -> Vec<RecordedPair> {
    let file = |dir: &str, f: &str| format!("{dir}/{f}");
    let mut v: Vec<RecordedPair> = [
        (
            "cones",
            "Middlebury cones (2003, 450x375)",
            "im2.png",
            "im6.png",
            "disp2.png",
            64,
        ),
        (
            "teddy",
            "Middlebury teddy (2003, 450x375)",
            "im2.png",
            "im6.png",
            "disp2.png",
            64,
        ),
        (
            "kitti-000070",
            "KITTI 2012 #70 (1241x376)",
            "left.png",
            "right.png",
            "disp_noc.png",
            128,
        ),
    ]
    .map(|(dir, name, l, r, t, disparities)| RecordedPair {
        dir,
        name: name.into(),
        left: file(dir, l),
        right: file(dir, r),
        truth: file(dir, t),
        disparities,
        truth_scale: None,
        validation: false,
    })
    .into();
    for (dir, width, validation) in [
        ("art", 463, false),
        ("dolls", 463, false),
        ("moebius", 463, false),
        ("books", 463, true),
        ("laundry", 447, true),
        ("reindeer", 447, true),
    ] {
        v.push(RecordedPair {
            dir,
            name: format!("Middlebury {dir} (2005, {width}x370)"),
            left: file(dir, "view1.png"),
            right: file(dir, "view5.png"),
            truth: file(dir, "disp1.png"),
            disparities: 80,
            truth_scale: Some(3.0),
            validation,
        });
    }
    v
}
