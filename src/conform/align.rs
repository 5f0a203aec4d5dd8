//! Automatic global alignment when the scan has no landmarks (an unattended station):
//! a similarity from centroids and principal axes, the axis-sign ambiguity resolved by
//! trying every proper candidate, each refined by trimmed ICP; the best fit wins. Up-axis
//! hints, when given, rule out candidates that turn the template upside down; front hints
//! (the crate's head end, the booth's front camera) rule out those that face it away.

use super::correspond::ScanSurface;
use crate::mesh::V3;
use crate::mesh::transform::{Similarity, fit_similarity};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Rotation3};
use rayon::prelude::*;

/// Options of the automatic alignment.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlignOptions {
    /// the template's up axis, in template coordinates
    pub template_up: Option<[f64; 3]>,
    /// the up axis of the scan (the rig's up), in scan coordinates
    pub scan_up: Option<[f64; 3]>,
    /// the way the template faces (its head or face), in template coordinates
    pub template_front: Option<[f64; 3]>,
    /// the way the subject faces on the rig (towards the crate's head gate, the booth's
    /// front camera), in scan coordinates
    pub scan_front: Option<[f64; 3]>,
    /// how far, in degrees, the subject may face from `scan_front` (about the up axis when
    /// it is known); 90 only settles front against back
    pub front_within_deg: f64,
    /// ICP iterations per candidate
    pub icp_iterations: usize,
    /// share of scan samples kept by the trimmed ICP (0.5 - 1)
    pub trim: f64,
    /// geodesic extremities of the template tried as limbs by the articulation search
    /// after the rigid alignment (`conform::limbs`); 0 = no search
    pub limbs: usize,
    /// a template without a rig gets an automatic one (`TemplateRig::automatic`: its
    /// limbs at geodesic extremities) fitted after the limb search; false fits none
    pub automatic_rig: bool,
}

impl Default for AlignOptions {
    fn default() -> Self {
        AlignOptions {
            template_up: None,
            scan_up: None,
            template_front: None,
            scan_front: None,
            front_within_deg: 90.0,
            icp_iterations: 40,
            trim: 0.85,
            limbs: 10,
            automatic_rig: true,
        }
    }
}

/// Outcome of the automatic alignment.
#[derive(Debug, Clone, serde::Serialize)]
pub struct AlignReport {
    pub candidates_tried: usize,
    /// trimmed RMS distance of the winner, relative to the scan's diagonal
    pub residual: f64,
    /// the same for the runner-up: close figures mean the choice was ambiguous
    pub runner_up_residual: Option<f64>,
    pub scale: f64,
    /// hypotheses carried through the whole elastic fit (more than one when the
    /// residuals could not tell them apart), and which of them was kept (0 = the best
    /// by residual)
    pub fitted: usize,
    pub kept: usize,
    /// template limbs found for the articulation search, and the turns (degrees) it made
    /// to the kept hypothesis's limbs
    pub limbs_found: usize,
    pub limb_turns: Vec<f64>,
    /// the template's rig fitted before the elastic fit, when it has one
    #[serde(skip_serializing_if = "Option::is_none")]
    pub articulated: Option<super::articulated::ArticulatedReport>,
}

/// Residual ratio under which the runner-up alignment is fitted too: near-symmetric
/// subjects (a pig seen from above, a body in a T pose) leave the rigid residuals of a
/// turned-round template close, and only the elastic fit's distortion tells them apart.
pub const AMBIGUOUS_RESIDUAL_RATIO: f64 = 1.25;

fn principal_frame(p: &[V3]) -> (V3, Matrix3<f64>, f64) {
    let c = p.iter().sum::<V3>() / p.len() as f64;
    let cov = p
        .iter()
        .fold(Matrix3::zeros(), |m, q| m + (q - c) * (q - c).transpose())
        / p.len() as f64;
    let e = cov.symmetric_eigen();
    // sort axes by decreasing variance
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|&a, &b| e.eigenvalues[b].total_cmp(&e.eigenvalues[a]));
    let mut m = Matrix3::from_columns(&[
        e.eigenvectors.column(idx[0]),
        e.eigenvectors.column(idx[1]),
        e.eigenvectors.column(idx[2]),
    ]);
    if m.determinant() < 0.0 {
        m.set_column(2, &(-m.column(2)));
    }
    (c, m, e.eigenvalues.sum().max(0.0).sqrt())
}

/// Finds the similarity taking the template onto the scan; with it, the runner-up when
/// its residual is within [`AMBIGUOUS_RESIDUAL_RATIO`] of the best (both refined), for
/// the caller to fit both.
///
/// - `template`: points spread evenly over the template's surface (`Mesh::surface_samples`):
///   its vertices would weigh a densely triangulated part more than the rest, and the
///   principal axes and scale would follow the triangulation rather than the shape
pub fn auto_align(
    template: &[V3],
    scan: &ScanSurface,
    opts: &AlignOptions,
) -> (Similarity, Option<Similarity>, AlignReport) {
    let subsample = |k: usize| -> Vec<V3> {
        let step = (scan.points.len() / k).max(1);
        scan.points.iter().step_by(step).copied().collect()
    };
    // candidates are told apart on a light sample; the winner is refined on a denser one
    let samples = subsample(1000);
    let fine = subsample(4000);
    let arr: Vec<[f64; 3]> = template.iter().map(|p| [p.x, p.y, p.z]).collect();
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);

    let (ct, ft, st) = principal_frame(template);
    let (cs, fs, ss) = principal_frame(&samples);
    let scale0 = ss / st;
    let up = match (opts.template_up, opts.scan_up) {
        (Some(a), Some(b)) => Some((V3::from(a).normalize(), V3::from(b).normalize())),
        _ => None,
    };
    let front = match (opts.template_front, opts.scan_front) {
        (Some(a), Some(b)) => Some((V3::from(a).normalize(), V3::from(b).normalize())),
        _ => None,
    };
    // the front is compared about the up axis when it is known (a subject leaning or
    // nodding still faces the same way)
    let level = |v: V3| match up {
        Some((_, su)) => v - su * v.dot(&su),
        None => v,
    };
    let faces_front = |r: &Rotation3<f64>| {
        front.is_none_or(|(tf, sf)| {
            let (a, b) = (level(r * tf), level(sf));
            let cos = a.dot(&b) / (a.norm() * b.norm());
            // a front along the up axis says nothing about the heading
            !cos.is_finite() || cos >= opts.front_within_deg.to_radians().cos() - 1e-9
        })
    };
    let quick = AlignOptions {
        icp_iterations: opts.icp_iterations / 2,
        ..opts.clone()
    };
    let signs = [[1., 1., 1.], [1., -1., -1.], [-1., 1., -1.], [-1., -1., 1.]];
    let candidates: Vec<Rotation3<f64>> = signs
        .iter()
        .map(|s| {
            Rotation3::from_matrix_unchecked(
                fs * Matrix3::from_diagonal(&V3::from(*s)) * ft.transpose(),
            )
        })
        .collect();
    let upright = |r: &&Rotation3<f64>| up.is_none_or(|(tu, su)| (*r * tu).dot(&su) >= 0.0);
    // hints exclude everything only if they contradict the data: the front goes first,
    // then the up axis
    let mut kept: Vec<&Rotation3<f64>> = candidates
        .iter()
        .filter(upright)
        .filter(|r| faces_front(r))
        .collect();
    if kept.is_empty() {
        kept = candidates.iter().filter(upright).collect();
    }
    if kept.is_empty() {
        kept = candidates.iter().collect();
    }
    let mut results: Vec<(f64, Similarity)> = kept
        .into_par_iter()
        .map(|&r| {
            let init = Similarity {
                scale: scale0,
                rotation: r,
                translation: cs - r * ct * scale0,
            };
            icp(&tree, template, &samples, init, &quick, scan.diagonal)
        })
        .collect();
    results.sort_by(|a, b| a.0.total_cmp(&b.0));
    let ambiguous = results
        .get(1)
        .is_some_and(|r| r.0 <= results[0].0 * AMBIGUOUS_RESIDUAL_RATIO);
    results[0] = icp(&tree, template, &fine, results[0].1, opts, scan.diagonal);
    let runner_up = ambiguous.then(|| {
        results[1] = icp(&tree, template, &fine, results[1].1, opts, scan.diagonal);
        results[1].1
    });
    let report = AlignReport {
        candidates_tried: results.len(),
        residual: results[0].0,
        runner_up_residual: results.get(1).map(|r| r.0),
        scale: results[0].1.scale,
        fitted: 1,
        kept: 0,
        limbs_found: 0,
        limb_turns: Vec::new(),
        articulated: None,
    };
    (results[0].1, runner_up, report)
}

/// Trimmed similarity ICP from scan samples to template vertices (scan to template, since
/// every scan point has a counterpart on a whole template but not the reverse).
fn icp(
    tree: &ImmutableKdTree<f64, 3>,
    template: &[V3],
    samples: &[V3],
    mut t: Similarity,
    opts: &AlignOptions,
    diag: f64,
) -> (f64, Similarity) {
    let mut residual = f64::INFINITY;
    for _ in 0..opts.icp_iterations.max(1) {
        let inv = t.inverse();
        let mut pairs: Vec<(f64, usize, usize)> = samples
            .par_iter()
            .enumerate()
            .map(|(i, s)| {
                let q = inv.apply(s);
                let nn = tree.nearest_one::<SquaredEuclidean>(&[q.x, q.y, q.z]);
                (nn.distance, i, nn.item as usize)
            })
            .collect();
        // the trimmed share: the nearest pairs, in no particular order
        let keep = ((pairs.len() as f64) * opts.trim.clamp(0.3, 1.0)) as usize;
        if keep > 0 && keep < pairs.len() {
            pairs.select_nth_unstable_by(keep - 1, |a, b| a.0.total_cmp(&b.0));
        }
        pairs.truncate(keep);
        let src: Vec<V3> = pairs.iter().map(|p| template[p.2]).collect();
        let dst: Vec<V3> = pairs.iter().map(|p| samples[p.1]).collect();
        let next = fit_similarity(&src, &dst, None, true);
        let rms = (pairs.iter().map(|p| p.0).sum::<f64>() / pairs.len().max(1) as f64).sqrt()
            * t.scale
            / diag;
        let moved = (next.translation - t.translation).norm() / diag
            + (next.rotation.matrix() - t.rotation.matrix()).norm();
        residual = rms;
        t = next;
        if moved < 1e-7 {
            break;
        }
    }
    (residual, t)
}
