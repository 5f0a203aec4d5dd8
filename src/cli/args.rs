//! The command line's arguments: every command and flag, with its help text.

use clap::{Parser, Subcommand};
use conformd::commands;
use conformd::conform::Method;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "conformd",
    version,
    about = "Photogrammetry station daemon: conform a template mesh onto scans"
)]
pub struct Cli {
    #[command(subcommand)]
    pub cmd: Cmd,
}

#[derive(Subcommand)]
pub enum Cmd {
    /// Conform a template mesh onto a scan (Ju et al. 2004, or conformd's default method).
    Conform(ConformArgs),
    /// Check a station file: print the resolved configuration, or every problem with its
    /// line.
    Check(CheckArgs),
    /// Process one capture set through the station's pipeline (reconstruct, conform,
    /// score) and write its result folder (scan.ply, conformed.ply, report.json,
    /// preview.png) atomically under --out.
    Process(ProcessArgs),
    /// Run the station: capture on trigger, watch captures/ and incoming/, process every
    /// set once (journal, worker processes), serve the HTTP API and status page.
    Daemon(DaemonArgs),
    /// Run jobs from a journal shared by several machines ([journal] url = postgres://...)
    /// on this one: claim, hold a lease, process as the daemon does, publish the result.
    Worker(WorkerArgs),
    /// The main job on built-in defaults, no hardware: `station` runs the daemon on a
    /// virtual crate (replay cameras, a simulated trigger box), fires 12 captures of a pig
    /// through the box, processes them and builds the posture model; `paper` runs the
    /// paper's sphere-to-box case with missing data, both methods.
    Demo(DemoArgs),
    /// Write a generic pig or body template (OBJ with groups, or PLY) and its landmarks.
    Template(TemplateArgs),
    /// Rig a template mesh automatically: limbs at its geodesic extremities, joints where
    /// each meets the body and half-way down it, skin weights along the surface, a length
    /// field per limb. The generic templates' rigs come from `template`.
    Autorig(AutorigArgs),
    /// Render a shaded preview PNG of a mesh.
    Render(RenderArgs),
    /// Capture one set with the station's cameras and trigger (atomically).
    Capture(CaptureArgs),
    /// Render capture sets of a subject as the rig's cameras would see it (speckle
    /// projector, lens distortion, sensor noise), with ground truth and calibrations.
    Simulate(SimulateArgs),
    /// Stereo calibration of one pod from chessboard pairs (leftNN/rightNN images); or,
    /// with --placement, every pod's pose in the rig frame from one capture set of a
    /// board that all pods see (writes the rig file with measured poses).
    Calibrate(CalibrateArgs),
    /// Reconstruct a capture set into a fused scan in the rig frame (OpenCV SGBM).
    Reconstruct(ReconstructArgs),
    /// Turns a recorded, rectified pair and its calibration (Middlebury or KITTI
    /// calib.txt) into a rig file, a pod calibration and a capture set, to replay it
    /// through reconstruct and process.
    ImportPair(ImportPairArgs),
    /// Disparity of an already-rectified pair (PFM, or 16-bit PNG x16 for .png).
    Disparity(DisparityArgs),
    /// List V4L2 cameras with their stable names, formats, sizes and controls.
    Cameras,
    /// Measurements of conformed meshes (lengths, girths, widths, heights, area, volume),
    /// as JSON on standard output and optionally CSV; with --model, also with the
    /// posture removed.
    Measure(MeasureArgs),
    /// All results as CSV (a row per capture: subject, fit figures, measurements raw
    /// and posture-free, weight), to standard output or --out; results an operator
    /// rejected (review.json) are left out.
    Export(ExportArgs),
    /// Statistical shape model over conformed meshes.
    Model {
        #[command(subcommand)]
        cmd: ModelCmd,
    },
    /// Describe a mesh: topology, watertightness, folded triangles, and with --original
    /// the paper's variation figures against it.
    Info(InfoArgs),
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum DemoKind {
    Station,
    Paper,
}

#[derive(Subcommand)]
pub enum ModelCmd {
    /// Build a model from conformed meshes (one template).
    Build {
        /// conformed meshes
        #[arg(required = true)]
        meshes: Vec<PathBuf>,
        #[arg(long)]
        out: PathBuf,
        /// procrustes (shape only), rigid (size kept) or none
        #[arg(long, default_value = "procrustes")]
        align: conformd::model::Align,
        /// model one vertex group alone (e.g. torso)
        #[arg(long)]
        group: Option<String>,
        #[arg(long, default_value_t = 30)]
        max_modes: usize,
        /// also compute compactness, generalisation and specificity (slower)
        #[arg(long)]
        quality: bool,
        /// the meshes are one subject in many postures: every mode is a posture mode
        /// (for `measure --normalise-posture`)
        #[arg(long)]
        posture: bool,
    },
    /// Fit the weight regression: weights a station recorded (`id,kg` rows: capture id
    /// or subject tag) against the measurements in the results' report.json; prints
    /// its leave-one-out error. Name the file in `[measure] weight`.
    Weigh {
        /// the recorded weights
        #[arg(long)]
        fit: PathBuf,
        /// the station's results folder
        #[arg(long)]
        results: PathBuf,
        /// measurements to use, comma-separated (default: all)
        #[arg(long, value_delimiter = ',')]
        features: Option<Vec<String>>,
        #[arg(long)]
        out: PathBuf,
    },
    /// The posture model of a generic template: random postures of it (every pose
    /// parameter within +/- --degrees), for `measure --normalise-posture`.
    Posture {
        kind: conformd::template::Kind,
        /// the template's resolution: that of the results to be measured
        #[arg(long, default_value_t = 10_000)]
        vertices: usize,
        #[arg(long, default_value_t = 60)]
        postures: usize,
        #[arg(long, default_value_t = 20.0)]
        degrees: f64,
        #[arg(long)]
        out: PathBuf,
    },
    /// Mean and mean +/- k sigma along the first modes, as meshes and a PNG sheet.
    Modes {
        #[arg(long)]
        model: PathBuf,
        #[arg(long, default_value_t = 3)]
        modes: usize,
        #[arg(long, default_value_t = 3.0)]
        sigma: f64,
        #[arg(long, default_value = "three-quarter")]
        view: String,
        #[arg(long)]
        out: PathBuf,
    },
    /// Mode scores, reconstruction residual and Mahalanobis distance of meshes.
    Score {
        #[arg(long)]
        model: PathBuf,
        #[arg(required = true)]
        meshes: Vec<PathBuf>,
    },
}

// Each command's flags (the help text of each is its variant's in `Cmd`).

#[derive(clap::Args)]
pub struct ConformArgs {
    /// template mesh (.obj, .ply or .off), or `pig` / `body` for a generic template
    /// (10,000 vertices, with its own landmarks); without it the config's [template]
    #[arg(long)]
    pub template: Option<String>,
    /// vertex groups of a template mesh: lines `name i j k ...`
    #[arg(long)]
    pub template_groups: Option<PathBuf>,
    /// the template mesh's rig (`autorig`, or one's own): fitted before the elastic
    /// fit when there are no landmarks (a generic template brings its own)
    #[arg(long)]
    pub template_rig: Option<PathBuf>,
    /// scan: a mesh with holes or a point cloud (.ply, .obj or .off)
    #[arg(long)]
    pub scan: PathBuf,
    /// template landmarks: `name vertex_index` lines (or `name x y z`, or MeshLab .pp)
    #[arg(long)]
    pub template_landmarks: Option<PathBuf>,
    /// scan landmarks: `name x y z` lines or MeshLab .pp; without landmarks the
    /// template is aligned automatically
    #[arg(long)]
    pub scan_landmarks: Option<PathBuf>,
    /// conformation options (TOML: a conform.toml, or a station config's [conform])
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// method: `paper` (as published) or `default` (conformd's); overrides the config
    #[arg(long)]
    pub method: Option<MethodArg>,
    /// output mesh (.ply or .obj)
    #[arg(long)]
    pub out: PathBuf,
    /// JSON report with the per-iteration figures
    #[arg(long)]
    pub report: Option<PathBuf>,
}

#[derive(clap::Args)]
pub struct CheckArgs {
    /// the station file (TOML)
    pub config: PathBuf,
}

#[derive(clap::Args)]
pub struct ProcessArgs {
    /// the capture set's folder
    pub capture: PathBuf,
    /// the station file ([template], [conform], [rig], [model])
    #[arg(long)]
    pub config: PathBuf,
    /// results folder; the result goes to OUT/<capture id>/
    #[arg(long)]
    pub out: PathBuf,
    /// print one JSON line (what the daemon reads) instead of the summary
    #[arg(long)]
    pub json: bool,
    /// exit when this process is no longer the parent (the daemon's workers)
    #[arg(long, hide = true)]
    pub parent: Option<u32>,
    /// leave the result complete under a hidden name in OUT and report it, for the
    /// worker to publish once the journal says the job is still its own
    #[arg(long, hide = true)]
    pub stage: bool,
    /// scan landmarks to fit by (`name x y z` lines, or MeshLab .pp), paired by name
    /// with the template's: what an operator placed on the capture page
    #[arg(long)]
    pub landmarks: Option<PathBuf>,
    /// a folder where a generic template is kept once built, for the next process
    /// of the same program (the daemon's workers use `<data>/cache`)
    #[arg(long)]
    pub template_cache: Option<PathBuf>,
}

#[derive(clap::Args)]
pub struct DaemonArgs {
    /// the station file
    #[arg(long)]
    pub config: PathBuf,
}

#[derive(clap::Args)]
pub struct WorkerArgs {
    /// a station file for this machine: [station] data (where it mounts the shared
    /// storage), [journal], [template], [rig], [conform], [worker]
    #[arg(long)]
    pub config: PathBuf,
}

#[derive(clap::Args)]
pub struct DemoArgs {
    #[arg(value_enum, default_value = "station")]
    pub which: DemoKind,
    #[arg(long, default_value = "demo-output")]
    pub out: PathBuf,
    /// station demo: keep the daemon and its status page running until Ctrl-C
    #[arg(long)]
    pub keep_running: bool,
    /// station demo: how many of the twelve postures to capture (a quicker look; the
    /// posture model needs at least 3)
    #[arg(long, default_value_t = 12, value_parser = clap::value_parser!(u8).range(3..=12))]
    pub captures: u8,
}

#[derive(clap::Args)]
pub struct TemplateArgs {
    /// `pig` or `body`
    pub kind: conformd::template::Kind,
    /// about how many vertices (2,000 to 100,000 is usual)
    #[arg(long, default_value_t = 10_000)]
    pub vertices: usize,
    /// pose, degrees per joint group, e.g. `swing=12,nod=-8,twist=5`
    #[arg(long, default_value = "")]
    pub pose: String,
    /// shape factors, e.g. `length=1.1,girth=0.95`
    #[arg(long, default_value = "")]
    pub shape: String,
    /// output mesh (.obj keeps the groups); landmarks go beside it as .landmarks
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args)]
pub struct AutorigArgs {
    /// the template mesh (.obj, .ply, .off)
    pub mesh: PathBuf,
    /// geodesic extremities tried as limbs
    #[arg(long, default_value_t = 10)]
    pub limbs: usize,
    /// the rig file (default: beside the mesh as MESH.rig.json)
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// also a PNG of the mesh coloured by bone, from the front, side and top
    #[arg(long)]
    pub preview: Option<PathBuf>,
}

#[derive(clap::Args)]
pub struct RenderArgs {
    pub mesh: PathBuf,
    /// `none`, `group`, or `distance-to=SCAN`
    #[arg(long, default_value = "none")]
    pub colour_by: commands::ColourBy,
    /// comma-separated views: front, back, left, right, side, top, three-quarter
    #[arg(long, default_value = "three-quarter,side", value_delimiter = ',')]
    pub views: Vec<String>,
    #[arg(long, default_value_t = 800)]
    pub width: u32,
    #[arg(long, default_value_t = 600)]
    pub height: u32,
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args)]
pub struct CaptureArgs {
    /// station config with [capture], [[cameras]] and optionally [trigger]
    #[arg(long)]
    pub config: PathBuf,
    /// the animal's or person's id, recorded in the manifest
    #[arg(long)]
    pub subject: Option<String>,
}

#[derive(clap::Args)]
pub struct SimulateArgs {
    #[arg(long)]
    pub rig: PathBuf,
    /// a mesh file, or `pig` / `body` (posed with --pose)
    #[arg(long, required_unless_present = "chessboard")]
    pub subject: Option<String>,
    /// render chessboard calibration views instead (inner corners, e.g. 9x6)
    #[arg(long)]
    pub chessboard: Option<String>,
    /// chessboard square size (m)
    #[arg(long, default_value_t = 0.03)]
    pub square: f64,
    /// chessboard views per pod
    #[arg(long, default_value_t = 15)]
    pub views: usize,
    /// with --chessboard: one capture set of the board lying on the rig's floor, seen
    /// by every pod (for `calibrate --placement`), instead of calibration views
    #[arg(long, requires = "chessboard")]
    pub placement: bool,
    /// with --placement: the board's long side turned this many degrees from the rig's
    /// x towards its y
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub board_yaw: f64,
    #[arg(long, default_value = "")]
    pub pose: String,
    #[arg(long, default_value_t = 1)]
    pub captures: usize,
    /// sensor noise, grey levels (standard deviation)
    #[arg(long, default_value_t = 2.0)]
    pub noise: f64,
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args)]
pub struct CalibrateArgs {
    /// chessboard pairs of one pod
    #[arg(
        long,
        required_unless_present = "placement",
        conflicts_with = "placement"
    )]
    pub images: Option<PathBuf>,
    /// a capture set of the board lying in the rig, seen by every pod
    #[arg(long, requires = "rig")]
    pub placement: Option<PathBuf>,
    /// the rig file whose pod poses --placement measures
    #[arg(long)]
    pub rig: Option<PathBuf>,
    /// folder of pod calibrations (`<pod>.yml`) for --placement's lenses
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// for --placement: where the board's origin lies in the rig frame, x,y,z (m). The
    /// board lies face up; the origin is the outer corner of the dark corner square
    /// from which the long side runs along the yaw direction and the short side to its
    /// right (seen from above)
    #[arg(long, default_value = "0,0,0", allow_hyphen_values = true)]
    pub board_origin: String,
    /// for --placement: the board's long side turned this many degrees from the rig's
    /// x towards its y
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub board_yaw: f64,
    /// inner corners, e.g. 9x6
    #[arg(long)]
    pub board: String,
    /// square size (m)
    #[arg(long)]
    pub square: f64,
    /// the pod's calibration (OpenCV YAML), or with --placement the measured rig file
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args)]
pub struct ReconstructArgs {
    pub capture: PathBuf,
    #[arg(long)]
    pub rig: PathBuf,
    /// folder of pod calibrations (`<pod>.yml`, OpenCV YAML) replacing the rig file's
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// triangulate each pod's depth grid (cut at depth jumps) into a mesh with holes
    /// instead of fusing a point cloud
    #[arg(long)]
    pub mesh: bool,
    /// a ground-truth disparity of a pod's left image (as `disparity --truth`): prints
    /// the scan's depth error, its bad-pixel share and coverage
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// divide the truth's PNG values by this instead
    #[arg(long)]
    pub truth_scale: Option<f64>,
    /// the pod whose left image the truth is of (default: the rig's first)
    #[arg(long)]
    pub truth_pod: Option<String>,
}

#[derive(clap::Args)]
pub struct ImportPairArgs {
    pub left: PathBuf,
    pub right: PathBuf,
    /// the pair's calibration: Middlebury 2014 `calib.txt` (cam0, cam1, baseline in
    /// mm, ndisp) or KITTI's (P0, P1)
    #[arg(long)]
    pub calib: PathBuf,
    /// its ground-truth disparity, copied into the capture set
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// disparities to search (default: the calibration's ndisp, else 128)
    #[arg(long)]
    pub num_disparities: Option<i32>,
    /// folder for rig.toml, calibration/ and captures/
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(clap::Args)]
pub struct DisparityArgs {
    pub left: PathBuf,
    pub right: PathBuf,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 128)]
    pub num_disparities: i32,
    #[arg(long, default_value_t = 5)]
    pub block_size: i32,
    /// what the cameras see: `natural` (passive texture: a pair given on its own is
    /// most often a photographed one; the default) or `speckle` (a projected
    /// pattern, the station's default), as `[reconstruct.sgbm] profile` in a rig file
    #[arg(long, default_value = "natural")]
    pub profile: String,
    /// a ground-truth disparity of the left image (.pfm; .png: 16-bit /256 as KITTI,
    /// 8-bit /4 as Middlebury's quarter-size sets): prints the bad-pixel share
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// divide the truth's PNG values by this instead
    #[arg(long)]
    pub truth_scale: Option<f64>,
    /// score columns from this one on (e.g. the disparity range, where the left
    /// image's first columns have no match in the right)
    #[arg(long, default_value_t = 0)]
    pub truth_from_x: u32,
    /// write each pixel's confidence in its match here too (.pfm, 0 to 1; 0 where
    /// no match is kept)
    #[arg(long)]
    pub confidence: Option<PathBuf>,
    /// drop matches less confident than this (0 to 1): fewer wrong matches, fewer
    /// matches (the profile's own by default: natural 0.1, speckle 0), as
    /// `[reconstruct.sgbm] min_confidence` in a rig file
    #[arg(long)]
    pub min_confidence: Option<f64>,
}

#[derive(clap::Args)]
pub struct MeasureArgs {
    /// conformed meshes (results of one template)
    #[arg(required = true)]
    pub meshes: Vec<PathBuf>,
    /// the template they were conformed from: `pig`, `body` or a mesh file
    #[arg(long)]
    pub template: String,
    /// a generic template's resolution (that of the results)
    #[arg(long)]
    pub vertices: Option<usize>,
    /// landmarks of a template mesh
    #[arg(long)]
    pub template_landmarks: Option<PathBuf>,
    /// vertex groups of a template mesh
    #[arg(long)]
    pub template_groups: Option<PathBuf>,
    /// measurement definitions (TOML; the generic templates bring their own:
    /// config/measurements/)
    #[arg(long)]
    pub definitions: Option<PathBuf>,
    /// a model with posture modes (`model posture`, `model build --posture`) for
    /// --normalise-posture; without it a generic template's own parts are used
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// also measure every mesh with its posture removed: each definition moved into
    /// the mesh's posture by the generic template's parts (or as its `posture_free`
    /// says), or --model's posture modes taken out
    #[arg(long)]
    pub normalise_posture: bool,
    /// write a CSV too: a row per mesh, a column per measurement
    #[arg(long)]
    pub csv: Option<PathBuf>,
    /// the meshes are one subject's in several postures: print each measurement's
    /// mean, SD and coefficient of variation over them (raw, and posture-free with
    /// --normalise-posture) instead of the per-mesh JSON
    #[arg(long)]
    pub repeatability: bool,
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// the station's results folder
    #[arg(long)]
    pub results: PathBuf,
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// also write, per subject with two results or more, how well each
    /// measurement repeats over them (mean, SD, CV; raw and posture-free) as CSV
    #[arg(long, value_name = "CSV")]
    pub repeatability: Option<PathBuf>,
}

#[derive(clap::Args)]
pub struct InfoArgs {
    pub mesh: PathBuf,
    #[arg(long)]
    pub original: Option<PathBuf>,
}

/// `--method`: the conformation method by its flag value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum MethodArg {
    /// conformd's method
    Default,
    /// Ju et al. 2004 as written
    Paper,
}

impl From<MethodArg> for Method {
    fn from(m: MethodArg) -> Method {
        match m {
            MethodArg::Default => Method::Default,
            MethodArg::Paper => Method::Paper,
        }
    }
}
