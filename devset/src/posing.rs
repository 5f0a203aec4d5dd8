//! Known-answer posing of any mesh with its vertex order kept, so that meshes conformd did
//! not make get posed truths. Limbs are found as geodesic extremities (farthest-point
//! sampling from the body's centre); each limb turns about a joint at the centre of its
//! cross-section part-way along it, with a weight that falls off along the surface; then
//! the whole is bent and twisted about its long axis and scaled.

use conformd::mesh::{Mesh, V3};
use nalgebra::{Rotation3, Unit};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Geodesic distances along the mesh's edges from `source` (Dijkstra); vertices of other
/// components stay at infinity.
pub fn edge_distances(mesh: &Mesh, neighbours: &[Vec<u32>], source: u32) -> Vec<f64> {
    conformd::mesh::topology::edge_distances(&mesh.vertices, neighbours, &[source]).0
}

/// The body's centre vertex and its extremities: farthest-point samples over geodesic
/// distance, from the vertex nearest the centroid. The first samples are the tips of
/// legs, tail, head and ears.
pub struct Extremities {
    pub centre: u32,
    /// farthest-point samples in order, with the geodesic distance from the centre
    pub samples: Vec<(u32, f64)>,
    pub from_centre: Vec<f64>,
}

pub fn extremities(mesh: &Mesh, neighbours: &[Vec<u32>], count: usize) -> Extremities {
    let c = mesh.centroid();
    let centre = (0..mesh.vertices.len())
        .min_by(|&a, &b| {
            (mesh.vertices[a] - c)
                .norm()
                .total_cmp(&(mesh.vertices[b] - c).norm())
        })
        .unwrap_or(0) as u32;
    let from_centre = edge_distances(mesh, neighbours, centre);
    let mut nearest: Vec<f64> = from_centre.clone();
    let mut samples = Vec::new();
    for _ in 0..count {
        let Some(v) = (0..nearest.len())
            .filter(|&i| nearest[i].is_finite())
            .max_by(|&a, &b| nearest[a].total_cmp(&nearest[b]))
        else {
            break;
        };
        if nearest[v] <= 0.0 {
            break;
        }
        samples.push((v as u32, from_centre[v]));
        let d = edge_distances(mesh, neighbours, v as u32);
        for (n, x) in nearest.iter_mut().zip(d) {
            *n = n.min(x);
        }
    }
    Extremities {
        centre,
        samples,
        from_centre,
    }
}

/// How hard to pose.
#[derive(Debug, Clone, Copy)]
pub struct PoseSettings {
    /// extremities tried as limbs (the first farthest-point samples; the thin ones turn)
    pub limbs: usize,
    /// limb turn, degrees, drawn between these (either sign)
    pub limb_degrees: (f64, f64),
    /// bend and twist of the whole about its long axis, degrees end to end
    pub bend: f64,
    pub twist: f64,
    pub scale: f64,
    pub seed: u64,
}

impl Default for PoseSettings {
    fn default() -> Self {
        PoseSettings {
            limbs: 8,
            limb_degrees: (15.0, 30.0),
            bend: 12.0,
            twist: 10.0,
            scale: 1.05,
            seed: 1,
        }
    }
}

/// The mesh's vertices in a new posture (see the module comment). Deterministic for a
/// seed.
pub fn pose(mesh: &Mesh, neighbours: &[Vec<u32>], ext: &Extremities, s: &PoseSettings) -> Vec<V3> {
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
    let mut x = mesh.vertices.clone();
    for &(tip, length) in ext.samples.iter().take(s.limbs) {
        let from_tip = edge_distances(mesh, neighbours, tip);
        // the limb: everything within 45% of the tip-to-centre path of the tip, blended
        // over a band of 40% of it (narrower bands fold the inside of the bend)
        let (r, h) = (0.45 * length, 0.2 * length);
        let ring: Vec<usize> = (0..x.len())
            .filter(|&i| (from_tip[i] - r).abs() < 0.5 * h)
            .collect();
        if ring.is_empty() {
            continue;
        }
        let joint = ring.iter().map(|&i| x[i]).sum::<V3>() / ring.len() as f64;
        // a limb is thin where it is cut: a wide ring is the body itself (a rump or a
        // back found as an extremity), which no joint turns
        let radius = ring.iter().map(|&i| (x[i] - joint).norm()).sum::<f64>() / ring.len() as f64;
        if radius > 0.35 * r {
            continue;
        }
        let along = x[tip as usize] - joint;
        if along.norm() == 0.0 {
            continue;
        }
        let along = along.normalize();
        let side = along.cross(&random_unit(&mut rng)).normalize();
        let deg = rng.random_range(s.limb_degrees.0..=s.limb_degrees.1)
            * if rng.random::<bool>() { 1.0 } else { -1.0 };
        let axis = Unit::new_normalize(side);
        for i in 0..x.len() {
            let w = smoothstep((r + h - from_tip[i]) / (2.0 * h));
            if w > 0.0 {
                let rot = Rotation3::from_axis_angle(&axis, (deg * w).to_radians());
                x[i] = joint + rot * (x[i] - joint);
            }
        }
    }
    bend_twist(&mut x, s);
    x
}

/// Bends the whole about an axis across its long axis and twists it about the long axis,
/// both in proportion to the position along it; then scales about the centroid.
fn bend_twist(x: &mut [V3], s: &PoseSettings) {
    let c = x.iter().sum::<V3>() / x.len() as f64;
    let cov = x.iter().fold(nalgebra::Matrix3::zeros(), |m, p| {
        let d = p - c;
        m + d * d.transpose()
    });
    let eig = cov.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let long = eig.eigenvectors.column(order[0]).into_owned();
    let across = eig.eigenvectors.column(order[2]).into_owned();
    let half = x
        .iter()
        .map(|p| (p - c).dot(&long).abs())
        .fold(0.0, f64::max)
        .max(1e-12);
    let (bend_axis, twist_axis) = (Unit::new_normalize(across), Unit::new_normalize(long));
    for p in x.iter_mut() {
        let t = (*p - c).dot(&long) / half;
        let r = Rotation3::from_axis_angle(&bend_axis, (0.5 * s.bend * t).to_radians())
            * Rotation3::from_axis_angle(&twist_axis, (0.5 * s.twist * t).to_radians());
        *p = c + (r * (*p - c)) * s.scale;
    }
}

/// A person's stance in a body-scanning booth, far from the T-pose of the outside body
/// meshes: the arms turned at the shoulders, which [`pose`] (turning limbs part-way
/// along) never does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stance {
    /// upper arms hanging, forearms forward and in, the hands before the belly
    HandsAtBelly,
    /// both arms reaching forward, a little down
    ArmsForward,
    /// both arms raised above the head, the feet apart
    ArmsRaised,
}

impl Stance {
    pub const ALL: [Stance; 3] = [
        Stance::HandsAtBelly,
        Stance::ArmsForward,
        Stance::ArmsRaised,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Stance::HandsAtBelly => "hands at the belly",
            Stance::ArmsForward => "arms forward",
            Stance::ArmsRaised => "arms raised",
        }
    }

    /// The world directions (up, outward to its own side, forward) an arm's upper and
    /// lower bone point in.
    fn arm_directions(self) -> ([f64; 3], [f64; 3]) {
        match self {
            Stance::HandsAtBelly => ([-0.95, 0.2, 0.15], [0.15, -0.6, 0.8]),
            Stance::ArmsForward => ([-0.15, 0.12, 1.0], [-0.1, -0.05, 1.0]),
            Stance::ArmsRaised => ([1.0, 0.35, 0.05], [1.0, 0.15, 0.1]),
        }
    }

    /// How far each leg swings out at the hip, degrees (the feet apart; in, together).
    fn leg_spread_deg(self) -> f64 {
        match self {
            Stance::HandsAtBelly => -4.0,
            Stance::ArmsForward => 3.0,
            Stance::ArmsRaised => 8.0,
        }
    }
}

/// A person's mesh (z up, in any rest pose with the limbs away from the body) in a
/// booth stance, through its automatic rig (`TemplateRig::automatic`: each limb's upper
/// bone from where it meets the body, its lower bone from half-way): each arm's bones
/// turned to point the stance's way, each leg swung out at the hip as the stance says.
/// `front` is the way the person faces (level). One pose per stance of `stances` (the
/// rig found once), vertex order kept. Fails when the rig does not find two arms and two
/// legs.
pub fn stand(
    mesh: &Mesh,
    front: V3,
    stances: &[Stance],
) -> Result<Vec<Vec<V3>>, crate::SynthError> {
    use conformd::template::rig::{AutoRigSettings, TemplateRig};
    let rig = TemplateRig::automatic(mesh, &AutoRigSettings::default())?;
    let up = V3::z();
    let front = V3::new(front.x, front.y, 0.0)
        .try_normalize(1e-12)
        .ok_or(crate::SynthError::Posing("the front is vertical"))?;
    let left = up.cross(&front);
    stances
        .iter()
        .map(|&stance| {
            let pose = stance_pose(&rig, up, front, left, stance)?;
            Ok(rig.pose(&mesh.vertices, &pose))
        })
        .collect()
}

/// The turns of `rig`'s arm and leg bones for `stance`, in the frame `up`, `front`,
/// `left`.
fn stance_pose(
    rig: &conformd::template::rig::TemplateRig,
    up: V3,
    front: V3,
    left: V3,
    stance: Stance,
) -> Result<conformd::template::rig::RigPose, crate::SynthError> {
    let dir = |b: usize| (rig.bones[b].tail - rig.bones[b].head).normalize();
    let mut pose = conformd::template::rig::RigPose::rest(rig);
    let (mut arms, mut legs) = (0, 0);
    for (upper, bone) in rig.bones.iter().enumerate() {
        let is_root_limb = bone.name.ends_with("_upper") && bone.parent == Some(0);
        if !is_root_limb {
            continue;
        }
        let Some(lower) = rig
            .bones
            .iter()
            .position(|b| b.parent == Some(upper) && b.name.ends_with("_lower"))
        else {
            continue;
        };
        let d = dir(upper);
        let side = if d.dot(&left) >= 0.0 { left } else { -left };
        let arm = d.dot(&side) > 0.7;
        let leg = d.dot(&up) < -0.7;
        if !arm && !leg {
            continue;
        }
        if arm {
            arms += 1;
        } else {
            legs += 1;
        }
        if leg {
            // out about the front axis, the foot staying under the hip's side
            let out = side.dot(&left).signum();
            let axis = Unit::new_normalize(front * out);
            pose.turns[upper] =
                Rotation3::from_axis_angle(&axis, stance.leg_spread_deg().to_radians());
            continue;
        }
        let world = |[u, s, f]: [f64; 3]| (up * u + side * s + front * f).normalize();
        let (to_upper, to_lower) = stance.arm_directions();
        rig.point_limb(&mut pose, (upper, lower), world(to_upper), world(to_lower))
            .ok_or(crate::SynthError::Posing(
                "a limb bone turned exactly round",
            ))?;
    }
    if arms != 2 || legs != 2 {
        return Err(crate::SynthError::Limbs { arms, legs });
    }
    Ok(pose)
}

fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn random_unit(rng: &mut ChaCha8Rng) -> V3 {
    loop {
        let v = V3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}
