//! Building a model: the samples checked against each other, generalised Procrustes
//! alignment, the segment's subset, and the principal components.

use super::*;

/// Aligns shapes to each other (generalised Procrustes): returns them in the mean's frame.
fn align_all(shapes: &[Vec<V3>], align: Align) -> Vec<Vec<V3>> {
    if align == Align::None {
        return shapes.to_vec();
    }
    let scale = align == Align::Procrustes;
    let mean_size = shapes.iter().map(|s| centroid_size(s)).sum::<f64>() / shapes.len() as f64;
    let mut mean = shapes[0].clone();
    for _ in 0..20 {
        let aligned: Vec<Vec<V3>> = shapes
            .par_iter()
            .map(|s| apply(&fit_similarity(s, &mean, None, scale), s))
            .collect();
        let mut next: Vec<V3> = (0..mean.len())
            .map(|i| aligned.iter().map(|s| s[i]).sum::<V3>() / aligned.len() as f64)
            .collect();
        // keep the mean centred and, for Procrustes, at the samples' mean size
        let c = next.iter().sum::<V3>() / next.len() as f64;
        let f = if scale {
            mean_size / centroid_size(&next)
        } else {
            1.0
        };
        next.iter_mut().for_each(|p| *p = (*p - c) * f);
        let change = next
            .iter()
            .zip(&mean)
            .map(|(a, b)| (a - b).norm_squared())
            .sum::<f64>()
            .sqrt();
        mean = next;
        if change < 1e-10 * mean_size * (mean.len() as f64).sqrt() {
            break;
        }
    }
    shapes
        .par_iter()
        .map(|s| apply(&fit_similarity(s, &mean, None, scale), s))
        .collect()
}

/// The samples agree: one vertex count and triangulation, every coordinate finite.
fn check_samples(samples: &[(String, Mesh)]) -> Result<(), ModelError> {
    let (first_name, first) = &samples[0];
    for (name, m) in samples {
        if m.vertices.len() != first.vertices.len() {
            return Err(ModelError::VertexCount {
                name: name.clone(),
                got: m.vertices.len(),
                first: first_name.clone(),
                want: first.vertices.len(),
            });
        }
        if m.triangles != first.triangles {
            return Err(ModelError::Topology {
                name: name.clone(),
                first: first_name.clone(),
            });
        }
        if let Some(v) = m.first_non_finite() {
            return Err(ModelError::NotFinite {
                name: name.clone(),
                vertex: v,
            });
        }
    }
    Ok(())
}

/// The vertices a model covers (all, or vertex group `group`), and the triangles among
/// them renumbered.
#[allow(clippy::type_complexity)]
fn group_subset(
    first: &Mesh,
    group: Option<&str>,
) -> Result<(Vec<u32>, Vec<[u32; 3]>), ModelError> {
    let indices: Vec<u32> = match group {
        Some(g) => first
            .groups
            .get(g)
            .cloned()
            .ok_or_else(|| ModelError::NoGroup {
                group: g.to_string(),
                known: first.group_names(),
            })?,
        None => (0..first.vertices.len() as u32).collect(),
    };
    let mut local = vec![u32::MAX; first.vertices.len()];
    for (k, &i) in indices.iter().enumerate() {
        local[i as usize] = k as u32;
    }
    let triangles: Vec<[u32; 3]> = first
        .triangles
        .iter()
        .filter(|t| t.iter().all(|&i| local[i as usize] != u32::MAX))
        .map(|t| t.map(|i| local[i as usize]))
        .collect();
    Ok((indices, triangles))
}

impl ShapeModel {
    /// Builds a model from conformed meshes sharing one template's topology.
    ///
    /// - `samples`: (name, mesh) pairs, at least 3
    /// - returns the model with min(n - 1, `max_modes`) modes
    pub fn build(
        samples: &[(String, Mesh)],
        opts: &BuildOptions,
    ) -> Result<ShapeModel, ModelError> {
        if samples.len() < 3 {
            return Err(ModelError::TooFew(samples.len()));
        }
        check_samples(samples)?;
        let first = &samples[0].1;
        let (indices, triangles) = group_subset(first, opts.group.as_deref())?;
        let shapes: Vec<Vec<V3>> = samples
            .iter()
            .map(|(_, m)| indices.iter().map(|&i| m.vertices[i as usize]).collect())
            .collect();
        let aligned = align_all(&shapes, opts.align);
        let n = aligned.len();
        let dim = indices.len() * 3;
        let rows: Vec<Vec<f64>> = aligned.iter().map(|s| flatten(s)).collect();
        let mean: Vec<f64> = (0..dim)
            .map(|j| rows.iter().map(|r| r[j]).sum::<f64>() / n as f64)
            .collect();
        let centred: Vec<Vec<f64>> = rows
            .iter()
            .map(|r| r.iter().zip(&mean).map(|(a, b)| a - b).collect())
            .collect();
        // Gram matrix G = X X^T / (n - 1): n x n instead of dim x dim
        let pairs: Vec<(usize, usize)> = (0..n).flat_map(|i| (i..n).map(move |j| (i, j))).collect();
        let dots: Vec<f64> = pairs
            .par_iter()
            .map(|&(i, j)| {
                centred[i]
                    .iter()
                    .zip(&centred[j])
                    .map(|(a, b)| a * b)
                    .sum::<f64>()
                    / (n - 1) as f64
            })
            .collect();
        let mut g = DMatrix::<f64>::zeros(n, n);
        for (&(i, j), &d) in pairs.iter().zip(&dots) {
            g[(i, j)] = d;
            g[(j, i)] = d;
        }
        let eig = SymmetricEigen::new(g);
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
        let total: f64 = eig.eigenvalues.iter().map(|l| l.max(0.0)).sum();
        // variance next to nothing, against the shapes' own spread about their centroid,
        // is rounding: the meshes are one shape, and a model of it would be noise
        let c = V3::from_iterator(
            (0..3).map(|a| mean.iter().skip(a).step_by(3).sum::<f64>() / indices.len() as f64),
        );
        let spread: f64 = mean
            .chunks_exact(3)
            .map(|p| (V3::new(p[0], p[1], p[2]) - c).norm_squared())
            .sum();
        if !(total > 1e-12 * spread) {
            return Err(ModelError::NoVariance { samples: n });
        }
        let lmax = eig.eigenvalues[order[0]].max(0.0);
        let keep: Vec<usize> = order
            .into_iter()
            .filter(|&k| eig.eigenvalues[k] > 1e-12 * lmax.max(1e-300))
            .take(opts.max_modes.min(n - 1))
            .collect();
        let modes: Vec<Vec<f32>> = keep
            .par_iter()
            .map(|&k| {
                let u = eig.eigenvectors.column(k);
                let mut m = vec![0.0f64; dim];
                for (i, row) in centred.iter().enumerate() {
                    let w = u[i];
                    m.iter_mut().zip(row).for_each(|(a, b)| *a += w * b);
                }
                let norm = m.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-300);
                m.iter().map(|x| (x / norm) as f32).collect()
            })
            .collect();
        let variances: Vec<f64> = keep.iter().map(|&k| eig.eigenvalues[k]).collect();
        Ok(ShapeModel {
            format: FORMAT.into(),
            version: VERSION,
            template_vertices: first.vertices.len(),
            template_fingerprint: fingerprint(first.vertices.len(), &first.triangles),
            align: opts.align,
            group: opts.group.clone(),
            indices,
            triangles,
            samples: samples.iter().map(|(n, _)| n.clone()).collect(),
            mean,
            explained: variances.iter().map(|v| v / total.max(1e-300)).collect(),
            variances,
            modes,
            total_variance: total,
            posture_modes: if opts.posture { keep.len() } else { 0 },
        })
    }
}
