//! Disparity on recorded stereo pairs with ground truth (`tests/data/stereo/`, issue 14's
//! development set): conformd's defaults against stock OpenCV SGBM_3WAY with the ordinary
//! settings of OpenCV's own sample (block 5, P1 200, P2 800, uniqueness 10, speckle 100 /
//! 32, left-right 1, pre-filter cap 63): the share of valid pixels more than 1 px off and
//! the coverage, per pair, for both profiles (`speckle`, the default, tuned on the
//! virtual rig's projected pattern, and `natural`). Run: `cargo bench --bench stereo_real`.

use conformd::stereo::disparity::{self, Profile, SgbmOptions};
use conformd::stereo::truth::{read_truth, score};
use std::path::Path;

/// (name, left, right, truth, disparities)
const PAIRS: [(&str, &str, &str, &str, i32); 3] = [
    (
        "Middlebury cones (2003, 450x375)",
        "cones/im2.png",
        "cones/im6.png",
        "cones/disp2.png",
        64,
    ),
    (
        "Middlebury teddy (2003, 450x375)",
        "teddy/im2.png",
        "teddy/im6.png",
        "teddy/disp2.png",
        64,
    ),
    (
        "KITTI 2012 #70 (1226x370)",
        "kitti-000070/left.png",
        "kitti-000070/right.png",
        "kitti-000070/disp_noc.png",
        128,
    ),
];

fn grey(p: &Path) -> image::GrayImage {
    image::open(p).unwrap().to_luma8()
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stereo");
    println!(
        "{:<34} {:>18} {:>18} {:>18}   (bad > 1 px of valid / coverage)",
        "pair", "speckle (default)", "natural profile", "stock SGBM_3WAY"
    );
    for (name, l, r, t, ndisp) in PAIRS {
        let (lg, rg) = (grey(&root.join(l)), grey(&root.join(r)));
        let truth = read_truth(&root.join(t), None).unwrap();
        let o = SgbmOptions {
            num_disparities: ndisp,
            ..Default::default()
        };
        let run = |o: &SgbmOptions| {
            let d =
                disparity::disparity(lg.as_raw(), rg.as_raw(), lg.width(), lg.height(), o).unwrap();
            score(&d, &truth, 0).unwrap()
        };
        let natural = SgbmOptions {
            num_disparities: ndisp,
            ..SgbmOptions::for_profile(Profile::Natural)
        };
        let cells = [
            run(&o),
            run(&natural),
            score(
                &disparity::stock_sgbm(lg.as_raw(), rg.as_raw(), lg.width(), lg.height(), ndisp)
                    .unwrap(),
                &truth,
                0,
            )
            .unwrap(),
        ]
        .map(|s| format!("{:>6.2}% / {:>5.1}%", s.bad1 * 100.0, s.coverage * 100.0));
        println!(
            "{name:<34} {:>18} {:>18} {:>18}",
            cells[0], cells[1], cells[2]
        );
    }
}
