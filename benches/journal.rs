//! Queue overhead (issue 13): claims per second with a no-op job (claim, then record it
//! done) by 1, 2 and 4 workers, each with its own connection, on PostgreSQL (a throwaway
//! local cluster, `fsync` off as in the tests) and on the SQLite file. Target on
//! PostgreSQL: >= 500 claims/s. Run: `cargo bench --bench journal`.

use conformd::daemon::journal::{self, Finish};
#[path = "../tests/common/postgres.rs"]
mod postgres;
use postgres::TempPostgres;
use std::path::Path;
use std::time::Instant;

const JOBS: usize = 2000;

fn run(label: &str, open: &(dyn Fn() -> journal::Journal + Sync), workers: usize) {
    {
        let mut j = open();
        for i in 0..JOBS {
            j.enqueue(&format!("{label}-{workers}-{i:05}"), Path::new("c"), None)
                .unwrap();
        }
    }
    let t = Instant::now();
    let counts: Vec<usize> = std::thread::scope(|s| {
        let hs: Vec<_> = (0..workers)
            .map(|w| {
                s.spawn(move || {
                    let mut j = open();
                    let name = format!("bench-{w}");
                    let done = Finish::Done {
                        result: "r".into(),
                        seconds: serde_json::json!({}),
                        landmarks: None,
                    };
                    let mut n = 0;
                    while let Some(job) = j.claim(&name, 30.0).unwrap() {
                        j.finish(&job.id, &name, &done, &mut || Ok(())).unwrap();
                        n += 1;
                    }
                    n
                })
            })
            .collect();
        hs.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let secs = t.elapsed().as_secs_f64();
    assert_eq!(
        counts.iter().sum::<usize>(),
        JOBS,
        "a job lost or taken twice"
    );
    println!(
        "{label:<10} {workers} worker(s): {JOBS} claims in {secs:.2} s = {:>6.0} claims/s (per worker {:?})",
        JOBS as f64 / secs,
        counts
    );
}

fn main() {
    let root = tempfile::tempdir().unwrap();
    let pg = TempPostgres::start().expect("a PostgreSQL server (make test installs it)");
    println!(
        "journal queue overhead, no-op jobs, {} cores",
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    );
    for workers in [1, 2, 4] {
        let url = pg.database(&format!("bench_{workers}")).unwrap();
        let open = || journal::open(Some(&url), root.path()).unwrap();
        run("postgres", &open, workers);
    }
    for workers in [1, 2, 4] {
        let file = root.path().join(format!("bench-{workers}.sqlite"));
        let open = || journal::open_sqlite(&file, root.path()).unwrap();
        run("sqlite", &open, workers);
    }
}
