//! The station journal: one SQLite row per capture id with its job state (queued,
//! running, done, failed), attempts, the last error and its stage, stage timings and the
//! result folder. WAL, `synchronous=FULL` (a job state that was reported survives a power
//! cut), a busy timeout, one writer (the daemon holds the only connection).

use rusqlite::{Connection, OptionalExtension, params};
use std::path::{Path, PathBuf};

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
    /// Unix seconds
    pub queued_at: f64,
    pub started_at: Option<f64>,
    pub finished_at: Option<f64>,
    /// a retried job waits until then
    pub not_before: f64,
}

#[derive(Debug, thiserror::Error)]
#[error("journal {path}: {source}")]
pub struct JournalError {
    pub path: String,
    #[source]
    pub source: rusqlite::Error,
}

/// Job counts by state.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Counts {
    pub queued: u64,
    pub running: u64,
    pub done: u64,
    pub failed: u64,
}

pub struct Journal {
    conn: Connection,
    path: String,
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS captures (
    id TEXT PRIMARY KEY NOT NULL,
    dir TEXT NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed')),
    attempts INTEGER NOT NULL DEFAULT 0,
    subject TEXT,
    stage TEXT,
    error TEXT,
    seconds TEXT,
    result TEXT,
    queued_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    not_before REAL NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS captures_by_state ON captures (state, not_before, queued_at);
";

pub fn now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

fn row_to_job(r: &rusqlite::Row) -> rusqlite::Result<Job> {
    let state: String = r.get("state")?;
    let seconds: Option<String> = r.get("seconds")?;
    Ok(Job {
        id: r.get("id")?,
        dir: PathBuf::from(r.get::<_, String>("dir")?),
        state: State::parse(&state).unwrap_or(State::Failed),
        attempts: r.get("attempts")?,
        subject: r.get("subject")?,
        stage: r.get("stage")?,
        error: r.get("error")?,
        seconds: seconds.and_then(|s| serde_json::from_str(&s).ok()),
        result: r.get::<_, Option<String>>("result")?.map(PathBuf::from),
        queued_at: r.get("queued_at")?,
        started_at: r.get("started_at")?,
        finished_at: r.get("finished_at")?,
        not_before: r.get("not_before")?,
    })
}

impl Journal {
    /// Opens (or creates) the journal file.
    pub fn open(path: &Path) -> Result<Journal, JournalError> {
        let name = path.display().to_string();
        let err = |source| JournalError {
            path: name.clone(),
            source,
        };
        let conn = Connection::open(path).map_err(err)?;
        conn.busy_timeout(std::time::Duration::from_secs(5))
            .map_err(err)?;
        conn.pragma_update(None, "journal_mode", "WAL")
            .map_err(err)?;
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(err)?;
        conn.execute_batch(SCHEMA).map_err(err)?;
        Ok(Journal { conn, path: name })
    }

    fn err(&self, source: rusqlite::Error) -> JournalError {
        JournalError {
            path: self.path.clone(),
            source,
        }
    }

    /// Queues a capture unless the journal knows it already; true when it was new.
    pub fn enqueue(
        &self,
        id: &str,
        dir: &Path,
        subject: Option<&str>,
    ) -> Result<bool, JournalError> {
        let n = self
            .conn
            .execute(
                "INSERT OR IGNORE INTO captures (id, dir, state, subject, queued_at) VALUES (?1, ?2, 'queued', ?3, ?4)",
                params![id, dir.display().to_string(), subject, now()],
            )
            .map_err(|e| self.err(e))?;
        Ok(n == 1)
    }

    pub fn contains(&self, id: &str) -> Result<bool, JournalError> {
        self.conn
            .query_row("SELECT 1 FROM captures WHERE id = ?1", [id], |_| Ok(()))
            .optional()
            .map(|r| r.is_some())
            .map_err(|e| self.err(e))
    }

    pub fn get(&self, id: &str) -> Result<Option<Job>, JournalError> {
        self.conn
            .query_row("SELECT * FROM captures WHERE id = ?1", [id], row_to_job)
            .optional()
            .map_err(|e| self.err(e))
    }

    /// Takes the oldest queued job that may run now, marking it running with one more
    /// attempt.
    pub fn claim(&self) -> Result<Option<Job>, JournalError> {
        let t = now();
        let id: Option<String> = self
            .conn
            .query_row(
                "SELECT id FROM captures WHERE state = 'queued' AND not_before <= ?1 ORDER BY queued_at, id LIMIT 1",
                [t],
                |r| r.get(0),
            )
            .optional()
            .map_err(|e| self.err(e))?;
        let Some(id) = id else { return Ok(None) };
        self.conn
            .execute(
                "UPDATE captures SET state = 'running', attempts = attempts + 1, started_at = ?2 WHERE id = ?1",
                params![id, t],
            )
            .map_err(|e| self.err(e))?;
        self.get(&id)
    }

    /// The earliest time a queued job may run, if any is queued.
    pub fn next_due(&self) -> Result<Option<f64>, JournalError> {
        self.conn
            .query_row(
                "SELECT MIN(not_before) FROM captures WHERE state = 'queued'",
                [],
                |r| r.get(0),
            )
            .map_err(|e| self.err(e))
    }

    pub fn done(
        &self,
        id: &str,
        result: &Path,
        seconds: &serde_json::Value,
    ) -> Result<(), JournalError> {
        self.conn
            .execute(
                "UPDATE captures SET state = 'done', result = ?2, seconds = ?3, stage = NULL, error = NULL, finished_at = ?4 WHERE id = ?1",
                params![id, result.display().to_string(), seconds.to_string(), now()],
            )
            .map(|_| ())
            .map_err(|e| self.err(e))
    }

    /// A failure: `retry_at` Some queues the job again for then, None fails it for good.
    pub fn failed(
        &self,
        id: &str,
        stage: &str,
        error: &str,
        retry_at: Option<f64>,
    ) -> Result<(), JournalError> {
        let (state, not_before) = match retry_at {
            Some(t) => ("queued", t),
            None => ("failed", 0.0),
        };
        self.conn
            .execute(
                "UPDATE captures SET state = ?2, stage = ?3, error = ?4, not_before = ?5, finished_at = ?6 WHERE id = ?1",
                params![id, state, stage, error, not_before, now()],
            )
            .map(|_| ())
            .map_err(|e| self.err(e))
    }

    /// Puts a running job back in the queue without counting its attempt (a stop that was
    /// not the job's fault).
    pub fn requeue(&self, id: &str) -> Result<(), JournalError> {
        self.conn
            .execute(
                "UPDATE captures SET state = 'queued', attempts = MAX(attempts - 1, 0), not_before = 0 WHERE id = ?1 AND state = 'running'",
                [id],
            )
            .map(|_| ())
            .map_err(|e| self.err(e))
    }

    /// Queues a capture again from the start (a reprocess request); false when unknown.
    pub fn reprocess(&self, id: &str) -> Result<bool, JournalError> {
        self.conn
            .execute(
                "UPDATE captures SET state = 'queued', attempts = 0, not_before = 0, stage = NULL, error = NULL, queued_at = ?2 WHERE id = ?1 AND state != 'running'",
                params![id, now()],
            )
            .map(|n| n == 1)
            .map_err(|e| self.err(e))
    }

    /// Jobs that were running when the daemon stopped; they are queued again by the
    /// reconciliation (their attempt counted).
    pub fn running(&self) -> Result<Vec<Job>, JournalError> {
        self.list(Some(State::Running), usize::MAX)
    }

    /// Makes a job that was running queued again (attempt kept: it counted).
    pub fn interrupted(&self, id: &str) -> Result<(), JournalError> {
        self.conn
            .execute(
                "UPDATE captures SET state = 'queued', not_before = 0 WHERE id = ?1 AND state = 'running'",
                [id],
            )
            .map(|_| ())
            .map_err(|e| self.err(e))
    }

    /// Newest first.
    pub fn list(&self, state: Option<State>, limit: usize) -> Result<Vec<Job>, JournalError> {
        let limit = limit.min(i64::MAX as usize) as i64;
        let mut stmt = self
            .conn
            .prepare(
                "SELECT * FROM captures WHERE (?1 IS NULL OR state = ?1) ORDER BY queued_at DESC, id DESC LIMIT ?2",
            )
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map(params![state.map(State::as_str), limit], row_to_job)
            .map_err(|e| self.err(e))?;
        rows.collect::<Result<Vec<_>, _>>().map_err(|e| self.err(e))
    }

    pub fn counts(&self) -> Result<Counts, JournalError> {
        let mut c = Counts::default();
        let mut stmt = self
            .conn
            .prepare("SELECT state, COUNT(*) FROM captures GROUP BY state")
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))
            .map_err(|e| self.err(e))?;
        for r in rows {
            let (s, n) = r.map_err(|e| self.err(e))?;
            let n = n.max(0) as u64;
            match State::parse(&s) {
                Some(State::Queued) => c.queued = n,
                Some(State::Running) => c.running = n,
                Some(State::Done) => c.done = n,
                Some(State::Failed) => c.failed = n,
                None => {}
            }
        }
        Ok(c)
    }

    /// Failures by stage, for the metrics.
    pub fn failures_by_stage(&self) -> Result<Vec<(String, u64)>, JournalError> {
        let mut stmt = self
            .conn
            .prepare("SELECT COALESCE(stage, 'unknown'), COUNT(*) FROM captures WHERE state = 'failed' GROUP BY 1")
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map([], |r| Ok((r.get(0)?, r.get::<_, i64>(1)?.max(0) as u64)))
            .map_err(|e| self.err(e))?;
        rows.collect::<Result<Vec<_>, _>>().map_err(|e| self.err(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_job_goes_through_its_states_once() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(&dir.path().join("j.sqlite")).unwrap();
        assert!(j.enqueue("a", Path::new("/c/a"), Some("tag-1")).unwrap());
        assert!(
            !j.enqueue("a", Path::new("/c/a"), None).unwrap(),
            "enqueued twice"
        );
        let job = j.claim().unwrap().unwrap();
        assert_eq!((job.state, job.attempts), (State::Running, 1));
        assert!(j.claim().unwrap().is_none());
        j.failed("a", "write", "disk full", Some(now() + 3600.0))
            .unwrap();
        assert!(j.claim().unwrap().is_none(), "a retry waits for its time");
        j.failed("a", "write", "disk full", Some(0.0)).unwrap();
        let job = j.claim().unwrap().unwrap();
        assert_eq!(job.attempts, 2);
        j.done("a", Path::new("/r/a"), &serde_json::json!({"total": 1.5}))
            .unwrap();
        let job = j.get("a").unwrap().unwrap();
        assert_eq!(job.state, State::Done);
        assert_eq!(job.seconds.unwrap()["total"], 1.5);
        assert_eq!(j.counts().unwrap().done, 1);
        assert!(j.reprocess("a").unwrap());
        assert_eq!(j.get("a").unwrap().unwrap().state, State::Queued);
    }
}
