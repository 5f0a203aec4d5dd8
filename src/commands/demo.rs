//! The station demo (`make demo`): no hardware, the real service. A virtual rig renders a
//! pig in twelve postures (or the first few of them); the daemon runs on replay cameras
//! and a simulated trigger box over a pseudo-terminal; one RFID read per posture fires a
//! capture through the box; every capture is reconstructed, conformed and scored; the
//! posture model is built; a table and the mode sheet come out.

use super::*;
use crate::daemon::{Handle, Shared, journal::State};
use crate::station::StationConfig;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Twelve postures (degrees per joint group) spread over swing, nod and twist.
const POSTURES: [&str; 12] = [
    "swing=12,nod=-6,twist=2",
    "swing=-10,nod=5,twist=-3",
    "swing=4,nod=10,twist=5",
    "swing=-14,nod=-9,twist=1",
    "swing=0,nod=2,twist=-6",
    "swing=8,nod=-12,twist=-2",
    "swing=-5,nod=-2,twist=6",
    "swing=15,nod=6,twist=-5",
    "swing=-2,nod=-4,twist=3",
    "swing=6,nod=12,twist=0",
    "swing=-12,nod=0,twist=4",
    "swing=2,nod=-10,twist=-4",
];

/// One row of the demo's table.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoRow {
    pub capture: String,
    pub subject: String,
    pub seconds: f64,
    /// mean distance of the conformed mesh to its scan, % of the diagonal
    pub mean_distance_pct: f64,
    /// share of template vertices filled in (no scan data near them)
    pub filled_pct: f64,
    /// standard deviation of the edge-length variation against the template
    pub distortion: f64,
    /// the first three mode scores, in standard deviations
    pub scores: Vec<f64>,
}

/// What the station demo did and wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct StationDemo {
    pub rows: Vec<DemoRow>,
    pub failed: Vec<(String, String)>,
    pub seconds_render: f64,
    pub seconds_station: f64,
    pub results: PathBuf,
    pub sheet: Option<PathBuf>,
    pub url: String,
    pub explained: Vec<f64>,
}

impl std::fmt::Display for StationDemo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "{:<30} {:<7} {:>7} {:>9} {:>7} {:>10}  top mode scores (sd)",
            "capture", "subject", "seconds", "distance", "filled", "distortion"
        )?;
        for r in &self.rows {
            let z: Vec<String> = r.scores.iter().map(|z| format!("{z:+.2}")).collect();
            writeln!(
                f,
                "{:<30} {:<7} {:>7.2} {:>8.3}% {:>6.1}% {:>10.3}  [{}]",
                r.capture,
                r.subject,
                r.seconds,
                r.mean_distance_pct,
                r.filled_pct,
                r.distortion,
                z.join(", ")
            )?;
        }
        for (id, e) in &self.failed {
            writeln!(f, "{id}: FAILED: {e}")?;
        }
        let cum: Vec<String> = self
            .explained
            .iter()
            .take(3)
            .scan(0.0, |c, e| {
                *c += e;
                Some(format!("{:.1}%", *c * 100.0))
            })
            .collect();
        writeln!(
            f,
            "{} captures processed by the daemon in {:.1} s (rendering the virtual rig's images took {:.1} s); posture model: first modes explain {} (cumulative)",
            self.rows.len(),
            self.seconds_station,
            self.seconds_render,
            cum.join(", ")
        )?;
        writeln!(f, "results: {}", self.results.display())?;
        if let Some(s) = &self.sheet {
            writeln!(f, "mode sheet: {}", s.display())?;
        }
        write!(f, "status page: {}", self.url)
    }
}

/// Waits until `done`, for at most `limit`; gives up at once when the daemon has stopped
/// (it stops on Ctrl-C and SIGTERM, as a station's does).
fn wait(
    daemon: &Handle,
    what: &str,
    limit: Duration,
    mut done: impl FnMut() -> bool,
) -> Result<(), CommandError> {
    let t = Instant::now();
    while !done() {
        if !daemon.running() {
            return Err(CommandError::Demo(format!(
                "the daemon stopped (Ctrl-C, SIGTERM, or an error logged above) while waiting for {what}"
            )));
        }
        if t.elapsed() > limit {
            return Err(CommandError::Demo(format!("waited {limit:?} for {what}")));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(())
}

/// Runs the station demo in `out` (see the module comment) on the first `captures` of
/// the twelve postures: `progress(stage, done, total)` as it goes, `show` with the
/// figures once everything is processed, then the daemon keeps serving its status page
/// while `keep_running` returns true and no Ctrl-C or SIGTERM has stopped it.
pub fn demo_station(
    out: &Path,
    captures: usize,
    progress: &mut dyn FnMut(&str, u64, u64),
    show: &mut dyn FnMut(&StationDemo),
    keep_running: &mut dyn FnMut() -> bool,
) -> Result<StationDemo, CommandError> {
    // refused before anything of an earlier run is removed
    if !(3..=POSTURES.len()).contains(&captures) {
        return Err(CommandError::Usage(format!(
            "demo: {captures} captures asked for; the demo has 3 to {} (the posture model needs 3)",
            POSTURES.len()
        )));
    }
    let out = std::path::absolute(out).map_err(|source| CommandError::Io {
        path: out.display().to_string(),
        source,
    })?;
    let io = |p: &Path| {
        let p = p.display().to_string();
        move |source| CommandError::Io { path: p, source }
    };
    if out.join("station").exists() {
        std::fs::remove_dir_all(out.join("station")).map_err(io(&out))?;
    }
    std::fs::create_dir_all(&out).map_err(io(&out))?;
    let rig = out.join("rig.toml");
    let example = include_str!("../../config/rig.example.toml");
    write_atomic(&rig, example.as_bytes())?;

    // the pig in twelve postures, as the rig's cameras see it
    let t = Instant::now();
    let sim = out.join("sim");
    if sim.exists() {
        std::fs::remove_dir_all(&sim).map_err(io(&sim))?;
    }
    let postures = &POSTURES[..captures];
    let mut sets = Vec::new();
    for (i, pose) in postures.iter().enumerate() {
        progress("render", i as u64, postures.len() as u64);
        sets.extend(simulate(&rig, "pig", pose, 1, 2.0, &sim)?);
    }
    let seconds_render = t.elapsed().as_secs_f64();

    // the station: replay cameras, the simulated box, the daemon
    let trigger = crate::synth::trigger_box::SimulatedBox::start()?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .map_err(io(Path::new("127.0.0.1")))?;
    let station_file = out.join("station.toml");
    let text = demo_station_file(&sets, &trigger.device, port);
    write_atomic(&station_file, text.as_bytes())?;
    let cfg = StationConfig::load(&station_file)?;
    let results = cfg.station.results();
    let t = Instant::now();
    let daemon = Handle::spawn(cfg, None)?;
    let shared = daemon.shared.clone();
    fire_and_process(&daemon, &trigger, sets.len() as u64, progress)?;
    let seconds_station = t.elapsed().as_secs_f64();

    let model_path = shared.cfg.model.file.clone().expect("set above");
    let model = crate::model::ShapeModel::load(&model_path).ok();
    let sheet = match &model {
        Some(_) => model_modes(&model_path, 3, 3.0, "three-quarter", &out.join("modes"))?
            .into_iter()
            .find(|p| p.extension().is_some_and(|e| e == "png")),
        None => None,
    };
    let (rows, failed) = demo_rows(&shared, &results, model.as_ref());
    let url = format!("http://{}/", shared.cfg.daemon.listen);
    let demo = StationDemo {
        rows,
        failed,
        seconds_render,
        seconds_station,
        results,
        sheet,
        url,
        explained: model.map(|m| m.explained).unwrap_or_default(),
    };
    show(&demo);
    // until the caller says stop, or a signal has stopped the daemon
    while keep_running() && daemon.running() {
        std::thread::sleep(Duration::from_millis(200));
    }
    drop(shared);
    daemon.stop()?;
    drop(trigger);
    Ok(demo)
}

/// The demo's station file: the example rig, replay cameras on the rendered `sets`, the
/// simulated box at `device`, the API on `port`.
fn demo_station_file(sets: &[PathBuf], device: &Path, port: u16) -> String {
    let replay: Vec<String> = sets
        .iter()
        .map(|s| format!("{:?}", s.display().to_string()))
        .collect();
    let mut cameras = String::new();
    for pod in ["pod1", "pod2"] {
        for side in ["left", "right"] {
            cameras.push_str(&format!(
                "\n[[cameras]]\nid = \"{pod}-{side}\"\npod = \"{pod}\"\nside = \"{side}\"\nreplay = [{}]\n",
                replay.join(", ")
            ));
        }
    }
    format!(
        "# written by `conformd demo`: a virtual crate with replay cameras and a simulated trigger box\n\
         [station]\nname = \"demo-crate\"\ndata = \"station\"\n\n\
         [template]\ngeneric = \"pig\"\nvertices = 10000\n\n\
         [rig]\nfile = \"rig.toml\"\ncalibration = \"sim/calibration\"\n\n\
         [capture]\nmax_skew_ms = 50.0\n[capture.camera_settings]\nformat = \"GREY\"\nwidth = 1280\nheight = 960\n\n\
         [trigger]\ndevice = {:?}\n\n\
         [model]\nfile = \"station/model.json\"\n\n\
         [daemon]\nlisten = \"127.0.0.1:{port}\"\nrescan_s = 5.0\n{cameras}",
        device.display().to_string()
    )
}

/// `n` captures fired through the box (an RFID read each), then every capture waited
/// for and the posture model rebuilt.
fn fire_and_process(
    daemon: &Handle,
    trigger: &crate::synth::trigger_box::SimulatedBox,
    n: u64,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<(), CommandError> {
    let shared = daemon.shared.clone();
    wait(daemon, "the trigger box", Duration::from_secs(20), || {
        shared
            .rig
            .lock()
            .map(|r| r.trigger_connected)
            .unwrap_or(false)
    })?;
    for i in 0..n {
        trigger.rfid(&format!("pig-{:02}", i + 1));
        wait(daemon, "a capture", Duration::from_secs(60), || {
            shared.rig.lock().map(|r| r.captures > i).unwrap_or(false)
        })?;
    }
    let mut last = u64::MAX;
    wait(
        daemon,
        "every capture to be processed",
        Duration::from_secs(1800),
        || {
            let c = shared.journal().counts().unwrap_or_default();
            let settled = c.done + c.failed;
            if settled != last {
                progress("process", settled, n);
                last = settled;
            }
            settled >= n && c.queued == 0 && c.running == 0
        },
    )?;
    crate::daemon::request_model_rebuild(&shared);
    wait(daemon, "the model", Duration::from_secs(300), || {
        !shared.model_busy.load(Ordering::SeqCst)
    })?;
    Ok(())
}

/// One row per processed capture (its fit figures and model scores), and the failed
/// captures with their errors.
#[allow(clippy::type_complexity)]
fn demo_rows(
    shared: &Shared,
    results: &Path,
    model: Option<&crate::model::ShapeModel>,
) -> (Vec<DemoRow>, Vec<(String, String)>) {
    let jobs = shared.journal().list(None, usize::MAX).unwrap_or_default();
    let mut rows = Vec::new();
    let mut failed = Vec::new();
    for job in jobs.iter().rev() {
        if job.state != State::Done {
            failed.push((job.id.clone(), job.error.clone().unwrap_or_default()));
            continue;
        }
        let dir = results.join(&job.id);
        let report: serde_json::Value =
            crate::files::read_limited(&dir.join("report.json"), crate::files::MAX_REPORT_BYTES)
                .ok()
                .and_then(|b| serde_json::from_slice(&b).ok())
                .unwrap_or_default();
        let c = &report["conformation"];
        let scores = match (model, mesh::read_mesh(&dir.join("conformed.ply"))) {
            (Some(m), Ok(mesh)) => m
                .score(&job.id, &mesh)
                .map(|s| s.scores_sd.into_iter().take(3).collect())
                .unwrap_or_default(),
            _ => Vec::new(),
        };
        let f = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
        rows.push(DemoRow {
            capture: job.id.clone(),
            subject: job.subject.clone().unwrap_or_default(),
            seconds: f(&report["seconds"]["total"]),
            mean_distance_pct: f(&c["mean_distance_relative"]) * 100.0,
            filled_pct: f(&c["filled"]) / f(&c["template_vertices"]) * 100.0,
            distortion: f(&c["final_variation"]["edge_length"]["std"]),
            scores,
        });
    }
    (rows, failed)
}
