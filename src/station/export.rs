//! The results folder as a table: one CSV row per result (capture, subject, station,
//! fit figures, measurements raw and posture-free, weight), for `conformd export` and
//! the daemon's `GET /api/export.csv`; and per subject, how well each measurement
//! repeats over its results (`export --repeatability`, the subject's page).

use crate::measure::{Measurement, Spread, spread};
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
        subjects: subject_spreads(&rows),
        skipped,
        rejected,
    })
}

/// How well one subject's measurements repeat over its results: each one's mean, SD and
/// CV, raw and posture-free.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SubjectSpread {
    pub subject: String,
    /// results the figures are over
    pub results: usize,
    pub raw: Vec<Spread>,
    /// empty when no result was measured posture-free
    pub posture_free: Vec<Spread>,
}

/// [`SubjectSpread`] of every subject with two results or more among `reports` (result
/// reports, `report.json`), subjects in first-seen order. A report's measurements that
/// do not read as measurements are left out of its subject's figures.
pub fn subject_spreads(reports: &[serde_json::Value]) -> Vec<SubjectSpread> {
    let mut subjects: Vec<(&str, Vec<&serde_json::Value>)> = Vec::new();
    for r in reports {
        let Some(s) = r.get("subject").and_then(|s| s.as_str()) else {
            continue;
        };
        match subjects.iter_mut().find(|(n, _)| *n == s) {
            Some((_, rs)) => rs.push(r),
            None => subjects.push((s, vec![r])),
        }
    }
    let measured = |r: &serde_json::Value, key: &str| -> Option<Vec<Measurement>> {
        serde_json::from_value(r.get(key)?.clone()).ok()
    };
    subjects
        .into_iter()
        .filter(|(_, rs)| rs.len() >= 2)
        .map(|(subject, rs)| {
            let raw: Vec<Vec<Measurement>> = rs
                .iter()
                .filter_map(|r| measured(r, "measurements"))
                .collect();
            let free: Vec<Vec<Measurement>> = rs
                .iter()
                .filter_map(|r| measured(r, "measurements_normalised"))
                .collect();
            SubjectSpread {
                subject: subject.to_string(),
                results: rs.len(),
                raw: spread(&raw),
                posture_free: spread(&free),
            }
        })
        .collect()
}

/// [`SubjectSpread`]s as CSV: one row per subject and measurement, raw and posture-free
/// figures side by side (empty where a measurement has no posture-free value).
pub fn spreads_csv(subjects: &[SubjectSpread]) -> String {
    let mut s = String::from(
        "subject,measurement,unit,results,mean,sd,cv,mean_posture_free,sd_posture_free,cv_posture_free\n",
    );
    for sub in subjects {
        for r in &sub.raw {
            let free = sub.posture_free.iter().find(|p| p.name == r.name);
            let f = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.6}"));
            s += &format!(
                "{},{},{},{},{:.6},{:.6},{:.6},{},{},{}\n",
                csv_field(&sub.subject),
                csv_field(&r.name),
                csv_field(&r.unit),
                r.count,
                r.mean,
                r.sd,
                r.cv,
                f(free.map(|p| p.mean)),
                f(free.map(|p| p.sd)),
                f(free.map(|p| p.cv)),
            );
        }
    }
    s
}

/// [`export_csv`]'s table, its subjects' repeatability and the result folders it left
/// out.
pub struct Export {
    pub csv: String,
    /// every subject with two results or more (rejected ones left out)
    pub subjects: Vec<SubjectSpread>,
    /// (report file, why it was left out)
    pub skipped: Vec<(String, String)>,
    /// result folders an operator rejected (`review.json`), left out
    pub rejected: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subjects_with_two_results_or_more_get_their_spread() {
        let report = |subject: &str, girth: f64, free: Option<f64>| {
            let m = |v: f64| serde_json::json!([{"name": "girth", "kind": "girth", "value": v, "unit": "m"}]);
            let mut r =
                serde_json::json!({"capture": "c", "subject": subject, "measurements": m(girth)});
            if let Some(f) = free {
                r["measurements_normalised"] = m(f);
            }
            r
        };
        let reports = [
            report("a", 1.0, Some(1.1)),
            report("b", 5.0, None),
            report("a", 1.2, Some(1.1)),
            serde_json::json!({"capture": "d", "measurements": []}),
            report("a", 1.4, None),
        ];
        let s = subject_spreads(&reports);
        assert_eq!(s.len(), 1, "b has one result, d none: {s:?}");
        assert_eq!((s[0].subject.as_str(), s[0].results), ("a", 3));
        let raw = &s[0].raw[0];
        assert!((raw.mean - 1.2).abs() < 1e-12 && (raw.sd - 0.2).abs() < 1e-12);
        assert!((raw.cv - 0.2 / 1.2).abs() < 1e-12);
        // posture-free over the two results measured so
        assert_eq!(s[0].posture_free[0].count, 2);
        assert_eq!(s[0].posture_free[0].sd, 0.0);
        let csv = spreads_csv(&s);
        assert_eq!(csv.lines().count(), 2, "{csv}");
        assert!(
            csv.lines()
                .nth(1)
                .unwrap()
                .starts_with("a,girth,m,3,1.200000,0.200000,0.166667,1.100000,0.000000,0.000000"),
            "{csv}"
        );
    }
}
