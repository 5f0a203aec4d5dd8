//! A template's rig: its bones (joint, parent, how far the joint turns), skin weights and
//! shape fields, kept in one JSON file beside the mesh (`conformd-rig`, version 1). The
//! generic templates' rig comes from the skeleton they are built from; any other mesh gets
//! an automatic one (limbs at its geodesic extremities, joints where a limb meets the
//! body and half-way down it, weights falling off along the surface). Posing and
//! reshaping through a rig keep the vertex order.

use crate::files::FileError;
use crate::mesh::{Mesh, V3, topology};
use nalgebra::{Rotation3, Unit};
use std::path::Path;

/// File format name and version written in every rig file.
pub const FORMAT: &str = "conformd-rig";
pub const VERSION: u32 = 1;
/// Largest rig file read: a 200,000-vertex template with a dozen shape fields.
pub const MAX_RIG_BYTES: u64 = 1 << 30;
/// Widest turn a joint may be given, degrees.
pub const MAX_LIMIT_DEG: f64 = 180.0;

/// One bone: it turns about its `head` (the joint) and points to its `tail`.
#[derive(Debug, Clone, PartialEq)]
pub struct RigBone {
    pub name: String,
    /// an earlier bone (bones are listed parents first)
    pub parent: Option<usize>,
    pub head: V3,
    pub tail: V3,
    /// the largest turn from the rest pose, degrees, about any axis (0: the bone only
    /// follows its parent; the root's turn is the fit's global rotation)
    pub limit_deg: f64,
}

/// A shape factor: `rest + (f - 1) * vertices` is the template at factor f, and each
/// bone's head moves by `(f - 1) * heads[b]`.
#[derive(Debug, Clone, PartialEq)]
pub struct ShapeField {
    pub name: String,
    /// the factors the template takes without folding
    pub range: (f64, f64),
    pub vertices: Vec<V3>,
    pub heads: Vec<V3>,
}

/// Where a rig came from.
#[derive(Debug, Clone, PartialEq)]
pub enum RigSource {
    /// a generic template's skeleton (`pig`, `body`)
    Generic(String),
    /// found on the mesh by [`TemplateRig::automatic`]
    Automatic,
    /// read from a file, with what the file said it was
    File(String),
}

impl std::fmt::Display for RigSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RigSource::Generic(k) => write!(f, "the generic {k}'s skeleton"),
            RigSource::Automatic => write!(f, "automatic"),
            RigSource::File(p) => write!(f, "{p}"),
        }
    }
}

/// A rig for a mesh of `weights.len()` vertices.
#[derive(Debug, Clone, PartialEq)]
pub struct TemplateRig {
    pub source: RigSource,
    pub bones: Vec<RigBone>,
    /// per vertex: (bone, weight), weights positive and summing to 1
    pub weights: Vec<Vec<(u32, f64)>>,
    pub shapes: Vec<ShapeField>,
}

/// A pose of a rig: each bone's turn about its joint, in its parent's frame at rest
/// (identity = rest), and a factor per shape field (1 = rest).
#[derive(Debug, Clone, PartialEq)]
pub struct RigPose {
    pub turns: Vec<Rotation3<f64>>,
    pub factors: Vec<f64>,
}

impl RigPose {
    pub fn rest(rig: &TemplateRig) -> RigPose {
        RigPose {
            turns: vec![Rotation3::identity(); rig.bones.len()],
            factors: vec![1.0; rig.shapes.len()],
        }
    }
}

/// What breaks a rig's promises for its mesh; names the element at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RigCheckError {
    #[error("no bones")]
    NoBones,
    #[error("{0} bones: at most {max}", max = u16::MAX)]
    TooManyBones(usize),
    #[error("bone {0}: an empty name")]
    EmptyBoneName(usize),
    #[error("bone {index} ('{name}'): {fault}")]
    Bone {
        index: usize,
        name: String,
        fault: BoneFault,
    },
    #[error("weights for {got} vertices, the mesh has {vertices}")]
    WeightCount { got: usize, vertices: usize },
    #[error("vertex {vertex}: {fault}")]
    Weights { vertex: usize, fault: WeightFault },
    #[error("shape {0}: an empty name")]
    EmptyShapeName(usize),
    #[error("shape {index} ('{name}'): {fault}")]
    Shape {
        index: usize,
        name: String,
        fault: ShapeFault,
    },
    #[error("a rig needs a mesh with triangles")]
    NoTriangles,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoneFault {
    #[error("the name is given twice")]
    NameTwice,
    #[error("its parent must be listed before it (bones are listed parents first)")]
    ParentAfter,
    #[error("only the first bone is the root")]
    SecondRoot,
    #[error("the first bone is the root")]
    RootWithParent,
    #[error("head and tail must be finite coordinates within 1e9")]
    NotFinite,
    #[error("limit_deg {0} is not 0 to {MAX_LIMIT_DEG}")]
    Limit(f64),
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum WeightFault {
    #[error("no weights")]
    None,
    #[error("bone {bone}, but the rig has {bones} bones")]
    Bone { bone: u32, bones: usize },
    #[error("weight {0} is not in (0, 1]")]
    Weight(f64),
    #[error("weights sum to {0}, not 1")]
    Sum(f64),
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShapeFault {
    #[error("the name is given twice")]
    NameTwice,
    #[error("range [{0}, {1}] must be positive and hold 1")]
    Range(f64, f64),
    #[error("{got} vertex offsets, the mesh has {vertices}")]
    VertexOffsets { got: usize, vertices: usize },
    #[error("{got} head offsets, the rig has {bones} bones")]
    HeadOffsets { got: usize, bones: usize },
    #[error("vertex {0}'s offset is not finite")]
    VertexNotFinite(usize),
    #[error("bone {0}'s head offset is not finite")]
    HeadNotFinite(usize),
}

impl TemplateRig {
    /// Checks everything a rig promises for a mesh of `vertices` vertices; the message
    /// names the element at fault.
    pub fn check(&self, vertices: usize) -> Result<(), RigCheckError> {
        let nb = self.bones.len();
        if nb == 0 {
            return Err(RigCheckError::NoBones);
        }
        if nb > u16::MAX as usize {
            return Err(RigCheckError::TooManyBones(nb));
        }
        let finite = |p: &V3| p.iter().all(|x| x.is_finite() && x.abs() <= 1e9);
        for (i, b) in self.bones.iter().enumerate() {
            let bad = |fault: BoneFault| {
                Err(RigCheckError::Bone {
                    index: i,
                    name: b.name.clone(),
                    fault,
                })
            };
            if b.name.trim().is_empty() {
                return Err(RigCheckError::EmptyBoneName(i));
            }
            if self.bones[..i].iter().any(|o| o.name == b.name) {
                return bad(BoneFault::NameTwice);
            }
            match b.parent {
                Some(p) if p >= i => return bad(BoneFault::ParentAfter),
                None if i > 0 => return bad(BoneFault::SecondRoot),
                Some(_) if i == 0 => return bad(BoneFault::RootWithParent),
                _ => {}
            }
            if !finite(&b.head) || !finite(&b.tail) {
                return bad(BoneFault::NotFinite);
            }
            if !(0.0..=MAX_LIMIT_DEG).contains(&b.limit_deg) {
                return bad(BoneFault::Limit(b.limit_deg));
            }
        }
        if self.weights.len() != vertices {
            return Err(RigCheckError::WeightCount {
                got: self.weights.len(),
                vertices,
            });
        }
        for (v, w) in self.weights.iter().enumerate() {
            let bad = |fault: WeightFault| Err(RigCheckError::Weights { vertex: v, fault });
            if w.is_empty() {
                return bad(WeightFault::None);
            }
            let mut sum = 0.0;
            for &(b, x) in w {
                if b as usize >= nb {
                    return bad(WeightFault::Bone { bone: b, bones: nb });
                }
                if !(x.is_finite() && x > 0.0 && x <= 1.0 + 1e-6) {
                    return bad(WeightFault::Weight(x));
                }
                sum += x;
            }
            if (sum - 1.0).abs() > 1e-3 {
                return bad(WeightFault::Sum(sum));
            }
        }
        for (k, s) in self.shapes.iter().enumerate() {
            let bad = |fault: ShapeFault| {
                Err(RigCheckError::Shape {
                    index: k,
                    name: s.name.clone(),
                    fault,
                })
            };
            if s.name.trim().is_empty() {
                return Err(RigCheckError::EmptyShapeName(k));
            }
            if self.shapes[..k].iter().any(|o| o.name == s.name) {
                return bad(ShapeFault::NameTwice);
            }
            let (lo, hi) = s.range;
            if !(lo.is_finite() && hi.is_finite() && 0.0 < lo && lo <= 1.0 && 1.0 <= hi) {
                return bad(ShapeFault::Range(lo, hi));
            }
            if s.vertices.len() != vertices {
                return bad(ShapeFault::VertexOffsets {
                    got: s.vertices.len(),
                    vertices,
                });
            }
            if s.heads.len() != nb {
                return bad(ShapeFault::HeadOffsets {
                    got: s.heads.len(),
                    bones: nb,
                });
            }
            if let Some(i) = s.vertices.iter().position(|p| !finite(p)) {
                return bad(ShapeFault::VertexNotFinite(i));
            }
            if let Some(i) = s.heads.iter().position(|p| !finite(p)) {
                return bad(ShapeFault::HeadNotFinite(i));
            }
        }
        Ok(())
    }

    pub fn bone(&self, name: &str) -> Option<usize> {
        self.bones.iter().position(|b| b.name == name)
    }

    /// Each vertex's bone of largest weight.
    pub fn dominant_bones(&self) -> Vec<u32> {
        self.weights
            .iter()
            .map(|w| {
                w.iter()
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .map_or(0, |x| x.0)
            })
            .collect()
    }

    /// The rest vertices and bone heads at shape `factors` (1 = rest).
    pub fn reshape(&self, rest: &[V3], factors: &[f64]) -> (Vec<V3>, Vec<V3>) {
        let mut v = rest.to_vec();
        let mut heads: Vec<V3> = self.bones.iter().map(|b| b.head).collect();
        for (s, &f) in self.shapes.iter().zip(factors) {
            if f == 1.0 {
                continue;
            }
            for (p, d) in v.iter_mut().zip(&s.vertices) {
                *p += d * (f - 1.0);
            }
            for (h, d) in heads.iter_mut().zip(&s.heads) {
                *h += d * (f - 1.0);
            }
        }
        (v, heads)
    }

    /// Each bone's transform `x -> R x + t` for joint turns `turns` about `heads`,
    /// composed down the hierarchy.
    pub fn bone_transforms(
        &self,
        heads: &[V3],
        turns: &[Rotation3<f64>],
    ) -> Vec<(Rotation3<f64>, V3)> {
        let mut xf: Vec<(Rotation3<f64>, V3)> = Vec::with_capacity(self.bones.len());
        for (b, bone) in self.bones.iter().enumerate() {
            let local = turns.get(b).copied().unwrap_or_else(Rotation3::identity);
            let (pr, pt) = bone
                .parent
                .map_or((Rotation3::identity(), V3::zeros()), |p| xf[p]);
            let h = heads[b];
            xf.push((pr * local, pr * (h - local * h) + pt));
        }
        xf
    }

    /// Bone `upper` turned (from rest) to point along `upper_to` and its child `lower`
    /// along `lower_to`, both directions in the rig's rest frame (the limb's parents'
    /// turns in `pose` not counted); `None` when a bone has no length or would turn
    /// exactly round.
    pub fn point_limb(
        &self,
        pose: &mut RigPose,
        (upper, lower): (usize, usize),
        upper_to: V3,
        lower_to: V3,
    ) -> Option<()> {
        let dir = |b: usize| (self.bones[b].tail - self.bones[b].head).try_normalize(1e-12);
        let upper_turn = Rotation3::rotation_between(&dir(upper)?, &upper_to)?;
        // the lower bone's turn is in the upper bone's frame
        let lower_turn =
            Rotation3::rotation_between(&dir(lower)?, &(upper_turn.inverse() * lower_to))?;
        pose.turns[upper] = upper_turn;
        pose.turns[lower] = lower_turn;
        Some(())
    }

    /// The rest vertices `rest` reshaped and posed by `pose` (linear blend skinning);
    /// same order.
    pub fn pose(&self, rest: &[V3], pose: &RigPose) -> Vec<V3> {
        let (v, heads) = self.reshape(rest, &pose.factors);
        let xf = self.bone_transforms(&heads, &pose.turns);
        v.iter()
            .zip(&self.weights)
            .map(|(p, w)| {
                w.iter()
                    .map(|&(b, x)| (xf[b as usize].0 * p + xf[b as usize].1) * x)
                    .sum::<V3>()
            })
            .collect()
    }
}

// ---- the generic templates' rig ----

/// How far each of the generic templates' joints turns from rest, degrees: the root
/// none (the fit's global rotation turns it), rigid parts of the face little.
fn generic_limit(name: &str) -> f64 {
    let base = name.trim_end_matches("_l").trim_end_matches("_r");
    let base = base
        .strip_suffix("_fl")
        .or_else(|| base.strip_suffix("_fr"))
        .or_else(|| base.strip_suffix("_hl"))
        .or_else(|| base.strip_suffix("_hr"))
        .unwrap_or(base);
    match base {
        "rump" | "pelvis" => 0.0,
        "nose" | "chin" | "snout" => 10.0,
        "chest" => 40.0,
        "neck" | "head" | "hoof" | "foot" | "shoulder" => 50.0,
        "ear" | "leg" | "hand" => 70.0,
        "tail" | "shank" => 90.0,
        "thigh" => 110.0,
        "shin" | "forearm" => 150.0,
        "upper_arm" => 160.0,
        _ => 45.0,
    }
}

impl TemplateRig {
    /// The rig of a generic template: its skeleton's bones, its skin weights and its
    /// shape fields (each bone's head moved by the field's mean near it).
    pub fn generic(fig: &super::figure::Figure, kind: super::Kind) -> TemplateRig {
        let skel = &fig.skeleton;
        let bones: Vec<RigBone> = skel
            .bones
            .iter()
            .map(|b| RigBone {
                name: b.name.clone(),
                parent: b.parent,
                head: b.head,
                tail: b.tail,
                limit_deg: generic_limit(&b.name),
            })
            .collect();
        let v = &fig.mesh.vertices;
        let shapes = super::shape_parameters(kind)
            .into_iter()
            .filter_map(|name| {
                let field = super::shape_field(fig, kind, name)?;
                let heads = skel
                    .bones
                    .iter()
                    .map(|b| {
                        // the field's mean over the skin around the joint, nearest most
                        let sigma = 1.5 * b.r_head.max(1e-6);
                        let (sum, wsum) =
                            v.iter()
                                .zip(&field)
                                .fold((V3::zeros(), 0.0), |(s, ws), (p, d)| {
                                    let w = (-(p - b.head).norm_squared() / (2.0 * sigma * sigma))
                                        .exp();
                                    (s + d * w, ws + w)
                                });
                        if wsum > 1e-12 {
                            sum / wsum
                        } else {
                            V3::zeros()
                        }
                    })
                    .collect();
                Some(ShapeField {
                    name: name.to_string(),
                    range: (*super::SHAPE_FACTORS.start(), *super::SHAPE_FACTORS.end()),
                    vertices: field,
                    heads,
                })
            })
            .collect();
        TemplateRig {
            source: RigSource::Generic(
                match kind {
                    super::Kind::Pig => "pig",
                    super::Kind::Body => "body",
                }
                .into(),
            ),
            bones,
            weights: fig.weights.clone(),
            shapes,
        }
    }
}

// ---- the automatic rig ----

/// Settings of the automatic rig.
#[derive(Debug, Clone, Copy)]
pub struct AutoRigSettings {
    /// geodesic extremities tried as limbs
    pub limbs: usize,
    /// a limb ends where its cross-section grows past this many times its own width near
    /// the tip (where it meets the body)
    pub widening: f64,
    /// how far each limb joint turns, degrees
    pub limit_deg: f64,
}

impl Default for AutoRigSettings {
    fn default() -> Self {
        AutoRigSettings {
            limbs: 10,
            widening: 1.6,
            limit_deg: 90.0,
        }
    }
}

/// Shares of the tip-to-centre path at which a limb's cross-section is measured.
const SHARES: std::ops::RangeInclusive<usize> = 2..=18;
const SHARE_STEP: f64 = 0.05;
/// A limb shorter than this share of its tip-to-centre path is a bump, not a limb.
const MIN_LIMB_SHARE: f64 = 0.2;
/// A limb's cross-sections are narrower than this share of their distance from its tip
/// (a disc's are about as wide as that distance).
const MAX_BUMP_SPREAD: f64 = 0.6;
/// Half the width of the band a joint's turn fades over, as a share of the path.
const BAND_SHARE: f64 = 0.06;
/// ... and at least this many times the limb's radius there.
const BAND_RADII: f64 = 0.8;

fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The vertices whose distance from the tip is within `half` of `d`, their centroid and
/// their mean distance from it.
fn cut(v: &[V3], from_tip: &[f64], d: f64, half: f64) -> Option<(Vec<u32>, V3, f64)> {
    let ring: Vec<u32> = (0..v.len())
        .filter(|&i| (from_tip[i] - d).abs() < half)
        .map(|i| i as u32)
        .collect();
    if ring.len() < 3 {
        return None;
    }
    let c = ring.iter().map(|&i| v[i as usize]).sum::<V3>() / ring.len() as f64;
    let r = ring
        .iter()
        .map(|&i| (v[i as usize] - c).norm())
        .sum::<f64>()
        / ring.len() as f64;
    Some((ring, c, r))
}

/// One limb found on a mesh: where it starts and bends, and how much of each vertex it
/// moves (1 beyond the joint, 0 before it).
struct FoundLimb {
    tip: u32,
    root: V3,
    middle: V3,
    root_share: Vec<f64>,
    middle_share: Vec<f64>,
}

impl TemplateRig {
    /// An automatic rig for any mesh: a root bone at the body's centre; for each geodesic
    /// extremity that is a limb (thin near its tip, widening where it meets the body), an
    /// upper bone from where it meets the body and a lower bone from half-way to its tip,
    /// parented to the bone that holds its root; weights falling off along the surface;
    /// a length field per limb. A mesh without limbs (a sphere) gets the root alone.
    pub fn automatic(mesh: &Mesh, s: &AutoRigSettings) -> Result<TemplateRig, RigCheckError> {
        let v = &mesh.vertices;
        if v.is_empty() || mesh.triangles.is_empty() {
            return Err(RigCheckError::NoTriangles);
        }
        let nb = topology::vertex_neighbours(v.len(), &mesh.triangles);
        let c = v.iter().sum::<V3>() / v.len() as f64;
        let (_, from_centre) = topology::centre_distances(v, &nb);
        let mut nearest = from_centre.clone();
        let mut found: Vec<FoundLimb> = Vec::new();
        for _ in 0..s.limbs {
            let Some(tip) = topology::farthest_sample(&nearest) else {
                break;
            };
            let length = from_centre[tip];
            let from_tip = topology::edge_distances(v, &nb, &[tip as u32]).0;
            for (n, d) in nearest.iter_mut().zip(&from_tip) {
                *n = n.min(*d);
            }
            if let Some(limb) = Self::limb_at(v, tip as u32, length, &from_tip, s) {
                found.push(limb);
            }
        }
        // bones: the root, then each limb's upper and lower bone
        let mut bones = vec![RigBone {
            name: "body".into(),
            parent: None,
            head: c,
            tail: c + V3::new(0.0, 0.0, 1e-3 * mesh.diagonal().max(1e-9)),
            limit_deg: 0.0,
        }];
        // membership[b][i]: the share of vertex i that bone b and its descendants move
        let mut membership: Vec<Vec<f64>> = vec![vec![1.0; v.len()]];
        for (k, limb) in found.iter().enumerate() {
            // the parent: the bone that holds most of the limb's root
            let at_root: Vec<usize> = (0..v.len())
                .filter(|&i| limb.root_share[i] > 0.0 && limb.root_share[i] < 1.0)
                .collect();
            let parent = (0..bones.len())
                .rev()
                .find(|&b| {
                    b > 0
                        && !at_root.is_empty()
                        && at_root.iter().map(|&i| membership[b][i]).sum::<f64>()
                            > 0.5 * at_root.len() as f64
                })
                .unwrap_or(0);
            let name = format!("limb{}", k + 1);
            let tip = v[limb.tip as usize];
            bones.push(RigBone {
                name: format!("{name}_upper"),
                parent: Some(parent),
                head: limb.root,
                tail: limb.middle,
                limit_deg: s.limit_deg,
            });
            membership.push(limb.root_share.clone());
            bones.push(RigBone {
                name: format!("{name}_lower"),
                parent: Some(bones.len() - 1),
                head: limb.middle,
                tail: tip,
                limit_deg: s.limit_deg,
            });
            membership.push(limb.middle_share.clone());
        }
        let weights = weights_from_membership(&bones, &membership);
        let shapes = found
            .iter()
            .enumerate()
            .map(|(k, limb)| {
                let upper = 1 + 2 * k;
                let axis = (v[limb.tip as usize] - limb.root)
                    .try_normalize(1e-12)
                    .unwrap_or_else(V3::z);
                let along = |p: &V3| axis * (p - limb.root).dot(&axis);
                let vertices = v
                    .iter()
                    .zip(&limb.root_share)
                    .map(|(p, &m)| along(p) * m)
                    .collect();
                let heads = bones
                    .iter()
                    .enumerate()
                    .map(|(b, bone)| {
                        if descends(&bones, b, upper) && b != upper {
                            along(&bone.head)
                        } else {
                            V3::zeros()
                        }
                    })
                    .collect();
                ShapeField {
                    name: format!("limb{}_length", k + 1),
                    range: (0.7, 1.4),
                    vertices,
                    heads,
                }
            })
            .collect();
        let rig = TemplateRig {
            source: RigSource::Automatic,
            bones,
            weights,
            shapes,
        };
        rig.check(v.len())?;
        Ok(rig)
    }

    /// The limb from `tip`, if the surface around it is one: its cross-sections measured
    /// at steps along the path to the centre, its root where they widen past
    /// `s.widening` times its width near the tip.
    fn limb_at(
        v: &[V3],
        tip: u32,
        length: f64,
        from_tip: &[f64],
        s: &AutoRigSettings,
    ) -> Option<FoundLimb> {
        let half = 0.5 * SHARE_STEP * length;
        let mut sections: Vec<(f64, V3, f64)> = Vec::new();
        for k in SHARES {
            let share = k as f64 * SHARE_STEP;
            let Some((_, c, r)) = cut(v, from_tip, share * length, half) else {
                break;
            };
            sections.push((share, c, r));
        }
        // the limb ends where its cross-section grows past `widening` times the narrowest
        // one so far (a hand or a hoof near the tip may be wider than the limb)
        let mut narrowest = f64::INFINITY;
        let mut end = sections.len();
        for (k, &(share, _, r)) in sections.iter().enumerate() {
            if share >= MIN_LIMB_SHARE - 1e-9 && r > s.widening * narrowest {
                end = k;
                break;
            }
            if share >= 0.2 - 1e-9 {
                narrowest = narrowest.min(r);
            }
        }
        // the joint a step before the widening: the body's own surface is not the limb's
        let root = end.checked_sub(1)?;
        let (root_share, root_at, root_radius) = sections[root];
        if root_share < MIN_LIMB_SHARE {
            return None;
        }
        // a bump on the body (a belly, a chest) is a disc: its cross-sections grow with
        // the distance from its tip, where a limb's stay as wide as the limb
        let mut spread: Vec<f64> = sections[..=root]
            .iter()
            .filter(|x| x.0 >= 0.15 - 1e-9)
            .map(|x| x.2 / (x.0 * length))
            .collect();
        spread.sort_by(f64::total_cmp);
        if spread
            .get(spread.len() / 2)
            .is_some_and(|&m| m > MAX_BUMP_SPREAD)
        {
            return None;
        }
        let middle_share = root_share / 2.0;
        let (_, middle_at, middle_radius) = cut(v, from_tip, middle_share * length, half)?;
        // a turn fading over less than the limb's thickness folds the inside of the bend
        let share_beyond = |d: f64, radius: f64| {
            let band = (BAND_SHARE * length).max(BAND_RADII * radius);
            from_tip
                .iter()
                .map(|&t| smoothstep((d + band - t) / (2.0 * band)))
                .collect::<Vec<f64>>()
        };
        Some(FoundLimb {
            tip,
            root: root_at,
            middle: middle_at,
            root_share: share_beyond(root_share * length, root_radius),
            middle_share: share_beyond(middle_share * length, middle_radius),
        })
    }
}

// ---- per-bone proportions ----

/// Factors a bone's length and girth fields take in the fit.
pub const BONE_FIELD_RANGE: (f64, f64) = (0.6, 1.6);
/// Bones shorter than this share of the template's diagonal get no fields.
const MIN_FIELD_BONE: f64 = 0.01;

impl TemplateRig {
    /// This rig with two shape fields per bone appended: `<bone>.length` stretches the
    /// bone along its axis (everything below it follows), `<bone>.girth` widens its own
    /// skin about its axis (the limbs hanging off it move out with it). A subject of
    /// other proportions (a cow for a pig, one person for another) is then reached by
    /// the rig, not left to the springs. `rest` is the template the rig belongs to.
    pub fn with_bone_fields(&self, rest: &[V3]) -> TemplateRig {
        let nb = self.bones.len();
        let below: Vec<Vec<bool>> = (0..nb)
            .map(|b| (0..nb).map(|d| descends(&self.bones, d, b)).collect())
            .collect();
        // per vertex, per bone: the weight it and its descendants carry
        let share = |p: usize, b: usize| -> f64 {
            self.weights[p]
                .iter()
                .filter(|&&(d, _)| below[b][d as usize])
                .map(|x| x.1)
                .sum()
        };
        let own = |p: usize, b: usize| -> f64 {
            self.weights[p]
                .iter()
                .filter(|&&(d, _)| d as usize == b)
                .map(|x| x.1)
                .sum()
        };
        let mut out = self.clone();
        let (lo, hi) = rest.iter().fold(
            (V3::repeat(f64::INFINITY), V3::repeat(f64::NEG_INFINITY)),
            |(lo, hi), p| (lo.inf(p), hi.sup(p)),
        );
        let shortest = MIN_FIELD_BONE * (hi - lo).norm();
        for (b, bone) in self.bones.iter().enumerate() {
            let length = (bone.tail - bone.head).norm();
            // a bone this short has no axis to stretch or widen about (the automatic
            // rig's root is a stub)
            if !(length >= shortest) {
                continue;
            }
            let axis = (bone.tail - bone.head) / length;
            let along = |q: &V3| axis * (q - bone.head).dot(&axis).clamp(0.0, length);
            let radial = |q: &V3| {
                let r = q - bone.head;
                r - axis * r.dot(&axis)
            };
            // the child of `b` each descendant hangs from
            let child_of = |mut d: usize| -> Option<usize> {
                while let Some(p) = self.bones[d].parent {
                    if p == b {
                        return Some(d);
                    }
                    d = p;
                }
                None
            };
            let length_field = ShapeField {
                name: format!("{}.length", bone.name),
                range: BONE_FIELD_RANGE,
                vertices: rest
                    .iter()
                    .enumerate()
                    .map(|(p, q)| {
                        let s = share(p, b);
                        if s > 0.0 { along(q) * s } else { V3::zeros() }
                    })
                    .collect(),
                heads: (0..nb)
                    .map(|d| {
                        if below[b][d] && d != b {
                            along(&self.bones[d].head)
                        } else {
                            V3::zeros()
                        }
                    })
                    .collect(),
            };
            let children: Vec<usize> = (0..nb)
                .filter(|&c| self.bones[c].parent == Some(b))
                .collect();
            let girth_field = ShapeField {
                name: format!("{}.girth", bone.name),
                range: BONE_FIELD_RANGE,
                vertices: rest
                    .iter()
                    .enumerate()
                    .map(|(p, q)| {
                        let mut d = radial(q) * own(p, b);
                        for &c in &children {
                            let s = share(p, c);
                            if s > 0.0 {
                                d += radial(&self.bones[c].head) * s;
                            }
                        }
                        d
                    })
                    .collect(),
                heads: (0..nb)
                    .map(|d| match child_of(d) {
                        Some(c) if d != b => radial(&self.bones[c].head),
                        _ => V3::zeros(),
                    })
                    .collect(),
            };
            out.shapes.push(length_field);
            out.shapes.push(girth_field);
        }
        out
    }
}

/// Whether bone `b` is `ancestor` or below it.
fn descends(bones: &[RigBone], mut b: usize, ancestor: usize) -> bool {
    loop {
        if b == ancestor {
            return true;
        }
        match bones[b].parent {
            Some(p) => b = p,
            None => return false,
        }
    }
}

/// Skin weights from each bone's membership (the share it and its descendants move):
/// a bone keeps its membership less its children's; shares that overlap between limbs
/// are normalised.
fn weights_from_membership(bones: &[RigBone], membership: &[Vec<f64>]) -> Vec<Vec<(u32, f64)>> {
    let nv = membership[0].len();
    let mut children: Vec<Vec<usize>> = vec![Vec::new(); bones.len()];
    for (b, bone) in bones.iter().enumerate() {
        if let Some(p) = bone.parent {
            children[p].push(b);
        }
    }
    (0..nv)
        .map(|i| {
            let mut w: Vec<(u32, f64)> = (0..bones.len())
                .filter_map(|b| {
                    let own = membership[b][i]
                        - children[b].iter().map(|&c| membership[c][i]).sum::<f64>();
                    (own > 1e-4).then_some((b as u32, own))
                })
                .collect();
            let sum: f64 = w.iter().map(|x| x.1).sum();
            if sum <= 0.0 {
                return vec![(0, 1.0)];
            }
            for x in &mut w {
                x.1 /= sum;
            }
            w
        })
        .collect()
}

// ---- the file ----

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct RigFile {
    format: String,
    version: u32,
    /// what the rig was made from
    source: String,
    vertices: usize,
    bones: Vec<BoneFile>,
    /// per vertex: [bone index, weight] pairs
    weights: Vec<Vec<(u32, f64)>>,
    #[serde(default)]
    shapes: Vec<ShapeFile>,
}

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct BoneFile {
    name: String,
    parent: Option<String>,
    head: [f64; 3],
    tail: [f64; 3],
    limit_deg: f64,
}

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ShapeFile {
    name: String,
    range: [f64; 2],
    /// per vertex offset at factor 2
    vertices: Vec<[f64; 3]>,
    /// per bone head offset at factor 2
    heads: Vec<[f64; 3]>,
}

fn arr(p: &V3) -> [f64; 3] {
    // six significant digits past the metre are beyond any scan
    let r = |x: f64| (x * 1e7).round() / 1e7;
    [r(p.x), r(p.y), r(p.z)]
}

impl TemplateRig {
    /// The rig as its JSON file.
    pub fn to_json(&self) -> String {
        let file = RigFile {
            format: FORMAT.into(),
            version: VERSION,
            source: match &self.source {
                RigSource::Generic(k) => format!("generic {k}"),
                RigSource::Automatic => "automatic".into(),
                RigSource::File(s) => s.clone(),
            },
            vertices: self.weights.len(),
            bones: self
                .bones
                .iter()
                .map(|b| BoneFile {
                    name: b.name.clone(),
                    parent: b.parent.map(|p| self.bones[p].name.clone()),
                    head: arr(&b.head),
                    tail: arr(&b.tail),
                    limit_deg: b.limit_deg,
                })
                .collect(),
            weights: self
                .weights
                .iter()
                .map(|w| {
                    w.iter()
                        .map(|&(b, x)| (b, (x * 1e6).round() / 1e6))
                        .collect()
                })
                .collect(),
            shapes: self
                .shapes
                .iter()
                .map(|s| ShapeFile {
                    name: s.name.clone(),
                    range: [s.range.0, s.range.1],
                    vertices: s.vertices.iter().map(arr).collect(),
                    heads: s.heads.iter().map(arr).collect(),
                })
                .collect(),
        };
        serde_json::to_string(&file).expect("a rig serialises")
    }

    /// Reads a rig file and checks it against a mesh of `vertices` vertices. Weights are
    /// renormalised after the file's rounding.
    pub fn read(path: &Path, vertices: usize) -> Result<TemplateRig, FileError> {
        let name = path.display().to_string();
        let text = crate::files::read_text_limited(path, MAX_RIG_BYTES)?;
        Self::parse(&text, &name, vertices)
    }

    /// A rig from its JSON text (`name` is what errors call it).
    pub fn parse(text: &str, name: &str, vertices: usize) -> Result<TemplateRig, FileError> {
        let file: RigFile = serde_json::from_str(text)
            .map_err(|e| FileError::line(name, e.line(), format!("not a rig file: {e}")))?;
        if file.format != FORMAT {
            return Err(FileError::content(
                name,
                format!("format '{}', expected '{FORMAT}'", file.format),
            ));
        }
        if file.version != VERSION {
            return Err(FileError::content(
                name,
                format!(
                    "version {} of the rig format; this conformd reads version {VERSION}",
                    file.version
                ),
            ));
        }
        if file.vertices != vertices {
            return Err(FileError::content(
                name,
                format!(
                    "a rig for a mesh of {} vertices; the template has {vertices}",
                    file.vertices
                ),
            ));
        }
        let mut bones: Vec<RigBone> = Vec::with_capacity(file.bones.len());
        for (i, b) in file.bones.iter().enumerate() {
            let parent = match &b.parent {
                None => None,
                Some(p) => Some(bones.iter().position(|o| &o.name == p).ok_or_else(|| {
                    FileError::content(
                        name,
                        format!(
                            "bone {i} ('{}'): parent '{p}' is not a bone listed before it",
                            b.name
                        ),
                    )
                })?),
            };
            bones.push(RigBone {
                name: b.name.clone(),
                parent,
                head: V3::from(b.head),
                tail: V3::from(b.tail),
                limit_deg: b.limit_deg,
            });
        }
        let mut rig = TemplateRig {
            source: RigSource::File(format!("{name} ({})", file.source)),
            bones,
            weights: file.weights,
            shapes: file
                .shapes
                .into_iter()
                .map(|s| ShapeField {
                    name: s.name,
                    range: (s.range[0], s.range[1]),
                    vertices: s.vertices.into_iter().map(V3::from).collect(),
                    heads: s.heads.into_iter().map(V3::from).collect(),
                })
                .collect(),
        };
        rig.check(vertices)
            .map_err(|e| FileError::content(name, e.to_string()))?;
        for w in &mut rig.weights {
            let sum: f64 = w.iter().map(|x| x.1).sum();
            for x in w.iter_mut() {
                x.1 /= sum;
            }
        }
        Ok(rig)
    }

    /// Writes the rig file atomically.
    pub fn write(&self, path: &Path) -> Result<(), FileError> {
        crate::files::write_atomic(path, self.to_json().as_bytes())
    }
}

/// A turn of `deg` degrees about `axis`.
pub fn turn(axis: V3, deg: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Unit::new_normalize(axis), deg.to_radians())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::template::{self, Kind};

    #[test]
    fn the_generic_rig_poses_as_the_figure_does() {
        let fig = template::build(Kind::Pig, 2000);
        let rig = TemplateRig::generic(&fig, Kind::Pig);
        rig.check(fig.mesh.vertices.len()).unwrap();
        let params = [("leg_fl".to_string(), 30.0), ("nod".to_string(), -20.0)]
            .into_iter()
            .collect();
        let pose = template::pose(Kind::Pig, &params);
        let want = fig.pose(&pose);
        let mut rp = RigPose::rest(&rig);
        for (bone, axis, deg) in &pose.joints {
            let b = rig.bone(bone).unwrap();
            rp.turns[b] = turn(*axis, *deg) * rp.turns[b];
        }
        let got = rig.pose(&fig.mesh.vertices, &rp);
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        assert!(worst < 1e-9, "{worst}");
        // and the file carries it: read back, it poses the same within the rounding
        let back =
            TemplateRig::parse(&rig.to_json(), "pig.rig.json", fig.mesh.vertices.len()).unwrap();
        let again = back.pose(&fig.mesh.vertices, &rp);
        let worst = again
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        assert!(worst < 1e-5, "{worst}");
    }

    #[test]
    fn the_generic_rig_reshapes_as_the_template_does() {
        let fig = template::build(Kind::Body, 2000);
        let rig = TemplateRig::generic(&fig, Kind::Body);
        let factors: std::collections::BTreeMap<String, f64> =
            [("leg_length".to_string(), 1.2), ("girth".to_string(), 0.9)]
                .into_iter()
                .collect();
        let want = template::reshape(&fig, Kind::Body, &factors).unwrap();
        let mut rp = RigPose::rest(&rig);
        for (k, s) in rig.shapes.iter().enumerate() {
            rp.factors[k] = factors.get(&s.name).copied().unwrap_or(1.0);
        }
        let (got, heads) = rig.reshape(&fig.mesh.vertices, &rp.factors);
        assert_eq!(got, want);
        // longer legs lift the hips: the pelvis joint rises with the skin around it
        let pelvis = rig.bone("pelvis").unwrap();
        let rise = heads[pelvis].z - rig.bones[pelvis].head.z;
        assert!((rise - 0.2 * 0.9).abs() < 0.03, "{rise}");
    }

    #[test]
    fn bone_fields_stretch_and_widen_one_bone() {
        let fig = template::build(Kind::Body, 2000);
        let rig = TemplateRig::generic(&fig, Kind::Body);
        let ext = rig.with_bone_fields(&fig.mesh.vertices);
        assert_eq!(ext.shapes[..rig.shapes.len()], rig.shapes[..]);
        ext.check(fig.mesh.vertices.len()).unwrap();
        let field = |name: &str| ext.shapes.iter().position(|s| s.name == name).unwrap();
        let at = |name: &str, f: f64| {
            let mut factors = vec![1.0; ext.shapes.len()];
            factors[field(name)] = f;
            ext.reshape(&fig.mesh.vertices, &factors)
        };
        let shin = rig.bone("shin_l").unwrap();
        let foot = rig.bone("foot_l").unwrap();
        let (b, bone) = (shin, &rig.bones[shin]);
        let length = (bone.tail - bone.head).norm();
        // the shin 20% longer: the foot (below it) moves down by a fifth of the shin,
        // the other leg stays
        let (v, heads) = at("shin_l.length", 1.2);
        let moved = heads[foot] - rig.bones[foot].head;
        assert!((moved.norm() - 0.2 * length).abs() < 1e-9, "{moved}");
        assert!(moved.z < -0.9 * moved.norm(), "down the shin: {moved}");
        let other = rig.bone("foot_r").unwrap();
        assert_eq!(heads[other], rig.bones[other].head);
        let dom = rig.dominant_bones();
        let toe = (0..v.len())
            .filter(|&i| dom[i] as usize == foot)
            .max_by(|&i, &j| fig.mesh.vertices[i].x.total_cmp(&fig.mesh.vertices[j].x))
            .unwrap();
        assert!((v[toe] - fig.mesh.vertices[toe] - moved).norm() < 0.02 * length);
        // the shin's skin 30% wider about its axis; nothing beyond its weights moves
        let (v, _) = at("shin_l.girth", 1.3);
        let axis = (bone.tail - bone.head) / length;
        let radius = |p: &V3| {
            let r = p - bone.head;
            (r - axis * r.dot(&axis)).norm()
        };
        // (a vertex the foot does not carry widens by its shin weight's share)
        let mid: Vec<(usize, f64)> = (0..v.len())
            .filter(|&i| rig.weights[i].iter().all(|&(k, _)| k as usize != foot))
            .filter_map(|i| {
                let w = rig.weights[i].iter().find(|x| x.0 as usize == b)?.1;
                (w > 0.5).then_some((i, w))
            })
            .collect();
        assert!(mid.len() > 10, "{}", mid.len());
        for &(i, w) in &mid {
            let (r0, r1) = (radius(&fig.mesh.vertices[i]), radius(&v[i]));
            assert!((r1 - (1.0 + 0.3 * w) * r0).abs() < 1e-9, "{r0} -> {r1}");
        }
        let head_bone = rig.bone("head").unwrap();
        let still = (0..v.len())
            .find(|&i| dom[i] as usize == head_bone)
            .unwrap();
        assert_eq!(v[still], fig.mesh.vertices[still]);
        // an automatic rig's stub of a root gets no fields
        let auto = TemplateRig::automatic(&fig.mesh, &AutoRigSettings::default()).unwrap();
        let ext = auto.with_bone_fields(&fig.mesh.vertices);
        assert!(ext.shapes.iter().all(|s| !s.name.starts_with("body.")));
        assert_eq!(
            ext.shapes.len(),
            auto.shapes.len() + 2 * (auto.bones.len() - 1)
        );
    }

    #[test]
    fn bad_rigs_are_named() {
        let fig = template::build(Kind::Pig, 600);
        let n = fig.mesh.vertices.len();
        let rig = TemplateRig::generic(&fig, Kind::Pig);
        let json = rig.to_json();
        let err = |text: &str, nv: usize| {
            TemplateRig::parse(text, "r.json", nv)
                .unwrap_err()
                .to_string()
        };
        assert!(err(&json, n + 1).contains(&format!("mesh of {n} vertices")));
        assert!(err(&json[..json.len() / 2], n).contains("line 1"));
        let swapped = json.replacen("\"parent\":null", "\"parent\":\"chest\"", 1);
        assert!(
            err(&swapped, n).contains("not a bone listed before it"),
            "{}",
            err(&swapped, n)
        );
        let mut bad = rig.clone();
        bad.weights[5] = vec![(0, 0.5)];
        assert!(
            err(&bad.to_json(), n).contains("vertex 5: weights sum to 0.5"),
            "{}",
            err(&bad.to_json(), n)
        );
        let mut bad = rig.clone();
        bad.bones[3].limit_deg = 400.0;
        assert!(err(&bad.to_json(), n).contains("limit_deg 400"));
        let mut bad = rig.clone();
        bad.weights[2] = vec![(99, 1.0)];
        assert!(err(&bad.to_json(), n).contains("vertex 2: bone 99"));
        let nan = json.replacen("\"limit_deg\":0.0", "\"limit_deg\":NaN", 1);
        assert!(err(&nan, n).contains("not a rig file"));
        let mut bad = rig.clone();
        bad.shapes[0].vertices.pop();
        assert!(err(&bad.to_json(), n).contains("shape 0 ('length')"));
    }

    #[test]
    fn the_automatic_rig_finds_the_pigs_limbs() {
        let fig = template::build(Kind::Pig, 3000);
        let rig = TemplateRig::automatic(&fig.mesh, &AutoRigSettings::default()).unwrap();
        let lms = fig.landmarks();
        let at = |name: &str| {
            let i = lms.iter().find(|l| l.name == name).unwrap();
            match i.pos {
                crate::mesh::landmarks::LandmarkPos::Vertex(k) => fig.mesh.vertices[k as usize],
                _ => unreachable!(),
            }
        };
        let diag = fig.mesh.diagonal();
        // every hoof is the tip of a lower bone
        for hoof in ["hoof_fl", "hoof_fr", "hoof_hl", "hoof_hr"] {
            let p = at(hoof);
            let near = rig
                .bones
                .iter()
                .filter(|b| b.name.ends_with("_lower"))
                .map(|b| (b.tail - p).norm())
                .fold(f64::INFINITY, f64::min);
            assert!(near < 0.05 * diag, "{hoof}: {near}");
        }
        // a leg's root lies at the body, not half-way down the leg
        let legs: Vec<&RigBone> = rig
            .bones
            .iter()
            .filter(|b| b.name.ends_with("_upper") && b.head.z < 0.6 && b.tail.z < 0.35)
            .collect();
        assert!(legs.len() >= 4, "{:?}", rig.bones);
        for b in legs {
            assert!(b.head.z > 0.3, "{}: root at {:?}", b.name, b.head);
        }
    }
}
