//! The modules' dependencies as ARCHITECTURE.md's table allows them: every `crate::x`
//! (and, in the binary, `conformd::x`) in `src/` outside test modules is checked against
//! the "may use" column of the module it is written in, and the table itself must point
//! one way (no two modules that may use each other, directly or round a loop).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The table's rows in order: module (`mesh`, `main.rs` as `main`) -> the modules of
/// this crate its "may use" cell names (`everything` for all).
fn table() -> Vec<(String, BTreeSet<String>)> {
    let text = std::fs::read_to_string(Path::new(ROOT).join("ARCHITECTURE.md")).unwrap();
    let section = text
        .split("## Modules")
        .nth(1)
        .expect("ARCHITECTURE.md has a Modules section");
    let section = section.split("\n## ").next().unwrap();
    let mut rows = Vec::new();
    for line in section.lines().filter(|l| l.starts_with("| `")) {
        let cells: Vec<&str> = line.split(" | ").collect();
        let (first, may) = (cells[0], cells[cells.len() - 1]);
        let may: BTreeSet<String> = may
            .trim_end_matches(" |")
            .split(", ")
            .map(|w| {
                // `template (its rig)`: the module's name is the first word
                w.trim()
                    .trim_matches('`')
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == '-')
                    .collect::<String>()
            })
            .collect();
        // `main.rs`, `cli/` share a row
        for name in first.trim_start_matches("| ").split(", ") {
            let name = name.trim_matches('`').trim_end_matches('/');
            let name = name.strip_suffix(".rs").unwrap_or(name);
            rows.push((name.to_string(), may.clone()));
        }
    }
    rows
}

/// Every `.rs` file under `src/` with the module it belongs to (its first folder, or
/// its own stem at the top; `main.rs` is `main`).
fn sources() -> Vec<(String, PathBuf)> {
    let mut out = Vec::new();
    let mut stack = vec![Path::new(ROOT).join("src")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let rel = p.strip_prefix(Path::new(ROOT).join("src")).unwrap();
                let first = rel
                    .components()
                    .next()
                    .unwrap()
                    .as_os_str()
                    .to_string_lossy();
                let module = first.strip_suffix(".rs").unwrap_or(&first).to_string();
                out.push((module, p));
            }
        }
    }
    out.sort();
    out
}

/// The crate's modules a source names, with the line: `crate::x`, `crate::{x, y::z}`,
/// and in the binary `conformd::x`; test modules (`#[cfg(test)]` to the file's end, and
/// files named `tests.rs`) left out.
fn uses(path: &Path, modules: &BTreeSet<String>) -> Vec<(String, usize)> {
    if path.file_name().is_some_and(|n| n == "tests.rs") {
        return Vec::new();
    }
    let text = std::fs::read_to_string(path).unwrap();
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("#[cfg(test)]") {
            break;
        }
        let code = line.split("//").next().unwrap_or("");
        for prefix in ["crate::", "conformd::"] {
            for (at, _) in code.match_indices(prefix) {
                // part of a longer path (`foo_crate::`) is not ours
                if code[..at]
                    .chars()
                    .last()
                    .is_some_and(|c| c.is_alphanumeric() || c == '_')
                {
                    continue;
                }
                let rest = &code[at + prefix.len()..];
                let names: Vec<String> = match rest.strip_prefix('{') {
                    Some(group) => group
                        .split('}')
                        .next()
                        .unwrap_or("")
                        .split(',')
                        .map(|s| s.trim().split("::").next().unwrap_or("").to_string())
                        .collect(),
                    None => vec![
                        rest.chars()
                            .take_while(|c| c.is_alphanumeric() || *c == '_')
                            .collect(),
                    ],
                };
                for name in names {
                    if modules.contains(&name) {
                        out.push((name, n + 1));
                    }
                }
            }
        }
    }
    out
}

#[test]
fn every_module_uses_only_what_the_architecture_table_allows() {
    let rows = table();
    let allowed: BTreeMap<String, BTreeSet<String>> = rows.iter().cloned().collect();
    let modules: BTreeSet<String> = allowed.keys().cloned().collect();
    for must in [
        "mesh", "conform", "station", "daemon", "commands", "devices", "main", "cli",
    ] {
        assert!(
            modules.contains(must),
            "ARCHITECTURE.md's table lost `{must}`"
        );
    }
    let mut wrong = Vec::new();
    let mut checked = 0;
    for (module, path) in sources() {
        let Some(may) = allowed.get(&module) else {
            // lib.rs declares the modules
            assert_eq!(
                module,
                "lib",
                "{} is in no row of the table",
                path.display()
            );
            continue;
        };
        for (used, line) in uses(&path, &modules) {
            checked += 1;
            if used != module && !may.contains(&used) && !may.contains("everything") {
                wrong.push(format!(
                    "{}:{line}: {module} uses {used}",
                    path.strip_prefix(ROOT).unwrap().display()
                ));
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} uses found: the scan is broken"
    );
    assert!(
        wrong.is_empty(),
        "dependencies ARCHITECTURE.md does not allow:\n{}",
        wrong.join("\n")
    );
}

#[test]
fn the_architecture_table_points_one_way() {
    let rows = table();
    let allowed: BTreeMap<String, BTreeSet<String>> = rows.iter().cloned().collect();
    // a module's reach through the table, "everything" meaning every module
    let everything: BTreeSet<String> = allowed.keys().cloned().collect();
    let direct = |m: &str| -> BTreeSet<String> {
        let may = &allowed[m];
        if may.contains("everything") {
            everything.iter().filter(|x| *x != m).cloned().collect()
        } else {
            may.iter()
                .filter(|x| everything.contains(*x))
                .cloned()
                .collect()
        }
    };
    for m in allowed.keys() {
        let mut seen = BTreeSet::new();
        let mut stack: Vec<String> = direct(m).into_iter().collect();
        while let Some(x) = stack.pop() {
            assert_ne!(&x, m, "{m} can reach itself through the table");
            if seen.insert(x.clone()) {
                stack.extend(direct(&x));
            }
        }
    }
}

/// Every fallible function in `src/` (and in the development set's crate) says why it failed with a typed error (a
/// `thiserror` enum or struct per module), never a bare sentence: a caller can then
/// match on the reason, and the CLI and the API still print it as one sentence.
#[test]
fn no_function_returns_a_sentence_as_its_error() {
    let mut found = Vec::new();
    let mut files = 0;
    let devset: Vec<PathBuf> = std::fs::read_dir(Path::new(ROOT).join("devset/src"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "rs"))
        .collect();
    assert!(devset.len() >= 4, "the development set's crate has moved");
    for path in sources().into_iter().map(|(_, p)| p).chain(devset) {
        files += 1;
        let text = std::fs::read_to_string(&path).unwrap();
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            let sentence_error = code.contains("type Err = String")
                || code
                    .match_indices("Result<")
                    .any(|(at, _)| result_error_is_string(&code[at + "Result<".len()..]));
            if sentence_error {
                found.push(format!(
                    "{}:{}: {}",
                    path.strip_prefix(ROOT).unwrap().display(),
                    n + 1,
                    line.trim()
                ));
            }
        }
    }
    assert!(files > 50, "only {files} sources found: the scan is broken");
    assert!(
        found.is_empty(),
        "errors that are bare sentences:\n{}",
        found.join("\n")
    );
}

/// Whether the `Result<...>` whose arguments start `args` has `String` as its error:
/// its second argument at the outermost level.
fn result_error_is_string(args: &str) -> bool {
    let mut depth = 0;
    let mut second = None;
    for (i, c) in args.char_indices() {
        match c {
            '<' | '(' | '[' => depth += 1,
            '>' | ')' | ']' if depth > 0 => depth -= 1,
            '>' => {
                return second.is_some_and(|s: usize| args[s..i].trim() == "String");
            }
            ',' if depth == 0 => second = Some(i + 1),
            _ => {}
        }
    }
    false
}

#[test]
fn the_sentence_error_scan_reads_result_types() {
    assert!(result_error_is_string("(), String> {"));
    assert!(result_error_is_string("Vec<(String, u32)>, String>"));
    assert!(!result_error_is_string("String, CaptureRefused>>,"));
    assert!(!result_error_is_string("Vec<String>, JournalError> {"));
    assert!(!result_error_is_string("T> {"));
}
