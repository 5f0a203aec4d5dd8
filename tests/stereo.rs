//! Stereo reconstruction on simulated captures: a two-pod capture of a
//! pig reconstructs a scan close to the true surface that covers what the cameras see;
//! conformed with the template, it gives dense correspondence against the ground truth.
use crate::common;
use common::stereo_pairs::{RecordedPair, recorded_pairs};
use common::{CHILD_LIMIT, Deadline};

use conformd::conform::correspond::ScanSurface;
use conformd::conform::{ConformOptions, conform};
use conformd::mesh::{Mesh, V3, read_mesh};
use conformd::stereo::rig::RigFile;
use conformd::synth::scanner;
use conformd::template as templates;
use std::path::Path;

#[test]
fn simulate_reconstruct_conform() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let rig_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let sets =
        conformd::commands::simulate(&rig_path, "pig", "swing=8,nod=-6", 1, 2.0, &d.join("sim"))
            .unwrap();
    let report = conformd::commands::reconstruct(
        &sets[0],
        &rig_path,
        Some(&d.join("sim/calibration")),
        &d.join("scan.ply"),
        None,
        false,
    )
    .unwrap(); // the calibration files simulate wrote, read back through OpenCV
    let scan = read_mesh(&d.join("scan.ply")).unwrap();
    let truth = read_mesh(&sets[0].join("truth.ply")).unwrap();
    let (mean, p95) = accuracy(&scan, &truth);
    let coverage = coverage(&scan, &truth, &rig_path);
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
    // bounds about 1.25x the figures measured (0.086%, 0.238%, 99.1%; README)
    assert!(mean < 0.0011, "mean distance {:.3}%", mean * 100.0);
    assert!(p95 < 0.003, "95th percentile {:.3}%", p95 * 100.0);
    assert!(coverage >= 0.97, "coverage {:.1}%", coverage * 100.0);
    // end to end: conform the rest template onto the reconstructed scan
    let err = conform_error(&scan, &truth);
    eprintln!(
        "simulate -> reconstruct -> conform: mean correspondence error {:.3}% of the diagonal",
        err * 100.0
    );
    // measured 0.144%
    assert!(err < 0.0018, "correspondence error {:.3}%", err * 100.0);
}

/// Mean and 95th percentile of the scan's vertices' distances to the true surface,
/// relative to the truth's diagonal.
fn accuracy(scan: &Mesh, truth: &Mesh) -> (f64, f64) {
    let surface = ScanSurface::new(truth).unwrap();
    let mut dist: Vec<f64> = scan
        .vertices
        .iter()
        .map(|p| surface.distance(p) / truth.diagonal())
        .collect();
    dist.sort_by(f64::total_cmp);
    let mean = dist.iter().sum::<f64>() / dist.len() as f64;
    (mean, dist[dist.len() * 95 / 100])
}

/// Share of the true surface the rig's cameras see (by area) that has scan vertices
/// within 1% of the diagonal.
fn coverage(scan: &Mesh, truth: &Mesh, rig_path: &Path) -> f64 {
    let diag = truth.diagonal();
    let rig = RigFile::load(rig_path).unwrap();
    let centres: Vec<V3> = rig
        .pods()
        .iter()
        .flat_map(|p| [p.left_pose.centre(), p.right_pose().centre()])
        .collect();
    let seen = scanner::visible_triangles(truth, &centres);
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
    covered / seen_area
}

/// Conforms the rest pig template onto `scan` with landmarks placed from the truth, and
/// returns the mean correspondence error relative to the diagonal.
fn conform_error(scan: &Mesh, truth: &Mesh) -> f64 {
    let fig = templates::build(templates::Kind::Pig, 20_000);
    assert_eq!(
        fig.mesh.vertices.len(),
        truth.vertices.len(),
        "the simulated pig is this template posed"
    );
    let lms = fig.landmarks();
    let scan_lms = conformd::synth::cases::landmarks_on(&lms, truth);
    let r = conform(
        &fig.mesh,
        scan,
        Some((&lms, &scan_lms)),
        &ConformOptions::default(),
        &mut |_| {},
    )
    .unwrap();
    r.mesh
        .vertices
        .iter()
        .zip(&truth.vertices)
        .map(|(a, b)| (a - b).norm())
        .sum::<f64>()
        / truth.vertices.len() as f64
        / truth.diagonal()
}

#[test]
fn reconstruct_mesh_cuts_depth_jumps_and_conforms() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let rig_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    // legs forward and the head turned: legs in front of the belly, the snout before the shoulder
    let sets =
        conformd::commands::simulate(&rig_path, "pig", "swing=15,nod=-10", 1, 2.0, &d.join("sim"))
            .unwrap();
    let truth = read_mesh(&sets[0].join("truth.ply")).unwrap();
    let mut station =
        conformd::stereo::rig::Reconstruction::load(&rig_path, Some(&d.join("sim/calibration")))
            .unwrap();
    let report = conformd::commands::reconstruct_with(
        &mut station,
        &sets[0],
        &d.join("scan.ply"),
        None,
        true,
    )
    .unwrap();
    let scan = read_mesh(&d.join("scan.ply")).unwrap();
    assert_eq!(scan.triangles.len(), report.triangles);
    let topo = conformd::mesh::topology::report(&scan);
    let (mean, p95) = accuracy(&scan, &truth);
    let cov = coverage(&scan, &truth, &rig_path);
    // bridges: triangles whose corners lie on the true surface (within 0.5% of the
    // diagonal) but whose centre hangs off it by over 1%: joins between two surfaces
    let bridges = |m: &Mesh| {
        let surface = ScanSurface::new(&truth).unwrap();
        let diag = truth.diagonal();
        (0..m.triangles.len())
            .filter(|&t| {
                let c = m.corners(t);
                c.iter().all(|p| surface.distance(p) < 0.005 * diag)
                    && surface.distance(&(c.iter().sum::<V3>() / 3.0)) > 0.01 * diag
            })
            .count()
    };
    let cut = bridges(&scan);
    // the cut at work: with the edge margin off, SGBM keeps pixels right up to a depth
    // jump, and grids joined without the cut bridge it (the maps come from the cache)
    station.options.sgbm.edge_margin = 0;
    conformd::commands::reconstruct_with(
        &mut station,
        &sets[0],
        &d.join("margin0.ply"),
        None,
        true,
    )
    .unwrap();
    let cut_only = bridges(&read_mesh(&d.join("margin0.ply")).unwrap());
    station.options.mesh.depth_cut = f64::INFINITY;
    let r2 = conformd::commands::reconstruct_with(
        &mut station,
        &sets[0],
        &d.join("uncut.ply"),
        None,
        true,
    )
    .unwrap();
    assert!(
        r2.pods.iter().all(|p| p.maps_reused),
        "second capture reuses the maps"
    );
    assert!(report.pods.iter().all(|p| !p.maps_reused));
    let uncut = bridges(&read_mesh(&d.join("uncut.ply")).unwrap());
    eprintln!(
        "reconstruct --mesh: {} vertices, {} triangles, {} boundary edges; mean distance {:.3}% p95 {:.3}%, coverage {:.1}%; bridging triangles {} (edge margin off: {} with the cut, {} without)",
        scan.vertices.len(),
        scan.triangles.len(),
        topo.boundary_edges,
        mean * 100.0,
        p95 * 100.0,
        cov * 100.0,
        cut,
        cut_only,
        uncut
    );
    // bounds about 1.25x the figures measured (0.081%, 0.222%, 94.9%)
    assert!(mean < 0.001, "mean distance {:.3}%", mean * 100.0);
    assert!(p95 < 0.0028, "95th percentile {:.3}%", p95 * 100.0);
    assert!(cov >= 0.93, "coverage {:.1}%", cov * 100.0);
    assert!(
        cut * 1000 <= scan.triangles.len() && cut_only * 1000 <= scan.triangles.len(),
        "{cut} / {cut_only} bridging triangles of {}",
        scan.triangles.len()
    );
    assert!(
        uncut >= 5 * cut_only.max(1),
        "the cut removes bridges ({uncut} -> {cut_only})"
    );
    assert!(
        topo.boundary_edges > 0 && topo.inconsistent_edges == 0,
        "a scan mesh has holes, consistently oriented"
    );
    let err = conform_error(&scan, &truth);
    eprintln!(
        "simulate -> reconstruct --mesh -> conform: mean correspondence error {:.3}%",
        err * 100.0
    );
    // measured 0.239%
    assert!(err < 0.003, "correspondence error {:.3}%", err * 100.0);
}

#[test]
fn disparity_rejects_bad_pairs_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    image::GrayImage::new(64, 48).save(d.join("l.png")).unwrap();
    image::GrayImage::new(60, 48).save(d.join("r.png")).unwrap();
    let o = conformd::stereo::disparity::SgbmOptions::default();
    let e = conformd::commands::disparity(&d.join("l.png"), &d.join("r.png"), &o, &d.join("d.pfm"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("r.png") && e.contains("one size"), "{e}");
    let e = conformd::commands::disparity(
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
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("multiple of 16")
    );
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
    let sets = conformd::commands::simulate(
        &rig_path,
        d.join("box.ply").to_str().unwrap(),
        "",
        1,
        2.0,
        &d.join("sim"),
    )
    .unwrap();
    // the small view reconstructs (each pod searches only the volume's disparities)
    let r =
        conformd::commands::reconstruct(&sets[0], &rig_path, None, &d.join("ok.ply"), None, false)
            .unwrap();
    assert!(
        r.pods
            .iter()
            .all(|p| p.points > 500 && p.disparities[1] - p.disparities[0] == 16)
    );
    // blank images match nothing: said plainly, not an empty scan written
    let keep: Vec<Vec<u8>> = ["pod1-left.png", "pod1-right.png"]
        .iter()
        .map(|f| std::fs::read(sets[0].join(f)).unwrap())
        .collect();
    for f in ["pod1-left.png", "pod1-right.png"] {
        image::GrayImage::from_pixel(160, 120, image::Luma([90]))
            .save(sets[0].join(f))
            .unwrap();
    }
    let e =
        conformd::commands::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None, false)
            .unwrap_err()
            .to_string();
    for (f, bytes) in ["pod1-left.png", "pod1-right.png"].iter().zip(&keep) {
        std::fs::write(sets[0].join(f), bytes).unwrap();
    }
    assert!(
        e.contains("pod pod1")
            && e.contains("disparity map is empty")
            && e.contains("camera pod1-left")
            && e.contains("pod1-right.png"),
        "{e}"
    );
    // the calibration simulate wrote belongs to this rig and is taken
    let cal = d.join("sim/calibration");
    conformd::stereo::rig::Reconstruction::load(&rig_path, Some(&cal)).unwrap();
    // calibrations from elsewhere are refused, naming the file and what does not fit
    let good = std::fs::read_to_string(cal.join("pod1.yml")).unwrap();
    let refused = |yaml: &str| -> String {
        std::fs::write(cal.join("pod1.yml"), yaml).unwrap();
        let e = match conformd::stereo::rig::Reconstruction::load(&rig_path, Some(&cal)) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("taken: {yaml}"),
        };
        assert!(e.contains("pod1.yml") && e.contains("another rig"), "{e}");
        e
    };
    let e = refused(&good.replace("rig: \"crate-1\"", "rig: \"booth-7\""));
    assert!(e.contains("booth-7") && e.contains("crate-1"), "{e}");
    let e = refused(&std::fs::read_to_string(cal.join("pod2.yml")).unwrap());
    assert!(e.contains("made for pod 'pod2'"), "{e}");
    let e = refused(&good.replace("image_width: 160", "image_width: 1280"));
    assert!(e.contains("1280x120") && e.contains("160x120"), "{e}");
    let t = good.find("T: !!opencv-matrix").unwrap();
    let e = refused(
        &(good[..t].to_string()
            + "T: !!opencv-matrix\n   rows: 3\n   cols: 1\n   dt: d\n   data: [ -0.30, 0.0, 0.0 ]\n"),
    );
    assert!(
        e.contains("baseline is 0.3000 m") && e.contains("0.1200 m"),
        "{e}"
    );
    std::fs::write(cal.join("pod1.yml"), &good).unwrap();
    // a corrupt image
    let png = sets[0].join("pod1-left.png");
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() / 3]).unwrap();
    let e =
        conformd::commands::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None, false)
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("camera pod1-left") && e.contains("pod1-left.png"),
        "{e}"
    );
    std::fs::write(&png, &bytes).unwrap();
    // an image gone
    std::fs::remove_file(sets[0].join("pod1-right.png")).unwrap();
    let e =
        conformd::commands::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None, false)
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
    let e =
        conformd::commands::reconstruct(&sets[0], &rig_path, None, &d.join("s.ply"), None, false)
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("pod1-right") && e.contains("80x60") && e.contains("160x120"),
        "{e}"
    );
    // a calibration folder without this pod's file, and a garbled file
    std::fs::create_dir_all(d.join("cal")).unwrap();
    let e = conformd::commands::reconstruct(
        &sets[0],
        &rig_path,
        Some(&d.join("cal")),
        &d.join("s.ply"),
        None,
        false,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("pod1.yml") && e.contains("no calibration for pod pod1"),
        "{e}"
    );
    std::fs::write(d.join("cal/pod1.yml"), "%YAML:1.0\n---\nM1: 3\n").unwrap();
    let e = conformd::commands::reconstruct(
        &sets[0],
        &rig_path,
        Some(&d.join("cal")),
        &d.join("s.ply"),
        None,
        false,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("pod1.yml"), "{e}");
    // a rig file without pods
    std::fs::write(d.join("empty.toml"), "name = \"x\"\npods = []\n").unwrap();
    let e = conformd::commands::reconstruct(
        &sets[0],
        &d.join("empty.toml"),
        None,
        &d.join("s.ply"),
        None,
        false,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("empty.toml") && e.contains("no [[pods]]"), "{e}");
    assert!(!d.join("s.ply").exists(), "nothing written on failure");
}

/// Sub-pixel refinement after SGBM: on a flat wall 1.9 m from a 1280x960 pod, the depth
/// noise (standard deviation about the true plane) falls by at least 30% against SGBM's
/// own interpolation, with no bias over 1 mm.
#[test]
fn subpixel_refinement_cuts_depth_noise_on_a_wall() {
    use conformd::stereo::disparity::SgbmOptions;
    use conformd::stereo::reconstruct::RectifierCache;
    let rig = RigFile::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml"))
        .unwrap();
    // a 2 x 2 m slab whose face y = -0.05 faces pod1
    let wall = conformd::synth::tessellated_box(V3::new(2.0, 0.1, 2.0), 40);
    let pods = rig.pods();
    let l =
        conformd::synth::virtual_rig::render_camera(&pods[0], &rig.pods[0], false, &wall, 2.0, 1);
    let r =
        conformd::synth::virtual_rig::render_camera(&pods[0], &rig.pods[0], true, &wall, 2.0, 1);
    let mut cache = RectifierCache::default();
    let (rect, _) = cache.get(&pods[0]).unwrap();
    let mut figures = Vec::new();
    for steps in [0, 1] {
        let o = SgbmOptions {
            subpixel_steps: steps,
            ..Default::default()
        };
        let g = common::whole_pod_grid(rect, &l.pixels, &r.pixels, &o);
        let d: Vec<f64> = g
            .valid()
            .filter(|p| (p.y + 0.05).abs() < 0.05 && p.x.abs() < 0.9 && p.z.abs() < 0.9)
            .map(|p| (p.y + 0.05) * 1000.0)
            .collect();
        let mean = d.iter().sum::<f64>() / d.len() as f64;
        let sd = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / d.len() as f64).sqrt();
        eprintln!(
            "wall, {} sub-pixel steps: {} points, bias {mean:.2} mm, noise {sd:.2} mm",
            steps,
            d.len()
        );
        assert!(d.len() > 400_000, "{} points on the wall", d.len());
        figures.push((mean, sd));
    }
    let ((_, sgbm), (bias, refined)) = (figures[0], figures[1]);
    assert!(
        refined < 0.7 * sgbm,
        "noise {refined:.2} mm vs SGBM's {sgbm:.2} mm"
    );
    assert!(bias.abs() < 1.0, "bias {bias:.2} mm");
}

/// A wide, near rig (pods 1.6 m from the crate's centre line, 25 cm baselines): the
/// nearest surface lies ~200 px of disparity away, beyond SGBM's default 128. Searching
/// each pod's disparity range from the working volume keeps the scan whole; the fixed
/// range loses the near side.
#[test]
fn disparity_range_follows_the_working_volume() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut rig =
        RigFile::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml"))
            .unwrap();
    for (p, side) in rig.pods.iter_mut().zip([-1.0, 1.0]) {
        p.position = [0.1, side * 1.6, 1.0];
        p.baseline = 0.25;
    }
    rig.working_volume = Some([[-1.0, -0.5, -0.05], [1.1, 0.5, 1.0]]);
    let rig_path = d.join("near.toml");
    std::fs::write(&rig_path, toml::to_string(&rig).unwrap()).unwrap();
    let sets = conformd::commands::simulate(&rig_path, "pig", "", 1, 2.0, &d.join("sim")).unwrap();
    let truth = read_mesh(&sets[0].join("truth.ply")).unwrap();
    let mut station = conformd::stereo::rig::Reconstruction::load(&rig_path, None).unwrap();
    let mut figures = Vec::new();
    for auto in [true, false] {
        station.options.auto_disparity_range = auto;
        let out = d.join(format!("scan-{auto}.ply"));
        let r = conformd::commands::reconstruct_with(&mut station, &sets[0], &out, None, false)
            .unwrap();
        let scan = read_mesh(&out).unwrap();
        let (mean, p95) = accuracy(&scan, &truth);
        let cov = coverage(&scan, &truth, &rig_path);
        eprintln!(
            "near rig, disparities {:?}: {} points, mean {:.3}% p95 {:.3}%, coverage {:.1}%",
            r.pods.iter().map(|p| p.disparities).collect::<Vec<_>>(),
            scan.vertices.len(),
            mean * 100.0,
            p95 * 100.0,
            cov * 100.0
        );
        figures.push((mean, p95, cov));
    }
    let ((mean, p95, cov), (_, _, fixed_cov)) = (figures[0], figures[1]);
    // bounds about 1.25x the figures measured (0.036%, 0.095%, 93.0%)
    assert!(
        mean < 0.00045 && p95 < 0.0012,
        "mean {:.3}% p95 {:.3}%",
        mean * 100.0,
        p95 * 100.0
    );
    assert!(cov >= 0.91, "coverage {:.1}%", cov * 100.0);
    assert!(
        cov > fixed_cov + 0.1,
        "coverage {:.1}% vs {:.1}% with the fixed range",
        cov * 100.0,
        fixed_cov * 100.0
    );
}

#[test]
fn a_working_volume_narrower_than_the_view_is_matched_in_its_window_alone() {
    // the example rig with its working volume drawn 5 cm around the pig: each pod
    // matches only the part of its images the volume can appear in, and the scan is the
    // one the whole images give
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut rig =
        RigFile::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml"))
            .unwrap();
    let wide = d.join("wide.toml");
    std::fs::write(&wide, toml::to_string(&rig).unwrap()).unwrap();
    let sets =
        conformd::commands::simulate(&wide, "pig", "swing=6", 1, 2.0, &d.join("sim")).unwrap();
    let truth = read_mesh(&sets[0].join("truth.ply")).unwrap();
    let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
    for p in &truth.vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k] - 0.05);
            hi[k] = hi[k].max(p[k] + 0.05);
        }
    }
    rig.working_volume = Some([lo, hi]);
    let tight = d.join("tight.toml");
    std::fs::write(&tight, toml::to_string(&rig).unwrap()).unwrap();
    let mut station = conformd::stereo::rig::Reconstruction::load(&tight, None).unwrap();
    let mut figures = Vec::new();
    for window in [true, false] {
        station.options.volume_window = window;
        let out = d.join(format!("scan-{window}.ply"));
        let r = conformd::commands::reconstruct_with(&mut station, &sets[0], &out, None, false)
            .unwrap();
        let scan = read_mesh(&out).unwrap();
        let (mean, p95) = accuracy(&scan, &truth);
        let cov = coverage(&scan, &truth, &tight);
        let windows: Vec<Option<[i32; 4]>> = r.pods.iter().map(|p| p.window).collect();
        eprintln!(
            "window {window}: {windows:?}, {} points, mean {:.3}% p95 {:.3}%, coverage {:.1}%, disparity {:?} s",
            scan.vertices.len(),
            mean * 100.0,
            p95 * 100.0,
            cov * 100.0,
            r.pods
                .iter()
                .map(|p| p.seconds_disparity)
                .collect::<Vec<_>>()
        );
        if window {
            for w in &windows {
                let [_, _, ww, wh] = w.expect("a window smaller than the image");
                assert!(ww * wh < 1280 * 960 * 9 / 10, "{w:?}");
            }
        } else {
            assert!(windows.iter().all(Option::is_none));
        }
        figures.push((scan.vertices.len() as f64, mean, p95, cov));
    }
    let (a, b) = (figures[0], figures[1]);
    assert!((a.0 / b.0 - 1.0).abs() < 0.01, "points {} vs {}", a.0, b.0);
    assert!((a.1 - b.1).abs() < 0.05 * b.1, "mean {} vs {}", a.1, b.1);
    assert!((a.2 - b.2).abs() < 0.05 * b.2, "p95 {} vs {}", a.2, b.2);
    assert!((a.3 - b.3).abs() < 0.005, "coverage {} vs {}", a.3, b.3);
}

/// A rig file's `[reconstruct]` tables set the reconstruction; a bad value or an unknown
/// key is named with the file.
#[test]
fn rig_file_reconstruct_settings() {
    let dir = tempfile::tempdir().unwrap();
    let base = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/rig.example.toml"
    ))
    .unwrap();
    let write = |extra: &str| {
        let p = dir.path().join("rig.toml");
        std::fs::write(&p, format!("{base}\n{extra}")).unwrap();
        p
    };
    let p = write("[reconstruct]\nvoxel = 0.01\n[reconstruct.sgbm]\nblock_size = 7\n");
    let station = conformd::stereo::rig::Reconstruction::load(&p, None).unwrap();
    assert_eq!(station.options.voxel, 0.01);
    assert_eq!(station.options.sgbm.block_size, 7);
    assert_eq!(station.options.working_volume, station.rig.working_volume);
    let e = RigFile::load(&write("[reconstruct.sgbm]\nblock_size = 4\n"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("rig.toml") && e.contains("[reconstruct.sgbm]") && e.contains("block_size"),
        "{e}"
    );
    let e = RigFile::load(&write("[reconstruct]\nvoxels = 0.01\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("rig.toml") && e.contains("voxels"), "{e}");
    // the natural profile's keys are range-checked too, each named
    for (bad, key) in [
        ("cross_check = -1.0", "cross_check"),
        ("contrast_window = 4", "contrast_window"),
        ("occlusion_margin = -2", "occlusion_margin"),
    ] {
        let e = RigFile::load(&write(&format!(
            "[reconstruct.sgbm]\nprofile = \"natural\"\n{bad}\n"
        )))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("[reconstruct.sgbm]") && e.contains(key),
            "{bad}: {e}"
        );
    }
}

/// Recorded pairs with their truth (tests/data/stereo): the truth readers decode each
/// format to the disparity range of its benchmark, and `disparity --truth` reports the
/// bad-pixel share and coverage an operator sees.
#[test]
fn recorded_pairs_are_scored_against_their_ground_truth() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stereo");
    // Middlebury 2005's third-size truths are disparity x 3 (art's largest 74.7)
    for (truth, scale, lo, hi) in [
        ("cones/disp2.png", None, 50.0, 64.0),
        ("teddy/disp2.png", None, 45.0, 64.0),
        ("kitti-000070/disp_noc.png", None, 60.0, 128.0),
        ("art/disp1.png", Some(3.0), 70.0, 80.0),
    ] {
        let t = conformd::stereo::truth::read_truth(&root.join(truth), scale).unwrap();
        let max = t
            .values
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(0.0, f32::max);
        assert!(max > lo && max < hi, "{truth}: largest disparity {max}");
    }
    let dir = tempfile::tempdir().unwrap();
    // Cones through `disparity --truth` with `extra` options; what it printed
    let cones = |extra: &[&str]| -> String {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
            .args(["disparity", "--num-disparities", "64"])
            .args(extra)
            .arg("--truth")
            .arg(root.join("cones/disp2.png"))
            .arg(root.join("cones/im2.png"))
            .arg(root.join("cones/im6.png"))
            .arg("--out")
            .arg(dir.path().join("d.pfm"))
            .output_within(CHILD_LIMIT);
        let text = String::from_utf8_lossy(&out.stdout).to_string();
        assert!(out.status.success(), "{text}");
        text
    };
    let text = cones(&[]);
    // "against the truth: 4.22% of valid pixels more than 1 px off ..., coverage 85.0% ..."
    let pct_in = |text: &str, after: &str| -> f64 {
        let s = &text[text.find(after).unwrap() + after.len()..];
        s.trim_start()
            .split('%')
            .next()
            .unwrap()
            .trim()
            .parse()
            .unwrap()
    };
    let (bad, coverage) = (
        pct_in(&text, "against the truth:"),
        pct_in(&text, "coverage"),
    );
    // measured 4.22% bad at 85.0% coverage (the natural profile)
    assert!(bad > 0.0 && bad < 5.3, "{text}");
    assert!(coverage > 84.0 && coverage <= 100.0, "{text}");
    // the confidence beside the map: 0 to 1, 0 exactly where no match is kept; a
    // stricter cut keeps fewer pixels, fewer of them wrong
    let conf = dir.path().join("c.pfm");
    let strict = cones(&[
        "--confidence",
        conf.to_str().unwrap(),
        "--min-confidence",
        "0.5",
    ]);
    assert!(strict.contains("c.pfm"), "{strict}");
    let read = |p: &Path| conformd::stereo::truth::read_truth(p, None).unwrap();
    let (c, d) = (read(&conf), read(&dir.path().join("d.pfm")));
    assert_eq!((c.width, c.height), (450, 375));
    for (c, d) in c.values.iter().zip(&d.values) {
        assert!((0.0..=1.0).contains(c), "{c}");
        assert_eq!(*c == 0.0, !d.is_finite(), "confidence {c}, disparity {d}");
        assert!(d.is_nan() || *c >= 0.5, "{c}");
    }
    let text_strict = strict;
    let (bad_strict, coverage_strict) = (
        pct_in(&text_strict, "against the truth:"),
        pct_in(&text_strict, "coverage"),
    );
    assert!(
        bad_strict < bad && coverage_strict < coverage,
        "{bad}% at {coverage}% -> {bad_strict}% at {coverage_strict}%"
    );
    // a profile or a truth the command cannot read is refused, naming what was wrong
    for (args, expect) in [
        (vec!["--profile", "sunny"], "--profile sunny"),
        (vec!["--truth", "truth.txt"], "truth.txt"),
        (vec!["--confidence", "c.png"], "c.png"),
        (vec!["--min-confidence", "2"], "min_confidence"),
    ] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
            .arg("disparity")
            .args(&args)
            .arg(root.join("cones/im2.png"))
            .arg(root.join("cones/im6.png"))
            .arg("--out")
            .arg(dir.path().join("e.pfm"))
            .current_dir(dir.path())
            .output_within(CHILD_LIMIT);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(expect), "{err}");
    }
    // a truth read at the wrong scale is pointed out (the quarter-size PNG read as pixels)
    let text = cones(&["--truth-scale", "1"]);
    assert!(
        text.contains("0.25 times the truth's") && text.contains("--truth-scale"),
        "{text}"
    );
    std::fs::write(dir.path().join("cut.pfm"), b"Pf\n450 375\n-1\n\0\0\0\0").unwrap();
    let e = conformd::commands::score_disparity(
        &conformd::stereo::disparity::Disparity {
            width: 450,
            height: 375,
            values: vec![1.0; 450 * 375],
        },
        &dir.path().join("cut.pfm"),
        None,
        0,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("cut.pfm") && e.contains("truncated"), "{e}");
    // a truth of another size is refused with both sizes named
    let e = conformd::commands::score_disparity(
        &conformd::stereo::disparity::Disparity {
            width: 10,
            height: 10,
            values: vec![1.0; 100],
        },
        &root.join("cones/disp2.png"),
        None,
        0,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("10 x 10") && e.contains("450 x 375"), "{e}");
}

/// The natural profile's bounds on a recorded pair (bad pixels, coverage): 1.2x the
/// figures measured (README) and a point under them.
fn natural_bounds(dir: &str) -> (f64, f64) {
    match dir {
        "cones" => (0.051, 0.84),
        "teddy" => (0.082, 0.842),
        "kitti-000070" => (0.083, 0.923),
        // measured 10.62% at 69.2% (stock 18.28% at 72.3%)
        "art" => (0.128, 0.682),
        // 7.37% at 84.2% (stock 9.61% at 79.6%)
        "dolls" => (0.089, 0.832),
        // 10.80% at 81.9% (stock 12.28% at 78.3%)
        "moebius" => (0.130, 0.809),
        // validation: 8.07% at 83.3% (stock 10.46% at 80.5%)
        "books" => (0.097, 0.823),
        // 14.56% at 78.2% (stock 17.28% at 76.8%)
        "laundry" => (0.175, 0.772),
        // 7.93% at 78.8% (stock 12.29% at 75.3%)
        "reindeer" => (0.096, 0.778),
        other => panic!("no bounds for the recorded pair {other}"),
    }
}

/// How the natural profile and stock SGBM do on a recorded pair: the profile's default
/// map, stock's, and the profile's map ranked by confidence (no cut) scored at stock's
/// coverage, at half its own and at all of it.
struct AgainstStock {
    ours: conformd::stereo::truth::TruthScore,
    stock: conformd::stereo::truth::TruthScore,
    at_stock: conformd::stereo::truth::TruthScore,
    half: conformd::stereo::truth::TruthScore,
    all: conformd::stereo::truth::TruthScore,
}

fn natural_against_stock(p: &RecordedPair) -> AgainstStock {
    use conformd::stereo::disparity::{self, Profile, SgbmOptions};
    use conformd::stereo::truth::{read_truth, score, score_at_coverage};
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stereo");
    let lg = image::open(root.join(&p.left)).unwrap().to_luma8();
    let rg = image::open(root.join(&p.right)).unwrap().to_luma8();
    let (w, h) = lg.dimensions();
    let truth = read_truth(&root.join(&p.truth), p.truth_scale).unwrap();
    let o = SgbmOptions {
        num_disparities: p.disparities,
        ..SgbmOptions::for_profile(Profile::Natural)
    };
    let ours = disparity::disparity(lg.as_raw(), rg.as_raw(), w, h, &o).unwrap();
    let ours = score(&ours, &truth, 0).unwrap();
    let stock = disparity::stock_sgbm(lg.as_raw(), rg.as_raw(), w, h, p.disparities).unwrap();
    let stock = score(&stock, &truth, 0).unwrap();
    let ranked = SgbmOptions {
        min_confidence: 0.0,
        ..o
    };
    let (d, c) =
        disparity::disparity_with_confidence(lg.as_raw(), rg.as_raw(), w, h, &ranked).unwrap();
    let all = score(&d, &truth, 0).unwrap();
    AgainstStock {
        ours,
        stock,
        at_stock: score_at_coverage(&d, &c, &truth, 0, stock.coverage).unwrap(),
        half: score_at_coverage(&d, &c, &truth, 0, all.coverage / 2.0).unwrap(),
        all,
    }
}

/// Issue 14's and 26's bar on the recorded pairs: the natural-texture profile is no
/// worse than stock OpenCV SGBM_3WAY (its sample's settings: block 5, P1 200, P2 800) in
/// bad pixels (more than 1 px off, of the valid ones), at equal or higher coverage, on
/// every pair but art's coverage ([`art_default_coverage_reaches_stock_known_failure`]);
/// its confidence puts fewer wrong matches than stock's first at stock's coverage on
/// every pair; and a rig file names the profile.
#[test]
fn the_natural_profile_beats_stock_sgbm_on_every_recorded_pair() {
    use conformd::stereo::disparity::{Profile, SgbmOptions};
    for p in &recorded_pairs() {
        let AgainstStock {
            ours,
            stock,
            at_stock,
            half,
            all,
        } = natural_against_stock(p);
        let l = &p.left;
        let (bad_bound, coverage_floor) = natural_bounds(p.dir);
        let line = format!(
            "{l}: natural {:.2}% bad at {:.1}% coverage, stock {:.2}% at {:.1}%",
            ours.bad1 * 100.0,
            ours.coverage * 100.0,
            stock.bad1 * 100.0,
            stock.coverage * 100.0
        );
        println!("{line}");
        assert!(ours.bad1 <= stock.bad1, "{line}");
        if p.dir != "art" {
            assert!(ours.coverage >= stock.coverage, "{line}");
        }
        assert!(
            ours.bad1 < bad_bound && ours.coverage > coverage_floor,
            "{line}"
        );
        // where stock SGBM is under 8%, under 5% at 80% coverage or more
        if stock.bad1 < 0.08 {
            assert!(ours.bad1 < 0.05 && ours.coverage >= 0.8, "{line}");
        }
        // ranked by confidence (no cut), the most confident pixels at stock's coverage
        // hold fewer wrong matches than stock (README: e.g. 3.12 / 5.61 / 6.83% against
        // 6.95 / 9.81 / 8.99% on the first three), and half of the full coverage far fewer
        // than all of it (the confidence orders the pixels, not merely thins them)
        let line = format!(
            "{l}: by confidence {:.2}% bad at stock's {:.1}% coverage (stock {:.2}%); {:.2}% at half of {:.1}% ({:.2}% at all)",
            at_stock.bad1 * 100.0,
            at_stock.coverage * 100.0,
            stock.bad1 * 100.0,
            half.bad1 * 100.0,
            all.coverage * 100.0,
            all.bad1 * 100.0
        );
        println!("{line}");
        assert!((at_stock.coverage - stock.coverage).abs() < 1e-3, "{line}");
        assert!(at_stock.bad1 < 0.9 * stock.bad1, "{line}");
        assert!(half.bad1 < 0.6 * all.bad1, "{line}");
    }
    // named in a rig file: the profile sets the defaults, given keys override them
    let sgbm: SgbmOptions = toml::from_str("profile = \"natural\"\nblock_size = 7\n").unwrap();
    assert_eq!(sgbm.profile, Profile::Natural);
    assert_eq!(
        (sgbm.block_size, sgbm.contrast_window, sgbm.subpixel_steps),
        (7, 21, 0)
    );
    assert!(sgbm.cross_check > 0.0 && sgbm.edge_margin == 0);
    let sgbm: SgbmOptions = toml::from_str("").unwrap();
    assert_eq!(sgbm.profile, Profile::Speckle);
    assert!(sgbm.min_contrast > 0.0 && sgbm.subpixel_steps > 0);
    let e = toml::from_str::<SgbmOptions>("profile = \"sunny\"").unwrap_err();
    assert!(e.to_string().contains("sunny"), "{e}");
    assert!(toml::from_str::<SgbmOptions>("min_contrst = 1.0").is_err());
}

/// Known failure (issue 26): on art the natural profile's default cut keeps 69.2% of the
/// pixels against stock's 72.3% (with 10.62% wrong against stock's 18.28%): its
/// confidence cut drops 6.5% of its matches there (2-4% on the other pairs), most of
/// them on the untextured backdrop. Without the cut it covers 74.0% at 12.80%, but
/// lowering the default cut raises every other pair's wrong matches. The assertion is
/// the right outcome; it fails today.
#[test]
#[should_panic(expected = "art: the default covers less than stock")]
fn art_default_coverage_reaches_stock_known_failure() {
    let art = recorded_pairs()
        .into_iter()
        .find(|p| p.dir == "art")
        .unwrap();
    let AgainstStock { ours, stock, .. } = natural_against_stock(&art);
    assert!(
        ours.coverage >= stock.coverage,
        "art: the default covers less than stock ({:.1}% against {:.1}%)",
        ours.coverage * 100.0,
        stock.coverage * 100.0
    );
}

/// A recorded pair replayed as a station would see it (issue 14): `import-pair` turns
/// KITTI #70 and its calibration into a rig file, a pod calibration and a capture set;
/// `reconstruct` runs on it like on any capture, and its scan is scored in depth against
/// the LiDAR truth: no worse than stock SGBM's matches at no less coverage, in depth
/// within a few percent. Bad calibrations and truths are refused before anything is
/// written.
#[test]
fn a_recorded_pair_replays_through_reconstruct_and_is_scored_in_depth() {
    use conformd::stereo::disparity::stock_sgbm;
    use conformd::stereo::truth::{read_truth, score};
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stereo/kitti-000070");
    let d = tempfile::tempdir().unwrap();
    // runs conformd, asserts it succeeded, returns what it printed
    let conformd = |cmd: &mut std::process::Command| -> String {
        let out = cmd.output_within(CHILD_LIMIT);
        let text = String::from_utf8_lossy(&out.stdout).to_string()
            + &String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{text}");
        text
    };
    let bin = || std::process::Command::new(env!("CARGO_BIN_EXE_conformd"));
    conformd(
        bin()
            .arg("import-pair")
            .arg(root.join("left.png"))
            .arg(root.join("right.png"))
            .arg("--calib")
            .arg(root.join("calib.txt"))
            .arg("--truth")
            .arg(root.join("disp_noc.png"))
            .arg("--out")
            .arg(d.path().join("replay")),
    );
    let sets: Vec<_> = std::fs::read_dir(d.path().join("replay/captures"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(sets.len(), 1, "{sets:?}");
    let set = &sets[0];
    for f in [
        "manifest.json",
        "pair-left.png",
        "pair-right.png",
        "truth.png",
        "calib.txt",
    ] {
        assert!(set.join(f).is_file(), "{f} missing from {}", set.display());
    }
    // the command the import prints, run as an operator would
    let reconstruct = |out: &str, truth: &Path| {
        let mut c = bin();
        c.arg("reconstruct")
            .arg(set)
            .arg("--rig")
            .arg(d.path().join("replay/rig.toml"))
            .arg("--calibration")
            .arg(d.path().join("replay/calibration"))
            .arg("--out")
            .arg(d.path().join(out))
            .arg("--truth")
            .arg(truth);
        c
    };
    let text = conformd(&mut reconstruct("scan.ply", &set.join("truth.png")));
    assert!(
        text.contains("depth error mean") && text.contains("coverage"),
        "{text}"
    );
    // a truth that cannot be used is refused before the scan is written
    std::fs::write(d.path().join("bad-truth.png"), b"not a png").unwrap();
    let out =
        reconstruct("refused.ply", &d.path().join("bad-truth.png")).output_within(CHILD_LIMIT);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("bad-truth.png"),
        "{err}"
    );
    assert!(
        !d.path().join("refused.ply").exists(),
        "the scan was written before the truth was refused"
    );
    // the same through the library, with the figures asserted
    let mut station = conformd::stereo::rig::Reconstruction::load(
        &d.path().join("replay/rig.toml"),
        Some(&d.path().join("replay/calibration")),
    )
    .unwrap();
    let (scan, _) = conformd::commands::reconstruct_scan(
        &mut station,
        set,
        &d.path().join("s.ply"),
        None,
        false,
    )
    .unwrap();
    let s = conformd::commands::score_scan(&scan, &station, None, &set.join("truth.png"), None)
        .unwrap();
    let lg = image::open(root.join("left.png")).unwrap().to_luma8();
    let rg = image::open(root.join("right.png")).unwrap().to_luma8();
    let truth = read_truth(&root.join("disp_noc.png"), None).unwrap();
    let stock = score(
        &stock_sgbm(lg.as_raw(), rg.as_raw(), lg.width(), lg.height(), 128).unwrap(),
        &truth,
        0,
    )
    .unwrap();
    println!(
        "replayed KITTI #70: {s}\nstock SGBM: {:.2}% bad at {:.1}% coverage",
        stock.bad1 * 100.0,
        stock.coverage * 100.0
    );
    assert!(s.known > 100_000, "{s}");
    assert!(s.bad1 <= stock.bad1 && s.coverage >= stock.coverage, "{s}");
    // depth error within a few percent of the depth (1 px of disparity at 20 m is 1 m)
    assert!(s.mean_relative < 0.05 && s.p95_depth < 1.5, "{s}");
    // and through `process`, as the station would: the same scan, a template conformed
    // onto it (a pig onto a street: the distortion warning must say so), the result whole
    std::fs::write(
        d.path().join("replay/station.toml"),
        "[station]\nname = \"replay\"\ndata = \"data\"\n[template]\ngeneric = \"pig\"\nvertices = 3000\n[rig]\nfile = \"rig.toml\"\ncalibration = \"calibration\"\n",
    )
    .unwrap();
    let text = conformd(
        bin()
            .arg("process")
            .arg(set)
            .arg("--config")
            .arg(d.path().join("replay/station.toml"))
            .arg("--out")
            .arg(d.path().join("results")),
    );
    assert!(text.contains("distorted"), "{text}");
    let result = d.path().join("results").join(set.file_name().unwrap());
    let processed = conformd::mesh::io::read_mesh(&result.join("scan.ply")).unwrap();
    assert_eq!(processed.vertices.len(), scan.vertices.len());
    assert!(result.join("conformed.ply").is_file() && result.join("report.json").is_file());
    // the scan scored against another pod, or a calibration and truth that cannot be
    // read, are refused naming what was wrong, and nothing is written
    let e =
        conformd::commands::score_scan(&scan, &station, Some("nope"), &set.join("truth.png"), None)
            .unwrap_err()
            .to_string();
    assert!(e.contains("nope"), "{e}");
    std::fs::write(
        d.path().join("calib.txt"),
        "P0: 1 0 0 0 0 1 0 0 0 0 1 0\nP1: 7 x\n",
    )
    .unwrap();
    let e = conformd::commands::import_pair(
        &root.join("left.png"),
        &root.join("right.png"),
        &d.path().join("calib.txt"),
        None,
        None,
        &d.path().join("bad"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("calib.txt") && e.contains("'x'"), "{e}");
    let cones = root.join("../cones/disp2.png");
    let e = conformd::commands::import_pair(
        &root.join("left.png"),
        &root.join("right.png"),
        &root.join("calib.txt"),
        Some(&cones),
        None,
        &d.path().join("bad"),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("450 x 375") && e.contains("1241 x 376"), "{e}");
    assert!(!d.path().join("bad").exists());
}

/// A careless recorded calibration (issue 42's weak class): a stated image size that is
/// not the images', a doffs of inf, a key given twice. `import-pair` refuses each naming
/// the file and writes nothing.
#[test]
fn import_pair_refuses_a_calibration_that_does_not_fit_its_pair() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/stereo/kitti-000070");
    let d = tempfile::tempdir().unwrap();
    let cam = "cam0=[721.5 0 609.6; 0 721.5 172.9; 0 0 1]\ncam1=[721.5 0 609.6; 0 721.5 172.9; 0 0 1]\nbaseline=537.2\n";
    for (extra, words) in [
        (
            "width=640\nheight=480\n",
            "the calibration is for 640x480 images",
        ),
        ("doffs=inf\n", "'inf' is not a number"),
        ("baseline=500\n", "'baseline' is given twice"),
    ] {
        std::fs::write(d.path().join("calib.txt"), format!("{cam}{extra}")).unwrap();
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
            .arg("import-pair")
            .arg(root.join("left.png"))
            .arg(root.join("right.png"))
            .arg("--calib")
            .arg(d.path().join("calib.txt"))
            .arg("--out")
            .arg(d.path().join("replay"))
            .output_within(CHILD_LIMIT);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains("calib.txt") && err.contains(words),
            "{extra}: {err}"
        );
        assert!(
            !d.path().join("replay").exists(),
            "{extra}: something was written"
        );
    }
}
