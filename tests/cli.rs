//! The `conformd` binary end to end on files: conform with landmarks and without, the
//! report's per-iteration figures, `info`, and the one-line error a bad file gets.

use crate::common;
use common::{Deadline, conformd};

use conformd::mesh::io::{PlyEncoding, obj_bytes, ply_bytes};
use conformd::mesh::landmarks::landmarks_text;
use conformd::synth::cases;
use std::path::Path;
use std::process::Command;

fn write_case(dir: &Path) -> cases::Case {
    let case = cases::sphere_to_box_with_missing(3);
    std::fs::write(dir.join("template.obj"), obj_bytes(&case.template)).unwrap();
    std::fs::write(
        dir.join("scan.ply"),
        ply_bytes(&case.scan, PlyEncoding::Ascii),
    )
    .unwrap();
    std::fs::write(dir.join("t.lm"), landmarks_text(&case.template_landmarks)).unwrap();
    std::fs::write(dir.join("s.lm"), landmarks_text(&case.scan_landmarks)).unwrap();
    case
}

#[test]
fn conform_with_landmarks_writes_mesh_and_report() {
    let dir = tempfile::tempdir().unwrap();
    let case = write_case(dir.path());
    let out = common::succeeded(conformd(
        &[
            "conform",
            "--template",
            "template.obj",
            "--scan",
            "scan.ply",
            "--template-landmarks",
            "t.lm",
            "--scan-landmarks",
            "s.lm",
            "--out",
            "out.ply",
            "--report",
            "report.json",
        ],
        dir.path(),
    ));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("wrote out.ply") && stdout.contains("wrote report.json"),
        "{stdout}"
    );
    let result = conformd::mesh::read_mesh(&dir.path().join("out.ply")).unwrap();
    assert_eq!(
        result.triangles, case.template.triangles,
        "template topology kept"
    );
    let f = cases::box_figures(&result);
    eprintln!(
        "missing region mean {:.3}% p90 {:.3}% max {:.3}%",
        f.missing_mean * 100.0,
        f.missing_p90 * 100.0,
        f.max_anywhere * 100.0
    );
    assert!(
        f.missing_mean < 0.02,
        "missing region mean {:.3}%",
        f.missing_mean * 100.0
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("report.json")).unwrap())
            .unwrap();
    let its = report["iterations"].as_array().unwrap();
    assert!(!its.is_empty());
    for key in [
        "matched",
        "filled",
        "mean_distance",
        "max_update",
        "seconds",
        "variation",
    ] {
        assert!(its[0].get(key).is_some(), "iteration report has {key}");
    }
    for key in ["edge_length", "angle", "area"] {
        assert!(
            its[0]["variation"][key]["std"].as_f64().is_some(),
            "variation has {key}"
        );
    }
    assert_eq!(report["global"]["kind"], "landmark_rbf");
    assert!(report["watertight_result"].as_bool().unwrap());
    // no temporary files left behind
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().contains(".tmp-"))
        .collect();
    assert!(leftovers.is_empty());
}

#[test]
fn conform_without_landmarks_and_paper_method() {
    let dir = tempfile::tempdir().unwrap();
    write_case(dir.path());
    common::succeeded(conformd(
        &[
            "conform",
            "--template",
            "template.obj",
            "--scan",
            "scan.ply",
            "--out",
            "auto.obj",
        ],
        dir.path(),
    ));
    assert!(dir.path().join("auto.obj").exists());
    common::succeeded(conformd(
        &[
            "conform",
            "--method",
            "paper",
            "--template",
            "template.obj",
            "--scan",
            "scan.ply",
            "--template-landmarks",
            "t.lm",
            "--scan-landmarks",
            "s.lm",
            "--out",
            "paper.ply",
            "--report",
            "paper.json",
        ],
        dir.path(),
    ));
    let report = std::fs::read_to_string(dir.path().join("paper.json")).unwrap();
    assert!(report.contains("\"method\": \"paper\""));
}

#[test]
fn bad_inputs_give_one_clear_line() {
    let dir = tempfile::tempdir().unwrap();
    write_case(dir.path());
    let bytes = std::fs::read(dir.path().join("scan.ply")).unwrap();
    std::fs::write(dir.path().join("cut.ply"), &bytes[..bytes.len() * 2 / 3]).unwrap();
    let out = conformd(
        &[
            "conform",
            "--template",
            "template.obj",
            "--scan",
            "cut.ply",
            "--out",
            "x.ply",
        ],
        dir.path(),
    );
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.starts_with("conformd: cut.ply:") && err.contains("truncated"),
        "{err}"
    );
    assert!(
        !dir.path().join("x.ply").exists(),
        "nothing written on failure"
    );

    std::fs::write(
        dir.path().join("bad.toml"),
        "max_iterations = 5\nmax_distanse = 0.1\n",
    )
    .unwrap();
    let out = conformd(
        &[
            "conform",
            "--template",
            "template.obj",
            "--scan",
            "scan.ply",
            "--config",
            "bad.toml",
            "--out",
            "x.ply",
        ],
        dir.path(),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("bad.toml") && err.contains("max_distanse"),
        "{err}"
    );

    let out = conformd(
        &["conform", "--scan", "scan.ply", "--out", "x.ply"],
        dir.path(),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("--template is needed"),
        "{err}"
    );
    std::fs::write(dir.path().join("g.txt"), "ears 1 2 999999\n").unwrap();
    let out = conformd(
        &[
            "conform",
            "--template",
            "template.obj",
            "--template-groups",
            "g.txt",
            "--scan",
            "scan.ply",
            "--out",
            "x.ply",
        ],
        dir.path(),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("g.txt: line 1") && err.contains("999999"),
        "{err}"
    );
}

#[test]
fn config_file_and_info() {
    let dir = tempfile::tempdir().unwrap();
    write_case(dir.path());
    std::fs::write(
        dir.path().join("station.toml"),
        "[conform]\nmax_iterations = 4\n[conform.align]\ntrim = 0.9\n",
    )
    .unwrap();
    common::succeeded(conformd(
        &[
            "conform",
            "--template",
            "template.obj",
            "--scan",
            "scan.ply",
            "--config",
            "station.toml",
            "--out",
            "c.ply",
            "--report",
            "r.json",
        ],
        dir.path(),
    ));
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("r.json")).unwrap()).unwrap();
    assert!(
        report["iterations"].as_array().unwrap().len() <= 4,
        "the config's iteration limit applies"
    );

    let out = common::succeeded(conformd(
        &["info", "c.ply", "--original", "template.obj"],
        dir.path(),
    ));
    let info: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(info["topology"]["watertight"], true);
    assert!(info["variation"]["edge_length"]["std"].as_f64().is_some());
}

#[test]
fn a_user_mesh_or_a_generic_template_named_in_a_config() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // a posed pig as the scan, the generic pig (with its own landmarks) as the template
    let out = conformd(
        &[
            "template",
            "pig",
            "--vertices",
            "3000",
            "--pose",
            "swing=10",
            "--out",
            "subject.ply",
        ],
        d,
    );
    assert!(out.status.success());
    let subject = conformd::mesh::read_mesh(&d.join("subject.ply")).unwrap();
    let lms = conformd::mesh::read_landmarks(&d.join("subject.landmarks")).unwrap();
    let pts = conformd::synth::cases::landmarks_on(&lms, &subject);
    std::fs::write(d.join("scan.landmarks"), landmarks_text(&pts)).unwrap();
    std::fs::write(
        d.join("station.toml"),
        "[template]\ngeneric = \"pig\"\nvertices = 3000\n[conform]\nmax_iterations = 8\n",
    )
    .unwrap();
    common::succeeded(conformd(
        &[
            "conform",
            "--config",
            "station.toml",
            "--scan",
            "subject.ply",
            "--scan-landmarks",
            "scan.landmarks",
            "--out",
            "c.ply",
        ],
        d,
    ));
    let c = conformd::mesh::read_mesh(&d.join("c.ply")).unwrap();
    assert_eq!(
        c.triangles, subject.triangles,
        "the generic pig of the config is the subject's template"
    );
    let diag = subject.diagonal();
    let err: f64 = c
        .vertices
        .iter()
        .zip(&subject.vertices)
        .map(|(a, b)| (a - b).norm())
        .sum::<f64>()
        / c.vertices.len() as f64
        / diag;
    assert!(err < 0.01, "correspondence error {:.3}%", err * 100.0);
    // a user mesh as the template: one of the samples serves as the generic mesh
    std::fs::write(d.join("groups.txt"), "front 0 1 2 3\n").unwrap();
    std::fs::write(d.join("user.toml"), "[template]\nmesh = \"subject.ply\"\nlandmarks = \"subject.landmarks\"\ngroups = \"groups.txt\"\n[conform]\nmax_iterations = 3\n[conform.stiffness]\nfront = 2.0\n").unwrap();
    common::succeeded(conformd(
        &[
            "conform",
            "--config",
            "user.toml",
            "--scan",
            "subject.ply",
            "--scan-landmarks",
            "scan.landmarks",
            "--out",
            "u.ply",
        ],
        d,
    ));
    std::fs::write(d.join("bad.toml"), "[template]\ngeneric = \"cow\"\n").unwrap();
    let out = conformd(
        &[
            "conform",
            "--config",
            "bad.toml",
            "--scan",
            "subject.ply",
            "--out",
            "x.ply",
        ],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("bad.toml") && err.contains("cow"),
        "{err}"
    );
}

#[test]
fn example_config_documents_the_defaults() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/conform.example.toml");
    let loaded = conformd::commands::load_conform_options(&path).expect("the example config loads");
    let as_json = |o: &conformd::conform::ConformOptions| serde_json::to_value(o).unwrap();
    assert_eq!(
        as_json(&loaded),
        as_json(&conformd::conform::ConformOptions::default())
    );
}

#[test]
fn template_model_modes_and_score() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::succeeded(conformd(
        &["template", "pig", "--vertices", "2000", "--out", "pig.obj"],
        d,
    ));
    assert!(d.join("pig.landmarks").exists());
    let back = conformd::mesh::read_mesh(&d.join("pig.obj")).unwrap();
    assert!(
        back.groups.contains_key("ears") && back.groups.contains_key("torso"),
        "groups survive the OBJ file"
    );
    let mut names = Vec::new();
    for (i, pose) in [
        "swing=10",
        "swing=-10,nod=5",
        "nod=-8",
        "twist=6",
        "swing=4,twist=-5",
        "nod=9,twist=2",
    ]
    .iter()
    .enumerate()
    {
        let name = format!("p{i}.ply");
        common::succeeded(conformd(
            &[
                "template",
                "pig",
                "--vertices",
                "2000",
                "--pose",
                pose,
                "--out",
                &name,
            ],
            d,
        ));
        names.push(name);
    }
    let mut args = vec!["model", "build", "--out", "m.json", "--quality"];
    args.extend(names.iter().map(String::as_str));
    let out = conformd(&args, d);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("mode  1") && text.contains("compactness"),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    common::succeeded(conformd(
        &[
            "model", "modes", "--model", "m.json", "--modes", "2", "--out", "modes",
        ],
        d,
    ));
    let sheet = image::open(d.join("modes/modes.png")).unwrap();
    assert_eq!(
        (sheet.width(), sheet.height()),
        (3 * 360, 2 * 270),
        "rows are modes, columns -, mean, +"
    );
    assert!(d.join("modes/mode1_plus3sd.ply").exists() && d.join("modes/mean.ply").exists());
    let out = conformd(
        &["model", "score", "--model", "m.json", "p0.ply", "pig.obj"],
        d,
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("p0.ply: scores") && text.contains("mahalanobis"),
        "{text}"
    );
    let out = conformd(
        &[
            "template",
            "body",
            "--vertices",
            "2000",
            "--out",
            "body.ply",
        ],
        d,
    );
    assert!(out.status.success());
    let out = conformd(&["model", "score", "--model", "m.json", "body.ply"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success()
            && err.contains("body.ply")
            && err.contains("not conformed from this model's template"),
        "{err}"
    );
}

#[test]
fn example_station_config_loads() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/station.example.toml");
    let opts = conformd::commands::load_conform_options(&path).expect("options load");
    assert_eq!(opts.stiffness.get("ears"), Some(&5.0));
    let src = conformd::commands::template_from_config(&path).expect("has [template]");
    assert_eq!(src.generic, Some(conformd::template::Kind::Pig));
    assert_eq!(src.vertices, Some(10_000));
}

/// `simulate --placement` then `calibrate --placement` through the binary, on a small
/// rig: every pod placed near its true pose, the measured rig file loads with rotations;
/// a malformed `--board-origin` or a missing `--rig` is refused in one line.
#[test]
fn placement_through_the_cli() {
    use conformd::stereo::rig::RigFile;
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
        p.image = [800, 600];
        p.focal_px = 690.0;
        p.distortion = [0.0; 5];
    }
    std::fs::write(d.join("rig.toml"), toml::to_string(&rig).unwrap()).unwrap();
    common::succeeded(conformd(
        &[
            "simulate",
            "--rig",
            "rig.toml",
            "--chessboard",
            "9x6",
            "--square",
            "0.08",
            "--placement",
            "--out",
            "place",
        ],
        d,
    ));
    let set = std::fs::read_dir(d.join("place"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let placement: toml::Table =
        toml::from_str(&std::fs::read_to_string(set.join("placement.toml")).unwrap()).unwrap();
    let origin: Vec<String> = placement["origin"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.to_string())
        .collect();
    let origin = format!("--board-origin={}", origin.join(","));
    let set = set.to_str().unwrap();
    let args = [
        "calibrate",
        "--placement",
        set,
        "--rig",
        "rig.toml",
        "--board",
        "9x6",
        "--square",
        "0.08",
    ];
    let out = conformd(
        &[&args[..], &[origin.as_str(), "--out", "measured.toml"]].concat(),
        d,
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("pod pod1: left camera at") && text.contains("pod pod2"),
        "{text}"
    );
    let measured = RigFile::load(&d.join("measured.toml")).unwrap();
    for (m, t) in measured.pods().iter().zip(rig.pods()) {
        let off = (m.left_pose.centre() - t.left_pose.centre()).norm();
        assert!(off < 0.01, "pod {} placed {off:.4} m off", m.id);
    }
    assert!(measured.pods.iter().all(|p| p.rotation.is_some()));
    // one clear line for a bad origin, and --rig is required
    let out = conformd(
        &[&args[..], &["--board-origin=1,2", "--out", "x.toml"]].concat(),
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("'1,2': expected x,y,z"),
        "{err}"
    );
    let out = conformd(
        &[
            "calibrate",
            "--placement",
            set,
            "--board",
            "9x6",
            "--square",
            "0.08",
            "--out",
            "x.toml",
        ],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && err.contains("--rig"), "{err}");
    assert!(!d.join("x.toml").exists());
}

#[test]
fn the_station_demo_runs_to_its_end() {
    // `make demo` on three of its postures: every capture fired through the box is
    // processed, fits as the README's table says, and the model and its sheet come out
    let dir = tempfile::tempdir().unwrap();
    let out = conformd(
        &["demo", "station", "--captures", "3", "--out", "d"],
        dir.path(),
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!stdout.contains("FAILED"), "{stdout}");
    let rows: Vec<Vec<&str>> = stdout
        .lines()
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .filter(|w| w.get(1).is_some_and(|s| s.starts_with("pig-")))
        .collect();
    let subjects: Vec<&str> = rows.iter().map(|w| w[1]).collect();
    assert_eq!(subjects, ["pig-01", "pig-02", "pig-03"], "{stdout}");
    for w in &rows {
        // the README's run: 0.049-0.050% of the diagonal, 26-28% filled (the crate's
        // floor and the far side unseen)
        let pct = |s: &str| s.trim_end_matches('%').parse::<f64>().unwrap();
        let (distance, filled) = (pct(w[3]), pct(w[4]));
        assert!(distance < 0.075, "{stdout}");
        assert!((15.0..40.0).contains(&filled), "{stdout}");
    }
    assert!(
        stdout.contains("3 captures processed by the daemon"),
        "{stdout}"
    );
    let d = dir.path().join("d");
    for id in rows.iter().map(|w| w[0]) {
        let result = d.join("station/results").join(id);
        for f in ["conformed.ply", "scan.ply", "report.json", "preview.png"] {
            assert!(result.join(f).is_file(), "{} has no {f}", result.display());
        }
    }
    let model: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.join("station/model.json")).unwrap()).unwrap();
    assert_eq!(model["samples"].as_array().map(Vec::len), Some(3));
    let sheet = std::fs::read(d.join("modes/modes.png")).unwrap();
    assert!(sheet.starts_with(b"\x89PNG"), "the mode sheet is no PNG");
    assert!(stdout.contains("mode sheet:"), "{stdout}");
    // fewer postures than the model needs: refused before anything runs
    let out = conformd(
        &["demo", "station", "--captures", "2", "--out", "e"],
        dir.path(),
    );
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("--captures"), "{stderr}");
    assert!(!dir.path().join("e").exists());
}

#[test]
fn the_station_demo_stops_on_ctrl_c() {
    // Ctrl-C once the demo's daemon runs (it owns SIGINT then): the demo says why it
    // stopped and exits, leaving no worker behind
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let mut child = common::GroupChild::new(
        Command::new(env!("CARGO_BIN_EXE_conformd"))
            .args([
                "demo",
                "station",
                "--captures",
                "3",
                "--keep-running",
                "--out",
            ])
            .arg(&out)
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let t = std::time::Instant::now();
    let listen = loop {
        assert!(
            t.elapsed().as_secs() < 300,
            "the demo never started its daemon"
        );
        if let Ok(text) = std::fs::read_to_string(out.join("station.toml"))
            && let Some(l) = text.lines().find_map(|l| l.strip_prefix("listen = "))
        {
            let addr = l.trim_matches('"').to_string();
            if std::net::TcpStream::connect(&addr).is_ok() {
                break addr;
            }
        }
        assert!(child.try_wait().unwrap().is_none(), "the demo ended early");
        std::thread::sleep(std::time::Duration::from_millis(200));
    };
    assert!(listen.starts_with("127.0.0.1:"), "{listen}");
    let pid = child.id().to_string();
    assert!(
        Command::new("kill")
            .args(["-INT", &pid])
            .status()
            .unwrap()
            .success()
    );
    let t = std::time::Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        assert!(
            t.elapsed().as_secs() < 60,
            "the demo did not stop within 60 s of Ctrl-C"
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut stderr).unwrap();
    assert!(
        !status.success(),
        "an interrupted demo is not a finished one"
    );
    assert!(
        stderr.contains("the daemon stopped (Ctrl-C, SIGTERM"),
        "{stderr}"
    );
    // nothing of this demo still runs (its workers name its station file)
    let station = out.join("station.toml").display().to_string();
    let left: Vec<String> = std::fs::read_dir("/proc")
        .unwrap()
        .flatten()
        .filter_map(|e| std::fs::read(e.path().join("cmdline")).ok())
        .map(|c| String::from_utf8_lossy(&c).replace('\0', " "))
        .filter(|c| c.contains(&station))
        .collect();
    assert!(left.is_empty(), "left running: {left:?}");
}

#[test]
fn the_paper_demo_writes_both_methods_results() {
    // `conformd demo paper`: the paper's sphere onto a box with missing data, both methods,
    // each result a mesh in the template's vertex order, a report and a preview
    let dir = tempfile::tempdir().unwrap();
    let out = conformd(&["demo", "paper", "--out", "d"], dir.path());
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let d = dir.path().join("d");
    let template = conformd::mesh::io::read_mesh(&d.join("template.ply")).unwrap();
    for method in ["paper", "default"] {
        let line = stdout
            .lines()
            .find(|l| l.trim_start().starts_with(method))
            .unwrap_or_else(|| panic!("no {method} line in {stdout}"));
        // "missing region (N vertices) mean X%": the figure the paper reports, held to the
        // sphere-to-box test's own bound
        let mean: f64 = line
            .split("mean ")
            .nth(1)
            .and_then(|t| t.split('%').next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("no mean in '{line}'"));
        assert!(mean > 0.0 && mean < 2.0, "{method}: {line}");
        let m = conformd::mesh::io::read_mesh(&d.join(format!("conformed-{method}.ply"))).unwrap();
        assert_eq!(m.vertices.len(), template.vertices.len(), "{method}");
        assert_eq!(m.triangles, template.triangles, "{method}");
        let report: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(d.join(format!("report-{method}.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(report["method"], method, "{report}");
        let png = image::open(d.join(format!("preview-{method}.png"))).unwrap();
        assert!(png.width() > 100 && png.height() > 100);
    }
}

#[test]
fn cameras_lists_what_the_machine_has() {
    // `conformd cameras` names every /dev/video* device it can open, or says there are none
    let dir = tempfile::tempdir().unwrap();
    let out = conformd(&["cameras"], dir.path());
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let devices: Vec<String> = std::fs::read_dir("/dev")
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("video"))
        .collect();
    if devices.is_empty() {
        assert!(stdout.contains("no V4L2 cameras found"), "{stdout}");
    } else {
        // every device is named: listed, or said why it cannot be used
        assert!(!stdout.contains("no V4L2 cameras found"), "{stdout}");
        for d in &devices {
            assert!(stdout.contains(&format!("/dev/{d}")), "{d}: {stdout}");
        }
    }
}

#[test]
fn template_and_autorig_write_rigs_that_a_station_reads() {
    use conformd::template::rig::TemplateRig;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ok = |args: &[&str]| {
        let out = conformd(args, d);
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).to_string()
    };
    // the generic template's rig beside it; none beside a posed one (a subject)
    ok(&["template", "pig", "--vertices", "2000", "--out", "pig.obj"]);
    let pig = conformd::mesh::read_mesh(&d.join("pig.obj")).unwrap();
    let rig = TemplateRig::read(&d.join("pig.rig.json"), pig.vertices.len()).unwrap();
    assert_eq!(rig.bones.len(), 20);
    assert_eq!(rig.bones[rig.bone("leg_fl").unwrap()].limit_deg, 70.0);
    assert_eq!(rig.shapes.len(), 4);
    let said = ok(&[
        "template",
        "pig",
        "--vertices",
        "2000",
        "--pose",
        "swing=10",
        "--out",
        "posed.obj",
    ]);
    assert!(
        !d.join("posed.rig.json").exists() && said.contains("no rig"),
        "{said}"
    );
    // an automatic rig of a mesh, with its picture
    let said = ok(&[
        "autorig",
        "pig.obj",
        "--out",
        "auto.rig.json",
        "--preview",
        "auto.png",
    ]);
    assert!(
        said.contains("limb1_upper") && said.contains("wrote"),
        "{said}"
    );
    let auto = TemplateRig::read(&d.join("auto.rig.json"), pig.vertices.len()).unwrap();
    // what cannot be rigged is refused by name, and no rig file is left
    let cloud = conformd::mesh::Mesh::new(pig.vertices.clone(), Vec::new());
    conformd::mesh::write_mesh(&d.join("cloud.ply"), &cloud).unwrap();
    for (args, words) in [
        (
            &["autorig", "cloud.ply", "--out", "no.rig.json"][..],
            &["cloud.ply", "triangles"][..],
        ),
        (
            &["autorig", "pig.obj", "--limbs", "0", "--out", "no.rig.json"][..],
            &["--limbs 0"][..],
        ),
    ] {
        let out = conformd(args, d);
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} passed");
        for w in words {
            assert!(err.contains(w), "{args:?}: '{w}' not in {err}");
        }
        assert!(!d.join("no.rig.json").exists());
    }
    assert!(auto.bones.len() >= 9, "{:?}", auto.bones);
    let png = image::open(d.join("auto.png")).unwrap();
    assert_eq!((png.width(), png.height()), (1200, 400));
    // a station reads the rig its [template] names; a bad one is refused by `check`
    let check = |rig: &str| {
        std::fs::write(
            d.join("station.toml"),
            format!("[template]\nmesh = \"pig.obj\"\nrig = \"{rig}\"\n"),
        )
        .unwrap();
        let out = conformd(&["check", "station.toml"], d);
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).to_string(),
        )
    };
    let (passed, err) = check("auto.rig.json");
    assert!(passed, "{err}");
    let text = std::fs::read_to_string(d.join("auto.rig.json")).unwrap();
    std::fs::write(d.join("cut.rig.json"), &text[..text.len() / 3]).unwrap();
    let (passed, err) = check("cut.rig.json");
    assert!(
        !passed && err.contains("cut.rig.json") && err.contains("line 1"),
        "{err}"
    );
    ok(&[
        "template",
        "pig",
        "--vertices",
        "3000",
        "--out",
        "other.obj",
    ]);
    let (passed, err) = check("other.rig.json");
    assert!(
        !passed && err.contains("other.rig.json") && err.contains("vertices"),
        "{err}"
    );
    // the rig a conformation without landmarks fits first, named by --template-rig
    ok(&[
        "template",
        "pig",
        "--vertices",
        "2000",
        "--pose",
        "leg_fl=40,leg_hr=-30,nod=-20",
        "--out",
        "bent.obj",
    ]);
    ok(&[
        "conform",
        "--template",
        "pig.obj",
        "--template-rig",
        "pig.rig.json",
        "--scan",
        "bent.obj",
        "--out",
        "c.ply",
        "--report",
        "r.json",
    ]);
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.join("r.json")).unwrap()).unwrap();
    let joints = &report["global"]["articulated"]["joints_deg"];
    let leg = joints["leg_fl"].as_f64().unwrap_or(0.0);
    assert!((leg - 40.0).abs() < 8.0, "leg_fl turned {leg}: {joints}");
    let bent = conformd::mesh::read_mesh(&d.join("bent.obj")).unwrap();
    let c = conformd::mesh::read_mesh(&d.join("c.ply")).unwrap();
    let err = c
        .vertices
        .iter()
        .zip(&bent.vertices)
        .map(|(a, b)| (a - b).norm())
        .sum::<f64>()
        / c.vertices.len() as f64
        / bent.diagonal();
    // measured 0.52%
    eprintln!("rigged fit of the bent pig: {:.3}%", err * 100.0);
    assert!(err < 0.0075, "correspondence error {:.3}%", err * 100.0);
    let out = conformd(
        &[
            "conform",
            "--template",
            "pig",
            "--template-rig",
            "pig.rig.json",
            "--scan",
            "bent.obj",
            "--out",
            "x.ply",
        ],
        d,
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("brings its own rig"),
        "{err}"
    );
    std::fs::write(
        d.join("station.toml"),
        "[template]\ngeneric = \"pig\"\nrig = \"auto.rig.json\"\n",
    )
    .unwrap();
    let out = conformd(&["check", "station.toml"], d);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && err.contains("brings its own"),
        "{err}"
    );
}

#[test]
fn a_child_past_its_deadline_is_killed_with_its_own_children_and_fails_its_test() {
    // what every test's child runs under: a regression that blocks (a reader waiting on
    // a FIFO) fails the test that ran it, and leaves no process behind
    let dir = tempfile::tempdir().unwrap();
    let (pid, grandchild) = (dir.path().join("pid"), dir.path().join("grandchild"));
    let t = std::time::Instant::now();
    let hung = std::panic::catch_unwind(|| {
        Command::new("sh")
            .arg("-c")
            .arg(format!(
                "sleep 60 & echo $! > '{}'; echo $$ > '{}'; wait",
                grandchild.display(),
                pid.display()
            ))
            .output_within(std::time::Duration::from_millis(500))
    });
    let why = hung.expect_err("a hung child must fail its test");
    let why = why.downcast_ref::<String>().cloned().unwrap_or_default();
    assert!(
        why.contains("was still running after 500ms: killed"),
        "{why}"
    );
    assert!(
        t.elapsed() < std::time::Duration::from_secs(10),
        "{:?}",
        t.elapsed()
    );
    for f in [&pid, &grandchild] {
        let id = std::fs::read_to_string(f).unwrap();
        // gone, or a zombie whose parent (here, not always an init that reaps) has not
        // collected it yet: killed either way
        let state = std::fs::read_to_string(format!("/proc/{}/stat", id.trim()))
            .ok()
            .and_then(|s| s.rsplit(')').next().map(|r| r.trim().chars().next()))
            .flatten();
        assert!(
            matches!(state, None | Some('Z') | Some('X')),
            "process {} outlived its deadline (state {state:?})",
            id.trim()
        );
    }
}
