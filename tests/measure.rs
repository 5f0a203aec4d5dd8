//! Measurements (`measure`): known answers on solids, refusals of bad definitions, the
//! generic pig's measurements on conformed scans against the truth, and posture
//! normalisation over 12 postures.
//!
//! Heavy (12 conformations): run it optimised, as `make test` does (`--profile ci`).
use crate::common;
use common::{CHILD_LIMIT, Deadline};

use conformd::conform::{ConformOptions, conform};
use conformd::measure::{Definitions, Measurement, hull_perimeter, section_piece, volume};
use conformd::mesh::{Landmark, Mesh, V3};
use conformd::model::{Align, BuildOptions, ShapeModel};
use conformd::synth::cases::{landmarks_on, scan_subject};
use conformd::template::{self, Kind};
use std::collections::BTreeMap;
use std::f64::consts::PI;

/// A closed cylinder along z: `n` segments around, `rings` along, radius `r`, height `h`.
fn cylinder(r: f64, h: f64, n: usize, rings: usize) -> Mesh {
    let mut v = Vec::new();
    let mut t = Vec::new();
    for j in 0..=rings {
        for i in 0..n {
            let a = 2.0 * PI * i as f64 / n as f64;
            v.push(V3::new(
                r * a.cos(),
                r * a.sin(),
                h * j as f64 / rings as f64,
            ));
        }
    }
    let id = |i: usize, j: usize| (j * n + i % n) as u32;
    for j in 0..rings {
        for i in 0..n {
            t.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
            t.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
        }
    }
    // caps: a centre vertex each
    let (bottom, top) = (v.len() as u32, v.len() as u32 + 1);
    v.push(V3::new(0.0, 0.0, 0.0));
    v.push(V3::new(0.0, 0.0, h));
    for i in 0..n {
        t.push([bottom, id(i + 1, 0), id(i, 0)]);
        t.push([top, id(i, rings), id(i + 1, rings)]);
    }
    Mesh::new(v, t)
}

/// An axis-aligned box [0,a]x[0,b]x[0,c], each face split into k x k squares.
fn boxed(a: f64, b: f64, c: f64, k: usize) -> Mesh {
    let size = V3::new(a, b, c);
    let mut v: Vec<V3> = Vec::new();
    let mut t: Vec<[u32; 3]> = Vec::new();
    let mut index: BTreeMap<[i64; 3], u32> = BTreeMap::new();
    let mut vert = |g: [i64; 3], v: &mut Vec<V3>| -> u32 {
        *index.entry(g).or_insert_with(|| {
            v.push(V3::new(
                g[0] as f64 / k as f64 * size.x,
                g[1] as f64 / k as f64 * size.y,
                g[2] as f64 / k as f64 * size.z,
            ));
            v.len() as u32 - 1
        })
    };
    let k = k as i64;
    for axis in 0..3 {
        for side in [0, k] {
            let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
            for i in 0..k {
                for j in 0..k {
                    let g = |di: i64, dj: i64| {
                        let mut p = [0i64; 3];
                        p[axis] = side;
                        p[u] = i + di;
                        p[w] = j + dj;
                        p
                    };
                    let q = [g(0, 0), g(1, 0), g(1, 1), g(0, 1)].map(|p| vert(p, &mut v));
                    // outward: +axis side counter-clockwise in (u, w)
                    if side == k {
                        t.push([q[0], q[1], q[2]]);
                        t.push([q[0], q[2], q[3]]);
                    } else {
                        t.push([q[0], q[2], q[1]]);
                        t.push([q[0], q[3], q[2]]);
                    }
                }
            }
        }
    }
    Mesh::new(v, t)
}

fn value(ms: &[Measurement], name: &str) -> f64 {
    ms.iter().find(|m| m.name == name).unwrap().value
}

#[test]
fn known_answers_on_solids() {
    // a cylinder's girth is 2 pi r (the hull of a 256-gon: within 0.003%)
    let cyl = cylinder(0.3, 1.0, 256, 20);
    let defs = Definitions::parse(
        r#"
        [[measurement]]
        name = "girth"
        kind = "girth"
        at = [0.3, 0.0, 0.5]
        axis = [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
        [[measurement]]
        name = "volume"
        kind = "volume"
        [[measurement]]
        name = "height"
        kind = "height"
        point = [0.0, 0.0, 1.0]
        "#,
        "test",
    )
    .unwrap();
    let ms = defs.resolve(&cyl, &[]).unwrap().measure(&cyl).unwrap();
    let girth = value(&ms, "girth");
    assert!((girth / (2.0 * PI * 0.3) - 1.0).abs() < 0.003, "{girth}");
    // the polygon's own area, pi r^2 sin(2pi/n)/(2pi/n), to 0.01%
    let v = value(&ms, "volume");
    assert!((v / (PI * 0.09) - 1.0).abs() < 0.003, "{v}");
    assert!((value(&ms, "height") - 1.0).abs() < 1e-12);

    // a box: volume exactly, widths across each axis, and its girth
    let b = boxed(0.4, 0.25, 0.9, 8);
    let defs = Definitions::parse(
        r#"
        [[measurement]]
        name = "volume"
        kind = "volume"
        [[measurement]]
        name = "width_x"
        kind = "width"
        at = [0.0, 0.1, 0.45]
        axis = [[0.2, 0.125, 0.0], [0.2, 0.125, 0.9]]
        across = [[0.0, 0.1, 0.45], [0.4, 0.1, 0.45]]
        [[measurement]]
        name = "width_y"
        kind = "width"
        at = [0.0, 0.1, 0.45]
        axis = [[0.2, 0.125, 0.0], [0.2, 0.125, 0.9]]
        across = [[0.2, 0.0, 0.45], [0.2, 0.25, 0.45]]
        [[measurement]]
        name = "girth"
        kind = "girth"
        at = [0.0, 0.1, 0.45]
        axis = [[0.2, 0.125, 0.0], [0.2, 0.125, 0.9]]
        [[measurement]]
        name = "area"
        kind = "area"
        "#,
        "test",
    )
    .unwrap();
    let ms = defs.resolve(&b, &[]).unwrap().measure(&b).unwrap();
    assert!((value(&ms, "volume") - 0.4 * 0.25 * 0.9).abs() < 1e-12);
    assert!((value(&ms, "width_x") - 0.4).abs() < 1e-9);
    assert!((value(&ms, "width_y") - 0.25).abs() < 1e-9);
    assert!((value(&ms, "girth") - 2.0 * (0.4 + 0.25)).abs() < 1e-9);
    let area = 2.0 * (0.4 * 0.25 + 0.25 * 0.9 + 0.4 * 0.9);
    assert!((value(&ms, "area") - area).abs() < 1e-12);

    // a sphere at template resolution (10,242 vertices): area 4 pi r^2, volume within 0.3%
    let s = conformd::synth::icosphere(5);
    let r = 1.0;
    let a = s.area();
    assert!((a / (4.0 * PI * r * r) - 1.0).abs() < 0.003, "area {a}");
    assert!((volume(&s) / (4.0 / 3.0 * PI) - 1.0).abs() < 0.003);
    // its equator's girth
    let piece = section_piece(&s, &V3::new(1.0, 0.0, 0.0), &V3::z()).unwrap();
    let g = hull_perimeter(&piece, &V3::z());
    assert!((g / (2.0 * PI) - 1.0).abs() < 0.003, "{g}");
}

#[test]
fn bad_definitions_are_refused_naming_the_measurement() {
    let pig = template::build(Kind::Pig, 3000);
    let lms = pig.landmarks();
    let refuse = |text: &str, want: &str| {
        let e = Definitions::parse(text, "defs.toml")
            .and_then(|d| d.resolve(&pig.mesh, &lms))
            .unwrap_err()
            .to_string();
        assert!(e.contains(want), "{e}");
    };
    refuse(
        "[[measurement]]\nname = \"len\"\nkind = \"distance\"\nfrom = \"nose\"\nto = \"withers\"\n",
        "measurement 'len': landmark 'nose' is not one of the template's",
    );
    refuse(
        "[[measurement]]\nname = \"len\"\nkind = \"distance\"\nfrom = 999999\nto = \"withers\"\n",
        "vertex 999999, but the template has",
    );
    refuse(
        "[[measurement]]\nname = \"a\"\nkind = \"area\"\n[[measurement]]\nname = \"a\"\nkind = \"volume\"\n",
        "measurement 'a': named twice",
    );
    refuse(
        "[[measurement]]\nname = \"g\"\nkind = \"girth\"\nat = \"withers\"\naxis = [\"withers\", \"withers\"]\n",
        "the axis' two points are the same vertex",
    );
    refuse(
        "[[measurement]]\nname = \"x\"\nkind = \"weight\"\n",
        "defs.toml",
    );
    refuse(
        "[[measurement]]\nname = \"a b\"\nkind = \"area\"\n",
        "a name must be letters",
    );
    // lengths that are 0 on every mesh, and a file that defines nothing
    refuse(
        "[[measurement]]\nname = \"len\"\nkind = \"distance\"\nfrom = \"withers\"\nto = \"withers\"\n",
        "measurement 'len': points 1 and 2 are the same place",
    );
    refuse(
        "[[measurement]]\nname = \"back\"\nkind = \"path\"\npoints = [\"withers\", 5, 5]\n",
        "points 2 and 3 are the same place",
    );
    refuse(
        "[[measurement]]\nname = \"s\"\nkind = \"surface\"\nfrom = 7\nto = 7\n",
        "from and to are the same place",
    );
    refuse(
        "[[measurement]]\nname = \"h\"\nkind = \"height\"\npoint = \"withers\"\nposture_free = \"straightened\"\n",
        "unknown variant `straightened`, expected one of `parts`, `as_measured`, `skeleton`",
    );
    refuse("", "defines no measurement");
    refuse("[frame]\nfloor = 0.0\n", "defines no measurement");
    // an open template encloses no volume
    let mut open = pig.mesh.clone();
    open.triangles.truncate(open.triangles.len() - 10);
    let e = Definitions::parse("[[measurement]]\nname = \"v\"\nkind = \"volume\"\n", "d")
        .unwrap()
        .resolve(&open, &lms)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("measurement 'v': the template is not watertight"),
        "{e}"
    );
    // a mesh of another template
    let defs = Definitions::parse(conformd::measure::PIG, "pig").unwrap();
    let r = defs.resolve(&pig.mesh, &lms).unwrap();
    let other = template::build(Kind::Pig, 5000);
    let e = r.measure(&other.mesh).unwrap_err().to_string();
    assert!(e.contains("not a result of this template"), "{e}");
}

/// Twelve postures of the generic pig, every pose parameter within +/- 20 degrees.
fn postures() -> Vec<template::figure::Pose> {
    template::random_postures(Kind::Pig, 12, 20.0, 7)
}

#[test]
fn the_generic_pig_measured_on_conformed_scans_matches_the_truth_and_loses_its_posture() {
    let vertices = 6000;
    let fig = template::build(Kind::Pig, vertices);
    let lms: Vec<Landmark> = fig.landmarks();
    let defs = Definitions::parse(conformd::measure::PIG, "pig").unwrap();
    let resolved = defs.resolve(&fig.mesh, &lms).unwrap();
    // the posture model: other postures of the template (another seed)
    let samples: Vec<(String, Mesh)> = template::random_postures(Kind::Pig, 60, 20.0, 1)
        .iter()
        .enumerate()
        .map(|(i, p)| {
            (
                format!("p{i}"),
                template::subject(&fig, Kind::Pig, &BTreeMap::new(), p).unwrap(),
            )
        })
        .collect();
    let model = ShapeModel::build(
        &samples,
        &BuildOptions {
            align: Align::Rigid,
            posture: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(model.posture_modes, model.modes.len());

    let names = ["body_length", "heart_girth", "withers_height", "volume"];
    let mut raw: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    let mut normalised: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    let mut linear: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    let mut worst_against_truth: (f64, String) = (0.0, String::new());
    let mut worst_by_name: BTreeMap<String, f64> = BTreeMap::new();
    for (k, pose) in postures().iter().enumerate() {
        let truth = template::subject(&fig, Kind::Pig, &BTreeMap::new(), pose).unwrap();
        let (scan, _) = scan_subject(&truth, &[0.0, 90.0, 180.0, 270.0], 80_000, 0.0003, k as u64);
        let scan_lms = landmarks_on(&lms, &truth);
        let r = conform(
            &fig.mesh,
            &scan,
            Some((&lms, &scan_lms)),
            &ConformOptions::default(),
            &mut |_| {},
        )
        .unwrap();
        let e = conformd::synth::cases::correspondence_error(
            &r.mesh.vertices,
            &truth.vertices,
            &vec![false; truth.vertices.len()],
            &truth.triangles,
        );
        eprintln!(
            "posture {k}: correspondence error mean {:.3}% p95 {:.3}% max {:.3}%, area {:.4} / {:.4}",
            e.mean * 100.0,
            e.p95 * 100.0,
            e.max * 100.0,
            r.mesh.area(),
            truth.area()
        );
        let got = resolved.measure(&r.mesh).unwrap();
        let want = resolved.measure(&truth).unwrap();
        for (g, w) in got.iter().zip(&want) {
            let rel = (g.value / w.value - 1.0).abs();
            let e = worst_by_name.entry(g.name.clone()).or_default();
            *e = e.max(rel);
            if rel > worst_against_truth.0 {
                worst_against_truth = (rel, format!("{} in posture {k}", g.name));
            }
        }
        let (unposed, _) = template::remove_posture(&fig, Kind::Pig, &r.mesh).unwrap();
        let n = resolved.measure(&unposed).unwrap();
        let by_modes = resolved
            .measure(&model.remove_posture("result", &r.mesh).unwrap())
            .unwrap();
        for name in names {
            raw.entry(name).or_default().push(value(&got, name));
            normalised.entry(name).or_default().push(value(&n, name));
            linear.entry(name).or_default().push(value(&by_modes, name));
        }
    }
    for (name, w) in &worst_by_name {
        eprintln!(
            "{name:<16} largest difference to the truth over 12 postures {:.2}%",
            w * 100.0
        );
    }
    eprintln!(
        "conformed against truth: worst {:.2}% ({})",
        worst_against_truth.0 * 100.0,
        worst_against_truth.1
    );
    assert!(
        worst_against_truth.0 < 0.01,
        "measurements of conformed scans within 1% of the truth's: worst {:.2}% ({})",
        worst_against_truth.0 * 100.0,
        worst_against_truth.1
    );
    let spread = |v: &[f64]| {
        let (lo, hi) = v
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
                (a.min(x), b.max(x))
            });
        (hi - lo) / (v.iter().sum::<f64>() / v.len() as f64)
    };
    for name in names {
        eprintln!(
            "{name:<16} spread over 12 postures: raw {:.2}%, posture removed {:.2}% (by the posture model's modes {:.2}%)",
            spread(&raw[name]) * 100.0,
            spread(&normalised[name]) * 100.0,
            spread(&linear[name]) * 100.0
        );
    }
    for name in ["body_length", "heart_girth"] {
        let (r, n) = (spread(&raw[name]), spread(&normalised[name]));
        assert!(
            n <= r / 3.0 && n < 0.01,
            "{name}: raw spread {:.2}%, normalised {:.2}%",
            r * 100.0,
            n * 100.0
        );
    }
}

/// Pigs of varied length, girth, legs and head in random postures, measured: (name,
/// measurements) per pig, from `seed`.
fn measured_pigs(count: usize, seed: u64) -> Vec<(String, Vec<Measurement>)> {
    use rand::{Rng, SeedableRng};
    let fig = template::build(Kind::Pig, 3000);
    let lms = fig.landmarks();
    let resolved = Definitions::parse(conformd::measure::PIG, "pig")
        .unwrap()
        .resolve(&fig.mesh, &lms)
        .unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..count)
        .map(|i| {
            let shape: BTreeMap<String, f64> = ["length", "girth", "leg_length", "head_size"]
                .iter()
                .map(|k| (k.to_string(), rng.random_range(0.85..1.15)))
                .collect();
            let pose = &template::random_postures(Kind::Pig, 1, 8.0, seed * 1000 + i as u64)[0];
            let subject = template::subject(&fig, Kind::Pig, &shape, pose).unwrap();
            (format!("s{i}"), resolved.measure(&subject).unwrap())
        })
        .collect()
}

#[test]
fn a_weight_that_depends_on_several_measurements_is_predicted_by_them_together() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    // the truth leans on two measurements that vary apart (the body's volume, and a
    // frame that weighs with its height, whatever the girth): neither predicts it
    // alone, both together do
    let truth =
        |ms: &[Measurement]| 1000.0 * value(ms, "volume") + 200.0 * value(ms, "withers_height");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    let noise = Normal::new(0.0, 0.005).unwrap();
    let weighed = |pigs: Vec<(String, Vec<Measurement>)>, rng: &mut rand_chacha::ChaCha8Rng| {
        pigs.into_iter()
            .map(|(n, ms)| {
                let kg = truth(&ms) * (1.0 + noise.sample(rng));
                (n, ms, kg)
            })
            .collect::<Vec<_>>()
    };
    let train = weighed(measured_pigs(40, 21), &mut rng);
    let fresh = weighed(measured_pigs(10, 22), &mut rng);
    let names = ["volume", "withers_height"];
    let features: Vec<String> = names.map(String::from).to_vec();
    let all = conformd::measure::weight::WeightModel::fit(&train, &features).unwrap();
    // on pigs the fit never saw: each prediction within 1.5%, where either measurement
    // alone misses by 2.5 times as much or more on average
    let error_of = |m: &conformd::measure::weight::WeightModel| {
        fresh
            .iter()
            .map(|(_, ms, kg)| (m.predict(ms).unwrap().kg / kg - 1.0).abs())
            .collect::<Vec<f64>>()
    };
    let together = error_of(&all);
    let worst = together.iter().copied().fold(0.0, f64::max);
    let mean = together.iter().sum::<f64>() / together.len() as f64;
    assert!(
        worst < 0.015,
        "three measurements: worst error {:.2}%",
        worst * 100.0
    );
    for name in names {
        let one = conformd::measure::weight::WeightModel::fit(&train, &[name.to_string()]).unwrap();
        let e = error_of(&one);
        let alone = e.iter().sum::<f64>() / e.len() as f64;
        eprintln!(
            "{name} alone: mean error {:.2}%; both together {:.2}% (worst {:.2}%)",
            alone * 100.0,
            mean * 100.0,
            worst * 100.0
        );
        assert!(
            alone > 2.5 * mean,
            "{name} alone: mean error {:.2}%, both together {:.2}%",
            alone * 100.0,
            mean * 100.0
        );
    }
    // and its own leave-one-out estimate says so
    assert!(all.cv_mean_relative_error < 0.01, "{all}");
}

#[test]
fn weights_are_recovered_from_measurements_with_cross_validated_error_under_4_percent() {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    let noise = Normal::new(0.0, 0.03).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let results = dir.path().join("results");
    let mut weights = String::from("id,kg\n");
    let mut samples = Vec::new();
    for (i, (_, ms)) in measured_pigs(40, 11).into_iter().enumerate() {
        // water-dense animals: volume x 1000 kg/m^3, a 3% scale error
        let kg = value(&ms, "volume") * 1000.0 * (1.0 + noise.sample(&mut rng));
        samples.push((format!("s{i}"), ms.clone(), kg));
        // as a station leaves them: results/<capture>/report.json, weights by subject tag
        let d = results.join(format!("cap-{i:02}"));
        std::fs::create_dir_all(&d).unwrap();
        let report = serde_json::json!({
            "capture": format!("cap-{i:02}"),
            "subject": format!("tag-{i}"),
            "station": "crate-t",
            "measurements": ms,
        });
        std::fs::write(d.join("report.json"), report.to_string()).unwrap();
        weights += &format!("tag-{i},{kg:.2}\n");
    }
    let features: Vec<String> = ["volume", "heart_girth", "body_length"]
        .map(String::from)
        .to_vec();
    let m = conformd::measure::weight::WeightModel::fit(&samples, &features).unwrap();
    eprintln!("{m}");
    assert!(m.cv_mean_relative_error < 0.04, "{m}");
    // through the CLI's job: the same fit from the results folder and weights.csv
    let wpath = dir.path().join("weights.csv");
    std::fs::write(&wpath, &weights).unwrap();
    let out = dir.path().join("weight.json");
    let j = conformd::commands::model_weigh(&wpath, &results, Some(features), &out).unwrap();
    assert_eq!(j.samples, 40);
    assert!((j.cv_mean_relative_error - m.cv_mean_relative_error).abs() < 1e-3);
    let loaded = conformd::measure::weight::WeightModel::load(&out).unwrap();
    let p = loaded.predict(&samples[0].1).unwrap();
    assert!(p.low < p.kg && p.kg < p.high);
    assert!(
        (p.kg / samples[0].2 - 1.0).abs() < 0.1,
        "{p:?} vs {}",
        samples[0].2
    );
    // the export: a row per result, a column per measurement
    let csv = conformd::commands::export_csv(&results).unwrap().csv;
    let lines: Vec<&str> = csv.lines().collect();
    assert_eq!(lines.len(), 41);
    assert!(lines[0].contains(",volume,") && lines[1].starts_with("cap-00,tag-0,crate-t,"));
    // a result an operator rejected weighs nothing and leaves the export
    let review = conformd::station::review::Review::new(
        conformd::station::review::Verdict::Rejected,
        Some("two animals in the crate".into()),
        0.0,
    )
    .unwrap();
    conformd::station::review::write(&results.join("cap-03"), &review).unwrap();
    let j = conformd::commands::model_weigh(&wpath, &results, None, &out).unwrap();
    assert_eq!(j.samples, 39);
    let export = conformd::commands::export_csv(&results).unwrap();
    assert_eq!(export.csv.lines().count(), 40);
    assert!(!export.csv.contains("\ncap-03,"));
    assert_eq!(export.rejected.len(), 1);
    // a damaged regression file is refused, naming it
    let bad = dir.path().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"format": "conformd-weight", "features": ["volume"]"#,
    )
    .unwrap();
    let e = conformd::measure::weight::WeightModel::load(&bad)
        .unwrap_err()
        .to_string();
    assert!(e.contains("bad.json: not a weight regression"), "{e}");
    // a bad weights file names its line
    std::fs::write(&wpath, "id,kg\ntag-1,heavy\n").unwrap();
    let e = conformd::commands::model_weigh(&wpath, &results, None, &out)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("line 2: weight 'heavy' is not a positive number"),
        "{e}"
    );
}

#[test]
fn the_measure_command_writes_json_and_csv_and_takes_the_posture_out() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let exe = env!("CARGO_BIN_EXE_conformd");
    let run = |args: &[&str]| {
        let out = std::process::Command::new(exe)
            .args(args)
            .current_dir(d)
            .output_within(CHILD_LIMIT);
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    run(&["template", "pig", "--vertices", "3000", "--out", "rest.obj"]);
    run(&[
        "template",
        "pig",
        "--vertices",
        "3000",
        "--pose",
        "nod=-25,swing=15,leg_fl=20",
        "--out",
        "posed.obj",
    ]);
    let json = run(&[
        "measure",
        "rest.obj",
        "posed.obj",
        "--template",
        "pig",
        "--vertices",
        "3000",
        "--normalise-posture",
        "--csv",
        "m.csv",
    ]);
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let get = |i: usize, key: &str, name: &str| {
        v[i][key]
            .as_array()
            .unwrap()
            .iter()
            .find(|m| m["name"] == name)
            .unwrap()["value"]
            .as_f64()
            .unwrap()
    };
    let (rest, posed) = (
        get(0, "measurements", "body_length"),
        get(1, "measurements", "body_length"),
    );
    let unposed = get(1, "normalised", "body_length");
    eprintln!("body length: rest {rest:.4}, posed {posed:.4}, posture removed {unposed:.4}");
    assert!(
        (posed / rest - 1.0).abs() > 0.02,
        "the posture changes the length"
    );
    assert!((unposed / rest - 1.0).abs() < 0.002, "{unposed} vs {rest}");
    let csv = std::fs::read_to_string(d.join("m.csv")).unwrap();
    assert!(csv.starts_with("mesh,body_length,") && csv.contains("body_length_normalised"));
    assert_eq!(csv.lines().count(), 3);
    // the two as one subject in two postures: the length varies raw, not posture-free
    run(&[
        "template",
        "pig",
        "--vertices",
        "3000",
        "--pose",
        "nod=15,swing=-20,leg_hl=-15",
        "--out",
        "posed2.obj",
    ]);
    let table = run(&[
        "measure",
        "rest.obj",
        "posed.obj",
        "posed2.obj",
        "--template",
        "pig",
        "--vertices",
        "3000",
        "--normalise-posture",
        "--repeatability",
    ]);
    assert!(table.starts_with("over 3 meshes"), "{table}");
    let row: Vec<&str> = table
        .lines()
        .find(|l| l.starts_with("body_length "))
        .unwrap_or_else(|| panic!("{table}"))
        .split_whitespace()
        .collect();
    // name mean sd cv% unit | mean sd cv%
    let cv = |k: usize| row[k].trim_end_matches('%').parse::<f64>().unwrap();
    assert!(
        cv(3) > 1.0 && cv(8) < 0.2,
        "raw {}% posture-free {}%: {table}",
        cv(3),
        cv(8)
    );
    for name in ["heart_girth", "flank_girth", "volume", "withers_height"] {
        assert!(table.contains(name), "{name}: {table}");
    }
    // a template mesh without definitions is refused with what to do
    let out = std::process::Command::new(exe)
        .args(["measure", "posed.obj", "--template", "rest.obj"])
        .current_dir(d)
        .output_within(CHILD_LIMIT);
    assert!(!out.status.success());
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(e.contains("--definitions"), "{e}");
}

/// A girth cut from its vertex group only (issue 22, item 2): the generic body's upper
/// chest (through the armpits) with its left arm turned 25-40 degrees either way. The
/// whole section's hull takes the arm in (1.45-2.50 m against 1.27 m); the torso's alone
/// stays within 1.3% of the arms-down figure (measured; held to 1.6%) and says what it
/// left out.
#[test]
fn a_girth_from_its_group_leaves_an_arm_against_the_chest_out() {
    use std::collections::BTreeMap;
    let fig = template::build(Kind::Body, 10_000);
    let lms = fig.landmarks();
    let definition = |group: &str| {
        Definitions::parse(
            &format!(
                "[[measurement]]\nname = \"upper_chest\"\nkind = \"girth\"\nat = [0.0, 0.0, 1.35]\naxis = [[\"hip_l\", \"hip_r\"], [\"shoulder_top_l\", \"shoulder_top_r\"]]\n{group}"
            ),
            "d",
        )
        .unwrap()
        .resolve(&fig.mesh, &lms)
        .unwrap()
    };
    let (whole, torso) = (definition(""), definition("group = \"torso\"\n"));
    let rest = torso.measure(&fig.mesh).unwrap()[0].value;
    for deg in [-40.0, -25.0, 25.0, 40.0] {
        let params = BTreeMap::from([("arm_l".to_string(), deg)]);
        let m = template::subject(
            &fig,
            Kind::Body,
            &BTreeMap::new(),
            &template::pose(Kind::Body, &params),
        )
        .unwrap();
        let w = whole.measure(&m).unwrap()[0].clone();
        let t = torso.measure(&m).unwrap()[0].clone();
        assert!(
            w.value > 1.1 * t.value,
            "arm {deg}: whole {} torso {}",
            w.value,
            t.value
        );
        assert!(
            (t.value / rest - 1.0).abs() < 0.016,
            "arm {deg}: torso {} against {rest} with the arms down",
            t.value
        );
        let warning = t.warning.unwrap_or_default();
        assert!(
            warning.contains("'torso' group only") && warning.contains(&format!("{:.4}", w.value)),
            "{warning}"
        );
        assert!(w.warning.is_none());
    }
}

/// The 3000-vertex generic body and the same posed by `degrees` per joint group.
fn posed_body(degrees: &[(&str, f64)]) -> (template::figure::Figure, Mesh) {
    let fig = template::build(Kind::Body, 3000);
    let pose = template::pose(
        Kind::Body,
        &degrees.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
    );
    let posed = template::subject(&fig, Kind::Body, &BTreeMap::new(), &pose).unwrap();
    (fig, posed)
}

/// Definitions `text` on the body `fig`: their values on it at rest, on `posed` as
/// measured, and on `posed` posture-free (the station's removal: the body's parts).
fn rest_raw_free(
    fig: &template::figure::Figure,
    posed: &Mesh,
    text: &str,
) -> [Vec<Measurement>; 3] {
    let r = Definitions::parse(text, "d")
        .unwrap()
        .resolve(&fig.mesh, &fig.landmarks())
        .unwrap();
    let removal = conformd::measure::PostureRemoval::for_figure(fig, Kind::Body, &r);
    [
        r.measure(&fig.mesh).unwrap(),
        r.measure(posed).unwrap(),
        removal.measure(&r, "posed", posed).unwrap(),
    ]
}

/// `posture_free = "as_measured"`: the posture-free value of such a measurement is the
/// raw one; the same definition without it is moved by the parts (and differs on a posed
/// subject).
#[test]
fn a_measurement_marked_as_measured_keeps_its_raw_value_posture_free() {
    let (fig, posed) = posed_body(&[("nod", 25.0), ("hip_l", -30.0), ("knee_l", 40.0)]);
    let text = |how: &str| {
        format!(
            "[[measurement]]\nname = \"crotch\"\nkind = \"height\"\npoint = [0.0, 0.0, 0.80]\n{how}\n\
             [[measurement]]\nname = \"neck\"\nkind = \"girth\"\nat = [0.0, 0.0, 1.555]\n\
             axis = [[\"shoulder_top_l\", \"shoulder_top_r\"], \"head_top\"]\n{how}\n"
        )
    };
    let measure = |how: &str| {
        let [_, raw, free] = rest_raw_free(&fig, &posed, &text(how));
        (raw, free)
    };
    let (raw, free) = measure("posture_free = \"as_measured\"");
    for name in ["crotch", "neck"] {
        assert_eq!(value(&raw, name), value(&free, name), "{name}");
    }
    let (raw_parts, moved) = measure("");
    for name in ["crotch", "neck"] {
        assert_eq!(value(&raw_parts, name), value(&raw, name), "{name}");
        assert!(
            (value(&moved, name) - value(&raw, name)).abs() > 1e-4 * value(&raw, name),
            "{name}: the parts changed nothing ({})",
            value(&raw, name)
        );
    }
}

/// `posture_free = "skeleton"`: the value is measured on the result with the template's
/// skeleton fitted and undone, so a subject the skeleton posed gets its rest neck back,
/// where the same girth as measured or moved by the parts does not.
#[test]
fn a_measurement_marked_skeleton_is_measured_with_the_skeleton_undone() {
    let (fig, posed) = posed_body(&[("nod", 30.0), ("head_turn", 25.0), ("bend", 15.0)]);
    let text = |how: &str| {
        format!(
            "[[measurement]]\nname = \"neck\"\nkind = \"girth\"\nat = [0.0, 0.0, 1.555]\n\
             axis = [[\"shoulder_top_l\", \"shoulder_top_r\"], \"head_top\"]\n{how}\n\
             [[measurement]]\nname = \"waist\"\nkind = \"girth\"\nat = [0.0, 0.0, 1.05]\n\
             axis = [[\"hip_l\", \"hip_r\"], [\"shoulder_top_l\", \"shoulder_top_r\"]]\n"
        )
    };
    let measure = |how: &str| rest_raw_free(&fig, &posed, &text(how));
    let [rest, raw, by_skeleton] = measure("posture_free = \"skeleton\"");
    let [_, _, by_parts] = measure("");
    let [_, _, as_measured] = measure("posture_free = \"as_measured\"");
    let off = |ms: &[Measurement], name: &str| {
        (value(ms, name) - value(&rest, name)).abs() / value(&rest, name)
    };
    assert!(
        off(&by_skeleton, "neck") < 0.002,
        "{}",
        off(&by_skeleton, "neck")
    );
    for (how, ms) in [
        ("raw", &raw),
        ("parts", &by_parts),
        ("as measured", &as_measured),
    ] {
        assert!(
            off(ms, "neck") > 5.0 * off(&by_skeleton, "neck").max(0.001),
            "{how}: neck {} off, the skeleton's {}",
            off(ms, "neck"),
            off(&by_skeleton, "neck")
        );
    }
    // the other measurement keeps its own route (the parts)
    assert_eq!(value(&by_skeleton, "waist"), value(&by_parts, "waist"));
}

#[test]
fn with_landmarks_the_booth_mans_girths_repeat_over_his_stances() {
    // The operator's 8 landmarks on the booth's man in three stances (hands at the
    // belly, arms forward, arms raised). The landmark RBF alone drew his shoulders up
    // round his head when the arms were raised (neck girth 1.31 m, thigh 0.78 m, against
    // 0.40 m and 0.51 m in the other stances); the rig fitted with the marks held keeps
    // every girth within 2% (3% asserted).
    use conformd::conform::conform_rigged;
    use conformd::template::rig::TemplateRig;
    use conformd_devset::{devset::Part, repeat};
    let subjects = repeat::subjects(Part::Development, 3, &["booth man"]).unwrap();
    let s = &subjects[0];
    let defs = Definitions::parse(conformd::measure::BODY, "generic").unwrap();
    let resolved = defs
        .resolve(&s.template.mesh, &s.template.landmarks())
        .unwrap();
    let rig = TemplateRig::generic(&s.template, s.kind);
    let never = std::sync::atomic::AtomicBool::new(false);
    let measured: Vec<Vec<Measurement>> = s
        .postures
        .iter()
        .map(|p| {
            let lm = Some((&p.template_landmarks[..], &p.scan_landmarks[..]));
            let r = conform_rigged(
                &s.template.mesh,
                Some(&rig),
                &p.scan,
                lm,
                &ConformOptions::default(),
                &mut |_| {},
                &never,
            )
            .unwrap();
            resolved.measure(&r.mesh).unwrap()
        })
        .collect();
    assert_eq!(measured.len(), 3, "three stances");
    for name in [
        "neck_girth",
        "chest_girth",
        "waist_girth",
        "hip_girth",
        "thigh_girth",
    ] {
        let v: Vec<f64> = measured.iter().map(|m| value(m, name)).collect();
        let (lo, hi) = v
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(l, h), &x| (l.min(x), h.max(x)));
        eprintln!("{name}: {v:?}");
        assert!(hi / lo - 1.0 < 0.03, "{name} over the stances: {v:?}");
    }
}
