//! The development set of outside meshes (`tests/data`, `conformd_devset::devset`): each mesh posed
//! with a known answer, scanned from four sides and above, conformed with and without
//! landmarks by the default options; correspondence error against the truth.
//!
//! Heavy: run it optimised, as `make test` does (`--profile ci`).

use conformd::conform::{ConformOptions, GlobalReport, conform};
use conformd::mesh::quality;
use conformd::mesh::topology;
use conformd::synth::cases::correspondence_error;
use conformd_devset::devset;

#[test]
fn the_development_meshes_are_what_the_set_needs() {
    let cat = devset::load("cat").unwrap();
    let made = devset::with_holes(&devset::uneven(&cat, 0.5, 11), 3, 0.03, 12).0;
    assert!(devset::edge_cv(&made) >= 0.3, "{}", devset::edge_cv(&made));
    assert!(!topology::report(&made).watertight);
    assert_eq!(topology::boundary_loops(&made.triangles).len(), 3);
    let human = devset::load("human").unwrap();
    assert!(devset::edge_cv(&human) >= 0.3);
    let hand = devset::load("hand").unwrap();
    assert!(
        !topology::boundary_loops(&hand.triangles).is_empty(),
        "the hand is open"
    );
    assert_eq!(quality::folded_triangles(&made), 0);
}

#[test]
fn booth_stances_put_the_hands_where_they_say() {
    // the man (z up, facing -y at rest), posed through his automatic rig: hand tips
    // against his head top and his nose; the legs keep him standing (heels at the floor)
    use conformd_devset::posing::{Stance, stand};
    let man = devset::load("human").unwrap();
    let marks = conformd_devset::semantic::marks_of("human").unwrap();
    let at = |x: &[conformd::mesh::V3], name: &str| {
        x[marks.iter().find(|m| m.0 == name).unwrap().1 as usize]
    };
    let front = conformd::mesh::V3::new(0.0, -1.0, 0.0);
    let posed = stand(&man, front, &Stance::ALL).unwrap();
    for (stance, x) in Stance::ALL.into_iter().zip(posed) {
        assert_eq!(x.len(), man.vertices.len());
        let (head, nose) = (at(&x, "head_top"), at(&x, "nose_tip"));
        let hands = [at(&x, "hand_tip_l"), at(&x, "hand_tip_r")];
        let ahead = |p: conformd::mesh::V3| (p - nose).dot(&front);
        for h in hands {
            match stance {
                Stance::ArmsRaised => assert!(h.z > head.z, "{stance:?}: {h:?}"),
                Stance::ArmsForward => assert!(ahead(h) > 0.3 && h.z < head.z, "{stance:?}: {h:?}"),
                Stance::HandsAtBelly => {
                    assert!(h.z < nose.z - 0.3 && ahead(h) > -0.1, "{stance:?}: {h:?}")
                }
            }
        }
        let apart = |x: &[conformd::mesh::V3]| (at(x, "heel_l") - at(x, "heel_r")).norm();
        if stance == Stance::ArmsRaised {
            assert!(apart(&x) > apart(&man.vertices) + 0.1, "feet not apart");
        }
        let lift = at(&x, "heel_l").z - at(&man.vertices, "heel_l").z;
        assert!(lift.abs() < 0.05, "{stance:?}: heel lifted {lift}");
        // a turned limb, not a crumple: the armpits may fold a triangle or two
        let folded =
            quality::folded_triangles(&conformd::mesh::Mesh::new(x, man.triangles.clone()));
        assert!(folded <= 2, "{stance:?}: {folded} folded");
    }
}

#[test]
fn posing_gives_a_posture_change_not_a_crumple() {
    for c in devset::standard_cases(&[]).unwrap() {
        let truth = c.case.truth.as_ref().unwrap();
        let t = &c.case.template;
        let v = quality::variation(&t.vertices, truth, &t.triangles);
        let moved = truth
            .iter()
            .zip(&t.vertices)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max)
            / t.diagonal();
        assert!(
            moved > 0.05,
            "{}: the posture moves parts ({moved:.3})",
            c.name
        );
        assert!(
            v.edge_length.std < 0.08,
            "{}: edge variation {:.3}",
            c.name,
            v.edge_length.std
        );
        // a sliver at a bent joint may turn over; more would be a crumple
        let folds = quality::flipped_against(truth, &t.vertices, &t.triangles);
        assert!(
            folds * 2000 <= t.triangles.len(),
            "{}: the truth folds {folds} triangles of the template",
            c.name
        );
    }
}

/// (case, mean %, p95 %, flipped triangles): about 1.25x the figures measured with the
/// defaults (README "development set" tables; a flip count gets 2 more besides).
type Bounds = [(&'static str, f64, f64, usize)];

const STANDARD_BOUNDS: &Bounds = &[
    ("koala posed, landmarks", 0.32, 0.79, 0),
    ("koala turned, no landmarks", 0.37, 0.89, 0),
    ("koala hard posture, landmarks", 0.45, 1.28, 0),
    ("cat posed, landmarks", 0.28, 0.71, 0),
    // one triangle turns over against the truth since the limb search starts the fit
    // from turned limbs (mean 0.270%, as before the search)
    ("cat turned, no landmarks", 0.34, 0.87, 1),
    ("human posed, landmarks", 0.22, 0.42, 0),
    ("human turned, no landmarks", 0.26, 0.60, 0),
    ("hand posed, landmarks", 0.42, 0.78, 0),
    ("hand turned, no landmarks", 0.68, 1.65, 0),
    // Spot, added 2026-12-08: 0.191% (p95 0.380%) and 0.195% (0.411%)
    ("spot posed, landmarks", 0.24, 0.48, 0),
    ("spot turned, no landmarks", 0.25, 0.52, 0),
];

/// The harder set: development and validation parts, the landmark-free cases measured
/// after the limb search was added, the dense uneven ones after the automatic rig's fit
/// (before it: dense man 1.420% with 1,614 flipped, SMPL-X 0.338% with 1,576), the
/// flips after the fold repair (before it: SMPL-X 2,655 and 1,165, koala 50k 24).
const HARD_BOUNDS: &Bounds = &[
    ("koala large posture, landmarks", 0.63, 1.71, 2),
    ("koala large posture, none", 1.2, 4.31, 2),
    ("cat large posture, landmarks", 0.84, 1.98, 2),
    ("cat large posture, none", 0.86, 1.91, 2),
    ("man large posture, landmarks", 0.82, 1.64, 2),
    ("man large posture, none", 0.57, 1.47, 2),
    ("man dense uneven, landmarks", 0.95, 2.55, 2),
    ("man dense uneven, none", 0.69, 2.29, 2),
    // eyeballs finer than the scan (2,562 vertices each) inside the head: placed with
    // the head (before: the fold repair turned 93 of their triangles back)
    ("man with eyes, landmarks", 0.69, 1.30, 2),
    ("man with eyes, none", 0.35, 1.08, 2),
    // since the rig is fitted with the marks held (0.937% with 12 flipped before it)
    ("cow large posture, landmarks", 0.93, 2.79, 2),
    ("cow large posture, none", 1.28, 3.72, 2),
    ("koala 50k large posture, landmarks", 0.47, 1.23, 25),
    ("koala 50k large posture, none", 0.75, 2.93, 73),
    // since the rig is fitted with the marks held (0.913% before it)
    ("man onto woman, landmarks", 0.66, 1.49, 2),
    ("man onto woman, none", 0.55, 1.32, 2),
    // its eyeballs placed with the head (before: 981-1,024 and 815 flipped, all of
    // the latter on one eye); with landmarks the rest are on an ear and the fingers
    // (145-196 over four runs: the sums' order varies)
    ("SMPL-X dense uneven, landmarks", 0.38, 0.78, 300),
    ("SMPL-X dense uneven, none", 0.27, 0.60, 2),
];

fn bound(table: &Bounds, name: &str) -> (&'static str, f64, f64, usize) {
    *table
        .iter()
        .find(|b| b.0 == name)
        .unwrap_or_else(|| panic!("no bound for case '{name}'"))
}

#[test]
fn the_harder_set_holds_per_case() {
    // large postures, one person onto another, dense uneven templates; each with
    // landmarks and without (the up axis given); the validation part was never tuned on
    let opts = ConformOptions::default();
    let mut failures = Vec::new();
    let mut seen = 0;
    for part in [devset::Part::Development, devset::Part::Validation] {
        for c in devset::hard_cases(part, &[]).unwrap() {
            let case = &c.case;
            let truth = case.truth.as_ref().unwrap();
            let lm = c
                .landmarks
                .then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
            let r = conform(
                &case.template,
                &case.scan,
                lm,
                &c.options(&opts),
                &mut |_| {},
            )
            .unwrap();
            let e = correspondence_error(
                &r.mesh.vertices,
                truth,
                &case.in_hole,
                &case.template.triangles,
            );
            let (_, mean, p95, flips) = bound(HARD_BOUNDS, &c.name);
            seen += 1;
            if c.name.starts_with("man with eyes") {
                // each eyeball placed whole with what surrounds it: its rest shape
                // under one similarity, however the fit drew on it
                let eyes =
                    topology::enclosed_parts(&case.template.vertices, &case.template.triangles);
                assert_eq!(eyes.len(), 2, "{}", c.name);
                assert_eq!(r.report.enclosed_vertices, 2 * 2562, "{}", c.name);
                for eye in &eyes {
                    let rest: Vec<_> = eye
                        .iter()
                        .map(|&i| case.template.vertices[i as usize])
                        .collect();
                    let now: Vec<_> = eye.iter().map(|&i| r.mesh.vertices[i as usize]).collect();
                    let sim = conformd::mesh::transform::fit_similarity(&rest, &now, None, true);
                    let off = rest
                        .iter()
                        .zip(&now)
                        .map(|(a, b)| (sim.apply(a) - b).norm())
                        .fold(0.0, f64::max);
                    assert!(
                        off < 1e-9 * r.mesh.diagonal(),
                        "{}: an eye bent by {off}",
                        c.name
                    );
                }
            }
            if c.name.contains("dense uneven, none") {
                // these templates have no rig: one is found on them, and its fit (not
                // the limb search's start) goes on to the elastic fit
                let GlobalReport::Automatic(a) = &r.report.global else {
                    panic!("{}: aligned without landmarks", c.name)
                };
                let art = a
                    .articulated
                    .as_ref()
                    .expect("the automatic rig was fitted");
                assert_eq!(art.rig, "automatic", "{}", c.name);
                assert!(!art.kept_limb_search, "{}: {art:?}", c.name);
            }
            eprintln!(
                "{:<36} {:?}: mean {:.3}% (bound {mean}%) p95 {:.3}% (bound {p95}%) flipped {} (bound {flips})",
                c.name,
                part,
                e.mean * 100.0,
                e.p95 * 100.0,
                e.flipped
            );
            if e.mean * 100.0 > mean || e.p95 * 100.0 > p95 || e.flipped > flips {
                failures.push(format!(
                    "{}: mean {:.3}% p95 {:.3}% flipped {}",
                    c.name,
                    e.mean * 100.0,
                    e.p95 * 100.0,
                    e.flipped
                ));
            }
        }
    }
    assert_eq!(seen, HARD_BOUNDS.len(), "every bound has its case");
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn the_harder_set_is_as_hard_as_it_says() {
    // dense and uneven: 50k+ vertices, edge CV about 1 and over
    for name in ["human", "neutral"] {
        let dense = devset::dense_uneven_body(&devset::load(name).unwrap());
        let cv = devset::edge_cv(&dense);
        eprintln!(
            "{name} refined: {} vertices, edge CV {cv:.2}",
            dense.vertices.len()
        );
        assert!(dense.vertices.len() > 50_000 && cv > 0.95, "{name}: {cv}");
        // refining splits triangles without folding or opening anything
        assert!(conformd::mesh::quality::folded_triangles(&dense) <= 1);
        let before = topology::report(&devset::load(name).unwrap()).watertight;
        assert_eq!(topology::report(&dense).watertight, before);
    }
    // one person onto another: the same vertex order, another shape
    let (man, woman) = (
        devset::load("human").unwrap(),
        devset::load("woman").unwrap(),
    );
    assert_eq!(man.triangles, woman.triangles);
    let moved = man
        .vertices
        .iter()
        .zip(&woman.vertices)
        .map(|(a, b)| (a - b).norm())
        .sum::<f64>()
        / man.vertices.len() as f64
        / man.diagonal();
    assert!(moved > 0.01, "another person: {moved}");
    // the validation meshes stay out of the set the defaults are chosen on
    for c in devset::standard_cases(&[]).unwrap() {
        assert!(
            devset::VALIDATION_MESHES
                .iter()
                .all(|m| !c.name.starts_with(&format!("{m} "))),
            "{}",
            c.name
        );
    }
}

#[test]
fn default_conformation_holds_on_outside_meshes() {
    let opts = ConformOptions::default();
    let mut failures = Vec::new();
    for c in devset::standard_cases(&[]).unwrap() {
        let case = &c.case;
        let truth = case.truth.as_ref().unwrap();
        let lm = c
            .landmarks
            .then(|| (&case.template_landmarks[..], &case.scan_landmarks[..]));
        let r = conform(&case.template, &case.scan, lm, &opts, &mut |_| {}).unwrap();
        let e = correspondence_error(
            &r.mesh.vertices,
            truth,
            &case.in_hole,
            &case.template.triangles,
        );
        eprintln!(
            "{:<34} mean {:.3}% holes {:.3}% p95 {:.3}% flipped {} edge std {:.3}",
            c.name,
            e.mean * 100.0,
            e.mean_in_holes * 100.0,
            e.p95 * 100.0,
            e.flipped,
            r.report.final_variation.edge_length.std
        );
        // per-case bounds at about 1.25x the figures measured (README table), so that a
        // regression of any one case fails
        let (_, mean, p95, flips) = bound(STANDARD_BOUNDS, &c.name);
        let (mean, p95) = (mean / 100.0, p95 / 100.0);
        if e.mean > mean || e.p95 > p95 || e.flipped > flips {
            failures.push(format!(
                "{}: mean {:.3}% p95 {:.3}% flipped {}",
                c.name,
                e.mean * 100.0,
                e.p95 * 100.0,
                e.flipped
            ));
        }
        // the human template has a folded triangle of its own; the fit adds none
        let own = quality::folded_triangles(&case.template);
        if r.report.distortion_warning.is_some() || r.report.folded_triangles > own {
            failures.push(format!(
                "{}: distortion warning {:?}, {} folded (the template {own})",
                c.name, r.report.distortion_warning, r.report.folded_triangles
            ));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}

#[test]
fn a_distorted_result_is_flagged_without_ground_truth() {
    // two scan landmarks swapped (an operator's slip): the fit must tear the template
    // across the body, and the report says so from the template alone
    let mut c = devset::standard_cases(&["koala"]).unwrap().remove(0);
    let case = &mut c.case;
    let (a, b) = (case.scan_landmarks[0].pos, case.scan_landmarks[1].pos);
    case.scan_landmarks[0].pos = b;
    case.scan_landmarks[1].pos = a;
    let lm = Some((&case.template_landmarks[..], &case.scan_landmarks[..]));
    let r = conform(
        &case.template,
        &case.scan,
        lm,
        &ConformOptions::default(),
        &mut |_| {},
    )
    .unwrap();
    let v = r.report.final_variation;
    eprintln!(
        "swapped landmarks: edge std {:.3} area std {:.3}",
        v.edge_length.std, v.area.std
    );
    let w = r.report.distortion_warning.as_deref().expect("a warning");
    assert!(
        w.contains("distorted far beyond a change of posture"),
        "{w}"
    );
    assert!(
        r.report
            .to_string()
            .contains("warning: the result is distorted")
    );
}

#[test]
fn no_landmarks_finds_head_and_tail_whichever_way_the_subject_faces() {
    // the koala turned round (head where the tail was) and tipped: a rigid residual
    // alone can prefer the template the wrong way round on a near-symmetric body; the
    // elastic fit of every close hypothesis decides
    use conformd_devset::devset::DevCaseSpec;
    let koala = devset::load("koala").unwrap();
    for turn in [90.0, 180.0] {
        let spec = DevCaseSpec {
            turn,
            shift: 0.05,
            seed: 9,
            ..Default::default()
        };
        let case = devset::case(&koala, &spec);
        let (e, _) = without_landmarks(&case, &format!("turned {turn}"));
        assert!(
            e.mean < 0.006 && e.p95 < 0.02,
            "turned {turn}: a part swapped"
        );
    }
}

#[test]
fn a_near_symmetric_subject_gets_both_alignments_fitted() {
    // an ellipsoid with a small snout at one end: turned round, the rigid residuals
    // barely differ, so both placements are fitted: by its automatic rig (the snout a
    // limb), the better by distances both ways going on; without a rig, both through
    // the elastic fit
    use conformd_devset::devset::DevCaseSpec;
    let mut m = conformd::synth::icosphere(4);
    for v in &mut m.vertices {
        let snout = (-((v.x - 1.0).powi(2) + v.y.powi(2) + v.z.powi(2)) / 0.05).exp();
        *v = conformd::mesh::V3::new(v.x * (2.0 + 0.4 * snout), v.y * 0.8, v.z * 0.6);
    }
    let case = devset::case(
        &m,
        &DevCaseSpec {
            turn: 15.0,
            seed: 4,
            ..Default::default()
        },
    );
    let (e, r) = conformed_without_landmarks(&case, "near-symmetric");
    let GlobalReport::Automatic(a) = &r.report.global else {
        unreachable!("aligned without landmarks")
    };
    let art = a.articulated.as_ref().expect("an automatic rig");
    assert_eq!(art.hypotheses.len(), 2, "the close runner-up is fitted too");
    // the two fits score alike (the snout is small): the result says so, and the
    // station lists it for an operator's look
    assert!(art.ambiguous, "{:?}", art.hypotheses);
    assert!(
        r.report
            .placement_warning
            .as_deref()
            .is_some_and(|w| w.contains("two placements")),
        "{:?}",
        r.report.placement_warning
    );
    eprintln!(
        "near-symmetric: mean {:.3}%, fits {:?}, ambiguous {}",
        e.mean * 100.0,
        art.hypotheses,
        art.ambiguous
    );
    assert!(
        e.mean < 0.01,
        "mean {:.3}%: the snout ended at the wrong end",
        e.mean * 100.0
    );
    let mut opts = ConformOptions::default();
    opts.align.automatic_rig = false;
    let r = conform(&case.template, &case.scan, None, &opts, &mut |_| {}).unwrap();
    let conformd::conform::GlobalReport::Automatic(a) = r.report.global else {
        panic!("no landmarks: automatic alignment")
    };
    assert_eq!(a.fitted, 2, "without a rig: both through the elastic fit");
    let e = correspondence_error(
        &r.mesh.vertices,
        case.truth.as_ref().unwrap(),
        &case.in_hole,
        &case.template.triangles,
    );
    assert!(e.mean < 0.01, "without a rig: mean {:.3}%", e.mean * 100.0);
}

/// Conforms a case without landmarks by the defaults; its correspondence error and what
/// the automatic alignment did, printed under `label`.
fn without_landmarks(
    case: &conformd::synth::cases::Case,
    label: &str,
) -> (
    conformd::synth::cases::CorrespondenceError,
    conformd::conform::align::AlignReport,
) {
    let (e, r) = conformed_without_landmarks(case, label);
    let GlobalReport::Automatic(a) = r.report.global else {
        unreachable!("checked by conformed_without_landmarks")
    };
    (e, a)
}

/// [`without_landmarks`] with the whole result.
fn conformed_without_landmarks(
    case: &conformd::synth::cases::Case,
    label: &str,
) -> (
    conformd::synth::cases::CorrespondenceError,
    conformd::conform::Conformed,
) {
    let r = conform(
        &case.template,
        &case.scan,
        None,
        &ConformOptions::default(),
        &mut |_| {},
    )
    .unwrap();
    let e = correspondence_error(
        &r.mesh.vertices,
        case.truth.as_ref().unwrap(),
        &case.in_hole,
        &case.template.triangles,
    );
    let GlobalReport::Automatic(a) = &r.report.global else {
        panic!("no landmarks: automatic alignment")
    };
    eprintln!(
        "{label}: mean {:.3}% p95 {:.3}% (hypotheses fitted {}, kept {}, residuals {:.5} / {:?})",
        e.mean * 100.0,
        e.p95 * 100.0,
        a.fitted,
        a.kept,
        a.residual,
        a.runner_up_residual
    );
    (e, r)
}

#[test]
fn the_decimated_level_loses_nothing_against_full_resolution() {
    // the cat: uneven triangles, three holes, 7,865 vertices (decimated to 2,000)
    let cases = devset::standard_cases(&["cat"]).unwrap();
    let c = cases.iter().find(|c| c.landmarks).unwrap();
    let case = &c.case;
    let lm = Some((&case.template_landmarks[..], &case.scan_landmarks[..]));
    let error = |opts: &ConformOptions| {
        let r = conform(&case.template, &case.scan, lm, opts, &mut |_| {}).unwrap();
        let e = correspondence_error(
            &r.mesh.vertices,
            case.truth.as_ref().unwrap(),
            &case.in_hole,
            &case.template.triangles,
        );
        (e, r.report)
    };
    let (multires, report) = error(&ConformOptions::default());
    let (full, full_report) = error(&ConformOptions {
        multires_vertices: 0,
        ..Default::default()
    });
    eprintln!(
        "cat: decimated then full {:.3}% (holes {:.3}%, {:.2} s), full throughout {:.3}% (holes {:.3}%, {:.2} s)",
        multires.mean * 100.0,
        multires.mean_in_holes * 100.0,
        report.seconds.total,
        full.mean * 100.0,
        full.mean_in_holes * 100.0,
        full_report.seconds.total
    );
    // the schedule ran on the decimated template, the last iterations on all vertices
    let n = case.template.vertices.len();
    let first = &report.iterations[0];
    let last = report.iterations.last().unwrap();
    assert!(
        first.vertices <= 2000 && first.vertices >= 1900,
        "{}",
        first.vertices
    );
    assert_eq!(last.vertices, n);
    assert!(full_report.iterations.iter().all(|it| it.vertices == n));
    assert!(last.mean_distance_relative < 0.001);
    // holes 1.15: since the rig is fitted with the landmarks the full resolution fills
    // the cat's holes better (0.258 -> 0.219%) than the decimated level does (0.260 ->
    // 0.246%), which still halves the time
    assert!(
        multires.mean <= full.mean * 1.05 && multires.mean_in_holes <= full.mean_in_holes * 1.15,
        "decimated level {:.3}% / holes {:.3}%, full resolution {:.3}% / {:.3}%",
        multires.mean * 100.0,
        multires.mean_in_holes * 100.0,
        full.mean * 100.0,
        full.mean_in_holes * 100.0
    );
    assert_eq!(multires.flipped, 0);
}

#[test]
fn the_limb_search_turns_swung_limbs_toward_the_scan() {
    use conformd::conform::correspond::ScanSurface;
    use conformd::conform::limbs;
    use conformd_devset::posing::PoseSettings;
    // the man with his limbs swung 45-90 degrees, in place (no heading, turn or shift),
    // so the template's own placement is the rigid start
    let man = devset::load("human").unwrap();
    let spec = devset::DevCaseSpec {
        pose: PoseSettings {
            limbs: 8,
            limb_degrees: (45.0, 90.0),
            bend: 0.0,
            twist: 0.0,
            scale: 1.0,
            seed: 31,
        },
        ..devset::DevCaseSpec::default()
    };
    let case = devset::case(&man, &spec);
    let truth = case.truth.as_ref().unwrap();
    let diag = man.diagonal();
    let error = |x: &[conformd::mesh::V3]| {
        x.iter()
            .zip(truth)
            .map(|(a, b)| (a - b).norm())
            .sum::<f64>()
            / x.len() as f64
            / diag
    };
    let nb = topology::vertex_neighbours(man.vertices.len(), &man.triangles);
    let found = limbs::find(&man.vertices, &nb, 10);
    // head, hands and feet
    assert!(found.len() >= 5, "{} limbs found", found.len());
    let scan = ScanSurface::new(&case.scan).unwrap();
    let mut x = man.vertices.clone();
    let before = error(&x);
    let turns = limbs::search(
        &mut x,
        &man.triangles,
        &found,
        &scan,
        &limbs::SearchSettings::default(),
    );
    let after = error(&x);
    eprintln!(
        "limb search: mean error {:.3}% -> {:.3}% of the diagonal, turns {turns:.0?}",
        before * 100.0,
        after * 100.0
    );
    assert!(!turns.is_empty(), "nothing turned");
    // measured 7.13% -> 0.895% (five limbs turned 45-78 degrees); bound at 1.25x
    assert!(before > 0.05, "the posture is large: {before}");
    assert!(after < 0.0112, "{before} -> {after}");
}

/// The generic templates onto outside subjects without landmarks, as a station fits them
/// (the template's rig first, each bone's length and girth fitted with it): (case, mean
/// semantic landmark error %, limb ends on another limb). Bounds about 1.25x the figures
/// measured (2026-12-06, with the bone fields: 3.97, 6.87, 3.37, 2.76, 2.74, 4.60, 1.76,
/// 1.59; the man in the large posture 2.36 since the bent-arms start, 2026-12-07), kept
/// at the earlier bound where that is lower (koala both, cow posed: 4.00, 6.70, 2.65
/// before the bone fields); far from the aim (1.5%, no limb swapped), and
/// the README says so. A limb end on another limb is a wrong result: the bound is 0
/// everywhere, and a case known to have one is listed in `KNOWN_ON_ANOTHER_LIMB`.
const GENERIC_BOUNDS: &[(&str, f64, usize)] = &[
    ("generic pig onto koala, posed", 4.94, 0),
    ("generic pig onto koala, large posture", 8.44, 0),
    ("generic body onto human, posed", 4.21, 0),
    ("generic body onto human, large posture", 2.95, 0),
    ("generic pig onto cow, posed", 3.29, 0),
    ("generic pig onto cow, large posture", 5.75, 0),
    ("generic body onto woman, posed", 2.20, 0),
    ("generic body onto woman, large posture", 1.99, 0),
];

/// Generic cases whose whole fit is known to be wrong, with why: the per-case test leaves
/// them out (no bound would be honest), and a test of the right outcome that is expected
/// to fail (`known_failure_the_pig_onto_spot_*`) shows when a change fixes them.
const KNOWN_WRONG: &[(&str, &str)] = &[
    (
        "generic pig onto spot, posed",
        "fitted backwards (snout at the tail, 40.5%); with the front known 23%, its legs in the big head",
    ),
    (
        "generic pig onto spot, large posture",
        "fitted backwards (40.7%); with the front known 24%, its legs in the big head",
    ),
];

/// Generic cases known to end with limb ends on another limb, with why: the per-case test
/// holds their mean and leaves their limbs to a test of the right outcome that is
/// expected to fail (`known_failure_*` below), so that a fix shows as that test failing.
const KNOWN_ON_ANOTHER_LIMB: &[(&str, &str)] = &[(
    "generic body onto human, posed",
    "both toes end nearer the other foot's true place (the posing crossed his legs)",
)];

#[test]
fn generic_templates_onto_outside_subjects_hold_per_case() {
    // the station's real case: conformd's pig or body (another shape, another
    // triangulation) onto an outside animal or person, the up axis known, no landmarks;
    // scored by semantic landmarks marked on both
    use conformd_devset::semantic;
    let opts = ConformOptions::default();
    let mut failures = Vec::new();
    let mut seen = 0;
    for part in [devset::Part::Development, devset::Part::Validation] {
        for c in semantic::generic_cases(part, &[]).unwrap() {
            assert!(c.marks.len() >= 7, "{}: {} marks", c.name, c.marks.len());
            if KNOWN_WRONG.iter().any(|k| k.0 == c.name) {
                continue;
            }
            let r = c.conform(&c.options(&opts)).unwrap();
            let s = c.score(&r.mesh.vertices);
            let &(_, mean, wrong) = GENERIC_BOUNDS
                .iter()
                .find(|b| b.0 == c.name)
                .unwrap_or_else(|| panic!("no bound for case '{}'", c.name));
            seen += 1;
            eprintln!(
                "{:<40} {part:?}: mean {:.3}% (bound {mean}%), max {:.2}%, on another limb {:?} (bound {wrong})",
                c.name,
                s.mean * 100.0,
                s.max * 100.0,
                s.wrong_limb
            );
            let known = KNOWN_ON_ANOTHER_LIMB.iter().any(|k| k.0 == c.name);
            if s.mean * 100.0 > mean || (!known && s.wrong_limb.len() > wrong) {
                failures.push(format!(
                    "{}: mean {:.3}%, on another limb {:?}",
                    c.name,
                    s.mean * 100.0,
                    s.wrong_limb
                ));
            }
        }
    }
    assert_eq!(seen, GENERIC_BOUNDS.len(), "every bound has its case");
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The generic case `name` of development subject `subject`, and its fit as a station
/// makes it (up axis known, no landmarks).
fn development_generic_fit(
    subject: &str,
    name: &str,
) -> (
    conformd_devset::semantic::SemanticCase,
    conformd::conform::Conformed,
) {
    let c = conformd_devset::semantic::generic_cases(devset::Part::Development, &[subject])
        .unwrap()
        .into_iter()
        .find(|c| c.name == name)
        .unwrap();
    let r = c.conform(&c.options(&ConformOptions::default())).unwrap();
    (c, r)
}

/// The right outcome for the man posed (no limb end on another limb), known to fail:
/// when a change fixes it, this test fails saying so, and the case leaves
/// `KNOWN_ON_ANOTHER_LIMB`.
#[test]
#[should_panic(expected = "on another limb")]
fn known_failure_the_man_posed_has_no_limb_end_on_another_limb() {
    let name = KNOWN_ON_ANOTHER_LIMB[0].0;
    let (c, r) = development_generic_fit("human", name);
    let s = c.score(&r.mesh.vertices);
    assert!(
        s.wrong_limb.is_empty(),
        "{name}: on another limb {:?}",
        s.wrong_limb
    );
}

/// The right outcome for the generic pig onto Spot posed (a cartoon cow: short legs, a
/// head as big as its body, sitting on the front legs), known to fail: the development
/// set's usual quality, a mean under 5% and no hoof on another limb.
#[test]
#[should_panic(expected = "generic pig onto spot, posed: mean")]
fn known_failure_the_pig_onto_spot_fits_as_the_koala_does() {
    let name = KNOWN_WRONG[0].0;
    let (c, r) = development_generic_fit("spot", name);
    let s = c.score(&r.mesh.vertices);
    assert!(
        s.mean < 0.05 && s.wrong_limb.is_empty(),
        "{name}: mean {:.2}%, on another limb {:?}",
        s.mean * 100.0,
        s.wrong_limb
    );
}

/// While the pig onto Spot is fitted backwards, the station must not pass it silently:
/// the two placements' rig fits score alike, and the result is flagged for review.
#[test]
fn the_backwards_pig_onto_spot_is_flagged_for_review() {
    let (c, r) = development_generic_fit("spot", KNOWN_WRONG[0].0);
    let warning = conformd::conform::placement_warning(&r.report.global);
    assert!(
        warning
            .as_deref()
            .is_some_and(|w| w.contains("check which way the result faces")),
        "{}: no review flag ({warning:?})",
        c.name
    );
}

/// The generic body onto people in a booth's stances (`semantic::booth_cases`: the arms
/// turned at the shoulders, which the generic set never does), the booth's front known as
/// a booth knows it: (case, mean semantic error %). Bounds 1.25x the figures measured
/// (2026-12-07: 1.642, 1.533, 1.191, 1.514; the man's hands at the belly 1.433 since the
/// bent-arms start; the same with the up axis alone), no limb end on another limb. The
/// woman's hands at the belly are a known failure (`known_failure_hands_at_the_belly_*`).
const BOOTH_BOUNDS: &[(&str, f64)] = &[
    ("generic body onto human, hands at the belly", 1.79),
    ("generic body onto human, arms forward", 2.05),
    ("generic body onto human, arms raised", 1.92),
    ("generic body onto woman, arms forward", 1.49),
    ("generic body onto woman, arms raised", 1.89),
];

/// The booth's case known to fit wrong (`known_failure_hands_at_the_belly_*`).
const BOOTH_KNOWN_FAILURE: &str = "generic body onto woman, hands at the belly";

/// The booth's cases of a part whose names `want`, each fitted with the front known:
/// (case, score).
fn booth_fits(
    part: devset::Part,
    want: fn(&str) -> bool,
) -> Vec<(
    conformd_devset::semantic::SemanticCase,
    conformd_devset::semantic::SemanticScore,
)> {
    let opts = ConformOptions::default();
    conformd_devset::semantic::booth_cases(part)
        .unwrap()
        .into_iter()
        .filter(|c| want(&c.name))
        .map(|c| {
            let r = c.conform(&c.options_with_front(&opts)).unwrap();
            let s = c.score(&r.mesh.vertices);
            eprintln!(
                "{:<44} {part:?}: mean {:.3}%, max {:.2}%, on another limb {:?}",
                c.name,
                s.mean * 100.0,
                s.max * 100.0,
                s.wrong_limb
            );
            (c, s)
        })
        .collect()
}

#[test]
fn booth_stances_hold_per_case_with_the_front_known() {
    let mut failures = Vec::new();
    let mut seen = 0;
    for part in [devset::Part::Development, devset::Part::Validation] {
        for (c, s) in booth_fits(part, |n| n != BOOTH_KNOWN_FAILURE) {
            let &(_, mean) = BOOTH_BOUNDS
                .iter()
                .find(|b| b.0 == c.name)
                .unwrap_or_else(|| panic!("no bound for '{}'", c.name));
            seen += 1;
            if s.mean * 100.0 > mean || !s.wrong_limb.is_empty() {
                failures.push(format!(
                    "{}: mean {:.3}% (bound {mean}%), on another limb {:?}",
                    c.name,
                    s.mean * 100.0,
                    s.wrong_limb
                ));
            }
        }
    }
    assert_eq!(seen, BOOTH_BOUNDS.len(), "every bound has its case");
    assert!(failures.is_empty(), "{failures:#?}");
}

/// The right outcome for the woman's hands held before the belly (validation): each hand
/// tip within 3% of the diagonal of its place. Known to fail (2026-12-07: the rig fit
/// leaves her left forearm hanging at the hip, its hand tip 16% off: the fit from the
/// bent-arms start, which holds the man's, scores 0.5% worse than the fit from the limb
/// search's arms); when a change fixes it this test fails saying so, and the case joins
/// `BOOTH_BOUNDS`.
#[test]
#[should_panic(expected = "hand tips off")]
fn known_failure_hands_at_the_belly_are_fitted_at_the_belly() {
    let mut off = Vec::new();
    for part in [devset::Part::Development, devset::Part::Validation] {
        for (c, s) in booth_fits(part, |n| n == BOOTH_KNOWN_FAILURE) {
            off.extend(
                s.per_mark
                    .iter()
                    .filter(|m| m.0.starts_with("hand_tip") && m.1 > 0.03)
                    .map(|m| format!("{}: {} {:.1}%", c.name, m.0, m.1 * 100.0)),
            );
        }
    }
    assert!(off.is_empty(), "hand tips off: {off:?}");
}

/// A generic case fitted: how far the result faces the way the subject faces (cosine,
/// from the template's heel marks to its toe marks, level), its semantic mean, the fit.
fn fitted_facing(
    c: &conformd_devset::semantic::SemanticCase,
    o: &ConformOptions,
) -> (f64, f64, conformd::conform::Conformed) {
    let r = c.conform(o).unwrap();
    let x = &r.mesh.vertices;
    let at = |prefix: &str| {
        let p: Vec<_> = c
            .marks
            .iter()
            .filter(|m| m.name.starts_with(prefix))
            .map(|m| x[m.vertex as usize])
            .collect();
        p.iter().sum::<conformd::mesh::V3>() / p.len() as f64
    };
    let f = at("toe_") - at("heel_");
    let facing = conformd::mesh::V3::new(f.x, f.y, 0.0)
        .normalize()
        .dot(&c.front);
    let mean = c.score(x).mean;
    eprintln!(
        "{}: faces {facing:.2} of the way, mean {:.3}%",
        c.name,
        mean * 100.0
    );
    (facing, mean, r)
}

/// The large-posture case of one generic subject, turned `turn` degrees further.
fn large_generic_case(
    part: devset::Part,
    subject: &str,
    turn: f64,
) -> conformd_devset::semantic::SemanticCase {
    conformd_devset::semantic::generic_cases_turned(part, &[subject], turn)
        .unwrap()
        .into_iter()
        .find(|c| c.name.contains("large posture"))
        .unwrap()
}

#[test]
fn a_person_facing_the_other_way_is_fitted_facing_that_way() {
    // the man in the large posture turned round (development): with the up axis alone
    // he is fitted backwards (25.8% with the rig, 27.8% before it); a station that knows
    // its front fits him facing it (accuracy: the next test)
    let c = large_generic_case(devset::Part::Development, "human", 180.0);
    let (facing, _, _) = fitted_facing(&c, &c.options_with_front(&ConformOptions::default()));
    assert!(facing > 0.7, "fitted facing away: {facing}");
}

#[test]
fn a_person_turned_round_is_fitted_well_when_the_front_is_known() {
    let c = large_generic_case(devset::Part::Development, "human", 180.0);
    let o = c.options_with_front(&ConformOptions::default());
    let r = c.conform(&o).unwrap();
    let s = c.score(&r.mesh.vertices);
    eprintln!(
        "{}: {:.3}%, on another limb {:?}",
        c.name,
        s.mean * 100.0,
        s.wrong_limb
    );
    // measured 4.21% and none (7.31% and a hand on another limb before the rig); bound
    // at 1.25x
    assert!(
        s.mean < 0.0526 && s.wrong_limb.is_empty(),
        "{} {:?}",
        s.mean,
        s.wrong_limb
    );
}

#[test]
fn a_station_that_knows_the_front_fits_the_person_facing_it() {
    // validation (never tuned on): the woman in the large posture, with `[align]
    // template_front`/`scan_front`: measured 1.79% with the rig (6.96% and a hand on the
    // other arm before it), bound at 1.25x
    let c = large_generic_case(devset::Part::Validation, "woman", 0.0);
    let (facing, mean, r) = fitted_facing(&c, &c.options_with_front(&ConformOptions::default()));
    assert!(facing > 0.7, "fitted facing away: {facing}");
    assert!(mean < 0.0231, "{mean}");
    match &r.report.global {
        conformd::conform::GlobalReport::Automatic(a) => {
            assert_eq!(a.fitted, 1, "the front leaves one heading to fit")
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn semantic_scoring_sees_a_swapped_limb() {
    // the score itself: the truth scores 0; a result with the two front hooves' template
    // vertices moved onto each other's true places is flagged, not averaged away
    use conformd_devset::semantic;
    let c = semantic::generic_cases(devset::Part::Development, &["koala"])
        .unwrap()
        .remove(0);
    let mut x = c.template.vertices.clone();
    for m in &c.marks {
        x[m.vertex as usize] = m.truth;
    }
    let s = c.score(&x);
    assert!(s.mean < 1e-12 && s.wrong_limb.is_empty());
    let mark = |n: &str| c.marks.iter().find(|m| m.name == n).unwrap();
    let (fl, fr) = (mark("hoof_fl"), mark("hoof_fr"));
    x[fl.vertex as usize] = fr.truth;
    x[fr.vertex as usize] = fl.truth;
    let s = c.score(&x);
    assert_eq!(
        s.wrong_limb,
        vec!["hoof_fl".to_string(), "hoof_fr".to_string()]
    );
    assert!(s.max > 0.05, "{}", s.max);
}

/// The automatic rig on outside meshes: every marked limb end (hand tip, toe, hoof) is
/// moved most by the lower bone of a limb, ends of different limbs by different limbs,
/// and turning every limb 30 degrees about its joints folds no triangle.
#[test]
fn the_automatic_rig_finds_the_limbs_of_outside_meshes() {
    use conformd::template::rig::{AutoRigSettings, RigPose, TemplateRig, turn};
    for (name, limb_ends) in [
        ("human", vec!["hand_tip_l", "hand_tip_r", "toe_l", "toe_r"]),
        ("cow", vec!["hoof_fl", "hoof_fr", "hoof_hl", "hoof_hr"]),
        ("koala", vec!["hoof_fl", "hoof_fr", "hoof_hl", "hoof_hr"]),
    ] {
        let mesh = devset::load(name).unwrap();
        let rig = TemplateRig::automatic(&mesh, &AutoRigSettings::default()).unwrap();
        let marks = conformd_devset::semantic::marks_of(name).unwrap();
        let owner = rig.dominant_bones();
        let mut limbs_of_ends = Vec::new();
        for end in &limb_ends {
            let v = marks.iter().find(|m| &m.0 == end).unwrap().1;
            let bone = &rig.bones[owner[v as usize] as usize].name;
            assert!(
                bone.ends_with("_lower"),
                "{name}: {end} is moved most by {bone}"
            );
            limbs_of_ends.push(bone.clone());
        }
        limbs_of_ends.sort();
        limbs_of_ends.dedup();
        assert_eq!(
            limbs_of_ends.len(),
            limb_ends.len(),
            "{name}: {limbs_of_ends:?}"
        );
        let mut pose = RigPose::rest(&rig);
        for (b, bone) in rig.bones.iter().enumerate().skip(1) {
            let along = bone.tail - bone.head;
            let side = along.cross(&conformd::mesh::V3::new(0.3, 0.5, 0.8));
            pose.turns[b] = turn(side, 30.0);
        }
        let posed = rig.pose(&mesh.vertices, &pose);
        let folded = quality::flipped_against(&posed, &mesh.vertices, &mesh.triangles);
        let moved = posed
            .iter()
            .zip(&mesh.vertices)
            .filter(|(a, b)| (*a - *b).norm() > 1e-3 * mesh.diagonal())
            .count();
        println!(
            "{name}: {} bones, {moved} of {} vertices moved, {folded} folded",
            rig.bones.len(),
            mesh.vertices.len()
        );
        assert!(moved * 10 > mesh.vertices.len(), "{name}: {moved} moved");
        assert_eq!(folded, 0, "{name}");
    }
}

#[test]
fn posing_a_box_keeps_its_triangles_unfolded_and_moves() {
    use conformd::mesh::{V3, topology};
    use conformd_devset::posing::{PoseSettings, extremities, pose};
    let m = conformd::synth::tessellated_box(V3::new(4.0, 1.0, 1.0), 8);
    let nb = topology::vertex_neighbours(m.vertices.len(), &m.triangles);
    let ext = extremities(&m, &nb, 4);
    assert_eq!(ext.samples.len(), 4);
    // the first extremity is a far end of the long box
    let tip = m.vertices[ext.samples[0].0 as usize];
    assert!(tip.x.abs() > 1.5, "{tip:?}");
    let posed = pose(&m, &nb, &ext, &PoseSettings::default());
    let moved = posed
        .iter()
        .zip(&m.vertices)
        .filter(|(a, b)| (*a - *b).norm() > 1e-3)
        .count();
    assert!(moved > m.vertices.len() / 2);
    assert_eq!(
        conformd::mesh::quality::flipped_against(&posed, &m.vertices, &m.triangles),
        0
    );
}
