//! The station pipeline: what a station runs for every capture, as one call held for the
//! life of a process. Capture set -> scan (stereo) -> conformed mesh -> model scores ->
//! results folder, in memory until [`Processed::write`] renames a finished folder into
//! place. Every failure is a [`StageError`] that names the stage, the capture, the file,
//! and whether the capture (permanent) or the machine (retryable) is at fault.

use crate::conform::{self, ConformError, ConformOptions, ConformReport, IterationReport};
use crate::devices::capture_set::{CaptureSetDir, CaptureSetError};
use crate::files::{sync_dir, write_synced};
use crate::measure::weight::{WeightModel, WeightPrediction};
use crate::measure::{Definitions, Measurement, PostureRemoval, Resolved};
use crate::mesh::{Landmark, Mesh};
use crate::model::{ModelError, Score, ShapeModel};
use crate::station::config::StationConfig;
use crate::stereo::reconstruct::{ReconstructError, ReconstructReport};
use crate::stereo::rig::{Reconstruction, RigError};
use crate::template::rig::TemplateRig;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Instant;

/// Fewest scan points worth conforming onto: fewer means the rig saw (almost) nothing.
pub const MIN_SCAN_POINTS: usize = 200;

/// The stages of [`Pipeline::process`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    /// the station file and its template loaded, before any capture is read (a worker
    /// process's start; no capture is at fault)
    Setup,
    Read,
    Reconstruct,
    Conform,
    Score,
    Write,
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Stage::Setup => "setup",
            Stage::Read => "read",
            Stage::Reconstruct => "reconstruct",
            Stage::Conform => "conform",
            Stage::Score => "score",
            Stage::Write => "write",
        })
    }
}

/// What went wrong inside a stage.
#[derive(Debug, thiserror::Error)]
pub enum StageCause {
    #[error(transparent)]
    CaptureSet(#[from] CaptureSetError),
    #[error("{0}; images: {1}")]
    Reconstruct(ReconstructError, String),
    #[error(
        "the scan has {points} points (at least {MIN_SCAN_POINTS} are needed): the rig saw no subject in its working volume"
    )]
    EmptyScan { points: usize },
    #[error(transparent)]
    Conform(#[from] ConformError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("cancelled")]
    Cancelled,
}

/// A failed stage of one capture.
#[derive(Debug, thiserror::Error)]
#[error("capture {capture}: {stage}: {cause}")]
pub struct StageError {
    pub stage: Stage,
    pub capture: String,
    /// true: the capture itself is at fault and processing it again cannot help; false:
    /// the machine is (disk, memory, a stop), and a later attempt may succeed
    pub permanent: bool,
    #[source]
    pub cause: StageCause,
}

impl StageError {
    fn new(stage: Stage, capture: &str, cause: StageCause) -> StageError {
        let permanent = match &cause {
            StageCause::CaptureSet(e) => e.is_permanent(),
            StageCause::Io { .. } | StageCause::Cancelled => false,
            StageCause::Conform(ConformError::Cancelled) => false,
            _ => true,
        };
        StageError {
            stage,
            capture: capture.to_string(),
            permanent,
            cause,
        }
    }
}

/// Why a pipeline could not be set up from a station file.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("{0}: no [rig] section, so captures cannot be reconstructed")]
    NoRig(String),
    #[error("{0}: no [template] section, so there is nothing to conform")]
    NoTemplate(String),
    #[error("template: {0}")]
    Template(#[from] crate::mesh::FileError),
    #[error(transparent)]
    Rig(#[from] RigError),
    #[error(transparent)]
    Model(#[from] ModelError),
    #[error("{0}")]
    Measure(String),
    #[error("{file}: [conform] {msg}")]
    Conform { file: String, msg: String },
}

/// What a long stage reports while it runs.
pub enum Progress<'a> {
    Stage(Stage),
    Iteration(&'a IterationReport),
}

/// A cancel flag and a progress callback for [`Pipeline::process`].
#[derive(Default)]
pub struct Control<'a> {
    pub cancel: Option<&'a AtomicBool>,
    pub progress: Option<&'a mut (dyn FnMut(Progress) + Send)>,
}

impl Control<'_> {
    fn cancelled(&self) -> bool {
        self.cancel.is_some_and(|c| c.load(Ordering::Relaxed))
    }
    fn stage(&mut self, s: Stage) {
        if let Some(p) = self.progress.as_mut() {
            p(Progress::Stage(s));
        }
    }
}

/// Seconds spent in each stage of one capture (a stage missing from a worker's line is 0).
#[derive(Debug, Clone, Default, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct StageSeconds {
    pub read: f64,
    pub reconstruct: f64,
    pub conform: f64,
    pub score: f64,
    pub preview: f64,
    pub total: f64,
}

/// `report.json` of a result.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ProcessReport {
    pub format: &'static str,
    pub version: u32,
    pub capture: String,
    pub station: String,
    pub subject: Option<String>,
    pub reconstruction: ReconstructReport,
    pub conformation: ConformReport,
    /// against the station's current model, when it has one
    pub scores: Option<Score>,
    /// the template's measurements of the result (`[measure]`), when it has definitions
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measurements: Option<Vec<Measurement>>,
    /// the same with the result's posture removed
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measurements_normalised: Option<Vec<Measurement>>,
    /// from the station's weight regression (`[measure] weight`)
    #[serde(skip_serializing_if = "Option::is_none")]
    pub weight: Option<WeightPrediction>,
    /// why a measurement could not be taken (the capture is still processed)
    #[serde(skip_serializing_if = "Option::is_none")]
    pub measurement_error: Option<String>,
    /// the scan landmarks an operator placed and the fit used, when it used any
    #[serde(skip_serializing_if = "Option::is_none")]
    pub manual_landmarks: Option<Vec<PlacedLandmark>>,
    pub seconds: StageSeconds,
}

/// A scan landmark as the report names it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlacedLandmark {
    pub name: String,
    pub position: [f64; 3],
}

impl std::fmt::Display for ProcessReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let c = &self.conformation;
        write!(
            f,
            "capture {}: scan of {} points; conformed {} vertices in {} iterations, mean distance {:.3}% of the diagonal, {} filled, {} folded; {:.2} s (reconstruct {:.2}, conform {:.2})",
            self.capture,
            c.scan_points,
            c.template_vertices,
            c.iterations.len(),
            c.mean_distance_relative * 100.0,
            c.filled,
            c.folded_triangles,
            self.seconds.total,
            self.seconds.reconstruct,
            self.seconds.conform
        )?;
        if let Some(s) = &self.scores {
            let z: Vec<String> = s
                .scores_sd
                .iter()
                .take(3)
                .map(|z| format!("{z:+.2}"))
                .collect();
            write!(
                f,
                "; scores (sd) [{}], mahalanobis {:.2}",
                z.join(", "),
                s.mahalanobis
            )?;
        }
        if let Some(w) = &self.weight {
            write!(f, "; weight {:.1} kg ({:.1}-{:.1})", w.kg, w.low, w.high)?;
        }
        for w in c.distortion_warning.iter().chain(&c.placement_warning) {
            write!(f, "\nwarning: {w}")?;
        }
        if let Some(e) = &self.measurement_error {
            write!(f, "\nmeasurements: {e}")?;
        }
        Ok(())
    }
}

/// One processed capture, in memory.
pub struct Processed {
    pub id: String,
    pub scan: Mesh,
    pub conformed: Mesh,
    pub report: ProcessReport,
    pub preview: image::RgbImage,
    /// what the capture page's 3D viewer draws beside the meshes
    pub view: super::view::View,
}

/// The files of a result folder (and [`super::view::VIEW_FILE`], which older results lack).
pub const RESULT_FILES: [&str; 4] = ["scan.ply", "conformed.ply", "report.json", "preview.png"];

impl Processed {
    /// Writes `results/<id>/` with [`RESULT_FILES`]: into a hidden temporary folder
    /// first, every file synced, then renamed into place (an older result of the same
    /// capture is replaced only then), so there is never half a result under its id.
    /// Returns the folder.
    pub fn write(&self, results: &Path) -> Result<PathBuf, StageError> {
        let staged = self.stage(results)?;
        publish(results, &self.id, &staged).map_err(|(path, source)| {
            let _ = std::fs::remove_dir_all(&staged);
            self.write_error(&path, source)
        })
    }

    fn write_error(&self, path: &Path, source: std::io::Error) -> StageError {
        StageError::new(
            Stage::Write,
            &self.id,
            StageCause::Io {
                path: path.display().to_string(),
                source,
            },
        )
    }

    /// The first half of [`Processed::write`]: the complete result in a hidden folder of
    /// `results` (`.<id>.partial-*`), every file synced, not yet under its id. A worker
    /// publishes it only once the journal says the job is still its own.
    pub fn stage(&self, results: &Path) -> Result<PathBuf, StageError> {
        let fail = |path: &Path, source: std::io::Error| self.write_error(path, source);
        crate::paths::check_plain_name("capture id", &self.id).map_err(|m| {
            fail(
                results,
                std::io::Error::new(std::io::ErrorKind::InvalidInput, m),
            )
        })?;
        std::fs::create_dir_all(results).map_err(|e| fail(results, e))?;
        let tag = format!("{}-{}", std::process::id(), unique());
        let tmp = results.join(format!(".{}.partial-{tag}", self.id));
        let enc = crate::mesh::io::PlyEncoding::BinaryLittleEndian;
        let json = serde_json::to_vec_pretty(&self.report).expect("a report serialises");
        let view = serde_json::to_vec(&self.view).expect("a view serialises");
        let files: [(&str, Vec<u8>); 5] = [
            ("scan.ply", crate::mesh::io::ply_bytes(&self.scan, enc)),
            (
                "conformed.ply",
                crate::mesh::io::ply_bytes(&self.conformed, enc),
            ),
            ("report.json", json),
            ("preview.png", crate::render::png_bytes(&self.preview)),
            (super::view::VIEW_FILE, view),
        ];
        let result = (|| {
            std::fs::create_dir(&tmp).map_err(|e| fail(&tmp, e))?;
            for (name, bytes) in &files {
                let p = tmp.join(name);
                write_synced(&p, bytes).map_err(|e| fail(&p, e))?;
            }
            sync_dir(&tmp);
            Ok(tmp.clone())
        })();
        if result.is_err() {
            let _ = std::fs::remove_dir_all(&tmp);
        }
        result
    }
}

/// The second half of [`Processed::write`]: renames a staged result (a folder of
/// `results` holding [`RESULT_FILES`]) into place as `results/<id>`, replacing an older
/// result only then. Returns the folder, or the path and error that stopped it.
pub fn publish(
    results: &Path,
    id: &str,
    staged: &Path,
) -> Result<PathBuf, (PathBuf, std::io::Error)> {
    let invalid = |m: String| {
        (
            staged.to_path_buf(),
            std::io::Error::new(std::io::ErrorKind::InvalidInput, m),
        )
    };
    crate::paths::check_plain_name("capture id", id).map_err(|e| invalid(e.to_string()))?;
    // only a complete folder beside its final place (a rename never crosses disks)
    if staged.parent() != Some(results) {
        return Err(invalid(format!(
            "a staged result must be a folder of {}",
            results.display()
        )));
    }
    if let Some(f) = RESULT_FILES.iter().find(|f| !staged.join(f).is_file()) {
        return Err(invalid(format!("the staged result lacks {f}")));
    }
    let dir = results.join(id);
    let old = results.join(format!(".{id}.old-{}-{}", std::process::id(), unique()));
    let replacing = dir.exists();
    if replacing {
        std::fs::rename(&dir, &old).map_err(|e| (dir.clone(), e))?;
    }
    if let Err(e) = std::fs::rename(staged, &dir) {
        if replacing {
            let _ = std::fs::rename(&old, &dir);
        }
        return Err((dir, e));
    }
    sync_dir(results);
    if replacing {
        let _ = std::fs::remove_dir_all(&old);
    }
    Ok(dir)
}

/// Removes what an interrupted [`Processed::write`] left in `results` (hidden
/// `.<id>.partial-*` and `.<id>.old-*` folders); returns how many. A finished result is
/// never touched.
pub fn remove_partial_results(results: &Path) -> std::io::Result<usize> {
    let mut n = 0;
    let Ok(rd) = std::fs::read_dir(results) else {
        return Ok(0);
    };
    for e in rd {
        let e = e?;
        let name = e.file_name().to_string_lossy().to_string();
        if name.starts_with('.') && (name.contains(".partial-") || name.contains(".old-")) {
            // an .old- folder whose result was never renamed in is the only copy: restore it
            if let Some(id) = name.strip_prefix('.').and_then(|s| s.split(".old-").next())
                && name.contains(".old-")
                && !results.join(id).exists()
            {
                std::fs::rename(e.path(), results.join(id))?;
                continue;
            }
            std::fs::remove_dir_all(e.path())?;
            n += 1;
        }
    }
    Ok(n)
}

fn unique() -> u128 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0)
}

/// A station's processing set-up, held for the life of a process: the template with its
/// landmarks and groups, the conformation options, the reconstruction with its cached
/// rectification maps, and the current shape model (replaceable while running through
/// [`Pipeline::model_handle`]).
pub struct Pipeline {
    pub station: String,
    pub template: Mesh,
    pub template_landmarks: Option<Vec<Landmark>>,
    /// the template's rig, fitted before the elastic fit when no landmarks are given: a
    /// generic template's own, or the rig file `[template]` names
    pub template_rig: Option<TemplateRig>,
    pub conform: ConformOptions,
    pub reconstruction: Reconstruction,
    /// scans as meshes with holes instead of point clouds
    pub as_mesh: bool,
    model: Arc<RwLock<Option<Arc<ShapeModel>>>>,
    measuring: Option<Measuring>,
}

/// What the station measures on every result (`[measure]`).
struct Measuring {
    resolved: Resolved,
    posture: Option<PostureRemoval>,
    weight: Option<WeightModel>,
}

impl Measuring {
    /// Definitions from `[measure]` or the generic template's own; none for a template
    /// mesh without a definitions file (nothing is measured, as before).
    fn from_config(
        cfg: &StationConfig,
        figure: Option<(crate::template::Kind, crate::template::figure::Figure)>,
        template: &Mesh,
        landmarks: Option<&[Landmark]>,
    ) -> Result<Option<Measuring>, PipelineError> {
        let m = &cfg.measure;
        let bad = |what: &str, e: String| PipelineError::Measure(format!("{what}: {e}"));
        let kind = figure.as_ref().map(|(k, _)| *k);
        let defs = match (&m.definitions, kind) {
            (Some(p), _) => {
                Definitions::read(p).map_err(|e| bad("[measure] definitions", e.to_string()))?
            }
            (None, Some(crate::template::Kind::Pig)) => {
                Definitions::parse(crate::measure::PIG, "pig")
                    .map_err(|e| bad("pig", e.to_string()))?
            }
            (None, Some(crate::template::Kind::Body)) => {
                Definitions::parse(crate::measure::BODY, "body")
                    .map_err(|e| bad("body", e.to_string()))?
            }
            (None, None) => return Ok(None),
        };
        let resolved = defs
            .resolve(template, landmarks.unwrap_or(&[]))
            .map_err(|e| bad("[measure] definitions", e.to_string()))?;
        let posture = match (&m.posture_model, figure, m.normalise_posture) {
            (_, _, false) => None,
            (Some(p), _, true) => Some(PostureRemoval::Model(Box::new(ShapeModel::load(p)?))),
            (None, Some((kind, fig)), true) => {
                Some(PostureRemoval::for_figure(&fig, kind, &resolved))
            }
            (None, None, true) => None,
        };
        let weight = m
            .weight
            .as_ref()
            .map(|p| WeightModel::load(p))
            .transpose()
            .map_err(|e| bad("[measure] weight", e.to_string()))?;
        Ok(Some(Measuring {
            resolved,
            posture,
            weight,
        }))
    }

    /// Raw and posture-free measurements and the weight; a failure is reported, not
    /// fatal: the conformed result stands without them.
    fn run(&self, id: &str, mesh: &Mesh) -> MeasuredResult {
        let mut out = MeasuredResult::default();
        let raw = match self.resolved.measure_drawn(mesh) {
            Ok(drawn) => {
                let raw: Vec<Measurement> = drawn.iter().map(|d| d.measurement.clone()).collect();
                out.drawn = drawn;
                raw
            }
            Err(e) => {
                out.error = Some(e.to_string());
                return out;
            }
        };
        if let Some(p) = &self.posture {
            match p.measure(&self.resolved, id, mesh) {
                Ok(n) => out.normalised = Some(n),
                Err(e) => out.error = Some(format!("posture not removed: {e}")),
            }
        }
        if let Some(w) = &self.weight {
            // posture-free measurements when there are
            match w.predict(out.normalised.as_deref().unwrap_or(&raw)) {
                Ok(p) => out.weight = Some(p),
                Err(e) => out.error = Some(format!("no weight: {e}")),
            }
        }
        out.raw = Some(raw);
        out
    }
}

#[derive(Default)]
struct MeasuredResult {
    raw: Option<Vec<Measurement>>,
    /// the raw ones with where they were taken
    drawn: Vec<crate::measure::Drawn>,
    normalised: Option<Vec<Measurement>>,
    weight: Option<WeightPrediction>,
    error: Option<String>,
}

impl Pipeline {
    /// Sets a pipeline up from a station file's `[template]`, `[conform]`, `[rig]` and
    /// `[model]` (the model only when its file exists yet).
    pub fn from_config(cfg: &StationConfig) -> Result<Pipeline, PipelineError> {
        Self::from_config_cached(cfg, None)
    }

    /// [`Pipeline::from_config`] with a generic template kept in the folder
    /// `template_cache` between processes ([`TemplateSource::figure_cached`]).
    pub fn from_config_cached(
        cfg: &StationConfig,
        template_cache: Option<&Path>,
    ) -> Result<Pipeline, PipelineError> {
        let name = cfg.file.display().to_string();
        let rig = cfg.rig.as_ref().ok_or(PipelineError::NoRig(name.clone()))?;
        let source = cfg
            .template
            .as_ref()
            .ok_or(PipelineError::NoTemplate(name))?;
        // a generic template's figure serves the template and the posture removal alike
        let figure = source.figure_cached(template_cache)?;
        let (template, template_landmarks) = match &figure {
            Some((_, fig)) => (fig.mesh.clone(), Some(fig.landmarks())),
            None => source.load()?,
        };
        let template_rig = match &figure {
            Some((kind, fig)) => Some(TemplateRig::generic(fig, *kind)),
            None => source
                .rig_file(&template)?
                .or_else(|| crate::conform::automatic_rig(&template, &cfg.conform)),
        };
        // each capture's fit would fail on it: said once, here, and by `check`
        cfg.conform
            .check_groups(&template)
            .map_err(|e| PipelineError::Conform {
                file: cfg.file.display().to_string(),
                msg: e.to_string(),
            })?;
        let measuring =
            Measuring::from_config(cfg, figure, &template, template_landmarks.as_deref())?;
        let reconstruction = Reconstruction::load(&rig.file, rig.calibration.as_deref())?;
        let model = match &cfg.model.file {
            Some(p) if p.exists() => Some(Arc::new(ShapeModel::load(p)?)),
            _ => None,
        };
        Ok(Pipeline {
            station: cfg.station.name.clone(),
            template,
            template_landmarks,
            template_rig,
            conform: cfg.conform.clone(),
            reconstruction,
            as_mesh: rig.mesh,
            model: Arc::new(RwLock::new(model)),
            measuring,
        })
    }

    /// A handle through which another thread can replace the model between captures.
    pub fn model_handle(&self) -> Arc<RwLock<Option<Arc<ShapeModel>>>> {
        self.model.clone()
    }

    /// The capture set in `dir` opened, its id checked against its folder's name
    /// (`fallback_id`), and every pod's images read.
    fn read_set(
        &self,
        dir: &Path,
        fallback_id: &str,
    ) -> Result<(CaptureSetDir, String, PodPixels), StageError> {
        let set = CaptureSetDir::open(dir)
            .map_err(|e| StageError::new(Stage::Read, fallback_id, e.into()))?;
        let id = set.id().to_string();
        if id != fallback_id {
            // results, journal and API are keyed by the folder's name
            return Err(StageError::new(
                Stage::Read,
                fallback_id,
                StageCause::CaptureSet(CaptureSetError::Manifest {
                    path: dir.join("manifest.json").display().to_string(),
                    msg: format!("its id '{id}' is not its folder's name '{fallback_id}'"),
                }),
            ));
        }
        let images = read_pod_images(&set, &self.reconstruction.pods)
            .map_err(|e| StageError::new(Stage::Read, &id, e.into()))?;
        Ok((set, id, images))
    }

    /// Landmarks an operator placed on the scan, checked as the page checks them
    /// (points, on the scan, finite, not in one plane) whether they came from the page or
    /// a file: the checked landmarks, and the placed points for the report.
    #[allow(clippy::type_complexity)]
    fn operator_landmarks(
        &self,
        id: &str,
        scan: &Mesh,
        scan_landmarks: Option<&[Landmark]>,
    ) -> Result<(Option<Vec<Landmark>>, Option<Vec<PlacedLandmark>>), StageError> {
        let bad =
            |e: String| StageError::new(Stage::Conform, id, ConformError::Landmarks(e).into());
        Ok(match (scan_landmarks, self.template_landmarks.as_deref()) {
            (None, _) => (None, None),
            (Some(_), None) => {
                return Err(bad(
                    "scan landmarks were given, but the station's template has none to pair them with ([template] landmarks)".into(),
                ));
            }
            (Some(s), Some(t)) => {
                let placed: Vec<PlacedLandmark> = crate::mesh::landmarks::scan_points(s)
                    .map_err(|e| bad(e.to_string()))?
                    .into_iter()
                    .map(|(name, p)| PlacedLandmark {
                        name,
                        position: [p.x, p.y, p.z],
                    })
                    .collect();
                let names: Vec<String> = t.iter().map(|l| l.name.clone()).collect();
                let checked =
                    super::placed::check(&placed, &names, scan).map_err(|e| bad(e.to_string()))?;
                (Some(checked), Some(placed))
            }
        })
    }

    /// The result's preview (coloured by its distance to the scan) and what the capture
    /// page's 3D viewer draws beside the meshes.
    fn pictures(
        &self,
        conformed: &Mesh,
        scan: &Mesh,
        drawn: &[crate::measure::Drawn],
    ) -> (image::RgbImage, super::view::View) {
        let distance = distances_to_scan(conformed, scan);
        let preview = preview(conformed, distance.as_deref());
        let view = super::view::View::new(
            conformed,
            &self.template,
            distance.as_deref(),
            self.template_landmarks.as_deref(),
            drawn,
        );
        (preview, view)
    }

    /// Processes the capture set in `dir`: reads and checks it, reconstructs the scan,
    /// conforms the template onto it (aligned automatically, or by `scan_landmarks` that
    /// an operator placed on an earlier scan of this set, paired by name with the
    /// template's), scores the result against the current model and renders a preview.
    /// Nothing is written; see [`Processed::write`].
    ///
    /// Example: `conformd process captures/<id> --config station.toml --out results`;
    /// see `tests/pipeline.rs`.
    pub fn process(
        &mut self,
        dir: &Path,
        scan_landmarks: Option<&[Landmark]>,
        control: &mut Control,
    ) -> Result<Processed, StageError> {
        let t_all = Instant::now();
        let fallback_id = dir
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        let mut seconds = StageSeconds::default();

        control.stage(Stage::Read);
        let t = Instant::now();
        let (set, id, images) = self.read_set(dir, &fallback_id)?;
        seconds.read = t.elapsed().as_secs_f64();
        let stop = |stage| StageError::new(stage, &id, StageCause::Cancelled);
        if control.cancelled() {
            return Err(stop(Stage::Reconstruct));
        }

        control.stage(Stage::Reconstruct);
        let t = Instant::now();
        let (scan, reconstruction) = self
            .reconstruction
            .run(&images.pixels, self.as_mesh)
            .map_err(|e| {
                let seen = images.named(e.pod());
                StageError::new(Stage::Reconstruct, &id, StageCause::Reconstruct(e, seen))
            })?;
        if scan.vertices.len() < MIN_SCAN_POINTS {
            return Err(StageError::new(
                Stage::Reconstruct,
                &id,
                StageCause::EmptyScan {
                    points: scan.vertices.len(),
                },
            ));
        }
        seconds.reconstruct = t.elapsed().as_secs_f64();
        if control.cancelled() {
            return Err(stop(Stage::Conform));
        }

        control.stage(Stage::Conform);
        let t = Instant::now();
        let (checked, placed) = self.operator_landmarks(&id, &scan, scan_landmarks)?;
        let pairs = checked
            .as_deref()
            .zip(self.template_landmarks.as_deref())
            .map(|(s, t)| (t, s));
        let never = AtomicBool::new(false);
        let cancel = control.cancel.unwrap_or(&never);
        let conformed = {
            let mut tick = |it: &IterationReport| {
                if let Some(p) = control.progress.as_mut() {
                    p(Progress::Iteration(it));
                }
            };
            conform::conform_rigged(
                &self.template,
                self.template_rig.as_ref(),
                &scan,
                pairs,
                &self.conform,
                &mut tick,
                cancel,
            )
            .map_err(|e| StageError::new(Stage::Conform, &id, e.into()))?
        };
        seconds.conform = t.elapsed().as_secs_f64();

        control.stage(Stage::Score);
        let t = Instant::now();
        let model = self.model.read().map(|m| m.clone()).unwrap_or(None);
        let scores = model
            .map(|m| m.score(&id, &conformed.mesh))
            .transpose()
            .map_err(|e| StageError::new(Stage::Score, &id, e.into()))?;
        let measured = self
            .measuring
            .as_ref()
            .map(|m| m.run(&id, &conformed.mesh))
            .unwrap_or_default();
        seconds.score = t.elapsed().as_secs_f64();

        let t = Instant::now();
        let (preview, view) = self.pictures(&conformed.mesh, &scan, &measured.drawn);
        seconds.preview = t.elapsed().as_secs_f64();
        seconds.total = t_all.elapsed().as_secs_f64();
        Ok(Processed {
            report: ProcessReport {
                format: "conformd-result",
                version: 1,
                capture: id.clone(),
                station: set.manifest.station.clone(),
                subject: set.manifest.subject.clone(),
                reconstruction,
                conformation: conformed.report,
                scores,
                measurements: measured.raw,
                measurements_normalised: measured.normalised,
                weight: measured.weight,
                measurement_error: measured.error,
                manual_landmarks: placed,
                seconds,
            },
            id,
            scan,
            conformed: conformed.mesh,
            preview,
            view,
        })
    }
}

/// Every pod's images of a capture set, in the order of `pods`, with the cameras' names
/// and files for later errors.
pub struct PodPixels {
    pub pixels: Vec<(Vec<u8>, Vec<u8>)>,
    /// (pod, "camera ID (FILE)")
    pub cameras: Vec<(String, String)>,
}

impl PodPixels {
    /// The cameras of `pod`, for an error sentence.
    pub fn named(&self, pod: &str) -> String {
        self.cameras
            .iter()
            .filter(|(p, _)| p == pod)
            .map(|(_, c)| c.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// Reads every pod's left and right image from a capture set, each checked against the
/// pod's calibrated size, before any matching starts.
pub fn read_pod_images(
    set: &CaptureSetDir,
    pods: &[crate::stereo::calib::Pod],
) -> Result<PodPixels, CaptureSetError> {
    set.check_distinct_files()?;
    let mut pixels = Vec::new();
    let mut cameras = Vec::new();
    for pod in pods {
        let size = (pod.left.width, pod.left.height);
        let mut pair = Vec::with_capacity(2);
        for side in ["left", "right"] {
            let img = set.grey_image(&pod.id, side, size)?;
            let cam = set.camera(&pod.id, side)?;
            cameras.push((
                pod.id.clone(),
                format!("camera {} ({})", cam.id, set.dir.join(&cam.file).display()),
            ));
            pair.push(img.into_raw());
        }
        let right = pair.pop().expect("two sides");
        let left = pair.pop().expect("two sides");
        pixels.push((left, right));
    }
    Ok(PodPixels { pixels, cameras })
}

/// Each vertex's distance to the scan's surface (None when the scan has none).
pub fn distances_to_scan(conformed: &Mesh, scan: &Mesh) -> Option<Vec<f64>> {
    let surface = crate::conform::correspond::ScanSurface::new(scan).ok()?;
    Some(
        conformed
            .vertices
            .iter()
            .map(|p| surface.distance(p))
            .collect(),
    )
}

/// The result's preview: the conformed mesh from two views, coloured by each vertex's
/// distance to the scan (`distance`, from [`distances_to_scan`]).
pub fn preview(conformed: &Mesh, distance: Option<&[f64]>) -> image::RgbImage {
    use crate::render::{Colouring, RenderOptions, View};
    let colouring = match distance {
        // the station works in metres; a fit's distances read in millimetres
        Some(d) => Colouring::distances(d.iter().map(|d| d * 1000.0).collect(), "MM"),
        None => Colouring::Plain,
    };
    let views = ["three-quarter", "side"]
        .iter()
        .filter_map(|v| View::named(v))
        .collect();
    crate::render::render(
        conformed,
        &colouring,
        &RenderOptions {
            width: 640,
            height: 400,
            views,
            ..Default::default()
        },
    )
}
