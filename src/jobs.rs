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

/// Reads conformation options from a TOML file: either a whole `conform.toml`, or a
/// station config whose `[conform]` table holds them. Unknown keys are errors.
pub fn load_conform_options(path: &Path) -> Result<ConformOptions, JobError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| JobError::Io {
        path: name.clone(),
        source,
    })?;
    let table: toml::Table = toml::from_str(&text).map_err(|e| JobError::Config {
        path: name.clone(),
        msg: e.to_string(),
    })?;
    let table = match table.get("conform") {
        Some(toml::Value::Table(t)) => t.clone(),
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

/// The files of one conformation.
#[derive(Debug, Clone)]
pub struct ConformFiles {
    pub template: PathBuf,
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
    let template = mesh::read_mesh(&files.template)?;
    let scan = mesh::read_mesh(&files.scan)?;
    let landmarks = match (&files.template_landmarks, &files.scan_landmarks) {
        (Some(t), Some(s)) => Some((mesh::read_landmarks(t)?, mesh::read_landmarks(s)?)),
        (None, None) => None,
        _ => {
            return Err(JobError::Usage(
                "landmarks need both --template-landmarks and --scan-landmarks (or neither, for automatic alignment)".into(),
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
