//! The elastic fit after the global mapping: the springs' set-up (rest shape, Laplacian,
//! landmark terms), the optional coarse deformation-graph stage, and the iterations of
//! correspondence, grass fire and elastic solve, for either method.

use super::correspond::{MatchLimits, ScanSurface};
use super::{
    CoarseStage, ConformOptions, HoleSprings, IterationReport, Method, Pairs, RestShape,
    StageTimes, coarse, fill, match_all, solve,
};
use crate::mesh::decimate::Decimated;
use crate::mesh::transform::Similarity;
use crate::mesh::{Mesh, V3, quality, topology};
use nalgebra::{Matrix3, UnitQuaternion};
use rayon::prelude::*;
use std::time::Instant;

/// Everything the iterations share, and the per-vertex rotations and scales they carry.
pub(super) struct Fit<'a> {
    pub tris: &'a [[u32; 3]],
    pub rest: Vec<V3>,
    pub lap: solve::Laplacian,
    /// the rest shape's bounding-box diagonal: distances in options are relative to it
    pub diag: f64,
    pub neighbours: Vec<Vec<u32>>,
    pub baseline: quality::VariationBaseline,
    pub landmark_weight: Vec<f64>,
    pub landmark_target: Vec<V3>,
    rest_norms: Vec<f64>,
    /// the patch each vertex's rotation is fitted over
    support: solve::RotationSupport,
    /// #V data weights by the surface each vertex stands for (a third of its triangles'
    /// area, against the mean): the data term then weighs a part by its area, not by how
    /// finely it is triangulated, as the cotangent springs do
    area_weight: Vec<f64>,
    rot: Vec<UnitQuaternion<f64>>,
    local_scale: Vec<f64>,
    pub limits: MatchLimits,
    /// the springs' epsilon once relaxed below epsilon_end (see
    /// `ConformOptions::relax_epsilon`); carried from a coarse level to the full one
    relaxed: Option<f64>,
}

impl<'a> Fit<'a> {
    /// The springs' rest shape is the template under the global similarity (or, for the
    /// paper's reading, the mapped mesh `x`), so that a scan in other units or another
    /// place does not load the springs.
    pub fn new(
        template: &'a Mesh,
        x: &[V3],
        global: &Similarity,
        pairs: Option<&Pairs>,
        opts: &ConformOptions,
    ) -> Fit<'a> {
        let n = template.vertices.len();
        let rest: Vec<V3> = match opts.rest {
            RestShape::Template => template.vertices.iter().map(|v| global.apply(v)).collect(),
            RestShape::Mapped => x.to_vec(),
        };
        let diag = Mesh::new(rest.clone(), template.triangles.clone()).diagonal();
        let mut stiff = vec![1.0f64; n];
        for (g, &k) in &opts.stiffness {
            for &v in &template.groups[g] {
                stiff[v as usize] = stiff[v as usize].max(k);
            }
        }
        let default_method = opts.method == Method::Default;
        // a fragmented template (a scan triangulated per pod) is held together by
        // springs across its gaps, up to three typical edges long
        let bridges = if default_method {
            topology::bridges(
                &rest,
                &template.triangles,
                3.0 * median_edge(&rest, template),
            )
        } else {
            Vec::new()
        };
        let lap = solve::laplacian(&rest, &template.triangles, default_method, &stiff, &bridges);
        // Springs are scaled so that epsilon means the same for either weighting.
        let mean_diag = lap.diag.iter().sum::<f64>() / n as f64;
        let lap = solve::Laplacian {
            weights: lap.weights.map(|w| w / mean_diag),
            diag: lap.diag.iter().map(|d| d / mean_diag).collect(),
        };
        let mut landmark_weight = vec![0.0; n];
        let mut landmark_target = vec![V3::zeros(); n];
        if let (Some(p), true) = (pairs, default_method) {
            for (&v, t) in p.vertex.iter().zip(&p.target) {
                landmark_weight[v as usize] += opts.landmark_weight;
                landmark_target[v as usize] += t * opts.landmark_weight;
            }
            for v in 0..n {
                if landmark_weight[v] > 0.0 {
                    landmark_target[v] /= landmark_weight[v];
                }
            }
        }
        let support = solve::RotationSupport::new(&lap, &rest, opts.rotation_rings);
        let rest_norms = solve::smoothed_rest_norms(&lap, &rest, &support);
        let area_weight = if default_method {
            vertex_area_weights(&rest, &template.triangles)
        } else {
            vec![1.0; n]
        };
        Fit {
            area_weight,
            tris: &template.triangles,
            neighbours: with_bridges(
                topology::vertex_neighbours(n, &template.triangles),
                &bridges,
            ),
            baseline: quality::VariationBaseline::new(&template.vertices, &template.triangles),
            limits: MatchLimits {
                max_distance: opts.max_distance * diag,
                min_normal_cos: opts.max_normal_angle.to_radians().cos(),
            },
            rest,
            lap,
            diag,
            landmark_weight,
            landmark_target,
            rest_norms,
            support,
            rot: vec![UnitQuaternion::identity(); n],
            local_scale: vec![1.0; n],
            relaxed: None,
        }
    }

    /// Takes over a fit made on the decimated template `level`: every vertex follows its
    /// nearest kept vertex rigidly (that vertex's rotation and scale applied to the rest
    /// offset between them), and inherits its rotation, scale and relaxation. Returns the
    /// full-resolution positions. (Blending the kept vertices around each vertex instead
    /// was measured to change nothing on the development set.)
    pub fn take_over(&mut self, coarse: &Fit, cx: &[V3], level: &Decimated) -> Vec<V3> {
        let x: Vec<V3> = (0..self.rest.len())
            .map(|i| {
                let c = level.owner[i] as usize;
                let k = level.kept[c] as usize;
                let r = coarse.rot[c] * (self.rest[i] - self.rest[k]);
                cx[c] + r * coarse.local_scale[c]
            })
            .collect();
        for (i, &c) in level.owner.iter().enumerate() {
            self.rot[i] = coarse.rot[c as usize];
            self.local_scale[i] = coarse.local_scale[c as usize];
        }
        self.relaxed = coarse.relaxed;
        x
    }

    /// The epsilon the last iteration used (relaxed or the schedule's end).
    pub fn final_epsilon(&self, opts: &ConformOptions) -> f64 {
        self.relaxed.unwrap_or(opts.epsilon_end)
    }

    /// Runs the coarse deformation-graph stage when the options ask for it (by default
    /// only without landmarks, with the default method); returns its seconds.
    pub fn coarse(
        &mut self,
        x: &mut Vec<V3>,
        surface: &ScanSurface,
        with_landmarks: bool,
        opts: &ConformOptions,
    ) -> f64 {
        let wanted = match opts.coarse {
            CoarseStage::Auto => !with_landmarks,
            CoarseStage::Always => true,
            CoarseStage::Never => false,
        };
        if opts.method != Method::Default
            || !wanted
            || opts.coarse_nodes == 0
            || opts.coarse_iterations == 0
        {
            return 0.0;
        }
        let t = Instant::now();
        let graph = coarse::build(&self.rest, &self.neighbours, opts.coarse_nodes);
        let settings = coarse::CoarseSettings {
            iterations: opts.coarse_iterations,
            epsilon_start: opts.epsilon_start,
            epsilon_end: opts.epsilon_end,
            max_distance_start: opts.max_distance_start,
            max_distance_end: opts.max_distance,
            min_normal_cos: self.limits.min_normal_cos,
            point_to_point: opts.point_to_point,
            scan_to_template: opts.scan_to_template,
        };
        let (xc, rc) = coarse::run(
            &graph,
            &self.rest,
            x,
            self.tris,
            surface,
            self.diag,
            &self.landmark_weight,
            &self.landmark_target,
            &settings,
        );
        *x = xc;
        self.rot = rc;
        t.elapsed().as_secs_f64()
    }

    /// The fine iterations (sections 2.2-2.3): match, fill, solve, until the largest
    /// update falls below the tolerance once epsilon has reached its end. Returns the
    /// per-iteration reports and whether it converged. Stops early once `cancel` is set.
    pub fn iterate(
        &mut self,
        x: &mut Vec<V3>,
        surface: &ScanSurface,
        opts: &ConformOptions,
        times: &mut StageTimes,
        progress: &mut dyn FnMut(&IterationReport),
        cancel: &std::sync::atomic::AtomicBool,
    ) -> (Vec<IterationReport>, bool) {
        let mut reports: Vec<IterationReport> = Vec::new();
        for it in 0..opts.max_iterations {
            if cancel.load(std::sync::atomic::Ordering::Relaxed) {
                break;
            }
            let t_it = Instant::now();
            let limits = MatchLimits {
                max_distance: opts.schedule(it, opts.max_distance_start, opts.max_distance)
                    * self.diag,
                ..self.limits
            };

            // 2. Correspondence.
            let t = Instant::now();
            let (matches, _) = match_all(surface, x, self.tris, &limits);
            times.correspond += t.elapsed().as_secs_f64();
            let summary = super::MatchSummary::of(&matches);
            if let Some(prev) = reports.last_mut() {
                prev.mean_distance = summary.mean_distance;
                prev.mean_distance_relative = summary.mean_distance / self.diag;
            }
            // A posture change is fitted to within the scan's noise at epsilon_end; a
            // fit still farther away is held off by springs too stiff for a change of
            // shape: loosen them, a step per iteration, down to relax_epsilon.
            let can_relax = opts.method == Method::Default
                && opts.relax_epsilon < opts.epsilon_end
                && self.relaxed.is_none_or(|e| e > opts.relax_epsilon);
            let far = summary.mean_distance > opts.relax_distance * self.diag;
            if can_relax && it >= opts.epsilon_steps && (self.relaxed.is_some() || far) {
                self.relaxed =
                    Some((self.relaxed.unwrap_or(opts.epsilon_end) * 0.5).max(opts.relax_epsilon));
            }
            let eps =
                self.relaxed
                    .unwrap_or(opts.schedule(it, opts.epsilon_start, opts.epsilon_end));

            // 3. Grass fire.
            let t = Instant::now();
            let matched: Vec<bool> = matches.iter().map(Option::is_some).collect();
            let mut disp: Vec<V3> = matches
                .iter()
                .zip(x.iter())
                .map(|(m, p)| m.map_or(V3::zeros(), |m| m.point - p))
                .collect();
            let ring = fill::grass_fire(&self.neighbours, &matched, &mut disp);
            let filled = ring.iter().filter(|&&r| r != 0 && r != u32::MAX).count();
            let unreachable = ring.iter().filter(|&&r| r == u32::MAX).count();
            times.fill += t.elapsed().as_secs_f64();

            // 4. Elastic solve.
            let x_prev = x.clone();
            let step = Step {
                matches: &matches,
                matched: &matched,
                disp: &disp,
                ring: &ring,
                eps,
                relaxed: self.relaxed.is_some(),
            };
            let solver_iterations = match opts.method {
                Method::Default => self.arap_solve(x, &x_prev, &step, opts, times),
                Method::Paper => self.paper_solve(x, &step, opts, times),
            };

            let updates: Vec<f64> = x.iter().zip(&x_prev).map(|(a, b)| (a - b).norm()).collect();
            let max_update = updates.iter().copied().fold(0.0, f64::max);
            let mean_update = updates.iter().sum::<f64>() / updates.len().max(1) as f64;
            let rep = IterationReport {
                iteration: it + 1,
                vertices: x.len(),
                epsilon: eps,
                variation: self.baseline.measure(x),
                matched: summary.matched,
                filled,
                unreachable,
                mean_distance: f64::NAN,
                mean_distance_relative: f64::NAN,
                max_update,
                max_update_relative: max_update / self.diag,
                mean_update_relative: mean_update / self.diag,
                solver_iterations,
                seconds: t_it.elapsed().as_secs_f64(),
            };
            progress(&rep);
            reports.push(rep);
            if max_update < opts.tolerance * self.diag
                && it + 1 >= opts.epsilon_steps
                && !(can_relax && (far || self.relaxed.is_some()))
            {
                return (reports, true);
            }
        }
        (reports, false)
    }

    /// The default method's solve: as-rigid-as-possible springs (rotations fitted over
    /// rings, local scale within its limit), point-to-plane data and soft landmarks;
    /// alternates rotation fits and linear solves. Returns solver iterations.
    fn arap_solve(
        &mut self,
        x: &mut Vec<V3>,
        x_prev: &[V3],
        s: &Step,
        opts: &ConformOptions,
        times: &mut StageTimes,
    ) -> usize {
        let n = x.len();
        let anchor = s.anchor();
        let d: Vec<f64> = (0..n)
            .map(|i| {
                s.matches[i].map_or(0.0, |m| m.weight) * self.area_weight[i]
                    + self.landmark_weight[i]
                    + anchor
            })
            .collect();
        // Start from the grass-fire displacement: unmatched vertices carry no data
        // weight, so the rotation-aware springs alone shape the holes.
        let mut xc: Vec<V3> = (0..n)
            .map(|i| if s.matched[i] { x[i] } else { x[i] + s.disp[i] })
            .collect();
        let mut solver_iterations = 0;
        let mut accel = Anderson::new(opts.anderson_history);
        for _ in 0..opts.rotation_iterations.max(1) {
            let x_in = xc.clone();
            let t = Instant::now();
            let limit = if s.relaxed {
                opts.relax_scale_limit
            } else {
                opts.local_scale_limit
            };
            let scale =
                (limit > 1.0).then_some((&mut self.local_scale[..], &self.rest_norms[..], limit));
            solve::fit_rotations(
                &self.lap,
                &self.rest,
                &xc,
                &self.support,
                &mut self.rot,
                scale,
            );
            let rm: Vec<Matrix3<f64>> = self
                .rot
                .iter()
                .zip(s.matched)
                .zip(&self.local_scale)
                .map(|((q, &m), &sc)| {
                    if m || opts.hole_springs == HoleSprings::Rotated {
                        q.to_rotation_matrix().matrix() * sc
                    } else {
                        Matrix3::identity()
                    }
                })
                .collect();
            let springs = self.lap.rotated_rest(&self.rest, Some(&rm));
            times.rotations += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let b: Vec<V3> = (0..n)
                .into_par_iter()
                .map(|i| {
                    let mut b = springs[i] * s.eps
                        + x_prev[i] * anchor
                        + self.landmark_target[i] * self.landmark_weight[i];
                    if let Some(m) = &s.matches[i] {
                        // point-to-plane: the foot of the current position on the scan's
                        // tangent plane, blended with the point itself
                        let foot = xc[i] - m.normal * m.normal.dot(&(xc[i] - m.point));
                        b += (foot * (1.0 - opts.point_to_point) + m.point * opts.point_to_point)
                            * (m.weight * self.area_weight[i]);
                    }
                    b
                })
                .collect();
            let st = solve::pcg(
                &self.lap,
                s.eps,
                &d,
                &b,
                &mut xc,
                opts.solver_tolerance,
                opts.solver_max_iterations,
            );
            solver_iterations += st.iterations;
            times.solve += t.elapsed().as_secs_f64();
            accel.step(&x_in, &mut xc);
        }
        *x = xc;
        solver_iterations
    }

    /// The paper's solve: every vertex labelled TRUE (matched, or filled by the grass
    /// fire) is attracted to its target; springs keep the rest shape's edge vectors.
    fn paper_solve(
        &self,
        x: &mut [V3],
        s: &Step,
        opts: &ConformOptions,
        times: &mut StageTimes,
    ) -> usize {
        let t = Instant::now();
        let n = x.len();
        let (anchor, mean_w) = (s.anchor(), s.mean_weight());
        let d: Vec<f64> = (0..n)
            .map(|i| match (&s.matches[i], s.ring[i]) {
                (Some(m), _) => m.weight + anchor,
                (None, r) if r != u32::MAX => mean_w + anchor,
                _ => anchor,
            })
            .collect();
        let springs = self.lap.rotated_rest(&self.rest, None);
        let b: Vec<V3> = (0..n)
            .map(|i| springs[i] * s.eps + (x[i] + s.disp[i]) * (d[i] - anchor) + x[i] * anchor)
            .collect();
        let st = solve::pcg(
            &self.lap,
            s.eps,
            &d,
            &b,
            x,
            opts.solver_tolerance,
            opts.solver_max_iterations,
        );
        times.solve += t.elapsed().as_secs_f64();
        st.iterations
    }
}

/// What the fold repair after the elastic fit found and left.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct FoldRepair {
    /// triangles turned over against the rest shape under the fitted rotations
    pub found: usize,
    /// vertices moved by the repair
    pub moved: usize,
    /// triangles still turned over after it
    pub left: usize,
}

/// Rings of neighbours around a fold that the repair frees besides the fold's own
/// vertices, per round; a fold still there after a round is freed wider.
const FOLD_RINGS: [usize; 3] = [2, 4, 8];

impl Fit<'_> {
    /// Triangles whose normal points away from their rest normal turned by their
    /// vertices' fitted rotations: a patch the data pulled inside out, typically a part
    /// finer than the scan resolves (fingers, ears), where the data carries no shape.
    fn turned_over(&self, x: &[V3]) -> Vec<usize> {
        let r: Vec<Matrix3<f64>> = self
            .rot
            .iter()
            .map(|q| *q.to_rotation_matrix().matrix())
            .collect();
        let normal = |p: &[V3], t: &[u32; 3]| {
            let [a, b, c] = t.map(|i| p[i as usize]);
            (b - a).cross(&(c - a))
        };
        (0..self.tris.len())
            .into_par_iter()
            .with_min_len(4096)
            .filter(|&k| {
                let t = &self.tris[k];
                let turn = t.iter().map(|&i| r[i as usize]).sum::<Matrix3<f64>>();
                normal(x, t).dot(&(turn * normal(&self.rest, t))) <= 0.0
            })
            .collect()
    }

    /// Gives turned-over patches back their rest shape: the vertices of every such
    /// triangle and a few rings round them are solved as-rigid-as-possible with no data,
    /// held by the rest of the fit as it stands (their first rotations taken from the
    /// nearest vertex outside, since a fold's own are meaningless). Where one round
    /// leaves folds, the next frees wider rings. The data term put the fold there, so
    /// the scan loses nothing it resolves.
    pub fn repair_folds(&mut self, x: &mut [V3]) -> FoldRepair {
        solve::fit_rotations(&self.lap, &self.rest, x, &self.support, &mut self.rot, None);
        let mut folds = self.turned_over(x);
        let mut repair = FoldRepair {
            found: folds.len(),
            ..FoldRepair::default()
        };
        let n = x.len();
        let mut ever_free = vec![false; n];
        for rings in FOLD_RINGS {
            if folds.is_empty() {
                break;
            }
            let mut seeds: Vec<u32> = folds.iter().flat_map(|&k| self.tris[k]).collect();
            seeds.sort_unstable();
            seeds.dedup();
            let free = topology::rings_around(&self.neighbours, &seeds, rings);
            let (rot_before, scale_before) = (self.rot.clone(), self.local_scale.clone());
            // first rotations of the freed vertices: the nearest held vertex's
            let from = topology::nearest_outside(&self.neighbours, &free);
            for (i, j) in from.iter().enumerate() {
                if let Some(j) = *j {
                    self.rot[i] = self.rot[j as usize];
                    self.local_scale[i] = self.local_scale[j as usize];
                }
            }
            // the freed vertices' springs alone, the held ones as they stand
            let (sub, index) = self.lap.restricted(&free);
            let mut xf: Vec<V3> = index.iter().map(|&i| x[i as usize]).collect();
            let mut xc = x.to_vec();
            let zeros = vec![0.0; index.len()];
            for round in 0..4 {
                if round > 0 {
                    let kept = self.rot.clone();
                    solve::fit_rotations(
                        &self.lap,
                        &self.rest,
                        &xc,
                        &self.support,
                        &mut self.rot,
                        None,
                    );
                    for i in 0..n {
                        if !free[i] {
                            self.rot[i] = kept[i];
                        }
                    }
                }
                // a relaxed fit's springs keep the scale they had taken
                let rm: Vec<Matrix3<f64>> = self
                    .rot
                    .iter()
                    .zip(&self.local_scale)
                    .map(|(q, &sc)| q.to_rotation_matrix().matrix() * sc)
                    .collect();
                let springs = self.lap.rotated_rest(&self.rest, Some(&rm));
                let b: Vec<V3> = index
                    .iter()
                    .map(|&i| springs[i as usize] + self.lap.held_pull(i as usize, &free, &xc))
                    .collect();
                solve::pcg(&sub, 1.0, &zeros, &b, &mut xf, 1e-8, 1000);
                for (&i, p) in index.iter().zip(&xf) {
                    xc[i as usize] = *p;
                }
            }
            // a part is kept repaired when it has fewer triangles turned over than before
            // and moved no farther than the data reaches (farther, it was folded by a
            // wrong fit, not by missing detail, and stays as the data left it)
            let parts = topology::parts_of(&self.neighbours, &free);
            let mut part_of = vec![usize::MAX; n];
            for (p, part) in parts.iter().enumerate() {
                for &i in part {
                    part_of[i as usize] = p;
                }
            }
            let count = |tris: &[usize]| {
                let mut c = vec![0usize; parts.len()];
                for &k in tris {
                    // a triangle turned over outside the freed parts counts nowhere
                    if let Some(&p) = self.tris[k]
                        .iter()
                        .map(|&i| &part_of[i as usize])
                        .find(|&&p| p != usize::MAX)
                    {
                        c[p] += 1;
                    }
                }
                c
            };
            let (before, after) = (count(&folds), count(&self.turned_over(&xc)));
            for (p, part) in parts.iter().enumerate() {
                let far = part
                    .iter()
                    .any(|&i| (xc[i as usize] - x[i as usize]).norm() > self.limits.max_distance);
                for &i in part {
                    let i = i as usize;
                    if !far && after[p] < before[p] {
                        x[i] = xc[i];
                        ever_free[i] = true;
                    } else {
                        self.rot[i] = rot_before[i];
                        self.local_scale[i] = scale_before[i];
                    }
                }
            }
            folds = self.turned_over(x);
        }
        repair.moved = ever_free.iter().filter(|&&f| f).count();
        repair.left = folds.len();
        repair
    }
}

/// Each vertex's share of the surface (a third of its triangles' areas) against the
/// mean share, clamped to 1/20..20 so that a degenerate corner keeps some data and a
/// huge triangle does not drown its neighbours.
fn vertex_area_weights(v: &[V3], tris: &[[u32; 3]]) -> Vec<f64> {
    let a = crate::mesh::vertex_areas(v, tris);
    let used = a.iter().filter(|&&x| x > 0.0).count().max(1);
    let mean = a.iter().sum::<f64>() / used as f64;
    if !(mean > 0.0) {
        return vec![1.0; v.len()];
    }
    a.iter().map(|x| (x / mean).clamp(0.05, 20.0)).collect()
}

fn median_edge(rest: &[V3], template: &Mesh) -> f64 {
    let mut l: Vec<f64> = topology::edges(&template.triangles)
        .iter()
        .map(|[a, b]| (rest[*a as usize] - rest[*b as usize]).norm())
        .collect();
    if l.is_empty() {
        return 0.0;
    }
    let k = l.len() / 2;
    *l.select_nth_unstable_by(k, f64::total_cmp).1
}

fn with_bridges(mut nb: Vec<Vec<u32>>, bridges: &[[u32; 2]]) -> Vec<Vec<u32>> {
    for &[a, b] in bridges {
        nb[a as usize].push(b);
        nb[b as usize].push(a);
    }
    nb
}

/// One iteration's data for the solve.
struct Step<'s> {
    matches: &'s [Option<super::correspond::Match>],
    matched: &'s [bool],
    /// grass-fire displacements (matched: to the match; filled: spread from neighbours)
    disp: &'s [V3],
    ring: &'s [u32],
    eps: f64,
    /// the springs have loosened below epsilon_end (see `ConformOptions::relax_epsilon`)
    relaxed: bool,
}

impl Step<'_> {
    fn mean_weight(&self) -> f64 {
        let (s, c) = self
            .matches
            .iter()
            .flatten()
            .fold((0.0, 0usize), |(s, c), m| (s + m.weight, c + 1));
        if c > 0 { s / c as f64 } else { 1.0 }
    }

    /// A whisper of anchoring to the previous positions keeps the system positive
    /// definite when a whole component has no data.
    fn anchor(&self) -> f64 {
        1e-6 * self.mean_weight()
    }
}

/// Anderson acceleration (type II) of the rotation-fit / linear-solve alternation, a
/// fixed-point map `x -> G(x)` that converges slowly when a rotation must travel far
/// along the mesh (a turned limb). Mixing the last few steps extrapolates along the
/// direction they agree on; a step whose residual grows is taken plainly and the
/// history restarts, so it cannot do worse than the plain alternation by much.
struct Anderson {
    history: usize,
    /// previous step's input and its residual `G(x) - x`, flattened
    prev: Option<(Vec<f64>, Vec<f64>)>,
    /// differences of successive residuals and of successive images `G(x)`
    df: Vec<Vec<f64>>,
    dg: Vec<Vec<f64>>,
    last_residual: f64,
}

impl Anderson {
    fn new(history: usize) -> Self {
        Anderson {
            history,
            prev: None,
            df: Vec::new(),
            dg: Vec::new(),
            last_residual: f64::INFINITY,
        }
    }

    /// `x_in` went into the map, `out` holds `G(x_in)`; overwritten with the next iterate.
    fn step(&mut self, x_in: &[V3], out: &mut [V3]) {
        if self.history == 0 {
            return;
        }
        let g: Vec<f64> = out.iter().flat_map(|v| [v.x, v.y, v.z]).collect();
        let f: Vec<f64> = x_in
            .iter()
            .zip(out.iter())
            .flat_map(|(a, b)| [b.x - a.x, b.y - a.y, b.z - a.z])
            .collect();
        let fnorm = f.iter().map(|v| v * v).sum::<f64>().sqrt();
        if fnorm > self.last_residual {
            // the extrapolation overshot: keep the plain step, forget the history
            self.df.clear();
            self.dg.clear();
            self.prev = None;
        }
        self.last_residual = fnorm;
        if let Some((g0, f0)) = self.prev.take() {
            self.df
                .push(f.iter().zip(&f0).map(|(a, b)| a - b).collect());
            self.dg
                .push(g.iter().zip(&g0).map(|(a, b)| a - b).collect());
            if self.df.len() > self.history {
                self.df.remove(0);
                self.dg.remove(0);
            }
        }
        self.prev = Some((g.clone(), f.clone()));
        let m = self.df.len();
        if m == 0 {
            return;
        }
        // least squares: gamma = argmin |f - DF gamma|, by the m x m normal equations
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).sum::<f64>();
        let mut ata = nalgebra::DMatrix::<f64>::zeros(m, m);
        let mut atb = nalgebra::DVector::<f64>::zeros(m);
        for i in 0..m {
            for j in i..m {
                let v = dot(&self.df[i], &self.df[j]);
                ata[(i, j)] = v;
                ata[(j, i)] = v;
            }
            atb[i] = dot(&self.df[i], &f);
        }
        // a little Tikhonov keeps nearly parallel steps from blowing up
        let ridge = 1e-10 * (0..m).map(|i| ata[(i, i)]).fold(0.0, f64::max);
        for i in 0..m {
            ata[(i, i)] += ridge;
        }
        let Some(gamma) = ata.cholesky().map(|c| c.solve(&atb)) else {
            return;
        };
        for (k, o) in out.iter_mut().enumerate() {
            let mut v = [g[3 * k], g[3 * k + 1], g[3 * k + 2]];
            for (i, dg) in self.dg.iter().enumerate() {
                for c in 0..3 {
                    v[c] -= gamma[i] * dg[3 * k + c];
                }
            }
            *o = V3::new(v[0], v[1], v[2]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::quality::flipped_against;

    /// A unit sphere as a template, turned and moved as a whole: its fit, the truth, and
    /// the turn and shift applied to a changed copy of its vertices.
    fn turned_sphere(change: impl Fn(usize, &V3) -> V3) -> (Mesh, Vec<V3>, Vec<V3>) {
        let sphere = crate::synth::icosphere(4);
        let turn = UnitQuaternion::from_euler_angles(0.3, -0.2, 0.5);
        let shift = V3::new(0.2, -0.1, 0.4);
        let truth = sphere.vertices.iter().map(|p| turn * p + shift).collect();
        let x = sphere
            .vertices
            .iter()
            .enumerate()
            .map(|(i, p)| turn * change(i, p) + shift)
            .collect();
        (sphere, truth, x)
    }

    /// The fit of a template onto itself as it stands, with the default options.
    fn fit_on(template: &Mesh) -> Fit<'_> {
        let opts = ConformOptions::default();
        Fit::new(
            template,
            &template.vertices,
            &Similarity::default(),
            None,
            &opts,
        )
    }

    fn largest_gap(a: &[V3], b: &[V3]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max)
    }

    /// A vertex pulled across its neighbours (its fan turned inside out, as the data
    /// leaves a part finer than the scan resolves): the repair gives the patch its shape
    /// back under the sphere's turn and leaves the rest where it was; run again, it
    /// finds nothing.
    #[test]
    fn a_fold_within_the_data_s_reach_gets_its_rest_shape_back() {
        // the icosphere's first vertex, (-1, t, 0) normalised: z is along its surface
        let pulled = 0;
        let (sphere, truth, mut x) = turned_sphere(|i, p| {
            if i == pulled {
                // across the ring (edges about 0.08 long), within the match distance
                p + V3::new(0.0, 0.0, 0.1)
            } else {
                *p
            }
        });
        let mut fit = fit_on(&sphere);
        let before = flipped_against(&x, &truth, &sphere.triangles);
        assert!(before >= 2, "{before} triangles turned over to start with");
        let moved_before = largest_gap(&x, &truth);

        let r = fit.repair_folds(&mut x);
        assert_eq!(flipped_against(&x, &truth, &sphere.triangles), 0, "{r:?}");
        assert!(r.found > 0 && r.left == 0 && r.moved > 0, "{r:?}");
        let far = (0..x.len())
            .filter(|&i| (sphere.vertices[i] - sphere.vertices[pulled]).norm() > 0.5)
            .map(|i| (x[i] - truth[i]).norm())
            .fold(0.0, f64::max);
        assert!(far < 1e-12, "far from the fold a vertex moved {far}");
        let after = largest_gap(&x, &truth);
        assert!(after < moved_before / 10.0, "{moved_before} -> {after}");
        let again = fit.repair_folds(&mut x);
        assert_eq!((again.found, again.moved), (0, 0), "{again:?}");
    }

    /// A cap mirrored (turned inside out a long way, as a wrong fit does): giving it its
    /// shape back would carry it farther than the data reaches, so it stays as it is.
    #[test]
    fn a_fold_beyond_the_data_s_reach_is_left_as_the_fit_left_it() {
        let (sphere, truth, mut x) = turned_sphere(|_, p| {
            if p.z > 0.8 {
                V3::new(-p.x, p.y, p.z)
            } else {
                *p
            }
        });
        let mut fit = fit_on(&sphere);
        let before = flipped_against(&x, &truth, &sphere.triangles);
        assert!(before >= 20, "{before} triangles turned over to start with");
        let as_left = x.clone();
        let r = fit.repair_folds(&mut x);
        assert!(r.found > 0 && r.moved == 0 && r.left == r.found, "{r:?}");
        assert_eq!(x, as_left);
    }
}
