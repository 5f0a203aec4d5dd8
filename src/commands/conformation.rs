//! Conformation jobs: options from config files, the template source, conforming files on
//! disk, the demo, and describing a mesh.

use super::*;
use crate::conform::{self, ConformOptions, ConformReport, IterationReport, Method};
use crate::mesh::{Mesh, quality, topology};
use crate::synth::cases;
use std::path::{Path, PathBuf};

/// Reads conformation options from a TOML file: either a whole `conform.toml`, or a
/// station file whose `[conform]` table holds them. Unknown keys are errors.
pub fn load_conform_options(path: &Path) -> Result<ConformOptions, CommandError> {
    let name = path.display().to_string();
    let table = read_toml(path)?;
    if crate::station::config::is_station_file(&table) {
        return Ok(crate::station::StationConfig::load(path)?.conform);
    }
    let opts: ConformOptions =
        table
            .try_into()
            .map_err(|e: toml::de::Error| CommandError::Config {
                path: name.clone(),
                msg: e.to_string(),
            })?;
    opts.validate().map_err(|e| CommandError::Config {
        path: name,
        msg: e.to_string(),
    })?;
    Ok(opts)
}

/// Conformation options from `config` (a `conform.toml` or a station file) or the
/// defaults, with `method` overriding: `paper` without a config means the paper's preset.
pub fn conform_options(
    config: Option<&Path>,
    method: Option<Method>,
) -> Result<ConformOptions, CommandError> {
    let mut opts = match config {
        Some(p) => load_conform_options(p)?,
        None => ConformOptions::default(),
    };
    if let Some(m) = method {
        if config.is_none() && m == Method::Paper {
            opts = ConformOptions::paper();
        }
        opts.method = m;
    }
    Ok(opts)
}

/// The `[template]` of a station file.
pub fn template_from_config(path: &Path) -> Result<crate::template::TemplateSource, CommandError> {
    crate::station::StationConfig::load(path)?
        .template
        .ok_or_else(|| CommandError::Input {
            path: path.display().to_string(),
            msg: "no [template] table, and no template named".into(),
        })
}

/// The files of one conformation.
#[derive(Debug, Clone)]
pub struct ConformFiles {
    pub template: crate::template::TemplateSource,
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
    progress: &mut conform::OnIteration,
) -> Result<ConformReport, CommandError> {
    let ext = files
        .out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    if ext != "ply" && ext != "obj" {
        return Err(CommandError::Usage(format!(
            "{}: the output must be a .ply or .obj file",
            files.out.display()
        )));
    }
    let (template, own_landmarks, rig) = files.template.load_rigged()?;
    let scan = mesh::read_mesh(&files.scan)?;
    let template_landmarks = match &files.template_landmarks {
        Some(t) => Some(mesh::read_landmarks(t)?),
        None => own_landmarks,
    };
    let landmarks = match (template_landmarks, &files.scan_landmarks) {
        (Some(t), Some(s)) => Some((t, mesh::read_landmarks(s)?)),
        (_, None) => None,
        (None, Some(_)) => {
            return Err(CommandError::Usage(
                "scan landmarks need template landmarks too (a template landmark file, or the template's own)".into(),
            ));
        }
    };
    let lm = landmarks.as_ref().map(|(t, s)| (&t[..], &s[..]));
    let never = std::sync::atomic::AtomicBool::new(false);
    let result =
        conform::conform_rigged(&template, rig.as_ref(), &scan, lm, opts, progress, &never)?;
    // the report first: a failed command leaves neither file
    if let Some(r) = &files.report {
        write_report(r, &result.report)?;
    }
    if let Err(e) = mesh::write_mesh(&files.out, &result.mesh) {
        if let Some(r) = &files.report {
            let _ = std::fs::remove_file(r);
        }
        return Err(e.into());
    }
    Ok(result.report)
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
pub fn demo_paper(
    out_dir: &Path,
    progress: &mut (dyn FnMut(Method, &IterationReport) + Send),
) -> Result<DemoSummary, CommandError> {
    std::fs::create_dir_all(out_dir).map_err(|source| CommandError::Io {
        path: out_dir.display().to_string(),
        source,
    })?;
    let case = cases::sphere_to_box_with_missing(4);
    let mut files = Vec::new();
    let mut put = |name: &str, bytes: &[u8]| -> Result<(), CommandError> {
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
                unit: "DISTANCE\nTO BOX".into(),
            },
            &crate::render::RenderOptions {
                views,
                ..Default::default()
            },
        );
        put(
            &format!("preview-{name}.png"),
            &crate::render::png_bytes(&img),
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
pub fn info(path: &Path, original: Option<&Path>) -> Result<MeshInfo, CommandError> {
    let m: Mesh = mesh::read_mesh(path)?;
    let variation = match original {
        Some(o_path) => {
            let o = mesh::read_mesh(o_path)?;
            if o.vertices.len() != m.vertices.len() || o.triangles != m.triangles {
                return Err(CommandError::Input {
                    path: path.display().to_string(),
                    msg: format!(
                        "{} does not share its topology, so their variations cannot be compared",
                        o_path.display()
                    ),
                });
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

impl std::fmt::Display for DemoSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "The paper's sphere-to-box case with missing data (the +x face and a disc on top removed):"
        )?;
        for m in &self.methods {
            write!(
                f,
                "\n  {:<8} {:>2} iterations {:.2} s: missing region ({} vertices) mean {:.2}%, 90th percentile {:.2}% of the box diagonal from the true box; watertight {}, folded {}",
                format!("{:?}", m.method).to_lowercase(),
                m.iterations,
                m.seconds,
                m.missing_vertices,
                m.missing_mean * 100.0,
                m.missing_p90 * 100.0,
                m.watertight,
                m.folded_triangles
            )?;
        }
        for p in &self.files {
            write!(f, "\nwrote {}", p.display())?;
        }
        Ok(())
    }
}
