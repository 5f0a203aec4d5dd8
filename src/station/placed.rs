//! Scan landmarks an operator placed on a result's scan (the capture page, or
//! `POST /api/captures/{id}/landmarks`): checked against the template's landmark names and
//! the scan they were placed on before a job is queued with them, so a wrong set is
//! refused with its reason at once instead of failing the job later. Kept as a landmark
//! text file (`name x y z`), which `conformd process --landmarks` and `conform` read.

use super::pipeline::PlacedLandmark;
use crate::mesh::{Landmark, LandmarkPos, Mesh, V3};

/// Fewest landmarks the global mapping can use (four not in one plane).
pub const MIN_PLACED: usize = 4;

/// Checks placed landmarks: at least [`MIN_PLACED`], each a name of the template's
/// (`names`) given once, finite, on or near the scan (inside its bounding box grown by
/// 5% of its diagonal), no two at one place and not all in one plane.
pub fn check(
    placed: &[PlacedLandmark],
    names: &[String],
    scan: &Mesh,
) -> Result<Vec<Landmark>, PlacedError> {
    if placed.len() < MIN_PLACED {
        return Err(PlacedError::TooFew(placed.len()));
    }
    let (lo, hi) = scan.bounding_box().ok_or(PlacedError::EmptyScan)?;
    let diag = (hi - lo).norm();
    let grow = V3::repeat(0.05 * diag);
    let mut out: Vec<Landmark> = Vec::with_capacity(placed.len());
    for p in placed {
        if !names.contains(&p.name) {
            let mut known: Vec<&str> = names.iter().map(String::as_str).collect();
            known.truncate(40);
            return Err(PlacedError::UnknownName {
                name: p.name.clone(),
                known: known.join(", "),
            });
        }
        if out.iter().any(|l| l.name == p.name) {
            return Err(PlacedError::Twice(p.name.clone()));
        }
        if !p.position.iter().all(|c| c.is_finite()) {
            return Err(PlacedError::NonFinite(p.name.clone()));
        }
        let q = V3::from(p.position);
        if (0..3).any(|k| q[k] < lo[k] - grow[k] || q[k] > hi[k] + grow[k]) {
            return Err(PlacedError::OffScan {
                name: p.name.clone(),
                at: q.into(),
                low: lo.into(),
                high: hi.into(),
            });
        }
        if let Some(same) = out.iter().find(|l| match l.pos {
            LandmarkPos::Point(o) => (o - q).norm() < 1e-6 * diag,
            LandmarkPos::Vertex(_) => false,
        }) {
            return Err(PlacedError::SamePlace(same.name.clone(), p.name.clone()));
        }
        out.push(Landmark {
            name: p.name.clone(),
            pos: LandmarkPos::Point(q),
        });
    }
    // flat: the smallest spread across the set's best plane against the largest along it
    let pts: Vec<V3> = placed.iter().map(|p| V3::from(p.position)).collect();
    let mean = pts.iter().fold(V3::zeros(), |a, p| a + p) / pts.len() as f64;
    let cov = pts.iter().fold(nalgebra::Matrix3::zeros(), |a, p| {
        let d = p - mean;
        a + d * d.transpose()
    });
    let eig = cov.symmetric_eigenvalues();
    let (min, max) = (eig.min().max(0.0), eig.max());
    if max <= 0.0 || (min / max).sqrt() < 1e-3 {
        return Err(PlacedError::Flat);
    }
    Ok(out)
}

/// Why a set of placed landmarks is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlacedError {
    #[error(
        "{0} landmark(s) placed; the fit needs at least {MIN_PLACED} that are not all in one plane"
    )]
    TooFew(usize),
    #[error("the scan has no points")]
    EmptyScan,
    #[error("'{name}' is not one of the template's landmarks ({known})")]
    UnknownName { name: String, known: String },
    #[error("'{0}' is placed twice")]
    Twice(String),
    #[error("'{0}' has a non-finite coordinate")]
    NonFinite(String),
    #[error(
        "'{name}' at ({:.4}, {:.4}, {:.4}) is off the scan (its box is ({:.4}, {:.4}, {:.4}) to ({:.4}, {:.4}, {:.4}))",
        at[0], at[1], at[2], low[0], low[1], low[2], high[0], high[1], high[2]
    )]
    OffScan {
        name: String,
        at: [f64; 3],
        low: [f64; 3],
        high: [f64; 3],
    },
    #[error("'{0}' and '{1}' are at the same place")]
    SamePlace(String, String),
    #[error("the landmarks all lie in one plane (or on a line): place one off that plane")]
    Flat,
}

/// The landmark file of an operator's landmarks, with a line saying where they came from.
pub fn text(landmarks: &[Landmark], capture: &str) -> String {
    format!(
        "# scan landmarks placed by an operator on capture {capture}'s scan (conformd)\n{}",
        crate::mesh::landmarks::landmarks_text(landmarks)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(name: &str, p: [f64; 3]) -> PlacedLandmark {
        PlacedLandmark {
            name: name.into(),
            position: p,
        }
    }

    #[test]
    fn placed_landmarks_are_checked_before_a_job_is_queued() {
        let scan = Mesh {
            vertices: vec![V3::zeros(), V3::new(1.0, 1.0, 1.0)],
            ..Default::default()
        };
        let names: Vec<String> = ["a", "b", "c", "d", "e"].map(String::from).into();
        let good = [
            at("a", [0.0, 0.0, 0.0]),
            at("b", [1.0, 0.0, 0.0]),
            at("c", [0.0, 1.0, 0.0]),
            at("d", [0.0, 0.0, 1.0]),
        ];
        let lms = check(&good, &names, &scan).unwrap();
        assert_eq!(lms.len(), 4);
        let err = |placed: &[PlacedLandmark]| check(placed, &names, &scan).unwrap_err();
        assert_eq!(err(&good[..3]), PlacedError::TooFew(3));
        assert!(err(&good[..3]).to_string().contains("at least 4"));
        let mut bad = good.clone();
        bad[3].name = "snout".into();
        assert!(matches!(err(&bad), PlacedError::UnknownName { name, .. } if name == "snout"));
        bad[3].name = "a".into();
        assert_eq!(err(&bad), PlacedError::Twice("a".into()));
        bad = good.clone();
        bad[2].position[1] = f64::NAN;
        assert_eq!(err(&bad), PlacedError::NonFinite("c".into()));
        bad[2].position[1] = 5.0;
        assert!(matches!(err(&bad), PlacedError::OffScan { name, .. } if name == "c"));
        bad = good.clone();
        bad[3].position = [1.0, 1.0, 0.0];
        assert_eq!(err(&bad), PlacedError::Flat);
        bad[3] = at("d", [0.0, 0.0, 0.0]);
        assert_eq!(err(&bad), PlacedError::SamePlace("a".into(), "d".into()));
        let t = text(&lms, "c-1");
        let back = crate::mesh::landmarks::parse_text("t", t.as_bytes()).unwrap();
        assert_eq!(back, lms);
    }
}
