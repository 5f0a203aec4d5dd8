//! The virtual rig renders what stereo needs: a speckled subject whose every surface
//! point looks the same in both cameras of a pod, at the place the calibration predicts
//! (lens distortion included); and `conformd simulate` writes standard capture sets.
use crate::common;
use common::{CHILD_LIMIT, Deadline};

use conformd::stereo::rig::RigFile;
use conformd::synth::virtual_rig::render_camera;
use conformd::template::{self as templates, Kind};

fn rig() -> RigFile {
    let mut r: RigFile = toml::from_str(
        &std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/rig.example.toml"
        ))
        .unwrap(),
    )
    .unwrap();
    for p in &mut r.pods {
        p.image = [480, 360];
        p.focal_px = 420.0;
    }
    r
}

fn ncc(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let cov: f64 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
    let va: f64 = a.iter().map(|x| (x - ma).powi(2)).sum();
    let vb: f64 = b.iter().map(|y| (y - mb).powi(2)).sum();
    cov / (va * vb).sqrt().max(1e-9)
}

#[test]
fn both_cameras_see_the_same_speckle_where_the_calibration_says() {
    let rig = rig();
    let pods = rig.pods();
    let subject = templates::build(Kind::Pig, 4000).mesh;
    let (pod, spec) = (&pods[0], &rig.pods[0]);
    let l = render_camera(pod, spec, false, &subject, 1.0, 1);
    let r = render_camera(pod, spec, true, &subject, 1.0, 1);
    let (w, h) = (l.width as usize, l.height as usize);
    let share = l.points.iter().filter(|p| p.is_some()).count() as f64 / (w * h) as f64;
    assert!(
        (0.05..0.8).contains(&share),
        "the pig fills {:.1}% of the view",
        share * 100.0
    );
    let patch = |img: &[u8], u: usize, v: usize| -> Option<Vec<f64>> {
        if u < 4 || v < 4 || u + 4 >= w || v + 4 >= h {
            return None;
        }
        Some(
            (v - 3..=v + 3)
                .flat_map(|y| (u - 3..=u + 3).map(move |x| img[y * w + x] as f64))
                .collect(),
        )
    };
    let right_pose = pod.right_pose();
    let (mut scores, mut checked) = (Vec::new(), 0);
    for i in (0..w * h).step_by(97) {
        let Some(p) = l.points[i] else { continue };
        let Some(q) = pod.right.project(&right_pose.to_camera(&p)) else {
            continue;
        };
        let (u, v) = (q.x.round() as usize, q.y.round() as usize);
        if u >= w || v >= h {
            continue;
        }
        // visible in the right camera too: it sees the same surface point there
        let Some(pr) = r.points[v * w + u] else {
            continue;
        };
        if (pr - p).norm() > 0.01 {
            continue;
        }
        checked += 1;
        // the right patch sampled bilinearly at the predicted (sub-pixel) place
        let at = |x: f64, y: f64| -> f64 {
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (fx, fy) = (x - x.floor(), y - y.floor());
            let g = |xx: usize, yy: usize| r.pixels[yy * w + xx] as f64;
            g(x0, y0) * (1.0 - fx) * (1.0 - fy)
                + g(x0 + 1, y0) * fx * (1.0 - fy)
                + g(x0, y0 + 1) * (1.0 - fx) * fy
                + g(x0 + 1, y0 + 1) * fx * fy
        };
        // pixel (x, y) is centred on image point (x, y), as in OpenCV
        let (qx, qy) = (q.x, q.y);
        if let (Some(a), true) = (
            patch(&l.pixels, i % w, i / w),
            qx > 4.0 && qy > 4.0 && qx + 5.0 < w as f64 && qy + 5.0 < h as f64,
        ) {
            let b: Vec<f64> = (-3..=3)
                .flat_map(|dy| (-3..=3).map(move |dx| (dx as f64, dy as f64)))
                .map(|(dx, dy)| at(qx + dx, qy + dy))
                .collect();
            scores.push(ncc(&a, &b));
        }
    }
    scores.sort_by(f64::total_cmp);
    let median = scores[scores.len() / 2];
    eprintln!(
        "{checked} points seen by both cameras; patch correlation median {median:.3}, 10th percentile {:.3}",
        scores[scores.len() / 10]
    );
    assert!(checked > 200);
    assert!(
        median > 0.9,
        "left and right patches of one surface point agree: median NCC {median:.3}"
    );
    // the speckle is texture, not noise: neighbouring patches differ
    let a = patch(&l.pixels, w / 2, h / 2).unwrap();
    let b = patch(&l.pixels, w / 2 + 9, h / 2).unwrap();
    assert!(ncc(&a, &b) < 0.7);
}

#[test]
fn simulate_writes_standard_capture_sets() {
    let dir = tempfile::tempdir().unwrap();
    let rig_path = dir.path().join("rig.toml");
    std::fs::write(&rig_path, toml::to_string(&rig()).unwrap()).unwrap();
    common::succeeded(
        std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
            .args([
                "simulate",
                "--rig",
                rig_path.to_str().unwrap(),
                "--subject",
                "pig",
                "--pose",
                "swing=10",
                "--captures",
                "2",
                "--out",
                "sim",
            ])
            .current_dir(dir.path())
            .output_within(CHILD_LIMIT),
    );
    let sets: Vec<_> = std::fs::read_dir(dir.path().join("sim"))
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name() != "calibration")
        .collect();
    assert_eq!(sets.len(), 2);
    for s in &sets {
        let m = conformd::devices::capture::Manifest::read(&s.path()).unwrap();
        assert_eq!(m.cameras.len(), 4);
        for c in &m.cameras {
            let img = image::open(s.path().join(&c.file)).unwrap();
            assert_eq!((img.width(), img.height()), (480, 360));
        }
        assert!(s.path().join("truth.ply").exists());
    }
    let yml = std::fs::read_to_string(dir.path().join("sim/calibration/pod1.yml")).unwrap();
    assert!(yml.contains("M1: !!opencv-matrix") && yml.contains("D2: !!opencv-matrix"));
}

/// Without its projector a pod sees bare, nearly textureless skin: the rendering drops
/// the speckle, and reconstruction leaves the untextured surface out rather than guess
/// (wrong matches are worse than holes): less than half the points (shading on curved
/// parts still carries some texture), and at most 0.2% of them far off.
#[test]
fn without_the_projector_stereo_leaves_holes_not_wrong_points() {
    use conformd::stereo::reconstruct::RectifierCache;
    let mut rig = rig();
    let subject = templates::build(Kind::Pig, 20_000).mesh;
    let surface = conformd::conform::correspond::ScanSurface::new(&subject).unwrap();
    let mut cache = RectifierCache::default();
    let mut seen = Vec::new();
    for projector in [true, false] {
        rig.pods[0].projector = projector;
        let pods = rig.pods();
        let (pod, spec) = (&pods[0], &rig.pods[0]);
        let l = render_camera(pod, spec, false, &subject, 1.0, 1);
        let r = render_camera(pod, spec, true, &subject, 1.0, 1);
        let (rect, _) = cache.get(pod).unwrap();
        let o = conformd::stereo::disparity::SgbmOptions {
            num_disparities: 64,
            ..Default::default()
        };
        let grid = common::whole_pod_grid(rect, &l.pixels, &r.pixels, &o);
        let d: Vec<f64> = grid
            .valid()
            .map(|p| surface.distance(&p) / subject.diagonal())
            .collect();
        // at 480x360 one pixel of disparity is ~8 cm of depth: wrong matches, not
        // noise, are what lies 5% of the diagonal (~8 cm) off
        let far = d.iter().filter(|&&x| x > 0.05).count();
        eprintln!(
            "projector {projector}: {} points, {far} more than 5% of the diagonal off",
            d.len()
        );
        seen.push((d.len(), far));
    }
    assert_eq!(cache.built, 1, "one calibration, one set of maps");
    let ((with, far_with), (without, far_without)) = (seen[0], seen[1]);
    assert!(with > 5000, "{with} points with the projector");
    assert!(
        without * 2 < with,
        "{without} points without vs {with} with"
    );
    assert!(
        far_without * 500 <= without.max(1) && far_with * 500 <= with,
        "wrong points: {far_with} of {with}, {far_without} of {without}"
    );
}
