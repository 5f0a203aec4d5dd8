//! The station journal: one row per capture id with its job state (queued, running, done,
//! failed), attempts, the last error and its stage, stage timings, the result folder, and
//! the worker that holds a running job with the end of its lease; and the workers with
//! their last heartbeat. One interface ([`Backend`]) over two stores: an SQLite file (one
//! station, the default) and PostgreSQL (`[journal] url`: several stations and workers on
//! other machines). Both get the same versioned migrations (`migrations/`, refinery) at
//! start-up. Folders are stored relative to the station's data root, which every machine
//! mounts (perhaps at another place), and handed out resolved against this machine's.

mod postgres;
pub use postgres::HANDSHAKE_LIMIT;
mod sqlite;

use std::path::{Path, PathBuf};

refinery::embed_migrations!("migrations");

/// A job's state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum State {
    Queued,
    Running,
    Done,
    Failed,
}

impl State {
    pub const ALL: [State; 4] = [State::Queued, State::Running, State::Done, State::Failed];

    pub fn as_str(self) -> &'static str {
        match self {
            State::Queued => "queued",
            State::Running => "running",
            State::Done => "done",
            State::Failed => "failed",
        }
    }

    pub fn parse(s: &str) -> Option<State> {
        State::ALL.into_iter().find(|x| x.as_str() == s)
    }
}

/// One capture's row.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Job {
    pub id: String,
    /// the capture set's folder
    pub dir: PathBuf,
    pub state: State,
    pub attempts: u32,
    pub subject: Option<String>,
    /// the last failure: stage and sentence
    pub stage: Option<String>,
    pub error: Option<String>,
    /// stage timings of the last success (JSON object)
    pub seconds: Option<serde_json::Value>,
    pub result: Option<PathBuf>,
    /// the names of the landmarks an operator placed, when the last result was fitted
    /// with them (comma-separated); None for an automatic fit
    pub landmarks: Option<String>,
    /// Unix seconds
    pub queued_at: f64,
    pub started_at: Option<f64>,
    pub finished_at: Option<f64>,
    /// a retried job waits until then
    pub not_before: f64,
    /// the worker running it, and until when its lease runs
    pub worker: Option<String>,
    pub lease_until: f64,
}

/// A worker as its heartbeats describe it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct WorkerInfo {
    pub name: String,
    pub host: String,
    pub pid: u32,
    pub started_at: f64,
    pub heartbeat_at: f64,
    /// the capture it is processing
    pub job: Option<String>,
    pub jobs_done: u64,
}

/// How a running job ended, as its worker records it.
#[derive(Debug, Clone)]
pub enum Finish {
    /// done, with its (published) result folder, stage timings and the names of the
    /// manual landmarks it was fitted with
    Done {
        result: PathBuf,
        seconds: serde_json::Value,
        landmarks: Option<String>,
    },
    /// failed: `retry_at` Some queues it again for then, None fails it for good
    Failed {
        stage: String,
        error: String,
        retry_at: Option<f64>,
    },
    /// stopped through no fault of its own (a shutdown): queued again, attempt not counted
    Requeue,
}

/// What became of a worker's [`Backend::finish`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Finished {
    Recorded,
    /// the worker no longer held the job (its lease ran out and another worker took it):
    /// nothing was recorded and its result was not published
    NotOwner,
}

#[derive(Debug, thiserror::Error)]
#[error("journal {store}: {source}")]
pub struct JournalError {
    /// the file, or the database URL without its password
    pub store: String,
    #[source]
    pub source: Box<dyn std::error::Error + Send + Sync>,
}

/// Job counts by state.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Counts {
    pub queued: u64,
    pub running: u64,
    pub done: u64,
    pub failed: u64,
}

/// What a journal store does. Every call is one transaction; `&mut self` because a
/// database client is one connection.
pub trait Backend: Send {
    /// "sqlite <file>" or "postgres <host/db>", for logs and the status page
    fn describe(&self) -> String;
    /// Queues a capture unless the journal knows it already; true when it was new.
    fn enqueue(
        &mut self,
        id: &str,
        dir: &Path,
        subject: Option<&str>,
    ) -> Result<bool, JournalError>;
    fn contains(&mut self, id: &str) -> Result<bool, JournalError>;
    fn get(&mut self, id: &str) -> Result<Option<Job>, JournalError>;
    /// Takes the oldest queued job that may run now for `worker`, marking it running with
    /// one more attempt and a lease of `lease_s`; concurrent claims never take one job
    /// twice.
    fn claim(&mut self, worker: &str, lease_s: f64) -> Result<Option<Job>, JournalError>;
    /// Extends the leases of the jobs `ids` that `worker` still holds; returns those (a
    /// job missing from it was lost: its lease ran out and it was queued again).
    fn renew(
        &mut self,
        worker: &str,
        ids: &[String],
        lease_s: f64,
    ) -> Result<Vec<String>, JournalError>;
    /// Running jobs whose lease ran out (their worker died or lost the database) are
    /// queued again, their attempt counted; returns their ids.
    fn expire_leases(&mut self) -> Result<Vec<String>, JournalError>;
    /// At a worker's start: the jobs it held in an earlier life (and, on an SQLite
    /// journal, jobs of no worker from before leases) are queued again; returns their ids.
    fn release(&mut self, worker: &str) -> Result<Vec<String>, JournalError>;
    /// Records how `worker`'s job ended, only if it still holds it. For `Done`,
    /// `publish` (the rename of the result into place) runs inside the transaction
    /// that marks it done: an error from it leaves the job running; another worker that
    /// took the job meanwhile makes this `NotOwner` and `publish` is not called.
    fn finish(
        &mut self,
        id: &str,
        worker: &str,
        how: &Finish,
        publish: &mut dyn FnMut() -> std::io::Result<()>,
    ) -> Result<Finished, JournalError>;
    /// A queued job whose complete result is found written (a stop between the rename
    /// and the journal) is done without running again; false when it was not queued.
    fn adopt(
        &mut self,
        id: &str,
        result: &Path,
        seconds: &serde_json::Value,
    ) -> Result<bool, JournalError>;
    /// The earliest time a queued job may run, if any is queued.
    fn next_due(&mut self) -> Result<Option<f64>, JournalError>;
    /// Queues a capture again from the start (a reprocess request); false when unknown
    /// or running.
    fn reprocess(&mut self, id: &str) -> Result<bool, JournalError>;
    /// Newest first; `state` None: all.
    fn list(&mut self, state: Option<State>, limit: usize) -> Result<Vec<Job>, JournalError>;
    fn counts(&mut self) -> Result<Counts, JournalError>;
    /// Failures by stage, for the metrics.
    fn failures_by_stage(&mut self) -> Result<Vec<(String, u64)>, JournalError>;
    /// A worker says it is alive (and what it runs); `done` counts a finished job.
    fn heartbeat(&mut self, w: &WorkerInfo) -> Result<(), JournalError>;
    /// A worker that stops cleanly leaves the list.
    fn worker_gone(&mut self, name: &str) -> Result<(), JournalError>;
    fn workers(&mut self) -> Result<Vec<WorkerInfo>, JournalError>;
    /// Waits up to `timeout` for news of queued work (PostgreSQL LISTEN/NOTIFY; an SQLite
    /// journal has none and just waits); true when woken by news.
    fn wait_for_work(&mut self, timeout: std::time::Duration) -> Result<bool, JournalError>;
}

/// A journal: either store behind the one interface.
pub type Journal = Box<dyn Backend>;

/// Where the journal is: `[journal] url`, or the SQLite file in the data folder.
pub fn open(url: Option<&str>, data: &Path) -> Result<Journal, JournalError> {
    match url {
        Some(u) if u.starts_with("postgres://") || u.starts_with("postgresql://") => {
            Ok(Box::new(postgres::PgJournal::connect(u, data)?))
        }
        Some(u) => Err(JournalError {
            store: u.to_string(),
            source: "a journal URL must start with postgres:// or postgresql://".into(),
        }),
        None => open_sqlite(&data.join("journal.sqlite"), data),
    }
}

/// As [`open`], but a PostgreSQL journal that cannot be reached yet is returned all the
/// same (its calls fail until it can, then it connects): a station starts capturing
/// while its database is away. A URL that cannot be a database is still an error.
pub fn open_tolerant(url: Option<&str>, data: &Path) -> Result<Journal, JournalError> {
    match url {
        Some(u) if u.starts_with("postgres://") || u.starts_with("postgresql://") => {
            Ok(Box::new(postgres::PgJournal::connect_later(u, data)?))
        }
        _ => open(url, data),
    }
}

/// The SQLite journal file `path`, folders relative to `data`.
pub fn open_sqlite(path: &Path, data: &Path) -> Result<Journal, JournalError> {
    Ok(Box::new(sqlite::SqliteJournal::open(path, data)?))
}

pub fn now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// A folder as the journal stores it: relative to the data root when inside it.
fn stored_path(p: &Path, root: &Path) -> String {
    p.strip_prefix(root).unwrap_or(p).display().to_string()
}

/// A stored folder on this machine.
fn resolved_path(s: &str, root: &Path) -> PathBuf {
    root.join(s)
}

/// This machine's name, for worker names and the status page.
pub fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_string())
        .ok()
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "localhost".into())
}

/// A `captures` row as a [`Job`], for either client: `$get` is its getter (`get` or
/// `try_get`), `$int` its integer type, `root` the data root folders are resolved against.
macro_rules! job_of_row {
    ($r:expr, $get:ident, $int:ty, $root:expr) => {{
        let r = $r;
        let state: String = r.$get("state")?;
        let seconds: Option<String> = r.$get("seconds")?;
        Ok(Job {
            id: r.$get("id")?,
            dir: resolved_path(&r.$get::<_, String>("dir")?, $root),
            state: State::parse(&state).unwrap_or(State::Failed),
            attempts: r.$get::<_, $int>("attempts")?.max(0) as u32,
            subject: r.$get("subject")?,
            stage: r.$get("stage")?,
            error: r.$get("error")?,
            seconds: seconds.and_then(|s| serde_json::from_str(&s).ok()),
            result: r
                .$get::<_, Option<String>>("result")?
                .map(|s| resolved_path(&s, $root)),
            landmarks: r.$get("landmarks")?,
            queued_at: r.$get("queued_at")?,
            started_at: r.$get("started_at")?,
            finished_at: r.$get("finished_at")?,
            not_before: r.$get("not_before")?,
            worker: r.$get("worker")?,
            lease_until: r.$get("lease_until")?,
        })
    }};
}
use job_of_row;

/// A `workers` row as a [`WorkerInfo`], for either client (as [`job_of_row`]).
macro_rules! worker_of_row {
    ($r:expr, $get:ident, $int:ty) => {{
        let r = $r;
        Ok(WorkerInfo {
            name: r.$get("name")?,
            host: r.$get("host")?,
            pid: r.$get::<_, $int>("pid")?.max(0) as u32,
            started_at: r.$get("started_at")?,
            heartbeat_at: r.$get("heartbeat_at")?,
            job: r.$get("job")?,
            jobs_done: r.$get::<_, $int>("jobs_done")?.max(0) as u64,
        })
    }};
}
use worker_of_row;

impl Finish {
    /// A failure's next state and when it may run again.
    fn failed_state(retry_at: Option<f64>) -> (&'static str, f64) {
        match retry_at {
            Some(at) => ("queued", at),
            None => ("failed", 0.0),
        }
    }
}

impl Counts {
    /// From (state, count) rows.
    fn of(rows: impl IntoIterator<Item = (String, i64)>) -> Counts {
        let mut c = Counts::default();
        for (s, n) in rows {
            let n = n.max(0) as u64;
            match State::parse(&s) {
                Some(State::Queued) => c.queued = n,
                Some(State::Running) => c.running = n,
                Some(State::Done) => c.done = n,
                Some(State::Failed) => c.failed = n,
                None => {}
            }
        }
        c
    }
}
