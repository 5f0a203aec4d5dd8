//! Running a child process with a deadline, so a regression that blocks it (a reader
//! waiting on a FIFO, a server that never stops) fails the test that ran it instead of
//! hanging the suite.

use std::io::Read;
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::time::{Duration, Instant};

/// How long a command-line child may take unless its test says otherwise.
pub const CHILD_LIMIT: Duration = Duration::from_secs(300);

/// Running a child to its end within a time limit.
pub trait Deadline {
    /// Like [`Command::output`], but the child (and every process it started) is
    /// killed and the test fails, naming the command, when it is still running after
    /// `limit`.
    fn output_within(&mut self, limit: Duration) -> Output;
}

impl Deadline for Command {
    fn output_within(&mut self, limit: Duration) -> Output {
        // its own process group: on the deadline the whole group is killed, so no
        // grandchild keeps the pipes open or outlives the test
        self.stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .process_group(0);
        let shown = format!("{self:?}");
        let child = self
            .spawn()
            .unwrap_or_else(|e| panic!("{shown} did not start: {e}"));
        output_of(child, &shown, limit)
    }
}

/// Waits for `child` (its output read as it comes, when piped) up to `limit`; past it,
/// kills the child (its process group too, when it leads one) and fails naming `shown`.
pub fn output_of(mut child: Child, shown: &str, limit: Duration) -> Output {
    let drain = |pipe: Option<Box<dyn Read + Send>>| {
        std::thread::spawn(move || {
            let mut v = Vec::new();
            if let Some(mut p) = pipe {
                let _ = p.read_to_end(&mut v);
            }
            v
        })
    };
    let out = drain(
        child
            .stdout
            .take()
            .map(|p| Box::new(p) as Box<dyn Read + Send>),
    );
    let err = drain(
        child
            .stderr
            .take()
            .map(|p| Box::new(p) as Box<dyn Read + Send>),
    );
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().expect("the child's state") {
            break s;
        }
        if start.elapsed() > limit {
            let _ = Command::new("kill")
                .args(["-KILL", "--", &format!("-{}", child.id())])
                .stderr(Stdio::null())
                .status();
            let _ = child.kill();
            let _ = child.wait();
            let err = String::from_utf8_lossy(&err.join().unwrap_or_default()).into_owned();
            panic!(
                "{shown} was still running after {limit:?}: killed. Its stderr: {}",
                err.chars().take(2000).collect::<String>()
            );
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    Output {
        status,
        stdout: out.join().unwrap_or_default(),
        stderr: err.join().unwrap_or_default(),
    }
}

/// [`output_of`] for a child whose output is not wanted: its exit status.
pub fn status_of(child: Child, shown: &str, limit: Duration) -> ExitStatus {
    output_of(child, shown, limit).status
}
