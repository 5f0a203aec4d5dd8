//! The known-answer case: an articulated figure whose parts are rotated 15-30 degrees and
//! whose whole is bent, twisted and scaled, seen from three viewpoints, resampled as a
//! noisy point cloud; the template's vertices have a known true place on it.
//!
//! Heavy: run it optimised, as `make test` does (`--profile ci`).

use crate::common;

use conformd::conform::ConformOptions;
use conformd::synth::cases::{self, ArticulatedSpec, correspondence_error};

fn errors(case: &cases::Case, r: &conformd::conform::Conformed) -> cases::CorrespondenceError {
    correspondence_error(
        &r.mesh.vertices,
        case.truth.as_ref().unwrap(),
        &case.in_hole,
        &case.template.triangles,
    )
}

#[test]
fn with_landmarks_default_beats_the_paper() {
    let case = cases::articulated(&ArticulatedSpec {
        template_vertices: 8000,
        scan_points: 80_000,
        ..Default::default()
    });
    let holes = case.in_hole.iter().filter(|h| **h).count();
    assert!(
        holes > case.template.vertices.len() / 20,
        "the scan has real holes ({holes} hidden vertices)"
    );
    let d = common::run(&case, &ConformOptions::default(), true);
    let p = common::run(&case, &ConformOptions::paper(), true);
    let (ed, ep) = (errors(&case, &d), errors(&case, &p));
    eprintln!(
        "articulated, landmarks, {} vertices ({holes} in holes), {} scan points:\n  default: mean {:.3}% holes {:.3}% p95 {:.3}% max {:.3}% flipped {} ({:.2} s)\n  paper:   mean {:.3}% holes {:.3}% p95 {:.3}% max {:.3}% flipped {} ({:.2} s)",
        case.template.vertices.len(),
        case.scan.vertices.len(),
        ed.mean * 100.0,
        ed.mean_in_holes * 100.0,
        ed.p95 * 100.0,
        ed.max * 100.0,
        ed.flipped,
        d.report.seconds.total,
        ep.mean * 100.0,
        ep.mean_in_holes * 100.0,
        ep.p95 * 100.0,
        ep.max * 100.0,
        ep.flipped,
        p.report.seconds.total,
    );
    // bounds about 1.25x the figures measured (0.434%, in holes 0.390%; README)
    assert!(
        ed.mean < 0.0055,
        "default mean correspondence error {:.3}%",
        ed.mean * 100.0
    );
    assert!(
        ed.mean_in_holes < 0.005,
        "default error in holes {:.3}%",
        ed.mean_in_holes * 100.0
    );
    assert_eq!(ed.flipped, 0, "no flipped triangles");
    assert_eq!(d.report.folded_triangles, 0);
    assert!(
        ed.mean < 0.9 * ep.mean,
        "default {:.3}% is not clearly below paper {:.3}%",
        ed.mean * 100.0,
        ep.mean * 100.0
    );
    assert!(ed.mean_in_holes < 0.8 * ep.mean_in_holes);
    assert!(ed.p95 < 0.8 * ep.p95);
    assert_eq!(d.mesh.triangles, case.template.triangles);
    assert!(d.report.watertight_result);
}

#[test]
fn without_landmarks_turned_and_shifted() {
    let case = cases::articulated(&ArticulatedSpec {
        template_vertices: 8000,
        scan_points: 80_000,
        turned: true,
        ..Default::default()
    });
    let d = common::run(&case, &ConformOptions::default(), false);
    let e = errors(&case, &d);
    eprintln!(
        "articulated, no landmarks, turned 35 deg and shifted: mean {:.3}% holes {:.3}% p95 {:.3}% max {:.3}% flipped {} ({:.2} s)",
        e.mean * 100.0,
        e.mean_in_holes * 100.0,
        e.p95 * 100.0,
        e.max * 100.0,
        e.flipped,
        d.report.seconds.total
    );
    // about 1.25x the figure measured (0.780%)
    assert!(
        e.mean < 0.0098,
        "mean correspondence error {:.3}%",
        e.mean * 100.0
    );
    assert!(
        e.mean_in_holes < 0.0105,
        "error in holes {:.3}%",
        e.mean_in_holes * 100.0
    );
    assert_eq!(e.flipped, 0, "no flipped triangles");
}

#[test]
fn stiffer_groups_keep_their_shape() {
    // The paper's section 3.2 remedy: a larger spring constant for parts that should not
    // distort (ears, hands, feet).
    let case = cases::articulated(&ArticulatedSpec {
        template_vertices: 5000,
        scan_points: 40_000,
        ..Default::default()
    });
    let hands: Vec<u32> = case.template.groups["hands"].clone();
    let distortion = |mesh: &conformd::mesh::Mesh| -> f64 {
        let tris: Vec<[u32; 3]> = case
            .template
            .triangles
            .iter()
            .filter(|t| t.iter().all(|v| hands.binary_search(v).is_ok()))
            .copied()
            .collect();
        conformd::mesh::quality::variation(&case.template.vertices, &mesh.vertices, &tris)
            .edge_length
            .std
    };
    let soft = common::run(&case, &ConformOptions::default(), true);
    let mut opts = ConformOptions::default();
    opts.stiffness.insert("hands".into(), 20.0);
    let stiff = common::run(&case, &opts, true);
    let (a, b) = (distortion(&soft.mesh), distortion(&stiff.mesh));
    eprintln!(
        "hands' edge-length variation std: {a:.4} with default springs, {b:.4} with springs x20"
    );
    assert!(b < 0.8 * a, "stiffer hands distort less: {a:.4} -> {b:.4}");
}
