//! Correspondence search: for each template vertex, its most similar point on the scan
//! (Ju et al. 2004, section 2.2): the closest point on the scan's triangles (a BVH, through
//! parry) or, for a point cloud, the foot on the plane through the nearest points
//! (kd-tree, through kiddo). A vertex whose best point is too far, faces the wrong way,
//! or lies on the scan's boundary (off the edge of the data) has no match: FALSE in the
//! paper's labelling, missing data.

use crate::mesh::{Mesh, MeshError, V3, topology};
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use parry3d_f64::math::Vector as PVec;
use parry3d_f64::query::PointQueryWithLocation;
use parry3d_f64::shape::{TriMesh, TrianglePointLocation};
use std::collections::HashSet;
use std::num::NonZero;

/// One match: the scan point, the scan's normal there, and the similarity weight `w_i`.
#[derive(Debug, Clone, Copy)]
pub struct Match {
    pub point: V3,
    pub normal: V3,
    pub weight: f64,
    pub distance: f64,
}

/// Limits on what counts as a match.
#[derive(Debug, Clone, Copy)]
pub struct MatchLimits {
    /// farthest match, in scan units
    pub max_distance: f64,
    /// cosine of the largest angle between template and scan normals
    pub min_normal_cos: f64,
}

enum Index {
    Mesh {
        tri: Box<TriMesh>,
        face_normals: Vec<V3>,
        vertex_normals: Vec<V3>,
        boundary_vertex: Vec<bool>,
        boundary_edge: HashSet<[u32; 2]>,
    },
    Cloud {
        normals: Vec<V3>,
        /// normals estimated here have no reliable sign
        oriented: bool,
    },
}

/// The scan's local plane around one of its points: the centroid and mean normal of the
/// point's CLOUD_K nearest, and how far they spread. Computed the first time a query
/// lands on that point and kept: the fit's vertices move little between iterations, so
/// most queries land where one did before.
#[derive(Debug, Clone, Copy)]
struct Patch {
    centroid: V3,
    normal: V3,
    reach: f64,
}

/// A scan prepared for repeated closest-point queries.
pub struct ScanSurface {
    index: Index,
    /// kd-tree over the scan's points (mesh vertices or cloud points)
    tree: ImmutableKdTree<f64, 3>,
    pub points: Vec<V3>,
    /// median distance from a point to its nearest neighbour
    pub spacing: f64,
    pub diagonal: f64,
    /// per point of a cloud: its plane, once asked for (empty for a mesh)
    patches: Vec<std::sync::OnceLock<Patch>>,
}

#[derive(Debug, Clone, thiserror::Error)]
pub enum ScanError {
    #[error("the scan is empty (no points)")]
    Empty,
    #[error("the scan has too few points ({0}); at least 16 are needed")]
    TooFew(usize),
    #[error("the scan is invalid: {0}")]
    Invalid(#[from] MeshError),
    #[error("the scan is invalid: {0}")]
    Triangles(String),
}

const CLOUD_K: usize = 8;

pub use crate::mesh::MAX_COORDINATE;

/// The point of `tree` nearest `p` and its distance, if one lies within `r` (a bounded
/// query: a far point costs no more than a near one).
pub(crate) fn nearest_within(
    tree: &ImmutableKdTree<f64, 3>,
    p: &V3,
    r: f64,
) -> Option<(usize, f64)> {
    const ONE: std::num::NonZero<usize> = std::num::NonZero::new(1).unwrap();
    tree.nearest_n_within::<SquaredEuclidean>(&[p.x, p.y, p.z], r * r, ONE, false)
        .first()
        .map(|nb| (nb.item as usize, nb.distance.sqrt()))
}

/// A point set fit for geometry: coordinates within [`MAX_COORDINATE`], and an extent
/// (not all points in one place). `what` names it in the sentence.
pub fn check_extent(m: &Mesh, what: &str) -> Result<(), MeshError> {
    m.check_coordinates(what)?;
    if !(m.diagonal() > 0.0) {
        return Err(MeshError::NoExtent {
            what: what.to_string(),
            points: m.vertices.len(),
        });
    }
    // spread across the main direction: points on a line give no surface to fit
    let n = m.vertices.len() as f64;
    let mean = m.vertices.iter().sum::<V3>() / n;
    let cov = m
        .vertices
        .iter()
        .map(|p| (p - mean) * (p - mean).transpose())
        .sum::<nalgebra::Matrix3<f64>>()
        / n;
    let mut ev: Vec<f64> = cov.symmetric_eigenvalues().iter().copied().collect();
    ev.sort_by(|a, b| b.total_cmp(a));
    if !(ev[1] > 1e-8 * ev[0]) {
        return Err(MeshError::OnALine {
            what: what.to_string(),
            points: m.vertices.len(),
        });
    }
    Ok(())
}

impl ScanSurface {
    /// Prepares a mesh scan (triangles) or a point cloud (no triangles; normals used when
    /// present, estimated from 12 neighbours otherwise).
    pub fn new(scan: &Mesh) -> Result<Self, ScanError> {
        if scan.vertices.is_empty() {
            return Err(ScanError::Empty);
        }
        scan.validate("scan")?;
        if scan.vertices.len() < 16 {
            return Err(ScanError::TooFew(scan.vertices.len()));
        }
        check_extent(scan, "scan")?;
        let points = scan.vertices.clone();
        let arr: Vec<[f64; 3]> = points.iter().map(|p| [p.x, p.y, p.z]).collect();
        let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
        let diagonal = scan.diagonal();
        let sample = points.len().min(2000);
        let step = (points.len() / sample).max(1);
        let mut nn: Vec<f64> = (0..points.len())
            .step_by(step)
            .map(|i| {
                let r = tree.nearest_n::<SquaredEuclidean>(&arr[i], NonZero::new(2).unwrap());
                r.get(1).map_or(0.0, |n| n.distance.sqrt())
            })
            .collect();
        nn.sort_by(f64::total_cmp);
        let spacing = nn[nn.len() / 2].max(diagonal * 1e-9);

        let index = if scan.triangles.is_empty() {
            let (normals, oriented) = match &scan.normals {
                Some(n) if n.iter().all(|v| v.norm() > 0.5) => (n.clone(), true),
                _ => (estimate_normals(&points, &tree), false),
            };
            Index::Cloud { normals, oriented }
        } else {
            let verts: Vec<PVec> = points.iter().map(|p| PVec::new(p.x, p.y, p.z)).collect();
            let tri = TriMesh::new(verts, scan.triangles.clone())
                .map_err(|e| ScanError::Triangles(format!("{e:?}")))?;
            let face_normals = (0..scan.triangles.len())
                .map(|t| {
                    scan.face_normal_scaled(t)
                        .try_normalize(0.0)
                        .unwrap_or_default()
                })
                .collect();
            let mut boundary_edge = HashSet::new();
            for ([a, b], c) in topology::edge_face_counts(&scan.triangles) {
                if c == 1 {
                    boundary_edge.insert([a, b]);
                }
            }
            Index::Mesh {
                tri: Box::new(tri),
                face_normals,
                vertex_normals: scan.vertex_normals(),
                boundary_vertex: topology::boundary_vertices(points.len(), &scan.triangles),
                boundary_edge,
            }
        };
        let patches = match &index {
            Index::Cloud { .. } => (0..points.len())
                .map(|_| std::sync::OnceLock::new())
                .collect(),
            Index::Mesh { .. } => Vec::new(),
        };
        Ok(ScanSurface {
            index,
            tree,
            points,
            spacing,
            diagonal,
            patches,
        })
    }

    /// Pulls from the scan to the template, the other direction of matching: about
    /// `count` scan points, each with its nearest vertex of `x` that lies within the
    /// limits and faces the same way (`normals`: #V vertex normals). Returns (vertex,
    /// scan point, scan normal) triples. Data a part has moved away from (a lifted leg)
    /// still reaches that part this way.
    pub fn pulls(
        &self,
        x: &[V3],
        normals: &[V3],
        count: usize,
        lim: &MatchLimits,
    ) -> Vec<(usize, V3, V3)> {
        use rayon::prelude::*;
        let arr: Vec<[f64; 3]> = x.iter().map(|p| [p.x, p.y, p.z]).collect();
        let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&arr);
        let step = (self.points.len() / count.max(1)).max(1);
        let r2 = lim.max_distance * lim.max_distance;
        (0..self.points.len())
            .into_par_iter()
            .step_by(step)
            .filter_map(|i| {
                let p = self.points[i];
                let sn = self.normal(i);
                // the nearest vertex mostly faces the same way; only where it does not
                // (a thin part's far side) are the 8 nearest searched
                let q = [p.x, p.y, p.z];
                let one = tree.nearest_one::<SquaredEuclidean>(&q);
                if one.distance > r2 {
                    return None;
                }
                let v = one.item as usize;
                if normals[v].dot(&sn) >= lim.min_normal_cos {
                    return Some((v, p, sn));
                }
                tree.nearest_n::<SquaredEuclidean>(&q, NonZero::new(8).expect("non-zero"))
                    .iter()
                    .filter(|m| m.distance <= r2)
                    .map(|m| m.item as usize)
                    .find(|&v| normals[v].dot(&sn) >= lim.min_normal_cos)
                    .map(|v| (v, p, sn))
            })
            .collect()
    }

    /// The plane around cloud point `i` (see [`Patch`]): its CLOUD_K nearest (gathered
    /// as the small ball of two spacings, far cheaper than kiddo's k-nearest search, which
    /// serves only where the ball holds too few), their normals turned to agree with the
    /// point's own.
    fn patch(&self, i: usize, normals: &[V3]) -> Patch {
        let points = &self.points;
        let p = points[i];
        let r = 2.0 * self.spacing;
        let mut ball: Vec<(f64, u32)> = self
            .tree
            .within_unsorted::<SquaredEuclidean>(&[p.x, p.y, p.z], r * r)
            .iter()
            .map(|m| (m.distance, m.item as u32))
            .collect();
        if ball.len() < CLOUD_K {
            ball = self
                .tree
                .nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], NonZero::new(CLOUD_K).unwrap())
                .iter()
                .map(|m| (m.distance, m.item as u32))
                .collect();
        }
        let k = CLOUD_K.min(ball.len());
        if k < ball.len() {
            ball.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
        }
        let nb = &ball[..k];
        let n0 = normals[i];
        let mut c = V3::zeros();
        let mut nsum = V3::zeros();
        for &(_, q) in nb {
            let q = q as usize;
            c += points[q];
            let nq = normals[q];
            nsum += if nq.dot(&n0) < 0.0 { -nq } else { nq };
        }
        c /= k.max(1) as f64;
        // how far the neighbours spread about their centroid: a foot beyond it looks past
        // the edge of a hole (all the neighbours lie to one side)
        let reach = nb
            .iter()
            .map(|&(_, q)| (points[q as usize] - c).norm())
            .fold(self.spacing, f64::max);
        Patch {
            centroid: c,
            normal: nsum.try_normalize(0.0).unwrap_or(n0),
            reach,
        }
    }

    /// The scan's unit normal at point `i` (a mesh's vertex normal, or the cloud's given
    /// or estimated normal).
    pub fn normal(&self, i: usize) -> V3 {
        match &self.index {
            Index::Mesh { vertex_normals, .. } => vertex_normals[i],
            Index::Cloud { normals, .. } => normals[i],
        }
    }

    /// Distance from `x` to the scan: to its surface for a mesh, to its nearest point for
    /// a cloud (for colouring previews and reports; no limits apply).
    pub fn distance(&self, x: &V3) -> f64 {
        match &self.index {
            Index::Mesh { tri, .. } => {
                let (proj, _) =
                    tri.project_local_point_and_get_location(PVec::new(x.x, x.y, x.z), false);
                (V3::new(proj.point.x, proj.point.y, proj.point.z) - x).norm()
            }
            Index::Cloud { .. } => self.nearest_point(x).1,
        }
    }

    /// Nearest scan point (index, distance), for alignment.
    pub fn nearest_point(&self, x: &V3) -> (usize, f64) {
        let r = self.tree.nearest_one::<SquaredEuclidean>(&[x.x, x.y, x.z]);
        (r.item as usize, r.distance.sqrt())
    }

    /// The nearest scan point (index, distance) if one lies within `r`: a bounded
    /// query, which a far point answers sooner.
    pub fn nearest_point_within(&self, x: &V3, r: f64) -> Option<(usize, f64)> {
        nearest_within(&self.tree, x, r)
    }

    /// The nearest scan point's distance, or `cap` when none lies nearer.
    pub fn distance_capped(&self, x: &V3, cap: f64) -> f64 {
        self.nearest_point_within(x, cap)
            .map_or(cap, |(_, d)| d.min(cap))
    }

    /// The most similar scan point for a template vertex at `x` with unit normal `n`, or
    /// `None` (missing data). `w` falls with the normal disagreement and the distance.
    pub fn query(&self, x: &V3, n: &V3, lim: &MatchLimits) -> Option<Match> {
        if !x.iter().all(|c| c.is_finite()) {
            return None;
        }
        let (point, normal, oriented) = match &self.index {
            Index::Mesh {
                tri,
                face_normals,
                vertex_normals,
                boundary_vertex,
                boundary_edge,
            } => {
                let (proj, (t, loc)) = tri.project_local_point_and_get_location_with_max_dist(
                    PVec::new(x.x, x.y, x.z),
                    false,
                    lim.max_distance,
                )?;
                let corners = tri.indices()[t as usize];
                let on_boundary = match loc {
                    TrianglePointLocation::OnVertex(i) => {
                        boundary_vertex[corners[i as usize] as usize]
                    }
                    TrianglePointLocation::OnEdge(e, _) => {
                        // parry's edge numbering: 0 = AB, 1 = BC, 2 = AC
                        let (a, b) = match e {
                            0 => (corners[0], corners[1]),
                            1 => (corners[1], corners[2]),
                            _ => (corners[0], corners[2]),
                        };
                        boundary_edge.contains(&[a.min(b), a.max(b)])
                    }
                    _ => false,
                };
                if on_boundary {
                    return None;
                }
                let p = V3::new(proj.point.x, proj.point.y, proj.point.z);
                let normal = match loc.barycentric_coordinates() {
                    Some(bc) if !matches!(loc, TrianglePointLocation::OnFace(..)) => {
                        let m = (0..3)
                            .map(|k| vertex_normals[corners[k] as usize] * bc[k])
                            .sum::<V3>();
                        m.try_normalize(0.0).unwrap_or(face_normals[t as usize])
                    }
                    _ => face_normals[t as usize],
                };
                (p, normal, true)
            }
            Index::Cloud { normals, oriented } => {
                let one = self.tree.nearest_one::<SquaredEuclidean>(&[x.x, x.y, x.z]);
                if one.distance > lim.max_distance * lim.max_distance {
                    return None;
                }
                let first = one.item as usize;
                let patch = self.patches[first].get_or_init(|| self.patch(first, normals));
                let (c, normal, reach) = (patch.centroid, patch.normal, patch.reach);
                let foot = x - normal * normal.dot(&(x - c));
                // the foot must lie where there is data
                if (foot - c).norm() > reach {
                    return None;
                }
                (foot, normal, *oriented)
            }
        };
        let distance = (point - x).norm();
        if distance > lim.max_distance {
            return None;
        }
        let mut cos = n.dot(&normal);
        if !oriented {
            cos = cos.abs();
        }
        if cos < lim.min_normal_cos {
            return None;
        }
        let normal = if oriented || normal.dot(n) >= 0.0 {
            normal
        } else {
            -normal
        };
        let d = distance / lim.max_distance;
        let weight = cos.clamp(0.0, 1.0) * (1.0 - d * d).max(0.0);
        (weight > 0.0).then_some(Match {
            point,
            normal,
            weight,
            distance,
        })
    }
}

/// Unit normals of a point cloud from the principal axes of each point's 12 nearest
/// neighbours, turned to point away from the cloud's centroid (a guess: the sign is
/// treated as unknown when matching).
fn estimate_normals(points: &[V3], tree: &ImmutableKdTree<f64, 3>) -> Vec<V3> {
    use rayon::prelude::*;
    let centroid = points.iter().sum::<V3>() / points.len() as f64;
    points
        .par_iter()
        .map(|p| {
            let nb =
                tree.nearest_n::<SquaredEuclidean>(&[p.x, p.y, p.z], NonZero::new(12).unwrap());
            let n = crate::mesh::plane_normal(nb.iter().map(|m| points[m.item as usize]));
            if n.dot(&(p - centroid)) < 0.0 { -n } else { n }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat square patch in z = 0, [-1, 1]^2, facing +z.
    fn patch() -> Mesh {
        let n = 10;
        let mut m = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                m.vertices.push(V3::new(
                    -1.0 + 2.0 * i as f64 / n as f64,
                    -1.0 + 2.0 * j as f64 / n as f64,
                    0.0,
                ));
            }
        }
        for j in 0..n {
            for i in 0..n {
                let a = (j * (n + 1) + i) as u32;
                let (b, c, d) = (a + 1, a + n as u32 + 2, a + n as u32 + 1);
                m.triangles.extend([[a, b, c], [a, c, d]]);
            }
        }
        m
    }

    fn check(surface: &ScanSurface) {
        let lim = MatchLimits {
            max_distance: 0.2,
            min_normal_cos: 0.5,
        };
        let up = V3::z();
        let m = surface
            .query(&V3::new(0.3, -0.2, 0.1), &up, &lim)
            .expect("above the patch: a match");
        assert!(
            (m.point - V3::new(0.3, -0.2, 0.0)).norm() < 1e-9 && (m.distance - 0.1).abs() < 1e-9
        );
        assert!(m.weight > 0.0 && m.weight <= 1.0);
        assert!(
            surface.query(&V3::new(0.3, -0.2, 0.5), &up, &lim).is_none(),
            "too far"
        );
        assert!(
            surface
                .query(&V3::new(0.3, -0.2, 0.1), &-up, &lim)
                .is_none(),
            "faces the wrong way"
        );
        assert!(
            surface.query(&V3::new(1.1, 0.0, 0.05), &up, &lim).is_none(),
            "past the scan's edge"
        );
    }

    #[test]
    fn mesh_scan_labels_missing_data() {
        check(&ScanSurface::new(&patch()).unwrap());
    }

    #[test]
    fn point_cloud_scan_labels_missing_data() {
        let mut cloud = Mesh::new(Vec::new(), Vec::new());
        let n = 60;
        for j in 0..=n {
            for i in 0..=n {
                cloud.vertices.push(V3::new(
                    -1.0 + 2.0 * i as f64 / n as f64,
                    -1.0 + 2.0 * j as f64 / n as f64,
                    0.0,
                ));
            }
        }
        cloud.normals = Some(vec![V3::z(); cloud.vertices.len()]);
        check(&ScanSurface::new(&cloud).unwrap());
        // without normals they are estimated (sign unknown): wrong-way faces still match
        let bare = Mesh::new(cloud.vertices.clone(), vec![]);
        let s = ScanSurface::new(&bare).unwrap();
        let lim = MatchLimits {
            max_distance: 0.2,
            min_normal_cos: 0.5,
        };
        assert!(s.query(&V3::new(0.0, 0.0, 0.1), &-V3::z(), &lim).is_some());
        assert!(s.query(&V3::new(1.2, 0.0, 0.05), &V3::z(), &lim).is_none());
    }
}
