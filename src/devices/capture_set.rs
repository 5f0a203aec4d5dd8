//! The capture-set format (ARCHITECTURE.md): a folder `<id>/` holding one image per camera and
//! `manifest.json`, written last. One writer (capture sessions and the virtual rig both
//! use it) and one reader, which trusts nothing in the folder: names in the manifest are
//! plain names inside the set, files are regular and size-limited, images are checked
//! against the manifest before anyone matches them.

use crate::files::{rename_no_replace, sync_dir, write_synced};
use crate::paths::check_plain_name;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

/// Largest `manifest.json` read.
const MAX_MANIFEST_BYTES: u64 = 1 << 20;
/// Largest camera image read (a 12-bit 20-megapixel PNG fits).
/// Most cameras one set may list.
const MAX_CAMERAS: usize = 256;

/// `manifest.json` of a capture set (layout in ARCHITECTURE.md).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    pub id: String,
    pub station: String,
    pub subject: Option<String>,
    pub started_utc: String,
    pub finished_utc: String,
    pub trigger: TriggerRecord,
    pub cameras: Vec<CameraRecord>,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TriggerRecord {
    pub kind: String,
    pub sequence: u32,
    pub box_time_us: Option<u64>,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraRecord {
    pub id: String,
    pub pod: String,
    pub side: String,
    pub file: String,
    pub width: u32,
    pub height: u32,
    pub sensor_timestamp_us: u64,
    pub sequence: u32,
    pub exposure_us: Option<u32>,
}

impl Manifest {
    pub const FORMAT: &'static str = "conformd-capture";
    pub const VERSION: u32 = 1;

    /// Checks what serde cannot: format and version, plain and distinct ids and file
    /// names, a pod and side for every camera, sizes within reason.
    pub fn check(&self) -> Result<(), ManifestError> {
        if self.format != Self::FORMAT || self.version != Self::VERSION {
            return Err(ManifestError::Format {
                format: self.format.escape_default().to_string(),
                version: self.version,
            });
        }
        check_plain_name("capture id", &self.id)?;
        if let Some(s) = &self.subject {
            // shown on pages, linked, exported to spreadsheets: the API's rule
            check_plain_name("subject", s)?;
        }
        if self.cameras.is_empty() || self.cameras.len() > MAX_CAMERAS {
            return Err(ManifestError::CameraCount(self.cameras.len()));
        }
        let mut ids = std::collections::BTreeSet::new();
        let mut files = std::collections::BTreeSet::new();
        let mut places = std::collections::BTreeSet::new();
        for c in &self.cameras {
            check_plain_name("camera id", &c.id)?;
            check_plain_name(&format!("camera {}'s file", c.id), &c.file)?;
            check_plain_name(&format!("camera {}'s pod", c.id), &c.pod)?;
            check_plain_name(&format!("camera {}'s side", c.id), &c.side)?;
            if !(1..=20_000).contains(&c.width) || !(1..=20_000).contains(&c.height) {
                return Err(ManifestError::ImageSize {
                    camera: c.id.clone(),
                    width: c.width,
                    height: c.height,
                });
            }
            if !ids.insert(&c.id) {
                return Err(ManifestError::TwoIds(c.id.clone()));
            }
            if !files.insert(&c.file) {
                return Err(ManifestError::SharedFile(c.file.clone()));
            }
            if !places.insert((&c.pod, &c.side)) {
                return Err(ManifestError::SamePlace {
                    pod: c.pod.clone(),
                    side: c.side.clone(),
                });
            }
        }
        Ok(())
    }

    /// Parses and checks the bytes of a `manifest.json`.
    pub fn parse(bytes: &[u8]) -> Result<Manifest, ManifestError> {
        let m: Manifest =
            serde_json::from_slice(bytes).map_err(|e| ManifestError::Json(e.to_string()))?;
        m.check()?;
        Ok(m)
    }

    /// Reads and checks a set's manifest (see [`CaptureSetDir::open`]).
    pub fn read(dir: &Path) -> Result<Manifest, CaptureSetError> {
        CaptureSetDir::open(dir).map(|s| s.manifest)
    }
}

/// UTC time as `YYYYMMDDTHHMMSS.mmmZ` (sortable, safe in file names).
pub fn utc_stamp(t: SystemTime) -> String {
    let d = t.duration_since(UNIX_EPOCH).unwrap_or_default();
    let secs = d.as_secs() as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // civil date from days since 1970-01-01 (H. Hinnant's algorithm)
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + if month <= 2 { 1 } else { 0 };
    format!(
        "{year:04}{month:02}{day:02}T{:02}{:02}{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        d.subsec_millis()
    )
}

/// What is wrong in a manifest that serde cannot see, or why it is not JSON of one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ManifestError {
    #[error("{0}")]
    Json(String),
    #[error(
        "format '{format}' version {version} is not {} {}",
        Manifest::FORMAT,
        Manifest::VERSION
    )]
    Format { format: String, version: u32 },
    #[error(transparent)]
    Name(#[from] crate::paths::NameError),
    #[error("lists {0} cameras (1 to {MAX_CAMERAS})")]
    CameraCount(usize),
    #[error("camera {camera}: {width}x{height} is not an image size")]
    ImageSize {
        camera: String,
        width: u32,
        height: u32,
    },
    #[error("two cameras have the id '{0}'")]
    TwoIds(String),
    #[error("two cameras share the file '{0}'")]
    SharedFile(String),
    #[error("two cameras are the {side} camera of pod {pod}")]
    SamePlace { pod: String, side: String },
}

/// Why a capture set could not be read or written. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum CaptureSetError {
    #[error("{dir}: no manifest.json, so this is not a complete capture set")]
    NoManifest { dir: String },
    #[error("{path}: not a valid capture manifest: {msg}")]
    Manifest { path: String, msg: String },
    #[error("{dir}: no {side} camera of pod {pod} in the manifest")]
    MissingCamera {
        dir: String,
        pod: String,
        side: String,
    },
    #[error("camera {camera}: {path}: {msg}")]
    Image {
        camera: String,
        path: String,
        msg: String,
    },
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
}

impl CaptureSetError {
    /// The file the error is about.
    pub fn path(&self) -> &str {
        match self {
            CaptureSetError::NoManifest { dir } | CaptureSetError::MissingCamera { dir, .. } => dir,
            CaptureSetError::Manifest { path, .. }
            | CaptureSetError::Image { path, .. }
            | CaptureSetError::Io { path, .. } => path,
        }
    }

    /// True when the set itself is at fault (processing it again cannot help); false when
    /// the machine is (a read or write that failed may succeed later).
    pub fn is_permanent(&self) -> bool {
        !matches!(self, CaptureSetError::Io { .. })
    }
}

fn io_err(path: &Path) -> impl Fn(std::io::Error) -> CaptureSetError + '_ {
    move |source| CaptureSetError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// A capture set on disk whose manifest has been read and checked.
#[derive(Debug, Clone)]
pub struct CaptureSetDir {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

impl CaptureSetDir {
    /// Opens the set in `dir`: reads `manifest.json` (a regular file of at most 1 MiB) and
    /// checks it ([`Manifest::check`]). A missing manifest means an incomplete set.
    pub fn open(dir: &Path) -> Result<CaptureSetDir, CaptureSetError> {
        let p = dir.join("manifest.json");
        let bad = |msg: String| CaptureSetError::Manifest {
            path: p.display().to_string(),
            msg,
        };
        if !dir.is_dir() {
            return Err(CaptureSetError::NoManifest {
                dir: format!("{} (not a folder)", dir.display()),
            });
        }
        match std::fs::symlink_metadata(&p) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(CaptureSetError::NoManifest {
                    dir: dir.display().to_string(),
                });
            }
            Err(e) => return Err(io_err(&p)(e)),
            Ok(m) if !m.is_file() => return Err(bad("not a regular file".into())),
            Ok(_) => {}
        }
        let bytes = read_regular(&p, MAX_MANIFEST_BYTES).map_err(|e| match e {
            ReadError::Io(source) => io_err(&p)(source),
            ReadError::Refused(msg) => bad(msg),
        })?;
        let manifest = Manifest::parse(&bytes).map_err(|e| bad(e.to_string()))?;
        Ok(CaptureSetDir {
            dir: dir.to_path_buf(),
            manifest,
        })
    }

    /// The set's id (its folder's name as the manifest gives it).
    pub fn id(&self) -> &str {
        &self.manifest.id
    }

    /// The record of pod `pod`'s `side` camera.
    pub fn camera(&self, pod: &str, side: &str) -> Result<&CameraRecord, CaptureSetError> {
        self.manifest
            .cameras
            .iter()
            .find(|c| c.pod == pod && c.side == side)
            .ok_or_else(|| CaptureSetError::MissingCamera {
                dir: self.dir.display().to_string(),
                pod: pod.into(),
                side: side.into(),
            })
    }

    /// Refuses two cameras whose files are one file on disk (one a link to the other, or
    /// hard-linked): the manifest's check sees only the names, and a pod would compare an
    /// image with itself.
    pub fn check_distinct_files(&self) -> Result<(), CaptureSetError> {
        use std::os::unix::fs::MetadataExt;
        let mut seen: std::collections::HashMap<(u64, u64), &str> = Default::default();
        for c in &self.manifest.cameras {
            let path = self.dir.join(&c.file);
            // a missing or unreadable file is named when its image is read
            let Ok(m) = std::fs::metadata(&path) else {
                continue;
            };
            if let Some(other) = seen.insert((m.dev(), m.ino()), &c.id) {
                return Err(CaptureSetError::Image {
                    camera: c.id.clone(),
                    path: path.display().to_string(),
                    msg: format!(
                        "the file is camera {other}'s image too (a link to it); every camera needs its own"
                    ),
                });
            }
        }
        Ok(())
    }

    /// Reads pod `pod`'s `side` camera image as 8-bit grey, checked against the size the
    /// manifest gives and against `expected` (the calibration's). The file must be a
    /// regular file inside the set: a symbolic link out of it is refused.
    pub fn grey_image(
        &self,
        pod: &str,
        side: &str,
        expected: (u32, u32),
    ) -> Result<image::GrayImage, CaptureSetError> {
        let cam = self.camera(pod, side)?;
        let path = self.dir.join(&cam.file);
        let fail = |msg: String| CaptureSetError::Image {
            camera: cam.id.clone(),
            path: path.display().to_string(),
            msg,
        };
        let inside = match (path.canonicalize(), self.dir.canonicalize()) {
            (Ok(file), Ok(dir)) => file.starts_with(&dir),
            (Err(e), _) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(fail("the image file is missing".into()));
            }
            (Err(e), _) | (_, Err(e)) => return Err(io_err(&path)(e)),
        };
        if !inside {
            return Err(fail("the file links outside the capture set".into()));
        }
        let bytes = read_regular(&path, crate::files::MAX_IMAGE_BYTES).map_err(|e| match e {
            ReadError::Io(source) => io_err(&path)(source),
            ReadError::Refused(msg) => fail(msg),
        })?;
        let img = image::load_from_memory(&bytes)
            .map_err(|e| fail(format!("not a readable image: {e}")))?
            .to_luma8();
        let got = img.dimensions();
        if got != (cam.width, cam.height) {
            return Err(fail(format!(
                "the image is {}x{}, the manifest says {}x{}",
                got.0, got.1, cam.width, cam.height
            )));
        }
        if got != expected {
            return Err(fail(format!(
                "the image is {}x{}, the calibration is for {}x{}",
                got.0, got.1, expected.0, expected.1
            )));
        }
        Ok(img)
    }
}

/// A regular file of at most `max` bytes ([`crate::files::read_limited`]): an I/O
/// failure is the machine's, a refusal (not a regular file, too large) the set's.
fn read_regular(path: &Path, max: u64) -> Result<Vec<u8>, ReadError> {
    use crate::mesh::FileError;
    crate::files::read_limited(path, max).map_err(|e| match e {
        FileError::Io { source, .. } => ReadError::Io(source),
        FileError::Content { msg, .. } | FileError::Line { msg, .. } => ReadError::Refused(msg),
        other => ReadError::Refused(other.to_string()),
    })
}

enum ReadError {
    Io(std::io::Error),
    Refused(String),
}

/// Writes a capture set under `root` as `root/<manifest.id>/`: into `root/.<id>.partial/`
/// first, every file synced, `manifest.json` last, then the folder renamed into place and
/// `root` synced, so a reader (or a crash) never sees half a set. `files` are (name,
/// bytes), plain names. On failure the partial folder is removed. Returns the set's folder.
pub fn write_capture_set(
    root: &Path,
    manifest: &Manifest,
    files: &[(String, Vec<u8>)],
) -> Result<PathBuf, CaptureSetError> {
    let bad = |msg: String| CaptureSetError::Manifest {
        path: root.join(&manifest.id).display().to_string(),
        msg,
    };
    manifest.check().map_err(|e| bad(e.to_string()))?;
    for (name, _) in files {
        check_plain_name("file", name).map_err(|e| bad(e.to_string()))?;
    }
    let partial = root.join(format!(".{}.partial", manifest.id));
    let dir = root.join(&manifest.id);
    let taken = |p: &Path| CaptureSetError::Io {
        path: p.display().to_string(),
        source: std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            "another writer has a set of this id",
        ),
    };
    if dir.exists() {
        return Err(taken(&dir));
    }
    std::fs::create_dir_all(root).map_err(io_err(root))?;
    // created, not reused: a second writer of this id fails here instead of mixing its
    // images into ours (and never removes ours on its way out)
    match std::fs::create_dir(&partial) {
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => return Err(taken(&partial)),
        r => r.map_err(io_err(&partial))?,
    }
    let result = (|| {
        for (name, bytes) in files {
            let p = partial.join(name);
            write_synced(&p, bytes).map_err(io_err(&p))?;
        }
        // the manifest last: a set without one is incomplete
        let json = serde_json::to_vec_pretty(manifest).expect("a manifest serialises");
        let mp = partial.join("manifest.json");
        write_synced(&mp, &json).map_err(io_err(&mp))?;
        sync_dir(&partial);
        match rename_no_replace(&partial, &dir) {
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => return Err(taken(&dir)),
            r => r.map_err(io_err(&dir))?,
        }
        sync_dir(root);
        Ok(dir.clone())
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&partial);
    }
    result
}

/// Whether a write failed only because the id was taken (another writer's set), so the
/// writer may try again under a new id.
pub fn id_taken(e: &CaptureSetError) -> bool {
    matches!(e, CaptureSetError::Io { source, .. } if source.kind() == std::io::ErrorKind::AlreadyExists)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn utc_stamps_are_civil_dates() {
        let t = UNIX_EPOCH + Duration::from_millis(1_795_313_106_789); // 2026-11-22T02:05:06.789Z
        assert_eq!(utc_stamp(t), "20261122T020506.789Z");
        assert_eq!(
            utc_stamp(UNIX_EPOCH + Duration::from_secs(951_782_400)),
            "20000229T000000.000Z"
        );
    }
}
