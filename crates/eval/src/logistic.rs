//! Logistic regression: the probability that a pose is right from several of its numbers.
//!
//! - [`Logistic::fit`]: maximum likelihood with an L2 penalty ½λ‖w‖² on the weights (not on
//!   the intercept), by Newton's method; the features may first be standardised (each minus
//!   its mean, over its standard deviation, so one λ treats every feature alike).
//! - [`Logistic::probability`]: σ(w·(x − mean)/scale + b).
//!
//! Serialises as JSON (`{"features": […], "mean": […], "scale": […], "weights": […],
//! "bias": b}`); [`Logistic::check`] validates a file's model. Deterministic: no random choice.

use serde::{Deserialize, Serialize};

/// A fitted logistic model over named features.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Logistic {
    /// The features' names, in the order of `x`.
    pub features: Vec<String>,
    /// Subtracted from each feature (0 when not standardised).
    pub mean: Vec<f64>,
    /// Each feature is divided by this after the mean (1 when not standardised).
    pub scale: Vec<f64>,
    /// One weight per feature, on the standardised value.
    pub weights: Vec<f64>,
    /// The intercept.
    pub bias: f64,
}

/// How [`Logistic::fit`] fits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogisticOptions {
    /// λ of the penalty ½λ‖w‖² (the intercept is free).
    pub l2: f64,
    /// Standardise the features first (mean 0, standard deviation 1 over the samples).
    pub standardise: bool,
    /// Newton steps at most (it stops earlier when no parameter moves by 1e-10).
    pub max_steps: usize,
}

impl Default for LogisticOptions {
    fn default() -> Self {
        LogisticOptions {
            l2: 1.0,
            standardise: true,
            max_steps: 100,
        }
    }
}

impl Logistic {
    /// Fits `right` on the rows of `x` (one row per sample, one column per name of
    /// `features`). Errors on no sample, a row of another length, a non-finite value or a
    /// singular system (λ = 0 on separable data).
    pub fn fit(
        features: Vec<String>,
        x: &[Vec<f64>],
        right: &[bool],
        options: LogisticOptions,
    ) -> Result<Logistic, String> {
        let d = features.len();
        if x.is_empty() || x.len() != right.len() {
            return Err(format!(
                "{} samples and {} labels: need at least one of each, as many labels as samples",
                x.len(),
                right.len()
            ));
        }
        for (i, row) in x.iter().enumerate() {
            if row.len() != d {
                return Err(format!("sample {i} has {} values, not {d}", row.len()));
            }
            if let Some(v) = row.iter().find(|v| !v.is_finite()) {
                return Err(format!("sample {i} has a value that is not finite ({v})"));
            }
        }
        let n = x.len() as f64;
        let (mean, scale) = if options.standardise {
            let mean: Vec<f64> = (0..d)
                .map(|j| x.iter().map(|r| r[j]).sum::<f64>() / n)
                .collect();
            let scale: Vec<f64> = (0..d)
                .map(|j| {
                    let var = x.iter().map(|r| (r[j] - mean[j]).powi(2)).sum::<f64>() / n;
                    // A constant feature keeps its scale 1 (its weight stays 0 under the penalty).
                    if var > 1e-24 { var.sqrt() } else { 1.0 }
                })
                .collect();
            (mean, scale)
        } else {
            (vec![0.0; d], vec![1.0; d])
        };
        let z: Vec<Vec<f64>> = x
            .iter()
            .map(|r| {
                r.iter()
                    .zip(&mean)
                    .zip(&scale)
                    .map(|((v, m), s)| (v - m) / s)
                    .chain([1.0])
                    .collect()
            })
            .collect();
        // θ = (w, b).
        let mut theta = vec![0.0f64; d + 1];
        for _ in 0..options.max_steps.max(1) {
            let mut grad = vec![0.0f64; d + 1];
            let mut hess = vec![vec![0.0f64; d + 1]; d + 1];
            for (zi, &yi) in z.iter().zip(right) {
                let s: f64 = zi.iter().zip(&theta).map(|(a, b)| a * b).sum();
                let p = sigmoid(s);
                let y = f64::from(u8::from(yi));
                for (a, (g, h)) in grad.iter_mut().zip(&mut hess).enumerate() {
                    *g += (p - y) * zi[a];
                    for (hab, zb) in h.iter_mut().zip(zi) {
                        *hab += p * (1.0 - p) * zi[a] * zb;
                    }
                }
            }
            for j in 0..d {
                grad[j] += options.l2 * theta[j];
                hess[j][j] += options.l2;
            }
            let step = solve(hess, grad)?;
            let mut change = 0.0f64;
            for (t, s) in theta.iter_mut().zip(step) {
                *t -= s;
                change = change.max(s.abs());
            }
            if change < 1e-10 {
                break;
            }
        }
        let bias = theta.pop().unwrap_or(0.0);
        Ok(Logistic {
            features,
            mean,
            scale,
            weights: theta,
            bias,
        })
    }

    /// Lengths agree, every number is finite and every scale positive: what a model read from
    /// a file must satisfy before [`Logistic::probability`] is used.
    pub fn check(&self) -> Result<(), String> {
        let d = self.features.len();
        if self.mean.len() != d || self.scale.len() != d || self.weights.len() != d {
            return Err(format!(
                "{d} features but {} means, {} scales and {} weights",
                self.mean.len(),
                self.scale.len(),
                self.weights.len()
            ));
        }
        let all = self
            .mean
            .iter()
            .chain(&self.scale)
            .chain(&self.weights)
            .chain([&self.bias]);
        if let Some(v) = all.into_iter().find(|v| !v.is_finite()) {
            return Err(format!("a parameter is not finite ({v})"));
        }
        if let Some(s) = self.scale.iter().find(|&&s| s <= 0.0) {
            return Err(format!("a scale is not positive ({s})"));
        }
        Ok(())
    }

    /// w·(x − mean)/scale + b for one sample (its values in the order of `features`).
    pub fn logit(&self, x: &[f64]) -> f64 {
        x.iter()
            .zip(&self.mean)
            .zip(&self.scale)
            .zip(&self.weights)
            .map(|(((v, m), s), w)| w * (v - m) / s)
            .sum::<f64>()
            + self.bias
    }

    /// σ([`Logistic::logit`]), in (0, 1).
    pub fn probability(&self, x: &[f64]) -> f64 {
        sigmoid(self.logit(x))
    }
}

fn sigmoid(s: f64) -> f64 {
    1.0 / (1.0 + (-s).exp())
}

/// Solves `a · x = b` by Gaussian elimination with partial pivoting.
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Result<Vec<f64>, String> {
    let n = b.len();
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .unwrap_or(col);
        if a[pivot][col].abs() < 1e-12 {
            return Err("the Newton system is singular (separable data without a penalty?)".into());
        }
        a.swap(col, pivot);
        b.swap(col, pivot);
        let (top, below) = a.split_at_mut(col + 1);
        let pivot_row = &top[col];
        let (pivot_b, rest_b) = {
            let (t, r) = b.split_at_mut(col + 1);
            (t[col], r)
        };
        for (row, rb) in below.iter_mut().zip(rest_b) {
            let f = row[col] / pivot_row[col];
            for (x, p) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                *x -= f * p;
            }
            *rb -= f * pivot_b;
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        let s: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    Ok(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(n: usize) -> Vec<String> {
        (0..n).map(|i| format!("f{i}")).collect()
    }

    #[test]
    fn the_fit_recovers_a_known_logistic_model_and_orders_samples_by_it() {
        // Labels drawn deterministically from p = σ(2·x₀ − x₁ + 0.5) on a grid: the fit
        // (no penalty to speak of) recovers the weights within sampling error.
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for i in 0..40 {
            for j in 0..40 {
                let (a, b) = (i as f64 / 10.0 - 2.0, j as f64 / 10.0 - 2.0);
                let p = sigmoid(2.0 * a - b + 0.5);
                // Several labels per point in proportion to p.
                for k in 0..10 {
                    x.push(vec![a, b]);
                    y.push((k as f64 + 0.5) / 10.0 < p);
                }
            }
        }
        let options = LogisticOptions {
            l2: 1e-6,
            standardise: false,
            ..LogisticOptions::default()
        };
        let m = Logistic::fit(names(2), &x, &y, options).unwrap();
        assert!((m.weights[0] - 2.0).abs() < 0.15, "{m:?}");
        assert!((m.weights[1] + 1.0).abs() < 0.1, "{m:?}");
        assert!((m.bias - 0.5).abs() < 0.1, "{m:?}");
        // Standardised: the same probabilities (nearly), other parameters.
        let standardised = LogisticOptions {
            standardise: true,
            ..options
        };
        let s = Logistic::fit(names(2), &x, &y, standardised).unwrap();
        for probe in [[0.0, 0.0], [1.0, -1.0], [-1.5, 1.5]] {
            assert!((m.probability(&probe) - s.probability(&probe)).abs() < 1e-3);
        }
        assert!(m.probability(&[1.0, 0.0]) > m.probability(&[0.0, 0.0]));
        m.check().unwrap();
    }

    #[test]
    fn separable_data_needs_the_penalty_and_bad_input_is_an_error() {
        let x = vec![vec![0.0], vec![1.0]];
        let y = [false, true];
        // The penalty keeps the weights finite on separable data.
        let m = Logistic::fit(names(1), &x, &y, LogisticOptions::default()).unwrap();
        assert!(m.weights[0] > 0.0 && m.weights[0].is_finite());
        assert!(Logistic::fit(names(1), &[], &[], LogisticOptions::default()).is_err());
        assert!(Logistic::fit(names(2), &x, &y, LogisticOptions::default()).is_err());
        let nan = vec![vec![f64::NAN], vec![1.0]];
        assert!(Logistic::fit(names(1), &nan, &y, LogisticOptions::default()).is_err());
        // A constant feature gets scale 1 and weight 0.
        let c = Logistic::fit(
            names(2),
            &[vec![0.0, 3.0], vec![1.0, 3.0]],
            &y,
            LogisticOptions::default(),
        )
        .unwrap();
        assert_eq!(c.scale[1], 1.0);
        assert!(c.weights[1].abs() < 1e-12);
        let mut bad = c.clone();
        bad.scale[0] = 0.0;
        assert!(bad.check().is_err());
        bad.weights.pop();
        assert!(bad.check().is_err());
    }
}
