//! Stage 4b of `cargo xtask bench`: the accuracy/speed curve of our one-shot pose over the
//! point counts (M model, N observed points) and the neighbours k of the DGCNN's k-NN graph,
//! with the shipped softmax weights (trained at 384 × 288, k = 16): how far fewer points or
//! neighbours buy speed before accuracy goes.
//!
//! For each (M, N) in [`CURVE_SIZES`] and each k in [`CURVE_K`]: the rotation accuracy of
//! `PoseEstimator::estimate` without ICP on the first `cases` object-alone cases (the blob
//! paper protocol, normalised units, camera frame), each case's source and target resampled to
//! M and N points with [`pair_rng`] — the same draws as the speed table — and its time, one
//! warm-up then `repeats` runs on each of the first `pairs` of them, the median of the pairs'
//! medians (as the speed table).

use std::path::Path;

use anyhow::{Context, Result};
use ic_data::export::CaseFolder;
use ic_geometry::Pose;
use ic_geometry::glam::Vec3;
use ic_pose::{Head, Refine};
use serde::Serialize;

use crate::bench::cases::CaseSet;
use crate::bench::speed::{
    Timed, estimator, read_points, resample_pair, size_label, time_estimates,
};

/// (model, observed) point counts of the curve: from a third of the operating point up to the
/// paper's inference size.
pub const CURVE_SIZES: [(usize, usize); 7] = [
    (128, 96),
    (192, 144),
    (256, 192),
    (320, 240),
    (384, 288),
    (512, 384),
    (1024, 768),
];

/// Neighbours per point of the k-NN graph (the shipped weights were trained with 16).
pub const CURVE_K: [usize; 4] = [8, 12, 16, 24];

/// One point of the curve.
#[derive(Clone, Debug, Serialize)]
pub struct CurvePoint {
    pub points: usize,
    pub observed_points: usize,
    pub k: usize,
    /// Cases whose rotation error is below 15° (a failed recovery counts as 180°).
    pub rotation_acc_15: f64,
    pub rotation_acc_5: f64,
    pub rotation_median_deg: f64,
    pub failures: usize,
    pub time: Timed,
}

/// The whole curve.
#[derive(Clone, Debug, Serialize)]
pub struct SpeedCurve {
    pub head: String,
    /// The k the weights were trained with.
    pub trained_k: usize,
    pub cases: usize,
    pub pairs: usize,
    pub repeats: usize,
    pub points: Vec<CurvePoint>,
    pub note: Option<String>,
}

impl SpeedCurve {
    pub fn at(&self, (m, n): (usize, usize), k: usize) -> Option<&CurvePoint> {
        self.points
            .iter()
            .find(|p| p.points == m && p.observed_points == n && p.k == k)
    }

    /// The values of k measured, ascending.
    pub fn ks(&self) -> Vec<usize> {
        let mut ks: Vec<usize> = self.points.iter().map(|p| p.k).collect();
        ks.sort_unstable();
        ks.dedup();
        ks
    }

    /// The (m, n) sizes measured, in the order measured.
    pub fn sizes(&self) -> Vec<(usize, usize)> {
        let mut sizes: Vec<(usize, usize)> = Vec::new();
        for p in &self.points {
            if !sizes.contains(&(p.points, p.observed_points)) {
                sizes.push((p.points, p.observed_points));
            }
        }
        sizes
    }
}

/// One case: model points (model frame), observed points (camera frame), the true pose.
struct Case {
    source: Vec<Vec3>,
    target: Vec<Vec3>,
    truth: Pose,
}

#[allow(clippy::too_many_arguments)]
pub fn measure(
    root: &Path,
    noback: &CaseSet,
    seed: u64,
    cases: usize,
    pairs: usize,
    repeats: usize,
    sizes: &[(usize, usize)],
    ks: &[usize],
) -> Result<SpeedCurve> {
    let cases = cases.clamp(1, noback.count.max(1) as usize);
    let pairs = pairs.clamp(1, cases);
    let folder = CaseFolder::new(&noback.dir);
    let data = (0..cases)
        .map(|i| {
            let c = folder.child(i as u64);
            Ok(Case {
                source: read_points(&c.source())?,
                target: read_points(&c.target())?,
                truth: c
                    .read_gt()
                    .with_context(|| format!("reading {}", c.gt().display()))?,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    let (mut e, note) = estimator(root, Head::Softmax, seed)?;
    let trained_k = e.config().net.k;
    e.recovery.refine = Refine::None;
    let bar = crate::bench::common::progress_bar((sizes.len() * ks.len()) as u64, "curve");
    let mut points = Vec::new();
    for &k in ks {
        e = e.with_neighbours(k)?;
        for &(m, n) in sizes {
            bar.set_message(format!("k={k} n={}", size_label((m, n))));
            let inputs: Vec<(Vec<Vec3>, Vec<Vec3>)> = data
                .iter()
                .enumerate()
                .map(|(i, c)| resample_pair((&c.source, &c.target), (m, n), seed, i))
                .collect();
            let mut errors = Vec::with_capacity(cases);
            let mut failures = 0;
            for ((x, y), c) in inputs.iter().zip(&data) {
                match e.estimate(x, y) {
                    Ok(p) => errors.push(ic_eval::rotation_error_deg(&p.pose, &c.truth)),
                    Err(err) => {
                        tracing::debug!("curve k={k} {m}x{n}: {err}");
                        failures += 1;
                        errors.push(180.0);
                    }
                }
            }
            let label = format!("ours-softmax k={k} {}", size_label((m, n)));
            // Failures are counted above; their time counts here.
            let (time, _) = time_estimates(&e, &label, repeats, &inputs[..pairs]);
            let point = CurvePoint {
                points: m,
                observed_points: n,
                k,
                rotation_acc_15: ic_eval::accuracy(&errors, 15.0),
                rotation_acc_5: ic_eval::accuracy(&errors, 5.0),
                rotation_median_deg: ic_eval::median(&errors),
                failures,
                time,
            };
            tracing::info!(
                k,
                m,
                n,
                acc15 = point.rotation_acc_15,
                median = ?point.time.median_seconds,
                "accuracy/speed curve"
            );
            points.push(point);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    Ok(SpeedCurve {
        head: "softmax".into(),
        trained_k,
        cases,
        pairs,
        repeats,
        points,
        note,
    })
}
