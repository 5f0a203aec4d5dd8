//! Names that become paths (capture ids, camera and pod ids, manifest file entries, API
//! ids): one rule for all of them, so no name read from a file or a request can point
//! outside its folder.

use std::path::{Path, PathBuf};

/// Longest name accepted: far beyond any real id, short enough for every file system.
pub const MAX_NAME: usize = 128;

/// Checks that `name` is a plain file or folder name: 1 to 128 characters of letters,
/// digits, `-`, `_` and `.`, not starting with a dot (so never `.`, `..`, a hidden file or
/// a partial set). Returns the reason when it is not; `what` names the thing in the
/// sentence (e.g. "camera id").
pub fn check_plain_name(what: &str, name: &str) -> Result<(), String> {
    let ok_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.');
    if name.is_empty() || name.len() > MAX_NAME {
        return Err(format!(
            "{what} '{name}' must be 1 to {MAX_NAME} characters long"
        ));
    }
    if name.starts_with('.') || !name.chars().all(ok_char) {
        return Err(format!(
            "{what} '{}' is not a plain name (letters, digits, '-', '_' and '.', not starting with '.')",
            name.escape_default()
        ));
    }
    Ok(())
}

/// `dir/name` for a checked plain name.
pub fn join_plain(dir: &Path, what: &str, name: &str) -> Result<PathBuf, String> {
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
