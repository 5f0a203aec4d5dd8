//! Hostile and careless input (the hostile-input issue's cases fixed so far): each gets
//! one clear sentence and a failing exit, never a panic, a hang, or a "success" with
//! garbage; a failed command leaves no output behind.
use crate::common;
use common::{CHILD_LIMIT, Deadline};

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
/// without a panic, and created no file or folder in `dir`. A child that blocks (a
/// reader opening a FIFO) is killed after 30 s and fails the test.
fn refused(dir: &Path, args: &[&str], words: &[&str]) -> String {
    let before = tree(dir);
    let t = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_conformd"))
        .args(args)
        .current_dir(dir)
        .output_within(Duration::from_secs(30));
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

/// Why the rig's calibrations in `calib` were refused (a panic naming `what` if they
/// were not).
fn calibration_refused(rig_path: &Path, calib: &Path, what: &str) -> String {
    match conformd::stereo::rig::Reconstruction::load(rig_path, Some(calib)) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("{what} was accepted"),
    }
}

/// `reconstruct` with the rig's calibrations in `dir/calibration`, refused with `words`
/// before any image is read.
fn reconstruct_refused(dir: &Path, rig_path: &Path, words: &[&str]) {
    refused(
        dir,
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
        words,
    );
}

/// The example rig's file, the rig, a temporary folder and its `calibration/` holding
/// every pod's calibration as the rig file gives it.
fn example_calibrations() -> (
    std::path::PathBuf,
    conformd::stereo::rig::RigFile,
    tempfile::TempDir,
    std::path::PathBuf,
) {
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
    (rig_path, rig, dir, calib)
}

#[test]
fn a_calibration_with_a_zero_focal_length_is_blamed_on_the_file() {
    let (rig_path, rig, dir, calib) = example_calibrations();
    let first = &rig.pods()[0].id;
    let file = calib.join(format!("{first}.yml"));
    let text = std::fs::read_to_string(&file).unwrap();
    // M1's first value is fx
    let m1 = text.find("M1").unwrap();
    let start = m1 + text[m1..].find('[').unwrap() + 1;
    let end = start + text[start..].find(',').unwrap();
    let broken = format!("{} 0.{}", &text[..start], &text[end..]);
    std::fs::write(&file, broken).unwrap();
    let err = calibration_refused(&rig_path, &calib, "a zero focal length");
    assert!(
        err.contains(&format!("{first}.yml")) && err.contains("focal length must be positive"),
        "{err}"
    );
    // and through the command line, before any image is read
    reconstruct_refused(
        dir.path(),
        &rig_path,
        &[&format!("{first}.yml"), "focal length"],
    );
    assert!(!dir.path().join("scan.ply").exists());
}

/// A calibration file of 100 KB of nested brackets (or nested by indentation) overflowed
/// OpenCV's recursive parser's stack and aborted the process (exit 134) in `check`,
/// `reconstruct` and the daemon's start: now it is refused before OpenCV sees it, naming
/// the file and the line.
#[test]
fn a_calibration_nested_too_deep_for_the_parser_is_refused_before_it() {
    let (rig_path, rig, dir, calib) = example_calibrations();
    let second = &rig.pods()[1].id;
    let file = calib.join(format!("{second}.yml"));
    let good = std::fs::read_to_string(&file).unwrap();
    let nested = format!(
        "%YAML:1.0\n---\nM1: {}{}\n",
        "[".repeat(50_000),
        "]".repeat(50_000)
    );
    let indented: String = std::iter::once("%YAML:1.0\n---\n".to_string())
        .chain((0..200).map(|i| format!("{}a{i}:\n", "  ".repeat(i))))
        .collect();
    for (what, text) in [("a bracket", nested), ("indentation", indented)] {
        std::fs::write(&file, &text).unwrap();
        let err = calibration_refused(&rig_path, &calib, what);
        assert!(
            err.contains(&format!("{second}.yml")) && err.contains(what) && err.contains("line"),
            "{err}"
        );
        reconstruct_refused(
            dir.path(),
            &rig_path,
            &[&format!("{second}.yml"), "nests deeper"],
        );
    }
    // what OpenCV's parser says of a file, in an operator's words, not its source lines
    for (text, words) in [
        ("%YAML:1.0\n---\nM1: [1, 2\n", "at line 3"),
        (
            "%YAML:1.0\n---\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1, 2 ]\n",
            "does not hold rows x cols values",
        ),
    ] {
        std::fs::write(&file, text).unwrap();
        let err = calibration_refused(&rig_path, &calib, text);
        assert!(
            err.contains(&format!("{second}.yml"))
                && err.contains(words)
                && !err.contains("OpenCV(")
                && !err.contains(".cpp"),
            "{err}"
        );
    }
    // a pipe where the calibration should be: named as what it is, not as missing
    std::fs::remove_file(&file).unwrap();
    mkfifo(&file);
    let err = calibration_refused(&rig_path, &calib, "a pipe");
    assert!(
        err.contains(&format!("{second}.yml"))
            && err.contains("named pipe")
            && !err.contains("no calibration"),
        "{err}"
    );
    std::fs::remove_file(&file).unwrap();
    // the good file still reads (from memory, as checked)
    std::fs::write(&file, good).unwrap();
    conformd::stereo::rig::Reconstruction::load(&rig_path, Some(&calib)).unwrap();
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
        .output_within(CHILD_LIMIT);
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

/// A noise image and the same shifted 4 pixels: a pair with texture and a known match.
fn textured_pair(dir: &Path) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let left = image::GrayImage::from_fn(96, 64, |_, _| image::Luma([rng.random::<u8>()]));
    let right = image::GrayImage::from_fn(96, 64, |x, y| *left.get_pixel((x + 4).min(95), y));
    left.save(dir.join("l.png")).unwrap();
    right.save(dir.join("r.png")).unwrap();
}

fn mkfifo(p: &Path) {
    assert!(Command::new("mkfifo").arg(p).status().unwrap().success());
}

#[test]
fn pipes_and_devices_where_a_file_belongs_are_refused_before_a_byte_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    conformd::mesh::write_mesh(&d.join("s.ply"), &icosphere(2)).unwrap();
    textured_pair(d);
    mkfifo(&d.join("pipe.ply"));
    mkfifo(&d.join("pipe.png"));
    let pipe = ["not a regular file (a named pipe)"];
    let device = ["/dev/zero", "not a regular file (a device)"];
    // a FIFO would block the reader until a writer came
    refused(d, &["info", "pipe.ply"], &pipe);
    refused(
        d,
        &["disparity", "pipe.png", "r.png", "--out", "d.pfm"],
        &pipe,
    );
    refused(
        d,
        &["render", "pipe.ply", "--out", "p.png"],
        &["pipe.ply", pipe[0]],
    );
    // /dev/zero would be read until memory runs out, by every reader
    let conform = |flag: &'static str| {
        // scan landmarks pair with the built-in pig's own
        let template = if flag == "--scan-landmarks" {
            "pig"
        } else {
            "s.ply"
        };
        vec![
            "conform",
            "--template",
            template,
            "--scan",
            "s.ply",
            flag,
            "/dev/zero",
            "--out",
            "c.ply",
        ]
    };
    for flag in [
        "--template-landmarks",
        "--scan-landmarks",
        "--template-groups",
        "--config",
    ] {
        let args = conform(flag);
        refused(d, &args, &device);
    }
    // a built-in template's groups are its own: a groups file is not ignored in silence
    refused(
        d,
        &[
            "conform",
            "--template",
            "pig",
            "--scan",
            "s.ply",
            "--template-groups",
            "g.txt",
            "--out",
            "c.ply",
        ],
        &["brings its own groups"],
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
            "--truth",
            "/dev/zero",
        ],
        &device,
    );
    refused(
        d,
        &["model", "score", "--model", "/dev/zero", "s.ply"],
        &device,
    );
}

#[test]
fn a_chessboard_that_cannot_be_in_the_images_is_refused_before_opencv_allocates_it() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let views = d.join("views");
    std::fs::create_dir(&views).unwrap();
    let grey = image::GrayImage::from_pixel(320, 240, image::Luma([90]));
    for k in 0..4 {
        grey.save(views.join(format!("left{k:02}.png"))).unwrap();
        grey.save(views.join(format!("right{k:02}.png"))).unwrap();
    }
    refused(
        d,
        &[
            "calibrate",
            "--images",
            "views",
            "--board",
            "100000x100000",
            "--square",
            "1",
            "--out",
            "pod.yml",
        ],
        &["100000x100000", "cannot be found in 320x240 images"],
    );
    refused(
        d,
        &[
            "calibrate",
            "--images",
            "views",
            "--board",
            "9x6",
            "--square",
            "0",
            "--out",
            "pod.yml",
        ],
        &["square size must be a positive length"],
    );
}

#[test]
fn figures_computed_from_nothing_are_refused_not_printed() {
    use conformd::measure::Definitions;
    use conformd::stereo::truth::{parse_truth, score};
    // a mesh beyond any real coordinate: not rendered blank, not described with nulls
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut far = icosphere(1);
    for v in &mut far.vertices {
        *v *= 1e300;
    }
    conformd::mesh::write_mesh(&d.join("far.ply"), &far).unwrap();
    let words = ["far.ply", "lies beyond 1e9 from the origin"];
    refused(d, &["render", "far.ply", "--out", "far.png"], &words);
    refused(d, &["info", "far.ply"], &words);

    // a girth plane through the sphere's top vertex, square to the axis through it,
    // touches it at one point: no girth of 0 (positions name their nearest vertices)
    let b = icosphere(2);
    let top = b.vertices[0];
    let at = |p: V3| format!("[{}, {}, {}]", p.x, p.y, p.z);
    let measure = |text: &str| {
        Definitions::parse(text, "defs.toml")
            .unwrap()
            .resolve(&b, &[])
            .unwrap()
            .measure(&b)
    };
    let axis = format!("[{}, {}]", at(-top), at(top));
    let e = measure(&format!(
        "[[measurement]]\nname = \"g\"\nkind = \"girth\"\nat = {}\naxis = {axis}\n",
        at(top)
    ))
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("measurement 'g'") && e.contains("only touches the mesh"),
        "{e}"
    );
    // a width whose direction across runs along its axis
    let e = measure(&format!(
        "[[measurement]]\nname = \"w\"\nkind = \"width\"\nat = [0.0, 0.0, 0.0]\naxis = {axis}\nacross = {axis}\n"
    ))
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("measurement 'w'") && e.contains("along the axis"),
        "{e}"
    );
    // across the section it measures the sphere's breadth
    let side = top.cross(&V3::new(0.3, 0.5, 0.7)).normalize();
    let ok = measure(&format!(
        "[[measurement]]\nname = \"w\"\nkind = \"width\"\nat = {}\naxis = {axis}\nacross = [{}, {}]\n",
        at(side),
        at(-side),
        at(side)
    ))
    .unwrap();
    assert!((ok[0].value - 2.0).abs() < 0.1, "{}", ok[0].value);

    // a PFM whose scale gives no byte order
    for scale in ["nan", "0"] {
        let mut pfm = format!("Pf\n2 2\n{scale}\n").into_bytes();
        pfm.extend(std::iter::repeat_n(0u8, 16));
        let e = parse_truth(Path::new("t.pfm"), &pfm, None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("t.pfm") && e.contains("PFM scale"), "{e}");
    }
    // a truth with no known pixel, or none from the first scored column on
    let disparity = conformd::stereo::disparity::Disparity {
        width: 4,
        height: 2,
        values: vec![3.0; 8],
    };
    let mut unknown = b"Pf\n4 2\n-1\n".to_vec();
    for _ in 0..8 {
        unknown.extend(f32::INFINITY.to_le_bytes());
    }
    let t = parse_truth(Path::new("t.pfm"), &unknown, None).unwrap();
    let e = score(&disparity, &t, 0).unwrap_err().to_string();
    assert!(e.contains("no known pixels"), "{e}");
    let mut known = b"Pf\n4 2\n-1\n".to_vec();
    for _ in 0..8 {
        known.extend(3.0f32.to_le_bytes());
    }
    let t = parse_truth(Path::new("t.pfm"), &known, None).unwrap();
    assert_eq!(score(&disparity, &t, 0).unwrap().bad1, 0.0);
    let e = score(&disparity, &t, 9).unwrap_err().to_string();
    assert!(
        e.contains("from column 9 on") && e.contains("4 wide"),
        "{e}"
    );
}

#[test]
fn quiet_wrong_answers_are_refused() {
    // a scan of points on one line has no surface to fit
    let sphere = icosphere(2);
    let line = Mesh::new(
        (0..200)
            .map(|i| V3::new(i as f64 * 0.01, 0.0, 0.0))
            .collect(),
        vec![],
    );
    let e = conform_err(&sphere, &line, &ConformOptions::default());
    assert!(e.contains("on one line"), "{e}");
    // a scan landmark the template lacks is a misspelling, not a point to drop
    use conformd::mesh::{Landmark, LandmarkPos};
    let tl = vec![
        Landmark {
            name: "snout".into(),
            pos: LandmarkPos::Vertex(0),
        },
        Landmark {
            name: "tail".into(),
            pos: LandmarkPos::Vertex(5),
        },
    ];
    let sl = vec![Landmark {
        name: "snuot".into(),
        pos: LandmarkPos::Point(sphere.vertices[0]),
    }];
    let e = match conform(
        &sphere,
        &sphere,
        Some((&tl, &sl)),
        &ConformOptions::default(),
        &mut |_| {},
    ) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("conformed with an unknown landmark"),
    };
    assert!(e.contains("'snuot'") && e.contains("snout, tail"), "{e}");
    // a simulation at NaN noise
    let dir = tempfile::tempdir().unwrap();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    refused(
        dir.path(),
        &[
            "simulate",
            "--rig",
            rig.to_str().unwrap(),
            "--subject",
            "pig",
            "--noise",
            "nan",
            "--out",
            "sim",
        ],
        &["--noise NaN", "0 to 100"],
    );
}

#[test]
fn results_are_never_written_into_what_they_are_made_from() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let results = d.join("results");
    std::fs::create_dir_all(results.join("c1")).unwrap();
    std::fs::write(results.join("c1/report.json"), "{\"capture\": \"c1\"}").unwrap();
    refused(
        d,
        &[
            "export",
            "--results",
            "results",
            "--out",
            "results/c1/report.json",
        ],
        &["lies inside the results folder"],
    );
    assert_eq!(
        std::fs::read_to_string(results.join("c1/report.json")).unwrap(),
        "{\"capture\": \"c1\"}"
    );
    std::fs::create_dir(d.join("set")).unwrap();
    refused(
        d,
        &[
            "process",
            "set",
            "--config",
            "station.toml",
            "--out",
            "set/out",
        ],
        &["lies inside the capture set"],
    );
    // a corrupt report is named, not skipped in silence; a formula is not run
    std::fs::create_dir_all(results.join("c2")).unwrap();
    std::fs::write(results.join("c2/report.json"), "{trunc").unwrap();
    std::fs::create_dir_all(results.join("c3")).unwrap();
    std::fs::write(
        results.join("c3/report.json"),
        "{\"capture\": \"c3\", \"subject\": \"=HYPERLINK(1)\"}",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_conformd"))
        .args(["export", "--results", "results"])
        .current_dir(d)
        .output_within(CHILD_LIMIT);
    let (csv, err) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("c2/report.json") && err.contains("not JSON"),
        "{err}"
    );
    assert_eq!(csv.lines().count(), 3, "{csv}");
    assert!(csv.contains("c3,'=HYPERLINK(1)"), "{csv}");
}

#[test]
fn every_folder_entry_the_daemon_will_not_take_is_named_with_its_reason() {
    use conformd::daemon::sets::{SETTLE, scan_folder};
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let set = |name: &str| {
        let p = root.join(name);
        std::fs::create_dir_all(&p).unwrap();
        std::fs::write(
            p.join("manifest.json"),
            r#"{"cameras": [{"file": "a.png"}, {"file": "b.png"}]}"#,
        )
        .unwrap();
        std::fs::write(p.join("a.png"), "a").unwrap();
        std::fs::write(p.join("b.png"), "b").unwrap();
        p
    };
    set("good");
    set("bad\nname");
    set("ünïcode");
    set(&"x".repeat(200));
    set(".hidden");
    set(".young"); // a writer's hidden name while it writes: passed over in silence
    set(".ours.partial"); // the daemon's own, however old
    for old in [".hidden", ".ours.partial"] {
        let p = root.join(old);
        assert!(
            Command::new("touch")
                .args(["-d", "1 hour ago"])
                .arg(&p)
                .status()
                .unwrap()
                .success()
        );
    }
    std::os::unix::fs::symlink(root.join("good"), root.join("linked")).unwrap();
    std::fs::write(root.join("stray.txt"), "a file").unwrap();
    let pipe = set("piped");
    std::fs::remove_file(pipe.join("manifest.json")).unwrap();
    mkfifo(&pipe.join("manifest.json"));
    let linked_manifest = set("linkedmanifest");
    std::fs::remove_file(linked_manifest.join("manifest.json")).unwrap();
    std::os::unix::fs::symlink(
        root.join("good/manifest.json"),
        linked_manifest.join("manifest.json"),
    )
    .unwrap();
    let t = Instant::now();
    let found = scan_folder(root, None, |_| false, |_| false);
    assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
    let ids: Vec<&str> = found.sets.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(ids, ["good"]);
    let why = |name: &str| {
        found
            .refused
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, w)| w.clone())
            .unwrap_or_else(|| panic!("{name} not reported: {:?}", found.refused))
    };
    assert!(why("bad\\nname").contains("not a plain name"));
    assert!(why("ünïcode").contains("not a plain name"));
    assert!(why(&"x".repeat(200)).contains("1 to 128 characters"));
    assert!(why(".hidden").contains("not starting with '.'"));
    assert!(why("linked").contains("symbolic link"));
    assert!(why("stray.txt").contains("not a capture set folder"));
    assert!(why("piped").contains("manifest.json is a named pipe"));
    assert!(why("linkedmanifest").contains("manifest.json is a symbolic link"));
    assert_eq!(found.refused.len(), 8, "{:?}", found.refused);
    // a set still being written (its files changed within the settle time) waits
    let fresh = tempfile::tempdir().unwrap();
    let p = fresh.path().join("growing");
    std::fs::create_dir(&p).unwrap();
    std::fs::write(
        p.join("manifest.json"),
        r#"{"cameras": [{"file": "a.png"}]}"#,
    )
    .unwrap();
    std::fs::write(p.join("a.png"), "part").unwrap();
    let waiting = scan_folder(fresh.path(), Some(SETTLE), |_| false, |_| false);
    assert!(waiting.sets.is_empty() && waiting.settling, "{waiting:?}");
    std::thread::sleep(SETTLE + Duration::from_millis(200));
    let settled = scan_folder(fresh.path(), Some(SETTLE), |_| false, |_| false);
    assert_eq!(settled.sets.len(), 1, "{settled:?}");
    assert!(!settled.settling);

    // a set written elsewhere and renamed in (the watcher saw the rename) is taken at
    // once; one written into after its rename still waits
    let drop = tempfile::tempdir().unwrap();
    let write_set = |dir: &Path| {
        std::fs::create_dir(dir).unwrap();
        std::fs::write(
            dir.join("manifest.json"),
            r#"{"cameras": [{"file": "a.png"}]}"#,
        )
        .unwrap();
        std::fs::write(dir.join("a.png"), "whole").unwrap();
    };
    let staging = drop.path().join(".whole.copying");
    write_set(&staging);
    // past the file system's clock tick: the rename is later than every write
    std::thread::sleep(Duration::from_millis(30));
    std::fs::rename(&staging, drop.path().join("whole")).unwrap();
    let now = scan_folder(drop.path(), Some(SETTLE), |n| n == "whole", |_| false);
    assert_eq!(now.sets.len(), 1, "renamed in whole: taken at once {now:?}");
    let unseen = scan_folder(drop.path(), Some(SETTLE), |_| false, |_| false);
    assert!(
        unseen.sets.is_empty() && unseen.settling,
        "no rename seen: it settles {unseen:?}"
    );
    let staging = drop.path().join(".late.copying");
    write_set(&staging);
    std::thread::sleep(Duration::from_millis(30));
    std::fs::rename(&staging, drop.path().join("late")).unwrap();
    std::thread::sleep(Duration::from_millis(30));
    std::fs::write(drop.path().join("late/a.png"), "written after the rename").unwrap();
    let late = scan_folder(drop.path(), Some(SETTLE), |_| true, |n| n == "whole");
    assert!(
        late.sets.is_empty() && late.settling,
        "written into after its rename: it settles {late:?}"
    );
}

#[test]
fn messages_say_what_to_write_and_pages_agree_with_their_pictures() {
    // a vertex index of -1: what a point may be, not serde's enum name
    let e = conformd::measure::Definitions::parse(
        "[[measurement]]\nname = \"h\"\nkind = \"height\"\npoint = -1\n",
        "defs.toml",
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("a point is a vertex index (0 or more)") && !e.contains("untagged"),
        "{e}"
    );
    // one id weighed twice with two weights
    let dir = tempfile::tempdir().unwrap();
    let w = dir.path().join("weights.csv");
    std::fs::write(&w, "id,kg\npig-1,80\npig-2,90\npig-1,80\npig-1,95\n").unwrap();
    let e = conformd::commands::read_weights(&w)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("line 5") && e.contains("95 kg here and 80 kg on line 2"),
        "{e}"
    );
    std::fs::write(&w, "id,kg\npig-1,80\npig-1,80\n").unwrap();
    assert_eq!(conformd::commands::read_weights(&w).unwrap().len(), 1);
}
