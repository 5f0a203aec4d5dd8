//! What the capture page's 3D viewer draws beside the scan and the conformed mesh: a
//! result's `view.json`, with each conformed vertex's distance to the scan, the
//! template's landmarks where they landed, and every measurement's lines where it was
//! taken, labelled with its value. Written with the result; older results without it are
//! still shown, without these.

use crate::measure::Drawn;
use crate::mesh::{Landmark, LandmarkPos, Mesh};

/// The file beside a result's [`super::pipeline::RESULT_FILES`] (not one of them: a result
/// written before it existed is still complete).
pub const VIEW_FILE: &str = "view.json";

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct View {
    pub format: String,
    pub version: u32,
    /// the unit of every position and distance (the station works in metres)
    pub unit: String,
    /// per conformed vertex, its distance to the scan's surface; empty when the scan
    /// had no surface to measure against
    pub distance: Vec<f32>,
    pub landmarks: Vec<ViewLandmark>,
    pub measurements: Vec<ViewMeasurement>,
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ViewLandmark {
    pub name: String,
    /// the template vertex it is fixed to (the nearest one for a landmark given as a point)
    pub vertex: u32,
    pub position: [f32; 3],
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ViewMeasurement {
    pub name: String,
    pub kind: String,
    pub value: f64,
    pub unit: String,
    /// polylines where it was taken (none for an area or a volume)
    pub lines: Vec<Vec<[f32; 3]>>,
    /// the lines are loops (girths)
    pub closed: bool,
}

fn f32s(p: &crate::mesh::V3) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}

impl View {
    /// The view of `conformed` (in `template`'s vertex order): `distance` per vertex,
    /// the template's `landmarks` moved with their vertices, `drawn` measurements.
    pub fn new(
        conformed: &Mesh,
        template: &Mesh,
        distance: Option<&[f64]>,
        landmarks: Option<&[Landmark]>,
        drawn: &[Drawn],
    ) -> View {
        let landmarks = landmarks
            .unwrap_or_default()
            .iter()
            .filter_map(|l| {
                let vertex = match l.pos {
                    LandmarkPos::Vertex(i) => i,
                    LandmarkPos::Point(p) => {
                        template
                            .vertices
                            .iter()
                            .enumerate()
                            .min_by(|a, b| (a.1 - p).norm().total_cmp(&(b.1 - p).norm()))?
                            .0 as u32
                    }
                };
                let position = f32s(conformed.vertices.get(vertex as usize)?);
                Some(ViewLandmark {
                    name: l.name.clone(),
                    vertex,
                    position,
                })
            })
            .collect();
        View {
            format: "conformd-view".into(),
            version: 1,
            unit: "m".into(),
            distance: distance
                .unwrap_or_default()
                .iter()
                .map(|&d| d as f32)
                .collect(),
            landmarks,
            measurements: drawn
                .iter()
                .map(|d| ViewMeasurement {
                    name: d.measurement.name.clone(),
                    kind: d.measurement.kind.clone(),
                    value: d.measurement.value,
                    unit: d.measurement.unit.clone(),
                    lines: d
                        .lines
                        .iter()
                        .map(|l| l.iter().map(f32s).collect())
                        .collect(),
                    closed: d.closed,
                })
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::V3;

    #[test]
    fn landmarks_follow_their_vertices_and_points_snap_to_the_nearest() {
        let template = Mesh {
            vertices: vec![V3::zeros(), V3::x(), V3::y()],
            triangles: vec![[0, 1, 2]],
            ..Default::default()
        };
        let mut conformed = template.clone();
        for v in &mut conformed.vertices {
            *v += V3::new(0.0, 0.0, 2.0);
        }
        let lms = [
            Landmark {
                name: "a".into(),
                pos: LandmarkPos::Vertex(1),
            },
            Landmark {
                name: "b".into(),
                pos: LandmarkPos::Point(V3::new(0.1, 0.9, 0.0)),
            },
            Landmark {
                name: "out of range".into(),
                pos: LandmarkPos::Vertex(7),
            },
        ];
        let v = View::new(&conformed, &template, Some(&[0.5; 3]), Some(&lms), &[]);
        assert_eq!(v.landmarks.len(), 2);
        assert_eq!(v.landmarks[0].position, [1.0, 0.0, 2.0]);
        assert_eq!(
            (v.landmarks[1].vertex, v.landmarks[1].position),
            (2, [0.0, 1.0, 2.0])
        );
        assert_eq!(v.distance, vec![0.5; 3]);
    }
}
