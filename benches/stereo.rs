//! Stereo speed (issue 4's targets): one pod pair of 1280x960 images, rectify + disparity
//! + reproject, with conformd's own share (everything but the OpenCV calls); and a 4-pod
//! capture to a fused scan. The captures are rendered by the virtual rig. Run:
//! `cargo bench --bench stereo`.

use conformd::stereo::reconstruct::{
    PodReport, ReconstructOptions, ReconstructReport, fuse, pod_points,
};
use conformd::synth::rig::{PodSpec, RigFile, render_rig};
use conformd::synth::templates::{self, Kind};
use std::time::Instant;

fn median(mut t: Vec<f64>) -> f64 {
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn main() {
    let mut rig: RigFile = toml::from_str(
        &std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/rig.example.toml"
        ))
        .unwrap(),
    )
    .unwrap();
    // two more pods, front and back, for a 4-pod station
    let base = rig.pods[0].clone();
    let extra = |id: &str, x: f64| PodSpec {
        id: id.into(),
        position: [x, -0.3, 1.2],
        look_at: [0.1, 0.0, 0.5],
        ..base.clone()
    };
    rig.pods.push(extra("pod3", 2.1));
    rig.pods.push(extra("pod4", -1.9));
    let subject = templates::subject(
        &templates::build(Kind::Pig, 20_000),
        Kind::Pig,
        &Default::default(),
        &Default::default(),
    )
    .unwrap();
    let images = render_rig(&rig, &subject, 2.0, 1);
    let pods = rig.pods();
    let opts = ReconstructOptions {
        working_volume: rig.working_volume,
        ..Default::default()
    };
    println!(
        "conformd stereo benchmark ({} threads), 1280x960 pairs",
        rayon::current_num_threads()
    );
    // one pod pair
    let mut reports = Vec::new();
    let pair: Vec<f64> = (0..5)
        .map(|_| {
            let mut r = PodReport::default();
            let t = Instant::now();
            let pts = pod_points(
                &pods[0],
                &images[0].pixels,
                &images[1].pixels,
                &opts.sgbm,
                &mut r,
            )
            .unwrap();
            std::hint::black_box(pts);
            let s = t.elapsed().as_secs_f64();
            reports.push(r);
            s
        })
        .collect();
    let p = median(pair);
    let own = median(reports.iter().map(|r| r.seconds_own).collect());
    println!(
        "one pod: rectify + disparity + reproject median {p:.3} s (target 1.0 s: {}); conformd's own share {:.1}% (target 15%: {})",
        if p <= 1.0 { "met" } else { "MISSED" },
        own / p * 100.0,
        if own / p <= 0.15 { "met" } else { "MISSED" }
    );
    // four pods to a fused scan
    let all: Vec<f64> = (0..3)
        .map(|_| {
            let t = Instant::now();
            let mut points = Vec::new();
            for (k, pod) in pods.iter().enumerate() {
                let mut r = PodReport::default();
                points.extend(
                    pod_points(
                        pod,
                        &images[2 * k].pixels,
                        &images[2 * k + 1].pixels,
                        &opts.sgbm,
                        &mut r,
                    )
                    .unwrap(),
                );
            }
            let mut rep = ReconstructReport::default();
            std::hint::black_box(fuse(points, &opts, &mut rep));
            t.elapsed().as_secs_f64()
        })
        .collect();
    let a = median(all);
    println!(
        "4-pod capture to a fused scan: median {a:.3} s (target 4 s: {})",
        if a <= 4.0 { "met" } else { "MISSED" }
    );
}
