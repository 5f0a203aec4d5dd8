//! One job run in a child process (`conformd process --json --stage`), and what its end
//! means for the journal: shared by the daemon's own workers and `conformd worker`. The
//! child leaves its result complete under a hidden name; it is renamed into place inside
//! the journal transaction that marks the job done, and only if the job is still this
//! worker's (a worker whose lease ran out while another took the job discards its own).

use super::journal::{Finish, Finished, Job, Journal, JournalError};
use crate::station::ProcessOutcome;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tracing::{error, info, warn};

/// How each job's child process is run.
#[derive(Debug, Clone)]
pub struct JobSpec {
    /// the program (`conformd`, or a wrapper that runs it)
    pub exe: PathBuf,
    /// the station file the child reads
    pub config: PathBuf,
    pub results: PathBuf,
    /// where operators' scan landmarks wait (`<id>.txt`): a job whose capture has a
    /// file there is fitted by them
    pub landmarks: PathBuf,
    /// rayon threads of the child
    pub threads: usize,
    pub timeout: Duration,
    pub max_attempts: u32,
    /// where the child keeps a generic template between jobs (`--template-cache`)
    pub template_cache: Option<PathBuf>,
}

/// How a child process ended.
pub enum Ended {
    Outcome(ProcessOutcome),
    Crashed(String),
    TimedOut,
    Aborted,
    NotStarted(String),
}

/// Runs `job` in a child process until it ends, its time is up or `abort` fires (the
/// child is killed then).
pub async fn run_child(spec: &JobSpec, job: &Job, abort: &tokio::sync::Notify) -> Ended {
    // a worker killed mid-job (or one whose lease ran out) may have left a staged
    // result of this capture: it is no one's now
    remove_staged(&spec.results, &job.id);
    let mut cmd = tokio::process::Command::new(&spec.exe);
    cmd.arg("process")
        .arg(&job.dir)
        .arg("--config")
        .arg(&spec.config)
        .arg("--out")
        .arg(&spec.results)
        .arg("--json")
        .arg("--stage");
    let landmarks = spec.landmarks.join(format!("{}.txt", job.id));
    // anything of that name counts, a pipe, a folder or a link too: the job's reader
    // refuses it naming why, rather than a refit running without the operator's points
    if std::fs::symlink_metadata(&landmarks).is_ok() {
        cmd.arg("--landmarks").arg(&landmarks);
    }
    if let Some(c) = &spec.template_cache {
        cmd.arg("--template-cache").arg(c);
    }
    cmd.arg("--parent")
        .arg(std::process::id().to_string())
        .env("RAYON_NUM_THREADS", spec.threads.to_string())
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true);
    info!(capture = %job.id, attempt = job.attempts, "processing");
    match cmd.spawn() {
        Err(e) => Ended::NotStarted(format!("{}: {e}", spec.exe.display())),
        Ok(child) => {
            tokio::select! {
                r = tokio::time::timeout(spec.timeout, child.wait_with_output()) => match r {
                    Err(_) => Ended::TimedOut,
                    Ok(Err(e)) => Ended::NotStarted(e.to_string()),
                    Ok(Ok(out)) => ended_of(&out),
                },
                _ = abort.notified() => Ended::Aborted,
            }
        }
    }
}

/// Removes hidden staged results of capture `id` (`.<id>.partial-*`).
fn remove_staged(results: &Path, id: &str) {
    let prefix = format!(".{id}.partial-");
    for e in std::fs::read_dir(results).into_iter().flatten().flatten() {
        if e.file_name().to_string_lossy().starts_with(&prefix) {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

fn ended_of(out: &std::process::Output) -> Ended {
    use std::os::unix::process::ExitStatusExt;
    let stderr = String::from_utf8_lossy(&out.stderr);
    let last_err = stderr.lines().last().map(str::to_string);
    if let Some(sig) = out.status.signal() {
        return Ended::Crashed(format!(
            "the worker process was killed by signal {sig} ({}){}",
            signal_name(sig),
            last_err
                .map(|l| format!("; it said: {l}"))
                .unwrap_or_default()
        ));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    match stdout
        .lines()
        .rev()
        .find_map(|l| serde_json::from_str::<ProcessOutcome>(l).ok())
    {
        Some(o) => Ended::Outcome(o),
        None => Ended::Crashed(format!(
            "the worker process exited with {} without a result{}",
            out.status,
            last_err
                .map(|l| format!("; it said: {l}"))
                .unwrap_or_default()
        )),
    }
}

fn signal_name(sig: i32) -> &'static str {
    match sig {
        6 => "SIGABRT",
        9 => "SIGKILL: out of memory, or killed",
        11 => "SIGSEGV",
        7 => "SIGBUS",
        4 => "SIGILL",
        8 => "SIGFPE",
        15 => "SIGTERM",
        _ => "a signal",
    }
}

/// What a job's end was recorded as.
#[derive(Debug, Clone)]
pub enum Recorded {
    /// done: its result published, with the stage timings
    Done(serde_json::Value),
    /// failed for good, or queued again with a backoff (`retry`)
    Failed {
        retry: bool,
    },
    /// the child crashed (a signal, no answer): the capture is failed
    Crashed,
    TimedOut {
        retry: bool,
    },
    /// stopped by a shutdown: queued again, attempt not counted
    Requeued,
    /// the job was no longer this worker's: nothing recorded, its result discarded
    Lost,
}

/// Seconds before attempt `n + 1`: 5, 20, 80 ... up to an hour.
pub fn backoff_s(attempts: u32) -> f64 {
    (5.0 * 4f64.powi(attempts.saturating_sub(1).min(10) as i32)).min(3600.0)
}

/// Records how `worker`'s `job` ended: done (the staged result published in the same
/// transaction), failed for good, queued again with a backoff, or nothing when the job
/// is no longer its own.
pub fn record(
    j: &mut Journal,
    worker: &str,
    job: &Job,
    ended: Ended,
    spec: &JobSpec,
) -> Result<Recorded, JournalError> {
    let retry_at =
        (job.attempts < spec.max_attempts).then(|| super::journal::now() + backoff_s(job.attempts));
    let nothing = &mut || Ok(());
    let (how, recorded) = match &ended {
        Ended::Outcome(o) if o.ok => return record_done(j, worker, job, o, spec),
        Ended::Outcome(o) => {
            let stage = o.stage.map_or_else(|| "unknown".into(), |s| s.to_string());
            let error = o.error.clone().unwrap_or_else(|| "failed".into());
            let retry_at = if o.permanent { None } else { retry_at };
            log_failure(job, &stage, &error, retry_at.is_some(), o.permanent);
            (
                Finish::Failed {
                    stage,
                    error,
                    retry_at,
                },
                Recorded::Failed {
                    retry: retry_at.is_some(),
                },
            )
        }
        Ended::Crashed(msg) => {
            error!(capture = %job.id, "{msg}");
            (
                Finish::Failed {
                    stage: "worker".into(),
                    error: msg.clone(),
                    retry_at: None,
                },
                Recorded::Crashed,
            )
        }
        Ended::TimedOut => {
            let msg = format!(
                "stopped after the time limit of {} s",
                spec.timeout.as_secs_f64()
            );
            log_failure(job, "worker", &msg, retry_at.is_some(), false);
            (
                Finish::Failed {
                    stage: "worker".into(),
                    error: msg,
                    retry_at,
                },
                Recorded::TimedOut {
                    retry: retry_at.is_some(),
                },
            )
        }
        Ended::NotStarted(msg) => {
            let msg = format!("the worker could not run: {msg}");
            log_failure(job, "worker", &msg, retry_at.is_some(), false);
            (
                Finish::Failed {
                    stage: "worker".into(),
                    error: msg,
                    retry_at,
                },
                Recorded::Failed {
                    retry: retry_at.is_some(),
                },
            )
        }
        Ended::Aborted => {
            info!(capture = %job.id, "stopped by the shutdown; queued for the next start");
            (Finish::Requeue, Recorded::Requeued)
        }
    };
    finish(j, worker, job, &how, nothing, recorded)
}

/// A job that ended well: its staged result published and the job done in one step
/// (the staged folder removed if that failed); a program that published by itself
/// only recorded.
fn record_done(
    j: &mut Journal,
    worker: &str,
    job: &Job,
    o: &ProcessOutcome,
    spec: &JobSpec,
) -> Result<Recorded, JournalError> {
    let nothing = &mut || Ok(());
    let seconds = o
        .seconds
        .as_ref()
        .and_then(|s| serde_json::to_value(s).ok())
        .unwrap_or_default();
    let staged = o.result.clone().filter(|_| o.staged);
    let Some(staged) = staged else {
        // a program that published by itself: nothing to rename
        let result = o
            .result
            .clone()
            .unwrap_or_else(|| spec.results.join(&job.id));
        let how = Finish::Done {
            result,
            seconds: seconds.clone(),
            landmarks: o.landmarks.clone(),
        };
        return finish(j, worker, job, &how, nothing, Recorded::Done(seconds));
    };
    let how = Finish::Done {
        result: spec.results.join(&job.id),
        seconds: seconds.clone(),
        landmarks: o.landmarks.clone(),
    };
    let mut publish = || {
        crate::station::pipeline::publish(&spec.results, &job.id, &staged)
            .map(|_| ())
            .map_err(|(p, e)| std::io::Error::new(e.kind(), format!("{}: {e}", p.display())))
    };
    let r = finish(j, worker, job, &how, &mut publish, Recorded::Done(seconds));
    if !matches!(r, Ok(Recorded::Done(_))) {
        let _ = std::fs::remove_dir_all(&staged);
    }
    if let Ok(Recorded::Done(s)) = &r {
        info!(
            capture = %job.id,
            seconds = s.get("total").and_then(|v| v.as_f64()).unwrap_or(0.0),
            mean_distance_pct = o.mean_distance_relative.unwrap_or(f64::NAN) * 100.0,
            "done"
        );
    }
    r
}

fn finish(
    j: &mut Journal,
    worker: &str,
    job: &Job,
    how: &Finish,
    publish: &mut dyn FnMut() -> std::io::Result<()>,
    recorded: Recorded,
) -> Result<Recorded, JournalError> {
    match j.finish(&job.id, worker, how, publish)? {
        Finished::Recorded => Ok(recorded),
        Finished::NotOwner => {
            warn!(
                capture = %job.id,
                "this worker's lease on the job ran out and another worker took it: its outcome is discarded"
            );
            Ok(Recorded::Lost)
        }
    }
}

fn log_failure(job: &Job, stage: &str, msg: &str, retry: bool, permanent: bool) {
    if permanent {
        error!(capture = %job.id, stage, "{msg}");
    } else if retry {
        warn!(capture = %job.id, stage, attempt = job.attempts, "{msg}; will retry");
    } else {
        error!(capture = %job.id, stage, "{msg}; giving up after {} attempts", job.attempts);
    }
}
