//! Reading and writing the files a command or the daemon names: one opener that refuses
//! what is not a regular file (a folder, a device, a FIFO, a socket) before a byte is read
//! and bounds what it reads, and atomic writes (temporary name, fsync, rename), so a reader
//! never blocks on a pipe or reads /dev/zero until memory runs out, and never sees half a
//! file.

use std::io::Write;
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
    use std::io::Read;
    let name = path.display().to_string();
    let meta = std::fs::metadata(path).map_err(|e| FileError::io(&name, e))?;
    check_regular(&name, &meta, max)?;
    let f = std::fs::File::open(path).map_err(|e| FileError::io(&name, e))?;
    let meta = f.metadata().map_err(|e| FileError::io(&name, e))?;
    check_regular(&name, &meta, max)?;
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    f.take(max + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| FileError::io(&name, e))?;
    if bytes.len() as u64 > max {
        return Err(content_err(
            &name,
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
/// over `path`, so a reader (or a crash) never sees a half-written file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), FileError> {
    let name = path.display().to_string();
    let io = |e| FileError::io(&name, e);
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| content_err(&name, "not a file name"))?;
    let tmp = dir.join(format!(
        ".{}.tmp-{}",
        file_name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)?;
        // Sync the directory so the rename itself survives a power cut.
        sync_dir(&dir);
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.map_err(io)
}
