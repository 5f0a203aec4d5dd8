//! Bad input gets a clear error naming the file and what was wrong, never a panic:
//! truncated or malformed meshes, out-of-range indices, NaN coordinates, bad or
//! degenerate landmarks, empty scans, bad options.

use conformd::conform::{ConformError, ConformOptions, conform};
use conformd::mesh::io::{PlyEncoding, ply_bytes, read_obj_bytes, read_off_bytes, read_ply_bytes};
use conformd::mesh::landmarks::{Landmark, LandmarkPos, parse_pp, parse_text};
use conformd::mesh::{Mesh, V3};
use conformd::synth::{icosphere, tessellated_box};

fn err_of<T: std::fmt::Debug, E: std::fmt::Display>(r: Result<T, E>) -> String {
    r.expect_err("should be rejected").to_string()
}

fn tet() -> Mesh {
    Mesh::new(
        vec![
            V3::new(0., 0., 0.),
            V3::new(1., 0., 0.),
            V3::new(0., 1., 0.),
            V3::new(0., 0., 1.),
        ],
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
    )
}

#[test]
fn truncated_binary_ply_names_the_element() {
    let bytes = ply_bytes(&tet(), PlyEncoding::BinaryLittleEndian);
    let e = err_of(read_ply_bytes("scan.ply", &bytes[..bytes.len() - 5]));
    assert!(
        e.contains("scan.ply") && e.contains("face") && e.contains("truncated"),
        "{e}"
    );
    let header_end = bytes.windows(10).position(|w| w == b"end_header").unwrap() + 11;
    let e = err_of(read_ply_bytes("scan.ply", &bytes[..header_end + 30]));
    assert!(
        e.contains("element 'vertex' row 1") && e.contains("truncated"),
        "{e}"
    );
}

#[test]
fn ascii_ply_errors_name_the_line() {
    let ok = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    assert!(read_ply_bytes("a.ply", ok.as_bytes()).is_ok());
    let e = err_of(read_ply_bytes(
        "a.ply",
        ok.replace("1 0 0\n", "1 zero 0\n").as_bytes(),
    ));
    assert!(
        e.contains("line 11") && e.contains("'zero' is not a number"),
        "{e}"
    );
    let e = err_of(read_ply_bytes(
        "a.ply",
        ok.replace("3 0 1 2", "3 0 1 7").as_bytes(),
    ));
    assert!(e.contains("face 0") && e.contains("out of range"), "{e}");
    let e = err_of(read_ply_bytes(
        "a.ply",
        ok.replace("element vertex 3", "element vertex 4")
            .as_bytes(),
    ));
    assert!(e.contains("a.ply"), "wrong count: {e}");
    let e = err_of(read_ply_bytes(
        "a.ply",
        ok.replace("0 1 0\n", "0 nan 0\n").as_bytes(),
    ));
    assert!(e.contains("vertex 2") && e.contains("non-finite"), "{e}");
    let e = err_of(read_ply_bytes(
        "a.ply",
        ok.replace("format ascii 1.0", "format binary_big_endian 1.0")
            .as_bytes(),
    ));
    assert!(
        e.contains("binary_big_endian") && e.contains("line 2"),
        "{e}"
    );
    let e = err_of(read_ply_bytes("a.ply", b"OFF\n"));
    assert!(e.contains("not a PLY file"), "{e}");
    let e = err_of(read_ply_bytes(
        "a.ply",
        ok.replace("end_header\n", "").as_bytes(),
    ));
    assert!(
        e.contains("end_header") || e.contains("unknown header keyword"),
        "{e}"
    );
}

#[test]
fn obj_and_off_errors() {
    let e = err_of(read_obj_bytes(
        "t.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
    ));
    assert!(e.contains("t.obj"), "{e}");
    let e = err_of(read_obj_bytes("t.obj", b"v 0 0 0\nv 1 nan 0\n"));
    assert!(e.contains("line 2") && e.contains("non-finite"), "{e}");
    let e = err_of(read_obj_bytes("t.obj", b"v 0 0\n"));
    assert!(e.contains("line 1") && e.contains("fewer than 3"), "{e}");
    let e = err_of(read_off_bytes("t.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n"));
    assert!(e.contains("t.off") && e.contains("vertex 2"), "{e}");
    let e = err_of(read_off_bytes(
        "t.off",
        b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n",
    ));
    assert!(
        e.contains("line 6") && e.contains("face 0") && e.contains("out of range"),
        "{e}"
    );
    let e = err_of(read_off_bytes("t.off", b"PLY\n"));
    assert!(e.contains("expected 'OFF'"), "{e}");
}

#[test]
fn read_mesh_names_missing_files_and_unknown_formats() {
    let e = err_of(conformd::mesh::read_mesh("/nonexistent/scan.ply".as_ref()));
    assert!(e.contains("/nonexistent/scan.ply"), "{e}");
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("scan.stl");
    std::fs::write(&p, b"solid").unwrap();
    let e = err_of(conformd::mesh::read_mesh(&p));
    assert!(e.contains("unsupported mesh format"), "{e}");
}

#[test]
fn landmark_files_are_checked() {
    let e = err_of(parse_text("l.txt", b"a 1\nb 1 2\n"));
    assert!(e.contains("line 2") && e.contains("found 3 fields"), "{e}");
    let e = err_of(parse_text("l.txt", b"a -1\n"));
    assert!(e.contains("not a vertex index"), "{e}");
    let e = err_of(parse_pp(
        "l.pp",
        b"<PickedPoints><point x=\"1\" y=\"q\" z=\"0\" name=\"a\"/></PickedPoints>",
    ));
    assert!(e.contains("y=\"q\""), "{e}");
    let e = err_of(parse_pp("l.pp", b"<html></html>"));
    assert!(e.contains("not a MeshLab PickedPoints file"), "{e}");
}

fn pairs(template: &Mesh, pts: &[(&str, V3)]) -> (Vec<Landmark>, Vec<Landmark>) {
    let t = pts
        .iter()
        .map(|(n, p)| {
            let v = (0..template.vertices.len())
                .min_by(|&a, &b| {
                    (template.vertices[a] - p)
                        .norm()
                        .total_cmp(&(template.vertices[b] - p).norm())
                })
                .unwrap();
            Landmark {
                name: n.to_string(),
                pos: LandmarkPos::Vertex(v as u32),
            }
        })
        .collect();
    let s = pts
        .iter()
        .map(|(n, p)| Landmark {
            name: n.to_string(),
            pos: LandmarkPos::Point(p * 2.0),
        })
        .collect();
    (t, s)
}

#[test]
fn degenerate_landmarks_are_rejected_with_a_reason() {
    let sphere = icosphere(2);
    let scan = tessellated_box(V3::new(2., 2., 2.), 6);
    let run = |t: &[Landmark], s: &[Landmark]| {
        conform(
            &sphere,
            &scan,
            Some((t, s)),
            &ConformOptions::default(),
            &mut |_| {},
        )
    };
    // too few
    let (t, s) = pairs(&sphere, &[("a", V3::x()), ("b", V3::y()), ("c", V3::z())]);
    let e = err_of(run(&t, &s));
    assert!(
        e.contains("3 landmark pairs") && e.contains("at least 4"),
        "{e}"
    );
    // all in one plane
    let (t, s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", -V3::x()),
            ("d", -V3::y()),
        ],
    );
    let e = err_of(run(&t, &s));
    assert!(e.contains("lie in one plane"), "{e}");
    // two at the same place
    let (t, mut s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", V3::z()),
            ("d", -V3::x()),
            ("e", -V3::z()),
        ],
    );
    s[4].pos = s[3].pos;
    let e = err_of(run(&t, &s));
    assert!(
        e.contains("'d' and 'e'") && e.contains("same place on the scan"),
        "{e}"
    );
    // NaN on the scan
    let (t, mut s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", V3::z()),
            ("d", -V3::x()),
        ],
    );
    s[2].pos = LandmarkPos::Point(V3::new(f64::NAN, 0., 0.));
    let e = err_of(run(&t, &s));
    assert!(e.contains("'c'") && e.contains("non-finite"), "{e}");
    // vertex index out of range
    let (mut t, s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", V3::z()),
            ("d", -V3::x()),
        ],
    );
    t[0].pos = LandmarkPos::Vertex(1_000_000);
    let e = err_of(run(&t, &s));
    assert!(e.contains("'a'") && e.contains("vertex 1000000"), "{e}");
    // unpaired names leave too few pairs
    let (t, mut s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", V3::z()),
            ("d", -V3::x()),
        ],
    );
    s.remove(0);
    assert!(matches!(run(&t, &s), Err(ConformError::Rbf(_))));
    // a scan landmark the template does not have is named, not dropped
    let (t, mut s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", V3::z()),
            ("d", -V3::x()),
        ],
    );
    s[0].name = "other".into();
    let e = err_of(run(&t, &s));
    assert!(
        e.contains("'other'") && e.contains("not among the template's"),
        "{e}"
    );
}

#[test]
fn nearly_coplanar_landmarks_are_regularised_not_blown_up() {
    let sphere = icosphere(3);
    let scan = tessellated_box(V3::new(2., 2., 2.), 8);
    // the scan's five landmarks all but lie in one plane: the fifth is 1% of their
    // spread above it
    let (t, mut s) = pairs(
        &sphere,
        &[
            ("a", V3::x()),
            ("b", V3::y()),
            ("c", -V3::x()),
            ("d", -V3::y()),
            ("e", V3::z()),
        ],
    );
    s[4].pos = LandmarkPos::Point(V3::new(0.3, 0.3, 0.02));
    let r = conform(
        &sphere,
        &scan,
        Some((&t, &s)),
        &ConformOptions::default(),
        &mut |_| {},
    )
    .expect("accepted");
    assert!(
        r.mesh
            .vertices
            .iter()
            .all(|v| v.iter().all(|c| c.is_finite()))
    );
    let diag = r.mesh.diagonal();
    assert!(
        diag < 3.0 * scan.diagonal(),
        "the mapping stays bounded: diagonal {diag}"
    );
}

#[test]
fn empty_or_tiny_scans_and_bad_templates() {
    let sphere = icosphere(2);
    let e = err_of(conform(
        &sphere,
        &Mesh::default(),
        None,
        &ConformOptions::default(),
        &mut |_| {},
    ));
    assert!(e.contains("scan") && e.contains("empty"), "{e}");
    let few = Mesh::new(vec![V3::zeros(); 5], vec![]);
    let e = err_of(conform(
        &sphere,
        &few,
        None,
        &ConformOptions::default(),
        &mut |_| {},
    ));
    assert!(e.contains("too few points (5)"), "{e}");
    let cloud = Mesh::new(sphere.vertices.clone(), vec![]);
    let e = err_of(conform(
        &cloud,
        &sphere,
        None,
        &ConformOptions::default(),
        &mut |_| {},
    ));
    assert!(e.contains("template") && e.contains("no triangles"), "{e}");
    let mut nan = sphere.clone();
    nan.vertices[7].y = f64::NAN;
    let e = err_of(conform(
        &nan,
        &sphere,
        None,
        &ConformOptions::default(),
        &mut |_| {},
    ));
    assert!(e.contains("template") && e.contains("vertex 7"), "{e}");
    let mut bad = sphere.clone();
    bad.triangles[3] = [0, 1, 99_999];
    let e = err_of(conform(
        &bad,
        &sphere,
        None,
        &ConformOptions::default(),
        &mut |_| {},
    ));
    assert!(
        e.contains("triangle 3") && e.contains("out of range"),
        "{e}"
    );
}

#[test]
fn bad_options_are_named() {
    let sphere = icosphere(1);
    let o = ConformOptions {
        max_distance: -1.0,
        ..Default::default()
    };
    let e = err_of(conform(&sphere, &sphere, None, &o, &mut |_| {}));
    assert!(e.contains("max_distance") && e.contains("-1"), "{e}");
    let mut o = ConformOptions::default();
    o.stiffness.insert("ears".into(), 3.0);
    let e = err_of(conform(&sphere, &sphere, None, &o, &mut |_| {}));
    assert!(e.contains("group 'ears'"), "{e}");
    // a front hint means nothing without the other half, nor with no room to face
    let mut o = ConformOptions::default();
    o.align.scan_front = Some([1.0, 0.0, 0.0]);
    let e = err_of(conform(&sphere, &sphere, None, &o, &mut |_| {}));
    assert!(
        e.contains("template_front") && e.contains("go together"),
        "{e}"
    );
    o.align.template_front = Some([f64::NAN, 0.0, 0.0]);
    let e = err_of(conform(&sphere, &sphere, None, &o, &mut |_| {}));
    assert!(
        e.contains("align.template_front") && e.contains("finite"),
        "{e}"
    );
    o.align.template_front = Some([1.0, 0.0, 0.0]);
    for bad in [0.0, 181.0, f64::NAN] {
        o.align.front_within_deg = bad;
        let e = err_of(conform(&sphere, &sphere, None, &o, &mut |_| {}));
        assert!(e.contains("front_within_deg"), "{bad}: {e}");
    }
}
