//! The station's speed (the daemon issue's targets): capture-to-result latency of one
//! simulated 2-pod 1280x960 capture with a 10,000-vertex pig (the set renamed into
//! `incoming/`, the time until the journal says done), and sustained throughput with 12
//! sets dropped at once. The daemon runs in this process; its workers are the `conformd`
//! binary. Run: `cargo bench --bench daemon`; `-- --postgres` puts the journal on a
//! throwaway PostgreSQL cluster, `-- --remote N` also (the daemon runs no job itself) and
//! has N `conformd worker` processes run the jobs.

#[path = "../tests/common/postgres.rs"]
mod postgres;

use conformd::daemon::Handle;
use conformd::station::StationConfig;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

fn copy_as(from: &Path, to_root: &Path, id: &str) -> PathBuf {
    let staging = to_root.join(format!(".{id}.copying"));
    std::fs::create_dir_all(&staging).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_name() == "manifest.json" {
            let mut v: serde_json::Value =
                serde_json::from_slice(&std::fs::read(e.path()).unwrap()).unwrap();
            v["id"] = id.into();
            std::fs::write(
                staging.join("manifest.json"),
                serde_json::to_vec(&v).unwrap(),
            )
            .unwrap();
        } else {
            std::fs::copy(e.path(), staging.join(e.file_name())).unwrap();
        }
    }
    staging
}

fn wait_done(h: &Handle, n: u64) {
    let t = Instant::now();
    loop {
        let c = h.shared.journal().counts().unwrap();
        assert_eq!(c.failed, 0, "a capture failed");
        if c.done >= n {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(900), "timed out");
        std::thread::sleep(Duration::from_millis(10));
    }
}

fn main() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let rig = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/rig.example.toml");
    let sets: Vec<PathBuf> = (0..3)
        .flat_map(|i| {
            let pose = format!("swing={},nod={}", 8 - 6 * i, -5 + 5 * i);
            conformd::commands::simulate(&rig, "pig", &pose, 1, 2.0, &d.join("sim")).unwrap()
        })
        .collect();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let args: Vec<String> = std::env::args().collect();
    let remote: usize = args
        .iter()
        .position(|a| a == "--remote")
        .and_then(|i| args.get(i + 1)?.parse().ok())
        .unwrap_or(0);
    let pg = (remote > 0 || args.iter().any(|a| a == "--postgres")).then(|| {
        postgres::TempPostgres::start().expect("a PostgreSQL server (make test installs it)")
    });
    let journal = match &pg {
        Some(pg) => format!("[journal]\nurl = \"{}\"\n", pg.database("bench").unwrap()),
        None => String::new(),
    };
    let station = d.join("station.toml");
    std::fs::write(
        &station,
        format!(
            "[station]\nname = \"bench\"\ndata = \"data\"\n[template]\ngeneric = \"pig\"\nvertices = 10000\n\
             [rig]\nfile = \"{}\"\ncalibration = \"sim/calibration\"\n\
             [daemon]\nlisten = \"127.0.0.1:{port}\"\nrescan_s = 1.0\nlocal_workers = {}\n{journal}",
            rig.display(),
            remote == 0
        ),
    )
    .unwrap();
    let workers: Vec<std::process::Child> = (0..remote)
        .map(|_| {
            std::process::Command::new(env!("CARGO_BIN_EXE_conformd"))
                .args(["worker", "--config"])
                .arg(&station)
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .spawn()
                .unwrap()
        })
        .collect();
    let cfg = StationConfig::load(&station).unwrap();
    let incoming = cfg.station.incoming();
    let exe = PathBuf::from(env!("CARGO_BIN_EXE_conformd"));
    let h = Handle::spawn(cfg, Some(exe)).unwrap();
    println!(
        "daemon ({}) with {} on {} cores",
        h.shared.journal().describe(),
        if remote > 0 {
            format!("{remote} remote worker process(es), none of its own")
        } else {
            format!("{} workers", h.shared.workers)
        },
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    );

    // latency: one capture at a time, from its arrival to done in the journal
    let mut latencies = Vec::new();
    let mut stages = Vec::new();
    for (i, set) in sets.iter().enumerate() {
        let id = format!("latency-{i}");
        let staged = copy_as(set, &incoming, &id);
        let t = Instant::now();
        // found by the folder watcher, as a set another program drops in is
        std::fs::rename(&staged, incoming.join(&id)).unwrap();
        wait_done(&h, i as u64 + 1);
        latencies.push(t.elapsed().as_secs_f64());
        let job = h.shared.journal().get(&id).unwrap().unwrap();
        stages.push(job.seconds.unwrap_or_default());
    }
    for (l, s) in latencies.iter().zip(&stages) {
        println!(
            "capture-to-result {l:.2} s (worker's stages: read {:.2}, reconstruct {:.2}, conform {:.2}, preview {:.2}, total {:.2})",
            s["read"].as_f64().unwrap_or(0.0),
            s["reconstruct"].as_f64().unwrap_or(0.0),
            s["conform"].as_f64().unwrap_or(0.0),
            s["preview"].as_f64().unwrap_or(0.0),
            s["total"].as_f64().unwrap_or(0.0)
        );
    }
    latencies.sort_by(f64::total_cmp);
    println!(
        "latency: median {:.2} s over {} captures (target < 5 s)",
        latencies[latencies.len() / 2],
        latencies.len()
    );

    // throughput: 12 sets at once
    let n = 12;
    let staged: Vec<(PathBuf, String)> = (0..n)
        .map(|i| {
            let id = format!("burst-{i:02}");
            (copy_as(&sets[i % sets.len()], &incoming, &id), id)
        })
        .collect();
    let t = Instant::now();
    for (s, id) in &staged {
        std::fs::rename(s, incoming.join(id)).unwrap();
    }
    h.shared.wake.notify_one();
    wait_done(&h, (sets.len() + n) as u64);
    let secs = t.elapsed().as_secs_f64();
    println!(
        "throughput: {n} captures in {secs:.1} s = {:.1} captures per minute",
        n as f64 / secs * 60.0
    );
    h.stop().unwrap();
    for mut w in workers {
        let _ = std::process::Command::new("kill")
            .arg("-TERM")
            .arg(w.id().to_string())
            .status();
        let _ = w.wait();
    }
}
