//! Generic templates: one connected, watertight, manifold mesh with no degenerate
//! triangles from 1,500 to 50,000 vertices; every landmark and group present; posing and
//! reshaping keep the vertex order.

use conformd::mesh::landmarks::LandmarkPos;
use conformd::mesh::topology;
use conformd::template::{self as templates, Kind};
use std::collections::BTreeMap;

fn check(kind: Kind, n: usize) {
    let fig = templates::build(kind, n);
    let m = &fig.mesh;
    let r = topology::report(m);
    assert_eq!(r.components, 1, "{kind:?} {n}: {r:?}");
    assert!(
        r.watertight && r.non_manifold_vertices == 0 && r.degenerate_triangles == 0,
        "{kind:?} {n}: {r:?}"
    );
    assert!(
        (m.vertices.len() as f64 - n as f64).abs() < 0.15 * n as f64,
        "{kind:?}: {} vertices for {n}",
        m.vertices.len()
    );
    // no sliver: the smallest angle of any triangle
    let min_angle = (0..m.triangles.len())
        .map(|t| {
            let [a, b, c] = m.corners(t);
            let ang = |o: conformd::mesh::V3, p: conformd::mesh::V3, q: conformd::mesh::V3| {
                (p - o).angle(&(q - o))
            };
            ang(a, b, c)
                .min(ang(b, c, a))
                .min(ang(c, a, b))
                .to_degrees()
        })
        .fold(180.0, f64::min);
    assert!(
        min_angle > 3.0,
        "{kind:?} {n}: smallest angle {min_angle:.2} degrees"
    );
    let lms = fig.landmarks();
    let (want_lms, want_groups): (usize, &[&str]) = match kind {
        Kind::Pig => (
            12,
            &["torso", "head", "snout", "ears", "legs", "hooves", "tail"],
        ),
        Kind::Body => (20, &["torso", "head", "arms", "hands", "legs", "feet"]),
    };
    assert!(lms.len() >= want_lms, "{kind:?}: {} landmarks", lms.len());
    let mut at: Vec<u32> = lms
        .iter()
        .map(|l| match l.pos {
            LandmarkPos::Vertex(v) => v,
            _ => unreachable!(),
        })
        .collect();
    at.sort_unstable();
    at.dedup();
    assert_eq!(
        at.len(),
        lms.len(),
        "{kind:?}: every landmark on its own vertex"
    );
    for g in want_groups {
        assert!(
            m.groups.get(*g).is_some_and(|v| !v.is_empty()),
            "{kind:?}: group {g}"
        );
    }
    eprintln!(
        "{kind:?} {n}: {} vertices, smallest angle {min_angle:.1} deg, {} landmarks, groups {:?}",
        m.vertices.len(),
        lms.len(),
        m.groups.keys().collect::<Vec<_>>()
    );
}

#[test]
fn templates_at_5000() {
    check(Kind::Pig, 5000);
    check(Kind::Body, 5000);
}

/// Below 6,000 vertices a template is decimated from a finer one: still one piece (at
/// 2,000 the pig was 3 pieces and the body 4, at 4,000 the body 2).
#[test]
fn small_templates_are_one_piece() {
    for n in [1500, 2000, 3000, 4000] {
        check(Kind::Pig, n);
        check(Kind::Body, n);
    }
}

#[test]
fn templates_at_50000() {
    check(Kind::Pig, 50_000);
    check(Kind::Body, 50_000);
}

#[test]
fn posing_and_reshaping_keep_the_vertex_order() {
    let fig = templates::build(Kind::Pig, 3000);
    let params = templates::parse_parameters(
        "swing=12,nod=-8,twist=5",
        &["swing", "nod", "twist"],
        "pose",
    )
    .unwrap();
    let shape = templates::parse_parameters("length=1.1,girth=0.95", &["length", "girth"], "shape")
        .unwrap();
    let m = templates::subject(
        &fig,
        Kind::Pig,
        &shape,
        &templates::pose(Kind::Pig, &params),
    )
    .unwrap();
    assert_eq!(m.triangles, fig.mesh.triangles);
    assert!(topology::report(&m).watertight);
    let moved = m
        .vertices
        .iter()
        .zip(&fig.mesh.vertices)
        .filter(|(a, b)| (*a - *b).norm() > 1e-6)
        .count();
    assert!(moved > m.vertices.len() / 2);
    // a longer pig is longer
    let (lo, hi) = m.bounding_box().unwrap();
    let (lo0, hi0) = fig.mesh.bounding_box().unwrap();
    assert!((hi.x - lo.x) > 1.05 * (hi0.x - lo0.x));
    let e = templates::parse_parameters("swing=x", &["swing"], "pose").unwrap_err();
    assert!(
        matches!(&e, templates::TemplateError::NotANumber { value, .. } if value == "x"),
        "{e:?}"
    );
    assert!(e.to_string().contains("'x' is not a number"), "{e}");
    let e = templates::parse_parameters("wag=3", &["swing"], "pose").unwrap_err();
    assert!(
        e.to_string().contains("unknown pose parameter 'wag'"),
        "{e}"
    );
    assert!(
        templates::subject(
            &fig,
            Kind::Pig,
            &BTreeMap::from([("height".into(), 1.1)]),
            &Default::default()
        )
        .is_err()
    );
}
