//! Stereo reconstruction on simulated captures (release builds): a two-pod capture of a
//! pig reconstructs a scan close to the true surface that covers what the cameras see;
//! conformed with the template, it gives dense correspondence against the ground truth.

use conformd::conform::correspond::ScanSurface;
use conformd::conform::{ConformOptions, conform};
use conformd::mesh::landmarks::{Landmark, LandmarkPos};
use conformd::mesh::{V3, read_mesh};
use conformd::synth::rig::RigFile;
use conformd::synth::{scanner, templates};
use std::path::Path;

#[test]
#[cfg_attr(debug_assertions, ignore = "heavy: runs in release builds")]
fn simulate_reconstruct_conform() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let rig_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let sets = conformd::jobs::simulate(&rig_path, "pig", "swing=8,nod=-6", 1, 2.0, &d.join("sim"))
        .unwrap();
    let report = conformd::jobs::reconstruct(
        &sets[0],
        &rig_path,
        Some(&d.join("sim/calibration")),
        &d.join("scan.ply"),
        None,
    )
    .unwrap(); // the calibration files simulate wrote, read back through OpenCV
    let scan = read_mesh(&d.join("scan.ply")).unwrap();
    let truth = read_mesh(&sets[0].join("truth.ply")).unwrap();
    let diag = truth.diagonal();

    // accuracy: scan points against the true surface
    let surface = ScanSurface::new(&truth).unwrap();
    let mut dist: Vec<f64> = scan
        .vertices
        .iter()
        .map(|p| surface.distance(p) / diag)
        .collect();
    dist.sort_by(f64::total_cmp);
    let mean = dist.iter().sum::<f64>() / dist.len() as f64;
    let p95 = dist[dist.len() * 95 / 100];
    eprintln!(
        "distance percentiles 10/50/90: {:.3}% {:.3}% {:.3}%",
        dist[dist.len() / 10] * 100.0,
        dist[dist.len() / 2] * 100.0,
        dist[dist.len() * 9 / 10] * 100.0
    );

    // coverage: the true surface the cameras see, by area, with scan points near it
    let rig = RigFile::load(&rig_path).unwrap();
    let centres: Vec<V3> = rig
        .pods()
        .iter()
        .flat_map(|p| [p.left_pose.centre(), p.right_pose().centre()])
        .collect();
    let seen = scanner::visible_triangles(&truth, &centres);
    let arr: Vec<[f64; 3]> = scan.vertices.iter().map(|p| [p.x, p.y, p.z]).collect();
    let tree: kiddo::ImmutableKdTree<f64, 3> = kiddo::ImmutableKdTree::new_from_slice(&arr);
    let (mut seen_area, mut covered) = (0.0, 0.0);
    for t in (0..truth.triangles.len()).filter(|&t| seen[t]) {
        let a = truth.face_normal_scaled(t).norm() / 2.0;
        let c = truth.corners(t).iter().sum::<V3>() / 3.0;
        seen_area += a;
        if tree
            .nearest_one::<kiddo::SquaredEuclidean>(&[c.x, c.y, c.z])
            .distance
            .sqrt()
            < 0.01 * diag
        {
            covered += a;
        }
    }
    let coverage = covered / seen_area;
    eprintln!(
        "stereo: {} points ({} fused), mean distance {:.3}% p95 {:.3}% of the diagonal, coverage {:.1}% of the seen surface; valid disparity {:?}",
        scan.vertices.len(),
        report.fused_points,
        mean * 100.0,
        p95 * 100.0,
        coverage * 100.0,
        report
            .pods
            .iter()
            .map(|p| format!("{:.0}%", p.valid_disparity_share * 100.0))
            .collect::<Vec<_>>()
    );
    assert!(mean < 0.005, "mean distance {:.3}%", mean * 100.0);
    assert!(p95 < 0.015, "95th percentile {:.3}%", p95 * 100.0);
    assert!(coverage >= 0.8, "coverage {:.1}%", coverage * 100.0);

    // end to end: conform the rest template onto the reconstructed scan
    let fig = templates::build(templates::Kind::Pig, 20_000);
    assert_eq!(
        fig.mesh.vertices.len(),
        truth.vertices.len(),
        "the simulated pig is this template posed"
    );
    let lms = fig.landmarks();
    let scan_lms: Vec<Landmark> = lms
        .iter()
        .map(|l| match l.pos {
            LandmarkPos::Vertex(v) => Landmark {
                name: l.name.clone(),
                pos: LandmarkPos::Point(truth.vertices[v as usize]),
            },
            p => Landmark {
                name: l.name.clone(),
                pos: p,
            },
        })
        .collect();
    let r = conform(
        &fig.mesh,
        &scan,
        Some((&lms, &scan_lms)),
        &ConformOptions::default(),
        &mut |_| {},
    )
    .unwrap();
    let err = r
        .mesh
        .vertices
        .iter()
        .zip(&truth.vertices)
        .map(|(a, b)| (a - b).norm())
        .sum::<f64>()
        / truth.vertices.len() as f64
        / diag;
    eprintln!(
        "simulate -> reconstruct -> conform: mean correspondence error {:.3}% of the diagonal",
        err * 100.0
    );
    assert!(err < 0.02, "correspondence error {:.3}%", err * 100.0);
}

#[test]
fn disparity_rejects_bad_pairs_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    image::GrayImage::new(64, 48).save(d.join("l.png")).unwrap();
    image::GrayImage::new(60, 48).save(d.join("r.png")).unwrap();
    let o = conformd::stereo::disparity::SgbmOptions::default();
    let e = conformd::jobs::disparity(&d.join("l.png"), &d.join("r.png"), &o, &d.join("d.pfm"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("r.png") && e.contains("one size"), "{e}");
    let e = conformd::jobs::disparity(
        &d.join("l.png"),
        &d.join("missing.png"),
        &o,
        &d.join("d.pfm"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("missing.png"), "{e}");
    let bad = conformd::stereo::disparity::SgbmOptions {
        num_disparities: 100,
        ..o
    };
    assert!(bad.validate().unwrap_err().contains("multiple of 16"));
}

#[test]
fn reconstruct_names_missing_and_mismatched_images() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut rig: RigFile = toml::from_str(
        &std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/rig.example.toml"
        ))
        .unwrap(),
    )
    .unwrap();
    for p in &mut rig.pods {
        p.image = [160, 120];
        p.focal_px = 140.0;
    }
    let rig_path = d.join("rig.toml");
    std::fs::write(&rig_path, toml::to_string(&rig).unwrap()).unwrap();
    let box_mesh = conformd::synth::tessellated_box(V3::new(0.6, 0.3, 0.3), 4);
    conformd::mesh::write_mesh(&d.join("box.ply"), &box_mesh).unwrap();
    let sets = conformd::jobs::simulate(
        &rig_path,
        d.join("box.ply").to_str().unwrap(),
        "",
        1,
        2.0,
        &d.join("sim"),
    )
    .unwrap();
    // so small a view matches nothing: said plainly, not an empty scan written
    let e = conformd::jobs::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("pod pod1") && e.contains("disparity map is empty"),
        "{e}"
    );
    // an image gone
    std::fs::remove_file(sets[0].join("pod1-right.png")).unwrap();
    let e = conformd::jobs::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("pod1-right") && e.contains("pod1-right.png"),
        "{e}"
    );
    // an image of another size than the calibration's
    image::GrayImage::new(80, 60)
        .save(sets[0].join("pod1-right.png"))
        .unwrap();
    let e = conformd::jobs::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("pod1-right") && e.contains("80x60") && e.contains("160x120"),
        "{e}"
    );
    // a calibration folder without this pod's file, and a garbled file
    std::fs::create_dir_all(d.join("cal")).unwrap();
    let e = conformd::jobs::reconstruct(
        &sets[0],
        &rig_path,
        Some(&d.join("cal")),
        &d.join("s.ply"),
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("pod1.yml") && e.contains("no calibration for pod pod1"),
        "{e}"
    );
    std::fs::write(d.join("cal/pod1.yml"), "%YAML:1.0\n---\nM1: 3\n").unwrap();
    let e = conformd::jobs::reconstruct(
        &sets[0],
        &rig_path,
        Some(&d.join("cal")),
        &d.join("s.ply"),
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("pod1.yml"), "{e}");
    // a rig file without pods
    std::fs::write(d.join("empty.toml"), "name = \"x\"\npods = []\n").unwrap();
    let e = conformd::jobs::reconstruct(
        &sets[0],
        &d.join("empty.toml"),
        None,
        &d.join("s.ply"),
        None,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("empty.toml") && e.contains("no [[pods]]"), "{e}");
    assert!(!d.join("s.ply").exists(), "nothing written on failure");
}
