//! The model's quality figures (compactness, generalisation, specificity).

use super::*;

/// Model quality figures for 1..=k modes (Davies et al.): compactness (cumulative
/// variance share), generalisation (mean leave-one-out reconstruction error) and
/// specificity (mean distance of random model instances to the nearest sample), the last
/// two as RMS per-vertex distances.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Quality {
    pub modes: Vec<usize>,
    pub compactness: Vec<f64>,
    pub generalisation: Vec<f64>,
    pub specificity: Vec<f64>,
}

pub fn quality(
    samples: &[(String, Mesh)],
    opts: &BuildOptions,
    max_k: usize,
    seed: u64,
) -> Result<Quality, ModelError> {
    let full = ShapeModel::build(samples, opts)?;
    let kmax = max_k.min(full.modes.len()).max(1);
    let ks: Vec<usize> = (1..=kmax).collect();
    let mut cum = 0.0;
    let compactness = full
        .explained
        .iter()
        .take(kmax)
        .map(|e| {
            cum += e;
            cum
        })
        .collect();
    // generalisation: leave one out, reconstruct it with k modes
    let loo: Vec<Vec<f64>> = (0..samples.len())
        .into_par_iter()
        .map(|i| {
            let rest: Vec<(String, Mesh)> = samples
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, s)| s.clone())
                .collect();
            let m = match ShapeModel::build(
                &rest,
                &BuildOptions {
                    max_modes: kmax,
                    ..opts.clone()
                },
            ) {
                Ok(m) => m,
                Err(_) => return vec![f64::NAN; kmax],
            };
            let s = m
                .score(&samples[i].0, &samples[i].1)
                .expect("same template");
            ks.iter()
                .map(|&k| {
                    let k = k.min(m.modes.len());
                    let target = m.instance(&s.scores); // all modes: the aligned sample minus residual
                    let recon = m.instance(&s.scores[..k]);
                    let d2: f64 = target
                        .iter()
                        .zip(&recon)
                        .map(|(a, b)| (a - b).norm_squared())
                        .sum();
                    (d2 / recon.len() as f64 + s.residual * s.residual).sqrt()
                })
                .collect()
        })
        .collect();
    let generalisation = (0..kmax)
        .map(|k| loo.iter().map(|l| l[k]).sum::<f64>() / loo.len() as f64)
        .collect();
    // specificity: random instances against the aligned training shapes
    let train: Vec<Vec<V3>> = samples
        .iter()
        .map(|(n, m)| {
            let s = full.score(n, m).expect("same template");

            full.instance(&s.scores)
        })
        .collect();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let specificity = ks
        .iter()
        .map(|&k| {
            let draws = 50;
            (0..draws)
                .map(|_| {
                    let b: Vec<f64> = full.variances[..k]
                        .iter()
                        .map(|v| Normal::new(0.0, v.sqrt()).expect("finite").sample(&mut rng))
                        .collect();
                    let x = full.instance(&b);
                    train
                        .iter()
                        .map(|t| {
                            (t.iter()
                                .zip(&x)
                                .map(|(a, b)| (a - b).norm_squared())
                                .sum::<f64>()
                                / x.len() as f64)
                                .sqrt()
                        })
                        .fold(f64::INFINITY, f64::min)
                })
                .sum::<f64>()
                / draws as f64
        })
        .collect();
    Ok(Quality {
        modes: ks,
        compactness,
        generalisation,
        specificity,
    })
}

impl std::fmt::Display for Quality {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "  modes  compactness  generalisation  specificity")?;
        for i in 0..self.modes.len() {
            write!(
                f,
                "\n  {:>5}  {:>11.3}  {:>14.4e}  {:>11.4e}",
                self.modes[i], self.compactness[i], self.generalisation[i], self.specificity[i]
            )?;
        }
        Ok(())
    }
}
