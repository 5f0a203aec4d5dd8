//! Hostile and careless input (the hostile-input issue's cases fixed so far): each gets
//! one clear sentence and a failing exit, never a panic, a hang, or a "success" with
//! garbage; a failed command leaves no output behind.

use conformd::conform::{ConformOptions, conform};
use conformd::mesh::{Mesh, V3};
use conformd::synth::icosphere;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// Every file and folder under `dir`.
fn tree(dir: &Path) -> Vec<std::path::PathBuf> {
    fn walk(p: &Path, out: &mut Vec<std::path::PathBuf>) {
        if let Ok(rd) = std::fs::read_dir(p) {
            for e in rd.flatten() {
                out.push(e.path());
                if e.file_type().is_ok_and(|t| t.is_dir()) {
                    walk(&e.path(), out);
                }
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, &mut out);
    out.sort();
    out
}

/// Runs the binary in `dir`; asserts it failed within 10 s with every word in stderr,
/// without a panic, and created no file or folder in `dir`.
fn refused(dir: &Path, args: &[&str], words: &[&str]) -> String {
    let before = tree(dir);
    let t = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_conformd"))
        .args(args)
        .current_dir(dir)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr).to_string();
    assert!(
        t.elapsed() < Duration::from_secs(10),
        "{args:?} took {:?}",
        t.elapsed()
    );
    assert!(
        !out.status.success(),
        "{args:?} succeeded: {}",
        String::from_utf8_lossy(&out.stdout)
    );
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    for w in words {
        assert!(err.contains(w), "{args:?}: '{w}' not in: {err}");
    }
    let after = tree(dir);
    let new: Vec<_> = after.iter().filter(|p| !before.contains(p)).collect();
    assert!(new.is_empty(), "{args:?} left {new:?}");
    err
}

fn conform_err(template: &Mesh, scan: &Mesh, opts: &ConformOptions) -> String {
    match conform(template, scan, None, opts, &mut |_| {}) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("conformed"),
    }
}

#[test]
fn degenerate_geometry_is_refused_with_a_sentence() {
    let sphere = icosphere(2);
    let o = ConformOptions::default();
    // coordinates near 1e300 (panicked in the kd-tree)
    let mut far = sphere.clone();
    far.vertices[3] = V3::new(1e300, 0.0, 0.0);
    let e = conform_err(&sphere, &far, &o);
    assert!(e.contains("vertex 3") && e.contains("beyond"), "{e}");
    // 500 identical points ("mean distance NaN" and a mesh written)
    let same = Mesh::new(vec![V3::new(0.1, 0.2, 0.3); 500], vec![]);
    let e = conform_err(&sphere, &same, &o);
    assert!(e.contains("one place"), "{e}");
    // a template of one triangle (panicked in the coarse stage)
    let one = Mesh::new(
        vec![
            V3::new(0., 0., 0.),
            V3::new(1., 0., 0.),
            V3::new(0., 1., 0.),
        ],
        vec![[0, 1, 2]],
    );
    let e = conform_err(&one, &sphere, &o);
    assert!(e.contains("at least 4 vertices"), "{e}");
}

#[test]
fn work_bounding_options_have_ranges() {
    let sphere = icosphere(1);
    for (set, word) in [
        (
            ConformOptions {
                rotation_rings: 100_000,
                ..Default::default()
            },
            "rotation_rings must be 1 to 10",
        ),
        (
            ConformOptions {
                max_iterations: 1_000_000,
                ..Default::default()
            },
            "max_iterations",
        ),
        (
            ConformOptions {
                coarse_nodes: 0,
                ..Default::default()
            },
            "coarse_nodes",
        ),
        (
            ConformOptions {
                scan_to_template: f64::NAN,
                ..Default::default()
            },
            "scan_to_template",
        ),
    ] {
        let t = Instant::now();
        let e = conform_err(&sphere, &sphere, &set);
        assert!(e.contains(word), "{e}");
        assert!(t.elapsed() < Duration::from_secs(1));
    }
}

#[test]
fn a_model_of_one_shape_is_refused() {
    let m = icosphere(2);
    let samples: Vec<(String, Mesh)> = (0..3).map(|i| (format!("m{i}"), m.clone())).collect();
    let e = conformd::model::ShapeModel::build(&samples, &Default::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("one shape") && e.contains("no variance"), "{e}");
}

#[test]
fn careless_commands_get_one_clear_line_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // a template name that is neither built in nor a file
    refused(
        d,
        &[
            "conform",
            "--template",
            "cow",
            "--scan",
            "s.ply",
            "--out",
            "c.ply",
        ],
        &["'cow'", "neither pig, body"],
    );
    // shape and pose values that fold the template
    refused(
        d,
        &["template", "pig", "--shape", "girth=0", "--out", "t.obj"],
        &["girth", "0.7 to 1.4"],
    );
    refused(
        d,
        &["template", "pig", "--pose", "swing=400", "--out", "t.obj"],
        &["swing", "-45 to 45"],
    );
    assert!(!d.join("t.obj").exists());
    // disparity: a wrong output type, a range wider than the image, a textureless pair
    let grey = image::GrayImage::from_pixel(64, 48, image::Luma([128]));
    grey.save(d.join("l.png")).unwrap();
    grey.save(d.join("r.png")).unwrap();
    refused(
        d,
        &["disparity", "l.png", "r.png", "--out", "d.txt"],
        &["d.txt", ".pfm", ".png"],
    );
    refused(
        d,
        &[
            "disparity",
            "l.png",
            "r.png",
            "--out",
            "d.pfm",
            "--num-disparities",
            "100000",
        ],
        &["num_disparities", "1024"],
    );
    refused(
        d,
        &[
            "disparity",
            "l.png",
            "r.png",
            "--out",
            "d.pfm",
            "--num-disparities",
            "64",
        ],
        &["64 disparities", "64 pixels wide"],
    );
    refused(
        d,
        &[
            "disparity",
            "l.png",
            "r.png",
            "--out",
            "d.pfm",
            "--num-disparities",
            "16",
        ],
        &["no texture"],
    );
    assert!(!d.join("d.pfm").exists() && !d.join("d.txt").exists());
    // a mesh path that is a device or a folder is not read
    refused(d, &["info", "/dev/zero"], &["/dev/zero"]);
    std::fs::create_dir(d.join("folder.ply")).unwrap();
    refused(
        d,
        &["info", "folder.ply"],
        &["folder.ply", "not a regular file"],
    );
    // model modes at NaN standard deviations
    refused(
        d,
        &[
            "model", "modes", "--model", "m.json", "--sigma", "NaN", "--out", "modes",
        ],
        &["sigma", "NaN"],
    );
    assert!(!d.join("modes").exists());
}

#[test]
fn a_ply_holding_more_than_its_header_declares_is_refused() {
    use conformd::mesh::io::{PlyEncoding, ply_bytes, read_ply_bytes};
    let cloud = Mesh::new(icosphere(1).vertices, vec![]);
    for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian] {
        let bytes = ply_bytes(&cloud, enc);
        let n = cloud.vertices.len();
        let text = String::from_utf8_lossy(&bytes).to_string();
        let header_end = text.find("end_header\n").unwrap() + 11;
        let mut fewer = bytes[..header_end].to_vec();
        fewer = String::from_utf8(fewer)
            .unwrap()
            .replace(
                &format!("element vertex {n}"),
                &format!("element vertex {}", n - 2),
            )
            .into_bytes();
        fewer.extend_from_slice(&bytes[header_end..]);
        let e = read_ply_bytes("scan.ply", &fewer).unwrap_err().to_string();
        assert!(
            e.contains("scan.ply") && e.contains("header"),
            "{enc:?}: {e}"
        );
        // the file as written still reads
        assert_eq!(
            read_ply_bytes("scan.ply", &bytes).unwrap().vertices.len(),
            n
        );
    }
}

#[test]
fn calibration_images_without_a_board_are_refused_quickly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // noise at 1280x960: the full board search, without its fast check, ran over a minute
    let mut seed = 7u32;
    for i in 0..6 {
        for side in ["left", "right"] {
            let img = image::GrayImage::from_fn(1280, 960, |_, _| {
                seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                image::Luma([(seed >> 24) as u8])
            });
            img.save(d.join(format!("{side}{i:02}.png"))).unwrap();
        }
    }
    refused(
        d,
        &[
            "calibrate",
            "--images",
            ".",
            "--board",
            "9x6",
            "--square",
            "0.03",
            "--out",
            "pod.yml",
        ],
        &["board"],
    );
    assert!(!d.join("pod.yml").exists());
}

#[test]
fn a_calibration_with_a_zero_focal_length_is_blamed_on_the_file() {
    let rig_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let rig = conformd::stereo::rig::RigFile::load(&rig_path).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let calib = dir.path().join("calibration");
    std::fs::create_dir(&calib).unwrap();
    for pod in rig.pods() {
        std::fs::write(
            calib.join(format!("{}.yml", pod.id)),
            pod.opencv_yaml_of(Some(&rig.name)),
        )
        .unwrap();
    }
    let first = &rig.pods()[0].id;
    let file = calib.join(format!("{first}.yml"));
    let text = std::fs::read_to_string(&file).unwrap();
    // M1's first value is fx
    let m1 = text.find("M1").unwrap();
    let start = m1 + text[m1..].find('[').unwrap() + 1;
    let end = start + text[start..].find(',').unwrap();
    let broken = format!("{} 0.{}", &text[..start], &text[end..]);
    std::fs::write(&file, broken).unwrap();
    let err = match conformd::stereo::rig::Reconstruction::load(&rig_path, Some(&calib)) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a zero focal length was accepted"),
    };
    assert!(
        err.contains(&format!("{first}.yml")) && err.contains("focal length must be positive"),
        "{err}"
    );
    // and through the command line, before any image is read
    refused(
        dir.path(),
        &[
            "reconstruct",
            "no-such-set",
            "--rig",
            rig_path.to_str().unwrap(),
            "--calibration",
            "calibration",
            "--out",
            "scan.ply",
        ],
        &[&format!("{first}.yml"), "focal length"],
    );
    assert!(!dir.path().join("scan.ply").exists());
}

#[test]
fn names_that_would_escape_their_folder_are_refused_before_anything_is_written() {
    // the command's folder inside a folder of its own, so that a write beside it (an id
    // climbing out with `..`) shows too
    let outer = tempfile::tempdir().unwrap();
    let d = outer.path().join("work");
    std::fs::create_dir(&d).unwrap();
    let rig = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml"),
    )
    .unwrap();
    // a pod id that climbs out of --out; two pods of one id (each would overwrite the
    // other's images)
    for (from, to, word) in [("pod1", "../../x", "../../x"), ("pod2", "pod1", "pod1")] {
        let edited = rig.replacen(&format!("id = \"{from}\""), &format!("id = \"{to}\""), 1);
        std::fs::write(d.join("rig.toml"), edited).unwrap();
        refused(
            &d,
            &[
                "simulate",
                "--rig",
                "rig.toml",
                "--subject",
                "pig",
                "--captures",
                "1",
                "--out",
                "sim",
            ],
            &["rig.toml", word],
        );
    }
    std::fs::remove_file(d.join("rig.toml")).unwrap();
    // a station whose camera id climbs out of captures/
    std::fs::write(
        d.join("station.toml"),
        "[station]\nname = \"s1\"\ndata = \"root\"\n[[cameras]]\nid = \"../x\"\npod = \"pod1\"\nside = \"left\"\ndevice = \"/dev/video0\"\n",
    )
    .unwrap();
    refused(&d, &["check", "station.toml"], &["station.toml", "../x"]);
    refused(
        &d,
        &["capture", "--config", "station.toml"],
        &["station.toml", "../x"],
    );
    std::fs::remove_file(d.join("station.toml")).unwrap();
    // a station file that is not there (a manifest naming a file outside its set:
    // tests/pipeline.rs)
    refused(
        &d,
        &[
            "process",
            "no-such-set",
            "--config",
            "no-station.toml",
            "--out",
            "results",
        ],
        &["no-station.toml"],
    );
    let beside: Vec<_> = std::fs::read_dir(outer.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(beside, ["work"], "written beside the command's folder");
}

#[test]
fn simulate_on_a_full_disk_leaves_nothing_behind() {
    // a file-size limit (with SIGXFSZ ignored, writes fail with EFBIG) stands in for a
    // disk that fills up in the middle of the images
    let dir = tempfile::tempdir().unwrap();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let t = Instant::now();
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "trap '' XFSZ; ulimit -f 200; exec '{}' simulate --rig '{}' --subject pig --captures 2 --out sim",
            env!("CARGO_BIN_EXE_conformd"),
            rig.display()
        ))
        .current_dir(dir.path())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "simulate succeeded on a full disk");
    assert!(
        err.contains("File too large") && err.contains(".png"),
        "{err}"
    );
    assert!(
        t.elapsed() < Duration::from_secs(10),
        "took {:?}",
        t.elapsed()
    );
    assert!(
        tree(dir.path()).is_empty(),
        "left behind: {:?}",
        tree(dir.path())
    );
}
