//! Measurements of conformed meshes: definitions stored beside a template (a TOML file of
//! named distances, paths, girths, widths, heights, areas and volumes, each fixed by
//! template landmarks, vertices or template positions), checked once against the template
//! and then taken on any mesh in the template's vertex order. Because every conformed
//! scan has the template's vertices, a measurement defined once holds for all of them.

use crate::mesh::{Landmark, LandmarkPos, Mesh, V3, topology};
use std::collections::BTreeMap;
use std::path::Path;

pub mod posture;
pub mod weight;

/// What went wrong with a definition file or a measurement, naming the measurement.
#[derive(Debug, thiserror::Error)]
pub enum MeasureError {
    #[error("measurement definitions {path}: {message}")]
    File { path: String, message: String },
    #[error("measurement '{name}': {message}")]
    Definition { name: String, message: String },
    #[error("the mesh has {got} vertices, the template {expected}: not a result of this template")]
    VertexCount { got: usize, expected: usize },
    /// a posture model's removal failed
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
    /// the generic template's skeleton could not be undone on the mesh
    #[error(transparent)]
    Template(#[from] crate::template::TemplateError),
    #[error("the parts method moves the definitions, not the mesh: use measure")]
    PartsMoveDefinitions,
    #[error("the mesh has no vertices")]
    EmptyMesh,
    #[error("the mesh's parts could not be fitted (degenerate mesh)")]
    PartsNotFitted,
}

/// A place on the template: a landmark name, a vertex index, a position in template
/// coordinates (its nearest vertex), or several of these (their centroid, e.g. the
/// middle between two hips).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(untagged)]
pub enum Point {
    Vertex(u32),
    Landmark(String),
    Position([f64; 3]),
    Centroid(Vec<Point>),
}

/// One measurement's kind and the places that fix it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Kind {
    /// straight distance between two points
    Distance { from: Point, to: Point },
    /// straight segments through a list of points (an arm over the elbow, a back)
    Path { points: Vec<Point> },
    /// shortest way along the mesh's edges (an overestimate of the true geodesic by up to
    /// a few percent on coarse meshes)
    Surface { from: Point, to: Point },
    /// tape-measure perimeter (the convex hull, as a tape lies) of the mesh's section by
    /// the plane through `at` square to the line `axis`; of the section's piece nearest
    /// `at` (a leg cut by the same plane does not count); with `group`, cut from that
    /// vertex group's triangles only (an arm lying against the chest does not count)
    Girth {
        at: Point,
        axis: [Point; 2],
        #[serde(default, skip_serializing_if = "Option::is_none")]
        group: Option<String>,
    },
    /// extent, along the line `across`, of the same section piece as a girth
    Width {
        at: Point,
        axis: [Point; 2],
        across: [Point; 2],
        #[serde(default, skip_serializing_if = "Option::is_none")]
        group: Option<String>,
    },
    /// height of a point above the floor (see `Frame`)
    Height { point: Point },
    /// surface area (of the triangles of `group`, or of all)
    Area {
        #[serde(default)]
        group: Option<String>,
    },
    /// enclosed volume; only for watertight templates
    Volume,
}

/// A named measurement.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Definition {
    pub name: String,
    #[serde(flatten)]
    pub kind: Kind,
    /// how its posture-free value is taken
    #[serde(default, skip_serializing_if = "PostureFree::is_parts")]
    pub posture_free: PostureFree,
}

/// How a measurement's posture-free value is taken by the parts method.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PostureFree {
    /// its definition moved into the subject's posture by the parts under it
    #[default]
    Parts,
    /// as measured: for a measurement the posture does not change but the parts' fit
    /// would disturb (a height the legs stand to whatever the arms do), chosen where it
    /// repeats better
    AsMeasured,
    /// on the result with the generic template's skeleton fitted and undone through
    /// its skinning: for a section across a joint both bones' skin blends (the neck),
    /// which a plane carried by either part cuts differently in every posture
    Skeleton,
}

impl PostureFree {
    fn is_parts(&self) -> bool {
        *self == PostureFree::Parts
    }
}

/// The frame heights are measured in: the floor is the plane `up . x = floor`; lengths
/// are in `unit` (the mesh's unit: metres in rig space).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Frame {
    pub up: [f64; 3],
    pub floor: f64,
    pub unit: String,
}

impl Default for Frame {
    fn default() -> Self {
        Frame {
            up: [0.0, 0.0, 1.0],
            floor: 0.0,
            unit: "m".into(),
        }
    }
}

/// A definitions file: `[frame]` and `[[measurement]]` tables.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Definitions {
    pub frame: Frame,
    #[serde(rename = "measurement")]
    pub measurements: Vec<Definition>,
}

/// The generic pig's measurements (x forward, z up, metres).
pub const PIG: &str = include_str!("../../config/measurements/pig.toml");
/// The generic body's measurements (ISO 8559-1 names).
pub const BODY: &str = include_str!("../../config/measurements/body.toml");

impl Definitions {
    pub fn parse(text: &str, path: &str) -> Result<Definitions, MeasureError> {
        toml::from_str(text).map_err(|e| MeasureError::File {
            path: path.into(),
            // serde's words for an untagged enum name the type, not what to write
            message: e.to_string().replace(
                "data did not match any variant of untagged enum Point",
                "not a point: a point is a vertex index (0 or more), a landmark name, a position [x, y, z], or a list of points (their centroid)",
            ),
        })
    }

    pub fn read(path: &Path) -> Result<Definitions, MeasureError> {
        let shown = path.display().to_string();
        let text =
            crate::files::read_text_limited(path, 1 << 20).map_err(|e| MeasureError::File {
                path: shown.clone(),
                message: e.to_string(),
            })?;
        Definitions::parse(&text, &shown)
    }

    /// Checks every definition against the template and fixes its vertices.
    pub fn resolve(
        &self,
        template: &Mesh,
        landmarks: &[Landmark],
    ) -> Result<Resolved, MeasureError> {
        let up = V3::from(self.frame.up);
        let up = up
            .try_normalize(0.0)
            .filter(|u| u.iter().all(|c| c.is_finite()))
            .ok_or_else(|| MeasureError::File {
                path: "[frame]".into(),
                message: format!(
                    "up must be a finite, non-zero direction, got {:?}",
                    self.frame.up
                ),
            })?;
        if !self.frame.floor.is_finite() {
            return Err(MeasureError::File {
                path: "[frame]".into(),
                message: format!("floor must be a finite number, got {}", self.frame.floor),
            });
        }
        if self.measurements.is_empty() {
            return Err(MeasureError::File {
                path: "[[measurement]]".into(),
                message: "the file defines no measurement (each is a [[measurement]] table with a name and a kind)".into(),
            });
        }
        let mut seen = std::collections::BTreeSet::new();
        let mut out = Vec::new();
        let watertight = topology::report(template).watertight;
        for d in &self.measurements {
            let err = |message: String| MeasureError::Definition {
                name: d.name.clone(),
                message,
            };
            if d.name.is_empty()
                || !d
                    .name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            {
                return Err(err(
                    "a name must be letters, digits, '_' or '-' (it becomes a CSV column)".into(),
                ));
            }
            if !seen.insert(d.name.clone()) {
                return Err(err("named twice".into()));
            }
            let kind = resolve_kind(&d.kind, template, landmarks, watertight, &err)?;
            out.push((d.name.clone(), d.kind.clone(), kind, d.posture_free));
        }
        Ok(Resolved {
            vertices: template.vertices.len(),
            up,
            floor: self.frame.floor,
            unit: self.frame.unit.clone(),
            items: out,
        })
    }
}

/// One definition's kind fixed on the template: its points' vertices, its group's
/// triangles; a length between one place and itself, an axis of one vertex or a
/// volume of an open template refused.
fn resolve_kind(
    kind: &Kind,
    template: &Mesh,
    landmarks: &[Landmark],
    watertight: bool,
    err: &dyn Fn(String) -> MeasureError,
) -> Result<Resolved1, MeasureError> {
    let at = |p: &Point| resolve_point(p, template, landmarks).map_err(|e| err(e.to_string()));
    let resolved = match kind {
        Kind::Distance { from, to } => Resolved1::Path(vec![at(from)?, at(to)?]),
        Kind::Path { points } => {
            if points.len() < 2 {
                return Err(err("a path needs two points or more".into()));
            }
            Resolved1::Path(points.iter().map(&at).collect::<Result<_, _>>()?)
        }
        Kind::Surface { from, to } => Resolved1::Surface(at(from)?, at(to)?),
        Kind::Girth { at: p, axis, group } => Resolved1::Section(SectionDef {
            at: at(p)?,
            axis: [at(&axis[0])?, at(&axis[1])?],
            across: None,
            only: group_triangles(template, group.as_deref()).map_err(|e| err(e.to_string()))?,
        }),
        Kind::Width {
            at: p,
            axis,
            across,
            group,
        } => Resolved1::Section(SectionDef {
            at: at(p)?,
            axis: [at(&axis[0])?, at(&axis[1])?],
            across: Some([at(&across[0])?, at(&across[1])?]),
            only: group_triangles(template, group.as_deref()).map_err(|e| err(e.to_string()))?,
        }),
        Kind::Height { point } => Resolved1::Height(at(point)?),
        Kind::Area { group } => Resolved1::Area(
            group_triangles(template, group.as_deref())
                .map_err(|e| err(e.to_string()))?
                .map(|(_, inside)| {
                    (0..inside.len() as u32)
                        .filter(|&t| inside[t as usize])
                        .collect()
                }),
        ),
        Kind::Volume => {
            if !watertight {
                return Err(err(
                    "the template is not watertight (open or non-manifold): it encloses no volume"
                        .into(),
                ));
            }
            Resolved1::Volume
        }
    };
    if let Resolved1::Section(SectionDef { axis, .. }) = &resolved
        && axis[0] == axis[1]
    {
        return Err(err("the axis' two points are the same vertex".into()));
    }
    // a length between one place and itself is 0 on every mesh: a mistake
    match &resolved {
        Resolved1::Path(points) => {
            if let Some(k) = points.windows(2).position(|w| w[0] == w[1]) {
                return Err(err(format!(
                    "points {} and {} are the same place: the length would be 0 on every mesh",
                    k + 1,
                    k + 2
                )));
            }
        }
        Resolved1::Surface(a, b) if a == b => {
            return Err(err(
                "from and to are the same place: the length would be 0 on every mesh".into(),
            ));
        }
        _ => {}
    }
    Ok(resolved)
}

/// A point fixed on the template: the vertices whose centroid it is.
type Fixed = Vec<u32>;

/// A place or group a definition names that the template does not have.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
enum PlaceError {
    #[error("vertex {vertex}, but the template has {vertices} vertices")]
    Vertex { vertex: u32, vertices: usize },
    #[error("landmark '{name}' is not one of the template's ({known})")]
    Landmark { name: String, known: String },
    #[error("landmark '{name}' names vertex {vertex} of {vertices}")]
    LandmarkVertex {
        name: String,
        vertex: u32,
        vertices: usize,
    },
    #[error("position {0:?} is not finite")]
    Position([f64; 3]),
    #[error("an empty list of points")]
    EmptyList,
    #[error("group '{group}' is not one of the template's ({has})")]
    Group { group: String, has: String },
    #[error("group '{0}' has no triangle of the template")]
    EmptyGroup(String),
}

/// The triangles of vertex group `group` (all three corners in it), as a mask over the
/// template's triangles, with the group's name; `None` without a group.
fn group_triangles(
    template: &Mesh,
    group: Option<&str>,
) -> Result<Option<(String, Vec<bool>)>, PlaceError> {
    let Some(g) = group else { return Ok(None) };
    let members = template.groups.get(g).ok_or_else(|| PlaceError::Group {
        group: g.to_string(),
        has: template.group_names(),
    })?;
    let mut inside = vec![false; template.vertices.len()];
    for &v in members {
        if let Some(x) = inside.get_mut(v as usize) {
            *x = true;
        }
    }
    let mask: Vec<bool> = template
        .triangles
        .iter()
        .map(|t| t.iter().all(|&v| inside[v as usize]))
        .collect();
    if !mask.iter().any(|&m| m) {
        return Err(PlaceError::EmptyGroup(g.to_string()));
    }
    Ok(Some((g.to_string(), mask)))
}

fn resolve_point(p: &Point, template: &Mesh, landmarks: &[Landmark]) -> Result<Fixed, PlaceError> {
    let n = template.vertices.len();
    Ok(match p {
        Point::Vertex(v) if (*v as usize) < n => vec![*v],
        Point::Vertex(v) => {
            return Err(PlaceError::Vertex {
                vertex: *v,
                vertices: n,
            });
        }
        Point::Landmark(name) => {
            let l =
                landmarks
                    .iter()
                    .find(|l| &l.name == name)
                    .ok_or_else(|| PlaceError::Landmark {
                        name: name.clone(),
                        known: landmarks
                            .iter()
                            .map(|l| l.name.as_str())
                            .collect::<Vec<_>>()
                            .join(", "),
                    })?;
            match l.pos {
                LandmarkPos::Vertex(v) if (v as usize) < n => vec![v],
                LandmarkPos::Vertex(v) => {
                    return Err(PlaceError::LandmarkVertex {
                        name: name.clone(),
                        vertex: v,
                        vertices: n,
                    });
                }
                LandmarkPos::Point(q) => vec![nearest(template, &q)],
            }
        }
        Point::Position(q) => {
            if !q.iter().all(|c| c.is_finite()) {
                return Err(PlaceError::Position(*q));
            }
            vec![nearest(template, &V3::from(*q))]
        }
        Point::Centroid(ps) => {
            if ps.is_empty() {
                return Err(PlaceError::EmptyList);
            }
            let mut all = Vec::new();
            for q in ps {
                all.extend(resolve_point(q, template, landmarks)?);
            }
            all
        }
    })
}

fn nearest(m: &Mesh, q: &V3) -> u32 {
    (0..m.vertices.len())
        .min_by(|&a, &b| {
            (m.vertices[a] - q)
                .norm()
                .total_cmp(&(m.vertices[b] - q).norm())
        })
        .unwrap_or(0) as u32
}

#[derive(Debug, Clone)]
enum Resolved1 {
    Path(Vec<Fixed>),
    Surface(Fixed, Fixed),
    Section(SectionDef),
    Height(Fixed),
    Area(Option<Vec<u32>>),
    Volume,
}

/// A girth or width: the section of the mesh by the plane through `at` across
/// `axis`, its hull's perimeter or its extent along `across`.
#[derive(Debug, Clone)]
struct SectionDef {
    at: Fixed,
    axis: [Fixed; 2],
    across: Option<[Fixed; 2]>,
    /// the group the section is cut from, and its triangles
    only: Option<(String, Vec<bool>)>,
}

impl SectionDef {
    /// The section's value, its line, whether it is a loop, and a warning when it was
    /// cut from its group while other parts touch it. With a posture, the plane where
    /// the parts at `at` carry the template's.
    fn measure(
        &self,
        mesh: &Mesh,
        posed: Option<&posture::Posed>,
        unit: &str,
        err: &dyn Fn(String) -> MeasureError,
    ) -> Result<(f64, Vec<V3>, bool, Option<String>), MeasureError> {
        let SectionDef {
            at,
            axis,
            across,
            only,
        } = self;
        let v = &mesh.vertices;
        let mean = |f: &Fixed, at: &dyn Fn(u32) -> V3| {
            f.iter().map(|&i| at(i)).sum::<V3>() / f.len() as f64
        };
        let place = |f: &Fixed| mean(f, &|i| v[i as usize]);
        let (p, normal, side) = match posed {
            None => (
                place(at),
                place(&axis[1]) - place(&axis[0]),
                across.as_ref().map(|[a, b]| place(b) - place(a)),
            ),
            // the plane where the parts at `at` carry the template's
            Some(ps) => {
                let rest = |f: &Fixed| mean(f, &|i| ps.rest(i));
                let turned = |d: V3| mean(at, &|i| ps.turned(i, &d));
                (
                    mean(at, &|i| ps.carried(i)),
                    turned(rest(&axis[1]) - rest(&axis[0])),
                    across.as_ref().map(|[a, b]| turned(rest(b) - rest(a))),
                )
            }
        };
        let normal = normal
            .try_normalize(0.0)
            .ok_or_else(|| err("the axis has no length on this mesh".into()))?;
        let mask = only.as_ref().map(|(_, m)| &m[..]);
        let (piece, whole) = section_pieces(mesh, &p, &normal, mask)
            .ok_or_else(|| err("the plane does not cut the mesh".into()))?;
        // a plane through the mesh's extreme vertex touches it at one point:
        // no section to measure, not a girth of 0
        let spread = piece
            .iter()
            .map(|q| (q - piece[0]).norm())
            .fold(0.0, f64::max);
        if !(spread > 1e-6 * mesh.diagonal()) {
            return Err(err(format!(
                "the plane only touches the mesh at ({:.4}, {:.4}, {:.4}); there is no section to measure",
                piece[0].x, piece[0].y, piece[0].z
            )));
        }
        let across_dir = match side {
            None => None,
            Some(d) => {
                let s = d - normal * normal.dot(&d);
                // within ~6 degrees of the axis the direction across is noise
                if !(s.norm() > 0.1 * d.norm()) {
                    return Err(err(
                        "the width's direction (across) lies along the axis on this mesh; it must cross the section".into(),
                    ));
                }
                Some(s.normalize())
            }
        };
        let (value, line, closed) = section_value(&piece, &normal, across_dir);
        let mut warning = None;
        if let (Some(whole), Some((group, _))) = (whole, only) {
            let with = section_value(&whole, &normal, across_dir).0;
            if (with - value).abs() > 0.01 * value {
                warning = Some(format!(
                    "cut from the '{group}' group only: other parts touching the section (left out) would make it {with:.4} {}",
                    unit
                ));
            }
        }
        Ok((value, line, closed, warning))
    }
}

/// Definitions fixed on one template, ready to measure its results.
#[derive(Debug, Clone)]
pub struct Resolved {
    vertices: usize,
    up: V3,
    floor: f64,
    unit: String,
    items: Vec<(String, Kind, Resolved1, PostureFree)>,
}

/// One measured value.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Measurement {
    pub name: String,
    pub kind: String,
    pub value: f64,
    pub unit: String,
    /// what the reader should know about how it was taken (a section that had to be cut
    /// away from another body part)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

impl Resolved {
    pub fn names(&self) -> Vec<String> {
        self.items.iter().map(|(n, ..)| n.clone()).collect()
    }

    /// How each measurement's posture-free value is taken, in order.
    pub fn routes(&self) -> Vec<PostureFree> {
        self.items.iter().map(|(.., how)| *how).collect()
    }

    /// Every measurement on `mesh` (the template's vertex order).
    pub fn measure(&self, mesh: &Mesh) -> Result<Vec<Measurement>, MeasureError> {
        Ok(self
            .measure_drawn(mesh)?
            .into_iter()
            .map(|d| d.measurement)
            .collect())
    }

    /// Every measurement on `mesh` with the lines it was taken along, for a viewer to
    /// draw where it was taken.
    pub fn measure_drawn(&self, mesh: &Mesh) -> Result<Vec<Drawn>, MeasureError> {
        self.measure_in(mesh, None, None)
    }

    /// Every measurement on `mesh` with each definition moved into the posture `posed`
    /// (fitted to this mesh): sections cut where the parts carry their planes, lengths
    /// and heights with the joints' rotations taken out; areas, volumes and surface
    /// paths as they are (a posture does not change them). A measurement marked
    /// `as_measured` is as measured; one marked `skeleton` is taken on `straight` (the
    /// mesh with the template's skeleton undone), as measured when there is none.
    pub fn measure_posed(
        &self,
        mesh: &Mesh,
        posed: &posture::Posed,
        straight: Option<&Mesh>,
    ) -> Result<Vec<Measurement>, MeasureError> {
        Ok(self
            .measure_in(mesh, Some(posed), straight)?
            .into_iter()
            .map(|d| d.measurement)
            .collect())
    }

    fn measure_in(
        &self,
        mesh: &Mesh,
        posed: Option<&posture::Posed>,
        straight: Option<&Mesh>,
    ) -> Result<Vec<Drawn>, MeasureError> {
        for m in std::iter::once(mesh).chain(straight) {
            if m.vertices.len() != self.vertices {
                return Err(MeasureError::VertexCount {
                    got: m.vertices.len(),
                    expected: self.vertices,
                });
            }
        }
        let mean = |f: &Fixed, at: &dyn Fn(u32) -> V3| {
            f.iter().map(|&i| at(i)).sum::<V3>() / f.len() as f64
        };
        let mut out = Vec::with_capacity(self.items.len());
        for (name, kind, r, how) in &self.items {
            // each measurement on the mesh and with the posture its route takes
            let (mesh, posed) = match how {
                PostureFree::Parts => (mesh, posed),
                PostureFree::AsMeasured => (mesh, None),
                PostureFree::Skeleton => (straight.unwrap_or(mesh), None),
            };
            let place = |f: &Fixed| mean(f, &|i| mesh.vertices[i as usize]);
            // lengths and heights: with a posture, the joints' rotations taken out
            let length_place = |f: &Fixed| match posed {
                Some(p) => mean(f, &|i| p.normalised(i)),
                None => place(f),
            };
            let err = |message: String| MeasureError::Definition {
                name: name.clone(),
                message,
            };
            let mut warning = None;
            let (value, power, lines, closed) = match r {
                Resolved1::Path(ps) => {
                    let line: Vec<V3> = ps.iter().map(length_place).collect();
                    let length = line.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
                    (length, 1, vec![line], false)
                }
                Resolved1::Surface(a, b) => {
                    let (length, line) = edge_path(mesh, a[0], b[0]);
                    (length, 1, vec![line], false)
                }
                Resolved1::Section(def) => {
                    let (value, line, closed, w) = def.measure(mesh, posed, &self.unit, &err)?;
                    warning = w;
                    (value, 1, vec![line], closed)
                }
                Resolved1::Height(f) => match posed {
                    None => {
                        let top = place(f);
                        let height = top.dot(&self.up) - self.floor;
                        (height, 1, vec![vec![top, top - self.up * height]], false)
                    }
                    // on the floor under the subject's own feet, its joints straightened
                    Some(ps) => {
                        let top = length_place(f);
                        let height = top.dot(&ps.up) - ps.floor(self.floor);
                        (height, 1, vec![vec![top, top - ps.up * height]], false)
                    }
                },
                Resolved1::Area(tris) => (
                    match tris {
                        None => mesh.area(),
                        Some(ts) => ts
                            .iter()
                            .map(|&t| 0.5 * mesh.face_normal_scaled(t as usize).norm())
                            .sum(),
                    },
                    2,
                    Vec::new(),
                    false,
                ),
                Resolved1::Volume => (volume(mesh), 3, Vec::new(), false),
            };
            if !value.is_finite() {
                return Err(err(format!("came out as {value} on this mesh")));
            }
            out.push(Drawn {
                measurement: Measurement {
                    name: name.clone(),
                    kind: kind_name(kind).into(),
                    value,
                    unit: match power {
                        1 => self.unit.clone(),
                        p => format!("{}^{p}", self.unit),
                    },
                    warning,
                },
                lines,
                closed,
            });
        }
        Ok(out)
    }
}

/// A section piece's girth (its hull's perimeter, `across` `None`) or width along
/// `across`, with the line to draw and whether it is a loop.
fn section_value(piece: &[V3], normal: &V3, across: Option<V3>) -> (f64, Vec<V3>, bool) {
    match across {
        None => {
            let hull = hull_loop(piece, normal);
            (loop_length(&hull), hull, true)
        }
        Some(d) => {
            let lo = piece
                .iter()
                .min_by(|a, b| a.dot(&d).total_cmp(&b.dot(&d)))
                .copied()
                .unwrap_or_default();
            let hi = piece
                .iter()
                .map(|q| q.dot(&d))
                .fold(f64::NEG_INFINITY, f64::max);
            let width = hi - lo.dot(&d);
            (width, vec![lo, lo + d * width], false)
        }
    }
}

/// A measurement with where it was taken: polylines on or beside the mesh (a girth's
/// loop, a length's path, a height's drop to the floor; none for areas and volumes).
#[derive(Debug, Clone)]
pub struct Drawn {
    pub measurement: Measurement,
    pub lines: Vec<Vec<V3>>,
    /// the lines are loops (a girth)
    pub closed: bool,
}

fn kind_name(k: &Kind) -> &'static str {
    match k {
        Kind::Distance { .. } => "distance",
        Kind::Path { .. } => "path",
        Kind::Surface { .. } => "surface",
        Kind::Girth { .. } => "girth",
        Kind::Width { .. } => "width",
        Kind::Height { .. } => "height",
        Kind::Area { .. } => "area",
        Kind::Volume => "volume",
    }
}

/// Enclosed volume by the divergence theorem (positive for outward-facing triangles).
pub fn volume(m: &Mesh) -> f64 {
    m.triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| m.vertices[i as usize]);
            a.dot(&b.cross(&c)) / 6.0
        })
        .sum::<f64>()
        .abs()
}

/// Shortest way from `a` to `b` along the mesh's edges (Dijkstra).
/// Length and vertices of the shortest way along the mesh's edges from `a` to `b`.
fn edge_path(m: &Mesh, a: u32, b: u32) -> (f64, Vec<V3>) {
    let nb = topology::vertex_neighbours(m.vertices.len(), &m.triangles);
    let dist = topology::edge_distances(&m.vertices, &nb, &[a]).0;
    // walk back from b, each step to the neighbour the distance came through
    let mut line = vec![m.vertices[b as usize]];
    let mut at = b as usize;
    while at != a as usize && dist[at].is_finite() {
        let prev = nb[at]
            .iter()
            .map(|&j| j as usize)
            .filter(|&j| dist[j] < dist[at])
            .min_by(|&i, &j| {
                let via = |k: usize| dist[k] + (m.vertices[k] - m.vertices[at]).norm();
                via(i).total_cmp(&via(j))
            });
        let Some(prev) = prev else { break };
        line.push(m.vertices[prev]);
        at = prev;
    }
    line.reverse();
    (dist[b as usize], line)
}

/// The points of the mesh's section by the plane through `p` with unit normal `n`, of
/// the connected piece of the section nearest `p`. `None` when the plane misses.
pub fn section_piece(m: &Mesh, p: &V3, n: &V3) -> Option<Vec<V3>> {
    section_pieces(m, p, n, None).map(|(piece, _)| piece)
}

/// As [`section_piece`]; with `only` (a mask over the triangles), the piece is cut from
/// those triangles alone: the points they give in the connected piece nearest `p` (so
/// an arm joined to the chest's loop is left out, and the loop stays whole where another
/// group's triangles break it), and that whole piece comes second when it is bigger.
fn section_pieces(
    m: &Mesh,
    p: &V3,
    n: &V3,
    only: Option<&[bool]>,
) -> Option<(Vec<V3>, Option<Vec<V3>>)> {
    let d: Vec<f64> = m.vertices.iter().map(|v| (v - p).dot(n)).collect();
    // each cut edge gives one point; a triangle cut by the plane joins two of them
    let mut point_of: BTreeMap<(u32, u32), usize> = BTreeMap::new();
    let mut points: Vec<V3> = Vec::new();
    // (a, b, of a triangle in `only`)
    let mut links: Vec<(usize, usize, bool)> = Vec::new();
    let mut cut = |a: u32, b: u32, points: &mut Vec<V3>| -> usize {
        let key = (a.min(b), a.max(b));
        *point_of.entry(key).or_insert_with(|| {
            let (da, db) = (d[a as usize], d[b as usize]);
            let t = da / (da - db);
            points.push(m.vertices[a as usize] * (1.0 - t) + m.vertices[b as usize] * t);
            points.len() - 1
        })
    };
    for (ti, t) in m.triangles.iter().enumerate() {
        let mut ends = Vec::with_capacity(2);
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            // an edge is cut when its ends lie strictly on two sides (a vertex exactly on
            // the plane counts as above, so no point is found twice)
            if (d[a as usize] >= 0.0) != (d[b as usize] >= 0.0) {
                ends.push(cut(a, b, &mut points));
            }
        }
        if ends.len() == 2 {
            let inside = only.is_none_or(|o| o.get(ti).copied().unwrap_or(false));
            links.push((ends[0], ends[1], inside));
        }
    }
    if points.is_empty() {
        return None;
    }
    fn find(p: &mut [usize], mut x: usize) -> usize {
        while p[x] != x {
            p[x] = p[p[x]];
            x = p[x];
        }
        x
    }
    // pieces of the section: components over the links; the chosen triangles' points
    let mut parent: Vec<usize> = (0..points.len()).collect();
    let mut chosen = vec![only.is_none(); points.len()];
    for &(a, b, inside) in &links {
        if inside {
            chosen[a] = true;
            chosen[b] = true;
        }
        let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
        if ra != rb {
            parent[ra] = rb;
        }
    }
    let nearest = (0..points.len())
        .filter(|&i| chosen[i])
        .min_by(|&a, &b| (points[a] - p).norm().total_cmp(&(points[b] - p).norm()))?;
    let root = find(&mut parent, nearest);
    let whole: Vec<usize> = (0..points.len())
        .filter(|&i| find(&mut parent, i) == root)
        .collect();
    let piece: Vec<V3> = whole
        .iter()
        .filter(|&&i| chosen[i])
        .map(|&i| points[i])
        .collect();
    let whole = (whole.len() > piece.len()).then(|| whole.iter().map(|&i| points[i]).collect());
    Some((piece, whole))
}

/// Perimeter of the convex hull of points lying in a plane with unit normal `n`.
pub fn hull_perimeter(points: &[V3], n: &V3) -> f64 {
    loop_length(&hull_loop(points, n))
}

fn loop_length(l: &[V3]) -> f64 {
    (0..l.len())
        .map(|i| (l[(i + 1) % l.len()] - l[i]).norm())
        .sum()
}

/// The convex hull, in order, of points lying in a plane with unit normal `n`.
pub fn hull_loop(points: &[V3], n: &V3) -> Vec<V3> {
    let u = n
        .cross(&if n.x.abs() < 0.9 { V3::x() } else { V3::y() })
        .normalize();
    let w = n.cross(&u);
    let Some(first) = points.first() else {
        return Vec::new();
    };
    let offset = first.dot(n);
    let mut q: Vec<(f64, f64)> = points.iter().map(|p| (p.dot(&u), p.dot(&w))).collect();
    q.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    q.dedup();
    let to_space = |(a, b): (f64, f64)| u * a + w * b + n * offset;
    if q.len() < 2 {
        return q.into_iter().map(to_space).collect();
    }
    let cross = |o: (f64, f64), a: (f64, f64), b: (f64, f64)| {
        (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0)
    };
    // Andrew's monotone chain
    let mut hull: Vec<(f64, f64)> = Vec::with_capacity(2 * q.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &(f64, f64)>> = if pass == 0 {
            Box::new(q.iter())
        } else {
            Box::new(q.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull.into_iter().map(to_space).collect()
}

/// How a result's posture is taken out of its measurements.
pub enum PostureRemoval {
    /// a generic template's parts fitted to the result, each definition moved into the
    /// subject's posture (see [`posture`]); the mesh is not deformed. The template and
    /// its kind serve the measurements marked `skeleton`.
    Parts {
        parts: Box<posture::Articulation>,
        figure: Box<crate::template::figure::Figure>,
        kind: crate::template::Kind,
    },
    /// a generic template's own skeleton: its pose parameters fitted and undone by
    /// its skinning, then measured
    Skeleton(Box<crate::template::figure::Figure>, crate::template::Kind),
    /// the posture modes of a model (`model posture`, `model build --posture`)
    Model(Box<crate::model::ShapeModel>),
}

impl PostureRemoval {
    /// The station's and the CLI's way for a generic template: by its parts, which
    /// repeat best over postures (`cargo bench --bench repeatability`).
    pub fn for_figure(
        fig: &crate::template::figure::Figure,
        kind: crate::template::Kind,
        resolved: &Resolved,
    ) -> Self {
        PostureRemoval::Parts {
            parts: Box::new(posture::Articulation::from_figure(fig, resolved.up)),
            figure: Box::new(fig.clone()),
            kind,
        }
    }

    /// `m` with its posture removed (same vertex order, its shape and size kept); the
    /// parts method measures without deforming and has no such mesh.
    pub fn apply(&self, name: &str, m: &Mesh) -> Result<Mesh, MeasureError> {
        match self {
            PostureRemoval::Model(model) => Ok(model.remove_posture(name, m)?),
            PostureRemoval::Skeleton(fig, kind) => {
                Ok(crate::template::remove_posture(fig, *kind, m)?.0)
            }
            PostureRemoval::Parts { .. } => Err(MeasureError::PartsMoveDefinitions),
        }
    }

    /// `resolved`'s measurements of `m` with its posture taken out.
    pub fn measure(
        &self,
        resolved: &Resolved,
        name: &str,
        m: &Mesh,
    ) -> Result<Vec<Measurement>, MeasureError> {
        match self {
            PostureRemoval::Parts {
                parts,
                figure,
                kind,
            } => {
                let posed = parts.fit(m)?;
                // the skeleton is fitted only when a measurement asks for it
                let straight = if resolved.routes().contains(&PostureFree::Skeleton) {
                    Some(crate::template::remove_posture(figure, *kind, m)?.0)
                } else {
                    None
                };
                resolved.measure_posed(m, &posed, straight.as_ref())
            }
            _ => resolved.measure(&self.apply(name, m)?),
        }
    }
}

/// Measurements as CSV rows `name,kind,value,unit`.
pub fn to_csv(ms: &[Measurement]) -> String {
    let mut s = String::from("name,kind,value,unit\n");
    for m in ms {
        s += &format!("{},{},{},{}\n", m.name, m.kind, m.value, m.unit);
    }
    s
}

/// One measurement over several results of one subject: how well it repeats.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Spread {
    pub name: String,
    pub unit: String,
    /// how many results had it
    pub count: usize,
    pub mean: f64,
    /// sample standard deviation (n - 1)
    pub sd: f64,
    /// coefficient of variation, sd / |mean|
    pub cv: f64,
}

/// Each measurement's mean, SD and CV over `results` (each one result's measurements; a
/// measurement missing from a result is left out of its figures).
pub fn spread(results: &[Vec<Measurement>]) -> Vec<Spread> {
    let mut names: Vec<(String, String)> = Vec::new();
    for r in results {
        for m in r {
            if !names.iter().any(|(n, _)| n == &m.name) {
                names.push((m.name.clone(), m.unit.clone()));
            }
        }
    }
    names
        .into_iter()
        .map(|(name, unit)| {
            let v: Vec<f64> = results
                .iter()
                .filter_map(|r| r.iter().find(|m| m.name == name).map(|m| m.value))
                .collect();
            let n = v.len();
            let mean = v.iter().sum::<f64>() / n.max(1) as f64;
            let sd = if n > 1 {
                (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt()
            } else {
                0.0
            };
            Spread {
                name,
                unit,
                count: n,
                mean,
                sd,
                cv: if mean != 0.0 { sd / mean.abs() } else { 0.0 },
            }
        })
        .collect()
}
