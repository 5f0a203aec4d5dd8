//! Mesh quality figures of Ju et al. 2004, section 3.1: how much each edge length,
//! triangle angle and triangle area of a deformed mesh varies against the same element of
//! the original (template) mesh, as mean and standard deviation; and flipped triangles.
//!
//! Variations are relative for lengths and areas, `(new - old) / old`, and absolute in
//! radians for angles. The paper does not say its units; relative figures keep the numbers
//! independent of the scan's scale, as the rest of conformd does.

use super::{Mesh, V3, topology};

/// Mean and standard deviation of one variation.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Stat {
    pub mean: f64,
    pub std: f64,
}

impl Stat {
    pub fn of(values: impl Iterator<Item = f64>) -> Stat {
        let (mut n, mut s, mut s2) = (0usize, 0.0, 0.0);
        for v in values.filter(|v| v.is_finite()) {
            n += 1;
            s += v;
            s2 += v * v;
        }
        if n == 0 {
            return Stat::default();
        }
        let mean = s / n as f64;
        Stat {
            mean,
            std: (s2 / n as f64 - mean * mean).max(0.0).sqrt(),
        }
    }
}

/// The paper's figures for a deformed mesh against its original.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Variation {
    /// per edge: (length - original) / original
    pub edge_length: Stat,
    /// per triangle corner: angle - original angle, radians
    pub angle: Stat,
    /// per triangle: (area - original) / original
    pub area: Stat,
}

/// Computes the variation figures of `deformed` against `original` (same topology).
///
/// - `original`, `deformed`: #V positions each
/// - `tris`: #F triangles shared by both
pub fn variation(original: &[V3], deformed: &[V3], tris: &[[u32; 3]]) -> Variation {
    VariationBaseline::new(original, tris).measure(deformed)
}

/// The original's edge lengths, angles and areas, measured once so that the figures of
/// many deformed versions (one per iteration) cost one pass each.
pub struct VariationBaseline {
    edges: Vec<[u32; 2]>,
    lengths: Vec<f64>,
    tris: Vec<[u32; 3]>,
    areas: Vec<f64>,
    angles: Vec<[f64; 3]>,
}

fn tri_area(p: &[V3], t: &[u32; 3]) -> f64 {
    0.5 * (p[t[1] as usize] - p[t[0] as usize])
        .cross(&(p[t[2] as usize] - p[t[0] as usize]))
        .norm()
}

fn tri_angles(p: &[V3], t: &[u32; 3]) -> [f64; 3] {
    std::array::from_fn(|k| {
        let o = p[t[k] as usize];
        (p[t[(k + 1) % 3] as usize] - o).angle(&(p[t[(k + 2) % 3] as usize] - o))
    })
}

impl VariationBaseline {
    pub fn new(original: &[V3], tris: &[[u32; 3]]) -> Self {
        let edges = topology::edges(tris);
        let lengths = edges
            .iter()
            .map(|&[a, b]| (original[a as usize] - original[b as usize]).norm())
            .collect();
        VariationBaseline {
            lengths,
            edges,
            tris: tris.to_vec(),
            areas: tris.iter().map(|t| tri_area(original, t)).collect(),
            angles: tris.iter().map(|t| tri_angles(original, t)).collect(),
        }
    }

    pub fn measure(&self, deformed: &[V3]) -> Variation {
        let edge_length = Stat::of(self.edges.iter().zip(&self.lengths).map(|(&[a, b], &l0)| {
            ((deformed[a as usize] - deformed[b as usize]).norm() - l0) / l0
        }));
        let area = Stat::of(
            self.tris
                .iter()
                .zip(&self.areas)
                .map(|(t, &a0)| (tri_area(deformed, t) - a0) / a0),
        );
        let angle = Stat::of(self.tris.iter().zip(&self.angles).flat_map(|(t, a0)| {
            let a1 = tri_angles(deformed, t);
            (0..3).map(move |k| a1[k] - a0[k])
        }));
        Variation {
            edge_length,
            angle,
            area,
        }
    }
}

/// Triangles folded over in the mesh itself: the triangle's normal is more than 150
/// degrees away from the normals of at least two of the triangles sharing its edges (or
/// the triangle has no area). A smooth surface, and a sound conformation of one, has none;
/// a fit that crumples or turns a patch inside out does.
pub fn folded_triangles(mesh: &Mesh) -> usize {
    let nt = mesh.triangles.len();
    let normals: Vec<Option<V3>> = (0..nt)
        .map(|t| {
            mesh.face_normal_scaled(t)
                .try_normalize(0.0)
                .filter(|n| n.iter().all(|c| c.is_finite()))
        })
        .collect();
    // (edge, triangle) sorted by edge: each run is the triangles sharing one edge
    let mut by_edge: Vec<(u64, u32)> = mesh
        .triangles
        .iter()
        .enumerate()
        .flat_map(|(i, t)| {
            (0..3).map(move |k| {
                (
                    super::topology::undirected_key(t[k], t[(k + 1) % 3]),
                    i as u32,
                )
            })
        })
        .collect();
    by_edge.sort_unstable();
    let mut opposed = vec![0u32; nt];
    for run in by_edge.chunk_by(|a, b| a.0 == b.0) {
        for &(_, i) in run {
            for &(_, j) in run {
                let (i, j) = (i as usize, j as usize);
                if let (Some(ni), Some(nj)) = (normals[i], normals[j])
                    && i != j
                    && ni.dot(&nj) < -0.866
                {
                    opposed[i] += 1;
                }
            }
        }
    }
    (0..nt)
        .filter(|&i| normals[i].is_none() || opposed[i] >= 2)
        .count()
}

/// Triangles whose orientation disagrees with the same triangle in a reference (a ground
/// truth, or the template): the normals point more than 90 degrees apart.
pub fn flipped_against(result: &[V3], reference: &[V3], tris: &[[u32; 3]]) -> usize {
    let n = |p: &[V3], t: &[u32; 3]| {
        (p[t[1] as usize] - p[t[0] as usize]).cross(&(p[t[2] as usize] - p[t[0] as usize]))
    };
    tris.iter()
        .filter(|t| n(result, t).dot(&n(reference, t)) <= 0.0)
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_scale_gives_constant_variations() {
        let v = vec![
            V3::new(0., 0., 0.),
            V3::new(1., 0., 0.),
            V3::new(0., 1., 0.),
            V3::new(0., 0., 1.),
        ];
        let t = vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];
        let w: Vec<V3> = v.iter().map(|p| p * 2.0).collect();
        let var = variation(&v, &w, &t);
        assert!((var.edge_length.mean - 1.0).abs() < 1e-12 && var.edge_length.std < 1e-9);
        assert!((var.area.mean - 3.0).abs() < 1e-12);
        assert!(var.angle.mean.abs() < 1e-12);
        assert_eq!(folded_triangles(&Mesh::new(w.clone(), t.clone())), 0);
        assert_eq!(flipped_against(&w, &v, &t), 0);
        // Mirror one vertex through the opposite face: its triangles flip.
        let mut m = w.clone();
        m[3] = V3::new(0., 0., -2.0);
        assert_eq!(flipped_against(&m, &v, &t), 3);
    }
}
