//! Repeatability cases: one subject scanned in many postures, the generic
//! template conformed onto every scan. What the station promises is that the subject's
//! measurements do not depend on how it stood; these cases show whether they do. The
//! subjects: a generic template of another shape and triangulation (the template's own
//! family), and outside animals and people (`tests/data/meshes`) posed by `posing`, each
//! scanned from four sides and above (occlusion holes, noise).

use crate::devset::{self, Part};
use crate::posing::{self, PoseSettings};
use conformd::mesh::landmarks::{Landmark, LandmarkPos};
use conformd::mesh::{Mesh, V3, topology};
use conformd::template::{self, Kind, figure::Figure};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;

/// One posture of a subject as the station sees it.
pub struct Posture {
    pub scan: Mesh,
    /// the template's landmarks that are marked on the subject, and where they truly are
    /// in this posture (for the runs with landmarks)
    pub template_landmarks: Vec<Landmark>,
    pub scan_landmarks: Vec<Landmark>,
    /// the way the subject faces (level)
    pub front: V3,
}

pub struct Subject {
    pub name: String,
    pub part: Part,
    pub kind: Kind,
    /// the generic template conformed onto every posture
    pub template: Figure,
    pub postures: Vec<Posture>,
}

/// Landmark pairs: `marks` (name, subject vertex) that the template also has.
fn landmark_pairs(
    template: &BTreeMap<String, u32>,
    marks: &[(String, u32)],
    posed: &[V3],
) -> (Vec<Landmark>, Vec<Landmark>) {
    marks
        .iter()
        .filter_map(|(name, v)| {
            let t = template.get(name)?;
            let p = posed.get(*v as usize)?;
            Some((
                Landmark {
                    name: name.clone(),
                    pos: LandmarkPos::Vertex(*t),
                },
                Landmark {
                    name: name.clone(),
                    pos: LandmarkPos::Point(*p),
                },
            ))
        })
        .unzip()
}

/// The subject stood on the floor (z = 0), as on a station's: its lowest point on it.
fn grounded(x: &mut [V3]) {
    let low = x.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
    if low.is_finite() {
        for p in x {
            p.z -= low;
        }
    }
}

fn turned(x: &mut [V3], degrees: f64) {
    let c = x.iter().sum::<V3>() / x.len().max(1) as f64;
    let rot = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), degrees.to_radians());
    for p in x {
        *p = c + rot * (*p - c);
    }
}

/// The subjects of a part, each in `count` postures. Development: the generic pig and
/// body of other proportions (and another triangulation), the koala and the man, and the
/// man in a booth's three stances (`posing::Stance`, whatever `count`); validation
/// (never tuned on): the cow and the woman, and the woman in the booth's stances.
pub fn subjects(
    part: Part,
    count: usize,
    names: &[&str],
) -> Result<Vec<Subject>, crate::SynthError> {
    let list: &[(&str, Kind)] = match part {
        Part::Development => &[
            ("generic pig", Kind::Pig),
            ("koala", Kind::Pig),
            ("generic body", Kind::Body),
            ("human", Kind::Body),
            ("booth man", Kind::Body),
        ],
        Part::Validation => &[
            ("cow", Kind::Pig),
            ("woman", Kind::Body),
            ("booth woman", Kind::Body),
        ],
    };
    let mut out = Vec::new();
    for (k, &(name, kind)) in list.iter().enumerate() {
        if !names.is_empty() && !names.iter().any(|n| name.contains(n)) {
            continue;
        }
        let fig = template::build(kind, 10_000);
        let named = fig.landmark_vertices();
        let seed = 500 + 100 * k as u64 + if part == Part::Validation { 50 } else { 0 };
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let postures = if name.starts_with("generic ") {
            generic_postures(kind, &named, count, seed, &mut rng)?
        } else {
            outside_postures(name, &named, count, seed, &mut rng)?
        };
        out.push(Subject {
            name: name.to_string(),
            part,
            kind,
            template: fig,
            postures,
        });
    }
    Ok(out)
}

/// Another individual of the template's family (other proportions, another
/// triangulation) in `count` random postures, each turned and stood on the floor, scanned.
fn generic_postures(
    kind: Kind,
    named: &BTreeMap<String, u32>,
    count: usize,
    seed: u64,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Posture>, crate::SynthError> {
    let other = template::build(kind, 8_000);
    let shape: BTreeMap<String, f64> = match kind {
        Kind::Pig => [
            ("length", 1.12),
            ("girth", 1.15),
            ("leg_length", 0.9),
            ("head_size", 1.1),
        ],
        Kind::Body => [
            ("height", 0.95),
            ("girth", 1.18),
            ("arm_length", 1.05),
            ("shoulders", 1.1),
        ],
    }
    .iter()
    .map(|(n, f)| (n.to_string(), *f))
    .collect();
    let marks: Vec<(String, u32)> = other.landmark_vertices().into_iter().collect();
    let mut postures = Vec::new();
    for (i, pose) in template::random_postures(kind, count, 20.0, seed)
        .iter()
        .enumerate()
    {
        let mut subject = template::subject(&other, kind, &shape, pose)?;
        let heading = rng.random_range(-15.0..15.0);
        turned(&mut subject.vertices, heading);
        grounded(&mut subject.vertices);
        postures.push(scanned(
            &subject,
            named,
            &marks,
            V3::new(heading.to_radians().cos(), heading.to_radians().sin(), 0.0),
            seed + i as u64,
        ));
    }
    Ok(postures)
}

/// An outside subject (`name`) posed part-way along its limbs as it moves in a crate or a
/// booth; or (`booth ...`) standing as a booth's people stand, the arms turned at the
/// shoulders; each turned and stood on the floor, scanned.
fn outside_postures(
    name: &str,
    named: &BTreeMap<String, u32>,
    count: usize,
    seed: u64,
    rng: &mut ChaCha8Rng,
) -> Result<Vec<Posture>, crate::SynthError> {
    let booth = name.strip_prefix("booth ");
    let mesh_name = match booth {
        Some("man") => "human",
        Some(person) => person,
        None => name,
    };
    let subject = devset::load(mesh_name)?;
    let marks = crate::semantic::marks_of(mesh_name)?;
    let rest_front = crate::semantic::rest_front(&subject, &marks)
        .ok_or_else(|| crate::SynthError::NoFront(name.to_string()))?;
    let poses: Vec<Vec<V3>> = if booth.is_some() {
        posing::stand(&subject, rest_front, &posing::Stance::ALL)?
    } else {
        let nb = topology::vertex_neighbours(subject.vertices.len(), &subject.triangles);
        let ext = posing::extremities(&subject, &nb, 8);
        (0..count)
            .map(|i| {
                // the subject's size kept (the same subject)
                let settings = PoseSettings {
                    limbs: 8,
                    limb_degrees: (5.0, 25.0),
                    bend: 10.0,
                    twist: 8.0,
                    scale: 1.0,
                    seed: seed + i as u64,
                };
                posing::pose(&subject, &nb, &ext, &settings)
            })
            .collect()
    };
    let mut postures = Vec::new();
    for (i, mut x) in poses.into_iter().enumerate() {
        let heading = rng.random_range(-15.0..15.0);
        turned(&mut x, heading);
        grounded(&mut x);
        let rot = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), heading.to_radians());
        let posed = Mesh::new(x, subject.triangles.clone());
        postures.push(scanned(
            &posed,
            named,
            &marks,
            rot * rest_front,
            seed + i as u64,
        ));
    }
    Ok(postures)
}

fn scanned(
    posed: &Mesh,
    template: &BTreeMap<String, u32>,
    marks: &[(String, u32)],
    front: V3,
    seed: u64,
) -> Posture {
    let (scan, _) = conformd::synth::cases::scan_subject(
        posed,
        &[0.0, 90.0, 180.0, 270.0],
        60_000,
        0.002,
        seed,
    );
    let (template_landmarks, scan_landmarks) = landmark_pairs(template, marks, &posed.vertices);
    Posture {
        scan,
        template_landmarks,
        scan_landmarks,
        front,
    }
}
