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
) -> Result<Vec<Landmark>, String> {
    if placed.len() < MIN_PLACED {
        return Err(format!(
            "{} landmark(s) placed; the fit needs at least {MIN_PLACED} that are not all in one plane",
            placed.len()
        ));
    }
    let (lo, hi) = scan.bounding_box().ok_or("the scan has no points")?;
    let diag = (hi - lo).norm();
    let grow = V3::repeat(0.05 * diag);
    let mut out: Vec<Landmark> = Vec::with_capacity(placed.len());
    for p in placed {
        if !names.contains(&p.name) {
            let mut known: Vec<&str> = names.iter().map(String::as_str).collect();
            known.truncate(40);
            return Err(format!(
                "'{}' is not one of the template's landmarks ({})",
                p.name,
                known.join(", ")
            ));
        }
        if out.iter().any(|l| l.name == p.name) {
            return Err(format!("'{}' is placed twice", p.name));
        }
        if !p.position.iter().all(|c| c.is_finite()) {
            return Err(format!("'{}' has a non-finite coordinate", p.name));
        }
        let q = V3::from(p.position);
        if (0..3).any(|k| q[k] < lo[k] - grow[k] || q[k] > hi[k] + grow[k]) {
            return Err(format!(
                "'{}' at ({:.4}, {:.4}, {:.4}) is off the scan (its box is ({:.4}, {:.4}, {:.4}) to ({:.4}, {:.4}, {:.4}))",
                p.name, q.x, q.y, q.z, lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
            ));
        }
        if let Some(same) = out.iter().find(|l| match l.pos {
            LandmarkPos::Point(o) => (o - q).norm() < 1e-6 * diag,
            LandmarkPos::Vertex(_) => false,
        }) {
            return Err(format!(
                "'{}' and '{}' are at the same place",
                same.name, p.name
            ));
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
        return Err(
            "the landmarks all lie in one plane (or on a line): place one off that plane".into(),
        );
    }
    Ok(out)
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
        assert!(err(&good[..3]).contains("at least 4"));
        let mut bad = good.clone();
        bad[3].name = "snout".into();
        assert!(err(&bad).contains("'snout' is not one of"));
        bad[3].name = "a".into();
        assert!(err(&bad).contains("placed twice"));
        bad = good.clone();
        bad[2].position[1] = f64::NAN;
        assert!(err(&bad).contains("non-finite"));
        bad[2].position[1] = 5.0;
        assert!(err(&bad).contains("off the scan"));
        bad = good.clone();
        bad[3].position = [1.0, 1.0, 0.0];
        assert!(err(&bad).contains("one plane"));
        bad[3] = at("d", [0.0, 0.0, 0.0]);
        assert!(err(&bad).contains("same place"));
        let t = text(&lms, "c-1");
        let back = crate::mesh::landmarks::parse_text("t", t.as_bytes()).unwrap();
        assert_eq!(back, lms);
    }
}
