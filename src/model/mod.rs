//! The statistical shape model (Ju et al. 2004, section 3.3): generalised Procrustes
//! alignment of conformed meshes, principal component analysis (the Gram-matrix route,
//! since there are far fewer samples than coordinates), mode scores, reconstruction
//! residuals, Mahalanobis outlier figures, and the model quality figures (compactness,
//! generalisation, specificity). One vertex group alone (a segment) can be modelled.

use crate::mesh::transform::{Similarity, fit_similarity};
use crate::mesh::{Mesh, V3};
use nalgebra::{DMatrix, SymmetricEigen};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

mod build;
mod quality;
pub use quality::{Quality, quality};

pub const FORMAT: &str = "conformd-shape-model";
pub const VERSION: u32 = 1;
/// Largest model file read: 500 shapes of a 100k-vertex template in JSON, with room.
pub const MAX_MODEL_BYTES: u64 = 4 << 30;

#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("a model needs at least 3 meshes, got {0}")]
    TooFew(usize),
    #[error(
        "{name}: it has {got} vertices, but {first} has {want}: meshes of one model must be conformed from one template"
    )]
    VertexCount {
        name: String,
        got: usize,
        first: String,
        want: usize,
    },
    #[error(
        "{name}: its triangles differ from {first}'s: meshes of one model must be conformed from one template"
    )]
    Topology { name: String, first: String },
    #[error("{name}: it was not conformed from this model's template ({detail})")]
    WrongTemplate { name: String, detail: String },
    #[error("the template has no vertex group '{group}' (it has: {known})")]
    NoGroup { group: String, known: String },
    #[error("{name}: non-finite coordinate at vertex {vertex}")]
    NotFinite { name: String, vertex: usize },
    #[error("{path}: not a valid shape model: {msg}")]
    File { path: String, msg: String },
    #[error(
        "the model has no posture modes: build one with `conformd model posture` (a generic template) or `model build --posture` (one subject in many postures)"
    )]
    NoPosture,
    #[error(
        "the {samples} meshes are one shape (no variance beyond rounding): a model needs different subjects or postures"
    )]
    NoVariance { samples: usize },
}

/// How samples are aligned before the analysis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Align {
    /// similarity (translation, rotation, scale): shape alone
    Procrustes,
    /// translation and rotation: size stays in the model (a growing pig)
    Rigid,
    /// as they are (already in one frame)
    None,
}

impl std::str::FromStr for Align {
    type Err = UnknownAlign;
    fn from_str(s: &str) -> Result<Self, UnknownAlign> {
        match s {
            "procrustes" => Ok(Align::Procrustes),
            "rigid" => Ok(Align::Rigid),
            "none" => Ok(Align::None),
            _ => Err(UnknownAlign(s.to_string())),
        }
    }
}

/// An alignment name that is not one of [`Align`]'s.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("unknown alignment '{0}' (expected procrustes, rigid or none)")]
pub struct UnknownAlign(pub String);

#[derive(Debug, Clone)]
pub struct BuildOptions {
    pub align: Align,
    /// model one vertex group alone
    pub group: Option<String>,
    /// modes kept at most
    pub max_modes: usize,
    /// the samples are one subject in many postures: every mode is a posture mode
    pub posture: bool,
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            align: Align::Procrustes,
            group: None,
            max_modes: 30,
            posture: false,
        }
    }
}

/// A point distribution model over one template's vertices (or one group of them).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ShapeModel {
    pub format: String,
    pub version: u32,
    /// the template's vertex count and a fingerprint of its triangles
    pub template_vertices: usize,
    pub template_fingerprint: String,
    pub align: Align,
    pub group: Option<String>,
    /// template vertex indices the model covers (all, or the group's)
    pub indices: Vec<u32>,
    /// triangles among those vertices, re-indexed, for drawing the model's shapes
    pub triangles: Vec<[u32; 3]>,
    pub samples: Vec<String>,
    /// 3 * #indices coordinates
    pub mean: Vec<f64>,
    /// one unit vector of 3 * #indices coordinates per mode
    pub modes: Vec<Vec<f32>>,
    /// variance along each mode (squared units, per coordinate vector)
    pub variances: Vec<f64>,
    /// share of the total variance each mode explains
    pub explained: Vec<f64>,
    pub total_variance: f64,
    /// the leading modes that are changes of posture, not of shape: all of a model built
    /// from one subject in many postures (`model posture`, `model build --posture`)
    #[serde(default)]
    pub posture_modes: usize,
}

/// Stable 64-bit FNV-1a of the vertex count and triangles (a model file outlives builds,
/// so no hasher whose output may change between Rust versions).
pub fn fingerprint(vertices: usize, tris: &[[u32; 3]]) -> String {
    let mut h: u64 = 0xcbf29ce484222325;
    let mut eat = |x: u32| {
        for b in x.to_le_bytes() {
            h ^= b as u64;
            h = h.wrapping_mul(0x100000001b3);
        }
    };
    eat(vertices as u32);
    for t in tris {
        t.iter().for_each(|&i| eat(i));
    }
    format!("{h:016x}")
}

/// One sample's figures against a model.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Score {
    pub name: String,
    /// mode scores, in units of each mode's standard deviation
    pub scores_sd: Vec<f64>,
    /// raw mode scores
    pub scores: Vec<f64>,
    /// root-mean-square per-vertex distance between the sample and its reconstruction
    pub residual: f64,
    /// Mahalanobis distance over the modes: large means unlike the training set
    pub mahalanobis: f64,
}

fn flatten(v: &[V3]) -> Vec<f64> {
    v.iter().flat_map(|p| [p.x, p.y, p.z]).collect()
}

fn unflatten(x: &[f64]) -> Vec<V3> {
    x.chunks_exact(3)
        .map(|c| V3::new(c[0], c[1], c[2]))
        .collect()
}

fn apply(t: &Similarity, v: &[V3]) -> Vec<V3> {
    v.iter().map(|p| t.apply(p)).collect()
}

fn centroid_size(v: &[V3]) -> f64 {
    let c = v.iter().sum::<V3>() / v.len() as f64;
    (v.iter().map(|p| (p - c).norm_squared()).sum::<f64>() / v.len() as f64).sqrt()
}

impl ShapeModel {
    /// `mesh` with its posture removed: aligned to the mean as the samples were, its
    /// components along the posture modes taken out, and moved back where it was (at its
    /// own size: the shape and the size stay, the posture goes). Modes are linear, so a
    /// posture is removed to first order: the larger the turn, the more is left.
    pub fn remove_posture(&self, name: &str, mesh: &Mesh) -> Result<Mesh, ModelError> {
        if self.posture_modes == 0 {
            return Err(ModelError::NoPosture);
        }
        let score = self.score(name, mesh)?;
        let pts: Vec<V3> = self
            .indices
            .iter()
            .map(|&i| mesh.vertices[i as usize])
            .collect();
        let t = match self.align {
            Align::None => Similarity::default(),
            a => fit_similarity(&pts, &self.mean_shape(), None, a == Align::Procrustes),
        };
        let inverse = t.inverse();
        let mut out = mesh.clone();
        for (k, &i) in self.indices.iter().enumerate() {
            let mut p = t.apply(&pts[k]);
            for (m, &b) in self
                .modes
                .iter()
                .zip(&score.scores)
                .take(self.posture_modes)
            {
                p -= V3::new(m[3 * k] as f64, m[3 * k + 1] as f64, m[3 * k + 2] as f64) * b;
            }
            out.vertices[i as usize] = inverse.apply(&p);
        }
        Ok(out)
    }

    pub fn mean_shape(&self) -> Vec<V3> {
        unflatten(&self.mean)
    }

    /// The shape at mode scores `b` (raw units), over the model's vertices.
    pub fn instance(&self, b: &[f64]) -> Vec<V3> {
        let mut x = self.mean.clone();
        for (m, &bi) in self.modes.iter().zip(b) {
            x.iter_mut().zip(m).for_each(|(a, &c)| *a += bi * c as f64);
        }
        unflatten(&x)
    }

    /// The mesh of an instance (the model's vertices and triangles).
    pub fn instance_mesh(&self, b: &[f64]) -> Mesh {
        Mesh::new(self.instance(b), self.triangles.clone())
    }

    /// Scores a conformed mesh of the same template: aligned to the mean as the samples
    /// were, projected on the modes.
    pub fn score(&self, name: &str, mesh: &Mesh) -> Result<Score, ModelError> {
        if mesh.vertices.len() != self.template_vertices {
            return Err(ModelError::WrongTemplate {
                name: name.into(),
                detail: format!(
                    "it has {} vertices, the model's template {}",
                    mesh.vertices.len(),
                    self.template_vertices
                ),
            });
        }
        if !mesh.triangles.is_empty()
            && fingerprint(mesh.vertices.len(), &mesh.triangles) != self.template_fingerprint
        {
            return Err(ModelError::WrongTemplate {
                name: name.into(),
                detail: "its triangles differ".into(),
            });
        }
        if let Some(v) = mesh.first_non_finite() {
            return Err(ModelError::NotFinite {
                name: name.into(),
                vertex: v,
            });
        }
        let pts: Vec<V3> = self
            .indices
            .iter()
            .map(|&i| mesh.vertices[i as usize])
            .collect();
        let mean = self.mean_shape();
        let aligned = match self.align {
            Align::None => pts,
            a => apply(
                &fit_similarity(&pts, &mean, None, a == Align::Procrustes),
                &pts,
            ),
        };
        let d: Vec<f64> = flatten(&aligned)
            .iter()
            .zip(&self.mean)
            .map(|(a, b)| a - b)
            .collect();
        let scores: Vec<f64> = self
            .modes
            .iter()
            .map(|m| m.iter().zip(&d).map(|(&a, b)| a as f64 * b).sum())
            .collect();
        let mut r = d.clone();
        for (m, &b) in self.modes.iter().zip(&scores) {
            r.iter_mut().zip(m).for_each(|(x, &c)| *x -= b * c as f64);
        }
        let residual = (r.iter().map(|x| x * x).sum::<f64>() / self.indices.len() as f64).sqrt();
        let scores_sd: Vec<f64> = scores
            .iter()
            .zip(&self.variances)
            .map(|(b, v)| b / v.sqrt().max(1e-300))
            .collect();
        Ok(Score {
            name: name.into(),
            mahalanobis: scores_sd.iter().map(|z| z * z).sum::<f64>().sqrt(),
            scores_sd,
            scores,
            residual,
        })
    }

    /// Checks the file's format, version and sizes.
    pub fn validate(&self, path: &str) -> Result<(), ModelError> {
        let bad = |msg: String| {
            Err(ModelError::File {
                path: path.into(),
                msg,
            })
        };
        if self.format != FORMAT {
            return bad(format!("format is '{}', expected '{FORMAT}'", self.format));
        }
        if self.version != VERSION {
            return bad(format!(
                "version {} is not supported (this conformd reads version {VERSION})",
                self.version
            ));
        }
        let dim = self.indices.len() * 3;
        if self.mean.len() != dim {
            return bad(format!(
                "the mean has {} coordinates, expected {dim}",
                self.mean.len()
            ));
        }
        if self.modes.len() != self.variances.len() || self.modes.iter().any(|m| m.len() != dim) {
            return bad("mode sizes do not match the mean or the variances".into());
        }
        if self
            .indices
            .iter()
            .any(|&i| i as usize >= self.template_vertices)
        {
            return bad("a vertex index exceeds the template".into());
        }
        if !self.mean.iter().all(|x| x.is_finite())
            || !self.variances.iter().all(|x| x.is_finite() && *x >= 0.0)
        {
            return bad("non-finite numbers".into());
        }
        Ok(())
    }

    pub fn save(&self, path: &std::path::Path) -> Result<(), crate::mesh::FileError> {
        let json = serde_json::to_vec(self).expect("a model serialises");
        crate::files::write_atomic(path, &json)
    }

    /// Reads a model saved by [`ShapeModel::save`] (at most [`MAX_MODEL_BYTES`]) and checks it.
    pub fn load(path: &std::path::Path) -> Result<ShapeModel, ModelError> {
        let name = path.display().to_string();
        let bytes =
            crate::files::read_limited(path, MAX_MODEL_BYTES).map_err(|e| ModelError::File {
                path: name.clone(),
                msg: e.to_string(),
            })?;
        let m: ShapeModel = serde_json::from_slice(&bytes).map_err(|e| ModelError::File {
            path: name.clone(),
            msg: e.to_string(),
        })?;
        m.validate(&name)?;
        Ok(m)
    }
}

impl std::fmt::Display for ShapeModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "model of {} meshes, {} vertices, {} modes",
            self.samples.len(),
            self.indices.len(),
            self.modes.len()
        )?;
        let mut cum = 0.0;
        for (i, e) in self.explained.iter().enumerate().take(10) {
            cum += e;
            write!(
                f,
                "\n  mode {:>2}: {:5.1}% of the variance ({:5.1}% cumulative)",
                i + 1,
                e * 100.0,
                cum * 100.0
            )?;
        }
        Ok(())
    }
}

impl std::fmt::Display for Score {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let z: Vec<String> = self
            .scores_sd
            .iter()
            .take(5)
            .map(|z| format!("{z:+.2}"))
            .collect();
        write!(
            f,
            "{}: scores (sd) [{}], residual {:.3e}, mahalanobis {:.2}",
            self.name,
            z.join(", "),
            self.residual,
            self.mahalanobis
        )
    }
}
