//! Conformation speed on this machine: the whole `conform` call (global mapping to the
//! final report) for the sizes issue 2 names, with the time per stage, and how it grows
//! with template and scan size. Run: `cargo bench --bench conform` (or `make bench`);
//! `-- --quick` runs the 10k case only.

use conformd::conform::{ConformOptions, Conformed, conform};
use conformd::synth::cases::{self, ArticulatedSpec, Case};
use std::time::Instant;

fn run(case: &Case, landmarks: bool) -> Conformed {
    let lm = landmarks.then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
    conform(
        &case.template,
        &case.scan,
        lm,
        &ConformOptions::default(),
        &mut |_| {},
    )
    .expect("conforms")
}

fn bench(label: &str, case: &Case, landmarks: bool, repeats: usize, target: Option<f64>) {
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..repeats {
        let t = Instant::now();
        let r = run(case, landmarks);
        times.push(t.elapsed().as_secs_f64());
        last = Some(r);
    }
    times.sort_by(f64::total_cmp);
    let r = last.unwrap();
    let s = &r.report.seconds;
    let e = cases::correspondence_error(
        &r.mesh.vertices,
        case.truth.as_ref().unwrap(),
        &case.in_hole,
        &case.template.triangles,
    );
    println!(
        "{label:<34} {:>6} v {:>7} pts  best {:>6.3} s  median {:>6.3} s{}  | global {:.3} coarse {:.3} match {:.3} rot {:.3} solve {:.3} other {:.3} | {} its, error {:.3}%",
        case.template.vertices.len(),
        case.scan.vertices.len(),
        times[0],
        times[times.len() / 2],
        target.map_or(String::new(), |t| format!(
            " (target {t} s: {})",
            if times[times.len() / 2] <= t {
                "met"
            } else {
                "MISSED"
            }
        )),
        s.global,
        s.coarse,
        s.correspond,
        s.rotations,
        s.solve,
        s.total - s.global - s.coarse - s.correspond - s.rotations - s.solve,
        r.report.iterations.len(),
        e.mean * 100.0,
    );
}

fn case(v: usize, pts: usize, turned: bool) -> Case {
    cases::articulated(&ArticulatedSpec {
        template_vertices: v,
        scan_points: pts,
        turned,
        ..Default::default()
    })
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    println!(
        "conformd conformation benchmark ({} threads)",
        rayon::current_num_threads()
    );
    let c = case(10_000, 100_000, false);
    bench("10k onto 100k, landmarks", &c, true, 5, Some(1.0));
    let c = case(10_000, 100_000, true);
    bench("10k onto 100k, no landmarks", &c, false, 5, Some(1.0));
    if quick {
        return;
    }
    let c = case(50_000, 500_000, false);
    bench("50k onto 500k, landmarks", &c, true, 3, Some(6.0));
    let c = case(50_000, 500_000, true);
    bench("50k onto 500k, no landmarks", &c, false, 3, Some(6.0));
    println!("-- growth with template size (scan 100k points, landmarks)");
    for v in [2_500, 5_000, 10_000, 20_000, 40_000] {
        bench(
            &format!("template {v}"),
            &case(v, 100_000, false),
            true,
            3,
            None,
        );
    }
    println!("-- growth with scan size (template 10k vertices, landmarks)");
    for p in [25_000, 100_000, 400_000, 1_000_000] {
        bench(&format!("scan {p}"), &case(10_000, p, false), true, 3, None);
    }
}
