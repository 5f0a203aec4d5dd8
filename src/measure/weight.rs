//! Weight from measurements: a linear regression (ridge on standardised measurements)
//! fitted to the weights a station records (scale readings), with its leave-one-out
//! error, saved as JSON; afterwards every result gets a predicted weight and an interval.

use super::Measurement;
use nalgebra::{DMatrix, DVector};

pub const FORMAT: &str = "conformd-weight";

#[derive(Debug, thiserror::Error)]
pub enum WeightError {
    #[error(
        "a weight regression on {features} measurement(s) needs at least {need} weighed results (3 more than its measurements, and never fewer than 5), got {got}"
    )]
    TooFew {
        got: usize,
        need: usize,
        features: usize,
    },
    #[error("sample {sample}: {message}")]
    Sample { sample: String, message: String },
    #[error("the result has no measurement '{0}', which the weight regression uses")]
    Missing(String),
    #[error("{path}: not a weight regression: {message}")]
    File { path: String, message: String },
}

/// A fitted regression `kg = b0 + sum_k b_k (m_k - mean_k) / sd_k`.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct WeightModel {
    pub format: String,
    pub version: u32,
    pub features: Vec<String>,
    pub means: Vec<f64>,
    pub sds: Vec<f64>,
    /// intercept, then one coefficient per feature
    pub coefficients: Vec<f64>,
    pub samples: usize,
    /// leave-one-out: mean absolute error relative to the weight, and its RMS in kg
    pub cv_mean_relative_error: f64,
    pub cv_rmse_kg: f64,
}

/// A predicted weight with a 95% interval (from the leave-one-out error).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct WeightPrediction {
    pub kg: f64,
    pub low: f64,
    pub high: f64,
}

/// Ridge strength on standardised features: enough to keep collinear measurements
/// (girths that move together) from trading huge coefficients.
const RIDGE: f64 = 1e-3;

fn solve(x: &[Vec<f64>], y: &[f64]) -> Option<DVector<f64>> {
    let (n, k) = (x.len(), x[0].len());
    let a = DMatrix::from_fn(n, k + 1, |i, j| if j == 0 { 1.0 } else { x[i][j - 1] });
    let mut ata = a.transpose() * &a;
    for j in 1..=k {
        ata[(j, j)] += RIDGE * n as f64;
    }
    let aty = a.transpose() * DVector::from_column_slice(y);
    ata.cholesky().map(|c| c.solve(&aty))
}

impl WeightModel {
    /// Fits weights `kg` of samples `(name, measurements)` on the measurements named
    /// `features`.
    pub fn fit(
        samples: &[(String, Vec<Measurement>, f64)],
        features: &[String],
    ) -> Result<WeightModel, WeightError> {
        let need = (features.len() + 3).max(5);
        if samples.len() < need {
            return Err(WeightError::TooFew {
                got: samples.len(),
                need,
                features: features.len(),
            });
        }
        let mut raw: Vec<Vec<f64>> = Vec::with_capacity(samples.len());
        let mut y = Vec::with_capacity(samples.len());
        for (name, ms, kg) in samples {
            if !(kg.is_finite() && *kg > 0.0) {
                return Err(WeightError::Sample {
                    sample: name.clone(),
                    message: format!("weight {kg} is not a positive number"),
                });
            }
            raw.push(
                features
                    .iter()
                    .map(|f| {
                        ms.iter()
                            .find(|m| &m.name == f)
                            .map(|m| m.value)
                            .ok_or_else(|| WeightError::Sample {
                                sample: name.clone(),
                                message: format!("no measurement '{f}'"),
                            })
                    })
                    .collect::<Result<_, _>>()?,
            );
            y.push(*kg);
        }
        let n = raw.len() as f64;
        let k = features.len();
        let means: Vec<f64> = (0..k)
            .map(|j| raw.iter().map(|r| r[j]).sum::<f64>() / n)
            .collect();
        let sds: Vec<f64> = (0..k)
            .map(|j| {
                let v = raw.iter().map(|r| (r[j] - means[j]).powi(2)).sum::<f64>() / n;
                if v > 0.0 { v.sqrt() } else { 1.0 }
            })
            .collect();
        let x: Vec<Vec<f64>> = raw
            .iter()
            .map(|r| (0..k).map(|j| (r[j] - means[j]) / sds[j]).collect())
            .collect();
        let bad = |m: &str| WeightError::Sample {
            sample: "all".into(),
            message: m.into(),
        };
        let coef = solve(&x, &y).ok_or_else(|| bad("the measurements do not determine a fit"))?;
        // leave-one-out: refit without each sample, predict it
        let (mut abs_rel, mut sq) = (0.0, 0.0);
        for i in 0..x.len() {
            let xs: Vec<Vec<f64>> = (0..x.len())
                .filter(|&j| j != i)
                .map(|j| x[j].clone())
                .collect();
            let ys: Vec<f64> = (0..y.len()).filter(|&j| j != i).map(|j| y[j]).collect();
            let c = solve(&xs, &ys).ok_or_else(|| bad("a leave-one-out fit failed"))?;
            let p = c[0] + (0..k).map(|j| c[j + 1] * x[i][j]).sum::<f64>();
            abs_rel += ((p - y[i]) / y[i]).abs();
            sq += (p - y[i]).powi(2);
        }
        Ok(WeightModel {
            format: FORMAT.into(),
            version: 1,
            features: features.to_vec(),
            means,
            sds,
            coefficients: coef.iter().copied().collect(),
            samples: x.len(),
            cv_mean_relative_error: abs_rel / n,
            cv_rmse_kg: (sq / n).sqrt(),
        })
    }

    /// The weight of a result from its measurements.
    pub fn predict(&self, ms: &[Measurement]) -> Result<WeightPrediction, WeightError> {
        let mut kg = self.coefficients[0];
        for (j, f) in self.features.iter().enumerate() {
            let m = ms
                .iter()
                .find(|m| &m.name == f)
                .ok_or_else(|| WeightError::Missing(f.clone()))?;
            kg += self.coefficients[j + 1] * (m.value - self.means[j]) / self.sds[j];
        }
        let half = 1.96 * self.cv_rmse_kg;
        Ok(WeightPrediction {
            kg,
            low: kg - half,
            high: kg + half,
        })
    }

    pub fn load(path: &std::path::Path) -> Result<WeightModel, WeightError> {
        let shown = path.display().to_string();
        let bad = |message: String| WeightError::File {
            path: shown.clone(),
            message,
        };
        let text =
            crate::files::read_text_limited(path, 1 << 20).map_err(|e| bad(e.to_string()))?;
        let m: WeightModel = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        let k = m.features.len();
        if m.format != FORMAT
            || m.means.len() != k
            || m.sds.len() != k
            || m.coefficients.len() != k + 1
            || !m
                .coefficients
                .iter()
                .chain(&m.means)
                .chain(&m.sds)
                .all(|v| v.is_finite())
        {
            return Err(bad(format!(
                "expected format '{FORMAT}' with {k} means, deviations and {} coefficients, all finite",
                k + 1
            )));
        }
        Ok(m)
    }
}

impl std::fmt::Display for WeightModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "weight from {} ({} weighed results): leave-one-out error {:.2}% mean, {:.2} kg RMS (95% interval +/- {:.2} kg)",
            self.features.join(", "),
            self.samples,
            self.cv_mean_relative_error * 100.0,
            self.cv_rmse_kg,
            1.96 * self.cv_rmse_kg
        )
    }
}
