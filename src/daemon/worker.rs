//! `conformd worker`: runs jobs from a journal that several machines share (PostgreSQL),
//! on a machine of its own. It claims jobs (`FOR UPDATE SKIP LOCKED`), holds a lease
//! renewed by heartbeat, runs each job as the daemon does (a child `conformd process`),
//! publishes the result under the capture id only if the job is still its own, and
//! sleeps on LISTEN/NOTIFY when idle (with a slow poll as a fallback). It captures
//! nothing, watches no folder, serves no HTTP and never rebuilds the model: the
//! station's daemon does those.

use super::{DaemonError, RigStatus, Shared, dispatch, drain, heartbeats, journal};
use crate::station::StationConfig;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;
use tracing::info;

/// Runs until SIGTERM or SIGINT; running jobs get `[daemon] drain_s` to finish, then are
/// queued again.
///
/// Example: `conformd worker --config /etc/conformd/worker.toml`; see `tests/workers.rs`.
pub fn run(cfg: StationConfig) -> Result<(), DaemonError> {
    super::init_tracing();
    super::runtime()?.block_on(work(cfg))
}

async fn work(mut cfg: StationConfig) -> Result<(), DaemonError> {
    if cfg.template.is_none() {
        return Err(DaemonError::Config(format!(
            "{}: a worker needs [template] (and [rig] for captures) to process captures",
            cfg.file.display()
        )));
    }
    if cfg.journal.url.is_none() {
        tracing::warn!(
            "{}: no [journal] url: this worker shares the SQLite journal of this machine's station only",
            cfg.file.display()
        );
    }
    // the station's daemon rebuilds the model; a worker runs jobs
    cfg.model.rebuild_every = 0;
    cfg.daemon.local_workers = true;
    let results = cfg.station.results();
    std::fs::create_dir_all(&results).map_err(super::io_err(&results))?;
    let mut journal = journal::open(cfg.journal.url.as_deref(), &cfg.station.data)?;
    let name = cfg
        .worker
        .name
        .clone()
        .unwrap_or_else(|| format!("{}:worker:{}", journal::hostname(), std::process::id()));
    // a worker of a fixed name that stopped while running jobs takes them back at once
    for id in journal.release(&name)? {
        info!(capture = %id, "interrupted job queued again");
    }
    let slots = super::half_the_cores(cfg.worker.jobs);
    let shared = Shared::new(
        cfg,
        None,
        journal,
        name.clone(),
        slots,
        None,
        RigStatus::default(),
    )?;
    tokio::spawn(heartbeats(shared.clone()));
    if let Some(url) = shared.cfg.journal.url.clone() {
        super::listen_for_work(shared.clone(), url);
    }
    info!(worker = %name, jobs = slots, "conformd worker ready");
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(super::io_err(std::path::Path::new("SIGTERM")))?;
    let mut int = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::interrupt())
        .map_err(super::io_err(std::path::Path::new("SIGINT")))?;
    let poll = Duration::from_secs_f64(shared.cfg.journal.poll_s);
    loop {
        dispatch(&shared);
        tokio::select! {
            _ = term.recv() => break,
            _ = int.recv() => break,
            _ = shared.wake.notified() => {}
            _ = tokio::time::sleep(poll) => {}
        }
    }
    stop(&shared).await;
    Ok(())
}

async fn stop(shared: &Arc<Shared>) {
    drain(shared).await;
    let gone = shared.journal().worker_gone(&shared.worker_name);
    shared.journal_result(gone);
    shared.stopping.store(true, Ordering::SeqCst);
    info!("conformd worker stopped");
}
