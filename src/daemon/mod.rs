//! The station service (`conformd daemon`): captures on trigger, watches `captures/` and
//! `incoming/`, keeps the journal, runs every capture once through the pipeline in a
//! worker process, rebuilds the shape model, serves the HTTP API and status page, and
//! talks to systemd. The only async module; everything it runs per capture is the
//! synchronous pipeline, in a child process (`conformd process --json`) so that a crash
//! inside a job (an OpenCV abort, a segfault, running out of memory) fails that job only.

mod capture;
pub mod http;
pub mod journal;
pub mod runner;
pub mod sets;
pub mod worker;

use crate::station::StationConfig;
use journal::{Journal, JournalError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tracing::{error, info, warn};

/// Why the daemon could not start or stopped on its own.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    #[error(transparent)]
    Journal(#[from] JournalError),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("HTTP server on {addr}: {source}")]
    Listen {
        addr: String,
        source: std::io::Error,
    },
    #[error("watching {path}: {msg}")]
    Watch { path: String, msg: String },
    #[error("{0}")]
    Config(String),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DaemonError + '_ {
    move |source| DaemonError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// A capture asked for by the trigger box, the API or a test.
pub struct CaptureRequest {
    pub subject: Option<String>,
    /// the capture's id, or why none was taken
    pub reply: Option<tokio::sync::oneshot::Sender<Result<String, CaptureRefused>>>,
}

/// Why a capture asked for was not taken.
#[derive(Debug, thiserror::Error)]
pub enum CaptureRefused {
    /// the cameras or the trigger box could not be opened (the rig tries again)
    #[error("the rig is not available: {0}")]
    RigUnavailable(String),
    #[error(transparent)]
    Failed(#[from] crate::devices::capture::CaptureError),
}

/// Why the shape model was not rebuilt.
#[derive(Debug, thiserror::Error)]
enum RebuildError {
    #[error("the station file has no [model] file")]
    NoFile,
    #[error(transparent)]
    Journal(#[from] JournalError),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    #[error(transparent)]
    Write(#[from] crate::mesh::FileError),
}

/// What the status page and `/api/status` say of the rig.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RigStatus {
    pub cameras: Vec<String>,
    pub trigger: Option<String>,
    pub trigger_connected: bool,
    pub last_capture: Option<String>,
    pub last_capture_error: Option<String>,
    pub captures: u64,
}

/// Seconds per stage of finished jobs, as Prometheus histograms.
#[derive(Debug, Clone, Default)]
pub struct Metrics {
    /// stage -> (bucket counts, sum, count)
    pub stages: BTreeMap<String, (Vec<u64>, f64, u64)>,
    pub jobs_started: u64,
    pub jobs_done: u64,
    pub worker_crashes: u64,
    pub timeouts: u64,
}

/// Upper bounds of the stage-duration histogram buckets, seconds.
pub const BUCKETS: [f64; 10] = [0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 300.0];

impl Metrics {
    fn observe(&mut self, stage: &str, seconds: f64) {
        let e = self
            .stages
            .entry(stage.to_string())
            .or_insert_with(|| (vec![0; BUCKETS.len()], 0.0, 0));
        for (i, b) in BUCKETS.iter().enumerate() {
            if seconds <= *b {
                e.0[i] += 1;
            }
        }
        e.1 += seconds;
        e.2 += 1;
    }
}

/// Everything the daemon's tasks share.
pub struct Shared {
    pub cfg: StationConfig,
    /// the `conformd` binary the workers run
    pub exe: PathBuf,
    pub journal: Mutex<Journal>,
    /// this daemon's name as a worker in the journal (`<host>:daemon:<station>`)
    pub worker_name: String,
    /// the journal cannot be reached: since when and why (the station carries on
    /// capturing; its captures are handed over when the journal is back)
    pub journal_offline: Mutex<Option<(f64, String)>>,
    /// capture sets in `captures/` waiting for the journal to be reachable
    pub waiting_handover: Mutex<std::collections::BTreeSet<String>>,
    /// entries of `captures/` and `incoming/` that will not be taken -> why
    pub refused: Mutex<BTreeMap<String, String>>,
    /// an incoming set waits for its files to settle: scan again soon
    settling: AtomicBool,
    /// scans of the capture folders so far (start-up, rescans, the watcher's hints)
    pub scans: std::sync::atomic::AtomicU64,
    /// folders the watcher saw renamed into `incoming/` (a set that came whole need not
    /// settle)
    moved_in: Arc<Mutex<std::collections::HashSet<String>>>,
    /// capture ids the journal is known to have
    known_ids: Mutex<std::collections::HashSet<String>>,
    /// something changed (a capture, a finished job, a request): scan and dispatch
    pub wake: tokio::sync::Notify,
    /// stop the running jobs now (the drain's time is up)
    pub abort: tokio::sync::Notify,
    pub stopping: AtomicBool,
    /// capture id -> when its job started
    pub running: Mutex<BTreeMap<String, Instant>>,
    pub workers: usize,
    pub metrics: Mutex<Metrics>,
    pub rig: Mutex<RigStatus>,
    pub capture: Option<std::sync::mpsc::Sender<CaptureRequest>>,
    pub model_busy: AtomicBool,
    pub model_error: Mutex<Option<String>>,
    since_rebuild: AtomicUsize,
    started: Instant,
}

impl Shared {
    /// Replaces the entries the scans will not take; a new one (or a new reason) is
    /// logged once, not at every scan.
    fn report_refused(&self, now: BTreeMap<String, String>) {
        let mut known = self.refused.lock().unwrap_or_else(|p| p.into_inner());
        for (entry, why) in &now {
            if known.get(entry) != Some(why) {
                warn!(entry = %entry, "not taken: {why}");
            }
        }
        *known = now;
    }

    pub fn captures_dir(&self) -> PathBuf {
        self.cfg.station.captures()
    }
    pub fn incoming_dir(&self) -> PathBuf {
        self.cfg.station.incoming()
    }
    pub fn results_dir(&self) -> PathBuf {
        self.cfg.station.results()
    }
    pub fn journal(&self) -> std::sync::MutexGuard<'_, Journal> {
        self.journal.lock().unwrap_or_else(|p| p.into_inner())
    }
    /// Notes whether the last journal call worked (the status page says when it did not).
    pub fn journal_result<T>(&self, r: Result<T, JournalError>) -> Option<T> {
        let mut off = self
            .journal_offline
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        match r {
            Ok(v) => {
                if off.take().is_some() {
                    info!("the journal is reachable again");
                }
                Some(v)
            }
            Err(e) => {
                if off.is_none() {
                    error!("{e}; captures wait in captures/ until it is back");
                    *off = Some((journal::now(), e.to_string()));
                }
                None
            }
        }
    }
    /// How the daemon's own jobs run.
    pub fn job_spec(&self) -> runner::JobSpec {
        runner::JobSpec {
            exe: self.exe.clone(),
            config: self.cfg.file.clone(),
            results: self.results_dir(),
            landmarks: self.cfg.station.landmarks(),
            threads: std::thread::available_parallelism()
                .map(|n| (n.get() / self.workers.max(1)).max(1))
                .unwrap_or(1),
            timeout: Duration::from_secs_f64(self.cfg.daemon.job_timeout_s),
            max_attempts: self.cfg.daemon.max_attempts,
            template_cache: Some(self.cfg.station.cache()),
        }
    }
    pub fn uptime(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}

impl Shared {
    fn new(
        cfg: StationConfig,
        exe: Option<PathBuf>,
        journal: Journal,
        worker_name: String,
        workers: usize,
        capture: Option<std::sync::mpsc::Sender<CaptureRequest>>,
        rig: RigStatus,
    ) -> Result<Arc<Shared>, DaemonError> {
        let exe = match exe.or_else(|| cfg.worker.program.clone()) {
            Some(e) => e,
            None => std::env::current_exe().map_err(io_err(Path::new("conformd")))?,
        };
        info!(journal = %journal.describe(), worker = %worker_name, "journal open");
        Ok(Arc::new(Shared {
            exe,
            journal: Mutex::new(journal),
            worker_name,
            journal_offline: Mutex::new(None),
            waiting_handover: Default::default(),
            refused: Default::default(),
            settling: AtomicBool::new(false),
            moved_in: Default::default(),
            scans: Default::default(),
            known_ids: Default::default(),
            wake: Default::default(),
            abort: Default::default(),
            stopping: AtomicBool::new(false),
            running: Mutex::new(BTreeMap::new()),
            workers,
            metrics: Default::default(),
            rig: Mutex::new(rig),
            capture,
            model_busy: AtomicBool::new(false),
            model_error: Mutex::new(None),
            since_rebuild: AtomicUsize::new(0),
            started: Instant::now(),
            cfg,
        }))
    }
}

/// A generic template built into the workers' cache at start-up, so that the first
/// capture's worker reads it as the later ones do (0.2 s sooner). Only when the workers
/// run this very program: the cache is kept per build of it.
fn warm_template_cache(shared: &Arc<Shared>) {
    let this = std::env::current_exe().and_then(|e| e.canonicalize());
    let same = matches!((this, shared.exe.canonicalize()), (Ok(a), Ok(b)) if a == b);
    let Some(source) = shared.cfg.template.clone() else {
        return;
    };
    if !same || source.generic.is_none() {
        return;
    }
    let cache = shared.cfg.station.cache();
    tokio::task::spawn_blocking(move || {
        if let Err(e) = source.figure_cached(Some(&cache)) {
            warn!("the generic template was not built ahead: {e}");
        }
    });
}

/// Jobs at once: `n`, or for 0 half the machine's cores (at least one).
fn half_the_cores(n: usize) -> usize {
    match n {
        0 => std::thread::available_parallelism()
            .map(|n| n.get().div_ceil(2))
            .unwrap_or(1),
        n => n,
    }
}

/// Runs the station until SIGTERM or SIGINT; returns once running jobs have finished or
/// were put back in the queue.
///
/// Example: `conformd daemon --config /etc/conformd/station.toml`; see `tests/daemon.rs`.
pub fn run(cfg: StationConfig) -> Result<(), DaemonError> {
    init_tracing();
    runtime()?.block_on(serve(cfg, None, None, None))
}

fn runtime() -> Result<tokio::runtime::Runtime, DaemonError> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| DaemonError::Config(format!("cannot start the runtime: {e}")))
}

/// A daemon running on a thread of this process (the demo runs one so it can watch the
/// journal while the real service works).
pub struct Handle {
    pub shared: Arc<Shared>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<Result<(), DaemonError>>>,
}

impl Handle {
    /// Starts the daemon on its own thread; returns once it is ready (journal open, first
    /// rescan done, HTTP server bound). Workers run `exe` (default: this program).
    pub fn spawn(cfg: StationConfig, exe: Option<PathBuf>) -> Result<Handle, DaemonError> {
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel();
        let thread = std::thread::spawn(move || {
            runtime()?.block_on(serve(cfg, exe, Some(stop_rx), Some(ready_tx)))
        });
        match ready_rx.recv() {
            Ok(shared) => Ok(Handle {
                shared,
                stop: Some(stop_tx),
                thread: Some(thread),
            }),
            Err(_) => Err(thread
                .join()
                .unwrap_or_else(|_| Err(DaemonError::Config("the daemon thread panicked".into())))
                .err()
                .unwrap_or_else(|| DaemonError::Config("the daemon stopped at once".into()))),
        }
    }

    /// Whether it still runs: it stops by itself on SIGINT and SIGTERM.
    pub fn running(&self) -> bool {
        self.thread.as_ref().is_some_and(|t| !t.is_finished())
    }

    /// Stops it as SIGTERM would (drain) and waits.
    pub fn stop(mut self) -> Result<(), DaemonError> {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(DaemonError::Config("the daemon thread panicked".into())),
            None => Ok(()),
        }
    }
}

fn init_tracing() {
    // journald keeps stderr; it adds its own time stamps
    let filter = tracing_subscriber::EnvFilter::try_from_env("CONFORMD_LOG")
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(false)
        .with_target(false)
        .without_time()
        .try_init();
}

async fn serve(
    cfg: StationConfig,
    exe: Option<PathBuf>,
    stop_rx: Option<tokio::sync::oneshot::Receiver<()>>,
    ready: Option<std::sync::mpsc::Sender<Arc<Shared>>>,
) -> Result<(), DaemonError> {
    if cfg.rig.is_none() || cfg.template.is_none() {
        return Err(DaemonError::Config(format!(
            "{}: the daemon needs [rig] and [template] to process captures",
            cfg.file.display()
        )));
    }
    // owned before the port is bound: a Ctrl-C once the page answers must drain, not kill
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(io_err(Path::new("SIGTERM")))?;
    let mut int = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(io_err(Path::new("SIGINT")))?;
    for d in [
        cfg.station.captures(),
        cfg.station.incoming(),
        cfg.station.results(),
    ] {
        std::fs::create_dir_all(&d).map_err(io_err(&d))?;
    }
    // a station keeps capturing while its database is away, from the start too
    let journal = journal::open_tolerant(cfg.journal.url.as_deref(), &cfg.station.data)?;
    let worker_name = format!("{}:daemon:{}", journal::hostname(), cfg.station.name);
    let workers = half_the_cores(cfg.daemon.workers);
    let (channel, rig_status) = capture::start(&cfg)?;
    let (capture, capture_rx) = match channel {
        Some((tx, rx)) => (Some(tx), Some(rx)),
        None => (None, None),
    };
    let shared = Shared::new(cfg, exe, journal, worker_name, workers, capture, rig_status)?;
    if let Some(rx) = capture_rx {
        capture::spawn_capture_thread(shared.clone(), rx);
    }
    warm_template_cache(&shared);
    reconcile(&shared);
    scan(&shared);
    tokio::spawn(heartbeats(shared.clone()));
    if let Some(url) = shared.cfg.journal.url.clone() {
        listen_for_work(shared.clone(), url);
    }

    let addr = shared.cfg.daemon.listen.clone();
    let server = start_http(&shared).await?;

    let (hint_tx, mut hints) = tokio::sync::mpsc::channel::<Hint>(16);
    let _watcher = if shared.cfg.daemon.watch {
        watch(&shared, hint_tx)
    } else {
        None
    };
    info!(
        station = %shared.cfg.station.name,
        listen = %addr,
        workers,
        "conformd daemon ready"
    );
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    if let Some(r) = ready {
        let _ = r.send(shared.clone());
    }
    main_loop(&shared, stop_rx, (&mut term, &mut int), &mut hints).await;
    drain(&shared).await;
    let name = shared.worker_name.clone();
    let gone = shared.journal().worker_gone(&name);
    shared.journal_result(gone);
    let _ = server.await;
    info!("conformd daemon stopped");
    Ok(())
}

/// The HTTP API and status page, served until the daemon is stopping.
async fn start_http(shared: &Arc<Shared>) -> Result<tokio::task::JoinHandle<()>, DaemonError> {
    let addr = shared.cfg.daemon.listen.clone();
    let listener = tokio::net::TcpListener::bind(&addr)
        .await
        .map_err(|source| DaemonError::Listen {
            addr: addr.clone(),
            source,
        })?;
    let app = http::router(shared.clone());
    let stop = shared.clone();
    Ok(tokio::spawn(http::serve(listener, app, async move {
        while !stop.stopping.load(Ordering::SeqCst) {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })))
}

/// The daemon's loop: jobs dispatched, captures found (watcher hints, wake-ups,
/// rescans, settling sets), the watchdog fed, until a stop request, SIGTERM or SIGINT.
async fn main_loop(
    shared: &Arc<Shared>,
    mut stop_rx: Option<tokio::sync::oneshot::Receiver<()>>,
    signals: (
        &mut tokio::signal::unix::Signal,
        &mut tokio::signal::unix::Signal,
    ),
    hints: &mut tokio::sync::mpsc::Receiver<Hint>,
) {
    let stop_requested = async {
        match stop_rx.as_mut() {
            Some(rx) => {
                let _ = rx.await;
            }
            None => std::future::pending::<()>().await,
        }
    };
    tokio::pin!(stop_requested);

    let mut rescan = tokio::time::interval(Duration::from_secs_f64(shared.cfg.daemon.rescan_s));
    // pings at under half the watchdog interval, only from this loop: a stuck loop stops them
    let watchdog_every = sd_notify::watchdog_enabled()
        .map(|d| d / 3)
        .unwrap_or(Duration::from_secs(3600));
    let mut watchdog = tokio::time::interval(watchdog_every);
    loop {
        dispatch(shared);
        let due = shared
            .journal()
            .next_due()
            .ok()
            .flatten()
            .map(|t| (t - journal::now()).clamp(0.05, 60.0))
            .unwrap_or(60.0);
        tokio::select! {
            _ = &mut stop_requested => break,
            _ = signals.0.recv() => break,
            _ = signals.1.recv() => break,
            _ = shared.wake.notified() => scan(shared),
            Some(hint) = hints.recv() => {
                // a set renamed in is whole: scanned at once. Files being written are a
                // burst of events: gathered, scanned once
                if hint == Hint::Changed {
                    let until = tokio::time::Instant::now() + Duration::from_millis(150);
                    while let Ok(Some(Hint::Changed)) = tokio::time::timeout_at(until, hints.recv()).await {}
                }
                while hints.try_recv().is_ok() {}
                scan(shared);
            }
            _ = rescan.tick() => scan(shared),
            _ = tokio::time::sleep(sets::SETTLE), if shared.settling.load(Ordering::SeqCst) => {
                scan(shared)
            }
            _ = watchdog.tick() => notify_watchdog(shared),
            _ = tokio::time::sleep(Duration::from_secs_f64(due)) => {}
        }
    }
}

/// The systemd watchdog's ping, with the queue's counts as the unit's status.
fn notify_watchdog(shared: &Shared) {
    if let Ok(c) = shared.journal().counts() {
        let status = format!(
            "{} queued, {} running, {} done, {} failed",
            c.queued, c.running, c.done, c.failed
        );
        let _ = sd_notify::notify(&[
            sd_notify::NotifyState::Watchdog,
            sd_notify::NotifyState::Status(&status),
        ]);
    }
}

/// Every third of a lease: the leases of this daemon's running jobs are renewed, it
/// says it is alive (the status page lists every worker), and jobs of workers whose lease
/// ran out are queued again.
async fn heartbeats(shared: Arc<Shared>) {
    let lease = shared.cfg.journal.lease_s;
    let started = journal::now();
    let mut every = tokio::time::interval(Duration::from_secs_f64(lease / 3.0));
    loop {
        every.tick().await;
        let running: Vec<String> = shared
            .running
            .lock()
            .map(|r| r.keys().cloned().collect())
            .unwrap_or_default();
        let done = shared.metrics.lock().map(|m| m.jobs_done).unwrap_or(0);
        let mut j = shared.journal();
        if !running.is_empty()
            && let Some(held) = shared.journal_result(j.renew(&shared.worker_name, &running, lease))
        {
            for id in running.iter().filter(|id| !held.contains(id)) {
                warn!(capture = %id, "this daemon lost its lease on the job; another worker may take it");
            }
        }
        if shared.cfg.daemon.local_workers {
            let me = journal::WorkerInfo {
                name: shared.worker_name.clone(),
                host: journal::hostname(),
                pid: std::process::id(),
                started_at: started,
                heartbeat_at: journal::now(),
                job: running.first().cloned(),
                jobs_done: done,
            };
            let r = j.heartbeat(&me);
            shared.journal_result(r);
        }
        let expired = j.expire_leases();
        if let Some(ids) = shared.journal_result(expired) {
            for id in &ids {
                warn!(capture = %id, "its worker's lease ran out: queued again");
            }
            if !ids.is_empty() {
                shared.wake.notify_one();
            }
        }
    }
}

/// A PostgreSQL journal announces new work (other stations' captures, requeued jobs):
/// a thread of its own listens and wakes the loop.
fn listen_for_work(shared: Arc<Shared>, url: String) {
    std::thread::spawn(move || {
        let poll = Duration::from_secs_f64(shared.cfg.journal.poll_s);
        let mut conn: Option<Journal> = None;
        while !shared.stopping.load(Ordering::SeqCst) {
            let c = match &mut conn {
                Some(c) => c,
                None => match journal::open(Some(&url), &shared.cfg.station.data) {
                    Ok(c) => conn.insert(c),
                    Err(_) => {
                        std::thread::sleep(poll);
                        continue;
                    }
                },
            };
            match c.wait_for_work(poll) {
                Ok(true) => shared.wake.notify_one(),
                Ok(false) => {}
                Err(_) => std::thread::sleep(poll),
            }
        }
    });
}

/// SIGTERM: nothing new starts; running jobs get `drain_s` to finish, then are stopped
/// and queued again for the next start.
async fn drain(shared: &Arc<Shared>) {
    shared.stopping.store(true, Ordering::SeqCst);
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    let n = shared.running.lock().map(|r| r.len()).unwrap_or(0);
    info!(running = n, "stopping: waiting for running jobs");
    let deadline = Instant::now() + Duration::from_secs_f64(shared.cfg.daemon.drain_s);
    while Instant::now() < deadline {
        if shared.running.lock().map(|r| r.is_empty()).unwrap_or(true) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    shared.abort.notify_waiters();
    while !shared.running.lock().map(|r| r.is_empty()).unwrap_or(true) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// At start-up: half-written results are removed; the jobs this daemon was running
/// when it stopped are queued again (their attempt counted), as are jobs of workers
/// whose lease ran out; a queued job whose complete result is newer than its request is
/// done, never redone.
fn reconcile(shared: &Shared) {
    let results = shared.results_dir();
    // on storage several machines share, another's result may be half-written right
    // now: there a stale one is cleared when its capture is claimed again
    if shared.cfg.journal.url.is_none() {
        match crate::station::pipeline::remove_partial_results(&results) {
            Ok(n) if n > 0 => info!(removed = n, "removed half-written results"),
            Ok(_) => {}
            Err(e) => warn!("cleaning {}: {e}", results.display()),
        }
    }
    let r = (|| -> Result<(), JournalError> {
        let mut j = shared.journal();
        for id in j.release(&shared.worker_name)? {
            info!(capture = %id, "interrupted job queued again");
        }
        for id in j.expire_leases()? {
            info!(capture = %id, "its worker's lease ran out: queued again");
        }
        for job in j.list(Some(journal::State::Queued), usize::MAX)? {
            let dir = results.join(&job.id);
            if let Some((seconds, written)) = complete_result(&dir)
                && written >= job.queued_at
                && j.adopt(&job.id, &dir, &seconds)?
            {
                info!(capture = %job.id, "its complete result exists: done");
            }
        }
        Ok(())
    })();
    // a journal that cannot be reached now is reconciled by the leases later
    shared.journal_result(r);
}

/// The stage timings of a complete result folder and when it was written (Unix
/// seconds), or None when it is not complete.
fn complete_result(dir: &Path) -> Option<(serde_json::Value, f64)> {
    if !crate::station::pipeline::RESULT_FILES
        .iter()
        .all(|f| dir.join(f).is_file())
    {
        return None;
    }
    let file = dir.join("report.json");
    let written = std::fs::metadata(&file)
        .and_then(|m| m.modified())
        .ok()?
        .duration_since(std::time::UNIX_EPOCH)
        .ok()?
        .as_secs_f64();
    let report: serde_json::Value = serde_json::from_slice(
        &crate::files::read_limited(&file, crate::files::MAX_REPORT_BYTES).ok()?,
    )
    .ok()?;
    Some((report.get("seconds").cloned().unwrap_or_default(), written))
}

/// Watches `captures/` and `incoming/`; every event is only a hint to rescan. When
/// inotify cannot be used (its watch limit reached, a file system without it) the
/// daemon says so and relies on the periodic rescans.
fn watch(
    shared: &Shared,
    hints: tokio::sync::mpsc::Sender<Hint>,
) -> Option<notify::RecommendedWatcher> {
    use notify::Watcher;
    use notify::event::{AccessKind, AccessMode, EventKind, ModifyKind, RenameMode};
    let (moved_in, incoming, captures) = (
        shared.moved_in.clone(),
        shared.incoming_dir(),
        shared.captures_dir(),
    );
    let handler = move |e: notify::Result<notify::Event>| {
        // a worker reading a capture changes nothing (a file closed after writing does)
        if let Ok(e) = &e
            && let EventKind::Access(a) = e.kind
            && a != AccessKind::Close(AccessMode::Write)
        {
            return;
        }
        let renamed_in = match &e {
            Ok(e)
                if matches!(
                    e.kind,
                    EventKind::Modify(ModifyKind::Name(RenameMode::To | RenameMode::Both))
                ) =>
            {
                e.paths.last().filter(|to| {
                    to.parent() == Some(incoming.as_path())
                        || to.parent() == Some(captures.as_path())
                })
            }
            _ => None,
        };
        if let Some(to) = renamed_in
            && to.parent() == Some(incoming.as_path())
            && let Some(name) = to.file_name()
        {
            let mut m = moved_in.lock().unwrap_or_else(|p| p.into_inner());
            // names of sets never taken (refused) are not kept for ever
            if m.len() >= MOVED_IN_KEPT {
                m.clear();
            }
            m.insert(name.to_string_lossy().into_owned());
        }
        let hint = if renamed_in.is_some() {
            Hint::RenamedIn
        } else {
            Hint::Changed
        };
        let _ = hints.try_send(hint);
    };
    let mut w = match notify::recommended_watcher(handler) {
        Ok(w) => w,
        Err(e) => {
            warn!("{}", watch_error("the capture folders", &e));
            return None;
        }
    };
    for d in [shared.captures_dir(), shared.incoming_dir()] {
        if let Err(e) = w.watch(&d, notify::RecursiveMode::NonRecursive) {
            warn!("{}", watch_error(&d.display().to_string(), &e));
            return None;
        }
    }
    Some(w)
}

/// What the folder watcher saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Hint {
    /// a folder renamed into `incoming/` or `captures/`: a set that came whole, scanned
    /// at once
    RenamedIn,
    /// anything else (files written): scanned once the burst is over
    Changed,
}

/// At most this many names of folders renamed into `incoming/` are remembered.
const MOVED_IN_KEPT: usize = 10_000;

fn watch_error(what: &str, e: &notify::Error) -> String {
    let limit = matches!(e.kind, notify::ErrorKind::MaxFilesWatch)
        || matches!(&e.kind, notify::ErrorKind::Io(io) if io.raw_os_error() == Some(28));
    if limit {
        format!(
            "cannot watch {what}: the inotify watch limit is reached (raise fs.inotify.max_user_watches); new captures are found by the rescan every few seconds instead"
        )
    } else {
        format!("cannot watch {what}: {e}; new captures are found by the rescan instead")
    }
}

/// Finds new capture sets: complete sets in `incoming/` (manifest and every image
/// present) are moved into `captures/`; every complete set in `captures/` the journal
/// does not know is queued. Events are hints; this is the truth.
pub fn scan(shared: &Shared) {
    scan_folders(shared);
    shared.scans.fetch_add(1, Ordering::SeqCst);
}

fn scan_folders(shared: &Shared) {
    let captures = shared.captures_dir();
    let incoming = shared.incoming_dir();
    let moved_in = |name: &str| {
        shared
            .moved_in
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .contains(name)
    };
    let from_incoming = sets::scan_folder(&incoming, Some(sets::SETTLE), moved_in, |_| false);
    let mut refused: BTreeMap<String, String> = from_incoming
        .refused
        .into_iter()
        .map(|(name, why)| (format!("incoming/{name}"), why))
        .collect();
    for (name, dir) in from_incoming.sets {
        let to = captures.join(&name);
        match crate::files::rename_no_replace(&dir, &to) {
            Ok(()) => {
                // (a set refused stays remembered: it is judged alike at every scan, so
                // its reason is logged once)
                shared
                    .moved_in
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .remove(&name);
                info!(capture = %name, "taken in from incoming/")
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                refused.insert(
                    format!("incoming/{name}"),
                    "not moved: captures/ already has a set of this id (rename one of them)".into(),
                );
            }
            Err(e) => {
                refused.insert(
                    format!("incoming/{name}"),
                    format!("moving it into captures/ failed: {e}"),
                );
            }
        }
    }
    shared
        .settling
        .store(from_incoming.settling, Ordering::SeqCst);
    let mut j = shared.journal();
    let mut seen = shared.known_ids.lock().unwrap_or_else(|p| p.into_inner());
    let mut waiting = shared
        .waiting_handover
        .lock()
        .unwrap_or_else(|p| p.into_inner());
    // sets the journal knows are skipped before their manifest is read: after months a
    // station holds many thousands. While the journal cannot be reached, every set it
    // was not known to have is a candidate, handed over when it is back.
    let mut online = true;
    let in_captures = sets::scan_folder(
        &captures,
        None,
        |_| false,
        |name| {
            if seen.contains(name) {
                return true;
            }
            if !online {
                return false;
            }
            match j.contains(name) {
                Ok(true) => {
                    seen.insert(name.to_string());
                    true
                }
                Ok(false) => false,
                Err(e) => {
                    shared.journal_result::<()>(Err(e));
                    online = false;
                    false
                }
            }
        },
    );
    refused.extend(
        in_captures
            .refused
            .into_iter()
            .map(|(name, why)| (format!("captures/{name}"), why)),
    );
    shared.report_refused(refused);
    for (name, dir) in in_captures.sets {
        // one failed call is enough to know: the others wait for the next rescan
        if !online {
            waiting.insert(name);
            continue;
        }
        let subject = crate::devices::capture_set::CaptureSetDir::open(&dir)
            .ok()
            .and_then(|s| s.manifest.subject);
        match shared.journal_result(j.enqueue(&name, &dir, subject.as_deref())) {
            Some(new) => {
                if new {
                    info!(capture = %name, "queued");
                }
                if waiting.remove(&name) {
                    info!(capture = %name, "handed over to the journal");
                }
                seen.insert(name);
            }
            None => {
                online = false;
                waiting.insert(name);
            }
        }
    }
}

/// Starts queued jobs while fewer than `workers` run.
fn dispatch(shared: &Arc<Shared>) {
    if shared.stopping.load(Ordering::SeqCst) || !shared.cfg.daemon.local_workers {
        return;
    }
    loop {
        let busy = shared.running.lock().map(|r| r.len()).unwrap_or(usize::MAX);
        if busy >= shared.workers {
            return;
        }
        let claimed = shared
            .journal()
            .claim(&shared.worker_name, shared.cfg.journal.lease_s);
        let Some(Some(job)) = shared.journal_result(claimed) else {
            return;
        };
        if let Ok(mut r) = shared.running.lock() {
            r.insert(job.id.clone(), Instant::now());
        }
        if let Ok(mut m) = shared.metrics.lock() {
            m.jobs_started += 1;
        }
        tokio::spawn(run_job(shared.clone(), job));
    }
}

async fn run_job(shared: Arc<Shared>, job: journal::Job) {
    let spec = shared.job_spec();
    let ended = runner::run_child(&spec, &job, &shared.abort).await;
    let recorded = {
        let mut j = shared.journal();
        runner::record(&mut j, &shared.worker_name, &job, ended, &spec)
    };
    if let Ok(mut r) = shared.running.lock() {
        r.remove(&job.id);
    }
    match recorded {
        Err(e) => {
            // the outcome could not be recorded (the result not published, the journal
            // away): give the job back for a later attempt rather than hold it
            error!(capture = %job.id, "{e}");
            let retry = journal::Finish::Failed {
                stage: "write".into(),
                error: e.to_string(),
                retry_at: Some(journal::now() + runner::backoff_s(job.attempts)),
            };
            let again = shared
                .journal()
                .finish(&job.id, &shared.worker_name, &retry, &mut || Ok(()));
            shared.journal_result(again);
        }
        Ok(r) => {
            if let Ok(mut m) = shared.metrics.lock() {
                match &r {
                    runner::Recorded::Done(seconds) => {
                        m.jobs_done += 1;
                        for (stage, v) in seconds.as_object().into_iter().flatten() {
                            if let Some(s) = v.as_f64() {
                                m.observe(stage, s);
                            }
                        }
                    }
                    runner::Recorded::Crashed => m.worker_crashes += 1,
                    runner::Recorded::TimedOut { .. } => m.timeouts += 1,
                    _ => {}
                }
            }
            if matches!(r, runner::Recorded::Done(_)) {
                let n = shared.since_rebuild.fetch_add(1, Ordering::SeqCst) + 1;
                let every = shared.cfg.model.rebuild_every;
                if every > 0 && n >= every {
                    shared.since_rebuild.store(0, Ordering::SeqCst);
                    request_model_rebuild(&shared);
                }
            }
        }
    }
    shared.wake.notify_one();
}

/// Rebuilds the shape model from every done result, in the background; false when a
/// rebuild is already running or the station has no `[model] file`.
pub fn request_model_rebuild(shared: &Arc<Shared>) -> bool {
    if shared.cfg.model.file.is_none() || shared.model_busy.swap(true, Ordering::SeqCst) {
        return false;
    }
    let s = shared.clone();
    // a plain thread: callable from the runtime and from outside it (the demo)
    std::thread::spawn(move || {
        let r = rebuild_model(&s);
        if let Ok(mut e) = s.model_error.lock() {
            *e = r.as_ref().err().map(|e| e.to_string());
        }
        match r {
            Ok(n) => info!(meshes = n, "shape model rebuilt"),
            Err(e) => warn!("shape model not rebuilt: {e}"),
        }
        s.model_busy.store(false, Ordering::SeqCst);
    });
    true
}

/// Builds the model over every done result's conformed mesh and writes it atomically to
/// `[model] file`; the workers load it for every later job. Returns the mesh count.
fn rebuild_model(shared: &Shared) -> Result<usize, RebuildError> {
    let path = shared.cfg.model.file.clone().ok_or(RebuildError::NoFile)?;
    let done = shared
        .journal()
        .list(Some(journal::State::Done), usize::MAX)?;
    let mut samples = Vec::new();
    for job in done {
        let Some(dir) = job.result else { continue };
        match crate::station::review::left_out(&dir) {
            Ok(false) => {}
            Ok(true) => continue,
            Err(e) => {
                warn!("model: {e}; {} left out as if rejected", job.id);
                continue;
            }
        }
        match crate::mesh::read_mesh(&dir.join("conformed.ply")) {
            Ok(m) => samples.push((job.id, m)),
            Err(e) => warn!("model: {e}"),
        }
    }
    samples.sort_by(|a, b| a.0.cmp(&b.0));
    let model = crate::model::ShapeModel::build(&samples, &Default::default())?;
    model.save(&path)?;
    Ok(samples.len())
}
