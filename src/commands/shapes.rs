//! Template, preview and shape-model jobs.

use super::*;
use crate::conform;
use crate::mesh::topology;
use std::path::{Path, PathBuf};

/// What `template` wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TemplateSummary {
    pub mesh: PathBuf,
    pub landmarks: PathBuf,
    /// written for the rest template only (a posed or reshaped one is a subject)
    pub rig: Option<PathBuf>,
    pub bones: usize,
    pub vertices: usize,
    pub triangles: usize,
    pub groups: Vec<(String, usize)>,
    pub landmark_count: usize,
    pub watertight: bool,
}

/// Writes a generic pig or body template of about `vertices` vertices, optionally posed
/// (`swing=12,nod=-8`) and reshaped (`length=1.1`), and its landmark file beside it
/// (`<out without extension>.landmarks`), and for the rest template its rig
/// (`<out without extension>.rig.json`: bones, skin weights, shape fields). The vertex order does not depend on pose or
/// shape, so subjects made this way are their own ground truth.
pub fn template(
    kind: crate::template::Kind,
    vertices: usize,
    pose: &str,
    shape: &str,
    out: &Path,
) -> Result<TemplateSummary, CommandError> {
    use crate::template as templates;
    if !(500..=200_000).contains(&vertices) {
        return Err(CommandError::Usage(format!(
            "a generic template has 500 to 200000 vertices, not {vertices}"
        )));
    }
    let pose_names: Vec<&str> = templates::pose_parameters(kind)
        .iter()
        .map(|p| p.0)
        .collect();
    let pose_params = templates::parse_parameters(pose, &pose_names, "pose")?;
    let shape_names = templates::shape_parameters(kind);
    let shape_params = templates::parse_parameters(shape, &shape_names, "shape")?;
    let fig = templates::build(kind, vertices);
    let mut mesh = templates::subject(
        &fig,
        kind,
        &shape_params,
        &templates::pose(kind, &pose_params),
    )?;
    mesh.groups = fig.mesh.groups.clone();
    mesh::write_mesh(out, &mesh)?;
    let landmarks = out.with_extension("landmarks");
    let lms = fig.landmarks();
    write_atomic(&landmarks, mesh::landmarks::landmarks_text(&lms).as_bytes())?;
    // the rig describes the rest template: a posed or reshaped one is a subject (its own
    // truth), and a rig beside it would put its joints where its limbs are not
    let rig = templates::rig::TemplateRig::generic(&fig, kind);
    let rig_path =
        (pose_params.is_empty() && shape_params.is_empty()).then(|| out.with_extension("rig.json"));
    if let Some(p) = &rig_path {
        rig.write(p)?;
    }
    Ok(TemplateSummary {
        mesh: out.to_path_buf(),
        landmarks,
        rig: rig_path,
        bones: rig.bones.len(),
        vertices: mesh.vertices.len(),
        triangles: mesh.triangles.len(),
        groups: mesh
            .groups
            .iter()
            .map(|(k, v)| (k.clone(), v.len()))
            .collect(),
        landmark_count: lms.len(),
        watertight: topology::report(&mesh).watertight,
    })
}

/// How a preview is coloured.
#[derive(Debug, Clone)]
pub enum ColourBy {
    None,
    Group,
    /// distance of each vertex to this scan
    DistanceTo(PathBuf),
}

impl std::str::FromStr for ColourBy {
    type Err = UnknownColouring;
    fn from_str(s: &str) -> Result<Self, UnknownColouring> {
        match s {
            "none" => Ok(ColourBy::None),
            "group" => Ok(ColourBy::Group),
            _ => match s.strip_prefix("distance-to=") {
                Some(p) if !p.is_empty() => Ok(ColourBy::DistanceTo(PathBuf::from(p))),
                _ => Err(UnknownColouring(s.to_string())),
            },
        }
    }
}

/// A `--colour-by` value that is none of [`ColourBy`]'s.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("'{0}': expected none, group or distance-to=SCAN")]
pub struct UnknownColouring(pub String);

/// Renders a mesh to a PNG preview from the named views (`front`, `back`, `left`,
/// `right`/`side`, `top`, `three-quarter`).
pub fn render(
    mesh_path: &Path,
    colour: &ColourBy,
    views: &[String],
    width: u32,
    height: u32,
    out: &Path,
) -> Result<(), CommandError> {
    use crate::render::{self, Colouring, RenderOptions, View};
    if !(64..=8192).contains(&width) || !(64..=8192).contains(&height) {
        return Err(CommandError::Usage(format!(
            "image size {width}x{height}: each side must be 64 to 8192 pixels"
        )));
    }
    let m = mesh::read_mesh(mesh_path)?;
    if m.triangles.is_empty() {
        return Err(CommandError::Input {
            path: mesh_path.display().to_string(),
            msg: "a point cloud has no surface to render".into(),
        });
    }
    let views = views
        .iter()
        .map(|v| {
            View::named(v).ok_or_else(|| {
                CommandError::Usage(format!(
                    "unknown view '{v}' (front, back, left, right, side, top, three-quarter)"
                ))
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let colouring = match colour {
        ColourBy::None => Colouring::Plain,
        ColourBy::Group => Colouring::Groups,
        ColourBy::DistanceTo(scan) => {
            let s = mesh::read_mesh(scan)?;
            let surface =
                conform::correspond::ScanSurface::new(&s).map_err(|source| CommandError::Scan {
                    path: scan.display().to_string(),
                    source,
                })?;
            Colouring::distances(
                m.vertices.iter().map(|p| surface.distance(p)).collect(),
                "MESH UNITS",
            )
        }
    };
    let img = render::render(
        &m,
        &colouring,
        &RenderOptions {
            width,
            height,
            views,
            ..Default::default()
        },
    );
    render::save_png(&img, out)?;
    Ok(())
}

/// Builds a shape model from conformed meshes and writes it; with `quality` the model
/// quality figures for up to 10 modes are computed too (leave-one-out: one model build
/// per sample).
pub fn model_build(
    paths: &[PathBuf],
    opts: &crate::model::BuildOptions,
    out: &Path,
    quality: bool,
) -> Result<(crate::model::ShapeModel, Option<crate::model::Quality>), CommandError> {
    let samples = paths
        .iter()
        .map(|p| Ok((p.display().to_string(), mesh::read_mesh(p)?)))
        .collect::<Result<Vec<_>, CommandError>>()?;
    let model = crate::model::ShapeModel::build(&samples, opts)?;
    model.save(out)?;
    let q = if quality {
        Some(crate::model::quality(&samples, opts, 10, 1)?)
    } else {
        None
    };
    Ok((model, q))
}

/// Writes the mean and mean +/- `sigma` standard deviations along each of the first
/// `modes` modes as meshes, and a PNG sheet of them (rows: modes; columns: -, mean, +).
pub fn model_modes(
    model_path: &Path,
    modes: usize,
    sigma: f64,
    view: &str,
    out_dir: &Path,
) -> Result<Vec<PathBuf>, CommandError> {
    use crate::render::{self, Colouring, RenderOptions, View};
    if !(sigma > 0.0 && sigma <= 10.0) {
        return Err(CommandError::Usage(format!(
            "sigma = {sigma}: the modes are drawn at 0 to 10 standard deviations"
        )));
    }
    if !(1..=50).contains(&modes) {
        return Err(CommandError::Usage(format!("{modes} modes: draw 1 to 50")));
    }
    let model = crate::model::ShapeModel::load(model_path)?;
    std::fs::create_dir_all(out_dir).map_err(|source| CommandError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    let view =
        View::named(view).ok_or_else(|| CommandError::Usage(format!("unknown view '{view}'")))?;
    let k = modes.min(model.modes.len());
    let mut files = Vec::new();
    let mean = model.instance_mesh(&[]);
    let p = out_dir.join("mean.ply");
    mesh::write_mesh(&p, &mean)?;
    files.push(p);
    let opts = RenderOptions {
        width: 360,
        height: 270,
        views: vec![view],
        ..Default::default()
    };
    let mut cells = Vec::new();
    for m in 0..k {
        let sd = model.variances[m].sqrt();
        for (col, f) in [-sigma, 0.0, sigma].iter().enumerate() {
            let mut b = vec![0.0; m + 1];
            b[m] = f * sd;
            let inst = model.instance_mesh(&b);
            if col != 1 {
                let p = out_dir.join(format!(
                    "mode{}_{}{}sd.ply",
                    m + 1,
                    if *f < 0.0 { "minus" } else { "plus" },
                    sigma
                ));
                mesh::write_mesh(&p, &inst)?;
                files.push(p);
            }
            let label = match col {
                0 => format!("MODE {} -{}SD", m + 1, sigma),
                1 => format!("MEAN  MODE {}: {:.1}%", m + 1, model.explained[m] * 100.0),
                _ => format!("+{}SD", sigma),
            };
            cells.push((render::render(&inst, &Colouring::Plain, &opts), label));
        }
    }
    let p = out_dir.join("modes.png");
    render::save_png(&render::sheet(&cells, 3, [250, 250, 250]), &p)?;
    files.push(p);
    Ok(files)
}

/// Scores conformed meshes against a model.
pub fn model_score(
    model_path: &Path,
    paths: &[PathBuf],
) -> Result<Vec<crate::model::Score>, CommandError> {
    let model = crate::model::ShapeModel::load(model_path)?;
    paths
        .iter()
        .map(|p| {
            let m = mesh::read_mesh(p)?;
            Ok(model.score(&p.display().to_string(), &m)?)
        })
        .collect()
}

impl std::fmt::Display for TemplateSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} vertices, {} triangles, {} landmarks, {} bones, groups {}; watertight {}\nwrote {}\nwrote {}{}",
            self.vertices,
            self.triangles,
            self.landmark_count,
            self.bones,
            self.groups
                .iter()
                .map(|(g, n)| format!("{g} ({n})"))
                .collect::<Vec<_>>()
                .join(", "),
            self.watertight,
            self.mesh.display(),
            self.landmarks.display(),
            match &self.rig {
                Some(p) => format!("\nwrote {}", p.display()),
                None => "\nno rig: a posed or reshaped template is a subject".into(),
            }
        )
    }
}

/// One bone `autorig` made.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AutorigBone {
    pub name: String,
    pub parent: Option<String>,
    pub joint: [f64; 3],
    pub limit_deg: f64,
    /// vertices it moves most
    pub vertices: usize,
}

/// What `autorig` found and wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AutorigSummary {
    pub rig: PathBuf,
    pub preview: Option<PathBuf>,
    pub vertices: usize,
    pub bones: Vec<AutorigBone>,
    pub shapes: Vec<String>,
}

/// Rigs a template mesh automatically ([`crate::template::rig::TemplateRig::automatic`])
/// and writes the rig file, and a picture of the mesh coloured by bone when asked.
pub fn autorig(
    mesh_path: &Path,
    limbs: usize,
    out: &Path,
    preview: Option<&Path>,
) -> Result<AutorigSummary, CommandError> {
    use crate::template::rig::{AutoRigSettings, TemplateRig};
    if !(1..=32).contains(&limbs) {
        return Err(CommandError::Usage(format!(
            "--limbs {limbs}: between 1 and 32 extremities are tried"
        )));
    }
    let mesh = mesh::read_mesh(mesh_path)?;
    let name = mesh_path.display().to_string();
    mesh.validate(&name)?;
    let settings = AutoRigSettings {
        limbs,
        ..Default::default()
    };
    let rig = TemplateRig::automatic(&mesh, &settings)
        .map_err(|e| mesh::FileError::content(&name, e.to_string()))?;
    rig.write(out)?;
    let owner = rig.dominant_bones();
    let mut moved = vec![0usize; rig.bones.len()];
    for &b in &owner {
        moved[b as usize] += 1;
    }
    if let Some(p) = preview {
        rig_picture(&mesh, &rig, p)?;
    }
    Ok(AutorigSummary {
        rig: out.to_path_buf(),
        preview: preview.map(Path::to_path_buf),
        vertices: mesh.vertices.len(),
        bones: rig
            .bones
            .iter()
            .zip(&moved)
            .map(|(b, &n)| AutorigBone {
                name: b.name.clone(),
                parent: b.parent.map(|p| rig.bones[p].name.clone()),
                joint: [b.head.x, b.head.y, b.head.z],
                limit_deg: b.limit_deg,
                vertices: n,
            })
            .collect(),
        shapes: rig.shapes.iter().map(|s| s.name.clone()).collect(),
    })
}

/// The mesh coloured by the bone that moves each vertex most, from three sides.
fn rig_picture(
    mesh: &mesh::Mesh,
    rig: &crate::template::rig::TemplateRig,
    out: &Path,
) -> Result<(), CommandError> {
    use crate::render::{self, Colouring, RenderOptions, View};
    let mut m = mesh.clone();
    m.groups.clear();
    for (i, b) in rig.dominant_bones().into_iter().enumerate() {
        m.groups
            .entry(rig.bones[b as usize].name.clone())
            .or_default()
            .push(i as u32);
    }
    let views = ["front", "side", "top"]
        .iter()
        .filter_map(|v| View::named(v))
        .collect();
    let img = render::render(
        &m,
        &Colouring::Groups,
        &RenderOptions {
            width: 1200,
            height: 400,
            views,
            ..Default::default()
        },
    );
    render::save_png(&img, out)?;
    Ok(())
}

impl std::fmt::Display for AutorigSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{} bones on {} vertices (limbs: {}):",
            self.bones.len(),
            self.vertices,
            self.bones.len().saturating_sub(1) / 2
        )?;
        for b in &self.bones {
            writeln!(
                f,
                "  {:<14} from {:<14} joint ({:.3}, {:.3}, {:.3})  turns up to {:.0} deg  moves {} vertices most",
                b.name,
                b.parent.as_deref().unwrap_or("-"),
                b.joint[0],
                b.joint[1],
                b.joint[2],
                b.limit_deg,
                b.vertices
            )?;
        }
        write!(f, "wrote {}", self.rig.display())?;
        if let Some(p) = &self.preview {
            write!(f, "\nwrote {}", p.display())?;
        }
        Ok(())
    }
}
