//! Conformation on the development set of outside meshes (`conformd_devset::devset`): per case the
//! correspondence error (mean, in holes, 95th percentile), triangles flipped against the
//! truth, the edge-length variation and the time. Run: `cargo bench --bench devset`;
//! `-- --options FILE` conforms with a `[conform]`-style TOML of options, `-- --only
//! NAME,...` keeps the cases of those meshes (`captured`, `box` included), `-- --export DIR` writes each case (template,
//! scan, truth, landmarks) for the peer comparison in `benches/peer/`; `-- --set
//! standard|hard|generic|booth|all` picks the standard cases (default), the harder set of
//! issue 29 (its last column says which part, development or VALIDATION), the generic
//! templates onto outside subjects scored by semantic landmarks, the generic body onto
//! people in a booth's stances, or all of them.

use conformd::conform::{ConformOptions, conform};
use conformd::mesh::io::write_mesh;
use conformd::mesh::{Mesh, quality};
use conformd::render::{self, Colouring, RenderOptions};
use conformd::synth::cases::correspondence_error;
use conformd_devset::devset;
use std::path::PathBuf;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let value = |flag: &str| {
        args.iter()
            .position(|a| a == flag)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let opts: ConformOptions = match value("--options") {
        Some(p) => toml::from_str(&std::fs::read_to_string(&p).expect("options file"))
            .expect("options parse"),
        None => ConformOptions::default(),
    };
    let only: Vec<String> = value("--only")
        .map(|v| v.split(',').map(str::to_string).collect())
        .unwrap_or_default();
    let only: Vec<&str> = only.iter().map(String::as_str).collect();
    let export = value("--export").map(PathBuf::from);
    let pictures = value("--pictures").map(PathBuf::from);
    let set = value("--set").unwrap_or_else(|| "standard".into());
    let mut cases = Vec::new();
    if set == "standard" || set == "all" {
        cases.extend(devset::standard_cases(&only).expect("development meshes load"));
        if only.is_empty() || only.contains(&"captured") {
            cases.extend(devset::captured_cases().expect("the captured case renders"));
        }
    }
    if set == "hard" || set == "all" {
        for part in [devset::Part::Development, devset::Part::Validation] {
            cases.extend(devset::hard_cases(part, &only).expect("development meshes load"));
        }
    }
    println!(
        "{:<34} {:>6} {:>6} {:>7} | {:>6} {:>6} {:>6} {:>5} | {:>6} {:>6} | {:>6}",
        "case", "verts", "edgeCV", "points", "mean%", "holes%", "p95%", "flip", "var", "truth", "s"
    );
    println!(
        "  (flip: triangles flipped against the truth; var: edge-length variation std of the result, truth: of the truth)"
    );
    let mut sum = 0.0;
    for c in &cases {
        let case = &c.case;
        let truth = case.truth.as_ref().expect("dev cases know the truth");
        if let Some(dir) = &export {
            let d = dir.join(c.name.replace([' ', ','], "_").replace("__", "_"));
            devset::export(case, c.landmarks, &d).expect("export");
        }
        let lm = c
            .landmarks
            .then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
        let t = Instant::now();
        let r = conform(
            &case.template,
            &case.scan,
            lm,
            &c.options(&opts),
            &mut |_| {},
        )
        .expect("conforms");
        let secs = t.elapsed().as_secs_f64();
        let e = correspondence_error(
            &r.mesh.vertices,
            truth,
            &case.in_hole,
            &case.template.triangles,
        );
        let truth_var =
            quality::variation(&case.template.vertices, truth, &case.template.triangles);
        sum += e.mean;
        if let Some(dir) = &pictures {
            // the result coloured by its correspondence error (0 to 3% of the diagonal)
            // beside the truth
            std::fs::create_dir_all(dir).expect("pictures folder");
            let diag = Mesh::new(truth.clone(), vec![]).diagonal();
            let err: Vec<f64> = r
                .mesh
                .vertices
                .iter()
                .zip(truth)
                .map(|(a, b)| 100.0 * (a - b).norm() / diag)
                .collect();
            let colour = Colouring::Values {
                values: err,
                min: 0.0,
                max: 3.0,
                unit: "% DIAGONAL".into(),
            };
            let ro = RenderOptions::default();
            let t = Mesh::new(truth.clone(), case.template.triangles.clone());
            let sheet = render::sheet(
                &[
                    (
                        render::render(&r.mesh, &colour, &ro),
                        format!("{} result", c.name),
                    ),
                    (render::render(&t, &Colouring::Plain, &ro), "truth".into()),
                ],
                1,
                [255, 255, 255],
            );
            let file = dir.join(format!("{}.png", c.name.replace([' ', ','], "_")));
            render::save_png(&sheet, &file).expect("picture");
            write_mesh(&file.with_extension("obj"), &r.mesh).expect("result mesh");
        }
        println!(
            "{:<34} {:>6} {:>6.2} {:>7} | {:>6.3} {:>6.3} {:>6.3} {:>5} | {:>6.3} {:>6.3} | {:>6.2} {}",
            c.name,
            case.template.vertices.len(),
            devset::edge_cv(&case.template),
            case.scan.vertices.len(),
            e.mean * 100.0,
            e.mean_in_holes * 100.0,
            e.p95 * 100.0,
            e.flipped,
            r.report.final_variation.edge_length.std,
            truth_var.edge_length.std,
            secs,
            part_label(c.part)
        );
        // the truth's own folds over neighbouring triangles (a crumpled posing would have
        // no true answer); turned triangles of a posed limb are not folds
        let folds =
            quality::folded_triangles(&Mesh::new(truth.clone(), case.template.triangles.clone()));
        let st = &r.report.seconds;
        eprintln!(
            "  distance to the scan {:.3}% of the diagonal; seconds: setup {:.2} global {:.2} coarse {:.2} match {:.2} fill {:.2} rot {:.2} solve {:.2}",
            r.report.mean_distance_relative * 100.0,
            st.setup,
            st.global,
            st.coarse,
            st.correspond,
            st.fill,
            st.rotations,
            st.solve
        );
        if let conformd::conform::GlobalReport::Automatic(a) = &r.report.global {
            let turns: Vec<String> = a.limb_turns.iter().map(|t| format!("{t:.0}")).collect();
            eprintln!(
                "  limbs: {} found, turned [{}] degrees",
                a.limbs_found,
                turns.join(", ")
            );
        }
        print_fold_repair(&r.report);
        let own = quality::folded_triangles(&case.template);
        if r.report.folded_triangles > 0 || own > 0 {
            println!(
                "  (the result folds {} triangles over their neighbours; the template itself {own})",
                r.report.folded_triangles
            );
        }
        if folds > 0 {
            println!("  (the truth folds {folds} triangles over their neighbours)");
        }
    }
    if !cases.is_empty() {
        println!(
            "mean over {} cases: {:.3}%",
            cases.len(),
            sum / cases.len() as f64 * 100.0
        );
    }
    if set == "generic" || set == "all" {
        generic(&opts, &only, pictures.as_deref(), false);
    }
    if set == "booth" || set == "all" {
        generic(&opts, &only, pictures.as_deref(), true);
    }
    if (set == "standard" || set == "all") && (only.is_empty() || only.contains(&"box")) {
        // the paper's shape change (not a posture): a sphere onto a box with a face
        // missing, which the defaults must still fill flat
        let case = conformd::synth::cases::sphere_to_box_with_missing(4);
        let lm = Some((&case.template_landmarks[..], &case.scan_landmarks[..]));
        let r = conform(&case.template, &case.scan, lm, &opts, &mut |_| {}).expect("conforms");
        let f = conformd::synth::cases::box_figures(&r.mesh);
        println!(
            "sphere onto box with a missing face: missing region mean {:.3}% p90 {:.3}%, max anywhere {:.3}%; distance to the scan {:.3}%",
            f.missing_mean * 100.0,
            f.missing_p90 * 100.0,
            f.max_anywhere * 100.0,
            r.report.mean_distance_relative * 100.0
        );
    }
}

/// How a case's part is printed: the validation part loud, as never tuned on.
fn part_label(p: devset::Part) -> &'static str {
    match p {
        devset::Part::Development => "dev",
        devset::Part::Validation => "VALIDATION",
    }
}

/// Each semantic landmark's error and the limb ends on another limb.
fn print_marks(s: &conformd_devset::semantic::SemanticScore) {
    let per: Vec<String> = s
        .per_mark
        .iter()
        .map(|(m, d)| format!("{m} {:.2}", d * 100.0))
        .collect();
    println!("  {}", per.join(", "));
    if !s.wrong_limb.is_empty() {
        println!("  on another limb: {}", s.wrong_limb.join(", "));
    }
}

/// The generic templates onto outside subjects without landmarks (the up axis known),
/// scored by the semantic landmarks marked on both; `booth`: the generic body onto
/// people in a booth's stances (`semantic::booth_cases`) instead.
fn generic(opts: &ConformOptions, only: &[&str], pictures: Option<&std::path::Path>, booth: bool) {
    use conformd_devset::semantic;
    println!(
        "{:<44} {:>6} | {:>6} {:>6} {:>6} | {:>5} {:>6} | {:>6}",
        "generic template onto", "points", "mean%", "max%", "wrong", "fold", "var", "s"
    );
    let mut sum = 0.0;
    let mut n = 0;
    // `--front`: the station also knows which way the subject faces
    let with_front = std::env::args().any(|a| a == "--front");
    // `--rig-only`: the articulated fit of the template's rig alone, no elastic fit
    let rig_only = std::env::args().any(|a| a == "--rig-only");
    // `--no-rig`: the template's rig not fitted first (the limb search's start, as
    // before the rig)
    let without_rig = std::env::args().any(|a| a == "--no-rig");
    // `--turns 0,90,180,270`: every subject also turned to these headings
    let turns: Vec<f64> = std::env::args()
        .skip_while(|a| a != "--turns")
        .nth(1)
        .map(|v| {
            v.split(',')
                .map(|t| t.parse().expect("--turns: degrees"))
                .collect()
        })
        .unwrap_or_else(|| vec![0.0]);
    let parts: Vec<devset::Part> = match std::env::args().skip_while(|a| a != "--part").nth(1) {
        Some(p) if p == "dev" => vec![devset::Part::Development],
        Some(p) if p == "validation" => vec![devset::Part::Validation],
        _ => vec![devset::Part::Development, devset::Part::Validation],
    };
    let cases: Vec<semantic::SemanticCase> = if booth {
        parts
            .iter()
            .flat_map(|&part| semantic::booth_cases(part).expect("booth cases"))
            .collect()
    } else {
        parts
            .iter()
            .flat_map(|&part| {
                turns.iter().flat_map(move |&t| {
                    semantic::generic_cases_turned(part, only, t).expect("generic cases")
                })
            })
            .collect()
    };
    for c in cases {
        let t = Instant::now();
        let o = if with_front {
            c.options_with_front(opts)
        } else {
            c.options(opts)
        };
        if rig_only {
            // the articulated fit alone: the generic template's rig from each placement
            // the automatic alignment leaves, the best kept by its trimmed distances
            let (fits, rep) =
                conformd::conform::rig_fit_only(&c.template, &c.rig, &c.scan, &o).expect("rig fit");
            let a = rep.articulated.expect("a rig fit");
            let scores: Vec<String> = a
                .hypotheses
                .iter()
                .map(|f| format!("{:.4}", (f.template_to_scan + f.scan_to_template) * 100.0))
                .collect();
            let best = &fits[0];
            let secs = t.elapsed().as_secs_f64();
            let s = c.score(best);
            sum += s.mean;
            n += 1;
            let mesh = conformd::mesh::Mesh::new(best.clone(), c.template.triangles.clone());
            println!(
                "{:<44} {:>6} | {:>6.3} {:>6.3} {:>6} | {:>5} {:>6.3} | {:>6.2} {} rig fit: scores {} coverage {} shape {:?}",
                c.name,
                c.scan.vertices.len(),
                s.mean * 100.0,
                s.max * 100.0,
                s.wrong_limb.len(),
                conformd::mesh::quality::folded_triangles(&mesh),
                0.0,
                secs,
                part_label(c.part),
                scores.join("/"),
                a.hypotheses
                    .iter()
                    .map(|f| format!("{:.2}", f.coverage))
                    .collect::<Vec<_>>()
                    .join("/"),
                a.shape
            );
            print_marks(&s);
            if let Some(dir) = pictures {
                std::fs::create_dir_all(dir).expect("pictures folder");
                let stem = c.name.replace([' ', ','], "_");
                write_mesh(&dir.join(format!("{stem}_rigfit.obj")), &mesh).expect("result");
                write_mesh(&dir.join(format!("{stem}_scan.ply")), &c.scan).expect("scan");
            }
            continue;
        }
        let r = if without_rig {
            conform(&c.template, &c.scan, None, &o, &mut |_| {}).expect("conforms")
        } else {
            c.conform(&o).expect("conforms")
        };
        let secs = t.elapsed().as_secs_f64();
        let s = c.score(&r.mesh.vertices);
        if let Some(dir) = pictures {
            // the result coloured by its distance to the scan, and both as files
            std::fs::create_dir_all(dir).expect("pictures folder");
            let stem = c.name.replace([' ', ','], "_");
            let surface = conformd::conform::correspond::ScanSurface::new(&c.scan).expect("scan");
            let colour = Colouring::distances(
                r.mesh
                    .vertices
                    .iter()
                    .map(|p| surface.nearest_point(p).1)
                    .collect(),
                "MESH UNITS",
            );
            let img = render::render(&r.mesh, &colour, &RenderOptions::default());
            render::save_png(&img, &dir.join(format!("{stem}.png"))).expect("picture");
            write_mesh(&dir.join(format!("{stem}_result.obj")), &r.mesh).expect("result");
            write_mesh(&dir.join(format!("{stem}_scan.ply")), &c.scan).expect("scan");
        }
        sum += s.mean;
        n += 1;
        println!(
            "{:<44} {:>6} | {:>6.3} {:>6.3} {:>6} | {:>5} {:>6.3} | {:>6.2} {}",
            c.name,
            c.scan.vertices.len(),
            s.mean * 100.0,
            s.max * 100.0,
            s.wrong_limb.len(),
            r.report.folded_triangles,
            r.report.final_variation.edge_length.std,
            secs,
            part_label(c.part)
        );
        print_marks(&s);
        print_fold_repair(&r.report);
        // what a station would flag for an operator's look
        if let Some(w) = conformd::conform::placement_warning(&r.report.global) {
            println!("  flagged for review: {w}");
        }
        if let conformd::conform::GlobalReport::Automatic(a) = &r.report.global {
            eprintln!(
                "  alignment: {} candidates, residual {:.4} (runner-up {:?}), {} fitted, kept {}; limbs turned {:?}",
                a.candidates_tried,
                a.residual,
                a.runner_up_residual,
                a.fitted,
                a.kept,
                a.limb_turns.iter().map(|t| t.round()).collect::<Vec<_>>()
            );
        }
    }
    println!(
        "{}: mean over {n} cases {:.3}%",
        if booth { "booth" } else { "generic" },
        sum / n.max(1) as f64 * 100.0
    );
}

/// What the fold repair after the elastic fit did, when it found anything.
fn print_fold_repair(report: &conformd::conform::ConformReport) {
    if let Some(f) = report.fold_repair.filter(|f| f.found > 0) {
        eprintln!(
            "  fold repair: {} turned over, {} vertices moved, {} left",
            f.found, f.moved, f.left
        );
    }
}
