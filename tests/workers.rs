//! Several machines on one PostgreSQL journal (a throwaway cluster per test): `conformd
//! worker` processes claiming jobs, one killed mid-job; a station whose database goes
//! away while it captures; the real pipeline through a worker. Jobs in the first two run
//! a stand-in program that imitates `conformd process --json --stage` (a staged result
//! and its JSON line) in a fifth of a second: what is tested is the queue.

use crate::common;
use common::free_port;

use crate::common::postgres::TempPostgres;
use common::GroupChild as Child;
use conformd::daemon::journal::{self, State};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_conformd");

/// The stand-in job: `PROGRAM process <capture> --config F --out R --json --stage ...`.
/// It logs each run to `R/../runs.log`.
fn stand_in(dir: &Path) -> PathBuf {
    let p = dir.join("fake-process.sh");
    std::fs::write(
        &p,
        r#"#!/bin/bash
cap="$2"; out="$6"; id=$(basename "$cap")
echo "$id $$" >> "$out/../runs.log"
sleep "${FAKE_JOB_S:-0.2}"
tmp="$out/.$id.partial-$$"
mkdir -p "$tmp"
for f in scan.ply conformed.ply preview.png; do echo "$$" > "$tmp/$f"; done
echo "{\"pid\": $$, \"seconds\": {\"total\": 0.2}}" > "$tmp/report.json"
echo "{\"ok\":true,\"capture\":\"$id\",\"result\":\"$tmp\",\"staged\":true,\"seconds\":{\"total\":0.2},\"permanent\":false}"
"#,
    )
    .unwrap();
    Command::new("chmod").arg("+x").arg(&p).status().unwrap();
    p
}

/// A station file for `dir/data` on the journal `url`.
fn config(dir: &Path, url: &str, program: Option<&Path>, extra: &str) -> PathBuf {
    let p = dir.join("station.toml");
    let program = program
        .map(|p| format!("program = \"{}\"\n", p.display()))
        .unwrap_or_default();
    std::fs::write(
        &p,
        format!(
            "[station]\nname = \"farm\"\ndata = \"data\"\n\
             [template]\ngeneric = \"pig\"\nvertices = 1500\n\
             [journal]\nurl = \"{url}\"\nlease_s = 2.0\npoll_s = 1.0\n\
             [worker]\njobs = 1\n{program}{extra}"
        ),
    )
    .unwrap();
    for d in ["data/captures", "data/results", "data/incoming"] {
        std::fs::create_dir_all(dir.join(d)).unwrap();
    }
    p
}

fn spawn(args: &[&str], log: &Path) -> Child {
    spawn_with_job_s(args, log, 0.2)
}

/// As `spawn`, the stand-in job taking `job_s` seconds.
fn spawn_with_job_s(args: &[&str], log: &Path, job_s: f64) -> Child {
    Command::new(BIN)
        .args(args)
        .env("CONFORMD_LOG", "info")
        .env("FAKE_JOB_S", job_s.to_string())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        // its own process group: killing it kills its job too, as a machine that dies
        .process_group(0)
        .spawn()
        .map(Child::new)
        .unwrap()
}

fn signal(group: u32, sig: &str) {
    Command::new("kill")
        .args([sig, "--", &format!("-{group}")])
        .status()
        .unwrap();
}

fn wait_until(what: &str, secs: f64, mut f: impl FnMut() -> bool) {
    let t = Instant::now();
    while !f() {
        assert!(
            t.elapsed().as_secs_f64() < secs,
            "waited {secs} s for {what}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Hidden folders left in the results (half-written or staged results).
fn hidden(results: &Path) -> Vec<String> {
    std::fs::read_dir(results)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.starts_with('.'))
        .collect()
}

fn assert_complete(results: &Path, id: &str) {
    for f in conformd::station::pipeline::RESULT_FILES {
        assert!(results.join(id).join(f).is_file(), "{id} lacks {f}");
    }
}

/// Enqueues `n` jobs `<prefix>-NN` with their (empty) capture folders.
fn enqueue(j: &mut journal::Journal, data: &Path, prefix: &str, n: usize) -> Vec<String> {
    let ids: Vec<String> = (0..n).map(|i| format!("{prefix}-{i:02}")).collect();
    for id in &ids {
        let set = data.join("captures").join(id);
        std::fs::create_dir_all(&set).unwrap();
        assert!(j.enqueue(id, &set, None).unwrap());
    }
    ids
}

#[test]
fn a_worker_that_stalls_past_its_lease_finds_its_job_taken_and_discards_its_result() {
    let pg = TempPostgres::start().unwrap();
    let url = pg.database("stall").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path(), &url, Some(&stand_in(dir.path())), "");
    let data = dir.path().join("data");
    let mut j = journal::open(Some(&url), &data).unwrap();
    let ids = enqueue(&mut j, &data, "stall", 4);
    let logs: Vec<PathBuf> = (0..2)
        .map(|k| dir.path().join(format!("worker-{k}.log")))
        .collect();
    let cfg_s = cfg.display().to_string();
    let workers: Vec<Child> = logs
        .iter()
        .map(|l| spawn_with_job_s(&["worker", "--config", &cfg_s], l, 1.0))
        .collect();
    let slow = workers[0].id();
    let mut held = String::new();
    wait_until("the slow worker holding a job", 30.0, || {
        j.list(Some(State::Running), 10)
            .unwrap()
            .into_iter()
            .find(|r| {
                r.worker
                    .as_deref()
                    .is_some_and(|w| w.ends_with(&format!(":{slow}")))
            })
            .map(|job| held = job.id)
            .is_some()
    });
    // it stalls (stopped, job and all) past its 2 s lease: the other takes the job
    signal(slow, "-STOP");
    wait_until("the job taken by the other worker", 30.0, || {
        j.get(&held)
            .unwrap()
            .unwrap()
            .worker
            .is_some_and(|w| !w.ends_with(&format!(":{slow}")))
    });
    signal(slow, "-CONT");
    wait_until("all 4 done", 60.0, || j.counts().unwrap().done == 4);
    // the late one finishes its run too, finds the job not its own, discards its result
    wait_until("the late writer's word", 30.0, || {
        std::fs::read_to_string(&logs[0])
            .unwrap()
            .contains("another worker took it: its outcome is discarded")
    });
    assert_eq!(
        common::recorded_done(&logs),
        ids,
        "a job published twice, or not at all"
    );
    let results = data.join("results");
    for id in &ids {
        assert_complete(&results, id);
    }
    wait_until("no staged result left", 10.0, || {
        hidden(&results).is_empty()
    });
    let runs = std::fs::read_to_string(data.join("runs.log")).unwrap();
    assert_eq!(
        runs.lines().filter(|l| l.starts_with(&held)).count(),
        2,
        "{runs}"
    );
    for w in workers {
        signal(w.id(), "-TERM");
        // a worker that ignores SIGTERM fails here rather than hanging the suite
        let status = common::deadline::status_of(
            w.into_inner(),
            "a worker told to stop",
            Duration::from_secs(60),
        );
        assert!(status.success(), "{status}");
    }
}

#[test]
fn three_workers_60_jobs_one_killed_mid_job_every_job_done_exactly_once() {
    let pg = TempPostgres::start().unwrap();
    let url = pg.database("farm").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let cfg = config(dir.path(), &url, Some(&stand_in(dir.path())), "");
    let data = dir.path().join("data");
    let results = data.join("results");
    let mut j = journal::open(Some(&url), &data).unwrap();
    let ids = enqueue(&mut j, &data, "pig", 60);
    let logs: Vec<PathBuf> = (0..3)
        .map(|k| dir.path().join(format!("worker-{k}.log")))
        .collect();
    let cfg_s = cfg.display().to_string();
    let mut workers: Vec<Child> = logs
        .iter()
        .map(|l| spawn(&["worker", "--config", &cfg_s], l))
        .collect();
    let victim = workers[1].id();
    // kill it while it holds a job, a few jobs in: stopped first, then the job it holds
    // read, so it cannot finish that job between the look and the kill (a job takes
    // 0.2 s here); if it held none once stopped, it goes on and is looked at again
    let mut held = String::new();
    let victims_job = |j: &mut journal::Journal| {
        j.list(Some(State::Running), 100)
            .unwrap()
            .into_iter()
            .find(|r| {
                r.worker
                    .as_deref()
                    .is_some_and(|w| w.ends_with(&format!(":{victim}")))
            })
    };
    wait_until("the victim stopped mid-job", 60.0, || {
        if j.counts().unwrap().done < 10 || victims_job(&mut j).is_none() {
            return false;
        }
        signal(victim, "-STOP");
        match victims_job(&mut j) {
            Some(job) => {
                held = job.id;
                true
            }
            None => {
                signal(victim, "-CONT");
                false
            }
        }
    });
    signal(victim, "-KILL");
    let _ = workers[1].wait();
    wait_until("all 60 jobs done", 120.0, || j.counts().unwrap().done == 60);
    let c = j.counts().unwrap();
    assert_eq!((c.queued, c.running, c.failed), (0, 0, 0));
    // the job the victim held was taken again after its lease ran out
    let again = j.get(&held).unwrap().unwrap();
    assert_eq!(
        (again.state, again.attempts),
        (State::Done, 2),
        "{held}: {again:?}"
    );
    // every result whole, none half-written or staged left behind
    for id in &ids {
        assert_complete(&results, id);
    }
    assert!(hidden(&results).is_empty(), "{:?}", hidden(&results));
    // exactly once: each job was recorded done (its result published) by one worker
    assert_eq!(
        common::recorded_done(&logs),
        ids,
        "a job published twice, or not at all"
    );
    // the victim ran at most the one job again; every job ran at least once
    let runs = std::fs::read_to_string(data.join("runs.log")).unwrap();
    assert!(
        runs.lines().count() >= 60 && runs.lines().count() <= 62,
        "{runs}"
    );
    // the two that live say so; they leave the list when they stop
    let names: Vec<String> = j.workers().unwrap().into_iter().map(|w| w.name).collect();
    assert!(names.len() >= 2, "{names:?}");
    for k in [0, 2] {
        signal(workers[k].id(), "-TERM");
        assert!(workers[k].wait().unwrap().success(), "worker {k} exit");
    }
    let left: Vec<String> = j.workers().unwrap().into_iter().map(|w| w.name).collect();
    assert!(
        left.iter().all(|n| n.ends_with(&format!(":{victim}"))),
        "{left:?}"
    );
}

/// A capture set the daemon takes in: a manifest and the one image it lists.
fn drop_fake_set(incoming: &Path, id: &str) {
    let tmp = incoming.join(format!(".{id}.copying"));
    std::fs::create_dir_all(&tmp).unwrap();
    std::fs::write(tmp.join("cam0.png"), b"not read by the stand-in").unwrap();
    std::fs::write(
        tmp.join("manifest.json"),
        format!("{{\"format\": \"conformd-capture\", \"version\": 1, \"id\": \"{id}\", \"cameras\": [{{\"id\": \"cam0\", \"file\": \"cam0.png\"}}]}}"),
    )
    .unwrap();
    std::fs::rename(&tmp, incoming.join(id)).unwrap();
}

fn status(port: u16) -> Option<serde_json::Value> {
    let body = ureq::get(&format!("http://127.0.0.1:{port}/api/status"))
        .call()
        .ok()?
        .into_body()
        .read_to_string()
        .ok()?;
    serde_json::from_str(&body).ok()
}

#[test]
fn a_station_that_loses_its_database_keeps_its_captures_and_hands_them_over_once() {
    let pg = TempPostgres::start().unwrap();
    let url = pg.database("station").unwrap();
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let extra = format!(
        "[rig]\nfile = \"{}\"\n[daemon]\nlisten = \"127.0.0.1:{port}\"\nworkers = 2\nrescan_s = 0.5\n",
        rig.display()
    );
    let cfg = config(dir.path(), &url, Some(&stand_in(dir.path())), &extra);
    let data = dir.path().join("data");
    let log = dir.path().join("daemon.log");
    let mut daemon = spawn(&["daemon", "--config", &cfg.display().to_string()], &log);
    wait_until("the daemon", 30.0, || status(port).is_some());
    pg.stop().unwrap();
    let ids: Vec<String> = (0..10).map(|i| format!("offline-{i}")).collect();
    for id in &ids {
        drop_fake_set(&data.join("incoming"), id);
    }
    // taken in and kept while the journal is away, and the status says so
    wait_until("10 captures waiting for the journal", 30.0, || {
        status(port).is_some_and(|s| {
            s["journal"]["online"] == false
                && s["journal"]["waiting_handover"].as_array().map(Vec::len) == Some(10)
        })
    });
    for id in &ids {
        assert!(
            data.join("captures")
                .join(id)
                .join("manifest.json")
                .is_file()
        );
    }
    pg.start_server().unwrap();
    let mut j = journal::open(Some(&url), &data).unwrap();
    wait_until("the 10 captures processed", 60.0, || {
        j.counts().unwrap().done == 10
    });
    for id in &ids {
        let job = j.get(id).unwrap().unwrap();
        assert_eq!((job.state, job.attempts), (State::Done, 1), "{id}");
        assert_complete(&data.join("results"), id);
    }
    let runs = std::fs::read_to_string(data.join("runs.log")).unwrap();
    assert_eq!(runs.lines().count(), 10, "processed more than once: {runs}");
    let s = status(port).unwrap();
    assert_eq!(s["journal"]["online"], true);
    let page = ureq::get(&format!("http://127.0.0.1:{port}/"))
        .call()
        .unwrap()
        .into_body()
        .read_to_string()
        .unwrap();
    assert!(
        page.contains("id=\"workers\"") && page.contains(":daemon:farm"),
        "the status page lists no workers"
    );
    assert_eq!(
        s["journal"]["waiting_handover"].as_array().unwrap().len(),
        0
    );
    assert!(
        s["worker_list"]
            .as_array()
            .unwrap()
            .iter()
            .any(|w| w["name"].as_str().unwrap().contains(":daemon:farm")),
        "{s}"
    );
    signal(daemon.id(), "-TERM");
    assert!(daemon.wait().unwrap().success());

    // a station that starts while its database is away captures all the same
    pg.stop().unwrap();
    let mut daemon = spawn(&["daemon", "--config", &cfg.display().to_string()], &log);
    wait_until("the daemon without its database", 30.0, || {
        status(port).is_some()
    });
    for i in 0..3 {
        drop_fake_set(&data.join("incoming"), &format!("late-{i}"));
    }
    wait_until("3 captures waiting", 30.0, || {
        status(port).is_some_and(|s| {
            s["journal"]["online"] == false
                && s["journal"]["waiting_handover"]
                    .as_array()
                    .is_some_and(|w| {
                        w.iter()
                            .filter(|x| x.as_str().unwrap().starts_with("late-"))
                            .count()
                            == 3
                    })
        })
    });
    pg.start_server().unwrap();
    let mut j = journal::open(Some(&url), &data).unwrap();
    wait_until("13 captures processed", 60.0, || {
        j.counts().unwrap().done == 13
    });
    let runs = std::fs::read_to_string(data.join("runs.log")).unwrap();
    assert_eq!(runs.lines().count(), 13, "processed more than once: {runs}");
    signal(daemon.id(), "-TERM");
    assert!(daemon.wait().unwrap().success());
}

#[test]
fn a_worker_runs_the_real_pipeline_and_publishes_whole_results() {
    let pg = TempPostgres::start().unwrap();
    let url = pg.database("real").unwrap();
    let dir = tempfile::tempdir().unwrap();
    // the example rig at half its resolution (as the daemon tests), two captures
    let rig = dir.path().join("rig.toml");
    std::fs::write(
        &rig,
        std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml"),
        )
        .unwrap()
        .replace("image = [1280, 960]", "image = [640, 480]")
        .replace("focal_px = 1100.0", "focal_px = 550.0")
        .replace("speckle_px = 3.0", "speckle_px = 2.0"),
    )
    .unwrap();
    let sim = dir.path().join("sim");
    let sets = conformd::commands::simulate(&rig, "pig", "swing=8,nod=-6", 2, 2.0, &sim).unwrap();
    let extra = format!(
        "[rig]\nfile = \"{}\"\ncalibration = \"{}\"\n[conform]\nmax_iterations = 10\n",
        rig.display(),
        sim.join("calibration").display()
    );
    let cfg = config(dir.path(), &url, None, &extra);
    let data = dir.path().join("data");
    let mut j = journal::open(Some(&url), &data).unwrap();
    let mut ids = Vec::new();
    for s in &sets {
        let id = s.file_name().unwrap().to_string_lossy().to_string();
        let to = data.join("captures").join(&id);
        std::fs::rename(s, &to).unwrap();
        assert!(j.enqueue(&id, &to, None).unwrap());
        ids.push(id);
    }
    let log = dir.path().join("worker.log");
    let mut w = spawn(&["worker", "--config", &cfg.display().to_string()], &log);
    wait_until("2 real jobs done", 240.0, || {
        j.counts().unwrap().done == 2 || j.counts().unwrap().failed > 0
    });
    let log_text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(j.counts().unwrap().done, 2, "{log_text}");
    for id in &ids {
        assert_complete(&data.join("results"), id);
        let report: serde_json::Value = serde_json::from_slice(
            &std::fs::read(data.join("results").join(id).join("report.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(report["capture"], id.as_str());
        let d = report["conformation"]["mean_distance_relative"]
            .as_f64()
            .unwrap();
        assert!(d > 0.0 && d < 0.01, "{id}: distance to the scan {d}");
        // stored relative to the shared root, handed out resolved on this machine
        let job = j.get(id).unwrap().unwrap();
        assert_eq!(job.result.unwrap(), data.join("results").join(id));
    }
    assert!(hidden(&data.join("results")).is_empty());
    signal(w.id(), "-TERM");
    assert!(w.wait().unwrap().success());
}

/// Issue 42's fault 6: a journal server that accepts connections and never answers (a
/// local listener that only accepts). The worker said nothing for 300 s and the daemon
/// never bound its port nor heeded SIGTERM. Now the handshake is time-limited: the
/// worker fails within seconds naming the wait, the daemon serves its API, says the
/// journal is offline and why, and stops on SIGTERM.
#[test]
fn a_journal_server_that_never_answers_hangs_neither_the_worker_nor_the_daemon() {
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let db_port = silent.local_addr().unwrap().port();
    std::thread::spawn(move || {
        let mut held = Vec::new();
        for s in silent.incoming().flatten() {
            held.push(s); // accepted, never read, never answered
        }
    });
    let url = format!("postgres://conformd@127.0.0.1:{db_port}/conformd");
    let limit = journal::HANDSHAKE_LIMIT.as_secs_f64();

    // the worker and the daemon wait out their handshakes side by side
    let worker_dir = tempfile::tempdir().unwrap();
    let cfg = config(worker_dir.path(), &url, None, "");
    let worker_log = worker_dir.path().join("worker.log");
    let t = Instant::now();
    let mut worker = spawn(
        &["worker", "--config", &cfg.display().to_string()],
        &worker_log,
    );

    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let extra = format!(
        "[rig]\nfile = \"{}\"\n[daemon]\nlisten = \"127.0.0.1:{port}\"\nworkers = 1\n",
        rig.display()
    );
    let cfg = config(dir.path(), &url, None, &extra);
    let log = dir.path().join("daemon.log");
    let mut daemon = spawn(&["daemon", "--config", &cfg.display().to_string()], &log);

    wait_until("the worker to give up", limit * 3.0, || {
        worker.try_wait().unwrap().is_some()
    });
    let text = std::fs::read_to_string(&worker_log).unwrap();
    assert!(
        !worker.wait().unwrap().success() && text.contains("has not answered its handshake"),
        "{text}"
    );
    assert!(t.elapsed().as_secs_f64() < limit * 3.0);

    wait_until("the daemon's API", limit * 4.0, || {
        status(port).is_some_and(|s| {
            s["journal"]["online"] == false
                && s["journal"]["error"]
                    .as_str()
                    .is_some_and(|e| e.contains("has not answered"))
        })
    });
    signal(daemon.id(), "-TERM");
    wait_until("the daemon to stop on SIGTERM", 15.0, || {
        daemon.try_wait().unwrap().is_some()
    });
}

/// Issue 45, item 6: a job that fails is queued again after a back-off (5 s, then 20 s
/// ...), up to `max_attempts`, then failed for good; one that runs past the job time
/// limit is stopped (its process killed, not left running) and counts as an attempt.
/// On the SQLite journal, through the runner the daemon and `conformd worker` share.
#[test]
fn failing_jobs_are_retried_with_back_off_up_to_max_attempts_and_slow_ones_stopped() {
    use conformd::daemon::runner::{self, JobSpec, Recorded};
    assert_eq!(
        [1, 2, 3, 4, 12].map(runner::backoff_s),
        [5.0, 20.0, 80.0, 320.0, 3600.0]
    );
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(data.join("results")).unwrap();
    let db = data.join("journal.sqlite");
    let mut j = journal::open_sqlite(&db, &data).unwrap();
    let id = enqueue(&mut j, &data, "retry", 1).remove(0);
    // the job's program: the first run fails as a reconstruction would (not the
    // capture's fault), the next ones hang past the time limit; each run logs its pid
    let program = dir.path().join("flaky.sh");
    std::fs::write(
        &program,
        r#"#!/bin/bash
log="$6/../runs.log"
echo "$$" >> "$log"
if [ "$(wc -l < "$log")" -eq 1 ]; then
  echo '{"ok":false,"stage":"reconstruct","error":"the disk went away","permanent":false}'
  exit 1
fi
exec sleep 60
"#,
    )
    .unwrap();
    Command::new("chmod")
        .arg("+x")
        .arg(&program)
        .status()
        .unwrap();
    let spec = JobSpec {
        exe: program,
        config: dir.path().join("station.toml"),
        results: data.join("results"),
        landmarks: data.join("landmarks"),
        threads: 1,
        timeout: Duration::from_secs(1),
        max_attempts: 3,
        template_cache: None,
    };
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let abort = tokio::sync::Notify::new();
    let pids = || -> Vec<i32> {
        std::fs::read_to_string(data.join("runs.log"))
            .unwrap_or_default()
            .lines()
            .map(|l| l.trim().parse().unwrap())
            .collect()
    };
    let mut outcomes = Vec::new();
    for attempt in 1..=3u32 {
        let job = j.claim("w1", 60.0).unwrap().expect("the job is due");
        assert_eq!(job.attempts, attempt);
        let started = Instant::now();
        let ended = rt.block_on(runner::run_child(&spec, &job, &abort));
        let took = started.elapsed();
        let now = journal::now();
        let recorded = runner::record(&mut j, "w1", &job, ended, &spec).unwrap();
        let after = j.get(&id).unwrap().unwrap();
        match attempt {
            1 => {
                assert!(matches!(recorded, Recorded::Failed { retry: true }));
                assert_eq!(after.stage.as_deref(), Some("reconstruct"));
            }
            _ => {
                // stopped at the limit, not after the program's 60 s, and killed
                assert!(
                    took >= Duration::from_millis(900) && took < Duration::from_secs(20),
                    "{took:?}"
                );
                // (killed: gone, or dead and waiting for the runtime to reap it)
                let pid = *pids().last().unwrap();
                let running = || {
                    std::fs::read_to_string(format!("/proc/{pid}/stat"))
                        .ok()
                        .and_then(|s| {
                            let state = s.rsplit(')').next()?.split_whitespace().next()?;
                            Some(state != "Z" && state != "X")
                        })
                        .unwrap_or(false)
                };
                let since = Instant::now();
                while running() && since.elapsed() < Duration::from_secs(10) {
                    std::thread::sleep(Duration::from_millis(20));
                }
                assert!(
                    !running(),
                    "the timed-out job's process {pid} is still running"
                );
                assert!(
                    after
                        .error
                        .as_deref()
                        .unwrap_or("")
                        .contains("time limit of 1 s"),
                    "{:?}",
                    after.error
                );
                assert!(matches!(
                    recorded,
                    Recorded::TimedOut { retry } if retry == (attempt < 3)
                ));
            }
        }
        if attempt < 3 {
            // queued again, due after the back-off for this attempt, not before
            assert_eq!(after.state, State::Queued);
            let wait = after.not_before - now;
            let want = runner::backoff_s(attempt);
            assert!((wait - want).abs() < 2.0, "due in {wait} s, want {want}");
            assert!(j.claim("w1", 60.0).unwrap().is_none(), "claimed before due");
            // (the test does not wait the back-off out: the job is made due now)
            let c = rusqlite::Connection::open(&db).unwrap();
            c.execute(
                "UPDATE captures SET not_before = 0 WHERE id = ?1",
                [id.as_str()],
            )
            .unwrap();
        } else {
            assert_eq!(
                after.state,
                State::Failed,
                "failed for good after 3 attempts"
            );
            assert_eq!(after.attempts, 3);
            assert!(j.claim("w1", 60.0).unwrap().is_none());
        }
        outcomes.push(format!("{recorded:?}"));
    }
    assert_eq!(pids().len(), 3, "one run per attempt: {outcomes:?}");
}
