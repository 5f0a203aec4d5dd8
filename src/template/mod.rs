//! Generic templates: a pig and a human body, built procedurally from articulated
//! skeletons, with named landmarks at anatomical places and named vertex groups. Both pose
//! (`swing=12,nod=-8,...`, degrees per joint group) and reshape (`length=1.1,girth=0.95`)
//! with the vertex order unchanged, so a posed or reshaped subject is its own ground truth.

pub mod figure;
pub mod rig;

use crate::mesh::{FileError, Landmark, Mesh, V3};
use figure::{Figure, Pose, Skeleton};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// What is wrong with a template's description, its parameters or a result given to it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TemplateError {
    #[error("unknown template '{0}' (expected 'pig' or 'body')")]
    UnknownKind(String),
    #[error("template '{0}' is neither pig, body nor an existing mesh file")]
    NotATemplate(String),
    #[error(
        "the generic {0} template brings its own groups; --template-groups is for a template mesh file"
    )]
    GroupsOfGeneric(String),
    #[error("vertices = {0}: a generic template has {min} to {max} vertices", min = VERTICES.start(), max = VERTICES.end())]
    Vertices(usize),
    #[error("a generic template brings its own landmarks, groups and rig")]
    GenericBringsItsOwn,
    #[error("vertices is for a generic template, not a mesh file")]
    VerticesOfMesh,
    #[error("needs either generic = \"pig\" or \"body\", or mesh = \"FILE\" (not both)")]
    NeitherOrBoth,
    #[error("{what} '{part}': expected name=value")]
    NotNameValue { what: String, part: String },
    #[error("unknown {what} parameter '{name}' (known: {known})")]
    UnknownParameter {
        what: String,
        name: String,
        known: String,
    },
    #[error("{what} '{name}': '{value}' is not a number")]
    NotANumber {
        what: String,
        name: String,
        value: String,
    },
    #[error("{what} '{name}' = {value}: must be {min} to {max}")]
    OutOfRange {
        what: String,
        name: String,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error("the mesh has {got} vertices, the template {expected}: not a result of this template")]
    VertexCount { got: usize, expected: usize },
}

/// Where a station's template comes from: a generic one (`pig`, `body`) built at a
/// resolution, or any user mesh with its landmark file and optional groups file (the
/// paper: "one of the 3D shape samples can serve as a generic mesh directly").
/// In a station file: `[template]` with `generic = "pig"` and `vertices = 10000`, or
/// `mesh = "..."`, `landmarks = "..."`, `groups = "..."` and `rig = "..."` (the
/// template's bones, skin weights and shape fields, `rig::TemplateRig`; without one a
/// mesh is rigged automatically).
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TemplateSource {
    pub generic: Option<Kind>,
    pub vertices: Option<usize>,
    pub mesh: Option<PathBuf>,
    pub landmarks: Option<PathBuf>,
    pub groups: Option<PathBuf>,
    pub rig: Option<PathBuf>,
}

/// Fewest and most vertices of a generic template.
pub const VERTICES: std::ops::RangeInclusive<usize> = 500..=200_000;

impl TemplateSource {
    /// A generic template at its default resolution.
    pub fn generic(kind: Kind) -> TemplateSource {
        TemplateSource {
            generic: Some(kind),
            ..Default::default()
        }
    }

    /// What a user names on the command line: `pig` or `body` (when no such file exists),
    /// else an existing mesh file.
    pub fn named(name: &str, groups: Option<PathBuf>) -> Result<TemplateSource, TemplateError> {
        match name.parse::<Kind>() {
            Ok(_) if !Path::new(name).exists() && groups.is_some() => {
                Err(TemplateError::GroupsOfGeneric(name.into()))
            }
            Ok(kind) if !Path::new(name).exists() => Ok(TemplateSource::generic(kind)),
            _ if Path::new(name).exists() => Ok(TemplateSource {
                mesh: Some(name.into()),
                groups,
                ..Default::default()
            }),
            _ => Err(TemplateError::NotATemplate(name.into())),
        }
    }

    /// Exactly one of a generic template or a mesh; a resolution only for a generic one.
    pub fn check(&self) -> Result<(), TemplateError> {
        match (&self.generic, &self.mesh) {
            (Some(_), None) => {
                if let Some(v) = self.vertices.filter(|v| !VERTICES.contains(v)) {
                    return Err(TemplateError::Vertices(v));
                }
                if self.landmarks.is_some() || self.groups.is_some() || self.rig.is_some() {
                    return Err(TemplateError::GenericBringsItsOwn);
                }
                Ok(())
            }
            (None, Some(_)) if self.vertices.is_some() => Err(TemplateError::VerticesOfMesh),
            (None, Some(_)) => Ok(()),
            _ => Err(TemplateError::NeitherOrBoth),
        }
    }

    /// Makes relative paths absolute against `base` (a config file's folder).
    pub fn resolve(&mut self, base: &Path) {
        for p in [
            &mut self.mesh,
            &mut self.landmarks,
            &mut self.groups,
            &mut self.rig,
        ]
        .into_iter()
        .flatten()
        {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
    }

    /// A generic template's figure (mesh, skeleton, skin weights) with its kind; `None`
    /// for a template mesh.
    pub fn figure(&self) -> Result<Option<(Kind, Figure)>, FileError> {
        self.figure_cached(None)
    }

    /// [`TemplateSource::figure`], kept in the folder `cache` between processes: built
    /// once per build of this program and resolution, read back to the bit after (a
    /// worker process then starts 0.1 s sooner). A cache that cannot be read or written
    /// is only warned about: the figure is built as without one.
    pub fn figure_cached(&self, cache: Option<&Path>) -> Result<Option<(Kind, Figure)>, FileError> {
        self.check()
            .map_err(|e| FileError::content("[template]", e.to_string()))?;
        let Some(kind) = self.generic else {
            return Ok(None);
        };
        let vertices = self.vertices.unwrap_or(10_000);
        let Some(dir) = cache else {
            return Ok(Some((kind, build(kind, vertices))));
        };
        let stem = format!("{}-{vertices}-", format!("{kind:?}").to_lowercase());
        let path = dir.join(format!("{stem}{:016x}.figure", program_fingerprint()));
        match std::fs::read(&path) {
            Ok(bytes) => match Figure::from_bytes(&skeleton(kind), &bytes) {
                Ok(fig) => return Ok(Some((kind, fig))),
                Err(e) => tracing::warn!("{}: {e}; the template is built again", path.display()),
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => tracing::warn!("{}: {e}; the template is built again", path.display()),
        }
        let fig = build(kind, vertices);
        let stored = std::fs::create_dir_all(dir)
            .map_err(|e| e.to_string())
            .and_then(|_| {
                crate::files::write_atomic(&path, &fig.to_bytes()).map_err(|e| e.to_string())
            });
        match stored {
            // the same template of earlier builds of the program will not be read again
            Ok(()) => {
                for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
                    let name = e.file_name().to_string_lossy().to_string();
                    if name.starts_with(&stem) && name.ends_with(".figure") && e.path() != path {
                        let _ = std::fs::remove_file(e.path());
                    }
                }
            }
            Err(e) => tracing::warn!("{}: {e}; the template is not cached", path.display()),
        }
        Ok(Some((kind, fig)))
    }

    /// The template mesh (with groups) and its landmarks, if it has any.
    pub fn load(&self) -> Result<(Mesh, Option<Vec<Landmark>>), FileError> {
        if let Some((_, fig)) = self.figure()? {
            let lms = fig.landmarks();
            return Ok((fig.mesh, Some(lms)));
        }
        match (&self.generic, &self.mesh) {
            (None, Some(path)) => {
                let mut m = crate::mesh::read_mesh(path)?;
                if let Some(g) = &self.groups {
                    crate::mesh::groups::read_into(g, &mut m)?;
                }
                let lms = self
                    .landmarks
                    .as_ref()
                    .map(|p| crate::mesh::read_landmarks(p))
                    .transpose()?;
                Ok((m, lms))
            }
            _ => unreachable!("checked: a generic template returned above"),
        }
    }
}

impl TemplateSource {
    /// The named rig file, read and checked against `mesh` (a bad one is an error at
    /// start-up, not at the first capture); `None` without one. A generic template's own
    /// rig comes from [`TemplateSource::load_rigged`].
    pub fn rig_file(&self, mesh: &Mesh) -> Result<Option<rig::TemplateRig>, FileError> {
        self.rig
            .as_ref()
            .map(|path| rig::TemplateRig::read(path, mesh.vertices.len()))
            .transpose()
    }

    /// [`TemplateSource::load`] with the rig the fit uses: a generic template's own
    /// (its figure built once), or the named rig file. A mesh without a rig file is
    /// fitted without one (the automatic rig is not yet measured in the fit).
    #[allow(clippy::type_complexity)]
    pub fn load_rigged(
        &self,
    ) -> Result<(Mesh, Option<Vec<Landmark>>, Option<rig::TemplateRig>), FileError> {
        if let Some((kind, fig)) = self.figure()? {
            let rig = rig::TemplateRig::generic(&fig, kind);
            let lms = fig.landmarks();
            return Ok((fig.mesh, Some(lms), Some(rig)));
        }
        let (mesh, lms) = self.load()?;
        let rig = self.rig_file(&mesh)?;
        Ok((mesh, lms, rig))
    }
}

/// This program's build: its version and its executable's size and time (a rebuilt
/// binary is another program, whose templates may differ).
fn program_fingerprint() -> u64 {
    use std::hash::{Hash, Hasher};
    let mut h = std::hash::DefaultHasher::new();
    env!("CARGO_PKG_VERSION").hash(&mut h);
    if let Ok(m) = std::env::current_exe().and_then(std::fs::metadata) {
        m.len().hash(&mut h);
        m.modified().ok().hash(&mut h);
    }
    h.finish()
}

/// Which generic template.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    Pig,
    Body,
}

impl std::str::FromStr for Kind {
    type Err = TemplateError;
    fn from_str(s: &str) -> Result<Self, TemplateError> {
        match s {
            "pig" => Ok(Kind::Pig),
            "body" => Ok(Kind::Body),
            _ => Err(TemplateError::UnknownKind(s.into())),
        }
    }
}

/// A pig standing in a crate, facing +x, z up, about 1.6 units long (metres).
pub fn pig() -> Skeleton {
    let mut s = Skeleton {
        bones: vec![],
        blend: 0.04,
        landmarks: vec![],
    };
    let v = V3::new;
    s.add(
        "rump",
        None,
        v(-0.45, 0., 0.55),
        v(-0.05, 0., 0.56),
        (0.20, 0.22),
        "torso",
    );
    s.add(
        "chest",
        Some("rump"),
        v(-0.05, 0., 0.56),
        v(0.33, 0., 0.55),
        (0.22, 0.19),
        "torso",
    );
    s.add(
        "neck",
        Some("chest"),
        v(0.33, 0., 0.56),
        v(0.48, 0., 0.56),
        (0.15, 0.13),
        "head",
    );
    s.add(
        "head",
        Some("neck"),
        v(0.48, 0., 0.56),
        v(0.66, 0., 0.51),
        (0.12, 0.09),
        "head",
    );
    s.add(
        "snout",
        Some("head"),
        v(0.66, 0., 0.51),
        v(0.80, 0., 0.47),
        (0.07, 0.06),
        "snout",
    );
    s.add(
        "tail",
        Some("rump"),
        v(-0.62, 0., 0.60),
        v(-0.73, 0., 0.50),
        (0.03, 0.02),
        "tail",
    );
    for (side, y) in [("l", 1.0), ("r", -1.0)] {
        let n = |b: &str| format!("{b}_{side}");
        s.add(
            &n("ear"),
            Some("head"),
            v(0.56, 0.07 * y, 0.64),
            v(0.60, 0.15 * y, 0.74),
            (0.04, 0.025),
            "ears",
        );
        for (leg, x) in [("f", 0.26), ("h", -0.36)] {
            let parent = if leg == "f" { "chest" } else { "rump" };
            let up = format!("leg_{leg}{side}");
            let low = format!("shank_{leg}{side}");
            let hoof = format!("hoof_{leg}{side}");
            s.add(
                &up,
                Some(parent),
                v(x, 0.11 * y, 0.46),
                v(x + 0.02, 0.11 * y, 0.24),
                (0.075, 0.05),
                "legs",
            );
            s.add(
                &low,
                Some(&up),
                v(x + 0.02, 0.11 * y, 0.24),
                v(x, 0.11 * y, 0.07),
                (0.05, 0.04),
                "legs",
            );
            s.add(
                &hoof,
                Some(&low),
                v(x, 0.11 * y, 0.07),
                v(x + 0.04, 0.11 * y, 0.03),
                (0.042, 0.035),
                "hooves",
            );
            s.landmarks
                .push((format!("hoof_{leg}{side}"), v(x + 0.07, 0.11 * y, 0.02)));
        }
        s.landmarks.extend([
            (n("ear_tip"), v(0.61, 0.17 * y, 0.77)),
            (n("shoulder"), v(0.24, 0.22 * y, 0.50)),
            (n("hip"), v(-0.36, 0.23 * y, 0.52)),
            (n("eye"), v(0.62, 0.08 * y, 0.58)),
        ]);
    }
    s.landmarks.extend([
        ("snout_tip".into(), v(0.87, 0., 0.47)),
        ("tail_base".into(), v(-0.64, 0., 0.64)),
        ("withers".into(), v(0.25, 0., 0.75)),
        ("rump_top".into(), v(-0.40, 0., 0.77)),
        ("belly".into(), v(0.05, 0., 0.33)),
        ("chin".into(), v(0.70, 0., 0.40)),
    ]);
    s
}

/// A standing human body, facing +x, z up, about 1.8 units tall (metres): the figure of
/// `figure::humanoid` with wrists and ankles marked too.
pub fn body() -> Skeleton {
    let mut s = figure::humanoid();
    for (side, y) in [("l", 1.0), ("r", -1.0)] {
        s.landmarks.extend([
            (
                format!("wrist_{side}"),
                V3::new(0.07, 0.58 * y, 1.06 - 0.04),
            ),
            (
                format!("ankle_{side}"),
                V3::new(0.0, (0.12 + 0.045) * y, 0.09),
            ),
        ]);
    }
    s
}

pub fn skeleton(kind: Kind) -> Skeleton {
    match kind {
        Kind::Pig => pig(),
        Kind::Body => body(),
    }
}

/// Builds a template of about `vertices` vertices (2,000 to 100,000).
pub fn build(kind: Kind, vertices: usize) -> Figure {
    figure::build(&skeleton(kind), vertices.clamp(500, 200_000))
}

/// The pose parameters a template understands: name -> (bone, axis, sign). A parameter
/// of d degrees rotates the bone about its joint by sign * d around the axis.
pub fn pose_parameters(kind: Kind) -> Vec<(&'static str, &'static str, V3, f64)> {
    let (x, y, z) = (V3::x(), V3::y(), V3::z());
    match kind {
        Kind::Pig => vec![
            ("swing", "chest", z, 1.0),
            ("nod", "neck", y, 1.0),
            ("twist", "chest", x, 1.0),
            ("head_turn", "neck", z, 1.0),
            ("tail", "tail", y, 1.0),
            ("leg_fl", "leg_fl", y, 1.0),
            ("leg_fr", "leg_fr", y, 1.0),
            ("leg_hl", "leg_hl", y, 1.0),
            ("leg_hr", "leg_hr", y, 1.0),
            ("ear_l", "ear_l", x, 1.0),
            ("ear_r", "ear_r", x, -1.0),
        ],
        Kind::Body => vec![
            ("head_turn", "neck", z, 1.0),
            ("nod", "neck", y, 1.0),
            ("twist", "chest", z, 1.0),
            ("bend", "chest", y, 1.0),
            ("arm_l", "upper_arm_l", x, 1.0),
            ("arm_r", "upper_arm_r", x, -1.0),
            ("elbow_l", "forearm_l", y, -1.0),
            ("elbow_r", "forearm_r", y, -1.0),
            ("hip_l", "thigh_l", y, -1.0),
            ("hip_r", "thigh_r", y, -1.0),
            ("knee_l", "shin_l", y, 1.0),
            ("knee_r", "shin_r", y, 1.0),
        ],
    }
}

/// Shape parameters: name and what they change.
pub fn shape_parameters(kind: Kind) -> Vec<&'static str> {
    match kind {
        Kind::Pig => vec!["length", "girth", "leg_length", "head_size"],
        Kind::Body => vec!["height", "girth", "arm_length", "leg_length", "shoulders"],
    }
}

/// Shape factors a generic template takes without folding.
pub const SHAPE_FACTORS: std::ops::RangeInclusive<f64> = 0.7..=1.4;
/// Pose angles (degrees per joint group) a generic template takes without folding.
pub const POSE_DEGREES: std::ops::RangeInclusive<f64> = -45.0..=45.0;

/// Parses `name=value,name=value` (the CLI's `--pose` and `--shape`); shape factors must
/// lie in [`SHAPE_FACTORS`], pose angles in [`POSE_DEGREES`].
pub fn parse_parameters(
    text: &str,
    known: &[&str],
    what: &str,
) -> Result<BTreeMap<String, f64>, TemplateError> {
    let mut out = BTreeMap::new();
    for part in text.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let (k, v) = part
            .split_once('=')
            .ok_or_else(|| TemplateError::NotNameValue {
                what: what.into(),
                part: part.into(),
            })?;
        let (k, v) = (k.trim(), v.trim());
        if !known.contains(&k) {
            return Err(TemplateError::UnknownParameter {
                what: what.into(),
                name: k.into(),
                known: known.join(", "),
            });
        }
        let x: f64 = v
            .parse()
            .ok()
            .filter(|x: &f64| x.is_finite())
            .ok_or_else(|| TemplateError::NotANumber {
                what: what.into(),
                name: k.into(),
                value: v.into(),
            })?;
        // beyond these a generic template folds over itself
        let range = match what {
            "shape" => SHAPE_FACTORS,
            _ => POSE_DEGREES,
        };
        if !range.contains(&x) {
            return Err(TemplateError::OutOfRange {
                what: what.into(),
                name: k.into(),
                value: x,
                min: *range.start(),
                max: *range.end(),
            });
        }
        out.insert(k.to_string(), x);
    }
    Ok(out)
}

/// A pose from named parameters (degrees).
pub fn pose(kind: Kind, params: &BTreeMap<String, f64>) -> Pose {
    let table = pose_parameters(kind);
    let joints = params
        .iter()
        .filter_map(|(k, &deg)| {
            table
                .iter()
                .find(|t| t.0 == k)
                .map(|&(_, bone, axis, sign)| (bone.to_string(), axis, sign * deg))
        })
        .collect();
    Pose {
        joints,
        scale: 1.0,
        ..Default::default()
    }
}

/// The displacement field of one shape parameter: #V vectors; `rest + (p - 1) * field`
/// is the template with that parameter at factor p. Fields are linear in the parameter,
/// so a population of reshaped templates spans exactly their span.
pub fn shape_field(fig: &Figure, kind: Kind, name: &str) -> Option<Vec<V3>> {
    let bones = &fig.skeleton.bones;
    let v = &fig.mesh.vertices;
    let (lo, hi) = fig.mesh.bounding_box()?;
    let centre = (lo + hi) / 2.0;
    // offset of each vertex from the axis of bone b, and its position along it (0..1)
    let axis = |b: usize, p: &V3| {
        let (a, t) = (bones[b].head, bones[b].tail);
        let ab = t - a;
        let s = ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
        (p - (a + ab * s), s, ab)
    };
    let of_group = |i: usize, groups: &[&str]| -> f64 {
        fig.weights[i]
            .iter()
            .filter(|(b, _)| groups.contains(&bones[*b as usize].group.as_str()))
            .map(|x| x.1)
            .sum()
    };
    let by_bones = |i: usize, names: &[&str], f: &dyn Fn(usize) -> V3| -> V3 {
        fig.weights[i]
            .iter()
            .filter(|(b, _)| names.iter().any(|n| bones[*b as usize].name.starts_with(n)))
            .map(|&(b, w)| f(b as usize) * w)
            .sum()
    };
    let field: Vec<V3> = (0..v.len())
        .map(|i| {
            let p = v[i];
            match (kind, name) {
                (Kind::Pig, "length") => V3::new(p.x - centre.x, 0.0, 0.0),
                (Kind::Body, "height") => V3::new(0.0, 0.0, p.z - lo.z),
                (_, "girth") => by_bones(i, &["rump", "chest", "pelvis"], &|b| axis(b, &p).0),
                // longer legs: everything above the hip joints rises, the legs stretch
                (Kind::Pig, "leg_length") => V3::new(0.0, 0.0, p.z.min(0.46) - 0.03),
                (Kind::Body, "leg_length") => V3::new(0.0, 0.0, p.z.min(0.90)),
                (Kind::Pig, "head_size") => by_bones(i, &["head", "snout", "neck"], &|b| {
                    let (off, _, _) = axis(b, &p);
                    off + (p - bones[b].head) * 0.3
                }),
                (Kind::Body, "arm_length") => {
                    by_bones(i, &["upper_arm", "forearm", "hand"], &|_| {
                        let shoulder = V3::new(0.0, 0.22 * p.y.signum(), 1.36);
                        (p - shoulder) * 0.5
                    })
                }
                // broader shoulders: the upper torso widens (not the head) and the arms
                // move out with it
                (Kind::Body, "shoulders") => {
                    let torso = of_group(i, &["torso"]);
                    let arms = of_group(i, &["arms", "hands"]);
                    let rise = ((p.z - 1.1) / 0.3).clamp(0.0, 1.0);
                    V3::new(0.0, p.y * rise * torso + 0.2 * p.y.signum() * arms, 0.0)
                }
                _ => return None,
            }
            .into()
        })
        .collect::<Option<Vec<V3>>>()?;
    Some(field)
}

/// Rest positions reshaped by named factors (1 = unchanged).
pub fn reshape(
    fig: &Figure,
    kind: Kind,
    factors: &BTreeMap<String, f64>,
) -> Result<Vec<V3>, TemplateError> {
    let mut out = fig.mesh.vertices.clone();
    for (name, &f) in factors {
        let field =
            shape_field(fig, kind, name).ok_or_else(|| TemplateError::UnknownParameter {
                what: "shape".into(),
                name: name.clone(),
                known: shape_parameters(kind).join(", "),
            })?;
        for (o, d) in out.iter_mut().zip(field) {
            *o += d * (f - 1.0);
        }
    }
    Ok(out)
}

/// A template reshaped, then posed: a subject with the template's vertex order.
pub fn subject(
    fig: &Figure,
    kind: Kind,
    shape: &BTreeMap<String, f64>,
    pose: &Pose,
) -> Result<Mesh, TemplateError> {
    let mut reshaped = fig.clone();
    reshaped.mesh.vertices = reshape(fig, kind, shape)?;
    let mut m = fig.mesh.clone();
    m.vertices = reshaped.pose(pose);
    Ok(m)
}

/// `n` postures of a generic template, every pose parameter drawn uniformly within
/// +/- `degrees` (seeded: the same call gives the same postures). What a posture model
/// of the template is built from (`conformd model posture`).
pub fn random_postures(kind: Kind, n: usize, degrees: f64, seed: u64) -> Vec<Pose> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let names: Vec<&str> = pose_parameters(kind).iter().map(|p| p.0).collect();
    (0..n)
        .map(|_| {
            let params: BTreeMap<String, f64> = names
                .iter()
                .map(|&k| (k.to_string(), rng.random_range(-degrees..=degrees)))
                .collect();
            pose(kind, &params)
        })
        .collect()
}

/// The posture of a result of a generic template: the pose parameters (degrees) and the
/// rigid placement that best explain its vertices, and what is left unexplained (RMS).
#[derive(Debug, Clone)]
pub struct PostureFit {
    pub params: BTreeMap<String, f64>,
    pub placement: crate::mesh::transform::Similarity,
    pub rms: f64,
}

/// Fits the pose parameters of `kind` (Gauss-Newton over the joint angles, the rigid
/// placement refitted in closed form at every step) to `x`, a result of `fig` in any
/// place. Angles stay within [`POSE_DEGREES`].
pub fn fit_posture(fig: &Figure, kind: Kind, x: &[V3]) -> PostureFit {
    use crate::mesh::transform::fit_similarity;
    let names: Vec<&str> = pose_parameters(kind).iter().map(|p| p.0).collect();
    let k = names.len();
    let at = |theta: &[f64]| -> Vec<V3> {
        let params: BTreeMap<String, f64> = names
            .iter()
            .zip(theta)
            .map(|(n, &d)| (n.to_string(), d))
            .collect();
        fig.pose(&pose(kind, &params))
    };
    let mut theta = vec![0.0; k];
    let mut placement = Default::default();
    let mut rms = f64::INFINITY;
    for _ in 0..20 {
        let p = at(&theta);
        placement = fit_similarity(&p, x, None, false);
        let inv = placement.inverse();
        let y: Vec<V3> = x.iter().map(|q| inv.apply(q)).collect();
        let r: Vec<V3> = p.iter().zip(&y).map(|(a, b)| a - b).collect();
        rms = (r.iter().map(|v| v.norm_squared()).sum::<f64>() / r.len() as f64).sqrt();
        // numeric Jacobian columns, half a degree apart
        let h = 0.5;
        let cols: Vec<Vec<V3>> = (0..k)
            .map(|j| {
                let mut t = theta.clone();
                t[j] += h;
                at(&t).iter().zip(&p).map(|(a, b)| (a - b) / h).collect()
            })
            .collect();
        let mut jtj = nalgebra::DMatrix::<f64>::zeros(k, k);
        let mut jtr = nalgebra::DVector::<f64>::zeros(k);
        for a in 0..k {
            for b in a..k {
                let v: f64 = cols[a].iter().zip(&cols[b]).map(|(u, w)| u.dot(w)).sum();
                jtj[(a, b)] = v;
                jtj[(b, a)] = v;
            }
            jtr[a] = cols[a].iter().zip(&r).map(|(u, w)| u.dot(w)).sum();
        }
        // a little damping keeps parameters the shape cannot see (a hidden tail) still
        let damping = 1e-6 * (0..k).map(|i| jtj[(i, i)]).fold(0.0, f64::max);
        for i in 0..k {
            jtj[(i, i)] += damping;
        }
        let Some(step) = jtj.cholesky().map(|c| c.solve(&(-jtr))) else {
            break;
        };
        for (t, s) in theta.iter_mut().zip(step.iter()) {
            *t = (*t + s).clamp(*POSE_DEGREES.start(), *POSE_DEGREES.end());
        }
        if step.amax() < 0.01 {
            break;
        }
    }
    PostureFit {
        params: names
            .iter()
            .zip(&theta)
            .map(|(n, &d)| (n.to_string(), d))
            .collect(),
        placement,
        rms,
    }
}

/// A result of generic template `fig` with its posture removed: its pose fitted
/// ([`fit_posture`]) and taken out joint by joint, then put back where it stood. Its
/// shape (and size) stay.
pub fn remove_posture(
    fig: &Figure,
    kind: Kind,
    mesh: &Mesh,
) -> Result<(Mesh, PostureFit), TemplateError> {
    if mesh.vertices.len() != fig.mesh.vertices.len() {
        return Err(TemplateError::VertexCount {
            got: mesh.vertices.len(),
            expected: fig.mesh.vertices.len(),
        });
    }
    let fit = fit_posture(fig, kind, &mesh.vertices);
    let inv = fit.placement.inverse();
    let local: Vec<V3> = mesh.vertices.iter().map(|q| inv.apply(q)).collect();
    let rest = fig.unpose(&pose(kind, &fit.params), &local);
    let mut out = mesh.clone();
    out.vertices = rest.iter().map(|q| fit.placement.apply(q)).collect();
    Ok((out, fit))
}
