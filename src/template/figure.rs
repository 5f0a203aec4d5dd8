//! An articulated figure built procedurally from a skeleton: bones are round cones
//! blended into one implicit surface, meshed by marching tetrahedra (always watertight
//! and manifold) and relaxed towards even triangles. Each vertex is skinned to the bones,
//! so the figure can be posed (joint rotations) and deformed (bend, twist, scale) with
//! its vertex order unchanged: a posed figure is its own ground-truth correspondence.

use crate::mesh::{
    Mesh, V3,
    landmarks::{Landmark, LandmarkPos},
    topology,
};
use nalgebra::{Rotation3, Unit};
use std::collections::{BTreeMap, HashMap};

/// One bone: a round cone from `head` (the joint) to `tail`, radii `r_head`, `r_tail`.
#[derive(Debug, Clone)]
pub struct Bone {
    pub name: String,
    pub parent: Option<usize>,
    pub head: V3,
    pub tail: V3,
    pub r_head: f64,
    pub r_tail: f64,
    /// vertex group this bone's skin belongs to
    pub group: String,
}

/// A skeleton and the smoothness of the blend between its bones.
#[derive(Debug, Clone)]
pub struct Skeleton {
    pub bones: Vec<Bone>,
    pub blend: f64,
    /// named surface points (landmarks), as rest-pose positions near the surface
    pub landmarks: Vec<(String, V3)>,
}

impl Skeleton {
    pub fn bone(&self, name: &str) -> Option<usize> {
        self.bones.iter().position(|b| b.name == name)
    }

    pub(crate) fn add(
        &mut self,
        name: &str,
        parent: Option<&str>,
        head: V3,
        tail: V3,
        r: (f64, f64),
        group: &str,
    ) {
        let parent = parent.map(|p| self.bone(p).expect("parent bone defined first"));
        self.bones.push(Bone {
            name: name.into(),
            parent,
            head,
            tail,
            r_head: r.0,
            r_tail: r.1,
            group: group.into(),
        });
    }

    /// Signed distance (approximately) to the blended surface: negative inside. Every
    /// bone measured; [`Field`] gives the same value faster for many points.
    pub fn sdf(&self, p: &V3) -> f64 {
        let k = self.blend;
        let mut d = f64::INFINITY;
        for b in &self.bones {
            d = smooth_min(d, round_cone(p, b), k);
        }
        d
    }
}

/// The polynomial smooth minimum of the running distance `d` and a bone's `db`, blend
/// `k` (the first bone's distance as it is).
fn smooth_min(d: f64, db: f64, k: f64) -> f64 {
    if d.is_infinite() {
        return db;
    }
    let h = (0.5 + 0.5 * (db - d) / k).clamp(0.0, 1.0);
    db * (1.0 - h) + d * h - k * h * (1.0 - h)
}

/// A skeleton's distance field with each bone's bounding sphere, so that a bone too far
/// from a point to change the blend is not measured (meshing a template calls it a few
/// hundred thousand times).
struct Field<'a> {
    skel: &'a Skeleton,
    /// per bone: the middle of its axis, and the farthest its surface reaches from it
    spheres: Vec<(V3, f64)>,
}

impl<'a> Field<'a> {
    fn new(skel: &'a Skeleton) -> Self {
        Field {
            skel,
            spheres: skel
                .bones
                .iter()
                .map(|b| {
                    let reach = 0.5 * (b.tail - b.head).norm() + b.r_head.max(b.r_tail);
                    ((b.head + b.tail) / 2.0, reach)
                })
                .collect(),
        }
    }

    /// [`Skeleton::sdf`]: the same value to the bit. A bone whose distance is at least
    /// twice the blend beyond the running minimum leaves it as it is (the smooth
    /// minimum's weight is then exactly 0, rounding or not), and its sphere bounds that
    /// distance from below.
    fn at(&self, p: &V3) -> f64 {
        let k = self.skel.blend;
        let mut d = f64::INFINITY;
        for (b, (mid, reach)) in self.skel.bones.iter().zip(&self.spheres) {
            if d.is_finite() && (p - mid).norm() - reach >= d + 2.0 * k {
                continue;
            }
            d = smooth_min(d, round_cone(p, b), k);
        }
        d
    }
}

fn round_cone(p: &V3, b: &Bone) -> f64 {
    let ab = b.tail - b.head;
    let t = ((p - b.head).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
    let r = b.r_head + (b.r_tail - b.r_head) * t;
    (p - (b.head + ab * t)).norm() - r
}

/// A standing human-like figure, z up, facing +x, about 1.7 units tall: torso, neck, head
/// with a nose, arms with hands, legs with feet. Front and back differ (nose, feet), so
/// alignment without landmarks is well posed.
pub fn humanoid() -> Skeleton {
    let mut s = Skeleton {
        bones: vec![],
        blend: 0.035,
        landmarks: vec![],
    };
    let v = V3::new;
    s.add(
        "pelvis",
        None,
        v(0., 0., 0.90),
        v(0., 0., 1.10),
        (0.15, 0.15),
        "torso",
    );
    s.add(
        "chest",
        Some("pelvis"),
        v(0., 0., 1.10),
        v(0.01, 0., 1.38),
        (0.15, 0.17),
        "torso",
    );
    s.add(
        "neck",
        Some("chest"),
        v(0., 0., 1.42),
        v(0., 0., 1.55),
        (0.055, 0.05),
        "head",
    );
    s.add(
        "head",
        Some("neck"),
        v(0., 0., 1.62),
        v(0.01, 0., 1.70),
        (0.10, 0.095),
        "head",
    );
    // a face the scanner can resolve: nose and chin, so the head has an orientation
    s.add(
        "nose",
        Some("head"),
        v(0.06, 0., 1.66),
        v(0.14, 0., 1.63),
        (0.035, 0.025),
        "head",
    );
    s.add(
        "chin",
        Some("head"),
        v(0.03, 0., 1.58),
        v(0.09, 0., 1.56),
        (0.04, 0.03),
        "head",
    );
    for (side, y) in [("l", 1.0), ("r", -1.0)] {
        let n = |b: &str| format!("{b}_{side}");
        s.add(
            &n("shoulder"),
            Some("chest"),
            v(0., 0.10 * y, 1.36),
            v(0., 0.21 * y, 1.37),
            (0.07, 0.065),
            "torso",
        );
        s.add(
            &n("upper_arm"),
            Some(&n("shoulder")),
            v(0., 0.22 * y, 1.36),
            v(0.02, 0.42 * y, 1.22),
            (0.055, 0.045),
            "arms",
        );
        s.add(
            &n("forearm"),
            Some(&n("upper_arm")),
            v(0.02, 0.42 * y, 1.22),
            v(0.07, 0.58 * y, 1.06),
            (0.045, 0.035),
            "arms",
        );
        s.add(
            &n("hand"),
            Some(&n("forearm")),
            v(0.07, 0.58 * y, 1.06),
            v(0.10, 0.66 * y, 0.98),
            (0.035, 0.03),
            "hands",
        );
        s.add(
            &n("thigh"),
            Some("pelvis"),
            v(0., 0.09 * y, 0.88),
            v(0.02, 0.11 * y, 0.50),
            (0.085, 0.06),
            "legs",
        );
        s.add(
            &n("shin"),
            Some(&n("thigh")),
            v(0.02, 0.11 * y, 0.50),
            v(0., 0.12 * y, 0.10),
            (0.055, 0.04),
            "legs",
        );
        s.add(
            &n("foot"),
            Some(&n("shin")),
            v(0., 0.12 * y, 0.08),
            v(0.16, 0.12 * y, 0.04),
            (0.045, 0.035),
            "feet",
        );
        s.landmarks.extend([
            (
                n("hand_tip"),
                v(
                    0.10 + 0.03 * 0.35,
                    (0.66 + 0.03 * 0.9) * y,
                    0.98 - 0.03 * 0.2,
                ),
            ),
            (n("elbow"), v(0.0, 0.42 * y, 1.22 + 0.06)),
            (n("shoulder_top"), v(0., 0.21 * y, 1.37 + 0.07)),
            (n("knee"), v(0.02 + 0.06, 0.11 * y, 0.50)),
            (n("toe"), v(0.16 + 0.04, 0.12 * y, 0.04)),
            (n("heel"), v(-0.05, 0.12 * y, 0.08)),
            (n("hip"), v(0., 0.09 * y + 0.12 * y, 0.90)),
        ]);
    }
    s.landmarks.extend([
        ("head_top".into(), v(0.01, 0., 1.80)),
        ("nose_tip".into(), v(0.17, 0., 1.63)),
        ("chin".into(), v(0.12, 0., 1.54)),
        ("navel".into(), v(0.16, 0., 1.05)),
        ("back".into(), v(-0.17, 0., 1.25)),
    ]);
    s
}

/// A figure mesh with its skin weights.
#[derive(Debug, Clone)]
pub struct Figure {
    pub skeleton: Skeleton,
    pub mesh: Mesh,
    /// #V lists of (bone, weight), weights summing to 1
    pub weights: Vec<Vec<(u32, f64)>>,
}

/// Meshes `skel` with about `target_vertices` vertices (within roughly 15%).
/// Fewest vertices a template is sampled with from its distance field: a coarser grid
/// loses thin parts (ears, tail, fingers) or cuts them off the body (a 2,000-vertex pig
/// came out in 3 pieces, a 4,000-vertex body in 2); smaller templates are decimated
/// from this one, which keeps the surface in one piece.
const MIN_SAMPLED_VERTICES: usize = 6000;

pub fn build(skel: &Skeleton, target_vertices: usize) -> Figure {
    let sampled = target_vertices.max(MIN_SAMPLED_VERTICES);
    let mut mesh = sample(skel, sampled);
    if sampled > target_vertices {
        mesh = crate::mesh::decimate::decimate(&mesh, target_vertices, &[]).mesh;
        relax(&mut mesh, skel, 2);
    }
    let weights = skin_weights(skel, &mesh.vertices);
    mesh.groups = groups_of(skel, &weights);
    Figure {
        skeleton: skel.clone(),
        mesh,
        weights,
    }
}

/// Each vertex in the group of the bone that weighs most on it.
fn groups_of(skel: &Skeleton, weights: &[Vec<(u32, f64)>]) -> BTreeMap<String, Vec<u32>> {
    let mut groups: BTreeMap<String, Vec<u32>> = BTreeMap::new();
    for (i, w) in weights.iter().enumerate() {
        let b = w
            .iter()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(0, |x| x.0);
        groups
            .entry(skel.bones[b as usize].group.clone())
            .or_default()
            .push(i as u32);
    }
    groups
}

/// The first bytes of [`Figure::to_bytes`].
const FIGURE_MAGIC: &[u8; 8] = b"CFDFIG1\n";

impl Figure {
    /// What building a figure computes (its mesh and skin weights), as bytes: with
    /// [`Figure::from_bytes`] and the same skeleton, the same figure to the bit, so a
    /// worker process can skip the build (`process --template-cache`). Little-endian:
    /// magic, vertex and triangle counts (u64), vertices (3 f64), triangles (3 u32),
    /// per vertex its weights' count (u32) and (bone u32, weight f64) pairs, then a
    /// checksum (u64) of all before it.
    pub fn to_bytes(&self) -> Vec<u8> {
        let m = &self.mesh;
        let mut b = Vec::with_capacity(16 + m.vertices.len() * 64 + m.triangles.len() * 12);
        b.extend_from_slice(FIGURE_MAGIC);
        b.extend_from_slice(&(m.vertices.len() as u64).to_le_bytes());
        b.extend_from_slice(&(m.triangles.len() as u64).to_le_bytes());
        for v in &m.vertices {
            for c in v.iter() {
                b.extend_from_slice(&c.to_le_bytes());
            }
        }
        for t in &m.triangles {
            for i in t {
                b.extend_from_slice(&i.to_le_bytes());
            }
        }
        for w in &self.weights {
            b.extend_from_slice(&(w.len() as u32).to_le_bytes());
            for (bone, x) in w {
                b.extend_from_slice(&bone.to_le_bytes());
                b.extend_from_slice(&x.to_le_bytes());
            }
        }
        let sum = checksum(&b);
        b.extend_from_slice(&sum.to_le_bytes());
        b
    }

    /// The figure of `skel` whose mesh and weights [`Figure::to_bytes`] wrote; an error
    /// naming what is wrong when the bytes are not such a figure of this skeleton.
    pub fn from_bytes(skel: &Skeleton, bytes: &[u8]) -> Result<Figure, FigureBytesError> {
        let body_len = bytes
            .len()
            .checked_sub(8)
            .filter(|n| *n >= FIGURE_MAGIC.len() + 16)
            .ok_or(FigureBytesError::TooShort)?;
        let (body, sum) = bytes.split_at(body_len);
        if !body.starts_with(FIGURE_MAGIC) {
            return Err(FigureBytesError::NotAFigure);
        }
        if checksum(body).to_le_bytes() != sum {
            return Err(FigureBytesError::Damaged);
        }
        let mut r = ByteReader {
            bytes: body,
            at: FIGURE_MAGIC.len(),
        };
        let nv = r.u64()? as usize;
        let nt = r.u64()? as usize;
        if nv == 0 || nv > 10_000_000 || nt > 20_000_000 {
            return Err(FigureBytesError::Counts { nv, nt });
        }
        let mut vertices = Vec::with_capacity(nv);
        for _ in 0..nv {
            vertices.push(V3::new(r.f64()?, r.f64()?, r.f64()?));
        }
        let mut triangles = Vec::with_capacity(nt);
        for _ in 0..nt {
            let t = [r.u32()?, r.u32()?, r.u32()?];
            if t.iter().any(|&i| i as usize >= nv) {
                return Err(FigureBytesError::Triangle { t, nv });
            }
            triangles.push(t);
        }
        let mut weights = Vec::with_capacity(nv);
        for _ in 0..nv {
            let n = r.u32()? as usize;
            if n > skel.bones.len() {
                return Err(FigureBytesError::Bones {
                    found: n,
                    bones: skel.bones.len(),
                });
            }
            let mut w = Vec::with_capacity(n);
            for _ in 0..n {
                let bone = r.u32()?;
                if bone as usize >= skel.bones.len() {
                    return Err(FigureBytesError::Bones {
                        found: bone as usize + 1,
                        bones: skel.bones.len(),
                    });
                }
                w.push((bone, r.f64()?));
            }
            weights.push(w);
        }
        if r.at != body.len() {
            return Err(FigureBytesError::LeftOver(body.len() - r.at));
        }
        let mut mesh = Mesh::new(vertices, triangles);
        mesh.groups = groups_of(skel, &weights);
        Ok(Figure {
            skeleton: skel.clone(),
            mesh,
            weights,
        })
    }
}

/// Why bytes are not a figure of the skeleton they were read for.
#[derive(Debug, thiserror::Error)]
pub enum FigureBytesError {
    #[error("too short for a figure")]
    TooShort,
    #[error("not a conformd figure")]
    NotAFigure,
    #[error("its checksum does not match (damaged)")]
    Damaged,
    #[error("{nv} vertices and {nt} triangles")]
    Counts { nv: usize, nt: usize },
    #[error("a triangle {t:?} beyond its {nv} vertices")]
    Triangle { t: [u32; 3], nv: usize },
    #[error("weights of {found} bones where the skeleton has {bones}")]
    Bones { found: usize, bones: usize },
    #[error("cut short at byte {0}")]
    CutShort(usize),
    #[error("{0} bytes left over")]
    LeftOver(usize),
}

/// FNV-1a over 8-byte words: catches a damaged file, no more.
fn checksum(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for chunk in bytes.chunks(8) {
        let mut w = [0u8; 8];
        w[..chunk.len()].copy_from_slice(chunk);
        h = (h ^ u64::from_le_bytes(w)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h ^ bytes.len() as u64
}

struct ByteReader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl ByteReader<'_> {
    fn take<const N: usize>(&mut self) -> Result<[u8; N], FigureBytesError> {
        let s = self
            .bytes
            .get(self.at..self.at + N)
            .ok_or(FigureBytesError::CutShort(self.at))?;
        self.at += N;
        Ok(s.try_into().expect("N bytes"))
    }
    fn u64(&mut self) -> Result<u64, FigureBytesError> {
        self.take::<8>().map(u64::from_le_bytes)
    }
    fn u32(&mut self) -> Result<u32, FigureBytesError> {
        self.take::<4>().map(u32::from_le_bytes)
    }
    fn f64(&mut self) -> Result<f64, FigureBytesError> {
        self.take::<8>().map(f64::from_le_bytes)
    }
}

/// The skeleton's surface, meshed from its distance field at about `target_vertices`
/// and relaxed onto it.
fn sample(skel: &Skeleton, target_vertices: usize) -> Mesh {
    let (lo, hi) = bounds(skel);
    let area_guess = {
        // one coarse pass measures the surface to choose the grid step
        let m = mesh_sdf(skel, lo, hi, (hi - lo).max() / 40.0, BAND);
        m.area()
    };
    // marching tetrahedra give about 1.3 vertices per h^2 of surface here (measured)
    let mut h = (1.3 * area_guess / target_vertices as f64).sqrt();
    let mut mesh = mesh_sdf(skel, lo, hi, h, BAND);
    let ratio = mesh.vertices.len() as f64 / target_vertices as f64;
    if !(0.9..=1.1).contains(&ratio) {
        h *= ratio.sqrt();
        mesh = mesh_sdf(skel, lo, hi, h, BAND);
    }
    relax(&mut mesh, skel, 6);
    mesh
}

fn bounds(skel: &Skeleton) -> (V3, V3) {
    let mut lo = V3::repeat(f64::INFINITY);
    let mut hi = V3::repeat(f64::NEG_INFINITY);
    for b in &skel.bones {
        let r = b.r_head.max(b.r_tail) + skel.blend;
        for p in [b.head, b.tail] {
            lo = lo.inf(&(p - V3::repeat(r)));
            hi = hi.sup(&(p + V3::repeat(r)));
        }
    }
    let pad = (hi - lo).max() * 0.05;
    (lo - V3::repeat(pad), hi + V3::repeat(pad))
}

/// The coarse grid's step, in fine grid steps.
const BAND: usize = 4;
/// How much faster than distance the skeleton's field may change (its round cones'
/// radii vary along their axes, so it is not exactly a distance): the band's margin.
const FIELD_SLOPE: f64 = 1.5;

/// The skeleton's field at every node of the grid from `lo` with step `h` and `dims`
/// nodes, found on a grid `band` times coarser first: a node whose nearest coarse node
/// is far from the surface (its distance beyond what the field can change over the
/// gap, with room to spare) lies on no edge the surface crosses, and takes the coarse
/// value: only its sign is read.
fn sampled_field(
    skel: &Skeleton,
    lo: V3,
    (nx, ny, nz): (usize, usize, usize),
    h: f64,
    band: usize,
) -> Vec<f64> {
    use rayon::prelude::*;
    let pos = |id: usize| {
        let (i, j, k) = (id % nx, (id / nx) % ny, id / (nx * ny));
        lo + V3::new(i as f64, j as f64, k as f64) * h
    };
    let sdf = Field::new(skel);
    let coarse_dims = (
        nx.div_ceil(band) + 1,
        ny.div_ceil(band) + 1,
        nz.div_ceil(band) + 1,
    );
    let coarse: Vec<f64> = (0..coarse_dims.0 * coarse_dims.1 * coarse_dims.2)
        .into_par_iter()
        .map(|id| {
            let (i, j, k) = (
                id % coarse_dims.0,
                (id / coarse_dims.0) % coarse_dims.1,
                id / (coarse_dims.0 * coarse_dims.1),
            );
            sdf.at(&(lo + V3::new(i as f64, j as f64, k as f64) * (h * band as f64)))
        })
        .collect();
    let far = FIELD_SLOPE * (band as f64 / 2.0) * 3f64.sqrt() * h + 3.0 * h;
    (0..nx * ny * nz)
        .into_par_iter()
        .map(|id| {
            let (i, j, k) = (id % nx, (id / nx) % ny, id / (nx * ny));
            let near = |n: usize, dim: usize| ((n + band / 2) / band).min(dim - 1);
            let c = coarse[(near(k, coarse_dims.2) * coarse_dims.1 + near(j, coarse_dims.1))
                * coarse_dims.0
                + near(i, coarse_dims.0)];
            if c.abs() > far {
                return c;
            }
            let f = sdf.at(&pos(id));
            // no value exactly zero: a zero would make degenerate triangles
            if f.abs() < 1e-9 * h { 1e-9 * h } else { f }
        })
        .collect()
}

/// Marching tetrahedra (six per grid cube, sharing the main diagonal, so neighbouring
/// cubes split their faces alike and the surface is closed); the field found exactly only
/// near the surface, on a grid `band` times coarser first (1: everywhere).
fn mesh_sdf(skel: &Skeleton, lo: V3, hi: V3, h: f64, band: usize) -> Mesh {
    let dims = ((hi - lo) / h).map(|d| d.ceil() as usize + 1);
    let (nx, ny, nz) = (dims.x, dims.y, dims.z);
    let node = |i: usize, j: usize, k: usize| (k * ny + j) * nx + i;
    let pos = |id: usize| {
        let (i, j, k) = (id % nx, (id / nx) % ny, id / (nx * ny));
        lo + V3::new(i as f64, j as f64, k as f64) * h
    };
    let field = sampled_field(skel, lo, (nx, ny, nz), h, band);
    const TETS: [[usize; 4]; 6] = [
        [0, 1, 3, 7],
        [0, 1, 5, 7],
        [0, 2, 3, 7],
        [0, 2, 6, 7],
        [0, 4, 5, 7],
        [0, 4, 6, 7],
    ];
    let mut verts: Vec<V3> = Vec::new();
    let mut on_edge: HashMap<(usize, usize), u32> = HashMap::new();
    let mut tris: Vec<[u32; 3]> = Vec::new();
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let c: [usize; 8] = std::array::from_fn(|b| {
                    node(i + (b & 1), j + ((b >> 1) & 1), k + ((b >> 2) & 1))
                });
                if c.iter().all(|&id| field[id] > 0.0) || c.iter().all(|&id| field[id] < 0.0) {
                    continue;
                }
                for tet in TETS {
                    let t = tet.map(|b| c[b]);
                    let inside: Vec<usize> =
                        t.iter().copied().filter(|&id| field[id] < 0.0).collect();
                    let outside: Vec<usize> =
                        t.iter().copied().filter(|&id| field[id] >= 0.0).collect();
                    if inside.is_empty() || outside.is_empty() {
                        continue;
                    }
                    let mut cut = |a: usize, b: usize| -> u32 {
                        let key = (a.min(b), a.max(b));
                        *on_edge.entry(key).or_insert_with(|| {
                            let s = field[a] / (field[a] - field[b]);
                            verts.push(pos(a) + (pos(b) - pos(a)) * s);
                            (verts.len() - 1) as u32
                        })
                    };
                    let out_dir = outside.iter().map(|&o| pos(o)).sum::<V3>()
                        / outside.len() as f64
                        - inside.iter().map(|&o| pos(o)).sum::<V3>() / inside.len() as f64;
                    let mut polys: Vec<[u32; 3]> = Vec::new();
                    match (inside.len(), outside.len()) {
                        (1, 3) => polys.push([
                            cut(inside[0], outside[0]),
                            cut(inside[0], outside[1]),
                            cut(inside[0], outside[2]),
                        ]),
                        (3, 1) => polys.push([
                            cut(outside[0], inside[0]),
                            cut(outside[0], inside[1]),
                            cut(outside[0], inside[2]),
                        ]),
                        _ => {
                            let (a, b) = (inside[0], inside[1]);
                            let (p, q) = (outside[0], outside[1]);
                            let (ap, aq, bq, bp) = (cut(a, p), cut(a, q), cut(b, q), cut(b, p));
                            polys.push([ap, aq, bq]);
                            polys.push([ap, bq, bp]);
                        }
                    }
                    for mut tri in polys {
                        let n = (verts[tri[1] as usize] - verts[tri[0] as usize])
                            .cross(&(verts[tri[2] as usize] - verts[tri[0] as usize]));
                        if n.dot(&out_dir) < 0.0 {
                            tri.swap(1, 2);
                        }
                        tris.push(tri);
                    }
                }
            }
        }
    }
    Mesh::new(verts, tris)
}

/// Tangential smoothing with re-projection onto the implicit surface: evens out the
/// slivers marching tetrahedra leave where the surface passes close to grid nodes.
fn relax(mesh: &mut Mesh, skel: &Skeleton, rounds: usize) {
    use rayon::prelude::*;
    let nb = topology::vertex_neighbours(mesh.vertices.len(), &mesh.triangles);
    let sdf = Field::new(skel);
    let grad = |p: &V3| {
        let e = 1e-5;
        V3::new(
            sdf.at(&(p + V3::x() * e)) - sdf.at(&(p - V3::x() * e)),
            sdf.at(&(p + V3::y() * e)) - sdf.at(&(p - V3::y() * e)),
            sdf.at(&(p + V3::z() * e)) - sdf.at(&(p - V3::z() * e)),
        ) / (2.0 * e)
    };
    for _ in 0..rounds {
        let normals = mesh.vertex_normals();
        let v = &mesh.vertices;
        let next: Vec<V3> = (0..v.len())
            .into_par_iter()
            .map(|i| {
                if nb[i].is_empty() {
                    return v[i];
                }
                let c = nb[i].iter().map(|&j| v[j as usize]).sum::<V3>() / nb[i].len() as f64;
                let d = c - v[i];
                let mut p = v[i] + (d - normals[i] * normals[i].dot(&d)) * 0.6;
                for _ in 0..2 {
                    let g = grad(&p);
                    let g2 = g.norm_squared();
                    if g2 > 1e-12 {
                        p -= g * (sdf.at(&p) / g2);
                    }
                }
                p
            })
            .collect();
        mesh.vertices = next;
    }
}

/// Skin weights from the distance to each bone's surface: sharp falloff, so a vertex
/// follows its own bone and blends only near joints.
pub fn skin_weights(skel: &Skeleton, v: &[V3]) -> Vec<Vec<(u32, f64)>> {
    let sigma = skel.blend * 0.8;
    v.iter()
        .map(|p| {
            let d: Vec<f64> = skel.bones.iter().map(|b| round_cone(p, b)).collect();
            let dmin = d.iter().copied().fold(f64::INFINITY, f64::min);
            let mut w: Vec<(u32, f64)> = d
                .iter()
                .enumerate()
                .map(|(b, &x)| (b as u32, (-(x - dmin) / sigma).exp()))
                .filter(|&(_, w)| w > 1e-4)
                .collect();
            let s: f64 = w.iter().map(|x| x.1).sum();
            for x in &mut w {
                x.1 /= s;
            }
            w
        })
        .collect()
}

/// Joint rotations (degrees, about each bone's joint, in the rest frame) and a global
/// deformation applied after them.
#[derive(Debug, Clone, Default)]
pub struct Pose {
    /// bone name -> (axis, degrees)
    pub joints: Vec<(String, V3, f64)>,
    /// bend of the whole about the y axis, degrees over the figure's height
    pub bend: f64,
    /// twist of the whole about the z axis, degrees over the figure's height
    pub twist: f64,
    /// uniform scale
    pub scale: f64,
    /// a final rigid motion: rotation (axis, degrees) and translation
    pub turn: Option<(V3, f64)>,
    pub shift: V3,
}

impl Figure {
    /// Each bone's transform in `pose` (joint rotations only), composed down the
    /// hierarchy: `x -> R x + t`.
    fn bone_transforms(&self, pose: &Pose) -> Vec<(Rotation3<f64>, V3)> {
        let bones = &self.skeleton.bones;
        // bone transforms: rotation about its joint, composed down the hierarchy
        let mut xf: Vec<(Rotation3<f64>, V3)> = Vec::with_capacity(bones.len());
        for b in bones.iter() {
            let local = pose.joints.iter().filter(|(n, _, _)| n == &b.name).fold(
                Rotation3::identity(),
                |r, (_, axis, deg)| {
                    Rotation3::from_axis_angle(&Unit::new_normalize(*axis), deg.to_radians()) * r
                },
            );
            // x -> R_local (x - head) + head, then the parent's transform
            let (pr, pt) = b
                .parent
                .map_or((Rotation3::identity(), V3::zeros()), |p| xf[p]);
            let r = pr * local;
            let t = pr * (b.head - local * b.head) + pt;
            xf.push((r, t));
        }
        xf
    }

    /// Takes the joint rotations of `pose` out of positions `x` (the template's vertex
    /// order): every vertex goes through the inverse of its blended bone transform, so
    /// a posed template comes back to its rest shape, and a subject of another shape
    /// keeps its shape in the rest posture.
    pub fn unpose(&self, pose: &Pose, x: &[V3]) -> Vec<V3> {
        let xf = self.bone_transforms(pose);
        x.iter()
            .zip(&self.weights)
            .map(|(p, w)| {
                let (a, t) = w.iter().fold(
                    (nalgebra::Matrix3::zeros(), V3::zeros()),
                    |(a, t), &(b, wt)| {
                        let (r, tb) = &xf[b as usize];
                        (a + r.matrix() * wt, t + tb * wt)
                    },
                );
                a.try_inverse().map_or(*p, |ai| ai * (p - t))
            })
            .collect()
    }

    /// Vertex positions in `pose`; same order as the rest mesh.
    pub fn pose(&self, pose: &Pose) -> Vec<V3> {
        let xf = self.bone_transforms(pose);
        let (lo, hi) = self.mesh.bounding_box().unwrap_or_default();
        let height = (hi.z - lo.z).max(1e-9);
        let scale = if pose.scale > 0.0 { pose.scale } else { 1.0 };
        let turn = pose
            .turn
            .map(|(a, d)| Rotation3::from_axis_angle(&Unit::new_normalize(a), d.to_radians()));
        self.mesh
            .vertices
            .iter()
            .zip(&self.weights)
            .map(|(p, w)| {
                let mut q = w
                    .iter()
                    .map(|&(b, wt)| (xf[b as usize].0 * p + xf[b as usize].1) * wt)
                    .sum::<V3>();
                let f = (q.z - lo.z) / height;
                let pivot = V3::new(0., 0., lo.z);
                q = Rotation3::from_axis_angle(&V3::y_axis(), (pose.bend * f).to_radians())
                    * (q - pivot)
                    + pivot;
                q = Rotation3::from_axis_angle(&V3::z_axis(), (pose.twist * f).to_radians()) * q;
                q *= scale;
                if let Some(r) = turn {
                    q = r * q;
                }
                q + pose.shift
            })
            .collect()
    }

    /// [`Figure::landmarks`] as name -> vertex.
    pub fn landmark_vertices(&self) -> BTreeMap<String, u32> {
        self.landmarks()
            .into_iter()
            .filter_map(|l| match l.pos {
                LandmarkPos::Vertex(v) => Some((l.name, v)),
                LandmarkPos::Point(_) => None,
            })
            .collect()
    }

    /// The skeleton's landmarks snapped to their nearest vertices.
    pub fn landmarks(&self) -> Vec<Landmark> {
        self.skeleton
            .landmarks
            .iter()
            .map(|(name, p)| {
                let v = (0..self.mesh.vertices.len())
                    .min_by(|&a, &b| {
                        (self.mesh.vertices[a] - p)
                            .norm()
                            .total_cmp(&(self.mesh.vertices[b] - p).norm())
                    })
                    .unwrap_or(0);
                Landmark {
                    name: name.clone(),
                    pos: LandmarkPos::Vertex(v as u32),
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::template::{Kind, skeleton};

    #[test]
    fn a_figure_read_back_from_its_bytes_is_the_same_to_the_bit() {
        let skel = skeleton(Kind::Body);
        let fig = build(&skel, 2000);
        let bytes = fig.to_bytes();
        let back = Figure::from_bytes(&skel, &bytes).unwrap();
        assert_eq!(back.mesh, fig.mesh);
        assert_eq!(back.weights, fig.weights);
        // damaged, cut short, another skeleton, not a figure: each refused, saying why
        let mut flipped = bytes.clone();
        flipped[100] ^= 1;
        let e = Figure::from_bytes(&skel, &flipped).unwrap_err().to_string();
        assert!(e.contains("checksum"), "{e}");
        let e = Figure::from_bytes(&skel, &bytes[..bytes.len() / 2])
            .unwrap_err()
            .to_string();
        assert!(e.contains("checksum"), "{e}");
        let e = Figure::from_bytes(&skel, b"ply\nformat ascii 1.0\nend_header\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("not a conformd figure"), "{e}");
        let mut few = skel.clone();
        few.bones.truncate(3);
        let e = Figure::from_bytes(&few, &bytes).unwrap_err().to_string();
        assert!(e.contains("bones where the skeleton has 3"), "{e}");
    }

    #[test]
    fn the_culled_field_and_the_band_change_nothing() {
        for kind in [Kind::Pig, Kind::Body] {
            let skel = skeleton(kind);
            let (lo, hi) = bounds(&skel);
            // every point of a 40^3 lattice over the figure, to the bit
            let n = 40;
            for id in 0..n * n * n {
                let t = V3::new(
                    (id % n) as f64 / (n - 1) as f64,
                    ((id / n) % n) as f64 / (n - 1) as f64,
                    (id / (n * n)) as f64 / (n - 1) as f64,
                );
                let p = lo + (hi - lo).component_mul(&t);
                assert_eq!(Field::new(&skel).at(&p), skel.sdf(&p), "{p}");
            }
            // the surface meshed through the band is the surface meshed everywhere
            let h = (hi - lo).max() / 90.0;
            let (a, b) = (
                mesh_sdf(&skel, lo, hi, h, BAND),
                mesh_sdf(&skel, lo, hi, h, 1),
            );
            assert!(a.vertices.len() > 2000, "{}", a.vertices.len());
            assert_eq!(a.vertices, b.vertices);
            assert_eq!(a.triangles, b.triangles);
        }
    }
}
