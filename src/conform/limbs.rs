//! Landmark-free articulation search: the template's limbs (geodesic extremities, each
//! turned about a joint part-way along it), and for each limb the turn that best explains
//! the scan after the rigid alignment. A rigid start leaves a limb swung far from the
//! template's rest pose lying on its neighbour (a leg on the other leg), where
//! closest-point matching keeps it; the search turns it to the scan data nothing covers.

use super::correspond::{ScanSurface, nearest_within};
use crate::mesh::{V3, topology, vertex_areas, vertex_normals};
use kiddo::ImmutableKdTree;
use nalgebra::{Rotation3, Unit};
use rayon::prelude::*;

/// One limb of the template: the vertices it moves, with weights that fall from 1 at the
/// tip side to 0 past the joint, and the joint it turns about.
#[derive(Debug, Clone)]
pub struct Limb {
    pub tip: u32,
    /// the vertices around the joint (their centroid is the joint, wherever the limb
    /// and the limbs it hangs from have been turned)
    pub ring: Vec<u32>,
    /// (vertex, weight in (0, 1])
    pub weights: Vec<(u32, f64)>,
}

/// Where the joint sits, as a share of the geodesic path from the tip to the body's
/// centre, and half the width of the band the turn fades over.
const JOINT_SHARE: f64 = 0.5;
const BAND_SHARE: f64 = 0.15;
/// A cut through the body itself (a back or a rump found as an extremity) is wide: no
/// joint turns it.
const THIN_RATIO: f64 = 0.35;

/// The template's limbs: the first `count` geodesic farthest-point samples from the
/// vertex nearest the centroid whose cut at the joint is thin.
///
/// - `v`: #V template vertices; `neighbours`: #V neighbour lists
pub fn find(v: &[V3], neighbours: &[Vec<u32>], count: usize) -> Vec<Limb> {
    if v.is_empty() {
        return Vec::new();
    }
    let (_, from_centre) = topology::centre_distances(v, neighbours);
    let mut nearest = from_centre.clone();
    let mut limbs = Vec::new();
    for _ in 0..count {
        let Some(tip) = topology::farthest_sample(&nearest) else {
            break;
        };
        let length = from_centre[tip];
        let (r, h) = (JOINT_SHARE * length, BAND_SHARE * length);
        // the limb needs exact distances out to r + h, the farthest-point update only
        // where the tip is nearer than every earlier sample (the distances are 1-Lipschitz
        // along edges, so nothing beyond can get nearer)
        let from_tip = topology::edge_distances_while(v, neighbours, &[tip as u32], |i, d| {
            d < nearest[i] || d < r + h
        })
        .0;
        for (n, d) in nearest.iter_mut().zip(&from_tip) {
            *n = n.min(*d);
        }
        let ring: Vec<usize> = (0..v.len())
            .filter(|&i| (from_tip[i] - r).abs() < 0.25 * h)
            .collect();
        if ring.is_empty() {
            continue;
        }
        let joint = ring.iter().map(|&i| v[i]).sum::<V3>() / ring.len() as f64;
        let radius = ring.iter().map(|&i| (v[i] - joint).norm()).sum::<f64>() / ring.len() as f64;
        if radius > THIN_RATIO * r {
            continue;
        }
        let weights: Vec<(u32, f64)> = (0..v.len())
            .filter_map(|i| {
                let w = smoothstep((r + h - from_tip[i]) / (2.0 * h));
                (w > 0.0).then_some((i as u32, w))
            })
            .collect();
        // a limb of more than a third of the body is the body
        if weights.len() * 3 > v.len() {
            continue;
        }
        limbs.push(Limb {
            tip: tip as u32,
            ring: ring.iter().map(|&i| i as u32).collect(),
            weights,
        });
    }
    limbs
}

fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Settings of the search, relative to the scan's diagonal.
#[derive(Debug, Clone, Copy)]
pub struct SearchSettings {
    /// a scan sample lies on the template when a vertex is this near
    pub cover: f64,
    /// directions tried per limb (spread over the sphere)
    pub directions: usize,
    /// largest turn tried, degrees
    pub max_degrees: f64,
    /// passes over the limbs
    pub passes: usize,
}

impl Default for SearchSettings {
    fn default() -> Self {
        SearchSettings {
            cover: 0.03,
            directions: 48,
            max_degrees: 150.0,
            passes: 1,
        }
    }
}

/// Scan samples the search scores with, and the part of them each limb may explain.
const SCAN_SAMPLES: usize = 3000;
const LIMB_SAMPLES: usize = 300;
/// The directions are priced on every this-many-th probe's distance to the scan, and
/// this many of the cheapest scored on all probes.
const PRICE_STRIDE: usize = 4;
const SHORTLIST: usize = 6;
const REST_SAMPLES: usize = 6000;
/// scan points the limbs' distance to the scan is looked up among
const SURFACE_SAMPLES: usize = 50_000;

/// Turns each limb of `x` (the template placed on the scan; `limbs` found on the
/// template) to the direction that leaves the fewest scan
/// samples uncovered and lies on the scan, when that beats leaving it. Returns the turns
/// made, degrees, one per limb turned.
///
/// - `x`: #V vertex positions, changed in place; `tris`: #F triangles
pub fn search(
    x: &mut [V3],
    tris: &[[u32; 3]],
    limbs: &[Limb],
    scan: &ScanSurface,
    s: &SearchSettings,
) -> Vec<f64> {
    let tau = s.cover * scan.diagonal;
    let step = (scan.points.len() / SCAN_SAMPLES).max(1);
    let samples: Vec<V3> = scan.points.iter().step_by(step).copied().collect();
    let dirs = sphere_directions(s.directions);
    let near = NearScan::new(scan);
    let mut turns = Vec::new();
    for _ in 0..s.passes {
        for limb in limbs {
            let area = vertex_areas(x, tris);
            let total_area: f64 = area.iter().sum();
            if !(total_area > 0.0) {
                return turns;
            }
            let normals = vertex_normals(x, tris);
            let body = Body {
                x,
                normals: &normals,
                area: &area,
                total_area,
            };
            let Some(turn) = LimbTurn::new(&body, limb, &samples, &near, tau) else {
                continue;
            };
            if let Some((axis, angle)) = turn.best(&dirs, s) {
                let joint = turn.joint;
                for &(i, w) in &limb.weights {
                    let r = Rotation3::from_axis_angle(&axis, angle * w);
                    x[i as usize] = joint + r * (x[i as usize] - joint);
                }
                turns.push(angle.to_degrees());
            }
        }
    }
    turns
}

/// The scan points the limbs' distance to the scan is looked up among, with their
/// normals: that distance is truncated at `tau`, so a sparser scan answers it as well
/// and its tree stays in cache.
struct NearScan {
    tree: ImmutableKdTree<f64, 3>,
    normals: Vec<V3>,
}

impl NearScan {
    fn new(scan: &ScanSurface) -> Self {
        let near_step = (scan.points.len() / SURFACE_SAMPLES).max(1);
        let near_idx: Vec<usize> = (0..scan.points.len()).step_by(near_step).collect();
        let near_pts: Vec<[f64; 3]> = near_idx
            .iter()
            .map(|&k| [scan.points[k].x, scan.points[k].y, scan.points[k].z])
            .collect();
        NearScan {
            tree: ImmutableKdTree::new_from_slice(&near_pts),
            normals: near_idx.iter().map(|&k| scan.normal(k)).collect(),
        }
    }
}

/// The template as placed now: positions, normals and areas per vertex.
struct Body<'a> {
    x: &'a [V3],
    normals: &'a [V3],
    area: &'a [f64],
    total_area: f64,
}

/// One limb's turns weighed: the scan samples the rest of the body leaves open near
/// the limb, and the probe vertices standing for the limb.
struct LimbTurn<'a> {
    body: &'a Body<'a>,
    near: &'a NearScan,
    tau: f64,
    /// open scan samples within the limb's reach of its joint (the others count the
    /// same for every turn)
    open: Vec<V3>,
    probe: Vec<(u32, f64)>,
    /// scan samples a unit of probe area stands for
    per_area: f64,
    /// scan samples the limb would hold if the scan saw all of it
    limb_samples: f64,
    joint: V3,
    along: V3,
}

impl<'a> LimbTurn<'a> {
    fn new(
        body: &'a Body<'a>,
        limb: &Limb,
        samples: &[V3],
        near: &'a NearScan,
        tau: f64,
    ) -> Option<Self> {
        let (x, area) = (body.x, body.area);
        let n = x.len();
        let m = samples.len() as f64;
        let mut moved = vec![false; n];
        for &(i, w) in &limb.weights {
            moved[i as usize] = w > 0.0;
        }
        // what the rest of the body covers does not depend on the limb's turn
        let rest: Vec<[f64; 3]> = {
            let others: Vec<usize> = (0..n).filter(|&i| !moved[i]).collect();
            let st = (others.len() / REST_SAMPLES).max(1);
            others
                .iter()
                .step_by(st)
                .map(|&i| [x[i].x, x[i].y, x[i].z])
                .collect()
        };
        if rest.is_empty() {
            return None;
        }
        let rest_tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&rest);
        let open: Vec<V3> = samples
            .par_iter()
            .filter(|p| !within(&rest_tree, p, tau))
            .copied()
            .collect();
        let st = (limb.weights.len() / LIMB_SAMPLES).max(1);
        let probe: Vec<(u32, f64)> = limb.weights.iter().step_by(st).copied().collect();
        let limb_area: f64 = limb.weights.iter().map(|&(i, _)| area[i as usize]).sum();
        let limb_samples = m * limb_area / body.total_area;
        // a probe vertex stands for its share of the limb, in scan samples
        let probe_area: f64 = probe.iter().map(|&(i, _)| area[i as usize]).sum();
        let per_area = if probe_area > 0.0 {
            m / body.total_area * limb_area / probe_area
        } else {
            0.0
        };
        let joint = limb.ring.iter().map(|&i| x[i as usize]).sum::<V3>() / limb.ring.len() as f64;
        let reach = limb
            .weights
            .iter()
            .map(|&(i, _)| (x[i as usize] - joint).norm())
            .fold(0.0, f64::max)
            + tau;
        let open: Vec<V3> = open
            .into_iter()
            .filter(|p| (p - joint).norm() <= reach)
            .collect();
        let along = x[limb.tip as usize] - joint;
        if !(along.norm() > 0.0) {
            return None;
        }
        Some(LimbTurn {
            body,
            near,
            tau,
            open,
            probe,
            per_area,
            limb_samples,
            joint,
            along: along.normalize(),
        })
    }

    /// The score of a turn (axis, angle; `None` for none): samples left open plus the
    /// limb's distance off the scan; with `stride` over 1, that distance is every
    /// `stride`-th probe's, weighted up to the probes' area (a price for sorting turns).
    fn score(&self, rot: &Option<(Unit<V3>, f64)>, stride: usize) -> f64 {
        let (x, normals, area) = (self.body.x, self.body.normals, self.body.area);
        let (joint, tau) = (self.joint, self.tau);
        let turned = |i: u32, w: f64| -> (V3, V3) {
            let (p, nv) = (x[i as usize], normals[i as usize]);
            match rot {
                Some((axis, angle)) => {
                    let r = Rotation3::from_axis_angle(axis, angle * w);
                    (joint + r * (p - joint), r * nv)
                }
                None => (p, nv),
            }
        };
        let (mut off, mut priced_area, mut probe_area) = (0.0, 0.0, 0.0);
        let mut pts = Vec::with_capacity(self.probe.len());
        for (k, &(i, w)) in self.probe.iter().enumerate() {
            let (p, nv) = turned(i, w);
            pts.push([p.x, p.y, p.z]);
            probe_area += area[i as usize];
            if k % stride.max(1) != 0 {
                continue;
            }
            // past `tau` the distance counts as `tau`: a bounded query is enough
            let dd = match nearest_within(&self.near.tree, &p, tau) {
                Some((k, d)) if self.near.normals[k].dot(&nv) > 0.3 => d / tau,
                _ => 1.0,
            };
            off += area[i as usize] * dd;
            priced_area += area[i as usize];
        }
        if priced_area > 0.0 {
            off *= probe_area / priced_area;
        }
        let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&pts);
        // a sample farther than `tau` from the probes' box stays open: no query
        let (lo, hi) = crate::mesh::bounds(pts.iter().map(|q| V3::from(*q)))
            .unwrap_or((V3::zeros(), V3::zeros()));
        let (lo, hi) = (lo - V3::repeat(tau), hi + V3::repeat(tau));
        let still_open = self
            .open
            .iter()
            .filter(|p| {
                let inside = p.x >= lo.x
                    && p.y >= lo.y
                    && p.z >= lo.z
                    && p.x <= hi.x
                    && p.y <= hi.y
                    && p.z <= hi.z;
                !inside || !within(&tree, p, tau)
            })
            .count();
        still_open as f64 + off * self.per_area
    }

    /// The best turn over the sphere's lattice `dirs`, then a finer one around its best
    /// direction; `None` unless it explains clearly more than noise (a tenth of the
    /// limb's samples) over leaving the limb as it is.
    fn best(&self, dirs: &[V3], s: &SearchSettings) -> Option<(Unit<V3>, f64)> {
        let along = self.along;
        let here = self.score(&None, 1);
        let turn_to = |d: &V3| -> Option<(Unit<V3>, f64)> {
            let angle = along.dot(d).clamp(-1.0, 1.0).acos();
            if angle.to_degrees() > s.max_degrees || angle < 1e-3 {
                return None;
            }
            Some((Unit::try_new(along.cross(d), 1e-9)?, angle))
        };
        // every direction priced on a share of the probes, the cheapest few on all
        let best_of = |dirs: &[V3]| {
            let mut priced: Vec<(f64, V3)> = dirs
                .par_iter()
                .filter_map(|d| Some((self.score(&Some(turn_to(d)?), PRICE_STRIDE), *d)))
                .collect();
            priced.sort_by(|a, b| a.0.total_cmp(&b.0));
            priced.truncate(SHORTLIST);
            priced
                .par_iter()
                .filter_map(|(_, d)| Some((self.score(&Some(turn_to(d)?), 1), *d)))
                .min_by(|a, b| a.0.total_cmp(&b.0))
        };
        let best = best_of(dirs).and_then(|(sc, d)| {
            let spread = (4.0 / s.directions as f64).sqrt();
            let near: Vec<V3> = dirs
                .iter()
                .map(|e| (d + (e - d * d.dot(e)) * spread).normalize())
                .filter(|e| e.dot(&d) > 0.0)
                .collect();
            best_of(&near).filter(|b| b.0 < sc).or(Some((sc, d)))
        });
        let (sc, d) = best?;
        let angle = along.dot(&d).clamp(-1.0, 1.0).acos();
        let axis = Unit::try_new(along.cross(&d), 1e-9)?;
        let margin = 0.1 * self.limb_samples;
        (sc < here - margin.max(3.0)).then_some((axis, angle))
    }
}

fn within(tree: &ImmutableKdTree<f64, 3>, p: &V3, r: f64) -> bool {
    nearest_within(tree, p, r).is_some()
}

/// `count` unit directions spread over the sphere (a Fibonacci lattice).
pub(crate) fn sphere_directions(count: usize) -> Vec<V3> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..count)
        .map(|k| {
            let z = 1.0 - 2.0 * (k as f64 + 0.5) / count as f64;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let t = golden * k as f64;
            V3::new(r * t.cos(), r * t.sin(), z)
        })
        .collect()
}
