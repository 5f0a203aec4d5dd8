//! Reading and writing the files a command or the daemon names: one opener that refuses
//! what is not a regular file (a folder, a device, a FIFO, a socket) before a byte is read
//! and bounds what it reads, and atomic writes (temporary name, fsync, rename), so a reader
//! never blocks on a pipe or reads /dev/zero until memory runs out, and never sees half a
//! file.

use rustix::fs as rfs;
use std::io::Write;
use std::os::fd::OwnedFd;
use std::path::{Path, PathBuf};

/// Why a mesh, landmark or groups file could not be read or written; every variant
/// names the file, and a parse error the line.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: line {line}: {msg}")]
    Line {
        path: String,
        line: usize,
        msg: String,
    },
    #[error("{path}: {msg}")]
    Content { path: String, msg: String },
    #[error("{path}: unsupported mesh format (expected .obj, .ply or .off)")]
    Format { path: String },
}

impl FileError {
    pub fn io(path: &str, source: std::io::Error) -> FileError {
        FileError::Io {
            path: path.to_string(),
            source,
        }
    }
    pub fn line(path: &str, line: usize, msg: impl Into<String>) -> FileError {
        FileError::Line {
            path: path.to_string(),
            line,
            msg: msg.into(),
        }
    }
    pub fn content(path: &str, msg: impl Into<String>) -> FileError {
        FileError::Content {
            path: path.to_string(),
            msg: msg.into(),
        }
    }
}

fn content_err(path: &str, msg: impl Into<String>) -> FileError {
    FileError::content(path, msg)
}

/// Largest image read (a capture, a truth, a calibration view): a 16-bit 8k x 8k PNG.
pub const MAX_IMAGE_BYTES: u64 = 256 << 20;
/// Largest small table read (groups, weights, landmarks): far beyond any real one.
pub const MAX_TABLE_BYTES: u64 = 16 << 20;

/// Largest JSON record read (a manifest, a report): a report holds figures, not meshes.
pub const MAX_REPORT_BYTES: u64 = 64 << 20;

/// Reads a regular file of at most `max` bytes. A folder, a device, a FIFO, a socket or a
/// larger file is refused with a sentence naming it, before anything is read: the kind is
/// checked on the path first (opening a FIFO would block until a writer came), then again
/// on the opened file (the path may have been swapped between the two).
pub fn read_limited(path: &Path, max: u64) -> Result<Vec<u8>, FileError> {
    let name = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|e| FileError::io(&name, e))?;
    check_regular(&name, &meta, max)?;
    let f = std::fs::File::open(path).map_err(|e| FileError::io(&name, e))?;
    read_opened(f, &name, max)
}

/// Reads an opened file, checked again as opened (the path may have been swapped), of
/// at most `max` bytes; `name` names it.
fn read_opened(f: std::fs::File, name: &str, max: u64) -> Result<Vec<u8>, FileError> {
    use std::io::Read;
    let meta = f.metadata().map_err(|e| FileError::io(name, e))?;
    check_regular(name, &meta, max)?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    f.take(max + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| FileError::io(name, e))?;
    if bytes.len() as u64 > max {
        return Err(content_err(
            name,
            format!("grew past {max} bytes while read"),
        ));
    }
    Ok(bytes)
}

/// Checks that `path` is a regular file of at most `max` bytes, for a library that opens
/// the file itself (OpenCV's FileStorage): a FIFO would block it, a device feed it forever.
pub fn check_regular_path(path: &Path, max: u64) -> Result<(), FileError> {
    let name = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|e| FileError::io(&name, e))?;
    check_regular(&name, &meta, max)
}

/// Refuses what is not a regular file of at most `max` bytes, naming its kind.
fn check_regular(name: &str, meta: &std::fs::Metadata, max: u64) -> Result<(), FileError> {
    if !meta.is_file() {
        return Err(content_err(
            name,
            format!("not a regular file (a {})", kind_of(meta)),
        ));
    }
    if meta.len() > max {
        return Err(content_err(
            name,
            format!(
                "{} bytes, more than the {} this file may have",
                meta.len(),
                max
            ),
        ));
    }
    Ok(())
}

/// What a path that is not a regular file is, in words an operator knows.
pub fn kind_of(meta: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = meta.file_type();
    if t.is_dir() {
        "folder"
    } else if t.is_fifo() {
        "named pipe"
    } else if t.is_socket() {
        "socket"
    } else if t.is_char_device() || t.is_block_device() {
        "device"
    } else if t.is_symlink() {
        "symbolic link"
    } else if t.is_file() {
        "regular file"
    } else {
        "special file"
    }
}

/// [`read_limited`] for UTF-8 text.
pub fn read_text_limited(path: &Path, max: u64) -> Result<String, FileError> {
    String::from_utf8(read_limited(path, max)?)
        .map_err(|_| content_err(&path.display().to_string(), "not UTF-8 text"))
}

/// Writes bytes to a new file and syncs it (inside a folder that is renamed into place
/// whole, where a temporary name per file is not needed).
pub fn write_synced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut f = std::fs::File::create(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}

/// Refuses an output path `out` that lies inside `folder` (raw captures are never
/// written into; a result folder is not overwritten by an export), links resolved. `what`
/// names the folder in the sentence, e.g. "the capture set".
pub fn refuse_inside(out: &Path, folder: &Path, what: &str) -> Result<(), FileError> {
    let Ok(folder_real) = folder.canonicalize() else {
        return Ok(()); // a folder that does not exist holds nothing
    };
    // the deepest part of `out` that exists, resolved, with the rest appended
    let out_abs = std::path::absolute(out).unwrap_or_else(|_| out.to_path_buf());
    let mut existing = out_abs.as_path();
    let mut rest = Vec::new();
    let real = loop {
        if let Ok(r) = existing.canonicalize() {
            break r;
        }
        match (existing.parent(), existing.file_name()) {
            (Some(p), Some(n)) => {
                rest.push(n.to_os_string());
                existing = p;
            }
            _ => return Ok(()),
        }
    };
    let real = rest.iter().rev().fold(real, |p, n| p.join(n));
    if real.starts_with(&folder_real) {
        return Err(content_err(
            &out.display().to_string(),
            format!(
                "lies inside {what} {}; write it somewhere else",
                folder.display()
            ),
        ));
    }
    Ok(())
}

/// Syncs a folder, so renames inside it survive a power cut (best effort).
pub fn sync_dir(dir: &Path) {
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// Writes `bytes` to a temporary name in the same directory, syncs it, then renames it
/// over `path`, so a reader (or a crash) never sees a half-written file. The temporary
/// name is new for every write (created exclusively), so two writers of one file at once
/// each rename a whole file of their own: the last one wins, nothing is mixed.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FileError> {
    let name = path.display().to_string();
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| content_err(&name, "not a file name"))?;
    let fd = rfs::open(&dir, dir_flags(), rfs::Mode::empty())
        .map_err(|e| FileError::io(&dir.display().to_string(), e.into()))?;
    write_atomic_at(&fd, &dir, file_name, bytes)
}

fn dir_flags() -> rfs::OFlags {
    rfs::OFlags::RDONLY | rfs::OFlags::DIRECTORY | rfs::OFlags::CLOEXEC
}

/// [`write_atomic`] of `name` inside the open folder `dir` (`dir_path` names it).
fn write_atomic_at(
    dir: &OwnedFd,
    dir_path: &Path,
    name: &std::ffi::OsStr,
    bytes: &[u8],
) -> Result<(), FileError> {
    let shown = dir_path.join(name).display().to_string();
    let io = |e: std::io::Error| FileError::io(&shown, e);
    let (tmp, file) = (0..16)
        .find_map(|_| {
            let tmp = format!(
                ".{}.tmp-{}-{:016x}",
                name.to_string_lossy(),
                std::process::id(),
                rand::random::<u64>()
            );
            match rfs::openat(
                dir,
                tmp.as_str(),
                rfs::OFlags::WRONLY
                    | rfs::OFlags::CREATE
                    | rfs::OFlags::EXCL
                    | rfs::OFlags::NOFOLLOW
                    | rfs::OFlags::CLOEXEC,
                rfs::Mode::from_raw_mode(0o666),
            ) {
                Err(rustix::io::Errno::EXIST) => None,
                r => Some(r.map(|fd| (tmp, std::fs::File::from(fd)))),
            }
        })
        .unwrap_or(Err(rustix::io::Errno::EXIST))
        .map_err(|e| io(e.into()))?;
    let result = (|| -> std::io::Result<()> {
        let mut file = file;
        file.write_all(bytes)?;
        file.sync_all()?;
        rfs::renameat(dir, tmp.as_str(), dir, name)?;
        // the rename itself must survive a power cut
        let _ = rfs::fsync(dir);
        Ok(())
    })();
    if result.is_err() {
        let _ = rfs::unlinkat(dir, tmp.as_str(), rfs::AtFlags::empty());
    }
    result.map_err(io)
}

/// Renames `from` to `to` unless `to` exists (RENAME_NOREPLACE: the check and the rename
/// are one step, so two writers cannot both take one name). `AlreadyExists` when it does.
pub fn rename_no_replace(from: &Path, to: &Path) -> std::io::Result<()> {
    match rfs::renameat_with(rfs::CWD, from, rfs::CWD, to, rfs::RenameFlags::NOREPLACE) {
        // a file system without the flag: the next best, a look before the rename
        Err(rustix::io::Errno::INVAL) | Err(rustix::io::Errno::NOSYS) => {
            if std::fs::symlink_metadata(to).is_ok() {
                return Err(std::io::ErrorKind::AlreadyExists.into());
            }
            std::fs::rename(from, to)
        }
        r => r.map_err(Into::into),
    }
}

/// A folder inside the station's data folder, reached from it one name at a time without
/// following a symbolic link (a result folder, `landmarks/`), so a link planted in shared
/// result storage cannot make the station serve or write a file elsewhere. Files in it
/// are read and written by name, again without following links.
pub struct DataDir {
    fd: OwnedFd,
    path: PathBuf,
}

impl DataDir {
    /// Opens `path`, which must lie inside `root` (the data folder, trusted as it is).
    pub fn open(root: &Path, path: &Path) -> Result<DataDir, FileError> {
        let shown = path.display().to_string();
        let rel = path.strip_prefix(root).map_err(|_| {
            content_err(
                &shown,
                format!("lies outside the data folder {}", root.display()),
            )
        })?;
        let mut fd = rfs::open(root, dir_flags(), rfs::Mode::empty())
            .map_err(|e| FileError::io(&root.display().to_string(), e.into()))?;
        let mut at = root.to_path_buf();
        for part in rel.components() {
            let std::path::Component::Normal(name) = part else {
                return Err(content_err(
                    &shown,
                    "is not a plain path below the data folder",
                ));
            };
            at.push(name);
            fd = rfs::openat(
                &fd,
                name,
                dir_flags() | rfs::OFlags::NOFOLLOW,
                rfs::Mode::empty(),
            )
            .map_err(|e| link_err(&fd, name, &at, e))?;
        }
        Ok(DataDir {
            fd,
            path: path.to_path_buf(),
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Reads the regular file `name` of at most `max` bytes (a link, a pipe or a folder
    /// refused, naming it).
    pub fn read(&self, name: &str, max: u64) -> Result<Vec<u8>, FileError> {
        let shown = self.path.join(name).display().to_string();
        let fd = rfs::openat(
            &self.fd,
            name,
            // NONBLOCK: opening a FIFO returns at once; a regular file reads as ever
            rfs::OFlags::RDONLY
                | rfs::OFlags::NOFOLLOW
                | rfs::OFlags::NONBLOCK
                | rfs::OFlags::CLOEXEC,
            rfs::Mode::empty(),
        )
        .map_err(|e| {
            link_err(
                &self.fd,
                std::ffi::OsStr::new(name),
                &self.path.join(name),
                e,
            )
        })?;
        read_opened(std::fs::File::from(fd), &shown, max)
    }

    /// Whether `name` is there (a link counts as there: it is not followed).
    pub fn has(&self, name: &str) -> bool {
        rfs::statat(&self.fd, name, rfs::AtFlags::SYMLINK_NOFOLLOW).is_ok()
    }

    /// [`write_atomic`] of `name` in this folder; a link of that name is replaced, never
    /// written through.
    pub fn write_atomic(&self, name: &str, bytes: &[u8]) -> Result<(), FileError> {
        write_atomic_at(&self.fd, &self.path, std::ffi::OsStr::new(name), bytes)
    }

    /// Holds this folder for one writer (an exclusive lock on it, across processes) until
    /// the guard is dropped.
    pub fn lock(&self) -> Result<DirLock, FileError> {
        let shown = self.path.display().to_string();
        let fd = rfs::openat(&self.fd, ".", dir_flags(), rfs::Mode::empty())
            .map_err(|e| FileError::io(&shown, e.into()))?;
        rfs::flock(&fd, rfs::FlockOperation::LockExclusive)
            .map_err(|e| FileError::io(&shown, e.into()))?;
        Ok(DirLock { _fd: fd })
    }
}

/// A folder's writer lock; dropping it (closing the descriptor) lets the next writer in.
pub struct DirLock {
    _fd: OwnedFd,
}

/// An open that refused a link or a non-folder said in words.
fn link_err(dir: &OwnedFd, name: &std::ffi::OsStr, at: &Path, e: rustix::io::Errno) -> FileError {
    let shown = at.display().to_string();
    let is_link = rfs::statat(dir, name, rfs::AtFlags::SYMLINK_NOFOLLOW)
        .is_ok_and(|st| rfs::FileType::from_raw_mode(st.st_mode) == rfs::FileType::Symlink);
    match e {
        _ if is_link => content_err(
            &shown,
            "is a symbolic link; the station follows no link inside its data folder",
        ),
        rustix::io::Errno::NOTDIR => content_err(&shown, "is not a folder"),
        e => FileError::io(&shown, e.into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writers_of_one_file_at_once_never_mix_or_fail() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("review.json");
        std::thread::scope(|s| {
            for w in 0..4u8 {
                let path = &path;
                s.spawn(move || {
                    for _ in 0..100 {
                        write_atomic(path, &vec![b'a' + w; 10_000]).unwrap();
                    }
                });
            }
            for _ in 0..200 {
                if let Ok(b) = std::fs::read(&path) {
                    assert!(b.len() == 10_000 && b.iter().all(|&c| c == b[0]), "mixed");
                }
            }
        });
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().flatten().collect();
        assert_eq!(names.len(), 1, "temporary files left: {names:?}");
    }

    #[test]
    fn links_below_the_data_folder_are_not_followed() {
        let root = tempfile::tempdir().unwrap();
        let data = root.path().join("data");
        let outside = root.path().join("outside");
        std::fs::create_dir_all(data.join("results/a")).unwrap();
        std::fs::create_dir_all(&outside).unwrap();
        std::fs::write(outside.join("secret"), "secret").unwrap();
        std::os::unix::fs::symlink(outside.join("secret"), data.join("results/a/view.json"))
            .unwrap();
        std::os::unix::fs::symlink(&outside, data.join("results/b")).unwrap();
        std::fs::write(data.join("results/a/report.json"), "{}").unwrap();

        let a = DataDir::open(&data, &data.join("results/a")).unwrap();
        assert_eq!(a.read("report.json", 100).unwrap(), b"{}");
        let e = a.read("view.json", 100).unwrap_err().to_string();
        assert!(
            e.contains("symbolic link") && e.contains("view.json"),
            "{e}"
        );
        assert!(a.read("missing", 100).is_err());
        assert!(a.has("view.json") && !a.has("missing"));
        // a linked result folder: neither read nor written through
        let e = DataDir::open(&data, &data.join("results/b"))
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("symbolic link") && e.contains("results/b"),
            "{e}"
        );
        assert!(DataDir::open(&data, &outside).is_err());
        assert!(DataDir::open(&data, &data.join("results/../../outside")).is_err());
        // writing over a link replaces the link, the file it named is untouched
        a.write_atomic("view.json", b"[]").unwrap();
        assert_eq!(std::fs::read(outside.join("secret")).unwrap(), b"secret");
        assert_eq!(a.read("view.json", 100).unwrap(), b"[]");
        // one writer at a time across descriptors
        let held = a.lock().unwrap();
        let other = DataDir::open(&data, &data.join("results/a")).unwrap();
        let got = std::sync::atomic::AtomicBool::new(false);
        std::thread::scope(|s| {
            s.spawn(|| {
                let _l = other.lock().unwrap();
                got.store(true, std::sync::atomic::Ordering::SeqCst);
            });
            std::thread::sleep(std::time::Duration::from_millis(50));
            assert!(
                !got.load(std::sync::atomic::Ordering::SeqCst),
                "two writers"
            );
            drop(held);
        });
        assert!(got.load(std::sync::atomic::Ordering::SeqCst));
    }

    #[test]
    fn a_name_taken_is_never_renamed_over() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b, c) = (
            dir.path().join("a"),
            dir.path().join("b"),
            dir.path().join("c"),
        );
        std::fs::create_dir(&a).unwrap();
        std::fs::create_dir(&b).unwrap();
        let e = rename_no_replace(&a, &b).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::AlreadyExists);
        rename_no_replace(&a, &c).unwrap();
        assert!(!a.exists() && c.exists() && b.exists());
    }
}
