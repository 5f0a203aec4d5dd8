//! What a user can do from the CLI, as library calls: conform files on disk, load a
//! conformation config, run the demo, describe a mesh. The CLI, the tests and (later) the
//! daemon call exactly these.

use crate::conform::{self, ConformOptions, ConformReport, IterationReport, Method};
use crate::mesh::io::write_atomic;
use crate::mesh::{self, Mesh, quality, topology};
use crate::synth::cases;
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error(transparent)]
    Groups(#[from] mesh::groups::GroupsError),
    #[error(transparent)]
    Mesh(#[from] mesh::MeshError),
    #[error(transparent)]
    Landmarks(#[from] mesh::LandmarkError),
    #[error("{path}: {msg}")]
    Config { path: String, msg: String },
    #[error("{0}")]
    Conform(#[from] conform::ConformError),
    #[error("{0}")]
    Usage(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

/// Reads a TOML file into a table; errors name the file.
fn read_toml(path: &Path) -> Result<toml::Table, JobError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| JobError::Io {
        path: name.clone(),
        source,
    })?;
    toml::from_str(&text).map_err(|e| JobError::Config {
        path: name,
        msg: e.to_string(),
    })
}

/// Reads conformation options from a TOML file: either a whole `conform.toml`, or a
/// station config whose `[conform]` table holds them. Unknown keys are errors.
pub fn load_conform_options(path: &Path) -> Result<ConformOptions, JobError> {
    let name = path.display().to_string();
    let table = read_toml(path)?;
    // a station config holds sections; a conform.toml holds the options themselves
    const STATION_SECTIONS: [&str; 8] = [
        "template", "station", "rig", "capture", "trigger", "cameras", "daemon", "model",
    ];
    let table = match table.get("conform") {
        Some(toml::Value::Table(t)) => t.clone(),
        _ if STATION_SECTIONS.iter().any(|k| table.contains_key(*k)) => toml::Table::new(),
        _ => table,
    };
    let opts: ConformOptions = table
        .try_into()
        .map_err(|e: toml::de::Error| JobError::Config {
            path: name.clone(),
            msg: e.to_string(),
        })?;
    opts.validate().map_err(|e| JobError::Config {
        path: name,
        msg: e.to_string(),
    })?;
    Ok(opts)
}

/// Where a station's template comes from: a generic one (`pig`, `body`) built at a
/// resolution, or any user mesh with its landmark file and optional groups file (the
/// paper: "one of the 3D shape samples can serve as a generic mesh directly").
/// In a config: `[template]` with `generic = "pig"` and `vertices = 10000`, or
/// `mesh = "..."`, `landmarks = "..."`, `groups = "..."`.
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TemplateSource {
    pub generic: Option<crate::synth::templates::Kind>,
    pub vertices: Option<usize>,
    pub mesh: Option<PathBuf>,
    pub landmarks: Option<PathBuf>,
    pub groups: Option<PathBuf>,
}

impl TemplateSource {
    /// Reads the `[template]` table of a config file; relative paths are taken from the
    /// config file's folder.
    pub fn from_config(path: &Path) -> Result<Option<TemplateSource>, JobError> {
        let name = path.display().to_string();
        let table = read_toml(path)?;
        let Some(t) = table.get("template") else {
            return Ok(None);
        };
        let mut src: TemplateSource =
            t.clone()
                .try_into()
                .map_err(|e: toml::de::Error| JobError::Config {
                    path: name.clone(),
                    msg: format!("[template]: {e}"),
                })?;
        let base = path.parent().unwrap_or(Path::new("."));
        for p in [&mut src.mesh, &mut src.landmarks, &mut src.groups]
            .into_iter()
            .flatten()
        {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
        Ok(Some(src))
    }

    /// The template mesh (with groups) and its landmarks, if it has any.
    pub fn load(&self) -> Result<(Mesh, Option<Vec<mesh::Landmark>>), JobError> {
        match (&self.generic, &self.mesh) {
            (Some(kind), None) => {
                let fig = crate::synth::templates::build(*kind, self.vertices.unwrap_or(10_000));
                let lms = fig.landmarks();
                Ok((fig.mesh, Some(lms)))
            }
            (None, Some(path)) => {
                let mut m = mesh::read_mesh(path)?;
                if let Some(g) = &self.groups {
                    mesh::groups::read_into(g, &mut m)?;
                }
                let lms = self.landmarks.as_ref().map(|p| mesh::read_landmarks(p)).transpose()?;
                Ok((m, lms))
            }
            _ => Err(JobError::Usage("[template] needs either generic = \"pig\" or \"body\", or mesh = \"FILE\" (not both)".into())),
        }
    }
}

/// The files of one conformation.
#[derive(Debug, Clone)]
pub struct ConformFiles {
    pub template: TemplateSource,
    pub scan: PathBuf,
    pub template_landmarks: Option<PathBuf>,
    pub scan_landmarks: Option<PathBuf>,
    pub out: PathBuf,
    pub report: Option<PathBuf>,
}

/// Reads the template, scan and landmarks, conforms, writes the result (`.ply` or
/// `.obj`) and the JSON report, each atomically. Landmarks are used only when both files
/// are given; one without the other is an error.
///
/// Example: `conformd conform --template t.obj --scan s.ply --out c.ply --report r.json`;
/// see `tests/cli.rs`.
pub fn conform_files(
    files: &ConformFiles,
    opts: &ConformOptions,
    progress: &mut dyn FnMut(&IterationReport),
) -> Result<ConformReport, JobError> {
    let ext = files
        .out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext != "ply" && ext != "obj" {
        return Err(JobError::Usage(format!(
            "{}: the output must be a .ply or .obj file",
            files.out.display()
        )));
    }
    let (template, own_landmarks) = files.template.load()?;
    let scan = mesh::read_mesh(&files.scan)?;
    let template_landmarks = match &files.template_landmarks {
        Some(t) => Some(mesh::read_landmarks(t)?),
        None => own_landmarks,
    };
    let landmarks = match (template_landmarks, &files.scan_landmarks) {
        (Some(t), Some(s)) => Some((t, mesh::read_landmarks(s)?)),
        (_, None) => None,
        (None, Some(_)) => {
            return Err(JobError::Usage(
                "--scan-landmarks needs template landmarks too (--template-landmarks, or the template's own)".into(),
            ));
        }
    };
    let lm = landmarks.as_ref().map(|(t, s)| (&t[..], &s[..]));
    let result = conform::conform(&template, &scan, lm, opts, progress)?;
    mesh::write_mesh(&files.out, &result.mesh)?;
    if let Some(r) = &files.report {
        write_report(r, &result.report)?;
    }
    Ok(result.report)
}

fn write_report<T: serde::Serialize>(path: &Path, report: &T) -> Result<(), JobError> {
    let json = serde_json::to_string_pretty(report).expect("reports serialise");
    write_atomic(path, json.as_bytes())?;
    Ok(())
}

/// What the demo wrote and measured.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoSummary {
    pub files: Vec<PathBuf>,
    /// per method: mean and 90th percentile distance of the missing region's vertices to
    /// the true box surface, relative to the box diagonal; largest anywhere; watertight
    pub methods: Vec<DemoFigures>,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoFigures {
    pub method: Method,
    pub iterations: usize,
    pub seconds: f64,
    pub missing_vertices: usize,
    pub missing_mean: f64,
    pub missing_p90: f64,
    pub max_anywhere: f64,
    pub watertight: bool,
    pub folded_triangles: usize,
}

/// The paper's sphere-to-box case with missing data (Ju et al. 2004, section 3.2), with
/// both methods: writes the template, the scan with its holes, landmarks, each conformed
/// mesh and report into `out_dir`.
pub fn demo(
    out_dir: &Path,
    progress: &mut dyn FnMut(Method, &IterationReport),
) -> Result<DemoSummary, JobError> {
    std::fs::create_dir_all(out_dir).map_err(|source| JobError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    let case = cases::sphere_to_box_with_missing(4);
    let mut files = Vec::new();
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), JobError> {
        let p = out_dir.join(name);
        write_atomic(&p, bytes)?;
        files.push(p);
        Ok(())
    };
    put(
        "template.ply",
        &mesh::io::ply_bytes(&case.template, mesh::io::PlyEncoding::BinaryLittleEndian),
    )?;
    put(
        "scan.ply",
        &mesh::io::ply_bytes(&case.scan, mesh::io::PlyEncoding::BinaryLittleEndian),
    )?;
    put(
        "template.landmarks",
        mesh::landmarks::landmarks_text(&case.template_landmarks).as_bytes(),
    )?;
    put(
        "scan.landmarks",
        mesh::landmarks::landmarks_text(&case.scan_landmarks).as_bytes(),
    )?;
    let mut methods = Vec::new();
    for (method, opts) in [
        (Method::Paper, ConformOptions::paper()),
        (Method::Default, ConformOptions::default()),
    ] {
        let lm = Some((&case.template_landmarks[..], &case.scan_landmarks[..]));
        let r = conform::conform(&case.template, &case.scan, lm, &opts, &mut |it| {
            progress(method, it)
        })?;
        let name = format!("{:?}", method).to_lowercase();
        put(
            &format!("conformed-{name}.ply"),
            &mesh::io::ply_bytes(&r.mesh, mesh::io::PlyEncoding::BinaryLittleEndian),
        )?;
        put(
            &format!("report-{name}.json"),
            serde_json::to_string_pretty(&r.report)
                .expect("serialises")
                .as_bytes(),
        )?;
        // a picture of the result, coloured by its distance to the true (whole) box
        let size = crate::mesh::V3::from(cases::BOX_SIZE);
        let values: Vec<f64> = r
            .mesh
            .vertices
            .iter()
            .map(|p| crate::synth::distance_to_box_surface(p, &size))
            .collect();
        let max = values.iter().cloned().fold(0.0, f64::max);
        let views = vec![
            crate::render::View {
                azimuth: 30.0,
                elevation: 30.0,
            },
            crate::render::View {
                azimuth: 150.0,
                elevation: -20.0,
            },
        ];
        let img = crate::render::render(
            &r.mesh,
            &crate::render::Colouring::Values {
                values,
                min: 0.0,
                max,
                unit: "TO BOX".into(),
            },
            &crate::render::RenderOptions {
                views,
                ..Default::default()
            },
        );
        let mut png = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .expect("encoding a PNG in memory");
        put(&format!("preview-{name}.png"), &png)?;
        let f = cases::box_figures(&r.mesh);
        methods.push(DemoFigures {
            method,
            iterations: r.report.iterations.len(),
            seconds: r.report.seconds.total,
            missing_vertices: f.missing_vertices,
            missing_mean: f.missing_mean,
            missing_p90: f.missing_p90,
            max_anywhere: f.max_anywhere,
            watertight: r.report.watertight_result,
            folded_triangles: r.report.folded_triangles,
        });
    }
    Ok(DemoSummary { files, methods })
}

/// A mesh's topology and, against an optional original of the same topology, the paper's
/// variation figures.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MeshInfo {
    pub topology: topology::TopologyReport,
    pub bounding_box: Option<[[f64; 3]; 2]>,
    pub diagonal: f64,
    pub area: f64,
    pub has_normals: bool,
    pub groups: Vec<(String, usize)>,
    pub folded_triangles: usize,
    pub variation: Option<quality::Variation>,
}

/// Describes a mesh file (and compares it with `original` when given).
pub fn info(path: &Path, original: Option<&Path>) -> Result<MeshInfo, JobError> {
    let m: Mesh = mesh::read_mesh(path)?;
    let variation = match original {
        Some(o) => {
            let o = mesh::read_mesh(o)?;
            if o.vertices.len() != m.vertices.len() || o.triangles != m.triangles {
                return Err(JobError::Usage(format!(
                    "{} and {} do not share a topology, so their variations cannot be compared",
                    path.display(),
                    original.unwrap().display()
                )));
            }
            Some(quality::variation(&o.vertices, &m.vertices, &m.triangles))
        }
        None => None,
    };
    Ok(MeshInfo {
        topology: topology::report(&m),
        bounding_box: m
            .bounding_box()
            .map(|(a, b)| [[a.x, a.y, a.z], [b.x, b.y, b.z]]),
        diagonal: m.diagonal(),
        area: m.area(),
        has_normals: m.normals.is_some(),
        groups: m.groups.iter().map(|(k, v)| (k.clone(), v.len())).collect(),
        folded_triangles: quality::folded_triangles(&m),
        variation,
    })
}

/// What `template` wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TemplateSummary {
    pub mesh: PathBuf,
    pub landmarks: PathBuf,
    pub vertices: usize,
    pub triangles: usize,
    pub groups: Vec<(String, usize)>,
    pub landmark_count: usize,
    pub watertight: bool,
}

/// Writes a generic pig or body template of about `vertices` vertices, optionally posed
/// (`swing=12,nod=-8`) and reshaped (`length=1.1`), and its landmark file beside it
/// (`<out without extension>.landmarks`). The vertex order does not depend on pose or
/// shape, so subjects made this way are their own ground truth.
pub fn template(
    kind: crate::synth::templates::Kind,
    vertices: usize,
    pose: &str,
    shape: &str,
    out: &Path,
) -> Result<TemplateSummary, JobError> {
    use crate::synth::templates;
    if !(500..=200_000).contains(&vertices) {
        return Err(JobError::Usage(format!(
            "--vertices must be 500 to 200000, got {vertices}"
        )));
    }
    let pose_names: Vec<&str> = templates::pose_parameters(kind)
        .iter()
        .map(|p| p.0)
        .collect();
    let pose_params =
        templates::parse_parameters(pose, &pose_names, "pose").map_err(JobError::Usage)?;
    let shape_names = templates::shape_parameters(kind);
    let shape_params =
        templates::parse_parameters(shape, &shape_names, "shape").map_err(JobError::Usage)?;
    let fig = templates::build(kind, vertices);
    let mut mesh = templates::subject(
        &fig,
        kind,
        &shape_params,
        &templates::pose(kind, &pose_params),
    )
    .map_err(JobError::Usage)?;
    mesh.groups = fig.mesh.groups.clone();
    mesh::write_mesh(out, &mesh)?;
    let landmarks = out.with_extension("landmarks");
    let lms = fig.landmarks();
    write_atomic(&landmarks, mesh::landmarks::landmarks_text(&lms).as_bytes())?;
    Ok(TemplateSummary {
        mesh: out.to_path_buf(),
        landmarks,
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
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(ColourBy::None),
            "group" => Ok(ColourBy::Group),
            _ => match s.strip_prefix("distance-to=") {
                Some(p) if !p.is_empty() => Ok(ColourBy::DistanceTo(PathBuf::from(p))),
                _ => Err(format!("'{s}': expected none, group or distance-to=SCAN")),
            },
        }
    }
}

/// Renders a mesh to a PNG preview from the named views (`front`, `back`, `left`,
/// `right`/`side`, `top`, `three-quarter`).
pub fn render(
    mesh_path: &Path,
    colour: &ColourBy,
    views: &[String],
    width: u32,
    height: u32,
    out: &Path,
) -> Result<(), JobError> {
    use crate::render::{self, Colouring, RenderOptions, View};
    if !(64..=8192).contains(&width) || !(64..=8192).contains(&height) {
        return Err(JobError::Usage(format!(
            "image size {width}x{height}: each side must be 64 to 8192 pixels"
        )));
    }
    let m = mesh::read_mesh(mesh_path)?;
    if m.triangles.is_empty() {
        return Err(JobError::Usage(format!(
            "{}: a point cloud has no surface to render",
            mesh_path.display()
        )));
    }
    let views = views
        .iter()
        .map(|v| {
            View::named(v).ok_or_else(|| {
                JobError::Usage(format!(
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
            let surface = conform::correspond::ScanSurface::new(&s)
                .map_err(|e| JobError::Usage(format!("{}: {e}", scan.display())))?;
            let values: Vec<f64> = m.vertices.iter().map(|p| surface.distance(p)).collect();
            let max = values.iter().cloned().fold(0.0, f64::max);
            Colouring::Values {
                values,
                min: 0.0,
                max,
                unit: "DISTANCE".into(),
            }
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
) -> Result<(crate::model::ShapeModel, Option<crate::model::Quality>), JobError> {
    let samples = paths
        .iter()
        .map(|p| Ok((p.display().to_string(), mesh::read_mesh(p)?)))
        .collect::<Result<Vec<_>, JobError>>()?;
    let model = crate::model::ShapeModel::build(&samples, opts)
        .map_err(|e| JobError::Usage(e.to_string()))?;
    model.save(out)?;
    let q = if quality {
        Some(
            crate::model::quality(&samples, opts, 10, 1)
                .map_err(|e| JobError::Usage(e.to_string()))?,
        )
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
) -> Result<Vec<PathBuf>, JobError> {
    use crate::render::{self, Colouring, RenderOptions, View};
    let model =
        crate::model::ShapeModel::load(model_path).map_err(|e| JobError::Usage(e.to_string()))?;
    std::fs::create_dir_all(out_dir).map_err(|source| JobError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    let view =
        View::named(view).ok_or_else(|| JobError::Usage(format!("unknown view '{view}'")))?;
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
) -> Result<Vec<crate::model::Score>, JobError> {
    let model =
        crate::model::ShapeModel::load(model_path).map_err(|e| JobError::Usage(e.to_string()))?;
    paths
        .iter()
        .map(|p| {
            let m = mesh::read_mesh(p)?;
            model
                .score(&p.display().to_string(), &m)
                .map_err(|e| JobError::Usage(e.to_string()))
        })
        .collect()
}

/// Captures one set with the station config's rig; the result names the set's folder.
pub fn capture(
    config: &Path,
    subject: Option<&str>,
) -> Result<crate::rig::capture::CaptureSet, JobError> {
    let rig =
        crate::rig::station::RigConfig::load(config).map_err(|e| JobError::Usage(e.to_string()))?;
    std::fs::create_dir_all(&rig.capture.root).map_err(|source| JobError::Io {
        path: rig.capture.root.display().to_string(),
        source,
    })?;
    let mut session = rig.open().map_err(|e| JobError::Usage(e.to_string()))?;
    session
        .capture(subject)
        .map_err(|e| JobError::Usage(e.to_string()))
}

/// Renders capture sets of a subject (a mesh file, or a generic `pig`/`body` posed with
/// `pose`) seen by the rig's cameras, written as standard capture sets under `out`, each
/// with the ground-truth mesh beside its images (`truth.ply`), and every pod's
/// calibration as OpenCV YAML under `out/calibration/`.
pub fn simulate(
    rig_path: &Path,
    subject: &str,
    pose: &str,
    captures: usize,
    noise: f64,
    out: &Path,
) -> Result<Vec<PathBuf>, JobError> {
    use crate::rig::capture::{CameraRecord, Manifest, TriggerRecord, utc_stamp};
    use crate::synth::templates;
    let rig = crate::synth::rig::RigFile::load(rig_path).map_err(JobError::Usage)?;
    let mesh = match subject.parse::<templates::Kind>() {
        Ok(kind) if !Path::new(subject).exists() => {
            let names: Vec<&str> = templates::pose_parameters(kind)
                .iter()
                .map(|p| p.0)
                .collect();
            let params =
                templates::parse_parameters(pose, &names, "pose").map_err(JobError::Usage)?;
            let fig = templates::build(kind, 20_000);
            templates::subject(
                &fig,
                kind,
                &std::collections::BTreeMap::new(),
                &templates::pose(kind, &params),
            )
            .map_err(JobError::Usage)?
        }
        _ => mesh::read_mesh(Path::new(subject))?,
    };
    let io = |p: &Path, source| JobError::Io {
        path: p.display().to_string(),
        source,
    };
    let calib = out.join("calibration");
    std::fs::create_dir_all(&calib).map_err(|e| io(&calib, e))?;
    for pod in rig.pods() {
        write_atomic(
            &calib.join(format!("{}.yml", pod.id)),
            pod.opencv_yaml().as_bytes(),
        )?;
    }
    let mut dirs = Vec::new();
    for n in 0..captures {
        let id = format!("{}-sim{n:03}", utc_stamp(std::time::SystemTime::now()));
        let partial = out.join(format!(".{id}.partial"));
        std::fs::create_dir_all(&partial).map_err(|e| io(&partial, e))?;
        let mut cameras = Vec::new();
        for r in crate::synth::rig::render_rig(&rig, &mesh, noise, n as u64) {
            let file = format!("{}-{}.png", r.pod, r.side);
            let img = image::GrayImage::from_raw(r.width, r.height, r.pixels).expect("sized");
            let mut bytes = Vec::new();
            img.write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Png,
            )
            .expect("in-memory PNG");
            write_atomic(&partial.join(&file), &bytes)?;
            cameras.push(CameraRecord {
                id: format!("{}-{}", r.pod, r.side),
                pod: r.pod.clone(),
                side: r.side.into(),
                file,
                width: r.width,
                height: r.height,
                sensor_timestamp_us: n as u64 * 1_000_000,
                sequence: n as u32,
                exposure_us: None,
            });
        }
        mesh::write_mesh(&partial.join("truth.ply"), &mesh)?;
        let now = utc_stamp(std::time::SystemTime::now());
        let manifest = Manifest {
            format: Manifest::FORMAT.into(),
            version: 1,
            id: id.clone(),
            station: rig.name.clone(),
            subject: Some(subject.into()),
            started_utc: now.clone(),
            finished_utc: now,
            trigger: TriggerRecord {
                kind: "simulated".into(),
                sequence: n as u32,
                box_time_us: None,
            },
            cameras,
        };
        write_atomic(
            &partial.join("manifest.json"),
            &serde_json::to_vec_pretty(&manifest).expect("serialises"),
        )?;
        let dir = out.join(&id);
        std::fs::rename(&partial, &dir).map_err(|e| io(&dir, e))?;
        dirs.push(dir);
    }
    Ok(dirs)
}

/// Reconstructs a capture set into a scan in the rig frame: every pod of the rig file
/// whose two images the set holds (cameras `<pod>-left` / `<pod>-right`, or the
/// manifest's pod and side) is rectified, matched and reprojected, then all are fused.
/// Writes the scan (PLY point cloud with normals) and, if asked, a JSON report.
pub fn reconstruct(
    capture: &Path,
    rig_path: &Path,
    calibration: Option<&Path>,
    out: &Path,
    report_path: Option<&Path>,
) -> Result<crate::stereo::reconstruct::ReconstructReport, JobError> {
    use crate::stereo::reconstruct::{
        self as rc, PodReport, ReconstructOptions, ReconstructReport,
    };
    let t = std::time::Instant::now();
    let rig = crate::synth::rig::RigFile::load(rig_path).map_err(JobError::Usage)?;
    let manifest =
        crate::rig::capture::Manifest::read(capture).map_err(|e| JobError::Usage(e.to_string()))?;
    let opts = ReconstructOptions {
        working_volume: rig.working_volume,
        ..Default::default()
    };
    let mut report = ReconstructReport::default();
    let mut points = Vec::new();
    for pod in rig.pods() {
        // a calibration file, when given, replaces the rig file's lenses and pair geometry
        let pod = match calibration.map(|d| d.join(format!("{}.yml", pod.id))) {
            Some(f) if f.exists() => crate::stereo::calibrate::read_yaml(
                &f,
                &pod.id,
                pod.left_pose,
                pod.left.width,
                pod.left.height,
            )
            .map_err(JobError::Usage)?,
            Some(f) => {
                return Err(JobError::Usage(format!(
                    "{}: no calibration for pod {}",
                    f.display(),
                    pod.id
                )));
            }
            None => pod,
        };
        let image = |side: &str| -> Result<Vec<u8>, JobError> {
            let cam = manifest
                .cameras
                .iter()
                .find(|c| c.pod == pod.id && c.side == side)
                .ok_or_else(|| {
                    JobError::Usage(format!(
                        "{}: no {side} image of pod {} in the capture set",
                        capture.display(),
                        pod.id
                    ))
                })?;
            let path = capture.join(&cam.file);
            let img = image::open(&path)
                .map_err(|e| {
                    JobError::Usage(format!("camera {}: {}: {e}", cam.id, path.display()))
                })?
                .to_luma8();
            if (img.width(), img.height()) != (pod.left.width, pod.left.height) {
                return Err(JobError::Usage(format!(
                    "camera {}: {} is {}x{}, the calibration is for {}x{}",
                    cam.id,
                    path.display(),
                    img.width(),
                    img.height(),
                    pod.left.width,
                    pod.left.height
                )));
            }
            Ok(img.into_raw())
        };
        let (l, r) = (image("left")?, image("right")?);
        let mut pr = PodReport {
            pod: pod.id.clone(),
            ..Default::default()
        };
        let pts = rc::pod_points(&pod, &l, &r, &opts.sgbm, &mut pr)
            .map_err(|e| JobError::Usage(format!("pod {}: OpenCV: {e}", pod.id)))?;
        if pts.is_empty() {
            return Err(JobError::Usage(format!(
                "pod {}: the disparity map is empty (no surface matched)",
                pod.id
            )));
        }
        points.extend(pts);
        report.pods.push(pr);
    }
    let scan = rc::fuse(points, &opts, &mut report);
    report.seconds_total = t.elapsed().as_secs_f64();
    mesh::write_mesh(out, &scan)?;
    if let Some(p) = report_path {
        write_report(p, &report)?;
    }
    Ok(report)
}

/// Disparity of an already-rectified pair, written as PFM (or 16-bit PNG x16 for .png).
pub fn disparity(
    left: &Path,
    right: &Path,
    opts: &crate::stereo::disparity::SgbmOptions,
    out: &Path,
) -> Result<f64, JobError> {
    let read = |p: &Path| -> Result<image::GrayImage, JobError> {
        Ok(image::open(p)
            .map_err(|e| JobError::Usage(format!("{}: {e}", p.display())))?
            .to_luma8())
    };
    let (l, r) = (read(left)?, read(right)?);
    if l.dimensions() != r.dimensions() {
        return Err(JobError::Usage(format!(
            "{} is {:?} but {} is {:?}: a rectified pair has one size",
            left.display(),
            l.dimensions(),
            right.display(),
            r.dimensions()
        )));
    }
    let d =
        crate::stereo::disparity::disparity(l.as_raw(), r.as_raw(), l.width(), l.height(), opts)
            .map_err(JobError::Usage)?;
    let bytes = if out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        let px: Vec<u16> = d
            .values
            .iter()
            .map(|v| {
                if v.is_finite() {
                    (v * 16.0).round().clamp(0.0, 65535.0) as u16
                } else {
                    0
                }
            })
            .collect();
        let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(d.width, d.height, px)
            .expect("sized");
        let mut b = Vec::new();
        img.write_to(&mut std::io::Cursor::new(&mut b), image::ImageFormat::Png)
            .expect("in-memory PNG");
        b
    } else {
        d.pfm()
    };
    write_atomic(out, &bytes)?;
    Ok(d.valid_share())
}

/// Parses `9x6` (inner corners).
pub fn parse_board(s: &str) -> Result<(u32, u32), JobError> {
    let bad = || {
        JobError::Usage(format!(
            "board '{s}': expected COLSxROWS inner corners, e.g. 9x6"
        ))
    };
    let (a, b) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (c, r): (u32, u32) = (a.parse().map_err(|_| bad())?, b.parse().map_err(|_| bad())?);
    if c < 3 || r < 3 {
        return Err(bad());
    }
    Ok((c, r))
}

/// Renders chessboard calibration views for every pod of the rig: `out/<pod>/leftNN.png`
/// and `rightNN.png`, and the pod's true calibration beside them (`truth.yml`).
pub fn simulate_chessboard(
    rig_path: &Path,
    board: &str,
    square: f64,
    views: usize,
    out: &Path,
) -> Result<Vec<PathBuf>, JobError> {
    use crate::synth::rig::{Chessboard, RigFile, chessboard_poses, render_chessboard};
    let (cols, rows) = parse_board(board)?;
    if !(square > 0.0) {
        return Err(JobError::Usage(format!(
            "--square must be positive, got {square}"
        )));
    }
    let rig = RigFile::load(rig_path).map_err(JobError::Usage)?;
    let cb = Chessboard { cols, rows, square };
    let mut dirs = Vec::new();
    for (pod, spec) in rig.pods().iter().zip(&rig.pods) {
        let dir = out.join(&pod.id);
        std::fs::create_dir_all(&dir).map_err(|source| JobError::Io {
            path: dir.display().to_string(),
            source,
        })?;
        for (k, b) in chessboard_poses(pod, spec, &cb, views, 7)
            .iter()
            .enumerate()
        {
            for (right, name) in [(false, "left"), (true, "right")] {
                let px = render_chessboard(pod, right, &cb, b, 1.0, k as u64);
                let img =
                    image::GrayImage::from_raw(pod.left.width, pod.left.height, px).expect("sized");
                let mut bytes = Vec::new();
                img.write_to(
                    &mut std::io::Cursor::new(&mut bytes),
                    image::ImageFormat::Png,
                )
                .expect("in-memory PNG");
                write_atomic(&dir.join(format!("{name}{k:02}.png")), &bytes)?;
            }
        }
        write_atomic(&dir.join("truth.yml"), pod.opencv_yaml().as_bytes())?;
        dirs.push(dir);
    }
    Ok(dirs)
}

/// Calibrates one pod from chessboard pairs in `images` (`leftNN.*` with `rightNN.*`, or
/// folders `left/` and `right/` with matching names) and writes OpenCV YAML.
pub fn calibrate(
    images: &Path,
    board: &str,
    square: f64,
    out: &Path,
) -> Result<crate::stereo::calibrate::CalibrationReport, JobError> {
    let (cols, rows) = parse_board(board)?;
    let list = |dir: &Path, prefix: &str| -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .map(|e| e.path())
                    .filter(|p| {
                        p.file_name()
                            .is_some_and(|n| n.to_string_lossy().starts_with(prefix))
                    })
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    };
    let (lefts, rights) = if images.join("left").is_dir() {
        (
            list(&images.join("left"), ""),
            list(&images.join("right"), ""),
        )
    } else {
        (list(images, "left"), list(images, "right"))
    };
    if lefts.is_empty() || lefts.len() != rights.len() {
        return Err(JobError::Usage(format!(
            "{}: found {} left and {} right images; expected pairs leftNN/rightNN (or folders left/ and right/)",
            images.display(),
            lefts.len(),
            rights.len()
        )));
    }
    let mut size = None;
    let mut pairs = Vec::new();
    for (l, r) in lefts.iter().zip(&rights) {
        let read = |p: &Path| -> Result<image::GrayImage, JobError> {
            Ok(image::open(p)
                .map_err(|e| JobError::Usage(format!("{}: {e}", p.display())))?
                .to_luma8())
        };
        let (a, b) = (read(l)?, read(r)?);
        let dims = a.dimensions();
        if b.dimensions() != dims || size.is_some_and(|s| s != dims) {
            return Err(JobError::Usage(format!(
                "{}: its size differs from the other views",
                r.display()
            )));
        }
        size = Some(dims);
        pairs.push((a.into_raw(), b.into_raw()));
    }
    let (w, h) = size.expect("at least one pair");
    let id = images
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| "pod".into());
    let (pod, report) = crate::stereo::calibrate::calibrate(&pairs, w, h, cols, rows, square, &id)
        .map_err(JobError::Usage)?;
    let yaml = crate::stereo::calibrate::full_yaml(&pod).map_err(JobError::Usage)?;
    write_atomic(out, yaml.as_bytes())?;
    Ok(report)
}
