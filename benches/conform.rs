//! Conformation speed on this machine: the whole `conform` call (global mapping to the
//! final report) for the sizes issue 2 names, with the time per stage, and how it grows
//! with template and scan size. Run: `cargo bench --bench conform` (or `make bench`);
//! `-- --quick` runs the 11k and outside-mesh cases only; `-- --peer` also runs trimesh's
//! Sumner non-rigid ICP (`benches/peer/trimesh_sumner.py`, needs python3 with trimesh,
//! scipy, rtree) on the 11k case in the same run and prints the speed ratio;
//! `-- --only TEXT` runs the cases whose label holds TEXT (e.g. `rig`, for a profiler).

use conformd::conform::{ConformOptions, Conformed, GlobalReport, conform, conform_rigged};
use conformd::synth::cases::{self, ArticulatedSpec, Case};
use conformd::template::rig::TemplateRig;
use conformd_devset::devset;
use std::time::Instant;

/// The options conformed with: the defaults, or `--options FILE` (a `[conform]`-style
/// TOML) to measure other settings.
fn options() -> ConformOptions {
    let args: Vec<String> = std::env::args().collect();
    match args.iter().position(|a| a == "--options") {
        Some(i) => {
            let text = std::fs::read_to_string(&args[i + 1]).expect("options file");
            toml::from_str(&text).expect("options parse")
        }
        None => ConformOptions::default(),
    }
}

fn run(case: &Case, landmarks: bool, rig: Option<&TemplateRig>) -> Conformed {
    let lm = landmarks.then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
    match rig {
        None => conform(&case.template, &case.scan, lm, &options(), &mut |_| {}),
        Some(rig) => {
            let never = std::sync::atomic::AtomicBool::new(false);
            conform_rigged(
                &case.template,
                Some(rig),
                &case.scan,
                lm,
                &options(),
                &mut |_| {},
                &never,
            )
        }
    }
    .expect("conforms")
}

fn bench(label: &str, case: &Case, landmarks: bool, repeats: usize, target: Option<f64>) -> f64 {
    bench_rigged(label, case, landmarks, None, repeats, target)
}

fn bench_rigged(
    label: &str,
    case: &Case,
    landmarks: bool,
    rig: Option<&TemplateRig>,
    repeats: usize,
    target: Option<f64>,
) -> f64 {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--only")
        && !label.contains(args[i + 1].as_str())
    {
        return f64::NAN;
    }
    let mut times = Vec::new();
    let mut last = None;
    for _ in 0..repeats {
        let t = Instant::now();
        let r = run(case, landmarks, rig);
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
        "{label:<34} {:>6} v {:>7} pts  best {:>6.3} s  median {:>6.3} s{}  | setup {:.3} global {:.3} (align {:.3} limbs {:.3} rig {:.3}) coarse {:.3} match {:.3} rot {:.3} solve {:.3} other {:.3} | {} its, error {:.3}%",
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
        s.setup,
        s.global,
        s.align,
        s.limbs,
        s.rig,
        s.coarse,
        s.correspond,
        s.rotations,
        s.solve,
        s.total - s.setup - s.global - s.coarse - s.correspond - s.rotations - s.solve,
        r.report.iterations.len(),
        e.mean * 100.0,
    );
    if let GlobalReport::Automatic(a) = &r.report.global {
        println!(
            "{:<34} placements fitted {}, kept {}{}",
            "",
            a.articulated
                .as_ref()
                .map_or(a.fitted, |x| x.hypotheses.len()),
            a.kept,
            a.articulated.as_ref().map_or(String::new(), |x| format!(
                ", the rig's start {}",
                if x.kept_limb_search {
                    "not kept (the limb search's)"
                } else if x.bent_arms_start {
                    "with the forearms bent"
                } else {
                    "from the limb search"
                }
            ))
        );
    }
    times[times.len() / 2]
}

/// The peer on the same case, in this run: exports it, runs the Python script, prints
/// its figures and the ratio of its time to ours.
fn peer(case: &Case, ours: f64) {
    let dir = tempfile::tempdir().expect("temp dir");
    devset::export(case, true, &dir.path().join("case_11k_landmarks")).expect("export");
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peer/trimesh_sumner.py");
    match std::process::Command::new("python3")
        .arg(&script)
        .arg(dir.path())
        .output()
    {
        Ok(out) if out.status.success() => {
            let text = String::from_utf8_lossy(&out.stdout);
            print!("peer (trimesh nricp_sumner): {text}");
            let secs: Option<f64> = text
                .split_whitespace()
                .rev()
                .nth(1)
                .and_then(|s| s.parse().ok());
            if let Some(s) = secs {
                println!(
                    "peer time / conformd time: {:.0}x (target >= 50x)",
                    s / ours
                );
            }
        }
        Ok(out) => println!(
            "peer did not run: {}",
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .last()
                .unwrap_or("")
        ),
        Err(e) => println!("peer did not run: python3: {e}"),
    }
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
    let c = case(11_300, 100_000, false);
    // nine runs: the ratio to the peer rests on this median
    let ours = bench("11k onto 100k, landmarks", &c, true, 9, Some(0.5));
    if std::env::args().any(|a| a == "--peer") {
        peer(&c, ours);
    }
    let c = case(11_300, 100_000, true);
    bench("11k onto 100k, no landmarks", &c, false, 5, Some(1.5));
    // the station's case: the generic body's rig fitted first (its figure is the case's
    // template)
    let fig = conformd::template::figure::build(&conformd::template::figure::humanoid(), 11_300);
    let rig = TemplateRig::generic(&fig, conformd::template::Kind::Body);
    bench_rigged(
        "11k onto 100k, no landmarks, rig",
        &c,
        false,
        Some(&rig),
        5,
        Some(0.5),
    );
    // an outside mesh (uneven, open), posed, onto 100k points
    let cat = devset::with_holes(
        &devset::uneven(&devset::load("cat").expect("dev mesh"), 0.5, 11),
        3,
        0.03,
        12,
    )
    .0;
    let spec = devset::DevCaseSpec {
        scan_points: 100_000,
        ..Default::default()
    };
    bench(
        "cat (outside, 7.9k) onto 100k, landmarks",
        &devset::case(&cat, &spec),
        true,
        5,
        None,
    );
    if quick {
        return;
    }
    let c = case(50_000, 500_000, false);
    bench("50k onto 500k, landmarks", &c, true, 3, Some(2.0));
    let c = case(50_000, 500_000, true);
    bench("50k onto 500k, no landmarks", &c, false, 3, Some(2.0));
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
