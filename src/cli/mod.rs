//! The `conformd` command line, apart from `main`: its arguments (`args`), one file per
//! command (`commands`) and the progress bars it shows during long work (`progress`).

pub mod args;
pub mod commands;
pub mod progress;

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
