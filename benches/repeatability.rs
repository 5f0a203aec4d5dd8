//! Repeatability of measurements over postures (issue 22, `conformd_devset::repeat`): each subject
//! scanned in several postures, the generic template (with its rig, as a station fits
//! it) conformed onto every scan with its landmarks and without (the up axis known, as
//! a station's config says), then measured raw and posture-free. Per subject and
//! measurement: the mean and the coefficient of variation over the postures (CV, %),
//! raw, by the template's skeleton undone (the old `--normalise-posture`), by the
//! subject's own parts (the default), and measured on the result with its parts'
//! turns taken out (`unposed`). Run: `cargo bench --bench repeatability` (`-- --postures N`,
//! `-- --only NAME,...`, `-- --part dev|val|all`, `-- --front` to give the heading too).

use conformd::conform::{ConformOptions, conform_rigged};
use conformd::measure::{self, Definitions, Measurement, PostureRemoval};
use conformd::mesh::V3;
use conformd::template::Kind;
use conformd::template::rig::TemplateRig;
use conformd_devset::devset::Part;
use conformd_devset::repeat;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let count: usize = value("--postures").map_or(8, |v| v.parse().expect("--postures N"));
    let only: Vec<String> = value("--only")
        .map(|v| v.split(',').map(str::to_string).collect())
        .unwrap_or_default();
    let only: Vec<&str> = only.iter().map(String::as_str).collect();
    let parts: Vec<Part> = match value("--part").as_deref() {
        Some("dev") => vec![Part::Development],
        Some("val") => vec![Part::Validation],
        _ => vec![Part::Development, Part::Validation],
    };
    let front = args.iter().any(|a| a == "--front");
    let t0 = Instant::now();
    for part in parts {
        for s in repeat::subjects(part, count, &only).expect("subjects") {
            let defs = Definitions::parse(
                match s.kind {
                    Kind::Pig => measure::PIG,
                    Kind::Body => measure::BODY,
                },
                "generic",
            )
            .expect("definitions");
            let lms = s.template.landmarks();
            let resolved = defs.resolve(&s.template.mesh, &lms).expect("resolve");
            let methods: Vec<(&str, PostureRemoval)> = vec![
                (
                    "skeleton",
                    PostureRemoval::Skeleton(Box::new(s.template.clone()), s.kind),
                ),
                (
                    "parts",
                    PostureRemoval::for_figure(&s.template, s.kind, &resolved),
                ),
            ];
            let art = measure::posture::Articulation::from_figure(&s.template, V3::z());
            // the generic template's own rig, as a station fits it
            let rig = TemplateRig::generic(&s.template, s.kind);
            let never = std::sync::atomic::AtomicBool::new(false);
            for with_landmarks in [true, false] {
                let mut unposed: Vec<Vec<Measurement>> = Vec::new();
                let mut raw: Vec<Vec<Measurement>> = Vec::new();
                let mut free: Vec<Vec<Vec<Measurement>>> = vec![Vec::new(); methods.len()];
                let mut seconds = 0.0;
                for p in &s.postures {
                    let mut o = ConformOptions::default();
                    if !with_landmarks {
                        o.align.template_up = Some([0.0, 0.0, 1.0]);
                        o.align.scan_up = Some([0.0, 0.0, 1.0]);
                        if front {
                            o.align.template_front = Some([1.0, 0.0, 0.0]);
                            o.align.scan_front = Some([p.front.x, p.front.y, p.front.z]);
                        }
                    }
                    let lm =
                        with_landmarks.then(|| (&p.template_landmarks[..], &p.scan_landmarks[..]));
                    let t = Instant::now();
                    let r = conform_rigged(
                        &s.template.mesh,
                        Some(&rig),
                        &p.scan,
                        lm,
                        &o,
                        &mut |_| {},
                        &never,
                    )
                    .expect("conforms");
                    seconds += t.elapsed().as_secs_f64();
                    raw.push(resolved.measure(&r.mesh).expect("measures"));
                    let fit = art.fit(&r.mesh).expect("parts fit");
                    unposed.push(
                        resolved
                            .measure(&fit.normalised_mesh(&r.mesh))
                            .expect("measures unposed"),
                    );
                    for (k, (_, m)) in methods.iter().enumerate() {
                        free[k].push(
                            m.measure(&resolved, "result", &r.mesh)
                                .expect("measures posture-free"),
                        );
                    }
                }
                println!(
                    "\n{} ({}), {} postures, {}: conformation {:.2} s each",
                    s.name,
                    match s.part {
                        Part::Development => "development",
                        Part::Validation => "VALIDATION",
                    },
                    s.postures.len(),
                    if with_landmarks {
                        format!("{} landmarks", s.postures[0].template_landmarks.len())
                    } else if front {
                        "no landmarks, up and front known".into()
                    } else {
                        "no landmarks, up known".into()
                    },
                    seconds / s.postures.len() as f64
                );
                print!("  {:<18} {:>10} {:>8}", "measurement", "mean", "raw CV%");
                for (n, _) in &methods {
                    print!(" {:>10}", format!("{n} CV%"));
                }
                println!(" {:>10}", "unposed CV%");
                let u = measure::spread(&unposed);
                let r = measure::spread(&raw);
                let f: Vec<Vec<measure::Spread>> =
                    free.iter().map(|x| measure::spread(x)).collect();
                for (i, m) in r.iter().enumerate() {
                    print!("  {:<18} {:>10.4} {:>8.2}", m.name, m.mean, 100.0 * m.cv);
                    for fk in &f {
                        print!(" {:>10.2}", 100.0 * fk[i].cv);
                    }
                    println!(" {:>10.2}", 100.0 * u[i].cv);
                }
            }
        }
    }
    println!("\ntotal {:.0} s", t0.elapsed().as_secs_f64());
}
