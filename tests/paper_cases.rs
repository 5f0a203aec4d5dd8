//! The paper's synthetic cases (Ju et al. 2004, sections 3.1 and 3.2): a sphere onto a
//! cube with 8 corner landmarks, and a sphere onto a box with missing data.

use crate::common;

use conformd::conform::{ConformOptions, Method};
use conformd::mesh::{V3, topology};
use conformd::synth::{cases, distance_to_box_surface};

#[test]
fn sphere_to_cube_paper_method_spreads_the_deformation() {
    let case = cases::sphere_to_cube(4);
    let r = common::run(&case, &ConformOptions::paper(), true);
    let stds: Vec<f64> = r
        .report
        .iterations
        .iter()
        .map(|i| i.variation.edge_length.std)
        .collect();
    // The first iteration runs before most vertices have reached the cube; from the
    // peak on, the deviation of edge-length variation falls at every iteration (the
    // paper: 1.52 to 0.78 over its run).
    let peak = stds
        .iter()
        .cloned()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    assert!(peak.0 <= 2, "peak at iteration {}: {stds:?}", peak.0 + 1);
    for w in stds[peak.0..].windows(2) {
        assert!(w[1] <= w[0] + 1e-9, "edge-length deviation rose: {stds:?}");
    }
    let last = *stds.last().unwrap();
    assert!(
        last < 0.8 * peak.1,
        "fell only from {:.3} to {last:.3}",
        peak.1
    );
    // final mean distance to the cube's surface below 1% of the cube's edge (2)
    let mean: f64 = r
        .mesh
        .vertices
        .iter()
        .map(|p| distance_to_box_surface(p, &V3::new(2., 2., 2.)))
        .sum::<f64>()
        / r.mesh.vertices.len() as f64;
    assert!(
        mean / 2.0 < 0.01,
        "mean distance {:.4}% of the edge",
        mean / 2.0 * 100.0
    );
    assert!(topology::report(&r.mesh).watertight);
    eprintln!(
        "sphere->cube paper: edge-length std {:.3} (peak) -> {last:.3}, angle std {:.3}, area std {:.3}, mean distance {:.3}% of the edge",
        peak.1,
        r.report.final_variation.angle.std,
        r.report.final_variation.area.std,
        mean / 2.0 * 100.0
    );

    let d = common::run(&case, &ConformOptions::default(), true);
    let mean_d: f64 = d
        .mesh
        .vertices
        .iter()
        .map(|p| distance_to_box_surface(p, &V3::new(2., 2., 2.)))
        .sum::<f64>()
        / d.mesh.vertices.len() as f64;
    assert!(mean_d / 2.0 < 0.01);
    eprintln!(
        "sphere->cube default: edge-length std {:.3}, angle std {:.3}, area std {:.3}, mean distance {:.3}% of the edge, {} iterations",
        d.report.final_variation.edge_length.std,
        d.report.final_variation.angle.std,
        d.report.final_variation.area.std,
        mean_d / 2.0 * 100.0,
        d.report.iterations.len()
    );
}

#[test]
fn sphere_to_box_with_missing_data_both_methods() {
    let case = cases::sphere_to_box_with_missing(4);
    assert!(
        !topology::report(&case.scan).watertight,
        "the scan has holes"
    );
    for (method, opts) in [
        (Method::Paper, ConformOptions::paper()),
        (Method::Default, ConformOptions::default()),
    ] {
        let r = common::run(&case, &opts, true);
        let f = cases::box_figures(&r.mesh);
        eprintln!(
            "sphere->box {method:?}: missing region {} vertices, mean {:.2}%, p90 {:.2}%, max {:.2}% (max anywhere {:.2}%) of the box diagonal",
            f.missing_vertices,
            f.missing_mean * 100.0,
            f.missing_p90 * 100.0,
            f.missing_max * 100.0,
            f.max_anywhere * 100.0
        );
        assert!(
            f.missing_vertices > 100,
            "{method:?}: the missing region is covered"
        );
        assert!(
            f.missing_mean < 0.02,
            "{method:?}: mean {:.3}%",
            f.missing_mean * 100.0
        );
        assert!(
            f.missing_p90 < 0.02,
            "{method:?}: 90th percentile {:.3}%",
            f.missing_p90 * 100.0
        );
        // The box's corners are rounded by any smooth sphere, even where data is whole:
        // no vertex strays far, though.
        assert!(
            f.max_anywhere < 0.04,
            "{method:?}: max {:.3}%",
            f.max_anywhere * 100.0
        );
        assert!(
            r.report.watertight_result,
            "{method:?}: the result is watertight"
        );
        assert_eq!(
            r.mesh.triangles, case.template.triangles,
            "topology kept exactly"
        );
    }
}
