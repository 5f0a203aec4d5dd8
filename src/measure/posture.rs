//! Posture-free measurement by the subject's own parts: the conformed mesh is
//! not deformed back to a rest posture. Instead each bone of the generic template's
//! skeleton gets a robust similarity fit (rest -> result) over the vertices it carries,
//! and each measurement's definition is moved into the subject's posture: a girth's
//! plane goes where the bone carries it, a length's points are taken back through the
//! joints' rotations only (the subject's own bone lengths kept), heights stand on the
//! floor under the subject's own feet taken back by the parts. Fitting hundreds of
//! vertices per part averages out the vertices a landmark-free fit slid, where undoing
//! the template's skinning moved them.

use crate::mesh::{Mesh, V3};
use crate::template::figure::Figure;
use nalgebra::{DMatrix, Matrix3, Rotation3};

/// A generic template's parts: rest positions, skin weights and the bone tree.
#[derive(Debug, Clone)]
pub struct Articulation {
    rest: Vec<V3>,
    weights: Vec<Vec<(u32, f64)>>,
    parents: Vec<Option<usize>>,
    /// each bone's joint (its head) in the rest posture
    joints: Vec<V3>,
    names: Vec<String>,
    up: V3,
}

/// A result's posture as its parts carry it.
pub struct Posed<'a> {
    art: &'a Articulation,
    /// rest -> result, per bone
    bones: Vec<BoneFit>,
    /// the result with every joint's rotation taken out (the root's kept)
    normalised: Vec<V3>,
    /// the template's up as the root bone carries it
    pub up: V3,
    /// the vertices the subject stands on: (height in the result, how far taking the
    /// turns out moves their bone's joint along `up`); see [`Posed::floor`]
    contact: Vec<(f64, f64)>,
    /// the median height in the result of the vertices it stands on
    sole: f64,
    /// the subject's height in the result (robust: 0.2% to 99.8% quantile)
    extent: f64,
    /// the lowest normalised point along `up` (its 0.2% quantile: a few stray vertices
    /// under the soles do not set it)
    lowest: f64,
}

/// How many vertices' worth of evidence a bone needs to turn unlike its parent.
const TIE_VERTICES: f64 = 0.0;
/// Robust fit rounds (Cauchy weights on the residuals).
const ROUNDS: usize = 4;

impl Articulation {
    /// `up` is the template's up direction (the measurement frame's).
    pub fn from_figure(fig: &Figure, up: V3) -> Articulation {
        let bones = &fig.skeleton.bones;
        Articulation {
            rest: fig.mesh.vertices.clone(),
            weights: fig.weights.clone(),
            parents: bones.iter().map(|b| b.parent).collect(),
            joints: bones.iter().map(|b| b.head).collect(),
            names: bones.iter().map(|b| b.name.clone()).collect(),
            up: up.try_normalize(0.0).unwrap_or(V3::z()),
        }
    }

    pub fn vertices(&self) -> usize {
        self.rest.len()
    }

    /// The parts' fits to `mesh` (the template's vertex order).
    pub fn fit(&self, mesh: &Mesh) -> Result<Posed<'_>, super::MeasureError> {
        if mesh.vertices.len() != self.rest.len() {
            return Err(super::MeasureError::VertexCount {
                got: mesh.vertices.len(),
                expected: self.rest.len(),
            });
        }
        let x = &mesh.vertices;
        let nb = self.parents.len();
        if x.is_empty() {
            return Err(super::MeasureError::EmptyMesh);
        }
        let bones = skinning_fit(&self.rest, &self.weights, &self.parents, &self.joints, x)
            .ok_or(super::MeasureError::PartsNotFitted)?;
        let root = self.parents.iter().position(|p| p.is_none()).unwrap_or(0);
        let r_root = bones[root].rotation;
        // N_b(x) = M_b x + c_b: bone b's offset from its joint turned back to the
        // orientation it has in the rest posture relative to the root
        let mut affine: Vec<(Matrix3<f64>, V3)> = Vec::with_capacity(nb);
        for b in 0..nb {
            let a = match self.parents[b] {
                None => (Matrix3::identity(), V3::zeros()),
                Some(p) => {
                    let j =
                        0.5 * (bones[b].apply(&self.joints[b]) + bones[p].apply(&self.joints[b]));
                    let (mp, cp) = affine[p];
                    let m = (r_root * bones[b].rotation.inverse()).into_inner();
                    (m, mp * j + cp - m * j)
                }
            };
            affine.push(a);
        }
        // a vertex is taken back to rest through its blend of the bones' transforms (as
        // skinning moved it), then out through the same blend of the normalised bones:
        // exact for a posture skinning made
        let normalised: Vec<V3> = x
            .iter()
            .zip(&self.weights)
            .map(|(q, w)| {
                let total = w.iter().map(|&(_, wt)| wt).sum::<f64>().max(1e-12);
                let mut m = Matrix3::zeros();
                let mut t = V3::zeros();
                for &(b, wt) in w {
                    m += bones[b as usize].linear * (wt / total);
                    t += bones[b as usize].translation * (wt / total);
                }
                let Some(r) = m.try_inverse().map(|mi| mi * (q - t)) else {
                    return *q;
                };
                w.iter()
                    .map(|&(b, wt)| {
                        let (m, c) = affine[b as usize];
                        (m * bones[b as usize].apply(&r) + c) * (wt / total)
                    })
                    .sum::<V3>()
            })
            .collect();
        let up = r_root * self.up;
        // each contact vertex moves as its bone's joint does (the ankle, not the sole: a
        // foot's own turn, fitted on unseen filled soles, does not move the floor)
        let joint_shift: Vec<f64> = (0..nb)
            .map(|b| {
                let raw = bones[b].apply(&self.joints[b]);
                let (m, c) = affine[b];
                (m * raw + c).dot(&up) - raw.dot(&self.up)
            })
            .collect();
        let dominant = |v: usize| {
            self.weights[v]
                .iter()
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .map_or(root, |w| w.0 as usize)
        };
        let (contact, extent) = contact(x, &self.up);
        let contact: Vec<(f64, f64)> = contact
            .into_iter()
            .map(|(v, h)| (h, joint_shift[dominant(v)]))
            .collect();
        let sole = median(contact.iter().map(|c| c.0).collect()).unwrap_or(f64::INFINITY);
        let mut heights: Vec<f64> = normalised.iter().map(|q| q.dot(&up)).collect();
        heights.sort_by(f64::total_cmp);
        let lowest = quantile(&heights, 0.002);
        Ok(Posed {
            art: self,
            bones,
            normalised,
            up,
            contact,
            sole,
            extent,
            lowest,
        })
    }
}

/// The `q` quantile of `sorted` (not empty).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() as f64 * q) as usize).min(sorted.len() - 1)]
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

/// The vertices the subject stands on, with their heights along `up` (those within 1% of
/// its height above its lowest point), and its height: robust quantiles, 0.2% and 99.8%,
/// so a few stray vertices set neither.
fn contact(x: &[V3], up: &V3) -> (Vec<(usize, f64)>, f64) {
    let heights: Vec<f64> = x.iter().map(|q| q.dot(up)).collect();
    let mut sorted = heights.clone();
    sorted.sort_by(f64::total_cmp);
    let at = |q: f64| quantile(&sorted, q);
    let extent = at(0.998) - at(0.002);
    let band = at(0.002) + 0.01 * extent;
    let contact = heights
        .into_iter()
        .enumerate()
        .filter(|&(_, h)| h <= band)
        .collect();
    (contact, extent)
}

/// One bone's fitted transform `x -> linear x + translation` and the rotation in it.
#[derive(Debug, Clone, Copy)]
struct BoneFit {
    linear: Matrix3<f64>,
    translation: V3,
    /// the rotation of `linear`'s polar decomposition (its shape change taken out)
    rotation: Rotation3<f64>,
}

impl BoneFit {
    fn apply(&self, p: &V3) -> V3 {
        self.linear * p + self.translation
    }
}

/// The bones' affine transforms that best skin `rest` onto `x` with the template's own
/// weights, all bones at once: `x_v ~ sum_b w_vb (A_b rest_v + t_b)` is linear in the
/// transforms, so one least-squares solve (each coordinate separately, one matrix)
/// fits every part, blended vertices included. Re-weighted by the residuals (Cauchy,
/// scale twice the median) so that vertices a landmark-free fit slid count little; a
/// weak tie of each bone to its parent keeps a bone with few vertices well posed.
fn skinning_fit(
    rest: &[V3],
    weights: &[Vec<(u32, f64)>],
    parents: &[Option<usize>],
    joints: &[V3],
    x: &[V3],
) -> Option<Vec<BoneFit>> {
    let nb = parents.len();
    let n = 4 * nb;
    let mut robust = vec![1.0; x.len()];
    let (lo, hi) = x
        .iter()
        .fold((x[0], x[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
    let scale = (hi - lo).norm();
    let (rlo, rhi) = rest
        .iter()
        .fold((rest[0], rest[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
    // a typical part's radius squared, times a few vertices
    let tie_linear = TIE_VERTICES * (0.05 * (rhi - rlo).norm()).powi(2);
    let tie_joint = 0.1 * x.len() as f64;
    let mut fits: Vec<BoneFit> = Vec::new();
    for round in 0..=ROUNDS {
        let mut a = DMatrix::<f64>::zeros(n, n);
        let mut rhs = DMatrix::<f64>::zeros(n, 3);
        for (v, w) in weights.iter().enumerate() {
            // each bone's transform about its own joint: well conditioned however far
            // from the origin a small part lies
            let basis = |b: u32| {
                let r = rest[v] - joints[b as usize];
                [r.x, r.y, r.z, 1.0]
            };
            for &(b, wb) in w {
                let bb = basis(b);
                for &(c, wc) in w {
                    let k = robust[v] * wb * wc;
                    let bc = basis(c);
                    for i in 0..4 {
                        for j in 0..4 {
                            a[(4 * b as usize + i, 4 * c as usize + j)] += k * bb[i] * bc[j];
                        }
                    }
                }
                let basis = bb;
                for i in 0..4 {
                    for d in 0..3 {
                        rhs[(4 * b as usize + i, d)] += robust[v] * wb * basis[i] * x[v][d];
                    }
                }
            }
        }
        add_ties(&mut a, parents, joints, tie_joint, tie_linear);
        let sol = a.cholesky()?.solve(&rhs);
        fits = bone_fits(&sol, joints);
        if fits.iter().any(|f| {
            !f.linear
                .iter()
                .chain(f.translation.iter())
                .all(|c| c.is_finite())
        }) {
            return None;
        }
        if round == ROUNDS {
            break;
        }
        let res: Vec<f64> = (0..x.len())
            .map(|v| {
                let q = weights[v]
                    .iter()
                    .map(|&(b, wb)| fits[b as usize].apply(&rest[v]) * wb)
                    .sum::<V3>();
                (q - x[v]).norm()
            })
            .collect();
        let mut sorted = res.clone();
        sorted.sort_by(f64::total_cmp);
        // a floor on the scale: an exact fit's round-off is no reason to re-weight
        let c = (2.0 * sorted[sorted.len() / 2]).max(1e-4 * scale);
        for v in 0..x.len() {
            robust[v] = 1.0 / (1.0 + (res[v] / c).powi(2));
        }
    }
    Some(fits)
}

/// The ties added to the normal equations `a`: bones meet at their joints (true of
/// every skinned posture, so no bias), and each bone's linear part is tied to its
/// parent's with the weight of a few vertices: a part the skin hardly shows (a neck
/// inside the shoulders, a flat ear) moves with its parent rather than as noise.
fn add_ties(
    a: &mut DMatrix<f64>,
    parents: &[Option<usize>],
    joints: &[V3],
    tie_joint: f64,
    tie_linear: f64,
) {
    for (b, p) in parents.iter().enumerate() {
        let Some(p) = *p else {
            for i in 0..3 {
                a[(4 * b + i, 4 * b + i)] += 1e-9 * tie_linear;
            }
            continue;
        };
        let mut g = vec![(4 * b + 3, 1.0), (4 * p + 3, -1.0)];
        let off = joints[b] - joints[p];
        g.extend((0..3).map(|i| (4 * p + i, -off[i])));
        for &(i, gi) in &g {
            for &(j, gj) in &g {
                a[(i, j)] += tie_joint * gi * gj;
            }
        }
        for i in 0..3 {
            let (bi, pi) = (4 * b + i, 4 * p + i);
            a[(bi, bi)] += tie_linear;
            a[(pi, pi)] += tie_linear;
            a[(bi, pi)] -= tie_linear;
            a[(pi, bi)] -= tie_linear;
        }
    }
}

/// Each bone's affine fit from the solution (its transform about its own joint).
fn bone_fits(sol: &DMatrix<f64>, joints: &[V3]) -> Vec<BoneFit> {
    (0..sol.nrows() / 4)
        .map(|b| {
            let mut linear = Matrix3::zeros();
            let mut translation = V3::zeros();
            for d in 0..3 {
                for i in 0..3 {
                    linear[(d, i)] = sol[(4 * b + i, d)];
                }
                translation[d] = sol[(4 * b + 3, d)];
            }
            let translation = translation - linear * joints[b];
            BoneFit {
                linear,
                translation,
                rotation: polar_rotation(&linear),
            }
        })
        .collect()
}

/// The rotation nearest `m` (its polar decomposition's), a proper one even if `m`
/// mirrors.
fn polar_rotation(m: &Matrix3<f64>) -> Rotation3<f64> {
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        let mut u = u;
        u.column_mut(2).neg_mut();
        r = u * vt;
    }
    Rotation3::from_matrix_unchecked(r)
}

impl Posed<'_> {
    /// Where the parts carry rest vertex `v` (its skin weights blended).
    pub fn carried(&self, v: u32) -> V3 {
        let w = &self.art.weights[v as usize];
        w.iter()
            .map(|&(b, wt)| self.bones[b as usize].apply(&self.art.rest[v as usize]) * wt)
            .sum::<V3>()
            / w.iter().map(|&(_, wt)| wt).sum::<f64>().max(1e-12)
    }

    /// A rest direction `d` at vertex `v` turned as the parts there turn (unit).
    pub fn turned(&self, v: u32, d: &V3) -> V3 {
        let w = &self.art.weights[v as usize];
        let sum = w
            .iter()
            .map(|&(b, wt)| self.bones[b as usize].rotation * d * wt)
            .sum::<V3>();
        sum.try_normalize(0.0).unwrap_or(*d)
    }

    /// Rest position of vertex `v`.
    pub fn rest(&self, v: u32) -> V3 {
        self.art.rest[v as usize]
    }

    /// `mesh` (the one fitted) with every joint's rotation taken out.
    pub fn normalised_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh {
            vertices: self.normalised.clone(),
            ..mesh.clone()
        }
    }

    /// The floor under the subject with the joints' rotations taken out, along
    /// [`Posed::up`], for a frame whose floor is at `frame_floor`. Soles fitted to data
    /// stand on the frame's floor, and the floor is the lowest normalised point (the
    /// soles with the feet's turns taken out). Soles below the frame's floor (the median
    /// of those the subject stands on, by more than 0.5% of its height) were filled, not
    /// seen: no camera sees through a floor. Their depth varies from fit to fit (2.7-4.0
    /// cm from stance to stance on the booth's people), and so does the feet's own turn
    /// fitted on them; the floor is then where the feet stand moved as their joints move
    /// (the ankle, not the sole), the filled soles raised to the frame's floor.
    pub fn floor(&self, frame_floor: f64) -> f64 {
        if !(self.sole < frame_floor - 0.005 * self.extent) {
            return self.lowest;
        }
        median(
            self.contact
                .iter()
                .map(|&(h, shift)| h.max(frame_floor) + shift)
                .collect(),
        )
        .unwrap_or(self.lowest)
    }

    /// Vertex `v` with the joints' rotations taken out.
    pub fn normalised(&self, v: u32) -> V3 {
        self.normalised[v as usize]
    }

    /// Each bone's rotation from rest, degrees (for reports and tests).
    pub fn bone_angles(&self) -> Vec<(String, f64)> {
        self.art
            .names
            .iter()
            .zip(&self.bones)
            .map(|(n, t)| {
                (
                    n.clone(),
                    crate::mesh::transform::rotation_angle(&t.rotation).to_degrees(),
                )
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::template::{self, Kind, figure::Pose};

    #[test]
    fn a_posture_skinning_made_is_taken_out_exactly() {
        let fig = template::build(Kind::Pig, 3000);
        let pose = Pose {
            joints: vec![
                ("neck".into(), V3::y(), -25.0),
                ("chest".into(), V3::z(), 15.0),
                ("leg_fl".into(), V3::y(), 20.0),
            ],
            ..Default::default()
        };
        let mut posed = fig.mesh.clone();
        posed.vertices = fig.pose(&pose);
        let art = Articulation::from_figure(&fig, V3::z());
        let p = art.fit(&posed).unwrap();
        let worst = (0..fig.mesh.vertices.len())
            .map(|v| (p.normalised(v as u32) - fig.mesh.vertices[v]).norm())
            .fold(0.0, f64::max);
        // the weak tie between parts is all that is left
        assert!(worst < 1e-5 * fig.mesh.diagonal(), "worst {worst}");
    }

    #[test]
    fn soles_filled_below_the_floor_do_not_lower_it() {
        // the generic body standing on z = 0, one leg swung forward at the hip; then the
        // same with the soles sunk 3 cm into the floor (filled where no camera sees)
        let fig = template::build(Kind::Body, 3000);
        let pose = Pose {
            joints: vec![("thigh_l".into(), V3::y(), -12.0)],
            ..Default::default()
        };
        let mut posed = fig.mesh.clone();
        posed.vertices = fig.pose(&pose);
        let low = posed
            .vertices
            .iter()
            .map(|p| p.z)
            .fold(f64::INFINITY, f64::min);
        for p in &mut posed.vertices {
            p.z -= low;
        }
        let art = Articulation::from_figure(&fig, V3::z());
        let seen = art.fit(&posed).unwrap().floor(0.0);
        let mut sunk = posed.clone();
        for p in &mut sunk.vertices {
            if p.z < 0.02 {
                p.z -= 0.03;
            }
        }
        let sunk = art.fit(&sunk).unwrap();
        let filled = sunk.floor(0.0);
        // the fault this guards: the lowest normalised point went down with the soles
        assert!(sunk.lowest < seen - 0.02, "lowest {}", sunk.lowest);
        // where the soles truly stand (the frame's floor)
        assert!(filled.abs() < 0.005, "filled soles: floor {filled}");
    }
}
