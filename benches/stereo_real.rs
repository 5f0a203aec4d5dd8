//! Disparity on recorded stereo pairs with ground truth (`tests/data/stereo/`, issue 14's
//! development set): conformd's defaults against stock OpenCV SGBM_3WAY with the ordinary
//! settings of OpenCV's own sample (block 5, P1 200, P2 800, uniqueness 10, speckle 100 /
//! 32, left-right 1, pre-filter cap 63): the share of valid pixels more than 1 px off and
//! the coverage, per pair, for both profiles (`speckle`, the default, tuned on the
//! virtual rig's projected pattern, and `natural`), and the seconds each takes; then KITTI
//! #70 replayed as a capture set (`import-pair`) through `reconstruct`, its scan scored
//! in depth. Run: `cargo bench --bench stereo_real`.

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
        "KITTI 2012 #70 (1241x376)",
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
        let mut seconds = Vec::new();
        let mut run = |o: &SgbmOptions| {
            let t = std::time::Instant::now();
            let d =
                disparity::disparity(lg.as_raw(), rg.as_raw(), lg.width(), lg.height(), o).unwrap();
            seconds.push(t.elapsed().as_secs_f64());
            score(&d, &truth, 0).unwrap()
        };
        let natural = SgbmOptions {
            num_disparities: ndisp,
            ..SgbmOptions::for_profile(Profile::Natural)
        };
        let (speckle, natural) = (run(&o), run(&natural));
        let t = std::time::Instant::now();
        let stock = disparity::stock_sgbm(lg.as_raw(), rg.as_raw(), lg.width(), lg.height(), ndisp)
            .unwrap();
        seconds.push(t.elapsed().as_secs_f64());
        let cells = [speckle, natural, score(&stock, &truth, 0).unwrap()]
            .map(|s| format!("{:>6.2}% / {:>5.1}%", s.bad1 * 100.0, s.coverage * 100.0));
        println!(
            "{name:<34} {:>18} {:>18} {:>18}   seconds {:.3} / {:.3} / {:.3}",
            cells[0], cells[1], cells[2], seconds[0], seconds[1], seconds[2]
        );
    }
    // a recorded pair replayed as a station's capture set, scored in depth
    let kitti = root.join("kitti-000070");
    let dir = tempfile::tempdir().unwrap();
    let p = conformd::jobs::import_pair(
        &kitti.join("left.png"),
        &kitti.join("right.png"),
        &kitti.join("calib.txt"),
        Some(&kitti.join("disp_noc.png")),
        None,
        dir.path(),
    )
    .unwrap();
    let mut station =
        conformd::stereo::rig::Reconstruction::load(&p.rig, Some(&p.calibration)).unwrap();
    let scan_path = dir.path().join("scan.ply");
    let (scan, r) =
        conformd::jobs::reconstruct_scan(&mut station, &p.capture, &scan_path, None, false)
            .unwrap();
    let s =
        conformd::jobs::score_scan(&scan, &station, None, p.truth.as_ref().unwrap(), None).unwrap();
    println!(
        "KITTI #70 replayed (import-pair, reconstruct, natural profile; {:.2} s): {s}",
        r.seconds_total
    );
}
