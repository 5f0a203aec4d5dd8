//! The development set of meshes conformd did not make (`tests/data/meshes`, sources and
//! licences in `tests/data/README.md`), the variants made from them (uneven triangles,
//! open boundaries) and their known-answer cases: posed by `posing`, scanned by the
//! virtual scanner from four sides and above, with noisy landmarks at extremities.

use crate::SynthError;
use crate::posing::{self, Extremities, PoseSettings};
use conformd::mesh::landmarks::{Landmark, LandmarkPos};
use conformd::mesh::{Mesh, V3, io, keep_triangles, topology};
use conformd::synth::cases::{Case, scan_subject};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::path::PathBuf;

/// A mesh of the set: its file under `tests/data/meshes`, stored y-up as published.
pub struct DevMesh {
    pub name: &'static str,
    pub file: &'static str,
    /// what makes it a test: thin parts, uneven triangles, open boundaries
    pub traits: &'static str,
}

pub const MESHES: &[DevMesh] = &[
    DevMesh {
        name: "koala",
        file: "koala.obj",
        traits: "four-legged, ears, even triangles",
    },
    DevMesh {
        name: "cat",
        file: "cat.obj",
        traits: "legs, long thin tail, ears",
    },
    DevMesh {
        name: "human",
        file: "human.obj",
        traits: "SMPL body, fingers, edge CV 0.59",
    },
    DevMesh {
        name: "hand",
        file: "hand.obj",
        traits: "open at the wrist, thin fingers, edge CV 0.44",
    },
    DevMesh {
        name: "woman",
        file: "human_woman.obj",
        traits: "SMPL body of another person, the man's vertex order",
    },
    DevMesh {
        name: "neutral",
        file: "human_neutral.obj",
        traits: "SMPL-X body, 10k vertices, refined unevenly in the cases",
    },
    DevMesh {
        name: "cow",
        file: "cow.obj",
        traits: "four-legged, horns, 10.8k vertices",
    },
    DevMesh {
        name: "spot",
        file: "spot.obj",
        traits: "four-legged cartoon cow: short legs, big head on the front legs, 11.5k even vertices",
    },
    DevMesh {
        name: "koala-dense",
        file: "koala_dense.obj",
        traits: "four-legged, 50k vertices",
    },
];

/// The meshes of the validation part: only ever measured, never tuned on (they stay out
/// of `standard_cases`, on which the defaults are chosen).
pub const VALIDATION_MESHES: &[&str] = &["woman", "neutral", "cow", "koala-dense"];

pub fn data_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/meshes")
}

/// Loads a mesh of the set turned z-up (the virtual station's cameras look across z).
pub fn load(name: &str) -> Result<Mesh, SynthError> {
    let m = MESHES
        .iter()
        .find(|m| m.name == name)
        .ok_or_else(|| SynthError::NoMesh(name.to_string()))?;
    let mut mesh = io::read_mesh(&data_dir().join(m.file))?;
    for v in &mut mesh.vertices {
        *v = V3::new(v.x, -v.z, v.y);
    }
    Ok(mesh)
}

/// Edge-length coefficient of variation (std / mean), the triangulation's unevenness.
pub fn edge_cv(mesh: &Mesh) -> f64 {
    let l: Vec<f64> = topology::edges(&mesh.triangles)
        .iter()
        .map(|[a, b]| (mesh.vertices[*a as usize] - mesh.vertices[*b as usize]).norm())
        .collect();
    let mean = l.iter().sum::<f64>() / l.len().max(1) as f64;
    let var = l.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / l.len().max(1) as f64;
    var.sqrt() / mean
}

/// The same surface triangulated unevenly: vertices slid along the surface by up to a
/// quarter of their shortest edge, then a share of the edges flipped where the flip keeps
/// both triangles' orientation (long thin triangles, uneven valence), as real
/// templates are.
pub fn uneven(mesh: &Mesh, flip_share: f64, seed: u64) -> Mesh {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let n = mesh.vertices.len();
    let nb = topology::vertex_neighbours(n, &mesh.triangles);
    let normals = mesh.vertex_normals();
    let mut v = mesh.vertices.clone();
    for i in 0..n {
        let shortest = nb[i]
            .iter()
            .map(|&j| (mesh.vertices[i] - mesh.vertices[j as usize]).norm())
            .fold(f64::INFINITY, f64::min);
        if !shortest.is_finite() {
            continue;
        }
        let r = V3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let t = r - normals[i] * normals[i].dot(&r);
        v[i] += t * (shortest / 4.0);
    }
    let mut tris = mesh.triangles.clone();
    let mut by_edge: std::collections::HashMap<[u32; 2], Vec<usize>> =
        std::collections::HashMap::new();
    for (t, tri) in tris.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            by_edge.entry([a.min(b), a.max(b)]).or_default().push(t);
        }
    }
    let mut edges: Vec<[u32; 2]> = by_edge.keys().copied().collect();
    edges.sort_unstable();
    let mut touched = vec![false; tris.len()];
    let mut existing: std::collections::HashSet<[u32; 2]> = edges.iter().copied().collect();
    let normal = |v: &[V3], t: &[u32; 3]| {
        (v[t[1] as usize] - v[t[0] as usize]).cross(&(v[t[2] as usize] - v[t[0] as usize]))
    };
    for e in edges {
        if rng.random::<f64>() >= flip_share {
            continue;
        }
        let ts = &by_edge[&e];
        if ts.len() != 2 || touched[ts[0]] || touched[ts[1]] {
            continue;
        }
        let (t0, t1) = (ts[0], ts[1]);
        let opposite = |t: &[u32; 3]| t.iter().copied().find(|x| !e.contains(x));
        let (Some(c), Some(d)) = (opposite(&tris[t0]), opposite(&tris[t1])) else {
            continue;
        };
        if existing.contains(&[c.min(d), c.max(d)]) {
            continue;
        }
        // keep the winding: in t0 the edge runs a -> b with c opposite
        let k = (0..3).find(|&k| tris[t0][k] == c).unwrap_or(0);
        let (a, b) = (tris[t0][(k + 1) % 3], tris[t0][(k + 2) % 3]);
        let (n0, n1) = (normal(&v, &tris[t0]), normal(&v, &tris[t1]));
        let (new0, new1) = ([c, a, d], [d, b, c]);
        // no slivers under 5 degrees (a smooth posing folds those, leaving no true
        // answer) and no flips across a ridge (within 45 degrees of both old normals)
        let ok = [new0, new1].iter().all(|t| {
            let nn = normal(&v, t);
            let c = |m: &V3| nn.dot(m) / (nn.norm() * m.norm()).max(1e-300);
            nn.norm() > 0.0 && c(&n0) > 0.7 && c(&n1) > 0.7 && min_angle(&v, t) > 5.0
        });
        if !ok {
            continue;
        }
        tris[t0] = new0;
        tris[t1] = new1;
        touched[t0] = true;
        touched[t1] = true;
        existing.remove(&e);
        existing.insert([c.min(d), c.max(d)]);
    }
    Mesh::new(v, tris)
}

fn min_angle(v: &[V3], t: &[u32; 3]) -> f64 {
    (0..3)
        .map(|k| {
            let o = v[t[k] as usize];
            let (a, b) = (
                v[t[(k + 1) % 3] as usize] - o,
                v[t[(k + 2) % 3] as usize] - o,
            );
            a.angle(&b).to_degrees()
        })
        .fold(180.0, f64::min)
}

/// The mesh with `holes` discs of surface (radius `radius` of the diagonal, about
/// vertices drawn at random) cut out: open boundaries, as templates with eye holes or an
/// open neck have. Returns the mesh and each kept vertex's old index.
pub fn with_holes(mesh: &Mesh, holes: usize, radius: f64, seed: u64) -> (Mesh, Vec<u32>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let r = radius * mesh.diagonal();
    let centres: Vec<V3> = (0..holes)
        .map(|_| mesh.vertices[rng.random_range(0..mesh.vertices.len())])
        .collect();
    keep_triangles(mesh, |t| {
        let [a, b, c] = mesh.corners(t);
        let mid = (a + b + c) / 3.0;
        centres.iter().all(|h| (mid - h).norm() > r)
    })
}

/// How a development case is made.
#[derive(Debug, Clone, Copy)]
pub struct DevCaseSpec {
    pub pose: PoseSettings,
    pub scan_points: usize,
    /// noise along the normal, relative to the diagonal
    pub noise: f64,
    pub landmarks: usize,
    /// landmark noise, relative to the diagonal
    pub landmark_noise: f64,
    /// turn (degrees, about a random axis) and shift (relative) of the subject as a whole
    pub turn: f64,
    /// turn about the vertical (z) through the subject's centre, degrees: a heading, as a
    /// station sees it (its up axis known)
    pub heading: f64,
    pub shift: f64,
    pub seed: u64,
}

impl Default for DevCaseSpec {
    fn default() -> Self {
        DevCaseSpec {
            pose: PoseSettings::default(),
            scan_points: 60_000,
            noise: 0.002,
            landmarks: 12,
            landmark_noise: 0.002,
            turn: 0.0,
            heading: 0.0,
            shift: 0.0,
            seed: 3,
        }
    }
}

/// A known-answer case for any template: the template posed (`posing`), turned and
/// shifted as asked, scanned from four sides and above; landmarks on the first
/// farthest-point samples (extremities first), their scan positions the truth plus noise.
pub fn case(template: &Mesh, spec: &DevCaseSpec) -> Case {
    case_onto(template, template, spec)
}

/// [`case`] with another subject in the template's vertex order (another person's
/// registered mesh): the subject is posed and scanned, so vertex i of the template truly
/// belongs where vertex i of the posed subject is.
pub fn case_onto(template: &Mesh, subject: &Mesh, spec: &DevCaseSpec) -> Case {
    assert_eq!(
        template.vertices.len(),
        subject.vertices.len(),
        "a subject in the template's vertex order"
    );
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let (truth, ext) = posed(subject, spec, template.diagonal(), &mut rng);
    let diag = template.diagonal();
    let subject = Mesh::new(truth.clone(), template.triangles.clone());
    let (scan, in_hole) = scan_as_spec_says(&subject, spec);
    let picked: Vec<u32> = ext
        .samples
        .iter()
        .take(spec.landmarks)
        .map(|s| s.0)
        .collect();
    let (template_landmarks, scan_landmarks) =
        landmark_pairs(&picked, &truth, spec.landmark_noise * diag, &mut rng);
    Case {
        template: template.clone(),
        scan,
        template_landmarks,
        scan_landmarks,
        truth: Some(truth),
        in_hole,
    }
}

/// The posed subject seen as the set sees every case: four cameras around and one
/// above, `spec`'s points and noise; the scan and which vertices it missed.
pub fn scan_as_spec_says(posed: &Mesh, spec: &DevCaseSpec) -> (Mesh, Vec<bool>) {
    scan_subject(
        posed,
        &[0.0, 90.0, 180.0, 270.0],
        spec.scan_points,
        spec.noise,
        spec.seed,
    )
}

/// The subject posed as `spec` says (its limbs turned, bent, twisted, scaled), then
/// turned to its heading and by `turn` about a random axis, and shifted by `shift` of
/// `diag`: each vertex's true place, and the extremities the posing found.
pub fn posed(
    subject: &Mesh,
    spec: &DevCaseSpec,
    diag: f64,
    rng: &mut ChaCha8Rng,
) -> (Vec<V3>, Extremities) {
    let mut nb = topology::vertex_neighbours(subject.vertices.len(), &subject.triangles);
    // loose parts (a body model's eyeballs) joined to what they touch, so they turn with
    // it: along the edges alone a turned head would leave its eyes behind
    for [a, b] in topology::bridges(
        &subject.vertices,
        &subject.triangles,
        0.01 * subject.diagonal(),
    ) {
        nb[a as usize].push(b);
        nb[b as usize].push(a);
    }
    let ext: Extremities = posing::extremities(subject, &nb, spec.landmarks.max(spec.pose.limbs));
    let mut truth = posing::pose(subject, &nb, &ext, &spec.pose);
    if spec.heading != 0.0 {
        let c = truth.iter().sum::<V3>() / truth.len() as f64;
        let rot = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), spec.heading.to_radians());
        for p in &mut truth {
            *p = c + rot * (*p - c);
        }
    }
    if spec.turn != 0.0 || spec.shift != 0.0 {
        let axis = nalgebra::Unit::new_normalize(V3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ));
        let rot = nalgebra::Rotation3::from_axis_angle(&axis, spec.turn.to_radians());
        let c = truth.iter().sum::<V3>() / truth.len() as f64;
        let dir = V3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        )
        .normalize();
        for p in &mut truth {
            *p = c + rot * (*p - c) + dir * spec.shift * diag;
        }
    }
    (truth, ext)
}

/// Landmarks `x0, x1, ...` on the `picked` template vertices, and on the scan at their
/// true places plus Gaussian noise of `sigma`.
fn landmark_pairs(
    picked: &[u32],
    truth: &[V3],
    sigma: f64,
    rng: &mut ChaCha8Rng,
) -> (Vec<Landmark>, Vec<Landmark>) {
    let g = Normal::new(0.0, sigma).expect("valid sigma");
    picked
        .iter()
        .enumerate()
        .map(|(k, &v)| {
            let noise = V3::new(g.sample(rng), g.sample(rng), g.sample(rng));
            (
                Landmark {
                    name: format!("x{k}"),
                    pos: LandmarkPos::Vertex(v),
                },
                Landmark {
                    name: format!("x{k}"),
                    pos: LandmarkPos::Point(truth[v as usize] + noise),
                },
            )
        })
        .unzip()
}

/// Writes a case for the peer script (`benches/peer/trimesh_sumner.py`): template,
/// scan, truth, per-vertex hole flags and, when used, both landmark files.
pub fn export(case: &Case, landmarks: bool, dir: &std::path::Path) -> Result<(), SynthError> {
    use conformd::mesh::io::write_mesh;
    use conformd::mesh::landmarks::landmarks_text;
    let write = |name: &str, text: String| {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(|source| SynthError::Io {
            path: path.display().to_string(),
            source,
        })
    };
    std::fs::create_dir_all(dir).map_err(|source| SynthError::Io {
        path: dir.display().to_string(),
        source,
    })?;
    let truth = case.truth.clone().ok_or(SynthError::NoTruth)?;
    write_mesh(&dir.join("template.obj"), &case.template)?;
    write_mesh(&dir.join("scan.ply"), &case.scan)?;
    let t = Mesh::new(truth, case.template.triangles.clone());
    write_mesh(&dir.join("truth.obj"), &t)?;
    let holes: String = case
        .in_hole
        .iter()
        .map(|h| if *h { "1\n" } else { "0\n" })
        .collect();
    write("in_hole.txt", holes)?;
    if landmarks {
        write("template.lm", landmarks_text(&case.template_landmarks))?;
        write("scan.lm", landmarks_text(&case.scan_landmarks))?;
    }
    Ok(())
}

/// One case of the development table: a name, the case, and whether the conformation
/// gets landmarks.
pub struct DevCase {
    pub name: String,
    pub case: Case,
    pub landmarks: bool,
    /// the scan's up axis when the station would know it (the template is z-up): given to
    /// the landmark-free alignment as `[align] template_up = scan_up`
    pub scan_up: Option<V3>,
    pub part: Part,
}

/// Which part of the set a case belongs to: the defaults are chosen on `Development`;
/// `Validation` is only ever measured, so that its figures stay evidence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Part {
    Development,
    Validation,
}

impl DevCase {
    /// The conformation options for this case: `base` with the up hint when it has one.
    pub fn options(
        &self,
        base: &conformd::conform::ConformOptions,
    ) -> conformd::conform::ConformOptions {
        let mut o = base.clone();
        if let Some(u) = self.scan_up {
            o.align.template_up = Some([0.0, 0.0, 1.0]);
            o.align.scan_up = Some([u.x, u.y, u.z]);
        }
        o
    }
}

/// The development table: every mesh posed and scanned, with landmarks and without
/// (turned 20 degrees, shifted 5%), plus a harder posture of the koala. The cat is made
/// uneven (edge CV >= 0.3) and opened by three holes, as an outside template is.
pub fn standard_cases(names: &[&str]) -> Result<Vec<DevCase>, SynthError> {
    let mut out = Vec::new();
    for m in MESHES {
        if VALIDATION_MESHES.contains(&m.name) || (!names.is_empty() && !names.contains(&m.name)) {
            continue;
        }
        let mut mesh = load(m.name)?;
        if m.name == "cat" {
            mesh = with_holes(&uneven(&mesh, 0.5, 11), 3, 0.03, 12).0;
        }
        let posed = DevCaseSpec::default();
        let turned = DevCaseSpec {
            turn: 20.0,
            shift: 0.05,
            seed: 5,
            pose: PoseSettings {
                seed: 2,
                ..posed.pose
            },
            ..posed
        };
        out.push(DevCase {
            name: format!("{} posed, landmarks", m.name),
            case: case(&mesh, &posed),
            landmarks: true,
            scan_up: None,
            part: Part::Development,
        });
        out.push(DevCase {
            name: format!("{} turned, no landmarks", m.name),
            case: case(&mesh, &turned),
            landmarks: false,
            scan_up: None,
            part: Part::Development,
        });
        if m.name == "koala" {
            let hard = DevCaseSpec {
                pose: PoseSettings {
                    limb_degrees: (30.0, 45.0),
                    bend: 20.0,
                    twist: 15.0,
                    seed: 4,
                    ..posed.pose
                },
                ..posed
            };
            out.push(DevCase {
                name: format!("{} hard posture, landmarks", m.name),
                case: case(&mesh, &hard),
                landmarks: true,
                scan_up: None,
                part: Part::Development,
            });
        }
    }
    Ok(out)
}

/// The paper's own pig study set-up: one capture's reconstruction, triangulated per pod
/// (`Reconstruction::run` with `as_mesh`: several components, holes, uneven triangles),
/// is the template; the scan is another capture of the same animal in another posture.
/// The subject is the generic pig posed both ways, so each template vertex's true place
/// is known: the point of the first posture's surface it was reconstructed at, carried
/// to the second posture (same triangle, same barycentric coordinates). Landmarks are
/// 12 template vertices spread by farthest-point sampling.
pub fn captured_template_case(
    station: &mut conformd::stereo::rig::Reconstruction,
    rig: &conformd::stereo::rig::RigFile,
    seed: u64,
) -> Result<Case, SynthError> {
    use conformd::template::{self, Kind};
    use parry3d_f64::math::Vector as PVec;
    use parry3d_f64::query::PointQueryWithLocation;
    use parry3d_f64::shape::TriMesh;
    let fig = template::build(Kind::Pig, 20_000);
    let posed = |p: &str| -> Result<Mesh, SynthError> {
        let names: Vec<&str> = template::pose_parameters(Kind::Pig)
            .iter()
            .map(|p| p.0)
            .collect();
        let params = template::parse_parameters(p, &names, "pose")?;
        Ok(template::subject(
            &fig,
            Kind::Pig,
            &std::collections::BTreeMap::new(),
            &template::pose(Kind::Pig, &params),
        )?)
    };
    let a = posed("nod=8,leg_fl=12,tail=-10")?;
    let b = posed("swing=14,nod=-12,twist=6,leg_hl=-18,leg_fr=15,tail=25")?;
    let mut capture = |subject: &Mesh, as_mesh: bool, seed: u64| -> Result<Mesh, SynthError> {
        let rendered = conformd::synth::virtual_rig::render_rig(rig, subject, 2.0, seed);
        let pairs: Vec<(Vec<u8>, Vec<u8>)> = rendered
            .chunks(2)
            .map(|p| (p[0].pixels.clone(), p[1].pixels.clone()))
            .collect();
        Ok(station.run(&pairs, as_mesh).map(|(m, _)| m)?)
    };
    let tpl = capture(&a, true, seed)?;
    let scan = capture(&b, false, seed + 1)?;
    // each template vertex's place on the first posture, carried to the second
    let verts: Vec<PVec> = a
        .vertices
        .iter()
        .map(|p| PVec::new(p.x, p.y, p.z))
        .collect();
    let tm = TriMesh::new(verts, a.triangles.clone())
        .map_err(|e| SynthError::Triangles(format!("{e:?}")))?;
    let truth: Vec<V3> = tpl
        .vertices
        .iter()
        .map(|p| {
            let (_, (t, loc)) =
                tm.project_local_point_and_get_location(PVec::new(p.x, p.y, p.z), false);
            let bc = loc.barycentric_coordinates().unwrap_or([1.0 / 3.0; 3]);
            let tri = b.triangles[t as usize];
            (0..3).map(|k| b.vertices[tri[k] as usize] * bc[k]).sum()
        })
        .collect();
    // a vertex is in a hole where the second capture saw nothing near its true place
    let surface = conformd::conform::correspond::ScanSurface::new(&scan)?;
    let gap = 5.0 * surface.spacing;
    let in_hole: Vec<bool> = truth
        .iter()
        .map(|p| surface.nearest_point(p).1 > gap)
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1a4d);
    let diag = tpl.diagonal();
    let picked = farthest_points(&tpl.vertices, 12);
    let (template_landmarks, scan_landmarks) =
        landmark_pairs(&picked, &truth, 0.002 * diag, &mut rng);
    Ok(Case {
        template: tpl,
        scan,
        template_landmarks,
        scan_landmarks,
        truth: Some(truth),
        in_hole,
    })
}

/// `count` points spread by Euclidean farthest-point sampling, from the point farthest
/// from the centroid.
pub fn farthest_points(p: &[V3], count: usize) -> Vec<u32> {
    if p.is_empty() {
        return Vec::new();
    }
    let c = p.iter().sum::<V3>() / p.len() as f64;
    let mut d: Vec<f64> = p.iter().map(|q| (q - c).norm()).collect();
    let mut out = Vec::new();
    for _ in 0..count.min(p.len()) {
        let (i, _) = d
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("non-empty");
        out.push(i as u32);
        for (dq, q) in d.iter_mut().zip(p) {
            *dq = dq.min((q - p[i]).norm());
        }
    }
    out
}

/// The captured-scan-as-template cases (with landmarks and without), on the example rig.
pub fn captured_cases() -> Result<Vec<DevCase>, SynthError> {
    let rig_path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../config/rig.example.toml");
    let rig = conformd::stereo::rig::RigFile::load(&rig_path)?;
    let mut station = conformd::stereo::rig::Reconstruction::load(&rig_path, None)?;
    let case = captured_template_case(&mut station, &rig, 21)?;
    let again = Case {
        template: case.template.clone(),
        scan: case.scan.clone(),
        template_landmarks: case.template_landmarks.clone(),
        scan_landmarks: case.scan_landmarks.clone(),
        truth: case.truth.clone(),
        in_hole: case.in_hole.clone(),
    };
    Ok(vec![
        DevCase {
            name: "captured pig as template, landmarks".into(),
            case,
            landmarks: true,
            scan_up: None,
            part: Part::Development,
        },
        DevCase {
            name: "captured pig as template, none".into(),
            case: again,
            landmarks: false,
            scan_up: None,
            part: Part::Development,
        },
    ])
}

/// The mesh with the edges of every triangle `select` takes (by its centroid) split at
/// their midpoints; triangles with one, two or three split edges become two, three or
/// four, so the result has no T-junctions and keeps its winding. Refining a part of a
/// mesh this way, once or more, gives the dense and very uneven triangulations real
/// templates have (fine where someone modelled detail, coarse elsewhere, slivers between).
pub fn refine(mesh: &Mesh, select: impl Fn(&V3) -> bool) -> Mesh {
    use std::collections::HashMap;
    let mut v = mesh.vertices.clone();
    let mut mid: HashMap<[u32; 2], u32> = HashMap::new();
    for (i, t) in mesh.triangles.iter().enumerate() {
        let [a, b, c] = mesh.corners(i);
        if select(&((a + b + c) / 3.0)) {
            for k in 0..3 {
                let (p, q) = (t[k], t[(k + 1) % 3]);
                mid.entry([p.min(q), p.max(q)]).or_insert_with(|| {
                    v.push((v[p as usize] + v[q as usize]) / 2.0);
                    (v.len() - 1) as u32
                });
            }
        }
    }
    let mut tris = Vec::with_capacity(mesh.triangles.len() * 2);
    for t in &mesh.triangles {
        let m: [Option<u32>; 3] = std::array::from_fn(|k| {
            let (p, q) = (t[k], t[(k + 1) % 3]);
            mid.get(&[p.min(q), p.max(q)]).copied()
        });
        match m.iter().filter(|x| x.is_some()).count() {
            0 => tris.push(*t),
            3 => {
                let [ab, bc, ca] = m.map(|x| x.unwrap_or(0));
                tris.extend([[t[0], ab, ca], [ab, t[1], bc], [ca, bc, t[2]], [ab, bc, ca]]);
            }
            1 => {
                // rotate so that the split edge is (t0, t1)
                let k = (0..3).find(|&k| m[k].is_some()).unwrap_or(0);
                let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
                let s = m[k].unwrap_or(0);
                tris.extend([[a, s, c], [s, b, c]]);
            }
            _ => {
                // two split edges: the unsplit one is (t[k+2], t[k]) for the k below
                let k = (0..3).find(|&k| m[(k + 2) % 3].is_none()).unwrap_or(0);
                let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
                let (s, u) = (m[k].unwrap_or(0), m[(k + 1) % 3].unwrap_or(0));
                tris.extend([[a, s, c], [s, b, u], [s, u, c]]);
            }
        }
    }
    Mesh::new(v, tris)
}

/// A body refined until it has more than 50k vertices with very uneven triangles: all of
/// the upper body once (above 45% of its height), its upper right quarter (above 60%,
/// right of the middle) once more.
pub fn dense_uneven_body(mesh: &Mesh) -> Mesh {
    let (lo, hi) = mesh.bounding_box().expect("a body");
    let h = |f: f64| lo.z + f * (hi.z - lo.z);
    let x = |f: f64| (lo.x + hi.x) / 2.0 + f * (hi.x - lo.x) / 2.0;
    let m = refine(mesh, |p| p.z > h(0.45));
    refine(&m, |p| p.z > h(0.6) && p.x > x(0.0))
}

/// `mesh` (a person, z up, facing the way from the top of the head to the nose tip)
/// with two eyeballs as loose spheres of 2,562 vertices (finer than any scan resolves them) in the eye sockets, their fronts
/// just out through the face, as a body model's are (SMPL-X): 3.2 cm either side of
/// the face's middle, 4 cm above the nose tip and 2 cm behind it, 1.25 cm across.
pub fn with_eyes(mesh: &Mesh, nose_tip: usize, head_top: usize) -> Mesh {
    let (nose, top) = (mesh.vertices[nose_tip], mesh.vertices[head_top]);
    let up = V3::z();
    let ahead = {
        let d = nose - top;
        (d - up * d.dot(&up)).normalize()
    };
    let side = up.cross(&ahead);
    let normals = mesh.vertex_normals();
    let ball = conformd::synth::icosphere(4);
    let radius = 0.0125;
    let mut out = mesh.clone();
    for sign in [-1.0, 1.0] {
        let guess = nose + up * 0.04 - ahead * 0.02 + side * (0.032 * sign);
        let (on_face, _) = mesh
            .vertices
            .iter()
            .enumerate()
            .map(|(i, p)| (i, (p - guess).norm_squared()))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("a mesh with vertices");
        let centre = mesh.vertices[on_face] - normals[on_face] * (0.9 * radius);
        out.append(&ball, |p| centre + p * radius);
    }
    out
}

/// The large posture of the harder set: 8 extremities tried as limbs, turned 45-90
/// degrees; the whole bent 20 and twisted 15 degrees, scaled 1.05, turned to `heading`.
pub fn large_posture(seed: u64, heading: f64) -> DevCaseSpec {
    DevCaseSpec {
        pose: PoseSettings {
            limbs: 8,
            limb_degrees: (45.0, 90.0),
            bend: 20.0,
            twist: 15.0,
            scale: 1.05,
            seed,
        },
        heading,
        seed: seed + 100,
        ..DevCaseSpec::default()
    }
}

/// The harder set: large postures (limbs swung 45-90 degrees, the whole bent
/// and twisted, a new heading), one person's mesh onto another person's, dense uneven
/// triangulations (50k+ vertices, edge CV near 1 and over), holes; each case with 12
/// landmarks and without (the up axis given, as a station's config does).
/// `Part::Development` is what the defaults may be tuned on; `Part::Validation` (the cow,
/// the dense koala, the man onto the woman, the dense SMPL-X body) is only measured.
pub fn hard_cases(part: Part, names: &[&str]) -> Result<Vec<DevCase>, SynthError> {
    let large = large_posture;
    // (name, what it is, template, subject, spec)
    let mut made: Vec<(String, Mesh, Option<Mesh>, DevCaseSpec)> = Vec::new();
    let want = |n: &str| names.is_empty() || names.contains(&n);
    match part {
        Part::Development => {
            if want("koala") {
                made.push((
                    "koala large posture".into(),
                    load("koala")?,
                    None,
                    large(7, 50.0),
                ));
            }
            if want("cat") {
                let cat = with_holes(&uneven(&load("cat")?, 0.5, 11), 3, 0.03, 12).0;
                made.push(("cat large posture".into(), cat, None, large(8, -70.0)));
            }
            if want("human") {
                made.push((
                    "man large posture".into(),
                    load("human")?,
                    None,
                    large(9, 120.0),
                ));
            }
            if want("human-dense") {
                let dense = dense_uneven_body(&load("human")?);
                made.push(("man dense uneven".into(), dense, None, large(10, 30.0)));
            }
            if want("human-eyes") {
                // with eyeballs, as the validation part's body model has them
                let marks = crate::semantic::marks_of("human")?;
                let mark = |name: &str| {
                    marks
                        .iter()
                        .find(|m| m.0 == name)
                        .map(|m| m.1 as usize)
                        .ok_or_else(|| SynthError::NoMark {
                            file: "human.marks".into(),
                            name: name.into(),
                        })
                };
                let eyed = with_eyes(&load("human")?, mark("nose_tip")?, mark("head_top")?);
                made.push(("man with eyes".into(), eyed, None, large(11, -20.0)));
            }
        }
        Part::Validation => {
            if want("cow") {
                made.push((
                    "cow large posture".into(),
                    load("cow")?,
                    None,
                    large(21, -40.0),
                ));
            }
            if want("koala-dense") {
                made.push((
                    "koala 50k large posture".into(),
                    load("koala-dense")?,
                    None,
                    large(22, 160.0),
                ));
            }
            if want("woman") {
                made.push((
                    "man onto woman".into(),
                    load("human")?,
                    Some(load("woman")?),
                    large(23, -100.0),
                ));
            }
            if want("neutral") {
                let dense = dense_uneven_body(&load("neutral")?);
                made.push(("SMPL-X dense uneven".into(), dense, None, large(24, 75.0)));
            }
        }
    }
    let mut out = Vec::new();
    for (name, template, subject, spec) in made {
        let c = case_onto(&template, subject.as_ref().unwrap_or(&template), &spec);
        let again = Case {
            template: c.template.clone(),
            scan: c.scan.clone(),
            template_landmarks: c.template_landmarks.clone(),
            scan_landmarks: c.scan_landmarks.clone(),
            truth: c.truth.clone(),
            in_hole: c.in_hole.clone(),
        };
        out.push(DevCase {
            name: format!("{name}, landmarks"),
            case: c,
            landmarks: true,
            scan_up: None,
            part,
        });
        out.push(DevCase {
            name: format!("{name}, none"),
            case: again,
            landmarks: false,
            scan_up: Some(V3::z()),
            part,
        });
    }
    Ok(out)
}
