//! The conformation cases that tests, benchmarks and the demo share: the paper's
//! sphere-to-cube and sphere-to-box-with-missing-data, and an articulated figure posed,
//! deformed and scanned from a few viewpoints, with ground-truth correspondence.

use super::{icosphere, scanner, tessellated_box};
use crate::mesh::keep_triangles;
use crate::mesh::landmarks::{Landmark, LandmarkPos};
use crate::mesh::{Mesh, V3};
use crate::template::figure::{self, Pose};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// A template, a scan, landmarks on both, and what is known of the truth.
pub struct Case {
    pub template: Mesh,
    pub scan: Mesh,
    pub template_landmarks: Vec<Landmark>,
    pub scan_landmarks: Vec<Landmark>,
    /// #V true positions of the template's vertices on the scanned subject, when known
    pub truth: Option<Vec<V3>>,
    /// #V flags: the vertex's true place was not seen by the scanner (in a hole)
    pub in_hole: Vec<bool>,
}

fn nearest(v: &[V3], p: &V3) -> u32 {
    (0..v.len())
        .min_by(|&a, &b| (v[a] - p).norm().total_cmp(&(v[b] - p).norm()))
        .unwrap_or(0) as u32
}

fn sphere_landmarks(sphere: &Mesh, dirs: &[(String, V3)]) -> Vec<Landmark> {
    dirs.iter()
        .map(|(n, d)| Landmark {
            name: n.clone(),
            pos: LandmarkPos::Vertex(nearest(&sphere.vertices, &d.normalize())),
        })
        .collect()
}

/// The paper's first test: a unit sphere (icosphere of `level`) onto a cube of edge 2
/// (a closed mesh), 8 corner landmarks.
pub fn sphere_to_cube(level: u32) -> Case {
    let sphere = icosphere(level);
    let cube = tessellated_box(V3::new(2., 2., 2.), 24);
    let mut dirs = Vec::new();
    for (i, c) in [
        [-1., -1., -1.],
        [1., -1., -1.],
        [-1., 1., -1.],
        [1., 1., -1.],
        [-1., -1., 1.],
        [1., -1., 1.],
        [-1., 1., 1.],
        [1., 1., 1.],
    ]
    .iter()
    .enumerate()
    {
        dirs.push((format!("corner{i}"), V3::from(*c)));
    }
    Case {
        template_landmarks: sphere_landmarks(&sphere, &dirs),
        scan_landmarks: dirs
            .iter()
            .map(|(n, c)| Landmark {
                name: n.clone(),
                pos: LandmarkPos::Point(*c),
            })
            .collect(),
        in_hole: vec![false; sphere.vertices.len()],
        template: sphere,
        scan: cube,
        truth: None,
    }
}

/// Size of the box of the missing-data case.
pub const BOX_SIZE: [f64; 3] = [2.0, 1.4, 1.0];

/// The paper's second test: a unit sphere onto a box with missing data (the whole +x
/// face, and a disc of radius 0.35 on the top face, removed), 6 landmarks at the face
/// centres. `in_hole` is left empty: the missing region is judged on the result.
pub fn sphere_to_box_with_missing(level: u32) -> Case {
    let sphere = icosphere(level);
    let size = V3::from(BOX_SIZE);
    let full = tessellated_box(size, 30);
    let (scan, _) = keep_triangles(&full, |t| {
        !in_box_hole(&full.corners(t).iter().sum::<V3>().scale(1.0 / 3.0))
    });
    let h = size / 2.0;
    let dirs: Vec<(String, V3, V3)> = vec![
        ("px".into(), V3::x(), V3::new(h.x, 0., 0.)),
        ("nx".into(), -V3::x(), V3::new(-h.x, 0., 0.)),
        ("py".into(), V3::y(), V3::new(0., h.y, 0.)),
        ("ny".into(), -V3::y(), V3::new(0., -h.y, 0.)),
        ("pz".into(), V3::z(), V3::new(0., 0., h.z)),
        ("nz".into(), -V3::z(), V3::new(0., 0., -h.z)),
    ];
    Case {
        template_landmarks: sphere_landmarks(
            &sphere,
            &dirs
                .iter()
                .map(|(n, d, _)| (n.clone(), *d))
                .collect::<Vec<_>>(),
        ),
        scan_landmarks: dirs
            .iter()
            .map(|(n, _, p)| Landmark {
                name: n.clone(),
                pos: LandmarkPos::Point(*p),
            })
            .collect(),
        in_hole: vec![false; sphere.vertices.len()],
        template: sphere,
        scan,
        truth: None,
    }
}

/// Whether a point of the box's surface lies in the removed region.
pub fn in_box_hole(p: &V3) -> bool {
    let h = V3::from(BOX_SIZE) / 2.0;
    let on_px = (p.x - h.x).abs() < 1e-9;
    let on_top_disc = (p.z - h.z).abs() < 1e-9 && !on_px && (p.x * p.x + p.y * p.y).sqrt() < 0.35;
    on_px || on_top_disc
}

/// How well a result of the box case fits the true (whole) box: distances to the true
/// surface relative to the box diagonal, over the vertices whose nearest box point lies
/// in the removed region, and the largest anywhere.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct BoxFigures {
    pub missing_vertices: usize,
    pub missing_mean: f64,
    pub missing_p90: f64,
    pub missing_max: f64,
    pub max_anywhere: f64,
}

pub fn box_figures(result: &Mesh) -> BoxFigures {
    let size = V3::from(BOX_SIZE);
    let diag = size.norm();
    let h = size / 2.0;
    let mut missing: Vec<f64> = Vec::new();
    let mut max_anywhere: f64 = 0.0;
    for p in &result.vertices {
        let d = super::distance_to_box_surface(p, &size) / diag;
        max_anywhere = max_anywhere.max(d);
        // the nearest point of the box surface
        let mut q = p.zip_map(&h, |a, b| a.clamp(-b, b));
        let gaps = [h.x - q.x.abs(), h.y - q.y.abs(), h.z - q.z.abs()];
        let k = (0..3)
            .min_by(|&a, &b| gaps[a].total_cmp(&gaps[b]))
            .unwrap_or(0);
        q[k] = h[k].copysign(q[k]);
        if in_box_hole(&q) {
            missing.push(d);
        }
    }
    missing.sort_by(f64::total_cmp);
    let n = missing.len();
    BoxFigures {
        missing_vertices: n,
        missing_mean: if n > 0 {
            missing.iter().sum::<f64>() / n as f64
        } else {
            0.0
        },
        missing_p90: if n > 0 {
            missing[(n * 9 / 10).min(n - 1)]
        } else {
            0.0
        },
        missing_max: missing.last().copied().unwrap_or(0.0),
        max_anywhere,
    }
}

/// Settings of the articulated case.
#[derive(Debug, Clone)]
pub struct ArticulatedSpec {
    pub template_vertices: usize,
    pub scan_points: usize,
    /// noise along the normal, relative to the subject's diagonal
    pub noise: f64,
    /// turn and shift the subject as a whole (the no-landmark case)
    pub turned: bool,
    pub seed: u64,
}

impl Default for ArticulatedSpec {
    fn default() -> Self {
        ArticulatedSpec {
            template_vertices: 6000,
            scan_points: 60_000,
            noise: 0.001,
            turned: false,
            seed: 7,
        }
    }
}

/// The subject's pose: parts rotated 15-30 degrees, the whole bent, twisted and scaled.
pub fn articulated_pose(turned: bool) -> Pose {
    let j = |n: &str, axis: [f64; 3], deg: f64| (n.to_string(), V3::from(axis), deg);
    Pose {
        joints: vec![
            j("neck", [0., 0., 1.], 25.0),
            j("neck", [0., 1., 0.], 12.0),
            j("upper_arm_l", [1., 0., 0.], 30.0),
            j("forearm_l", [0., 1., 0.], -25.0),
            j("upper_arm_r", [0., 1., 0.], -20.0),
            j("forearm_r", [1., 0., 0.], 20.0),
            j("thigh_l", [0., 1., 0.], -20.0),
            j("shin_l", [0., 1., 0.], 25.0),
            j("thigh_r", [1., 0., 0.], 15.0),
            j("foot_r", [0., 1., 0.], 15.0),
        ],
        bend: 12.0,
        twist: 15.0,
        scale: 1.08,
        turn: turned.then_some((V3::new(0.2, 0.3, 1.0), 35.0)),
        shift: if turned {
            V3::new(0.4, -0.3, 0.2)
        } else {
            V3::zeros()
        },
    }
}

/// The articulated known-answer case: a humanoid template at rest; the same figure posed
/// and deformed is the subject, seen from three viewpoints, resampled as a noisy point
/// cloud. Scan landmarks are the true positions of the
/// template's landmark vertices with 0.2% noise.
///
/// Two cameras in front to either side and one overhead see the figure; the back and
/// the inner surfaces stay hidden.
pub fn articulated(spec: &ArticulatedSpec) -> Case {
    let fig = figure::build(&figure::humanoid(), spec.template_vertices);
    let pose = articulated_pose(spec.turned);
    let truth = fig.pose(&pose);
    let subject = Mesh::new(truth.clone(), fig.mesh.triangles.clone());
    let (lo, hi) = subject.bounding_box().expect("non-empty figure");
    let centre = (lo + hi) / 2.0;
    let diag = (hi - lo).norm();
    let mid_turn = pose.turn.map_or(0.0, |(_, d)| d);
    // two cameras in front at either side and one overhead: the back, the backs of the
    // legs, the soles and the inner surfaces stay hidden
    let r = 1.4 * diag;
    let mut views = scanner::ring_viewpoints(centre, r, 0.1 * diag, -60.0 + mid_turn, 120.0, 2);
    views.push(centre + V3::new(-0.1 * diag, 0.0, 1.2 * diag));
    let seen = scanner::visible_triangles(&subject, &views);
    let scan = scanner::sample_points(
        &subject,
        &seen,
        spec.scan_points,
        spec.noise * diag,
        spec.seed,
    );
    let mut in_hole = vec![true; truth.len()];
    for (t, tri) in subject.triangles.iter().enumerate() {
        if seen[t] {
            for &i in tri {
                in_hole[i as usize] = false;
            }
        }
    }
    let template_landmarks = fig.landmarks();
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x5eed);
    let g = Normal::new(0.0, 0.002 * diag).expect("valid sigma");
    let scan_landmarks = template_landmarks
        .iter()
        .map(|l| {
            let LandmarkPos::Vertex(v) = l.pos else {
                unreachable!("figure landmarks are vertices")
            };
            let p = truth[v as usize]
                + V3::new(g.sample(&mut rng), g.sample(&mut rng), g.sample(&mut rng));
            Landmark {
                name: l.name.clone(),
                pos: LandmarkPos::Point(p),
            }
        })
        .collect();
    Case {
        template: fig.mesh,
        scan,
        template_landmarks,
        scan_landmarks,
        truth: Some(truth),
        in_hole,
    }
}

/// Scans a subject as a station would: cameras on a ring at the given azimuths (degrees,
/// 0 = +x) and one overhead; triangles none of them sees are holes. Returns the point
/// cloud (`points` samples, normal noise `noise` relative to the diagonal) and, per
/// vertex, whether its place went unseen.
pub fn scan_subject(
    subject: &Mesh,
    azimuths: &[f64],
    points: usize,
    noise: f64,
    seed: u64,
) -> (Mesh, Vec<bool>) {
    let (lo, hi) = subject.bounding_box().expect("non-empty subject");
    let centre = (lo + hi) / 2.0;
    let diag = (hi - lo).norm();
    let r = 1.4 * diag;
    let mut views: Vec<V3> = azimuths
        .iter()
        .flat_map(|&a| scanner::ring_viewpoints(centre, r, 0.1 * diag, a, 0.0, 1))
        .collect();
    views.push(centre + V3::new(-0.1 * diag, 0.0, 1.2 * diag));
    let seen = scanner::visible_triangles(subject, &views);
    let scan = scanner::sample_points(subject, &seen, points, noise * diag, seed);
    let mut in_hole = vec![true; subject.vertices.len()];
    for (t, tri) in subject.triangles.iter().enumerate() {
        if seen[t] {
            for &i in tri {
                in_hole[i as usize] = false;
            }
        }
    }
    (scan, in_hole)
}

/// Correspondence error figures of a result against the truth, relative to the truth's
/// bounding-box diagonal.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct CorrespondenceError {
    pub mean: f64,
    pub mean_in_holes: f64,
    pub p95: f64,
    pub max: f64,
    pub flipped: usize,
}

pub fn correspondence_error(
    result: &[V3],
    truth: &[V3],
    in_hole: &[bool],
    tris: &[[u32; 3]],
) -> CorrespondenceError {
    let diag = Mesh::new(truth.to_vec(), vec![]).diagonal();
    let mut e: Vec<f64> = result
        .iter()
        .zip(truth)
        .map(|(a, b)| (a - b).norm() / diag)
        .collect();
    let (hs, hc) = e
        .iter()
        .zip(in_hole)
        .filter(|(_, h)| **h)
        .fold((0.0, 0usize), |(s, c), (x, _)| (s + x, c + 1));
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    e.sort_by(f64::total_cmp);
    CorrespondenceError {
        mean,
        mean_in_holes: if hc > 0 { hs / hc as f64 } else { 0.0 },
        p95: e[(e.len() as f64 * 0.95) as usize],
        max: *e.last().unwrap_or(&0.0),
        flipped: crate::mesh::quality::flipped_against(result, truth, tris),
    }
}

/// Template landmarks placed on a subject in the template's vertex order (a posed truth):
/// each vertex landmark becomes the subject's point there, as an operator would click it
/// on the scan; point landmarks stay.
pub fn landmarks_on(landmarks: &[Landmark], subject: &Mesh) -> Vec<Landmark> {
    landmarks
        .iter()
        .map(|l| Landmark {
            name: l.name.clone(),
            pos: match l.pos {
                LandmarkPos::Vertex(v) => LandmarkPos::Point(subject.vertices[v as usize]),
                p => p,
            },
        })
        .collect()
}
