//! Names that become paths (capture ids, camera and pod ids, manifest file entries, API
//! ids): one rule for all of them, so no name read from a file or a request can point
//! outside its folder.

use std::path::{Path, PathBuf};

/// Longest name accepted: far beyond any real id, short enough for every file system.
pub const MAX_NAME: usize = 128;

/// A name or a line of text refused; `what` names the thing in the sentence.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    #[error("{what} '{name}' must be 1 to {MAX_NAME} characters long")]
    Length { what: String, name: String },
    /// `name` as shown (escaped)
    #[error(
        "{what} '{name}' is not a plain name (letters, digits, '-', '_' and '.', not starting with '.')"
    )]
    NotPlain { what: String, name: String },
    #[error("{what} must be one line of plain text: it holds U+{code:04X}")]
    NotOneLine { what: String, code: u32 },
}

/// Checks that free text (a review's reason) reads as one line as written: no control
/// character, no line or paragraph separator (U+2028, U+2029) and no bidirectional
/// control (U+061C, U+200E, U+200F, U+202A-U+202E, U+2066-U+2069), which would break a
/// log line or a CSV row, or show other text than is stored.
pub fn check_one_line(what: &str, text: &str) -> Result<(), NameError> {
    let bad = |c: char| {
        c.is_control()
            || matches!(
                c,
                '\u{2028}' | '\u{2029}' | '\u{061c}' | '\u{200e}' | '\u{200f}'
            )
            || ('\u{202a}'..='\u{202e}').contains(&c)
            || ('\u{2066}'..='\u{2069}').contains(&c)
    };
    match text.chars().find(|&c| bad(c)) {
        Some(c) => Err(NameError::NotOneLine {
            what: what.into(),
            code: c as u32,
        }),
        None => Ok(()),
    }
}

/// Checks that `name` is a plain file or folder name: 1 to 128 characters of letters,
/// digits, `-`, `_` and `.`, not starting with a dot (so never `.`, `..`, a hidden file or
/// a partial set). Returns the reason when it is not; `what` names the thing in the
/// sentence (e.g. "camera id").
pub fn check_plain_name(what: &str, name: &str) -> Result<(), NameError> {
    let ok_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.');
    if name.is_empty() || name.len() > MAX_NAME {
        return Err(NameError::Length {
            what: what.into(),
            name: name.into(),
        });
    }
    if name.starts_with('.') || !name.chars().all(ok_char) {
        return Err(NameError::NotPlain {
            what: what.into(),
            name: name.escape_default().to_string(),
        });
    }
    Ok(())
}

/// `dir/name` for a checked plain name.
pub fn join_plain(dir: &Path, what: &str, name: &str) -> Result<PathBuf, NameError> {
    check_plain_name(what, name)?;
    Ok(dir.join(name))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_plain_names_pass() {
        for good in ["pod1", "20261201T101010.000Z-000", "left.png", "a_b-c.9"] {
            assert!(check_plain_name("id", good).is_ok(), "{good}");
        }
        for bad in [
            "",
            ".",
            "..",
            "../x",
            "a/b",
            "/etc/passwd",
            ".hidden",
            "a\\b",
            "a b",
            "é",
            "a\0b",
        ] {
            assert!(check_plain_name("id", bad).is_err(), "{bad:?}");
        }
        assert!(check_plain_name("id", &"x".repeat(MAX_NAME + 1)).is_err());
    }
}
