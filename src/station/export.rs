//! The results folder as a table: one CSV row per result (capture, subject, station,
//! fit figures, measurements raw and posture-free, weight), for `conformd export` and
//! the daemon's `GET /api/export.csv`.

use std::path::Path;

/// A CSV text field, quoted when it holds a comma, quote or line break; one that starts
/// like a formula (`=`, `+`, `-`, `@`, a tab) gets a leading `'`, so a spreadsheet shows
/// it rather than runs it.
pub fn csv_field(s: &str) -> String {
    let s = &if s.starts_with(['=', '+', '-', '@', '\t', '\r']) {
        format!("'{s}")
    } else {
        s.to_string()
    };
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// One CSV row per result folder under `results`: capture, subject, station,
/// the fit's distance and distortion, every measurement (raw and posture-free) and the
/// weight. A folder whose report cannot be read, is not JSON or names no capture is left
/// out and listed in [`Export::skipped`] with the reason; a rejected result is left out
/// and listed in [`Export::rejected`].
pub fn export_csv(results: &Path) -> std::io::Result<Export> {
    let entries = std::fs::read_dir(results)?;
    let mut dirs: Vec<_> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.join("report.json").is_file()
                && !p
                    .file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with('.'))
        })
        .collect();
    dirs.sort();
    let mut rows: Vec<serde_json::Value> = Vec::new();
    let mut skipped = Vec::new();
    let mut rejected = Vec::new();
    for d in dirs {
        let file = d.join("report.json");
        let read = crate::files::read_text_limited(&file, crate::files::MAX_REPORT_BYTES)
            .map_err(|e| e.to_string())
            .and_then(|text| {
                serde_json::from_str::<serde_json::Value>(&text)
                    .map_err(|e| format!("not JSON: {e}"))
            })
            .and_then(|v| match v.get("capture") {
                Some(serde_json::Value::String(_)) => Ok(v),
                _ => Err("not a result report (no capture id)".into()),
            });
        match (super::review::left_out(&d), read) {
            (Ok(true), _) => rejected.push(d.display().to_string()),
            (Err(why), _) => skipped.push((
                d.join(super::review::REVIEW_FILE).display().to_string(),
                format!("{why} (left out as if rejected)"),
            )),
            (Ok(false), Ok(v)) => rows.push(v),
            (Ok(false), Err(why)) => skipped.push((file.display().to_string(), why)),
        }
    }
    // the columns: every measurement name any result has, in first-seen order
    let mut names: Vec<String> = Vec::new();
    for r in &rows {
        if let Some(ms) = r.get("measurements").and_then(|m| m.as_array()) {
            for m in ms {
                if let Some(n) = m.get("name").and_then(|n| n.as_str())
                    && !names.iter().any(|x| x == n)
                {
                    names.push(n.to_string());
                }
            }
        }
    }
    let mut header = vec![
        "capture",
        "subject",
        "station",
        "mean_distance_relative",
        "edge_length_std",
    ]
    .into_iter()
    .map(String::from)
    .collect::<Vec<_>>();
    header.extend(names.iter().cloned());
    header.extend(names.iter().map(|n| format!("{n}_normalised")));
    header.extend(["weight_kg", "weight_low", "weight_high"].map(String::from));
    let mut s = header.join(",") + "\n";
    let text = |v: Option<&serde_json::Value>| -> String {
        match v {
            Some(serde_json::Value::String(s)) => csv_field(s),
            Some(serde_json::Value::Number(n)) => n.to_string(),
            _ => String::new(),
        }
    };
    let value_of = |r: &serde_json::Value, key: &str, name: &str| -> String {
        r.get(key)
            .and_then(|m| m.as_array())
            .and_then(|ms| {
                ms.iter()
                    .find(|m| m.get("name").and_then(|n| n.as_str()) == Some(name))
            })
            .map(|m| text(m.get("value")))
            .unwrap_or_default()
    };
    for r in &rows {
        let c = r.get("conformation");
        let mut row = vec![
            text(r.get("capture")),
            text(r.get("subject")),
            text(r.get("station")),
            text(c.and_then(|c| c.get("mean_distance_relative"))),
            text(
                c.and_then(|c| c.get("final_variation"))
                    .and_then(|v| v.get("edge_length"))
                    .and_then(|e| e.get("std")),
            ),
        ];
        row.extend(names.iter().map(|n| value_of(r, "measurements", n)));
        row.extend(
            names
                .iter()
                .map(|n| value_of(r, "measurements_normalised", n)),
        );
        let w = r.get("weight");
        row.extend(["kg", "low", "high"].map(|k| text(w.and_then(|w| w.get(k)))));
        s += &(row.join(",") + "\n");
    }
    Ok(Export {
        csv: s,
        skipped,
        rejected,
    })
}

/// [`export_csv`]'s table and the result folders it left out.
pub struct Export {
    pub csv: String,
    /// (report file, why it was left out)
    pub skipped: Vec<(String, String)>,
    /// result folders an operator rejected (`review.json`), left out
    pub rejected: Vec<String>,
}
