//! Disparity on recorded stereo pairs with ground truth (`tests/data/stereo/`, issue 14's
//! development set): conformd's defaults against stock OpenCV SGBM_3WAY with the ordinary
//! settings of OpenCV's own sample (block 5, P1 200, P2 800, uniqueness 10, speckle 100 /
//! 32, left-right 1, pre-filter cap 63): the share of valid pixels more than 1 px off and
//! the coverage, per pair, for both profiles (`speckle`, the default, tuned on the
//! virtual rig's projected pattern, and `natural`), and the seconds each takes; then KITTI
//! #70 replayed as a capture set (`import-pair`) through `reconstruct`, its scan scored
//! in depth. Per pair also the natural profile's most confident pixels at stock's
//! coverage, and every pair's coverage/error curve (pixels kept in order of confidence)
//! drawn into a PNG (`-- --plot FILE.png`, default `target/stereo-curves.png`).
//! Run: `cargo bench --bench stereo_real`.

use conformd::render::plot::{Series, xy_png};
use conformd::stereo::disparity::{self, Profile, SgbmOptions};
use conformd::stereo::truth::{read_truth, score, score_at_coverage};
use std::path::Path;

#[path = "../tests/common/stereo_pairs.rs"]
mod stereo_pairs;

fn grey(p: &Path) -> image::GrayImage {
    image::open(p).unwrap().to_luma8()
}

fn main() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stereo");
    println!(
        "{:<42} {:>18} {:>18} {:>18}   (bad > 1 px of valid / coverage)",
        "pair", "speckle (default)", "natural profile", "stock SGBM_3WAY"
    );
    let mut curves: Vec<Series> = Vec::new();
    for pair in stereo_pairs::recorded_pairs() {
        let name = if pair.validation {
            format!("{} (val.)", pair.name)
        } else {
            pair.name.clone()
        };
        let (name, ndisp) = (name.as_str(), pair.disparities);
        let (l, r, t) = (&pair.left, &pair.right, &pair.truth);
        let (lg, rg) = (grey(&root.join(l)), grey(&root.join(r)));
        let truth = read_truth(&root.join(t), pair.truth_scale).unwrap();
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
        let natural_opts = SgbmOptions {
            num_disparities: ndisp,
            ..SgbmOptions::for_profile(Profile::Natural)
        };
        let (speckle, natural) = (run(&o), run(&natural_opts));
        let t = std::time::Instant::now();
        let stock = disparity::stock_sgbm(lg.as_raw(), rg.as_raw(), lg.width(), lg.height(), ndisp)
            .unwrap();
        seconds.push(t.elapsed().as_secs_f64());
        let stock_score = score(&stock, &truth, 0).unwrap();
        let cells = [speckle, natural, stock_score]
            .map(|s| format!("{:>6.2}% / {:>5.1}%", s.bad1 * 100.0, s.coverage * 100.0));
        println!(
            "{name:<42} {:>18} {:>18} {:>18}   seconds {:.3} / {:.3} / {:.3}",
            cells[0], cells[1], cells[2], seconds[0], seconds[1], seconds[2]
        );
        // the natural profile without its confidence cut, ranked by confidence: the
        // most confident pixels at stock's coverage, and the whole curve
        let ranked = SgbmOptions {
            min_confidence: 0.0,
            ..natural_opts
        };
        let (nd, nc) = disparity::disparity_with_confidence(
            lg.as_raw(),
            rg.as_raw(),
            lg.width(),
            lg.height(),
            &ranked,
        )
        .unwrap();
        let at = score_at_coverage(&nd, &nc, &truth, 0, stock_score.coverage).unwrap();
        println!(
            "{:<42} the most confident at stock's coverage: {:.2}% bad at {:.1}% (stock {:.2}%)",
            "",
            at.bad1 * 100.0,
            at.coverage * 100.0,
            stock_score.bad1 * 100.0
        );
        let full = score(&nd, &truth, 0).unwrap().coverage;
        let points: Vec<(f64, f64)> = (1..=40)
            .map(|k| full * k as f64 / 40.0)
            .filter_map(|c| score_at_coverage(&nd, &nc, &truth, 0, c).ok())
            .map(|s| (s.coverage * 100.0, s.bad1 * 100.0))
            .collect();
        let short = pair.dir;
        curves.push(Series {
            name: format!("{short}: conformd, by confidence"),
            unit: "%".into(),
            points,
        });
        curves.push(Series {
            name: format!("{short}: stock SGBM"),
            unit: "%".into(),
            points: vec![(stock_score.coverage * 100.0, stock_score.bad1 * 100.0)],
        });
    }
    // the curves as a picture: `--plot FILE.png` (default target/stereo-curves.png)
    let args: Vec<String> = std::env::args().collect();
    let plot = args
        .iter()
        .position(|a| a == "--plot")
        .and_then(|i| args.get(i + 1))
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("target/stereo-curves.png"));
    let png = xy_png(
        "Wrong matches against coverage, the most confident pixels first",
        (
            "coverage, % of the pixels with a known truth",
            "more than 1 px off, % of the kept",
        ),
        &curves,
        1000,
        700,
    )
    .unwrap();
    conformd::files::write_atomic(&plot, &png).unwrap();
    println!("coverage/error curves: {}", plot.display());
    // a recorded pair replayed as a station's capture set, scored in depth
    let kitti = root.join("kitti-000070");
    let dir = tempfile::tempdir().unwrap();
    let p = conformd::commands::import_pair(
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
        conformd::commands::reconstruct_scan(&mut station, &p.capture, &scan_path, None, false)
            .unwrap();
    let s = conformd::commands::score_scan(&scan, &station, None, p.truth.as_ref().unwrap(), None)
        .unwrap();
    println!(
        "KITTI #70 replayed (import-pair, reconstruct, natural profile; {:.2} s): {s}",
        r.seconds_total
    );
}
