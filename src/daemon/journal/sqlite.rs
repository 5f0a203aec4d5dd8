//! The journal in an SQLite file: one station. WAL, `synchronous=FULL` (a job state that
//! was reported survives a power cut), a busy timeout; claims take the write lock first
//! (`BEGIN IMMEDIATE`), so worker processes on the same machine may share the file.

use super::{
    Backend, Counts, Finish, Finished, Job, JournalError, State, WorkerInfo, now, resolved_path,
    stored_path,
};
use rusqlite::{Connection, OptionalExtension, TransactionBehavior, params};
use std::path::{Path, PathBuf};

pub struct SqliteJournal {
    conn: Connection,
    path: String,
    root: PathBuf,
}

fn row_to_job(r: &rusqlite::Row, root: &Path) -> rusqlite::Result<Job> {
    super::job_of_row!(r, get, i64, root)
}

fn row_to_worker(r: &rusqlite::Row) -> rusqlite::Result<WorkerInfo> {
    super::worker_of_row!(r, get, i64)
}

impl SqliteJournal {
    /// Opens (or creates) the journal file and brings its schema up to date.
    pub fn open(path: &Path, root: &Path) -> Result<SqliteJournal, JournalError> {
        let name = path.display().to_string();
        let err = |source: rusqlite::Error| JournalError {
            store: name.clone(),
            source: source.into(),
        };
        let mut conn = Connection::open(path).map_err(err)?;
        conn.busy_timeout(std::time::Duration::from_secs(5))
            .map_err(err)?;
        conn.pragma_update(None, "journal_mode", "WAL")
            .map_err(err)?;
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(err)?;
        super::migrations::runner()
            .run(&mut conn)
            .map_err(|e| JournalError {
                store: name.clone(),
                source: format!("migrating the schema: {e}").into(),
            })?;
        Ok(SqliteJournal {
            conn,
            path: name,
            root: root.to_path_buf(),
        })
    }

    fn err(&self, source: rusqlite::Error) -> JournalError {
        JournalError {
            store: self.path.clone(),
            source: source.into(),
        }
    }

    fn ids(&mut self, sql: &str, p: impl rusqlite::Params) -> Result<Vec<String>, JournalError> {
        let mut stmt = self.conn.prepare(sql).map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map(p, |r| r.get::<_, String>(0))
            .and_then(|r| r.collect::<Result<Vec<_>, _>>());
        rows.map_err(|e| self.err(e))
    }
}

impl Backend for SqliteJournal {
    fn describe(&self) -> String {
        format!("sqlite {}", self.path)
    }

    fn enqueue(
        &mut self,
        id: &str,
        dir: &Path,
        subject: Option<&str>,
    ) -> Result<bool, JournalError> {
        let n = self
            .conn
            .execute(
                "INSERT INTO captures (id, dir, state, subject, queued_at) VALUES (?1, ?2, 'queued', ?3, ?4) ON CONFLICT (id) DO NOTHING",
                params![id, stored_path(dir, &self.root), subject, now()],
            )
            .map_err(|e| self.err(e))?;
        Ok(n == 1)
    }

    fn contains(&mut self, id: &str) -> Result<bool, JournalError> {
        self.conn
            .query_row("SELECT 1 FROM captures WHERE id = ?1", [id], |_| Ok(()))
            .optional()
            .map(|r| r.is_some())
            .map_err(|e| self.err(e))
    }

    fn get(&mut self, id: &str) -> Result<Option<Job>, JournalError> {
        let root = self.root.clone();
        self.conn
            .query_row("SELECT * FROM captures WHERE id = ?1", [id], |r| {
                row_to_job(r, &root)
            })
            .optional()
            .map_err(|e| self.err(e))
    }

    fn claim(&mut self, worker: &str, lease_s: f64) -> Result<Option<Job>, JournalError> {
        let t = now();
        let root = self.root.clone();
        let path = self.path.clone();
        let err = |e: rusqlite::Error| JournalError {
            store: path.clone(),
            source: e.into(),
        };
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(err)?;
        let claimed = (|| {
            let id: Option<String> = tx
                .query_row(
                    "SELECT id FROM captures WHERE state = 'queued' AND not_before <= ?1 ORDER BY queued_at, id LIMIT 1",
                    [t],
                    |r| r.get(0),
                )
                .optional()?;
            let Some(id) = id else { return Ok(None) };
            tx.execute(
                "UPDATE captures SET state = 'running', attempts = attempts + 1, started_at = ?2, worker = ?3, lease_until = ?4 WHERE id = ?1",
                params![id, t, worker, t + lease_s],
            )?;
            tx.query_row("SELECT * FROM captures WHERE id = ?1", [&id], |r| {
                row_to_job(r, &root)
            })
            .optional()
        })();
        let job = claimed.map_err(err)?;
        tx.commit().map_err(err)?;
        Ok(job)
    }

    fn renew(
        &mut self,
        worker: &str,
        ids: &[String],
        lease_s: f64,
    ) -> Result<Vec<String>, JournalError> {
        let until = now() + lease_s;
        let mut held = Vec::new();
        for id in ids {
            held.extend(self.ids(
                "UPDATE captures SET lease_until = ?3 WHERE id = ?1 AND state = 'running' AND worker = ?2 RETURNING id",
                params![id, worker, until],
            )?);
        }
        Ok(held)
    }

    fn expire_leases(&mut self) -> Result<Vec<String>, JournalError> {
        self.ids(
            "UPDATE captures SET state = 'queued', worker = NULL, not_before = 0 WHERE state = 'running' AND worker IS NOT NULL AND lease_until < ?1 RETURNING id",
            [now()],
        )
    }

    fn release(&mut self, worker: &str) -> Result<Vec<String>, JournalError> {
        self.ids(
            "UPDATE captures SET state = 'queued', worker = NULL, not_before = 0 WHERE state = 'running' AND (worker = ?1 OR worker IS NULL) RETURNING id",
            [worker],
        )
    }

    fn finish(
        &mut self,
        id: &str,
        worker: &str,
        how: &Finish,
        publish: &mut dyn FnMut() -> std::io::Result<()>,
    ) -> Result<Finished, JournalError> {
        let t = now();
        let root = self.root.clone();
        let path = self.path.clone();
        let tx = self
            .conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(|e| JournalError {
                store: path.clone(),
                source: e.into(),
            })?;
        let owner = "WHERE id = ?1 AND worker = ?2 AND state = 'running'";
        let n = match how {
            Finish::Done { result, seconds, landmarks } => tx.execute(
                &format!("UPDATE captures SET state = 'done', result = ?3, seconds = ?4, landmarks = ?6, stage = NULL, error = NULL, finished_at = ?5, worker = NULL {owner}"),
                params![id, worker, stored_path(result, &root), seconds.to_string(), t, landmarks],
            ),
            Finish::Failed { stage, error, retry_at } => {
                let (state, not_before) = Finish::failed_state(*retry_at);
                tx.execute(
                    &format!("UPDATE captures SET state = ?3, stage = ?4, error = ?5, not_before = ?6, finished_at = ?7, worker = NULL {owner}"),
                    params![id, worker, state, stage, error, not_before, t],
                )
            }
            Finish::Requeue => tx.execute(
                &format!("UPDATE captures SET state = 'queued', attempts = MAX(attempts - 1, 0), not_before = 0, worker = NULL {owner}"),
                params![id, worker],
            ),
        }
        .map_err(|e| JournalError {
            store: path.clone(),
            source: e.into(),
        })?;
        if n == 0 {
            return Ok(Finished::NotOwner);
        }
        if matches!(how, Finish::Done { .. }) {
            publish().map_err(|e| JournalError {
                store: path.clone(),
                source: format!("publishing the result of {id}: {e}").into(),
            })?;
        }
        tx.commit().map_err(|e| JournalError {
            store: path,
            source: e.into(),
        })?;
        Ok(Finished::Recorded)
    }

    fn adopt(
        &mut self,
        id: &str,
        result: &Path,
        seconds: &serde_json::Value,
    ) -> Result<bool, JournalError> {
        self.conn
            .execute(
                "UPDATE captures SET state = 'done', result = ?2, seconds = ?3, stage = NULL, error = NULL, finished_at = ?4, worker = NULL WHERE id = ?1 AND state = 'queued'",
                params![id, stored_path(result, &self.root), seconds.to_string(), now()],
            )
            .map(|n| n == 1)
            .map_err(|e| self.err(e))
    }

    fn next_due(&mut self) -> Result<Option<f64>, JournalError> {
        self.conn
            .query_row(
                "SELECT MIN(not_before) FROM captures WHERE state = 'queued'",
                [],
                |r| r.get(0),
            )
            .map_err(|e| self.err(e))
    }

    fn reprocess(&mut self, id: &str) -> Result<bool, JournalError> {
        self.conn
            .execute(
                "UPDATE captures SET state = 'queued', attempts = 0, not_before = 0, stage = NULL, error = NULL, queued_at = ?2 WHERE id = ?1 AND state != 'running'",
                params![id, now()],
            )
            .map(|n| n == 1)
            .map_err(|e| self.err(e))
    }

    fn list(&mut self, state: Option<State>, limit: usize) -> Result<Vec<Job>, JournalError> {
        let limit = limit.min(i64::MAX as usize) as i64;
        let root = self.root.clone();
        let mut stmt = self
            .conn
            .prepare(
                "SELECT * FROM captures WHERE (?1 IS NULL OR state = ?1) ORDER BY queued_at DESC, id DESC LIMIT ?2",
            )
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map(params![state.map(State::as_str), limit], |r| {
                row_to_job(r, &root)
            })
            .and_then(|r| r.collect::<Result<Vec<_>, _>>());
        rows.map_err(|e| self.err(e))
    }

    fn counts(&mut self) -> Result<Counts, JournalError> {
        let mut stmt = self
            .conn
            .prepare("SELECT state, COUNT(*) FROM captures GROUP BY state")
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, i64>(1)?)))
            .and_then(|r| r.collect::<Result<Vec<_>, _>>())
            .map_err(|e| self.err(e))?;
        Ok(Counts::of(rows))
    }

    fn failures_by_stage(&mut self) -> Result<Vec<(String, u64)>, JournalError> {
        let mut stmt = self
            .conn
            .prepare("SELECT COALESCE(stage, 'unknown'), COUNT(*) FROM captures WHERE state = 'failed' GROUP BY 1")
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map([], |r| Ok((r.get(0)?, r.get::<_, i64>(1)?.max(0) as u64)))
            .and_then(|r| r.collect::<Result<Vec<_>, _>>());
        rows.map_err(|e| self.err(e))
    }

    fn heartbeat(&mut self, w: &WorkerInfo) -> Result<(), JournalError> {
        self.conn
            .execute(
                "INSERT INTO workers (name, host, pid, started_at, heartbeat_at, job, jobs_done) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)
                 ON CONFLICT (name) DO UPDATE SET host = excluded.host, pid = excluded.pid, started_at = excluded.started_at, heartbeat_at = excluded.heartbeat_at, job = excluded.job, jobs_done = excluded.jobs_done",
                params![w.name, w.host, w.pid, w.started_at, w.heartbeat_at, w.job, w.jobs_done as i64],
            )
            .map(|_| ())
            .map_err(|e| self.err(e))
    }

    fn worker_gone(&mut self, name: &str) -> Result<(), JournalError> {
        self.conn
            .execute("DELETE FROM workers WHERE name = ?1", [name])
            .map(|_| ())
            .map_err(|e| self.err(e))
    }

    fn workers(&mut self) -> Result<Vec<WorkerInfo>, JournalError> {
        let mut stmt = self
            .conn
            .prepare("SELECT * FROM workers ORDER BY name")
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map([], row_to_worker)
            .and_then(|r| r.collect::<Result<Vec<_>, _>>());
        rows.map_err(|e| self.err(e))
    }

    fn wait_for_work(&mut self, timeout: std::time::Duration) -> Result<bool, JournalError> {
        std::thread::sleep(timeout);
        Ok(false)
    }
}
