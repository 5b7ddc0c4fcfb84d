//! Confidence calibration: how often a pose with a given score is right.
//!
//! - [`Calibration`]: a monotone map from a raw score in [0, 1] (e.g. the render-and-compare
//!   score of `incontext`'s verified pipeline) to the probability that the pose is right,
//!   fitted by isotonic regression (pool adjacent violators) on validation views and applied
//!   by linear interpolation between its knots. Serialises as JSON (`{"knots": [[s, p], …]}`).
//! - [`reliability_bins`]: the reliability diagram of (confidence, right) samples — per
//!   confidence bin, the mean confidence against the fraction right — and
//!   [`expected_calibration_error`]; [`plot_reliability`] draws it (PNG or SVG).
//!
//! "Right" is whatever the caller decided (in this project: ADD-S below 0.1 of the object's
//! diameter).

use std::path::Path;

use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::EvalError;

/// The calibrated confidence (the probability that the pose is right) from which
/// `incontext`'s verified pose is `ok`: its `VERIFIED_OK`, and what `cargo xtask
/// fit-clutter-calibration` counts as `ok` (`docs/decisions.md`).
pub const VERIFIED_OK: f64 = 0.9;

/// The raw render-and-compare score below which `incontext`'s verified pose counts as not
/// found (the model at its best pose explains almost none of the object's depth): its
/// `VERIFIED_FOUND`, and what `cargo xtask fit-clutter-calibration` replays.
pub const VERIFIED_FOUND: f64 = 0.05;

/// A monotone non-decreasing map from a score to a probability, by linear interpolation
/// between `knots` (score, probability), constant beyond the first and last knot.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Sorted by score, probabilities non-decreasing, all in [0, 1].
    pub knots: Vec<(f64, f64)>,
}

impl Calibration {
    /// Isotonic regression of `right` on `score` over the samples (pool adjacent violators,
    /// equal neighbours pooled too): each pooled block of equal fitted probability becomes
    /// knots at its lowest and highest score, so the map is flat across a block and linear
    /// between blocks. Errors on no sample or a non-finite score.
    pub fn fit(samples: &[(f64, bool)]) -> Result<Calibration, String> {
        if samples.is_empty() {
            return Err("no samples to fit a calibration on".into());
        }
        if let Some((s, _)) = samples.iter().find(|(s, _)| !s.is_finite()) {
            return Err(format!("a score is not finite ({s})"));
        }
        let mut sorted = samples.to_vec();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        // Blocks: (right, count, lowest score, highest score).
        let mut blocks: Vec<(f64, f64, f64, f64)> = Vec::new();
        for (s, r) in sorted {
            blocks.push((r as u8 as f64, 1.0, s, s));
            while blocks.len() >= 2 {
                let n = blocks.len();
                let (a, b) = (blocks[n - 2], blocks[n - 1]);
                if a.0 / a.1 < b.0 / b.1 {
                    break;
                }
                blocks.truncate(n - 2);
                blocks.push((a.0 + b.0, a.1 + b.1, a.2, b.3));
            }
        }
        let mut knots = Vec::with_capacity(2 * blocks.len());
        for &(r, n, lo, hi) in &blocks {
            knots.push((lo, r / n));
            if hi > lo {
                knots.push((hi, r / n));
            }
        }
        Calibration::new(knots)
    }

    /// Checks and wraps knots (sorted scores, non-decreasing probabilities in [0, 1]).
    pub fn new(knots: Vec<(f64, f64)>) -> Result<Calibration, String> {
        if knots.is_empty() {
            return Err("a calibration needs at least one knot".into());
        }
        for (i, &(s, p)) in knots.iter().enumerate() {
            if !s.is_finite() || !(0.0..=1.0).contains(&p) {
                return Err(format!(
                    "knot {i} ({s}, {p}) is not a finite score with p in [0, 1]"
                ));
            }
            if i > 0 && (s < knots[i - 1].0 || p < knots[i - 1].1) {
                return Err(format!(
                    "knot {i} ({s}, {p}) is out of order: scores must be sorted and probabilities non-decreasing"
                ));
            }
        }
        Ok(Calibration { knots })
    }

    /// The calibrated probability of `score` (NaN maps to the lowest knot's probability).
    pub fn apply(&self, score: f64) -> f64 {
        let k = &self.knots;
        let (first, last) = (k[0], k[k.len() - 1]);
        if score.is_nan() || score <= first.0 {
            return first.1;
        }
        if score >= last.0 {
            return last.1;
        }
        let i = k.partition_point(|&(s, _)| s <= score);
        let ((s0, p0), (s1, p1)) = (k[i - 1], k[i]);
        if s1 <= s0 {
            return p1;
        }
        p0 + (p1 - p0) * (score - s0) / (s1 - s0)
    }
}

/// One bin of a reliability diagram.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    /// The bin's confidence range [lo, hi) (the last bin includes 1).
    pub lo: f64,
    pub hi: f64,
    pub count: usize,
    /// Mean confidence and fraction right of the samples in the bin (NaN when empty).
    pub mean_confidence: f64,
    pub fraction_right: f64,
}

/// `bins` equal-width confidence bins over [0, 1] (confidences outside are clamped).
pub fn reliability_bins(samples: &[(f64, bool)], bins: usize) -> Vec<ReliabilityBin> {
    let bins = bins.max(1);
    let mut acc = vec![(0.0f64, 0usize, 0usize); bins];
    for &(c, right) in samples {
        let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
        let i = ((c * bins as f64) as usize).min(bins - 1);
        acc[i].0 += c;
        acc[i].1 += right as usize;
        acc[i].2 += 1;
    }
    acc.iter()
        .enumerate()
        .map(|(i, &(sum, right, n))| ReliabilityBin {
            lo: i as f64 / bins as f64,
            hi: (i + 1) as f64 / bins as f64,
            count: n,
            mean_confidence: if n > 0 { sum / n as f64 } else { f64::NAN },
            fraction_right: if n > 0 {
                right as f64 / n as f64
            } else {
                f64::NAN
            },
        })
        .collect()
}

/// Σ over bins of (count / total) · |fraction right − mean confidence|.
pub fn expected_calibration_error(bins: &[ReliabilityBin]) -> f64 {
    let total: usize = bins.iter().map(|b| b.count).sum();
    if total == 0 {
        return f64::NAN;
    }
    bins.iter()
        .filter(|b| b.count > 0)
        .map(|b| b.count as f64 / total as f64 * (b.fraction_right - b.mean_confidence).abs())
        .sum()
}

/// Draws reliability diagrams (fraction right against mean confidence per non-empty bin, one
/// line per series, markers growing with the bin's count, and the diagonal of perfect
/// calibration) to `path` (.png or .svg).
pub fn plot_reliability(
    path: &Path,
    title: &str,
    series: &[(String, Vec<ReliabilityBin>)],
) -> Result<(), EvalError> {
    crate::plot::draw_to_file!(path, (640, 560), |root| draw(root, title, series))
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    title: &str,
    series: &[(String, Vec<ReliabilityBin>)],
) -> Result<(), EvalError>
where
    DB::ErrorType: 'static,
{
    let font = crate::plot::FONT_NAME;
    let err = |e: DrawingAreaErrorKind<DB::ErrorType>| EvalError::Plot(e.to_string());
    root.fill(&WHITE).map_err(err)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (font, 20))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d(0.0..1.0, 0.0..1.0)
        .map_err(err)?;
    chart
        .configure_mesh()
        .x_desc("confidence (mean of the bin)")
        .y_desc("fraction of poses right")
        .label_style((font, 13))
        .axis_desc_style((font, 15))
        .draw()
        .map_err(err)?;
    chart
        .draw_series(LineSeries::new(
            vec![(0.0, 0.0), (1.0, 1.0)],
            BLACK.mix(0.4).stroke_width(1),
        ))
        .map_err(err)?
        .label("perfect calibration")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK.mix(0.4)));
    for (i, (name, bins)) in series.iter().enumerate() {
        let colour = Palette99::pick(i).to_rgba();
        let points: Vec<(f64, f64)> = bins
            .iter()
            .filter(|b| b.count > 0)
            .map(|b| (b.mean_confidence, b.fraction_right))
            .collect();
        crate::plot::labelled_line(&mut chart, points, colour, name)?;
        // Markers grow with the bin's count (few samples: a small dot, little weight).
        chart
            .draw_series(bins.iter().filter(|b| b.count > 0).map(|b| {
                let r = (2.0 + (b.count as f64).sqrt() / 2.0).min(12.0) as i32;
                Circle::new((b.mean_confidence, b.fraction_right), r, colour.filled())
            }))
            .map_err(err)?;
    }
    crate::plot::legend_and_present(&mut chart, &root, SeriesLabelPosition::UpperLeft)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn isotonic_fit_pools_violators_and_is_monotone() {
        // Scores 0.1..0.9; right at 0.1 (a violator), wrong at 0.2 and 0.3, right above.
        let samples = [
            (0.1, true),
            (0.2, false),
            (0.3, false),
            (0.5, true),
            (0.6, false),
            (0.7, true),
            (0.9, true),
        ];
        let c = Calibration::fit(&samples).unwrap();
        // Blocks: {0.1, 0.2, 0.3} → 1/3, {0.5, 0.6} → 1/2, {0.7, 0.9} → 1 (equal pooled).
        let third = 1.0 / 3.0;
        assert_eq!(
            c.knots,
            vec![
                (0.1, third),
                (0.3, third),
                (0.5, 0.5),
                (0.6, 0.5),
                (0.7, 1.0),
                (0.9, 1.0)
            ]
        );
        for w in c.knots.windows(2) {
            assert!(w[0].0 <= w[1].0 && w[0].1 <= w[1].1);
        }
        assert_eq!(c.apply(0.0), third);
        assert_eq!(c.apply(0.2), third);
        assert_eq!(c.apply(0.55), 0.5);
        assert!((c.apply(0.4) - (third + (0.5 - third) * 0.5)).abs() < 1e-12);
        assert_eq!(c.apply(1.0), 1.0);
        assert_eq!(c.apply(f64::NAN), third);
        assert!(Calibration::fit(&[]).is_err());
        assert!(Calibration::fit(&[(f64::NAN, true)]).is_err());
        assert!(Calibration::new(vec![(0.5, 0.9), (0.6, 0.1)]).is_err());
    }

    #[test]
    fn reliability_bins_count_and_average_per_bin() {
        let samples = [
            (0.05, false),
            (0.15, true),
            (0.95, true),
            (1.0, true),
            (0.9, false),
        ];
        let bins = reliability_bins(&samples, 10);
        assert_eq!(bins.len(), 10);
        assert_eq!(bins[0].count, 1);
        assert_eq!(bins[1].count, 1);
        assert_eq!(bins[9].count, 3);
        assert!((bins[9].fraction_right - 2.0 / 3.0).abs() < 1e-12);
        assert!(bins[5].fraction_right.is_nan());
        let ece = expected_calibration_error(&bins);
        let expect = (0.05 + (1.0 - 0.15) + 3.0 * (2.0 / 3.0 - 2.85 / 3.0f64).abs()) / 5.0;
        assert!((ece - expect).abs() < 1e-12, "{ece} vs {expect}");
    }

    #[test]
    fn reliability_plot_writes_png_and_svg() {
        let dir = tempfile::tempdir().unwrap();
        let samples: Vec<(f64, bool)> = (0..100).map(|i| (i as f64 / 100.0, i % 3 != 0)).collect();
        let series = vec![("val".to_string(), reliability_bins(&samples, 10))];
        let svg = dir.path().join("c.svg");
        plot_reliability(&svg, "calibration", &series).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("perfect calibration") && text.contains("val"));
        let png = dir.path().join("c.png");
        plot_reliability(&png, "calibration", &series).unwrap();
        assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
        assert!(plot_reliability(&dir.path().join("c.gif"), "x", &series).is_err());
    }
}
