//! Mesh files round trip through the writers and readers, on disk and atomically.

use conformd::mesh::V3;
use conformd::mesh::io::{PlyEncoding, ply_bytes, read_ply_bytes};
use conformd::mesh::{read_mesh, topology, write_mesh};
use conformd::synth::{icosphere, scanner, tessellated_box};

#[test]
fn meshes_and_point_clouds_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let sphere = icosphere(3);
    for name in ["s.ply", "s.obj"] {
        let p = dir.path().join(name);
        write_mesh(&p, &sphere).unwrap();
        let back = read_mesh(&p).unwrap();
        assert_eq!(back.triangles, sphere.triangles, "{name}");
        assert!(
            back.vertices
                .iter()
                .zip(&sphere.vertices)
                .all(|(a, b)| (a - b).norm() < 1e-12),
            "{name}"
        );
        assert!(topology::report(&back).watertight, "{name}");
    }
    let cloud = scanner::sample_points(&sphere, &vec![true; sphere.triangles.len()], 500, 0.001, 3);
    for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian] {
        let back = read_ply_bytes("c.ply", &ply_bytes(&cloud, enc)).unwrap();
        assert!(back.is_point_cloud());
        assert_eq!(back.vertices.len(), 500);
        let n = back.normals.unwrap();
        assert!(
            n.iter()
                .zip(cloud.normals.as_ref().unwrap())
                .all(|(a, b)| (a - b).norm() < 1e-9)
        );
    }
}

#[test]
fn obj_keeps_triangle_order_and_groups() {
    let fig = conformd::template::build(conformd::template::Kind::Pig, 2000);
    let back = conformd::mesh::io::read_obj_bytes(
        "t.obj",
        conformd::mesh::io::obj_bytes(&fig.mesh).as_bytes(),
    )
    .unwrap();
    assert_eq!(
        back.triangles, fig.mesh.triangles,
        "triangle order is part of the template"
    );
    assert_eq!(back.vertices, fig.mesh.vertices);
    for (g, vs) in &fig.mesh.groups {
        let got = &back.groups[g];
        assert!(
            vs.iter().filter(|v| got.binary_search(v).is_ok()).count() * 10 >= vs.len() * 9,
            "group {g} kept"
        );
    }
}

#[test]
fn synthetic_solids_are_watertight() {
    assert!(topology::report(&icosphere(4)).watertight);
    let b = tessellated_box(V3::new(2., 1., 0.5), 7);
    let r = topology::report(&b);
    assert!(r.watertight && r.components == 1, "{r:?}");
    assert!((b.area() - 2.0 * (2.0 + 1.0 + 0.5)).abs() < 1e-9);
}
