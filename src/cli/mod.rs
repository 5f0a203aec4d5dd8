//! The `conformd` command line, apart from `main`: its arguments (`args`), one file per
//! command (`commands`) and the progress bars it shows during long work (`progress`).

pub mod args;
pub mod commands;
pub mod progress;

use std::path::Path;

/// A worker process exits once the daemon that started it is gone (it is then owned by
/// init), so a killed daemon leaves no job running behind its back.
pub fn exit_with_parent(pid: u32) {
    std::thread::spawn(move || {
        loop {
            if std::os::unix::process::parent_id() != pid {
                std::process::exit(3);
            }
            std::thread::sleep(std::time::Duration::from_millis(100));
        }
    });
}

/// Test hook for the daemon's crash tests (feature `test-hooks` only): a worker whose
/// capture folder is named in `CONFORMD_TEST_CRASH` aborts (SIGABRT), as a crash inside
/// OpenCV would.
#[cfg(feature = "test-hooks")]
pub fn crash_hook(capture: &Path) {
    if let (Ok(name), Some(dir)) = (std::env::var("CONFORMD_TEST_CRASH"), capture.file_name())
        && dir.to_string_lossy() == name
    {
        std::process::abort();
    }
}

#[cfg(not(feature = "test-hooks"))]
pub fn crash_hook(_: &Path) {}
