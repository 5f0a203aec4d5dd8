//! The station journal: one suite, both stores; every test runs on an SQLite file and
//! on a throwaway PostgreSQL cluster (`common::postgres::TempPostgres`).

use crate::common::postgres as cluster;
use conformd::daemon::journal::*;
use std::path::Path;
use std::sync::OnceLock;

/// One server for the whole test binary, a database per test.
fn server() -> &'static cluster::TempPostgres {
    static PG: OnceLock<cluster::TempPostgres> = OnceLock::new();
    PG.get_or_init(|| cluster::TempPostgres::start().expect("a test PostgreSQL server"))
}

fn next_db() -> String {
    static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    format!(
        "journal_test_{}",
        N.fetch_add(1, std::sync::atomic::Ordering::SeqCst)
    )
}

/// Both journals of a test, with the data root they resolve folders against; `open`
/// makes another connection to the same store.
struct Stores {
    root: tempfile::TempDir,
    pg_url: String,
}

impl Stores {
    fn new() -> Stores {
        Stores {
            root: tempfile::tempdir().unwrap(),
            pg_url: server().database(&next_db()).unwrap(),
        }
    }

    fn open(&self, which: &str) -> Journal {
        match which {
            "sqlite" => {
                open_sqlite(&self.root.path().join("journal.sqlite"), self.root.path()).unwrap()
            }
            _ => open(Some(&self.pg_url), self.root.path()).unwrap(),
        }
    }
}

fn both(test: impl Fn(&Stores, &str)) {
    let s = Stores::new();
    for which in ["sqlite", "postgres"] {
        test(&s, which);
    }
}

fn done(result: &Path) -> Finish {
    Finish::Done {
        result: result.to_path_buf(),
        seconds: serde_json::json!({"total": 1.5}),
        landmarks: None,
    }
}

#[test]
fn a_job_goes_through_its_states_once() {
    both(|s, which| {
        let mut j = s.open(which);
        let root = s.root.path();
        let id = format!("a-{which}");
        assert!(
            j.enqueue(&id, &root.join("captures").join(&id), Some("tag-1"))
                .unwrap()
        );
        assert!(
            !j.enqueue(&id, &root.join("x"), None).unwrap(),
            "enqueued twice"
        );
        let job = j.claim("w1", 30.0).unwrap().unwrap();
        assert_eq!((job.state, job.attempts), (State::Running, 1), "{which}");
        assert_eq!(job.worker.as_deref(), Some("w1"));
        // folders are stored relative to the data root and come back resolved
        assert_eq!(job.dir, root.join("captures").join(&id));
        assert!(j.claim("w2", 30.0).unwrap().is_none(), "claimed twice");
        let retry = Finish::Failed {
            stage: "write".into(),
            error: "disk full".into(),
            retry_at: Some(now() + 3600.0),
        };
        assert_eq!(
            j.finish(&id, "w1", &retry, &mut || Ok(())).unwrap(),
            Finished::Recorded
        );
        assert!(
            j.claim("w1", 30.0).unwrap().is_none(),
            "a retry waits for its time"
        );
        assert_eq!(
            j.next_due().unwrap().map(|t| t > now() + 3000.0),
            Some(true)
        );
        assert!(j.reprocess(&id).unwrap());
        let job = j.claim("w2", 30.0).unwrap().unwrap();
        assert_eq!(job.attempts, 1, "reprocess starts the count again");
        let mut published = 0;
        let r = j
            .finish(
                &id,
                "w2",
                &done(&root.join("results").join(&id)),
                &mut || {
                    published += 1;
                    Ok(())
                },
            )
            .unwrap();
        assert_eq!((r, published), (Finished::Recorded, 1));
        let job = j.get(&id).unwrap().unwrap();
        assert_eq!(job.state, State::Done);
        assert_eq!(job.seconds.unwrap()["total"], 1.5);
        assert_eq!(job.result.unwrap(), root.join("results").join(&id));
        assert_eq!(job.landmarks, None, "an automatic fit");
        // reprocessed with an operator's landmarks: the row names them
        assert!(j.reprocess(&id).unwrap());
        j.claim("w2", 30.0).unwrap().unwrap();
        let manual = Finish::Done {
            result: root.join("results").join(&id),
            seconds: serde_json::json!({"total": 2.0}),
            landmarks: Some("snout, tail_root".into()),
        };
        j.finish(&id, "w2", &manual, &mut || Ok(())).unwrap();
        let job = j.get(&id).unwrap().unwrap();
        assert_eq!(job.landmarks.as_deref(), Some("snout, tail_root"));
        assert_eq!(j.counts().unwrap().done, 1, "{which}");
        assert_eq!(j.list(Some(State::Done), 10).unwrap().len(), 1);
        // a failure for good, then the metrics' view of it
        assert!(j.enqueue("b", &root.join("captures/b"), None).unwrap());
        j.claim("w1", 30.0).unwrap().unwrap();
        let fail = Finish::Failed {
            stage: "reconstruct".into(),
            error: "no points".into(),
            retry_at: None,
        };
        j.finish("b", "w1", &fail, &mut || Ok(())).unwrap();
        assert_eq!(
            j.failures_by_stage().unwrap(),
            vec![("reconstruct".to_string(), 1)]
        );
        assert!(!j.reprocess("nope").unwrap());
        // clean up for the other store's turn: ids differ per store, "b" does not
        drop(j);
    });
}

#[test]
fn only_the_worker_holding_a_job_records_it_and_a_lost_lease_goes_back_to_the_queue() {
    both(|s, which| {
        let mut a = s.open(which);
        let mut b = s.open(which);
        let root = s.root.path();
        let id = format!("lease-{which}");
        a.enqueue(&id, &root.join("captures").join(&id), None)
            .unwrap();
        let job = a.claim("A", 2.0).unwrap().unwrap();
        assert_eq!(job.attempts, 1);
        // A renews while it lives
        assert_eq!(
            a.renew("A", std::slice::from_ref(&id), 2.0).unwrap(),
            vec![id.clone()]
        );
        assert!(
            b.renew("B", std::slice::from_ref(&id), 2.0)
                .unwrap()
                .is_empty(),
            "renewed another's"
        );
        assert!(
            b.expire_leases().unwrap().is_empty(),
            "a live lease expired"
        );
        // A stops answering: its lease runs out and B takes the job
        std::thread::sleep(std::time::Duration::from_millis(2300));
        assert_eq!(b.expire_leases().unwrap(), vec![id.clone()], "{which}");
        let job = b.claim("B", 30.0).unwrap().unwrap();
        assert_eq!((job.attempts, job.worker.as_deref()), (2, Some("B")));
        // A comes back late: its renewal no longer holds the job, its result is not
        // published, nothing is recorded
        assert!(
            a.renew("A", std::slice::from_ref(&id), 2.0)
                .unwrap()
                .is_empty()
        );
        let mut published = false;
        let r = a
            .finish(
                &id,
                "A",
                &done(&root.join("results").join(&id)),
                &mut || {
                    published = true;
                    Ok(())
                },
            )
            .unwrap();
        assert_eq!(r, Finished::NotOwner);
        assert!(!published, "the late writer published");
        assert_eq!(b.get(&id).unwrap().unwrap().state, State::Running);
        // a publish that fails leaves the job running, B's still
        let r = b.finish(&id, "B", &done(&root.join("r")), &mut || {
            Err(std::io::Error::other("disk gone"))
        });
        assert!(r.unwrap_err().to_string().contains("disk gone"));
        assert_eq!(
            b.get(&id).unwrap().unwrap().state,
            State::Running,
            "{which}"
        );
        assert_eq!(
            b.finish(&id, "B", &done(&root.join("r")), &mut || Ok(()))
                .unwrap(),
            Finished::Recorded
        );
        // a shutdown's requeue does not count the attempt
        let id2 = format!("requeue-{which}");
        a.enqueue(&id2, &root.join("c"), None).unwrap();
        a.claim("A", 30.0).unwrap().unwrap();
        a.finish(&id2, "A", &Finish::Requeue, &mut || Ok(()))
            .unwrap();
        let j2 = a.get(&id2).unwrap().unwrap();
        assert_eq!((j2.state, j2.attempts), (State::Queued, 0));
        // a worker that restarts under its name takes its running jobs back at once
        a.claim("A", 30.0).unwrap().unwrap();
        assert_eq!(b.release("A").unwrap(), vec![id2.clone()]);
        assert_eq!(a.get(&id2).unwrap().unwrap().attempts, 1);
    });
}

#[test]
fn concurrent_claims_never_take_one_job_twice() {
    both(|s, which| {
        let n = 120;
        {
            let mut j = s.open(which);
            for i in 0..n {
                j.enqueue(&format!("c{i:03}"), &s.root.path().join("c"), None)
                    .unwrap();
            }
        }
        let taken: Vec<Vec<String>> = std::thread::scope(|sc| {
            let hs: Vec<_> = (0..4)
                .map(|w| {
                    sc.spawn(move || {
                        let mut j = s.open(which);
                        let name = format!("w{w}");
                        let mut mine = Vec::new();
                        while let Some(job) = j.claim(&name, 30.0).unwrap() {
                            // a job takes a moment: the others get their turn
                            std::thread::sleep(std::time::Duration::from_millis(2));
                            j.finish(&job.id, &name, &done(Path::new("r")), &mut || Ok(()))
                                .unwrap();
                            mine.push(job.id);
                        }
                        mine
                    })
                })
                .collect();
            hs.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let mut all: Vec<String> = taken.concat();
        all.sort();
        let before = all.len();
        all.dedup();
        assert_eq!(
            (before, all.len()),
            (n, n),
            "{which}: a job taken twice or lost"
        );
        assert!(
            taken.iter().filter(|t| !t.is_empty()).count() >= 2,
            "{which}: one worker took everything: {:?}",
            taken.iter().map(Vec::len).collect::<Vec<_>>()
        );
        let c = s.open(which).counts().unwrap();
        assert_eq!((c.done, c.queued, c.running), (n as u64, 0, 0));
        // start the other store afresh: same ids
        let mut j = s.open(which);
        for i in 0..n {
            j.reprocess(&format!("c{i:03}")).unwrap();
        }
    });
}

#[test]
fn workers_say_they_are_alive_and_a_found_result_is_adopted() {
    both(|s, which| {
        let mut j = s.open(which);
        let w = WorkerInfo {
            name: format!("host-1:worker:{which}"),
            host: "host-1".into(),
            pid: 42,
            started_at: now() - 10.0,
            heartbeat_at: now(),
            job: Some("x".into()),
            jobs_done: 3,
        };
        j.heartbeat(&w).unwrap();
        j.heartbeat(&WorkerInfo {
            jobs_done: 4,
            ..w.clone()
        })
        .unwrap();
        let ws = j.workers().unwrap();
        assert_eq!(ws.len(), 1, "{which}: {ws:?}");
        assert_eq!((ws[0].jobs_done, ws[0].pid), (4, 42));
        j.worker_gone(&w.name).unwrap();
        assert!(j.workers().unwrap().is_empty());
        let id = format!("adopt-{which}");
        j.enqueue(&id, &s.root.path().join("c"), None).unwrap();
        let seconds = serde_json::json!({"total": 2.0});
        assert!(
            j.adopt(&id, &s.root.path().join("results").join(&id), &seconds)
                .unwrap()
        );
        assert!(
            !j.adopt(&id, Path::new("r"), &seconds).unwrap(),
            "adopted twice"
        );
        assert_eq!(j.get(&id).unwrap().unwrap().state, State::Done);
    });
}

#[test]
fn postgres_wakes_an_idle_worker_on_new_work() {
    let s = Stores::new();
    let mut idle = s.open("postgres");
    let mut station = s.open("postgres");
    assert!(
        !idle
            .wait_for_work(std::time::Duration::from_millis(200))
            .unwrap()
    );
    let t = std::time::Instant::now();
    let h = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_millis(300));
        station.enqueue("n1", Path::new("/c/n1"), None).unwrap();
    });
    assert!(
        idle.wait_for_work(std::time::Duration::from_secs(10))
            .unwrap()
    );
    assert!(
        t.elapsed().as_secs_f64() < 5.0,
        "woken by the poll, not the news"
    );
    h.join().unwrap();
}

#[test]
fn a_dropped_database_link_is_made_again() {
    // a server of its own: the other tests share theirs
    let pg = cluster::TempPostgres::start().unwrap();
    let root = tempfile::tempdir().unwrap();
    let mut j = open(Some(&pg.database("dropped").unwrap()), root.path()).unwrap();
    j.enqueue("l1", Path::new("/c/l1"), None).unwrap();
    pg.stop().unwrap();
    let offline = j.enqueue("l2", Path::new("/c/l2"), None);
    pg.start_server().unwrap();
    let e = offline.expect_err("the database was down");
    assert!(e.to_string().contains("postgres 127.0.0.1"), "{e}");
    assert!(j.enqueue("l2", Path::new("/c/l2"), None).unwrap());
    assert_eq!(j.counts().unwrap().queued, 2);
}

#[test]
fn a_server_never_dropped_stops_when_its_owner_ends() {
    // what a test's static server is: never dropped. Owned here by a short-lived child
    // instead of this test process, so that its end can be watched.
    let mut owner = std::process::Command::new("sleep")
        .arg("1")
        .spawn()
        .unwrap();
    let pg = cluster::TempPostgres::start_watched_by(owner.id()).unwrap();
    let pid = pg.server_pid().expect("the server runs");
    let folder = pg.folder().to_path_buf();
    let alive = |pid: u32| Path::new(&format!("/proc/{pid}")).exists();
    assert!(alive(pid));
    std::mem::forget(pg);
    owner.wait().unwrap();
    let t = std::time::Instant::now();
    while (alive(pid) || folder.exists()) && t.elapsed().as_secs() < 20 {
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    assert!(!alive(pid), "server {pid} still runs after its owner ended");
    assert!(!folder.exists(), "{} left behind", folder.display());
    eprintln!(
        "server {pid} stopped {:.1} s after its owner ended",
        t.elapsed().as_secs_f64()
    );
}
