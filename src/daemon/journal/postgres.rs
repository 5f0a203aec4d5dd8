//! The journal on PostgreSQL: many stations and workers share it. Claims take a row with
//! `FOR UPDATE SKIP LOCKED` (two workers never take one job, and never wait for each
//! other); leases run on the database's clock; new work is announced with NOTIFY on
//! `conformd_jobs`, which idle workers LISTEN for. A dropped connection is made again at
//! the next call, so a station that lost the database carries on once it is back.

use super::{
    Backend, Counts, Finish, Finished, Job, JournalError, State, WorkerInfo, now, resolved_path,
    stored_path,
};
use postgres::fallible_iterator::FallibleIterator;
use postgres::{Client, NoTls, Row};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

const CHANNEL: &str = "conformd_jobs";
/// The database's clock, Unix seconds.
const DB_NOW: &str = "EXTRACT(EPOCH FROM clock_timestamp())::DOUBLE PRECISION";

pub struct PgJournal {
    config: postgres::Config,
    client: Option<Client>,
    /// a connection being made on a thread of its own, and since when
    connecting: Option<(Receiver<Result<Client, postgres::Error>>, Instant)>,
    store: String,
    root: PathBuf,
}

/// Longest wait for a new connection's handshake. The client's `connect_timeout` bounds
/// the TCP connect only: a server (or a port forward) that accepts and never answers
/// would hold the caller for ever.
pub const HANDSHAKE_LIMIT: Duration = Duration::from_secs(10);

/// Runs blocking database work from inside the daemon's runtime as well as outside it
/// (the sync client runs a small runtime of its own, which may not start on a runtime
/// thread unless that thread is first handed over to blocking work).
fn blocking<R>(f: impl FnOnce() -> R) -> R {
    match tokio::runtime::Handle::try_current() {
        Ok(h) if h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
            tokio::task::block_in_place(f)
        }
        _ => f(),
    }
}

fn row_to_job(r: &Row, root: &Path) -> Result<Job, postgres::Error> {
    super::job_of_row!(r, try_get, i32, root)
}

fn row_to_worker(r: &Row) -> Result<WorkerInfo, postgres::Error> {
    super::worker_of_row!(r, try_get, i32)
}

fn ids(rows: Vec<Row>) -> Result<Vec<String>, postgres::Error> {
    rows.iter().map(|r| r.try_get(0)).collect()
}

impl PgJournal {
    /// Connects, brings the schema up to date and listens for new work.
    pub fn connect(url: &str, root: &Path) -> Result<PgJournal, JournalError> {
        let mut j = PgJournal::unconnected(url, root)?;
        j.with(|_, _| Ok(()))?;
        Ok(j)
    }

    /// As `connect`, but a first connection that fails is only logged; every call tries
    /// again.
    pub fn connect_later(url: &str, root: &Path) -> Result<PgJournal, JournalError> {
        let mut j = PgJournal::unconnected(url, root)?;
        if let Err(e) = j.with(|_, _| Ok(())) {
            tracing::error!("{e}; trying again at every call");
        }
        Ok(j)
    }

    fn unconnected(url: &str, root: &Path) -> Result<PgJournal, JournalError> {
        let mut config: postgres::Config = url.parse().map_err(|e| JournalError {
            store: "postgres (its URL)".into(),
            source: Box::new(e),
        })?;
        // an unreachable database fails a call in seconds, not minutes: the station
        // carries on capturing and hands its captures over later
        config.connect_timeout(Duration::from_secs(3));
        config.keepalives_idle(Duration::from_secs(30));
        let hosts: Vec<String> = config
            .get_hosts()
            .iter()
            .map(|h| match h {
                postgres::config::Host::Tcp(s) => s.clone(),
                postgres::config::Host::Unix(p) => p.display().to_string(),
            })
            .collect();
        let store = format!(
            "postgres {}/{}",
            hosts.join(","),
            config.get_dbname().unwrap_or("")
        );
        Ok(PgJournal {
            config,
            client: None,
            connecting: None,
            store,
            root: root.to_path_buf(),
        })
    }

    fn err(&self, e: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> JournalError {
        JournalError {
            store: self.store.clone(),
            source: e.into(),
        }
    }

    /// The connection, made (again) when there is none or it was lost: migrations run
    /// and LISTEN is issued on each new one.
    fn client(&mut self) -> Result<&mut Client, JournalError> {
        if self.client.as_ref().is_none_or(|c| c.is_closed()) {
            self.client = None;
            let mut c = self.connection()?;
            super::migrations::runner()
                .run(&mut c)
                .map_err(|e| self.err(format!("migrating the schema: {e}")))?;
            c.batch_execute(&format!("LISTEN {CHANNEL}"))
                .map_err(|e| self.err(e))?;
            self.client = Some(c);
        }
        Ok(self.client.as_mut().expect("connected above"))
    }

    /// A new connection, made on a thread of its own and waited for at most
    /// [`HANDSHAKE_LIMIT`]. A server that accepts and never answers costs that one thread
    /// (it ends when the server closes the socket), never the caller: while it waits,
    /// later calls fail at once, saying since when, instead of starting another.
    fn connection(&mut self) -> Result<Client, JournalError> {
        let (rx, since) = self.connecting.get_or_insert_with(|| {
            let (tx, rx) = std::sync::mpsc::channel();
            let config = self.config.clone();
            std::thread::spawn(move || {
                let _ = tx.send(config.connect(NoTls));
            });
            (rx, Instant::now())
        });
        let since = *since;
        let left = HANDSHAKE_LIMIT.saturating_sub(since.elapsed());
        match rx.recv_timeout(left) {
            Ok(r) => {
                self.connecting = None;
                r.map_err(|e| self.err(e))
            }
            Err(RecvTimeoutError::Timeout) => {
                let e = self.err(format!(
                    "the server accepted the connection but has not answered its handshake for {:.0} s",
                    since.elapsed().as_secs_f64()
                ));
                tracing::warn!("{e}");
                Err(e)
            }
            Err(RecvTimeoutError::Disconnected) => {
                self.connecting = None;
                Err(self.err("the connecting thread ended without a word"))
            }
        }
    }

    /// One call on the connection; a connection found broken is dropped, to be made
    /// again next time.
    fn with<R>(
        &mut self,
        f: impl FnOnce(&mut Client, &Path) -> Result<R, postgres::Error>,
    ) -> Result<R, JournalError> {
        blocking(|| {
            let root = self.root.clone();
            let c = self.client()?;
            let r = f(c, &root);
            if r.is_err() && c.is_closed() {
                self.client = None;
            }
            r.map_err(|e| self.err(e))
        })
    }
}

impl Backend for PgJournal {
    fn describe(&self) -> String {
        self.store.clone()
    }

    fn enqueue(
        &mut self,
        id: &str,
        dir: &Path,
        subject: Option<&str>,
    ) -> Result<bool, JournalError> {
        let dir = stored_path(dir, &self.root);
        self.with(|c, _| {
            let n = c.execute(
                "INSERT INTO captures (id, dir, state, subject, queued_at) VALUES ($1, $2, 'queued', $3, $4) ON CONFLICT (id) DO NOTHING",
                &[&id, &dir, &subject, &now()],
            )?;
            if n == 1 {
                c.batch_execute(&format!("NOTIFY {CHANNEL}"))?;
            }
            Ok(n == 1)
        })
    }

    fn contains(&mut self, id: &str) -> Result<bool, JournalError> {
        self.with(|c, _| {
            Ok(c.query_opt("SELECT 1 FROM captures WHERE id = $1", &[&id])?
                .is_some())
        })
    }

    fn get(&mut self, id: &str) -> Result<Option<Job>, JournalError> {
        self.with(|c, root| {
            c.query_opt("SELECT * FROM captures WHERE id = $1", &[&id])?
                .map(|r| row_to_job(&r, root))
                .transpose()
        })
    }

    fn claim(&mut self, worker: &str, lease_s: f64) -> Result<Option<Job>, JournalError> {
        let t = now();
        self.with(|c, root| {
            c.query_opt(
                &format!(
                    "UPDATE captures SET state = 'running', attempts = attempts + 1, started_at = $1, worker = $2, lease_until = {DB_NOW} + $3
                     WHERE id = (SELECT id FROM captures WHERE state = 'queued' AND not_before <= $1 ORDER BY queued_at, id LIMIT 1 FOR UPDATE SKIP LOCKED)
                     RETURNING *"
                ),
                &[&t, &worker, &lease_s],
            )?
            .map(|r| row_to_job(&r, root))
            .transpose()
        })
    }

    fn renew(
        &mut self,
        worker: &str,
        held: &[String],
        lease_s: f64,
    ) -> Result<Vec<String>, JournalError> {
        self.with(|c, _| {
            ids(c.query(
                &format!("UPDATE captures SET lease_until = {DB_NOW} + $3 WHERE id = ANY($2) AND state = 'running' AND worker = $1 RETURNING id"),
                &[&worker, &held, &lease_s],
            )?)
        })
    }

    fn expire_leases(&mut self) -> Result<Vec<String>, JournalError> {
        self.with(|c, _| {
            let expired = ids(c.query(
                &format!("UPDATE captures SET state = 'queued', worker = NULL, not_before = 0 WHERE state = 'running' AND worker IS NOT NULL AND lease_until < {DB_NOW} RETURNING id"),
                &[],
            )?)?;
            if !expired.is_empty() {
                c.batch_execute(&format!("NOTIFY {CHANNEL}"))?;
            }
            Ok(expired)
        })
    }

    fn release(&mut self, worker: &str) -> Result<Vec<String>, JournalError> {
        self.with(|c, _| {
            let released = ids(c.query(
                "UPDATE captures SET state = 'queued', worker = NULL, not_before = 0 WHERE state = 'running' AND worker = $1 RETURNING id",
                &[&worker],
            )?)?;
            if !released.is_empty() {
                c.batch_execute(&format!("NOTIFY {CHANNEL}"))?;
            }
            Ok(released)
        })
    }

    fn finish(
        &mut self,
        id: &str,
        worker: &str,
        how: &Finish,
        publish: &mut dyn FnMut() -> std::io::Result<()>,
    ) -> Result<Finished, JournalError> {
        let store = self.store.clone();
        let result = match how {
            Finish::Done { result, .. } => stored_path(result, &self.root),
            _ => String::new(),
        };
        let published = std::cell::Cell::new(None);
        let r = self.with(|c, _| {
            let mut tx = c.transaction()?;
            let owner = "WHERE id = $1 AND worker = $2 AND state = 'running'";
            let t = now();
            let n = match how {
                Finish::Done { seconds, landmarks, .. } => tx.execute(
                    &format!("UPDATE captures SET state = 'done', result = $3, seconds = $4, landmarks = $6, stage = NULL, error = NULL, finished_at = $5, worker = NULL {owner}"),
                    &[&id, &worker, &result, &seconds.to_string(), &t, landmarks],
                )?,
                Finish::Failed { stage, error, retry_at } => {
                    let (state, not_before) = Finish::failed_state(*retry_at);
                    tx.execute(
                        &format!("UPDATE captures SET state = $3, stage = $4, error = $5, not_before = $6, finished_at = $7, worker = NULL {owner}"),
                        &[&id, &worker, &state, &stage, &error, &not_before, &t],
                    )?
                }
                Finish::Requeue => tx.execute(
                    &format!("UPDATE captures SET state = 'queued', attempts = GREATEST(attempts - 1, 0), not_before = 0, worker = NULL {owner}"),
                    &[&id, &worker],
                )?,
            };
            if n == 0 {
                tx.rollback()?;
                return Ok(Finished::NotOwner);
            }
            if matches!(how, Finish::Done { .. })
                && let Err(e) = publish()
            {
                tx.rollback()?;
                published.set(Some(e));
                return Ok(Finished::NotOwner);
            }
            if !matches!(how, Finish::Done { .. } | Finish::Failed { retry_at: None, .. }) {
                tx.batch_execute(&format!("NOTIFY {CHANNEL}"))?;
            }
            tx.commit()?;
            Ok(Finished::Recorded)
        })?;
        match published.take() {
            Some(e) => Err(JournalError {
                store,
                source: format!("publishing the result of {id}: {e}").into(),
            }),
            None => Ok(r),
        }
    }

    fn adopt(
        &mut self,
        id: &str,
        result: &Path,
        seconds: &serde_json::Value,
    ) -> Result<bool, JournalError> {
        let result = stored_path(result, &self.root);
        self.with(|c, _| {
            Ok(c.execute(
                "UPDATE captures SET state = 'done', result = $2, seconds = $3, stage = NULL, error = NULL, finished_at = $4, worker = NULL WHERE id = $1 AND state = 'queued'",
                &[&id, &result, &seconds.to_string(), &now()],
            )? == 1)
        })
    }

    fn next_due(&mut self) -> Result<Option<f64>, JournalError> {
        self.with(|c, _| {
            c.query_one(
                "SELECT MIN(not_before) FROM captures WHERE state = 'queued'",
                &[],
            )?
            .try_get(0)
        })
    }

    fn reprocess(&mut self, id: &str) -> Result<bool, JournalError> {
        self.with(|c, _| {
            let n = c.execute(
                "UPDATE captures SET state = 'queued', attempts = 0, not_before = 0, stage = NULL, error = NULL, queued_at = $2 WHERE id = $1 AND state != 'running'",
                &[&id, &now()],
            )?;
            if n == 1 {
                c.batch_execute(&format!("NOTIFY {CHANNEL}"))?;
            }
            Ok(n == 1)
        })
    }

    fn list(&mut self, state: Option<State>, limit: usize) -> Result<Vec<Job>, JournalError> {
        let limit = limit.min(i64::MAX as usize) as i64;
        let state = state.map(State::as_str);
        self.with(|c, root| {
            c.query(
                "SELECT * FROM captures WHERE ($1::TEXT IS NULL OR state = $1) ORDER BY queued_at DESC, id DESC LIMIT $2",
                &[&state, &limit],
            )?
            .iter()
            .map(|r| row_to_job(r, root))
            .collect()
        })
    }

    fn counts(&mut self) -> Result<Counts, JournalError> {
        let rows = self.with(|c, _| {
            c.query("SELECT state, COUNT(*) FROM captures GROUP BY state", &[])?
                .iter()
                .map(|r| Ok((r.try_get::<_, String>(0)?, r.try_get::<_, i64>(1)?)))
                .collect::<Result<Vec<_>, postgres::Error>>()
        })?;
        Ok(Counts::of(rows))
    }

    fn failures_by_stage(&mut self) -> Result<Vec<(String, u64)>, JournalError> {
        self.with(|c, _| {
            c.query(
                "SELECT COALESCE(stage, 'unknown'), COUNT(*) FROM captures WHERE state = 'failed' GROUP BY 1",
                &[],
            )?
            .iter()
            .map(|r| Ok((r.try_get(0)?, r.try_get::<_, i64>(1)?.max(0) as u64)))
            .collect()
        })
    }

    fn heartbeat(&mut self, w: &WorkerInfo) -> Result<(), JournalError> {
        let pid = w.pid as i32;
        let done = w.jobs_done.min(i32::MAX as u64) as i32;
        self.with(|c, _| {
            c.execute(
                "INSERT INTO workers (name, host, pid, started_at, heartbeat_at, job, jobs_done) VALUES ($1, $2, $3, $4, $5, $6, $7)
                 ON CONFLICT (name) DO UPDATE SET host = excluded.host, pid = excluded.pid, started_at = excluded.started_at, heartbeat_at = excluded.heartbeat_at, job = excluded.job, jobs_done = excluded.jobs_done",
                &[&w.name, &w.host, &pid, &w.started_at, &w.heartbeat_at, &w.job, &done],
            )?;
            Ok(())
        })
    }

    fn worker_gone(&mut self, name: &str) -> Result<(), JournalError> {
        self.with(|c, _| {
            c.execute("DELETE FROM workers WHERE name = $1", &[&name])?;
            Ok(())
        })
    }

    fn workers(&mut self) -> Result<Vec<WorkerInfo>, JournalError> {
        self.with(|c, _| {
            c.query("SELECT * FROM workers ORDER BY name", &[])?
                .iter()
                .map(row_to_worker)
                .collect()
        })
    }

    fn wait_for_work(&mut self, timeout: Duration) -> Result<bool, JournalError> {
        self.with(|c, _| {
            let mut n = c.notifications();
            // news that came in during other calls counts; then wait for more
            let mut woken = n.iter().next()?.is_some();
            while n.iter().next()?.is_some() {}
            if !woken {
                woken = n.timeout_iter(timeout).next()?.is_some();
                while n.iter().next()?.is_some() {}
            }
            Ok(woken)
        })
    }
}
