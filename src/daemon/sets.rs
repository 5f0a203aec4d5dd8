//! What the daemon finds in `captures/` and `incoming/`: the capture sets it can take,
//! the ones still being written, and every entry it will not take with the reason, so an
//! operator sees each set the station will not process (in the log once, and on the
//! status page) instead of a silent ignore.

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// An incoming set is taken once none of its files has changed for this long: a writer
/// that writes in place (manifest first) is not robbed of a growing image.
pub const SETTLE: Duration = Duration::from_secs(1);

/// A folder still incomplete after this long is reported (a copy that stopped half way).
pub const STALE: Duration = Duration::from_secs(600);

/// One folder's scan.
#[derive(Debug, Default)]
pub struct Found {
    /// complete sets: (id, folder), sorted by id
    pub sets: Vec<(String, PathBuf)>,
    /// entries that will not be taken: (name as shown, reason)
    pub refused: Vec<(String, String)>,
    /// some set is complete but its files changed within [`SETTLE`]: scan again soon
    pub settling: bool,
}

/// Scans `root`. Entries `skip` names (sets the journal already has) are passed over
/// before anything is read; with `settle`, a complete set whose files changed within
/// that time waits, unless `moved_in` says the folder was renamed into `root` and none
/// of its files changed after that (a set that came whole).
pub fn scan_folder(
    root: &Path,
    settle: Option<Duration>,
    moved_in: impl Fn(&str) -> bool,
    mut skip: impl FnMut(&str) -> bool,
) -> Found {
    let mut found = Found::default();
    let Ok(rd) = std::fs::read_dir(root) else {
        return found;
    };
    let now = SystemTime::now();
    for e in rd.flatten() {
        let raw = e.file_name();
        let name = raw.to_string_lossy().to_string();
        if name.starts_with('.') && in_progress(&name, &e.path(), now) {
            continue;
        }
        if let Err(why) = crate::paths::check_plain_name("capture id", &name) {
            found.refused.push((
                name.escape_debug().to_string(),
                format!("{why}; it is never taken in: rename the folder"),
            ));
            continue;
        }
        if skip(&name) {
            continue;
        }
        match look_at(&e.path(), settle, moved_in(&name), now) {
            Look::Set => found.sets.push((name, e.path())),
            Look::Waiting => {}
            Look::Settling => found.settling = true,
            Look::Refused(why) => found.refused.push((name, why)),
        }
    }
    found.sets.sort();
    found.refused.sort();
    found
}

/// A hidden name is how writers keep a set out of sight while it is on its way (this
/// daemon's own `.<id>.partial`, copiers' and editors' temporary names): passed over
/// without a word while it is young, reported once it has stayed [`STALE`]; this
/// daemon's own partial folders never.
fn in_progress(name: &str, path: &Path, now: SystemTime) -> bool {
    if name.ends_with(".partial") || name.contains(".partial-") {
        return true;
    }
    std::fs::symlink_metadata(path)
        .ok()
        .and_then(|m| m.modified().ok())
        .and_then(|t| now.duration_since(t).ok())
        .is_none_or(|age| age < STALE)
}

enum Look {
    Set,
    Waiting,
    Settling,
    Refused(String),
}

fn look_at(dir: &Path, settle: Option<Duration>, moved_in: bool, now: SystemTime) -> Look {
    let Ok(meta) = std::fs::symlink_metadata(dir) else {
        return Look::Waiting; // gone between listing and looking
    };
    if meta.file_type().is_symlink() {
        return Look::Refused(
            "a symbolic link; a capture set must be a folder here (links are not followed)".into(),
        );
    }
    if !meta.is_dir() {
        return Look::Refused(format!(
            "a {}, not a capture set folder",
            crate::files::kind_of(&meta)
        ));
    }
    let age = |m: &std::fs::Metadata| {
        m.modified()
            .ok()
            .and_then(|t| now.duration_since(t).ok())
            .unwrap_or_default()
    };
    let manifest = dir.join("manifest.json");
    let mm = match std::fs::symlink_metadata(&manifest) {
        Ok(m) => m,
        Err(_) if age(&meta) > STALE => {
            return Look::Refused(format!(
                "no manifest.json after {} minutes; a set counts once its manifest and images are there",
                STALE.as_secs() / 60
            ));
        }
        Err(_) => return Look::Waiting,
    };
    if !mm.is_file() {
        return Look::Refused(format!(
            "its manifest.json is a {}, not a regular file",
            crate::files::kind_of(&mm)
        ));
    }
    // a manifest that cannot be read or parsed is taken anyway: the job fails naming why
    let files: Vec<String> = crate::files::read_limited(&manifest, crate::files::MAX_REPORT_BYTES)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| {
            v.get("cameras")?.as_array().map(|cs| {
                cs.iter()
                    .filter_map(|c| c.get("file")?.as_str().map(str::to_string))
                    .collect()
            })
        })
        .unwrap_or_default();
    let mut newest = age(&mm);
    let mut last_write = mm.modified().ok();
    let mut missing = Vec::new();
    for f in &files {
        if crate::paths::check_plain_name("file", f).is_err() {
            continue; // the job refuses it, naming it
        }
        match std::fs::symlink_metadata(dir.join(f)) {
            Ok(m) => {
                newest = newest.min(age(&m));
                last_write = last_write.max(m.modified().ok());
            }
            Err(_) => missing.push(f.as_str()),
        }
    }
    if !missing.is_empty() {
        if age(&mm) > STALE {
            return Look::Refused(format!(
                "its manifest lists {}, missing for more than {} minutes",
                missing.join(", "),
                STALE.as_secs() / 60
            ));
        }
        return Look::Waiting;
    }
    if settle.is_some_and(|s| newest < s) && !(moved_in && written_before_move(&meta, last_write)) {
        return Look::Settling;
    }
    Look::Set
}

/// Whether every file was last written no later than the folder changed last (its
/// ctime): for a folder renamed into place, the rename. A file written into it after the
/// rename is newer (creating one also moves the folder's ctime, but its writes come
/// after).
fn written_before_move(dir: &std::fs::Metadata, last_write: Option<SystemTime>) -> bool {
    use std::os::unix::fs::MetadataExt;
    let Ok(nanos) = u32::try_from(dir.ctime_nsec()) else {
        return false;
    };
    let Some(changed) = u64::try_from(dir.ctime())
        .ok()
        .map(|s| SystemTime::UNIX_EPOCH + Duration::new(s, nanos))
    else {
        return false;
    };
    last_write.is_some_and(|w| w <= changed)
}
