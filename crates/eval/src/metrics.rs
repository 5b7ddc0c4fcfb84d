//! Aggregates over many samples: accuracy at thresholds, mAP, area under the curve, medians.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::PoseErrors;

/// The paper's rotation thresholds (degrees).
pub const ROTATION_THRESHOLDS_DEG: [f64; 3] = [5.0, 10.0, 15.0];
/// The paper's translation thresholds, on the *squared* L2 error (normalised units²).
pub const TRANSLATION_SQ_THRESHOLDS: [f64; 3] = [1e-3, 5e-3, 1e-2];

/// Fraction of `errors` that are ≤ `threshold` (NaN counts as a failure); 0 for no errors.
pub fn accuracy(errors: &[f64], threshold: f64) -> f64 {
    if errors.is_empty() {
        return 0.0;
    }
    errors.iter().filter(|&&e| e <= threshold).count() as f64 / errors.len() as f64
}

/// [`accuracy`] at each threshold.
pub fn accuracy_curve(errors: &[f64], thresholds: &[f64]) -> Vec<f64> {
    thresholds.iter().map(|&t| accuracy(errors, t)).collect()
}

/// mAP in the convention of Yi et al. 2018 ("Learning to find good correspondences"), as the
/// paper uses it: the mean of the accuracies at the thresholds `step, 2·step, …` up to `tau`:
///
/// mAP(τ) = (1/K) Σ_{k=1..K} acc(k·step),  K = ⌊τ/step⌋.
///
/// For rotations `step` = 5° (mAP@15° = mean of acc@5°, @10°, @15°); for the squared
/// translation error we use `step` = 1e-3 (mAP@1e-2 = mean of the accuracies at 1e-3 … 1e-2).
pub fn map_yi2018(errors: &[f64], step: f64, tau: f64) -> f64 {
    let k = (tau / step + 1e-9).floor() as usize;
    if k == 0 {
        return 0.0;
    }
    (1..=k)
        .map(|i| accuracy(errors, i as f64 * step))
        .sum::<f64>()
        / k as f64
}

/// Area under the accuracy-vs-threshold curve on [0, max], normalised to [0, 1]
/// (trapezoids on `samples` evenly spaced thresholds).
pub fn auc(errors: &[f64], max: f64, samples: usize) -> f64 {
    let n = samples.max(2);
    let ys: Vec<f64> = (0..n)
        .map(|i| accuracy(errors, max * i as f64 / (n - 1) as f64))
        .collect();
    ys.windows(2).map(|w| 0.5 * (w[0] + w[1])).sum::<f64>() / (n - 1) as f64
}

/// The median (mean of the two middle values for an even count); NaN for no values.
pub fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let m = v.len() / 2;
    if v.len() % 2 == 1 {
        v[m]
    } else {
        0.5 * (v[m - 1] + v[m])
    }
}

/// One method's results on a test set.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub count: usize,
    /// Estimates that failed (counted as infinitely wrong in every accuracy).
    pub failures: usize,
    pub rotation_median_deg: f64,
    pub translation_median: f64,
    pub translation_sq_median: f64,
    /// (threshold°, accuracy) at the paper's thresholds.
    pub rotation_accuracy: Vec<(f64, f64)>,
    /// (threshold, accuracy) on the squared translation error.
    pub translation_accuracy: Vec<(f64, f64)>,
    /// mAP (Yi et al. 2018) at 15°, step 5°.
    pub rotation_map_15: f64,
    /// mAP at 1e-2 on the squared translation error, step 1e-3.
    pub translation_map_1e2: f64,
    /// ADD-S below 0.1·diameter, when ADD-S was computed and a diameter given.
    pub add_s_accuracy: Option<f64>,
}

impl Summary {
    /// Summarises per-sample errors; `None` entries are failures. `diameter` enables the
    /// ADD-S 0.1·d criterion.
    pub fn new(errors: &[Option<PoseErrors>], diameter: Option<f64>) -> Summary {
        let failures = errors.iter().filter(|e| e.is_none()).count();
        let pick = |f: &dyn Fn(&PoseErrors) -> f64| -> Vec<f64> {
            errors
                .iter()
                .map(|e| e.as_ref().map_or(f64::INFINITY, f))
                .collect()
        };
        let rot = pick(&|e| e.rotation_deg);
        let tsq = pick(&|e| e.translation_sq);
        let t = pick(&|e| e.translation);
        let add_s: Vec<f64> = errors
            .iter()
            .map(|e| e.and_then(|e| e.add_s).unwrap_or(f64::INFINITY))
            .collect();
        let has_add_s = errors.iter().flatten().any(|e| e.add_s.is_some());
        Summary {
            count: errors.len(),
            failures,
            rotation_median_deg: median(&rot),
            translation_median: median(&t),
            translation_sq_median: median(&tsq),
            rotation_accuracy: ROTATION_THRESHOLDS_DEG
                .iter()
                .map(|&th| (th, accuracy(&rot, th)))
                .collect(),
            translation_accuracy: TRANSLATION_SQ_THRESHOLDS
                .iter()
                .map(|&th| (th, accuracy(&tsq, th)))
                .collect(),
            rotation_map_15: map_yi2018(&rot, 5.0, 15.0),
            translation_map_1e2: map_yi2018(&tsq, 1e-3, 1e-2),
            add_s_accuracy: match (has_add_s, diameter) {
                (true, Some(d)) => Some(accuracy(&add_s, 0.1 * d)),
                _ => None,
            },
        }
    }
}

/// [`Summary`] per object id, plus the overall one under the key `"all"`.
pub fn per_object(
    samples: &[(String, Option<PoseErrors>)],
    diameter: Option<f64>,
) -> BTreeMap<String, Summary> {
    let mut groups: BTreeMap<String, Vec<Option<PoseErrors>>> = BTreeMap::new();
    for (id, e) in samples {
        groups.entry(id.clone()).or_default().push(*e);
    }
    let mut out: BTreeMap<String, Summary> = groups
        .into_iter()
        .map(|(k, v)| (k, Summary::new(&v, diameter)))
        .collect();
    let all: Vec<Option<PoseErrors>> = samples.iter().map(|s| s.1).collect();
    out.insert("all".into(), Summary::new(&all, diameter));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accuracy_map_and_auc_on_known_values() {
        let e = [1.0, 4.0, 6.0, 12.0, 30.0, f64::NAN];
        assert_eq!(accuracy(&e, 5.0), 2.0 / 6.0);
        assert_eq!(
            accuracy_curve(&e, &[5.0, 10.0, 15.0]),
            vec![2.0 / 6.0, 3.0 / 6.0, 4.0 / 6.0]
        );
        // mAP@15° = mean(acc@5, acc@10, acc@15) = (2 + 3 + 4) / 18.
        assert!((map_yi2018(&e, 5.0, 15.0) - 9.0 / 18.0).abs() < 1e-12);
        assert!((map_yi2018(&e, 5.0, 5.0) - 2.0 / 6.0).abs() < 1e-12);
        assert_eq!(map_yi2018(&e, 5.0, 4.0), 0.0);
        // All-perfect errors: the accuracy curve is 1 everywhere.
        assert!((auc(&[0.0; 4], 10.0, 101) - 1.0).abs() < 1e-12);
        // Uniform errors on [0, 10]: the curve is the identity, area 1/2.
        let uniform: Vec<f64> = (0..1000).map(|i| i as f64 / 100.0).collect();
        assert!((auc(&uniform, 10.0, 1001) - 0.5).abs() < 2e-3);
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(&[]).is_nan());
    }

    /// mAP and AUC on a small list worked out by hand: errors 2°, 7°, 12°, 40° and a failure.
    #[test]
    fn map_and_auc_on_a_small_hand_computed_list() {
        let e = [2.0, 7.0, 12.0, 40.0, f64::INFINITY];
        // acc@5 = 1/5, acc@10 = 2/5, acc@15 = 3/5 → mAP@15° = (1 + 2 + 3)/15 = 0.4.
        assert_eq!(accuracy_curve(&e, &[5.0, 10.0, 15.0]), vec![0.2, 0.4, 0.6]);
        assert!((map_yi2018(&e, 5.0, 15.0) - 0.4).abs() < 1e-12);
        // mAP@10° = (1/5 + 2/5)/2 = 0.3; mAP@30° adds acc@20, @25, @30 = 3/5 each → 0.5.
        assert!((map_yi2018(&e, 5.0, 10.0) - 0.3).abs() < 1e-12);
        assert!((map_yi2018(&e, 5.0, 30.0) - 0.5).abs() < 1e-12);
        // AUC on [0, 15]: the step curve is 0 on [0, 2), 1/5 on [2, 7), 2/5 on [7, 12), 3/5 on
        // [12, 15] → (0·2 + 0.2·5 + 0.4·5 + 0.6·3)/15 = 4.8/15 = 0.32.
        assert!((auc(&e, 15.0, 1501) - 0.32).abs() < 1e-3);
        // On [0, 50] the 40° error counts for the last 10°: (4.8 + 0.6·25 + 0.8·10)/50 = 0.556.
        assert!((auc(&e, 50.0, 5001) - 0.556).abs() < 1e-3);
        // Squared translation errors with the 1e-3 step: 0.5e-3, 1.5e-3, 8.5e-3, 0.5 →
        // acc at 1e-3 … 1e-2 = 1, 2, 2, 2, 2, 2, 2, 2, 3, 3 quarters → mAP = 21/40.
        let t = [0.5e-3, 1.5e-3, 8.5e-3, 0.5];
        assert!((map_yi2018(&t, 1e-3, 1e-2) - 21.0 / 40.0).abs() < 1e-12);
        // Thresholds are inclusive: an error exactly at 5° counts at 5°.
        assert_eq!(accuracy(&[5.0], 5.0), 1.0);
        assert_eq!(accuracy(&[], 5.0), 0.0);
    }

    #[test]
    fn summary_counts_failures_as_wrong_and_groups_per_object() {
        let ok = PoseErrors {
            rotation_deg: 3.0,
            translation_sq: 4e-4,
            translation: 0.02,
            add: None,
            add_s: Some(0.01),
        };
        let bad = PoseErrors {
            rotation_deg: 40.0,
            translation_sq: 0.5,
            translation: 0.7,
            add: None,
            add_s: Some(0.5),
        };
        let samples = vec![
            ("a".to_string(), Some(ok)),
            ("a".to_string(), None),
            ("b".to_string(), Some(bad)),
            ("b".to_string(), Some(ok)),
        ];
        let s = per_object(&samples, Some(1.0));
        let all = &s["all"];
        assert_eq!((all.count, all.failures), (4, 1));
        assert_eq!(all.rotation_accuracy[0], (5.0, 0.5));
        assert_eq!(all.translation_accuracy[0], (1e-3, 0.5));
        assert_eq!(all.add_s_accuracy, Some(0.5));
        assert_eq!(s["a"].rotation_accuracy[2], (15.0, 0.5));
        assert_eq!(s["b"].rotation_median_deg, 21.5);
    }
}
