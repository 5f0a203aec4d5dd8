//! A throwaway PostgreSQL server for tests and benchmarks: Debian's server binaries, a
//! cluster in a temporary folder, trust authentication on 127.0.0.1 and a socket in that
//! folder, a free port. Run as root, it runs as the `postgres` user (the server refuses
//! root). `make test` installs the `postgresql` package when it is missing.

// each includer (the tests, two benches) uses some of it
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

pub struct TempPostgres {
    bin: PathBuf,
    dir: tempfile::TempDir,
    port: u16,
    /// run the server's programs as this user (we are root)
    user: Option<String>,
}

fn server_bin() -> Result<PathBuf, String> {
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .map_err(|_| {
            "the PostgreSQL server is not installed (/usr/lib/postgresql is missing): `make test` installs it, or `apt-get install postgresql`".to_string()
        })?
        .flatten()
        .filter_map(|e| {
            let v = e.file_name().to_string_lossy().parse::<u32>().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").is_file().then_some((v, bin))
        })
        .collect();
    versions.sort();
    versions
        .pop()
        .map(|(_, b)| b)
        .ok_or_else(|| "no PostgreSQL server version under /usr/lib/postgresql has initdb".into())
}

impl TempPostgres {
    /// Makes and starts a cluster; its database `postgres` and user `conformd` exist.
    /// The server stops when this value is dropped, and at the latest when this process
    /// ends (a test's static is never dropped; a test may be killed).
    pub fn start() -> Result<TempPostgres, String> {
        TempPostgres::start_watched_by(std::process::id())
    }

    /// [`TempPostgres::start`], the server stopped and its folder removed once process
    /// `owner` has ended, by a watchdog outside this process.
    pub fn start_watched_by(owner: u32) -> Result<TempPostgres, String> {
        let bin = server_bin()?;
        let root = running_as_root();
        // the server's user must reach its folder: /tmp, not a private TMPDIR of root's
        let parent = if root {
            PathBuf::from("/tmp")
        } else {
            std::env::temp_dir()
        };
        let dir = tempfile::Builder::new()
            .prefix("conformd-pg-")
            .tempdir_in(parent)
            .map_err(|e| format!("temporary folder: {e}"))?;
        let user = root.then(|| "postgres".to_string());
        if root {
            let out = Command::new("chown")
                .arg("-R")
                .arg("postgres:")
                .arg(dir.path())
                .output()
                .map_err(|e| format!("chown: {e}"))?;
            if !out.status.success() {
                return Err(format!(
                    "cannot hand {} to the postgres user: {}",
                    dir.path().display(),
                    String::from_utf8_lossy(&out.stderr).trim()
                ));
            }
        }
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(|e| format!("a free port: {e}"))?
            .port();
        let pg = TempPostgres {
            bin,
            dir,
            port,
            user,
        };
        let data = pg.data();
        pg.run(
            "initdb",
            &[
                "-D",
                &data,
                "-A",
                "trust",
                "-U",
                "conformd",
                "-E",
                "UTF8",
                "--no-sync",
            ],
        )?;
        pg.start_server()?;
        pg.watch(owner)?;
        Ok(pg)
    }

    /// A shell loop that waits for `owner` to end, then stops the server at once and
    /// removes its folder; it ends with them.
    fn watch(&self, owner: u32) -> Result<(), String> {
        let quote = |s: &str| format!("'{}'", s.replace('\'', r"'\''"));
        let pg_ctl = self.bin.join("pg_ctl").display().to_string();
        let stop = match &self.user {
            Some(u) => format!("runuser -u {} -- {}", quote(u), quote(&pg_ctl)),
            None => quote(&pg_ctl),
        };
        let script = format!(
            "while kill -0 {owner} 2>/dev/null; do sleep 0.5; done; {stop} -D {} -m immediate -w stop; rm -rf {}",
            quote(&self.data()),
            quote(&self.dir.path().display().to_string())
        );
        Command::new("sh")
            .arg("-c")
            .arg(script)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .map(drop)
            .map_err(|e| format!("the server's watchdog (sh): {e}"))
    }

    /// The server's process id while it runs (the first line of `postmaster.pid`).
    pub fn server_pid(&self) -> Option<u32> {
        std::fs::read_to_string(self.dir.path().join("data/postmaster.pid"))
            .ok()?
            .lines()
            .next()?
            .trim()
            .parse()
            .ok()
    }

    fn data(&self) -> String {
        self.dir.path().join("data").display().to_string()
    }

    fn run(&self, program: &str, args: &[&str]) -> Result<(), String> {
        let exe = self.bin.join(program);
        let mut cmd = match &self.user {
            Some(u) => {
                let mut c = Command::new("runuser");
                c.arg("-u").arg(u).arg("--").arg(&exe);
                c
            }
            None => Command::new(&exe),
        };
        let out = cmd
            .args(args)
            .current_dir(self.dir.path())
            .output()
            .map_err(|e| format!("{}: {e}", exe.display()))?;
        if out.status.success() {
            Ok(())
        } else {
            Err(format!(
                "{program} failed: {}{}",
                String::from_utf8_lossy(&out.stderr).trim(),
                std::fs::read_to_string(self.dir.path().join("log"))
                    .map(|l| format!("; server log: {}", l.trim()))
                    .unwrap_or_default()
            ))
        }
    }

    /// Starts the server (again, after [`TempPostgres::stop`]).
    pub fn start_server(&self) -> Result<(), String> {
        let opts = format!(
            "-p {} -k {} -c listen_addresses=127.0.0.1 -c fsync=off -c synchronous_commit=off -c max_connections=60",
            self.port,
            self.dir.path().display()
        );
        let log = self.dir.path().join("log").display().to_string();
        self.run(
            "pg_ctl",
            &["-D", &self.data(), "-o", &opts, "-l", &log, "-w", "start"],
        )
    }

    /// Stops the server at once (the link to the database is gone).
    pub fn stop(&self) -> Result<(), String> {
        self.run("pg_ctl", &["-D", &self.data(), "-m", "fast", "-w", "stop"])
    }

    /// Creates database `name`; returns its URL.
    pub fn database(&self, name: &str) -> Result<String, String> {
        let mut c = postgres::Client::connect(&self.url("postgres"), postgres::NoTls)
            .map_err(|e| format!("connecting to the test server: {e}"))?;
        c.batch_execute(&format!("CREATE DATABASE {name}"))
            .map_err(|e| format!("CREATE DATABASE {name}: {e}"))?;
        Ok(self.url(name))
    }

    pub fn url(&self, db: &str) -> String {
        format!("postgres://conformd@127.0.0.1:{}/{db}", self.port)
    }

    pub fn folder(&self) -> &Path {
        self.dir.path()
    }
}

impl Drop for TempPostgres {
    fn drop(&mut self) {
        let _ = self.run(
            "pg_ctl",
            &["-D", &self.data(), "-m", "immediate", "-w", "stop"],
        );
    }
}

fn running_as_root() -> bool {
    // the effective user id, from the kernel's own record of this process
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("Uid:"))
                .and_then(|l| l.split_whitespace().nth(2).map(|u| u == "0"))
        })
        .unwrap_or(false)
}
