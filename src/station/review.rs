//! An operator's verdict on one result: accepted, or rejected with a reason. It is kept
//! beside the result it judges (`results/<id>/review.json`), so a reprocessed capture's
//! new result starts unreviewed, and whatever reads the results folder (the export, the
//! weight fit, the daemon's model rebuild) leaves a rejected result out.

use crate::files::DataDir;
use std::path::Path;

pub const REVIEW_FILE: &str = "review.json";

/// Longest reason kept (a sentence or two, not a document).
pub const MAX_REASON_CHARS: usize = 500;

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    Accepted,
    Rejected,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Review {
    pub verdict: Verdict,
    /// why (required for a rejection)
    #[serde(default)]
    pub reason: Option<String>,
    /// when it was given, Unix seconds
    pub at: f64,
}

/// A verdict refused, or a review file that cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum ReviewError {
    #[error("the reason has {0} characters; at most {MAX_REASON_CHARS}")]
    TooLong(usize),
    #[error(transparent)]
    Reason(#[from] crate::paths::NameError),
    #[error("a rejection needs a reason (what is wrong with the result)")]
    NoReason,
    #[error(transparent)]
    Read(#[from] crate::files::FileError),
    #[error("{path}: not a review: {msg}")]
    NotAReview { path: String, msg: String },
}

impl Review {
    /// A verdict as given: a rejection must say why; a reason is one line of at most
    /// [`MAX_REASON_CHARS`] characters.
    pub fn new(verdict: Verdict, reason: Option<String>, at: f64) -> Result<Review, ReviewError> {
        let reason = reason
            .map(|r| r.trim().to_string())
            .filter(|r| !r.is_empty());
        if let Some(r) = &reason {
            if r.chars().count() > MAX_REASON_CHARS {
                return Err(ReviewError::TooLong(r.chars().count()));
            }
            crate::paths::check_one_line("the reason", r)?;
        }
        if verdict == Verdict::Rejected && reason.is_none() {
            return Err(ReviewError::NoReason);
        }
        Ok(Review {
            verdict,
            reason,
            at,
        })
    }
}

/// The review of the result in `dir`, None when it has none.
pub fn read(dir: &Path) -> Result<Option<Review>, ReviewError> {
    read_in(&DataDir::open(dir, dir)?)
}

/// [`read`] in a result folder opened without following links (a `review.json` that is
/// a link is refused, not followed).
pub fn read_in(dir: &DataDir) -> Result<Option<Review>, ReviewError> {
    if !dir.has(REVIEW_FILE) {
        return Ok(None);
    }
    let bytes = dir.read(REVIEW_FILE, crate::files::MAX_REPORT_BYTES)?;
    serde_json::from_slice(&bytes)
        .map(Some)
        .map_err(|e| ReviewError::NotAReview {
            path: dir.path().join(REVIEW_FILE).display().to_string(),
            msg: e.to_string(),
        })
}

/// Writes the review of the result in `dir` (see [`write_in`]).
pub fn write(dir: &Path, review: &Review) -> Result<(), crate::files::FileError> {
    write_in(&DataDir::open(dir, dir)?, review)
}

/// Writes the review of the result in `dir` (atomically, replacing an older one), one
/// writer at a time: two verdicts given at once each land whole, the later one stays.
pub fn write_in(dir: &DataDir, review: &Review) -> Result<(), crate::files::FileError> {
    let json = serde_json::to_vec_pretty(review).expect("a review serialises");
    let _one_writer = dir.lock()?;
    dir.write_atomic(REVIEW_FILE, &json)
}

/// Whether the result in `dir` is to be left out of exports, models and fits: it was
/// rejected. A review that cannot be read is an error, which callers take as rejected (an
/// operator meant something, and a result is easier to put back than to take out of a
/// model already built) and name.
pub fn left_out(dir: &Path) -> Result<bool, ReviewError> {
    read(dir).map(|r| r.is_some_and(|r| r.verdict == Verdict::Rejected))
}

/// [`left_out`] in a result folder opened without following links.
pub fn left_out_in(dir: &DataDir) -> Result<bool, ReviewError> {
    read_in(dir).map(|r| r.is_some_and(|r| r.verdict == Verdict::Rejected))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::NameError;

    #[test]
    fn a_rejection_needs_a_reason_and_reasons_are_one_short_line() {
        assert!(Review::new(Verdict::Rejected, None, 0.0).is_err());
        assert!(Review::new(Verdict::Rejected, Some("  ".into()), 0.0).is_err());
        assert!(Review::new(Verdict::Rejected, Some("a\nb".into()), 0.0).is_err());
        for sneaky in [
            "a\u{2028}b",
            "a\u{2029}b",
            "paid \u{202e}0001\u{202c}",
            "x\u{2066}y",
        ] {
            let e = Review::new(Verdict::Rejected, Some(sneaky.into()), 0.0).unwrap_err();
            assert!(
                matches!(e, ReviewError::Reason(NameError::NotOneLine { .. })),
                "{e}"
            );
            assert!(e.to_string().contains("one line"), "{e}");
        }
        assert!(Review::new(Verdict::Accepted, Some("x".repeat(501)), 0.0).is_err());
        let r = Review::new(Verdict::Accepted, None, 1.0).unwrap();
        assert_eq!(r.reason, None);
        let d = tempfile::tempdir().unwrap();
        assert!(matches!(left_out(d.path()), Ok(false)));
        let r = Review::new(Verdict::Rejected, Some(" legs swapped ".into()), 2.0).unwrap();
        write(d.path(), &r).unwrap();
        assert_eq!(
            read(d.path()).unwrap().unwrap().reason.as_deref(),
            Some("legs swapped")
        );
        assert!(matches!(left_out(d.path()), Ok(true)));
        std::fs::write(d.path().join(REVIEW_FILE), "{").unwrap();
        assert!(matches!(
            left_out(d.path()),
            Err(ReviewError::NotAReview { .. })
        ));
    }
}
