//! The station's real case as a development case: conformd's generic pig or body
//! template conformed without landmarks onto an outside animal or person (another shape,
//! another triangulation, no vertex correspondence), scored by semantic landmarks marked
//! on both: the template's own named landmarks, and the same points marked on the outside
//! mesh (`tests/data/meshes/*.marks`, how they were placed in `tests/data/README.md`).

use crate::SynthError;
use crate::devset::{self, DevCaseSpec, Part, large_posture, posed};
use conformd::mesh::landmarks::{self, LandmarkPos};
use conformd::mesh::{Mesh, V3};
use conformd::template::{self, Kind};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// One semantic landmark: the template vertex its name is on, and where it truly is on
/// the posed subject.
pub struct Mark {
    pub name: String,
    pub vertex: u32,
    pub truth: V3,
}

pub struct SemanticCase {
    pub name: String,
    /// which generic template, and its rig
    pub kind: Kind,
    pub rig: conformd::template::rig::TemplateRig,
    pub template: Mesh,
    pub scan: Mesh,
    pub marks: Vec<Mark>,
    /// the posed subject's bounding-box diagonal: errors are relative to it
    pub diag: f64,
    pub part: Part,
    /// the way the subject faces on the rig (level; its rest pose's front turned to its
    /// heading): what a station knows of its crate's head end or its booth's front camera
    pub front: V3,
}

/// Per-landmark distances (relative to the diagonal), their mean, and the limb ends
/// (hooves, hands, toes) that ended nearer another limb end's true place than their own.
pub struct SemanticScore {
    pub per_mark: Vec<(String, f64)>,
    pub mean: f64,
    pub max: f64,
    pub wrong_limb: Vec<String>,
}

impl SemanticCase {
    /// The conformation options of a station: `base` with the up axis known.
    pub fn options(
        &self,
        base: &conformd::conform::ConformOptions,
    ) -> conformd::conform::ConformOptions {
        let mut o = base.clone();
        o.align.template_up = Some([0.0, 0.0, 1.0]);
        o.align.scan_up = Some([0.0, 0.0, 1.0]);
        o
    }

    /// A station that also knows which way the subject faces (`[align] template_front`,
    /// `scan_front`; the generic templates face +x), to within the default 90 degrees.
    pub fn options_with_front(
        &self,
        base: &conformd::conform::ConformOptions,
    ) -> conformd::conform::ConformOptions {
        let mut o = self.options(base);
        o.align.template_front = Some([1.0, 0.0, 0.0]);
        o.align.scan_front = Some([self.front.x, self.front.y, self.front.z]);
        o
    }

    /// The station's conformation of the case: the template's rig fitted first
    /// (`conform_rigged`).
    pub fn conform(
        &self,
        opts: &conformd::conform::ConformOptions,
    ) -> Result<conformd::conform::Conformed, conformd::conform::ConformError> {
        let never = std::sync::atomic::AtomicBool::new(false);
        conformd::conform::conform_rigged(
            &self.template,
            Some(&self.rig),
            &self.scan,
            None,
            opts,
            &mut |_| {},
            &never,
        )
    }

    pub fn score(&self, result: &[V3]) -> SemanticScore {
        let per_mark: Vec<(String, f64)> = self
            .marks
            .iter()
            .map(|m| {
                let d = (result[m.vertex as usize] - m.truth).norm() / self.diag;
                (m.name.clone(), d)
            })
            .collect();
        let mean = per_mark.iter().map(|m| m.1).sum::<f64>() / per_mark.len().max(1) as f64;
        let max = per_mark.iter().map(|m| m.1).fold(0.0, f64::max);
        let ends: Vec<&Mark> = self.marks.iter().filter(|m| is_limb_end(&m.name)).collect();
        let wrong_limb = ends
            .iter()
            .filter(|m| {
                let p = result[m.vertex as usize];
                let own = (p - m.truth).norm();
                ends.iter()
                    .any(|o| o.name != m.name && (p - o.truth).norm() < own)
            })
            .map(|m| m.name.clone())
            .collect();
        SemanticScore {
            per_mark,
            mean,
            max,
            wrong_limb,
        }
    }
}

/// The way a subject faces in its rest pose, level (z up): from its heels to its toes
/// (a person's head may lean back), else from its centre to its snout.
pub fn rest_front(subject: &Mesh, marks: &[(String, u32)]) -> Option<V3> {
    let at = |prefix: &str| -> Option<V3> {
        let p: Vec<V3> = marks
            .iter()
            .filter(|(n, _)| n.starts_with(prefix))
            .filter_map(|(_, v)| subject.vertices.get(*v as usize).copied())
            .collect();
        (!p.is_empty()).then(|| p.iter().sum::<V3>() / p.len() as f64)
    };
    let f = match (at("toe_"), at("heel_"), at("snout_tip")) {
        (Some(t), Some(h), _) => t - h,
        (_, _, Some(s)) => {
            s - subject.vertices.iter().sum::<V3>() / subject.vertices.len().max(1) as f64
        }
        _ => return None,
    };
    let f = V3::new(f.x, f.y, 0.0);
    (f.norm() > 0.0).then(|| f.normalize())
}

/// The ends of limbs, one mark per limb: a hoof, a hand or a toe found on another limb is
/// a swapped part, not an imprecise fit.
fn is_limb_end(name: &str) -> bool {
    ["hoof_", "hand_tip_", "toe_"]
        .iter()
        .any(|p| name.starts_with(p))
}

/// The semantic marks of an outside mesh: `<file stem>.marks` beside it, `name vertex`
/// per line (the landmark text format).
pub fn marks_of(mesh_name: &str) -> Result<Vec<(String, u32)>, SynthError> {
    let stem = match mesh_name {
        // the woman is in the man's vertex order: the same vertices are the same points
        "human" | "woman" => "human",
        other => other,
    };
    let path = devset::data_dir().join(format!("{stem}.marks"));
    let bytes = conformd::files::read_limited(&path, conformd::files::MAX_TABLE_BYTES)?;
    landmarks::parse_text(&path.display().to_string(), &bytes)?
        .into_iter()
        .map(|l| match l.pos {
            LandmarkPos::Vertex(v) => Ok((l.name, v)),
            LandmarkPos::Point(_) => Err(SynthError::MarkNotVertex {
                file: path.display().to_string(),
                name: l.name,
            }),
        })
        .collect()
}

/// The generic templates onto outside subjects, posed twice (the development set's
/// posture and the harder set's large one), each to its own heading: the pig onto the
/// koala and onto Spot, the body onto the man (development), the pig onto the cow and
/// the body onto the woman (validation, never tuned on).
pub fn generic_cases(part: Part, names: &[&str]) -> Result<Vec<SemanticCase>, SynthError> {
    generic_cases_turned(part, names, 0.0)
}

/// The same cases with every subject turned `turn` degrees further about the vertical:
/// whether the fit finds the subject's heading wherever it faces (the bench's heading
/// sweep).
pub fn generic_cases_turned(
    part: Part,
    names: &[&str],
    turn: f64,
) -> Result<Vec<SemanticCase>, SynthError> {
    let subjects: &[(&str, Kind)] = match part {
        Part::Development => &[
            ("koala", Kind::Pig),
            ("human", Kind::Body),
            ("spot", Kind::Pig),
        ],
        Part::Validation => &[("cow", Kind::Pig), ("woman", Kind::Body)],
    };
    let mut out = Vec::new();
    for (k, &(subject_name, kind)) in subjects.iter().enumerate() {
        if !names.is_empty() && !names.contains(&subject_name) {
            continue;
        }
        let fig = template::build(kind, 10_000);
        let subject = devset::load(subject_name)?;
        let marks = marks_of(subject_name)?;
        let rest_front = rest_front(&subject, &marks)
            .ok_or_else(|| SynthError::NoFront(subject_name.to_string()))?;
        let seed = 40 + 10 * k as u64 + if part == Part::Validation { 100 } else { 0 };
        let postures = [
            (
                "posed",
                DevCaseSpec {
                    heading: 35.0,
                    seed: seed + 1,
                    pose: crate::posing::PoseSettings {
                        seed,
                        ..Default::default()
                    },
                    ..DevCaseSpec::default()
                },
            ),
            ("large posture", large_posture(seed + 2, -65.0)),
        ];
        for (what, mut spec) in postures {
            spec.heading += turn;
            let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
            let (truth, _) = posed(&subject, &spec, subject.diagonal(), &mut rng);
            let turned = if turn == 0.0 {
                String::new()
            } else {
                format!(", turned {turn}")
            };
            let subject = Subject {
                name: subject_name,
                mesh: &subject,
                marks: &marks,
                rest_front,
            };
            out.push(semantic_case(
                &subject,
                kind,
                &fig,
                truth,
                &spec,
                &format!("{what}{turned}"),
                part,
            )?);
        }
    }
    Ok(out)
}

/// An outside subject with its semantic marks and the way it faces at rest.
struct Subject<'a> {
    name: &'a str,
    mesh: &'a Mesh,
    marks: &'a [(String, u32)],
    rest_front: V3,
}

/// The case of the generic template `fig` onto `subject` posed as `truth` (its vertices,
/// already turned to `spec.heading`), scanned as `spec` says.
fn semantic_case(
    subject: &Subject,
    kind: Kind,
    fig: &template::figure::Figure,
    truth: Vec<V3>,
    spec: &DevCaseSpec,
    what: &str,
    part: Part,
) -> Result<SemanticCase, SynthError> {
    let named = fig.landmark_vertices();
    let posed_mesh = Mesh::new(truth.clone(), subject.mesh.triangles.clone());
    let (scan, _) = devset::scan_as_spec_says(&posed_mesh, spec);
    let marks: Vec<Mark> = subject
        .marks
        .iter()
        .map(|(name, v)| {
            let vertex = named
                .get(name)
                .copied()
                .ok_or_else(|| SynthError::TemplateLandmark(name.clone()))?;
            let truth = *truth
                .get(*v as usize)
                .ok_or_else(|| SynthError::MarkPastMesh {
                    subject: subject.name.to_string(),
                    name: name.clone(),
                    vertex: *v,
                })?;
            Ok(Mark {
                name: name.clone(),
                vertex,
                truth,
            })
        })
        .collect::<Result<_, SynthError>>()?;
    let front = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), spec.heading.to_radians())
        * subject.rest_front;
    Ok(SemanticCase {
        kind,
        rig: conformd::template::rig::TemplateRig::generic(fig, kind),
        name: format!(
            "generic {} onto {}, {what}",
            match kind {
                Kind::Pig => "pig",
                Kind::Body => "body",
            },
            subject.name
        ),
        template: fig.mesh.clone(),
        scan,
        marks,
        diag: posed_mesh.diagonal(),
        part,
        front,
    })
}

/// The generic body onto people in a booth's stances (`posing::Stance`: hands at the
/// belly, arms forward, arms raised; the arms turned at the shoulders, which the other
/// cases never do), each to its own heading: the man (development) and the woman
/// (validation).
pub fn booth_cases(part: Part) -> Result<Vec<SemanticCase>, SynthError> {
    let subject_name = match part {
        Part::Development => "human",
        Part::Validation => "woman",
    };
    let fig = template::build(Kind::Body, 10_000);
    let mesh = devset::load(subject_name)?;
    let marks = marks_of(subject_name)?;
    let rest_front =
        rest_front(&mesh, &marks).ok_or_else(|| SynthError::NoFront(subject_name.to_string()))?;
    let subject = Subject {
        name: subject_name,
        mesh: &mesh,
        marks: &marks,
        rest_front,
    };
    let base = if part == Part::Validation { 300 } else { 200 };
    let mut out = Vec::new();
    let stances = crate::posing::Stance::ALL;
    let posed = crate::posing::stand(&mesh, rest_front, &stances)?;
    for (k, ((stance, heading), mut truth)) in stances
        .into_iter()
        .zip([25.0, -110.0, 160.0])
        .zip(posed)
        .enumerate()
    {
        let spec = DevCaseSpec {
            heading,
            seed: base + k as u64,
            ..DevCaseSpec::default()
        };
        let c = truth.iter().sum::<V3>() / truth.len() as f64;
        let rot = nalgebra::Rotation3::from_axis_angle(&V3::z_axis(), heading.to_radians());
        for p in &mut truth {
            *p = c + rot * (*p - c);
        }
        out.push(semantic_case(
            &subject,
            Kind::Body,
            &fig,
            truth,
            &spec,
            stance.name(),
            part,
        )?);
    }
    Ok(out)
}
