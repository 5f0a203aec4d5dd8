//! Conformation of a generic template mesh onto a scan (Ju et al. 2004, sections 2.1-2.3):
//! global mapping (landmark RBF, or automatic alignment), correspondence search, the
//! elastic solve, grass-fire filling of missing data, the iteration driver and its report.
//!
//! Two methods share this driver:
//! - `paper`: the paper as written: closest-point targets, springs that keep the original
//!   edge vectors (equation 4), grass-fire targets treated as data.
//! - `default`: rotation-aware springs (as-rigid-as-possible with cotangent weights and
//!   smoothed rotations), a point-to-plane data term with soft landmark terms, and grass
//!   fire that only sets the starting displacement of unmatched vertices.
//!
//! The result keeps the template's vertex order and triangles exactly.

pub mod align;
pub mod articulated;
pub mod coarse;
pub mod correspond;
pub mod fill;
mod fit;
pub mod limbs;
pub mod rbf;
pub mod solve;

use crate::mesh::decimate::Decimated;
use crate::mesh::landmarks::{Landmark, LandmarkPos};
use crate::mesh::quality::{self, Variation};
use crate::mesh::transform::fit_similarity;
use crate::mesh::{Mesh, V3, topology, vertex_normals};
use crate::template::rig::TemplateRig;
use correspond::{MatchLimits, ScanSurface};
pub use fit::FoldRepair;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::time::Instant;

/// Which conformation method runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Ju et al. 2004 exactly as written
    Paper,
    /// conformd's method: rotation-aware springs, point-to-plane data, soft landmarks
    Default,
}

/// When the coarse stage runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CoarseStage {
    Auto,
    Always,
    Never,
}

/// How springs behave where there is no data (default method).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HoleSprings {
    Rotated,
    Translated,
}

/// What the springs hold the mesh to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RestShape {
    Template,
    Mapped,
}

/// Options of a conformation; the `[conform]` part of a station config, or a
/// `conform.toml` of its own. Distances are relative to the template's bounding-box
/// diagonal after global mapping.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConformOptions {
    pub method: Method,
    /// iteration limit
    pub max_iterations: usize,
    /// stop when the largest vertex update is below this (relative to the diagonal)
    pub tolerance: f64,
    /// spring weight (epsilon of equation 2) of the first iteration: stiff
    pub epsilon_start: f64,
    /// spring weight reached after `epsilon_steps` iterations: loose
    pub epsilon_end: f64,
    pub epsilon_steps: usize,
    /// farthest match (relative) in the first iteration: wide, to catch parts the global
    /// mapping left far off
    pub max_distance_start: f64,
    /// farthest match (relative), reached after `epsilon_steps` iterations
    pub max_distance: f64,
    /// largest angle between template and scan normals for a match, degrees
    pub max_normal_angle: f64,
    /// weight of a landmark pair in the local fit (default method), against 1 for data
    pub landmark_weight: f64,
    /// share of point-to-point in the default method's data term (the rest is
    /// point-to-plane); a little keeps vertices from drifting along flat regions
    pub point_to_point: f64,
    /// rotation fit / linear solve alternations per iteration (default method)
    pub rotation_iterations: usize,
    /// Anderson acceleration of those alternations: how many past steps are mixed
    /// (0 = plain alternation)
    pub anderson_history: usize,
    /// vertices of the decimated template the schedule runs on (default method) before
    /// the last iterations at full resolution; 0, or a template under twice this size,
    /// fits at full resolution throughout
    pub multires_vertices: usize,
    /// the same without landmarks: the decimated level then carries the posture alone,
    /// and a finer one follows limbs better (0 = off)
    pub multires_vertices_no_landmarks: usize,
    /// iterations at full resolution after the decimated template's
    pub multires_iterations: usize,
    /// rings of neighbours over which each vertex's rotation is fitted (default method);
    /// 0 fits each vertex alone
    pub rotation_rings: usize,
    /// springs of vertices without data: `rotated` (as-rigid-as-possible, keeping the
    /// template's local shape) or `translated` (the paper's springs: a smooth
    /// displacement field across the hole)
    pub hole_springs: HoleSprings,
    /// let each vertex's springs also scale (as-similar-as-possible), up to this factor
    /// either way; 1 keeps them rigid
    pub local_scale_limit: f64,
    /// relaxation (default method): when the schedule has reached `epsilon_end` and the
    /// fit still lies farther than `relax_distance` (relative) from the scan on average,
    /// the subject differs from the template in shape, not only in posture; the springs
    /// then loosen step by step down to this epsilon and may scale up to
    /// `relax_scale_limit`. At or above `epsilon_end`: never relax
    pub relax_epsilon: f64,
    pub relax_scale_limit: f64,
    /// mean distance to the scan (relative) above which the fit relaxes; posture changes
    /// of the development set end at 0.04-0.14%
    pub relax_distance: f64,
    /// spring stiffness factor per named vertex group (the paper's section 3.2 remedy)
    pub stiffness: BTreeMap<String, f64>,
    /// relative regularisation of the landmark RBF (0 interpolates exactly)
    pub rbf_smoothing: f64,
    /// the springs' rest shape: the template under the global similarity (`template`),
    /// or the template as the global mapping left it (`mapped`)
    pub rest: RestShape,
    /// when the coarse deformation-graph stage runs (default method): `auto` when the
    /// scan has no landmarks (the landmark mapping already places the parts), `always`,
    /// or `never`
    pub coarse: CoarseStage,
    /// nodes of the coarse deformation graph
    pub coarse_nodes: usize,
    /// iterations of the coarse stage
    pub coarse_iterations: usize,
    /// weight of scan-to-template pulls in the coarse stage (0 = template-to-scan only)
    pub scan_to_template: f64,
    /// relative residual at which a linear solve stops
    pub solver_tolerance: f64,
    pub solver_max_iterations: usize,
    /// after the elastic fit, give triangles the data turned inside out their rest shape
    /// back (default method; see `FoldRepair`)
    pub repair_folds: bool,
    pub align: align::AlignOptions,
}

impl Default for ConformOptions {
    /// Defaults chosen on the development set of outside meshes (`conformd_devset::devset`, README
    /// table), checked on the articulated and box cases of `tests/`.
    fn default() -> Self {
        ConformOptions {
            method: Method::Default,
            max_iterations: 20,
            tolerance: 2e-4,
            epsilon_start: 80.0,
            epsilon_end: 10.0,
            epsilon_steps: 6,
            max_distance_start: 0.2,
            max_distance: 0.035,
            max_normal_angle: 60.0,
            landmark_weight: 10.0,
            point_to_point: 0.1,
            rotation_iterations: 3,
            anderson_history: 3,
            multires_vertices: 2000,
            multires_vertices_no_landmarks: 4000,
            multires_iterations: 2,
            rotation_rings: 4,
            hole_springs: HoleSprings::Rotated,
            local_scale_limit: 1.0,
            relax_epsilon: 2.0,
            relax_scale_limit: 2.0,
            relax_distance: 0.002,
            stiffness: BTreeMap::new(),
            rbf_smoothing: 1e-6,
            rest: RestShape::Template,
            coarse: CoarseStage::Auto,
            coarse_nodes: 300,
            coarse_iterations: 90,
            scan_to_template: 6.0,
            solver_tolerance: 1e-4,
            solver_max_iterations: 300,
            repair_folds: true,
            align: align::AlignOptions::default(),
        }
    }
}

impl ConformOptions {
    /// The paper's method with settings that suit it. The springs' rest shape is the
    /// generic mesh as the global mapping left it: equation 4's "original positions in
    /// the generic mesh" read as the mesh the local stage starts from (the paper's second
    /// step "relies on the first step").
    pub fn paper() -> Self {
        ConformOptions {
            method: Method::Paper,
            rest: RestShape::Mapped,
            max_iterations: 30,
            epsilon_start: 1.0,
            epsilon_end: 1.0,
            max_distance_start: 0.05,
            max_distance: 0.05,
            ..Default::default()
        }
    }

    /// Checks every value before work starts.
    /// Refuses a `stiffness` entry for a group `template` does not have (a misspelt
    /// group would silently leave its springs as they are).
    pub fn check_groups(&self, template: &Mesh) -> Result<(), UnknownGroup> {
        match self
            .stiffness
            .keys()
            .find(|g| !template.groups.contains_key(*g))
        {
            Some(g) => Err(UnknownGroup {
                group: g.clone(),
                has: template.group_names(),
            }),
            None => Ok(()),
        }
    }

    pub fn validate(&self) -> Result<(), ConformError> {
        let bad = |m: String| Err(ConformError::Options(m));
        let positive = [
            ("tolerance", self.tolerance),
            ("epsilon_start", self.epsilon_start),
            ("epsilon_end", self.epsilon_end),
            ("max_distance", self.max_distance),
            ("max_distance_start", self.max_distance_start),
            ("relax_distance", self.relax_distance),
            ("solver_tolerance", self.solver_tolerance),
        ];
        for (name, v) in positive {
            if !(v > 0.0 && v.is_finite()) {
                return bad(format!("{name} must be a positive number, got {v}"));
            }
        }
        for (name, v) in [
            ("local_scale_limit", self.local_scale_limit),
            ("relax_scale_limit", self.relax_scale_limit),
        ] {
            if !(v >= 1.0 && v.is_finite()) {
                return bad(format!("{name} must be 1 or more, got {v}"));
            }
        }
        if !(self.relax_epsilon > 0.0 && self.relax_epsilon.is_finite()) {
            return bad(format!(
                "relax_epsilon must be a positive number, got {}",
                self.relax_epsilon
            ));
        }
        // counts that bound work: a typo must not run for hours
        let counts = [
            ("max_iterations", self.max_iterations, 1, 1000),
            ("epsilon_steps", self.epsilon_steps, 1, 1000),
            ("rotation_iterations", self.rotation_iterations, 1, 50),
            ("rotation_rings", self.rotation_rings, 1, 10),
            ("anderson_history", self.anderson_history, 0, 20),
            ("multires_iterations", self.multires_iterations, 1, 1000),
            ("multires_vertices", self.multires_vertices, 0, 10_000_000),
            (
                "multires_vertices_no_landmarks",
                self.multires_vertices_no_landmarks,
                0,
                10_000_000,
            ),
            ("coarse_nodes", self.coarse_nodes, 4, 20_000),
            ("coarse_iterations", self.coarse_iterations, 1, 10_000),
            (
                "solver_max_iterations",
                self.solver_max_iterations,
                1,
                100_000,
            ),
            ("align.icp_iterations", self.align.icp_iterations, 1, 10_000),
            ("align.limbs", self.align.limbs, 0, 64),
        ];
        for (name, v, lo, hi) in counts {
            if !(lo..=hi).contains(&v) {
                return bad(format!("{name} must be {lo} to {hi}, got {v}"));
            }
        }
        if !(self.scan_to_template >= 0.0 && self.scan_to_template.is_finite()) {
            return bad(format!(
                "scan_to_template must be 0 or more, got {}",
                self.scan_to_template
            ));
        }
        self.validate_align()?;
        if !(0.0..=180.0).contains(&self.max_normal_angle) {
            return bad(format!(
                "max_normal_angle must be 0-180 degrees, got {}",
                self.max_normal_angle
            ));
        }
        if !(0.0..=1.0).contains(&self.point_to_point) {
            return bad(format!(
                "point_to_point must be 0-1, got {}",
                self.point_to_point
            ));
        }
        if !(self.landmark_weight >= 0.0 && self.landmark_weight.is_finite()) {
            return bad(format!(
                "landmark_weight must be 0 or more, got {}",
                self.landmark_weight
            ));
        }
        if !(self.rbf_smoothing >= 0.0 && self.rbf_smoothing.is_finite()) {
            return bad(format!(
                "rbf_smoothing must be 0 or more, got {}",
                self.rbf_smoothing
            ));
        }
        for (g, &k) in &self.stiffness {
            if !(k > 0.0 && k.is_finite()) {
                return bad(format!(
                    "stiffness of group '{g}' must be positive, got {k}"
                ));
            }
        }
        Ok(())
    }

    /// The alignment's hints: directions finite and non-zero, a front on both sides or
    /// neither, the front's tolerance and the trimmed share in range.
    fn validate_align(&self) -> Result<(), ConformError> {
        let bad = |m: String| Err(ConformError::Options(m));
        for (name, v) in [
            ("align.template_up", self.align.template_up),
            ("align.scan_up", self.align.scan_up),
            ("align.template_front", self.align.template_front),
            ("align.scan_front", self.align.scan_front),
        ] {
            if let Some(u) =
                v.filter(|u| !(u.iter().all(|c| c.is_finite()) && u.iter().any(|c| *c != 0.0)))
            {
                return bad(format!(
                    "{name} must be a finite, non-zero direction, got {u:?}"
                ));
            }
        }
        if self.align.template_front.is_some() != self.align.scan_front.is_some() {
            return bad(
                "align.template_front and align.scan_front go together: the way the template \
                 faces means nothing without the way the subject faces on the rig"
                    .into(),
            );
        }
        if !(self.align.front_within_deg > 0.0 && self.align.front_within_deg <= 180.0) {
            return bad(format!(
                "align.front_within_deg must be over 0 and at most 180 degrees, got {}",
                self.align.front_within_deg
            ));
        }
        if !(0.3..=1.0).contains(&self.align.trim) {
            return bad(format!("align.trim must be 0.3-1, got {}", self.align.trim));
        }
        Ok(())
    }

    /// Geometric progression from `start` to `end` over the first `epsilon_steps`.
    fn schedule(&self, it: usize, start: f64, end: f64) -> f64 {
        if self.epsilon_steps <= 1 {
            return end;
        }
        let f = (it as f64 / (self.epsilon_steps - 1) as f64).min(1.0);
        start * (end / start).powf(f)
    }
}

/// A `stiffness` entry for a group the template does not have.
#[derive(Debug, Clone, thiserror::Error)]
#[error("stiffness names group '{group}', which the template does not have (it has: {has})")]
pub struct UnknownGroup {
    pub group: String,
    /// the template's groups, listed
    pub has: String,
}

#[derive(Debug, thiserror::Error)]
pub enum ConformError {
    #[error("template: {0}")]
    Template(String),
    #[error("template: {0}")]
    TemplateMesh(crate::mesh::MeshError),
    #[error("scan: {0}")]
    Scan(#[from] correspond::ScanError),
    #[error("landmarks: {0}")]
    Landmarks(String),
    #[error("landmarks: {0}")]
    Rbf(#[from] rbf::RbfError),
    #[error("options: {0}")]
    Options(String),
    #[error("options: {0}")]
    Group(#[from] UnknownGroup),
    #[error("cancelled")]
    Cancelled,
    /// a fault of the method, never of the input: reported rather than written out
    #[error("the fit went numerically wrong ({0}); nothing was written")]
    Numerical(String),
}

/// The figures of one iteration (the paper's section 3.1, plus fit figures).
#[derive(Debug, Clone, serde::Serialize)]
pub struct IterationReport {
    pub iteration: usize,
    /// the template vertices this iteration moved: fewer on the decimated level
    pub vertices: usize,
    pub epsilon: f64,
    /// variations of edge length, angle and area against the original template
    pub variation: Variation,
    pub matched: usize,
    /// vertices given a displacement by the grass fire
    pub filled: usize,
    /// vertices no match can reach (a component with no data)
    pub unreachable: usize,
    /// mean distance of the matched vertices of this iteration's result to the scan
    pub mean_distance: f64,
    pub mean_distance_relative: f64,
    /// largest vertex update of this iteration, scan units and relative
    pub max_update: f64,
    pub max_update_relative: f64,
    /// mean vertex update of this iteration, relative to the diagonal
    pub mean_update_relative: f64,
    pub solver_iterations: usize,
    pub seconds: f64,
}

/// Where the time went, seconds.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct StageTimes {
    pub setup: f64,
    pub global: f64,
    /// parts of `global` without landmarks: the rigid alignment, the limb search, the
    /// rig's fit
    pub align: f64,
    pub limbs: f64,
    pub rig: f64,
    pub coarse: f64,
    pub correspond: f64,
    pub fill: f64,
    pub rotations: f64,
    pub solve: f64,
    pub fold_repair: f64,
    pub total: f64,
}

/// How the template was first placed on the scan.
#[derive(Debug, Clone, serde::Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum GlobalReport {
    LandmarkRbf {
        pairs: Vec<String>,
        unpaired: Vec<String>,
        /// the rig's fit with the marks held, when the template has a rig (its own or
        /// an automatic one)
        #[serde(skip_serializing_if = "Option::is_none")]
        articulated: Option<articulated::ArticulatedReport>,
    },
    Automatic(align::AlignReport),
}

/// The whole report of a conformation, written as JSON by the CLI.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ConformReport {
    pub method: Method,
    pub template_vertices: usize,
    pub template_triangles: usize,
    pub scan_points: usize,
    pub scan_is_mesh: bool,
    pub global: GlobalReport,
    pub iterations: Vec<IterationReport>,
    pub converged: bool,
    /// figures of the result: against the original template
    pub final_variation: Variation,
    pub folded_triangles: usize,
    /// what the fold repair found and left (absent when it did not run)
    pub fold_repair: Option<FoldRepair>,
    /// vertices of parts the template holds inside itself (eyeballs, teeth), placed
    /// with what surrounds them rather than fitted ([`place_enclosed`])
    pub enclosed_vertices: usize,
    pub matched: usize,
    pub filled: usize,
    pub mean_distance: f64,
    pub mean_distance_relative: f64,
    /// RMS distance of landmark vertices to their scan landmarks, when landmarks were used
    pub landmark_rms: Option<f64>,
    pub watertight_template: bool,
    pub watertight_result: bool,
    /// set when the result is distorted far beyond what a change of posture explains
    pub distortion_warning: Option<String>,
    /// set when two placements of the rig fit scored almost alike: the result may face
    /// the wrong way
    pub placement_warning: Option<String>,
    pub seconds: StageTimes,
}

/// Edge-length and area variation (standard deviations) above which a result is distorted
/// far beyond a change of posture. Posed truths of the development set vary 0.03-0.06
/// (edge) and 0.05-0.12 (area); fits whose vertices slid along the scan reached 0.2 and
/// more.
pub const DISTORTION_EDGE_STD: f64 = 0.12;
pub const DISTORTION_AREA_STD: f64 = 0.25;

/// The warning for a fit whose placements scored almost alike (the rig fit's
/// `ambiguous`): the result may face the wrong way.
pub fn placement_warning(global: &GlobalReport) -> Option<String> {
    let GlobalReport::Automatic(a) = global else {
        return None;
    };
    let r = a.articulated.as_ref().filter(|r| r.ambiguous)?;
    let s: Vec<String> = r
        .hypotheses
        .iter()
        .map(|h| format!("{:.3}%", (h.template_to_scan + h.scan_to_template) * 100.0))
        .collect();
    Some(format!(
        "two placements of the rig fit almost alike (trimmed distances {}): check which way the result faces, or fit it by landmarks",
        s.join(" and ")
    ))
}

/// The warning for a result's variation against its template, if it is far above what a
/// posture change gives.
pub fn distortion_warning(v: &Variation) -> Option<String> {
    (v.edge_length.std > DISTORTION_EDGE_STD || v.area.std > DISTORTION_AREA_STD).then(|| {
        format!(
            "the result is distorted far beyond a change of posture (edge-length variation std {:.3}, area {:.3}; a posture change gives about 0.03-0.06 and 0.05-0.12): vertices may have slid along the scan; check the landmarks, the template's fit to this subject, or the options",
            v.edge_length.std, v.area.std
        )
    })
}

impl std::fmt::Display for ConformReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "conformed {} vertices onto {} scan points in {} iterations, {:.2} s ({} method{})",
            self.template_vertices,
            self.scan_points,
            self.iterations.len(),
            self.seconds.total,
            format!("{:?}", self.method).to_lowercase(),
            if self.converged {
                ""
            } else {
                ", iteration limit reached"
            }
        )?;
        writeln!(
            f,
            "mean distance to the scan {:.3e} ({:.3}% of the diagonal); {} vertices matched, {} filled; {} folded triangles; watertight {}",
            self.mean_distance,
            self.mean_distance_relative * 100.0,
            self.matched,
            self.filled,
            self.folded_triangles,
            self.watertight_result
        )?;
        if let GlobalReport::Automatic(a) = &self.global
            && let Some(r) = &a.articulated
        {
            writeln!(
                f,
                "rig fitted ({}): {} joints turned, scale {:.3}; the elastic fit started from {}",
                r.rig,
                r.joints_deg.len(),
                r.scale,
                if r.kept_limb_search {
                    "the limb search's turns (they explained the scan as well)"
                } else {
                    "the rig's fit"
                }
            )?;
        }
        let v = &self.final_variation;
        write!(
            f,
            "distortion against the template (std): edge length {:.3}, angles {:.2} deg, area {:.3}",
            v.edge_length.std,
            v.angle.std.to_degrees(),
            v.area.std
        )?;
        if let Some(w) = &self.distortion_warning {
            write!(f, "\nwarning: {w}")?;
        }
        if let Some(w) = &self.placement_warning {
            write!(f, "\nwarning: {w}")?;
        }
        Ok(())
    }
}

/// A conformed mesh and its report.
#[derive(Debug)]
pub struct Conformed {
    pub mesh: Mesh,
    pub report: ConformReport,
}

/// Landmark pairs by name: template vertex index and scan point.
#[derive(Debug, Clone)]
struct Pairs {
    names: Vec<String>,
    vertex: Vec<u32>,
    target: Vec<V3>,
    unpaired: Vec<String>,
}

impl Pairs {
    /// The same pairs on a decimated template (landmark vertices are kept by it).
    fn on_level(&self, level: &Decimated) -> Pairs {
        Pairs {
            vertex: self
                .vertex
                .iter()
                .map(|&v| level.owner[v as usize])
                .collect(),
            ..self.clone()
        }
    }
}

/// The decimated template the default method runs its schedule on, when the options ask
/// for one and the template is large enough to gain from it.
fn multires_level(
    template: &Mesh,
    pairs: Option<&Pairs>,
    opts: &ConformOptions,
) -> Option<Decimated> {
    let target = if pairs.is_some() {
        opts.multires_vertices
    } else {
        opts.multires_vertices_no_landmarks
    };
    if opts.method != Method::Default || target == 0 || template.vertices.len() * 4 < target * 5 {
        return None;
    }
    let protected = pairs.map_or(&[][..], |p| &p.vertex[..]);
    Some(crate::mesh::decimate::decimate(template, target, protected))
}

fn pair_landmarks(
    tl: &[Landmark],
    sl: &[Landmark],
    template: &Mesh,
) -> Result<Pairs, ConformError> {
    let mut p = Pairs {
        names: vec![],
        vertex: vec![],
        target: vec![],
        unpaired: vec![],
    };
    for t in tl {
        let Some(s) = sl.iter().find(|s| s.name == t.name) else {
            p.unpaired.push(t.name.clone());
            continue;
        };
        let v = match t.pos {
            LandmarkPos::Vertex(i) if (i as usize) < template.vertices.len() => i,
            LandmarkPos::Vertex(i) => {
                return Err(ConformError::Landmarks(format!(
                    "template landmark '{}' names vertex {i}, but the template has {} vertices",
                    t.name,
                    template.vertices.len()
                )));
            }
            LandmarkPos::Point(q) => nearest_vertex(&template.vertices, &q),
        };
        let target = crate::mesh::landmarks::scan_points(std::slice::from_ref(s))
            .map_err(|e| ConformError::Landmarks(e.to_string()))?[0]
            .1;
        if !target.iter().all(|c| c.is_finite()) {
            return Err(ConformError::Landmarks(format!(
                "scan landmark '{}' has a non-finite coordinate",
                s.name
            )));
        }
        p.names.push(t.name.clone());
        p.vertex.push(v);
        p.target.push(target);
    }
    // a scan landmark the template lacks is a misspelt or foreign name: dropping it
    // would fit without the point its user placed
    let unknown: Vec<&str> = sl
        .iter()
        .filter(|s| !tl.iter().any(|t| t.name == s.name))
        .map(|s| s.name.as_str())
        .collect();
    if !unknown.is_empty() {
        let mut known: Vec<&str> = tl.iter().map(|t| t.name.as_str()).collect();
        known.truncate(30);
        return Err(ConformError::Landmarks(format!(
            "scan landmark(s) {} are not among the template's ({})",
            unknown
                .iter()
                .map(|n| format!("'{}'", n.escape_default()))
                .collect::<Vec<_>>()
                .join(", "),
            known.join(", ")
        )));
    }
    Ok(p)
}

fn nearest_vertex(v: &[V3], q: &V3) -> u32 {
    (0..v.len())
        .min_by(|&a, &b| {
            (v[a] - q)
                .norm_squared()
                .total_cmp(&(v[b] - q).norm_squared())
        })
        .unwrap_or(0) as u32
}

/// Conforms `template` onto `scan`.
///
/// - `template`: a triangle mesh (#V vertices, #F triangles), optionally with groups
/// - `scan`: a mesh with holes or a point cloud (normals used when present)
/// - `landmarks`: template and scan landmarks, paired by name; `None` aligns automatically
/// - `progress`: called after every iteration
///
/// Returns a mesh with the template's #V vertices in the same order and its #F triangles,
/// shaped like the scan, and the report. Example: `tests/paper_cases.rs`.
pub fn conform(
    template: &Mesh,
    scan: &Mesh,
    landmarks: Option<(&[Landmark], &[Landmark])>,
    opts: &ConformOptions,
    progress: &mut OnIteration,
) -> Result<Conformed, ConformError> {
    let never = std::sync::atomic::AtomicBool::new(false);
    conform_cancellable(template, scan, landmarks, opts, progress, &never)
}

/// [`conform_cancellable`] with the template's rig: without landmarks (default method)
/// the rig's pose, shape and placement are fitted first (`articulated`) from each
/// placement the alignment leaves, the best by its distances both ways kept, and the
/// elastic fit starts from it (its springs still hold the template's own shape: with
/// the posed template as their rest shape the development set came out worse).
pub fn conform_rigged(
    template: &Mesh,
    rig: Option<&TemplateRig>,
    scan: &Mesh,
    landmarks: Option<(&[Landmark], &[Landmark])>,
    opts: &ConformOptions,
    progress: &mut OnIteration,
    cancel: &std::sync::atomic::AtomicBool,
) -> Result<Conformed, ConformError> {
    if let Some(r) = rig {
        r.check(template.vertices.len())
            .map_err(|e| ConformError::Template(format!("its rig: {e}")))?;
    }
    // On one of the pool's threads, the many short parallel loops of an iteration are
    // shared by work stealing; called from outside, each would be handed to the pool
    // and waited for (about a tenth of the time on 2 cores).
    rayon::scope(|_| conform_on_pool(template, rig, scan, landmarks, opts, progress, cancel))
}

/// What a conformation tells its caller after each iteration. `Send`: the work runs on
/// the thread pool.
pub type OnIteration<'a> = dyn FnMut(&IterationReport) + Send + 'a;

/// [`conform`] that a service can stop: `cancel` is read between stages and iterations,
/// and once it is set the call returns [`ConformError::Cancelled`] within one iteration.
pub fn conform_cancellable(
    template: &Mesh,
    scan: &Mesh,
    landmarks: Option<(&[Landmark], &[Landmark])>,
    opts: &ConformOptions,
    progress: &mut OnIteration,
    cancel: &std::sync::atomic::AtomicBool,
) -> Result<Conformed, ConformError> {
    conform_rigged(template, None, scan, landmarks, opts, progress, cancel)
}

fn conform_on_pool(
    template: &Mesh,
    rig: Option<&TemplateRig>,
    scan: &Mesh,
    landmarks: Option<(&[Landmark], &[Landmark])>,
    opts: &ConformOptions,
    progress: &mut OnIteration,
    cancel: &std::sync::atomic::AtomicBool,
) -> Result<Conformed, ConformError> {
    let t_start = Instant::now();
    check_inputs(template, opts)?;
    // The scan's search structures and the decimated template (which keeps the landmark
    // vertices) are independent: built side by side.
    let ((surface, template_topology), paired) = rayon::join(
        || (ScanSurface::new(scan), topology::report(template)),
        || -> Result<_, ConformError> {
            let pairs = match landmarks {
                Some((tl, sl)) => Some(pair_landmarks(tl, sl, template)?),
                None => None,
            };
            let level = multires_level(template, pairs.as_ref(), opts);
            Ok((pairs, level))
        },
    );
    let surface = surface?;
    let (pairs, level) = paired?;
    let mut times = StageTimes {
        setup: t_start.elapsed().as_secs_f64(),
        ..Default::default()
    };

    // 1. Global mapping.
    let t0 = Instant::now();
    let (hypotheses, mut global_report) =
        global_mapping(template, rig, &surface, pairs.as_ref(), opts, &mut times)?;
    times.global = t0.elapsed().as_secs_f64();

    // 2-4. The elastic fit: coarse stage, then the iterations; for each alignment
    // hypothesis the residuals could not tell apart, kept by the fit's distortion and
    // distance to the scan (a template turned round fits with torn, stretched springs).
    // On a decimated level the hypotheses are told apart there, and only the kept one
    // goes on to the full resolution.
    let elastic = Elastic {
        template,
        surface: &surface,
        pairs: pairs.as_ref(),
        opts,
        fitted: hypotheses.len(),
        cancel,
    };
    let best = match &level {
        Some(level) => elastic.on_level(level, hypotheses, &mut times, progress)?,
        None => elastic.at_full_resolution(hypotheses, &mut times, progress)?,
    };
    elastic.cancelled()?;
    if let GlobalReport::Automatic(rep) = &mut global_report {
        rep.fitted = elastic.fitted;
        // with a rig the placement was kept before the elastic fit
        if rep.articulated.is_none() {
            rep.kept = best.index;
        }
        rep.limb_turns = best.turns.clone();
    }
    finish(
        &elastic,
        best,
        global_report,
        template_topology,
        scan,
        times,
        t_start,
    )
}

/// The checks a template and the options must pass before any work.
fn check_inputs(template: &Mesh, opts: &ConformOptions) -> Result<(), ConformError> {
    opts.validate()?;
    if template.triangles.is_empty() {
        return Err(ConformError::Template(
            "has no triangles (a template must be a triangle mesh)".into(),
        ));
    }
    template
        .validate("template")
        .map_err(ConformError::TemplateMesh)?;
    correspond::check_extent(template, "template").map_err(ConformError::TemplateMesh)?;
    if template.vertices.len() < 4 || !(template.area() > 0.0) {
        return Err(ConformError::Template(format!(
            "{} vertices and an area of {:e}: a template needs at least 4 vertices and a surface",
            template.vertices.len(),
            template.area()
        )));
    }
    Ok(opts.check_groups(template)?)
}

/// What every hypothesis's elastic fit shares.
struct Elastic<'a> {
    template: &'a Mesh,
    surface: &'a ScanSurface,
    pairs: Option<&'a Pairs>,
    opts: &'a ConformOptions,
    /// how many hypotheses go through the fit
    fitted: usize,
    cancel: &'a std::sync::atomic::AtomicBool,
}

impl<'a> Elastic<'a> {
    fn cancelled(&self) -> Result<(), ConformError> {
        if self.cancel.load(std::sync::atomic::Ordering::Relaxed) {
            Err(ConformError::Cancelled)
        } else {
            Ok(())
        }
    }

    /// A fitted hypothesis's score (lower is better): its distortion and distance to the
    /// scan; 0 when there is only one.
    fn score(&self, fit: &fit::Fit, x: &[V3], tris: &[[u32; 3]]) -> f64 {
        if self.fitted > 1 {
            let (m, _) = match_all(self.surface, x, tris, &fit.limits);
            let distance = MatchSummary::of(&m).mean_distance / fit.diag;
            fit.baseline.measure(x).edge_length.std + 10.0 * distance
        } else {
            0.0
        }
    }

    /// Every hypothesis fitted on the decimated `level`, the best one's fit then carried
    /// on at full resolution.
    fn on_level(
        &self,
        level: &Decimated,
        hypotheses: Vec<Hypothesis>,
        times: &mut StageTimes,
        progress: &mut OnIteration,
    ) -> Result<FittedHypothesis<'a>, ConformError> {
        let (opts, surface, pairs) = (self.opts, self.surface, self.pairs);
        let cpairs = pairs.map(|p| p.on_level(level));
        // (score, index, hypothesis, level positions, level fit, level reports)
        type OnLevel<'l> = (
            f64,
            usize,
            Hypothesis,
            Vec<V3>,
            fit::Fit<'l>,
            Vec<IterationReport>,
        );
        let mut coarse_best: Option<OnLevel> = None;
        for (k, h) in hypotheses.into_iter().enumerate() {
            let mut cx: Vec<V3> = level.kept.iter().map(|&i| h.x[i as usize]).collect();
            let mut cfit = fit::Fit::new(&level.mesh, &cx, &h.sim, cpairs.as_ref(), opts);
            // the decimated level's iterations are cheap: all of them run
            let coarse_opts = ConformOptions {
                tolerance: opts.tolerance * 1e-3,
                ..opts.clone()
            };
            times.coarse += cfit.coarse(&mut cx, surface, pairs.is_some(), opts);
            self.cancelled()?;
            let (mut reports, _) =
                cfit.iterate(&mut cx, surface, &coarse_opts, times, progress, self.cancel);
            self.cancelled()?;
            // the coarse level's last distance (the full level's first match is of
            // another mesh)
            let t = Instant::now();
            let (m, _) = match_all(surface, &cx, &level.mesh.triangles, &cfit.limits);
            times.correspond += t.elapsed().as_secs_f64();
            if let Some(r) = reports.last_mut() {
                r.mean_distance = MatchSummary::of(&m).mean_distance;
                r.mean_distance_relative = r.mean_distance / cfit.diag;
            }
            let score = self.score(&cfit, &cx, &level.mesh.triangles);
            if coarse_best.as_ref().is_none_or(|b| score < b.0) {
                coarse_best = Some((score, k, h, cx, cfit, reports));
            }
        }
        let (score, k, h, cx, cfit, mut reports) = coarse_best.expect("at least one hypothesis");
        let mut fit = fit::Fit::new(self.template, &h.x, &h.sim, pairs, opts);
        let mut x = fit.take_over(&cfit, &cx, level);
        let eps = cfit.final_epsilon(opts);
        // a change of shape (the fit relaxed) needs the full resolution's detail
        // (corners, edges) longer than a change of posture
        let iterations = if eps < opts.epsilon_end {
            opts.multires_iterations.max(opts.max_iterations)
        } else {
            opts.multires_iterations
        };
        let fine = ConformOptions {
            max_iterations: iterations,
            epsilon_start: eps,
            epsilon_end: eps,
            epsilon_steps: 1,
            max_distance_start: opts.max_distance,
            ..opts.clone()
        };
        let done = reports.len();
        let mut renumbered = |r: &IterationReport| {
            let mut r = r.clone();
            r.iteration += done;
            progress(&r)
        };
        let (more, converged) =
            fit.iterate(&mut x, surface, &fine, times, &mut renumbered, self.cancel);
        reports.extend(more.into_iter().map(|mut r| {
            r.iteration += done;
            r
        }));
        Ok(FittedHypothesis {
            score,
            x,
            fit,
            reports,
            converged,
            index: k,
            turns: h.turns,
        })
    }

    /// Every hypothesis fitted at full resolution; the best kept.
    fn at_full_resolution(
        &self,
        hypotheses: Vec<Hypothesis>,
        times: &mut StageTimes,
        progress: &mut OnIteration,
    ) -> Result<FittedHypothesis<'a>, ConformError> {
        let (opts, surface) = (self.opts, self.surface);
        let mut best: Option<FittedHypothesis> = None;
        for (k, Hypothesis { x: x0, sim, turns }) in hypotheses.into_iter().enumerate() {
            let mut x = x0;
            let mut fit = fit::Fit::new(self.template, &x, &sim, self.pairs, opts);
            self.cancelled()?;
            times.coarse += fit.coarse(&mut x, surface, self.pairs.is_some(), opts);
            self.cancelled()?;
            let (reports, converged) =
                fit.iterate(&mut x, surface, opts, times, progress, self.cancel);
            let score = self.score(&fit, &x, &self.template.triangles);
            if best.as_ref().is_none_or(|b| score < b.score) {
                best = Some(FittedHypothesis {
                    score,
                    x,
                    fit,
                    reports,
                    converged,
                    index: k,
                    turns,
                });
            }
        }
        Ok(best.expect("at least one hypothesis"))
    }
}

/// The conformed mesh and its report from the kept hypothesis's fit: its distance to
/// the scan, landmark residual, distortion, folds and the template's watertightness.
fn finish(
    elastic: &Elastic,
    best: FittedHypothesis,
    global: GlobalReport,
    template_topology: topology::TopologyReport,
    scan: &Mesh,
    mut times: StageTimes,
    t_start: Instant,
) -> Result<Conformed, ConformError> {
    let (template, surface, opts) = (elastic.template, elastic.surface, elastic.opts);
    let n = template.vertices.len();
    let FittedHypothesis {
        mut x,
        mut fit,
        mut reports,
        converged,
        ..
    } = best;
    let diag = fit.diag;
    let enclosed = topology::enclosed_parts(&template.vertices, &template.triangles);
    place_enclosed(template, &enclosed, &mut x);
    let fold_repair = (opts.repair_folds && opts.method == Method::Default).then(|| {
        let t = Instant::now();
        let r = fit.repair_folds(&mut x);
        times.fold_repair = t.elapsed().as_secs_f64();
        r
    });

    // The distance of the final result to the scan.
    let t = Instant::now();
    let (final_matches, normals) = match_all(surface, &x, &template.triangles, &fit.limits);
    let fin = MatchSummary::of(&final_matches);
    times.correspond += t.elapsed().as_secs_f64();
    if let Some(r) = reports.last_mut() {
        r.mean_distance = fin.mean_distance;
        r.mean_distance_relative = fin.mean_distance / diag;
    }
    let mut mesh = Mesh::new(x, template.triangles.clone());
    mesh.groups = template.groups.clone();
    mesh.normals = Some(normals);
    let landmark_rms = elastic.pairs.filter(|p| !p.names.is_empty()).map(|p| {
        let s: f64 = p
            .vertex
            .iter()
            .zip(&p.target)
            .map(|(&v, t)| (mesh.vertices[v as usize] - t).norm_squared())
            .sum();
        (s / p.names.len() as f64).sqrt()
    });
    times.total = t_start.elapsed().as_secs_f64();
    if let Some(i) = mesh.first_non_finite() {
        return Err(ConformError::Numerical(format!(
            "vertex {i} of the result is not a finite point"
        )));
    }
    let final_variation = fit.baseline.measure(&mesh.vertices);
    let placement = placement_warning(&global);
    let report = ConformReport {
        method: opts.method,
        template_vertices: n,
        template_triangles: template.triangles.len(),
        scan_points: scan.vertices.len(),
        scan_is_mesh: !scan.triangles.is_empty(),
        global,
        converged,
        final_variation,
        distortion_warning: distortion_warning(&final_variation),
        placement_warning: placement,
        folded_triangles: quality::folded_triangles(&mesh),
        fold_repair,
        enclosed_vertices: enclosed.iter().map(Vec::len).sum(),
        matched: fin.matched,
        filled: n - fin.matched,
        mean_distance: fin.mean_distance,
        mean_distance_relative: fin.mean_distance / diag,
        landmark_rms,
        watertight_template: template_topology.watertight,
        watertight_result: template_topology.moved(&mesh).watertight,
        iterations: reports,
        seconds: times,
    };
    Ok(Conformed { mesh, report })
}

/// Each part the template holds inside itself (`topology::enclosed_parts`) moved as a
/// whole by the similarity that takes what surrounds it (the other vertices within
/// twice the part's radius of its centre, at rest, or its 64 nearest) where the fit put
/// them. No camera sees such a part, and the springs do not join it to the rest: fitted
/// on its own it was pulled inside out onto the surface around it (a body model's
/// eyeball onto the eyelids).
fn place_enclosed(template: &Mesh, parts: &[Vec<u32>], x: &mut [V3]) {
    if parts.is_empty() {
        return;
    }
    let rest = &template.vertices;
    let mut inside = vec![false; rest.len()];
    for &i in parts.iter().flatten() {
        inside[i as usize] = true;
    }
    let around: Vec<usize> = (0..rest.len()).filter(|&i| !inside[i]).collect();
    if around.len() < 3 {
        return;
    }
    let arr: Vec<[f64; 3]> = around.iter().map(|&i| rest[i].into()).collect();
    let tree: kiddo::ImmutableKdTree<f64, 3> = kiddo::ImmutableKdTree::new_from_slice(&arr);
    for part in parts {
        let c = part.iter().map(|&i| rest[i as usize]).sum::<V3>() / part.len() as f64;
        let r = part
            .iter()
            .map(|&i| (rest[i as usize] - c).norm())
            .fold(0.0, f64::max);
        let reach = 2.0 * r;
        let mut near: Vec<usize> = tree
            .within_unsorted::<kiddo::SquaredEuclidean>(&c.into(), reach * reach)
            .iter()
            .map(|m| around[m.item as usize])
            .collect();
        if near.len() < 64 {
            near = tree
                .nearest_n::<kiddo::SquaredEuclidean>(
                    &c.into(),
                    std::num::NonZero::new(64).unwrap(),
                )
                .iter()
                .map(|m| around[m.item as usize])
                .collect();
        }
        let src: Vec<V3> = near.iter().map(|&i| rest[i]).collect();
        let dst: Vec<V3> = near.iter().map(|&i| x[i]).collect();
        let sim = fit_similarity(&src, &dst, None, true);
        for &i in part {
            x[i as usize] = sim.apply(&rest[i as usize]);
        }
    }
}

/// Section 2.1: the template mapped onto the scan by the landmark RBF, or (without
/// landmarks) by the automatic alignment; with the similarity that best explains the
/// mapping (the springs' frame) and what the report says of it.
fn global_mapping(
    template: &Mesh,
    rig: Option<&TemplateRig>,
    surface: &ScanSurface,
    pairs: Option<&Pairs>,
    opts: &ConformOptions,
    times: &mut StageTimes,
) -> Result<(Vec<Hypothesis>, GlobalReport), ConformError> {
    Ok(match pairs {
        Some(p) => {
            let (h, articulated) = landmark_hypothesis(template, rig, surface, p, opts, times)?;
            (
                vec![h],
                GlobalReport::LandmarkRbf {
                    pairs: p.names.clone(),
                    unpaired: p.unpaired.clone(),
                    articulated,
                },
            )
        }
        None => {
            let (h, rep) = automatic_hypotheses(template, rig, surface, opts, times);
            (h, GlobalReport::Automatic(rep))
        }
    })
}

/// Without landmarks: the automatic alignment's placement (and its runner-up, when the
/// residuals cannot tell them apart), each with the limb search's turns; with a rig
/// (default method) the rig fitted from each, guided by the limb search's result, and
/// only the best by its distances both ways kept.
fn automatic_hypotheses(
    template: &Mesh,
    rig: Option<&TemplateRig>,
    surface: &ScanSurface,
    opts: &ConformOptions,
    times: &mut StageTimes,
) -> (Vec<Hypothesis>, align::AlignReport) {
    let t = Instant::now();
    let samples = template.surface_samples(ALIGN_TEMPLATE_SAMPLES);
    let (sim, runner_up, mut rep) = align::auto_align(&samples, surface, &opts.align);
    times.align = t.elapsed().as_secs_f64();
    let t = Instant::now();
    // the paper's method has no distortion-aware springs to judge by
    let default_method = opts.method == Method::Default;
    let found = if default_method && opts.align.limbs > 0 {
        let nb = topology::vertex_neighbours(template.vertices.len(), &template.triangles);
        limbs::find(&template.vertices, &nb, opts.align.limbs)
    } else {
        Vec::new()
    };
    let placed = |s: &crate::mesh::transform::Similarity| -> Hypothesis {
        let mut x: Vec<V3> = template.vertices.iter().map(|v| s.apply(v)).collect();
        let turns = limbs::search(
            &mut x,
            &template.triangles,
            &found,
            surface,
            &limbs::SearchSettings::default(),
        );
        Hypothesis { x, sim: *s, turns }
    };
    // the placements are searched (and their rigs fitted, below) side by side: each
    // search's and fit's own parallel loops leave cores idle
    let h = match (runner_up, default_method) {
        (Some(r), true) => {
            let (a, b) = rayon::join(|| placed(&sim), || placed(&r));
            vec![a, b]
        }
        _ => vec![placed(&sim)],
    };
    rep.limbs_found = found.len();
    times.limbs = t.elapsed().as_secs_f64();
    let t = Instant::now();
    // a template without a rig (a user's own mesh) gets one from its limbs (a station
    // finds it once, at start-up)
    let Some(rig) = rig_or_automatic(rig, template, opts) else {
        return (h, rep);
    };
    let rig = rig.as_ref();
    // the rig fitted to the limb search's result first, then to the scan: from the rest
    // pose instead it ended the same on six of eight generic cases and worse on the large
    // postures (a leg left on its neighbour), and fitting both cost twice the time
    let settings = articulated::ArticulatedSettings::default();
    let fit_rig = articulated::FitRig::new(rig, template, &settings);
    let fits: Vec<articulated::Articulated> = h
        .par_iter()
        .map(|guess| {
            articulated::fit(
                template,
                &fit_rig,
                surface,
                &guess.sim,
                Some(&guess.x),
                &[],
                &settings,
            )
        })
        .collect();
    rep.articulated = Some(articulated::ArticulatedReport::new(&fit_rig, &fits));
    // the rig fit's distances both ways tell the placements apart better than the
    // elastic fit's stretch (which kept the cow in the large posture facing backwards):
    // only the best goes on
    let (kept, best) = fits
        .into_iter()
        .zip(h)
        .enumerate()
        .min_by(|a, b| a.1.0.score().total_cmp(&b.1.0.score()))
        .expect("at least one placement");
    rep.kept = kept;
    let (f, guess) = best;
    // where the limb search's rigid turns explain the scan about as well, its start is
    // kept: the rig's bends then cost accuracy (a cat's legs, one person onto another)
    let guess_score = articulated::score_vertices(template, &guess.x, surface, &settings);
    let keep_guess = guess_score <= f.score() * RIG_START_MARGIN;
    if let Some(a) = rep.articulated.as_mut() {
        a.limb_search_score = Some(guess_score);
        a.kept_limb_search = keep_guess;
    }
    times.rig = t.elapsed().as_secs_f64();
    if keep_guess {
        return (vec![guess], rep);
    }
    let h = vec![Hypothesis {
        x: f.vertices,
        sim: f.placement,
        turns: guess.turns,
    }];
    (h, rep)
}

/// The rig the default method fits: the template's own, else an automatic one
/// ([`automatic_rig`]); `None` for the paper's method or when none can be found.
fn rig_or_automatic<'a>(
    rig: Option<&'a TemplateRig>,
    template: &Mesh,
    opts: &ConformOptions,
) -> Option<std::borrow::Cow<'a, TemplateRig>> {
    if opts.method != Method::Default {
        return None;
    }
    match rig {
        Some(r) => Some(std::borrow::Cow::Borrowed(r)),
        None => automatic_rig(template, opts).map(std::borrow::Cow::Owned),
    }
}

/// The rig a template without one is fitted with when `opts` ask for it
/// (`align.automatic_rig`, limbs searched): found on its limbs; `None` when the rig
/// finder cannot make one (the fit then runs without).
pub fn automatic_rig(template: &Mesh, opts: &ConformOptions) -> Option<TemplateRig> {
    if !opts.align.automatic_rig || opts.align.limbs == 0 {
        return None;
    }
    let settings = crate::template::rig::AutoRigSettings {
        limbs: opts.align.limbs,
        ..Default::default()
    };
    TemplateRig::automatic(template, &settings).ok()
}

/// The rig's fit starts the elastic fit only when it scores (distances both ways) this
/// many times better than the limb search's start: chosen on the development part of
/// the harder set, where the limb search's start was the better one at ratios up to 1.18
/// (koala, cat) and the rig's at 1.25 (the dense uneven man).
const RIG_START_MARGIN: f64 = 1.2;

/// The rig's fit alone, without landmarks and without the elastic fit: the kept
/// hypothesis's template vertices and the alignment's report (every hypothesis's
/// figures). What a development set scores to see the rig's share of a result.
pub fn rig_fit_only(
    template: &Mesh,
    rig: &TemplateRig,
    scan: &Mesh,
    opts: &ConformOptions,
) -> Result<(Vec<Vec<V3>>, align::AlignReport), ConformError> {
    let surface = ScanSurface::new(scan)?;
    let (h, rep) = automatic_hypotheses(
        template,
        Some(rig),
        &surface,
        opts,
        &mut StageTimes::default(),
    );
    Ok((h.into_iter().map(|x| x.x).collect(), rep))
}

/// Points spread over the template's surface for the automatic alignment: about twice
/// the scan samples its ICP refines on.
const ALIGN_TEMPLATE_SAMPLES: usize = 8000;

/// The template mapped by the landmark RBF of `p`, with the similarity that best explains
/// the mapping (the springs' frame).
fn rbf_hypothesis(template: &Mesh, p: &Pairs, smoothing: f64) -> Result<Hypothesis, ConformError> {
    let src: Vec<V3> = p
        .vertex
        .iter()
        .map(|&i| template.vertices[i as usize])
        .collect();
    let map = rbf::fit(&p.names, &src, &p.target, smoothing)?;
    let mapped: Vec<V3> = template.vertices.par_iter().map(|v| map.apply(v)).collect();
    let sim = fit_similarity(&template.vertices, &mapped, None, true);
    Ok(Hypothesis {
        x: mapped,
        sim,
        turns: Vec::new(),
    })
}

/// With landmarks: the template mapped by the landmark RBF; with a rig (the template's
/// own, else an automatic one; default method), the rig then fitted to the scan with
/// the marks held (the RBF's placing as its guide), and what the marks still miss taken
/// up by an RBF of their residuals. The landmark RBF alone bends the template's space
/// as a whole: arms raised from a T-pose drag the shoulders and the head with them.
fn landmark_hypothesis(
    template: &Mesh,
    rig: Option<&TemplateRig>,
    surface: &ScanSurface,
    p: &Pairs,
    opts: &ConformOptions,
    times: &mut StageTimes,
) -> Result<(Hypothesis, Option<articulated::ArticulatedReport>), ConformError> {
    let rbf_start = rbf_hypothesis(template, p, opts.rbf_smoothing)?;
    let t = Instant::now();
    let Some(rig) = rig_or_automatic(rig, template, opts) else {
        return Ok((rbf_start, None));
    };
    let rig = rig.as_ref();
    let settings = articulated::ArticulatedSettings::default();
    let fit_rig = articulated::FitRig::new(rig, template, &settings);
    let marks: Vec<(usize, V3)> = p
        .vertex
        .iter()
        .zip(&p.target)
        .map(|(&v, &t)| (v as usize, t))
        .collect();
    let f = articulated::fit(
        template,
        &fit_rig,
        surface,
        &rbf_start.sim,
        Some(&rbf_start.x),
        &marks,
        &settings,
    );
    let report = articulated::ArticulatedReport::new(&fit_rig, std::slice::from_ref(&f));
    times.rig = t.elapsed().as_secs_f64();
    let src: Vec<V3> = p.vertex.iter().map(|&i| f.vertices[i as usize]).collect();
    // the marks' posed vertices fall where the RBF cannot interpolate (two on one
    // place): the RBF's own placing, which the same marks allowed, goes on instead
    let Ok(map) = rbf::fit(&p.names, &src, &p.target, opts.rbf_smoothing) else {
        return Ok((rbf_start, Some(report)));
    };
    let x: Vec<V3> = f.vertices.par_iter().map(|v| map.apply(v)).collect();
    // the springs' frame as the RBF route's (the rig fit's own placement: a better
    // mean, more folds; docs/experiments.md)
    let sim = fit_similarity(&template.vertices, &x, None, true);
    Ok((
        Hypothesis {
            x,
            sim,
            turns: Vec::new(),
        },
        Some(report),
    ))
}

/// One hypothesis carried through the elastic fit, with its score (lower is better).
struct FittedHypothesis<'a> {
    score: f64,
    x: Vec<V3>,
    fit: fit::Fit<'a>,
    reports: Vec<IterationReport>,
    converged: bool,
    index: usize,
    turns: Vec<f64>,
}

/// A starting placement of the template and the similarity behind it.
struct Hypothesis {
    x: Vec<V3>,
    sim: crate::mesh::transform::Similarity,
    /// limbs the articulation search turned, degrees
    turns: Vec<f64>,
}

/// Every vertex's match (None: missing data), and the vertex normals used.
fn match_all(
    surface: &ScanSurface,
    x: &[V3],
    tris: &[[u32; 3]],
    limits: &MatchLimits,
) -> (Vec<Option<correspond::Match>>, Vec<V3>) {
    let normals = vertex_normals(x, tris);
    let matches = x
        .par_iter()
        .zip(&normals)
        .map(|(p, nv)| surface.query(p, nv, limits))
        .collect();
    (matches, normals)
}

#[derive(Debug, Clone, Copy)]
struct MatchSummary {
    matched: usize,
    mean_distance: f64,
}

impl MatchSummary {
    fn of(m: &[Option<correspond::Match>]) -> Self {
        let (s, c) = m
            .iter()
            .flatten()
            .fold((0.0, 0usize), |(s, c), m| (s + m.distance, c + 1));
        MatchSummary {
            matched: c,
            mean_distance: if c > 0 { s / c as f64 } else { f64::NAN },
        }
    }
}
