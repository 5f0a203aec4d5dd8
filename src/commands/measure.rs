//! Measurements from the CLI: `conformd measure` (one conformed mesh, raw and with its
//! posture removed) and `conformd model posture` (the posture model of a generic
//! template).

use super::CommandError;
use crate::measure::{Definitions, Measurement, PostureRemoval, Resolved};
use crate::mesh;
use crate::model::{Align, BuildOptions, ShapeModel};
use crate::template::{self, Kind, TemplateSource};

/// For `measure --normalise-posture`: the model when one is given, else the generic
/// template's parts.
pub fn posture_removal(
    source: &TemplateSource,
    model: Option<&Path>,
    resolved: &Resolved,
) -> Result<PostureRemoval, CommandError> {
    match (model, source.generic) {
        (Some(p), _) => Ok(PostureRemoval::Model(Box::new(ShapeModel::load(p)?))),
        (None, Some(kind)) => Ok(PostureRemoval::for_figure(
            &template::build(kind, source.vertices.unwrap_or(10_000)),
            kind,
            resolved,
        )),
        (None, None) => Err(CommandError::Usage(
            "--normalise-posture with a template mesh needs --model (a model with posture modes: `model build --posture`)"
                .into(),
        )),
    }
}
use std::path::Path;

/// One mesh's measurements; with a posture model also after its posture was removed.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MeasureReport {
    pub mesh: String,
    pub measurements: Vec<Measurement>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normalised: Option<Vec<Measurement>>,
}

/// How well each measurement repeats over several meshes of one subject:
/// mean, SD and CV raw, and posture-free when the meshes were measured so too.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Repeatability {
    pub meshes: usize,
    pub raw: Vec<crate::measure::Spread>,
    pub posture_free: Option<Vec<crate::measure::Spread>>,
}

/// [`Repeatability`] of `reports` (one subject's meshes); at least two are needed.
pub fn repeatability(reports: &[MeasureReport]) -> Result<Repeatability, CommandError> {
    if reports.len() < 2 {
        return Err(CommandError::Usage(format!(
            "--repeatability needs two meshes or more of one subject ({} given)",
            reports.len()
        )));
    }
    let raw: Vec<Vec<Measurement>> = reports.iter().map(|r| r.measurements.clone()).collect();
    let free: Option<Vec<Vec<Measurement>>> =
        reports.iter().map(|r| r.normalised.clone()).collect();
    Ok(Repeatability {
        meshes: reports.len(),
        raw: crate::measure::spread(&raw),
        posture_free: free.map(|f| crate::measure::spread(&f)),
    })
}

impl std::fmt::Display for Repeatability {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "over {} meshes: mean, SD and coefficient of variation (CV){}",
            self.meshes,
            if self.posture_free.is_some() {
                ", raw | posture-free"
            } else {
                ""
            }
        )?;
        for (i, r) in self.raw.iter().enumerate() {
            write!(
                f,
                "{:<20} {:>10.4} {:>9.4} {:>6.2}% {:<4}",
                r.name,
                r.mean,
                r.sd,
                100.0 * r.cv,
                r.unit
            )?;
            if let Some(p) = self.posture_free.as_ref().and_then(|p| p.get(i)) {
                write!(
                    f,
                    " | {:>10.4} {:>9.4} {:>6.2}%",
                    p.mean,
                    p.sd,
                    100.0 * p.cv
                )?;
            }
            writeln!(f)?;
        }
        Ok(())
    }
}

/// The definitions a template is measured by: `definitions` when given, else the
/// generic template's own.
pub fn definitions_for(
    source: &TemplateSource,
    definitions: Option<&Path>,
) -> Result<Definitions, CommandError> {
    let bad = CommandError::Definitions;
    match (definitions, source.generic) {
        (Some(p), _) => Definitions::read(p).map_err(bad),
        (None, Some(Kind::Pig)) => Definitions::parse(crate::measure::PIG, "pig").map_err(bad),
        (None, Some(Kind::Body)) => Definitions::parse(crate::measure::BODY, "body").map_err(bad),
        (None, None) => Err(CommandError::Usage(
            "a template mesh needs its measurement definitions (--definitions FILE; see config/measurements/)"
                .into(),
        )),
    }
}

/// Loads the template and fixes the definitions on it.
pub fn resolve_measurements(
    source: &TemplateSource,
    definitions: Option<&Path>,
) -> Result<Resolved, CommandError> {
    let defs = definitions_for(source, definitions)?;
    let (template, landmarks) = source.load()?;
    defs.resolve(&template, landmarks.as_deref().unwrap_or(&[]))
        .map_err(CommandError::Definitions)
}

/// Measures a conformed mesh; with `posture`, also with its posture removed.
pub fn measure(
    mesh_path: &Path,
    resolved: &Resolved,
    posture: Option<&PostureRemoval>,
) -> Result<MeasureReport, CommandError> {
    let m = mesh::read_mesh(mesh_path)?;
    measure_mesh(&mesh_path.display().to_string(), &m, resolved, posture)
}

pub fn measure_mesh(
    name: &str,
    m: &mesh::Mesh,
    resolved: &Resolved,
    posture: Option<&PostureRemoval>,
) -> Result<MeasureReport, CommandError> {
    let bad = |source| CommandError::Measure {
        mesh: name.into(),
        source,
    };
    let measurements = resolved.measure(m).map_err(bad)?;
    let normalised = match posture {
        Some(p) => Some(p.measure(resolved, name, m).map_err(bad)?),
        None => None,
    };
    Ok(MeasureReport {
        mesh: name.into(),
        measurements,
        normalised,
    })
}

/// CSV of reports: one row per mesh, a column per measurement (and `<name>_normalised`).
pub fn measurements_csv(reports: &[MeasureReport]) -> String {
    let Some(first) = reports.first() else {
        return String::new();
    };
    let mut header = vec!["mesh".to_string()];
    header.extend(first.measurements.iter().map(|m| m.name.clone()));
    if let Some(n) = &first.normalised {
        header.extend(n.iter().map(|m| format!("{}_normalised", m.name)));
    }
    let mut s = header.join(",") + "\n";
    for r in reports {
        let mut row = vec![crate::station::export::csv_field(&r.mesh)];
        row.extend(r.measurements.iter().map(|m| m.value.to_string()));
        if let Some(n) = &r.normalised {
            row.extend(n.iter().map(|m| m.value.to_string()));
        }
        s += &(row.join(",") + "\n");
    }
    s
}

/// The posture model of a generic template: `postures` random postures (every pose
/// parameter within +/- `degrees`), every mode a posture mode; written to `out`.
pub fn model_posture(
    kind: Kind,
    vertices: usize,
    postures: usize,
    degrees: f64,
    out: &Path,
) -> Result<ShapeModel, CommandError> {
    if !(3..=1000).contains(&postures) {
        return Err(CommandError::Usage(format!(
            "--postures must be 3 to 1000, got {postures}"
        )));
    }
    if !(degrees > 0.0 && template::POSE_DEGREES.contains(&degrees)) {
        return Err(CommandError::Usage(format!(
            "--degrees must be above 0 and at most {}, got {degrees}",
            template::POSE_DEGREES.end()
        )));
    }
    let fig = template::build(kind, vertices);
    let samples = template::random_postures(kind, postures, degrees, 1)
        .iter()
        .enumerate()
        .map(|(i, p)| {
            template::subject(&fig, kind, &Default::default(), p)
                .map(|m| (format!("posture {i}"), m))
                .map_err(CommandError::from)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let model = ShapeModel::build(
        &samples,
        &BuildOptions {
            align: Align::Rigid,
            posture: true,
            ..Default::default()
        },
    )?;
    model.save(out)?;
    Ok(model)
}

/// The measurements a result folder's `report.json` holds: the posture-free ones when
/// there are, else the raw ones; with the capture's subject.
pub fn result_measurements(dir: &Path) -> Result<(Option<String>, Vec<Measurement>), CommandError> {
    let path = dir.join("report.json");
    let shown = path.display().to_string();
    let text = crate::files::read_text_limited(&path, 64 << 20)?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| CommandError::Config {
        path: shown.clone(),
        msg: e.to_string(),
    })?;
    let pick = |key: &str| -> Option<Vec<Measurement>> {
        v.get(key)
            .and_then(|m| serde_json::from_value(m.clone()).ok())
    };
    let ms = pick("measurements_normalised")
        .or_else(|| pick("measurements"))
        .ok_or_else(|| CommandError::Config {
            path: shown,
            msg: "has no measurements (a station measures when its template has definitions)"
                .into(),
        })?;
    Ok((
        v.get("subject").and_then(|s| s.as_str()).map(String::from),
        ms,
    ))
}

/// Reads `weights.csv` (`id,kg` rows: a capture id or a subject's tag; a header line
/// is allowed): each row with its line.
pub fn read_weights(path: &Path) -> Result<Vec<(String, f64)>, CommandError> {
    let shown = path.display().to_string();
    let text = crate::files::read_text_limited(path, 16 << 20)?;
    let mut out: Vec<(String, f64)> = Vec::new();
    // id -> (line, kg): a second weighing of one id must agree with the first
    let mut first: std::collections::HashMap<String, (usize, f64)> = Default::default();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut f = line.split(',').map(str::trim);
        let (Some(id), Some(kg), None) = (f.next(), f.next(), f.next()) else {
            return Err(CommandError::Config {
                path: shown,
                msg: format!("line {}: expected `id,kg`, got '{line}'", i + 1),
            });
        };
        match kg.parse::<f64>() {
            Ok(kg) if kg.is_finite() && kg > 0.0 => match first.get(id) {
                Some(&(_, earlier)) if earlier == kg => {}
                Some(&(at, earlier)) => {
                    return Err(CommandError::Config {
                        path: shown,
                        msg: format!(
                            "line {}: '{id}' weighs {kg} kg here and {earlier} kg on line {at}; one weight per id",
                            i + 1
                        ),
                    });
                }
                None => {
                    first.insert(id.to_string(), (i + 1, kg));
                    out.push((id.to_string(), kg));
                }
            },
            _ if i == 0 => continue, // a header
            _ => {
                return Err(CommandError::Config {
                    path: shown,
                    msg: format!("line {}: weight '{kg}' is not a positive number", i + 1),
                });
            }
        }
    }
    Ok(out)
}

/// `model weigh`: pairs every weighed id with the results of `results` (by capture id,
/// else every result of that subject) and fits the weight regression on `features`
/// (default: every measurement).
pub fn model_weigh(
    weights: &Path,
    results: &Path,
    features: Option<Vec<String>>,
    out: &Path,
) -> Result<crate::measure::weight::WeightModel, CommandError> {
    let weighed = read_weights(weights)?;
    let mut all: Vec<(String, Option<String>, Vec<Measurement>)> = Vec::new();
    let entries = std::fs::read_dir(results).map_err(|e| CommandError::Io {
        path: results.display().to_string(),
        source: e,
    })?;
    let mut dirs: Vec<_> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("report.json").is_file())
        // a rejected result (or one whose review cannot be read) weighs nothing
        .filter(|p| matches!(crate::station::review::left_out(p), Ok(false)))
        .collect();
    dirs.sort();
    for d in dirs {
        let id = d
            .file_name()
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        if let Ok((subject, ms)) = result_measurements(&d) {
            all.push((id, subject, ms));
        }
    }
    let mut samples = Vec::new();
    for (id, kg) in &weighed {
        let by_capture: Vec<_> = all.iter().filter(|(c, _, _)| c == id).collect();
        let matched = if by_capture.is_empty() {
            all.iter()
                .filter(|(_, s, _)| s.as_deref() == Some(id.as_str()))
                .collect()
        } else {
            by_capture
        };
        for (c, _, ms) in matched {
            samples.push((c.clone(), ms.clone(), *kg));
        }
    }
    let features = match features {
        Some(f) => f,
        None => samples
            .first()
            .map(|(_, ms, _)| ms.iter().map(|m| m.name.clone()).collect())
            .unwrap_or_default(),
    };
    let model = crate::measure::weight::WeightModel::fit(&samples, &features)?;
    crate::files::write_atomic(
        out,
        serde_json::to_string_pretty(&model)
            .expect("serialises")
            .as_bytes(),
    )?;
    Ok(model)
}

/// `export`: all results as CSV (see [`crate::station::export::export_csv`]).
pub fn export_csv(results: &Path) -> Result<crate::station::export::Export, CommandError> {
    crate::station::export::export_csv(results).map_err(|e| CommandError::Io {
        path: results.display().to_string(),
        source: e,
    })
}
