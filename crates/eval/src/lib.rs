//! `ic_eval` — how accurate is a pose?
//!
//! - [`errors`]: per-sample errors — rotation E_rot = arccos((tr(R̂ᵀR) − 1)/2) in degrees,
//!   translation as the paper's squared L2 and as plain L2, ADD and ADD-S, BOP's MSSD and MSPD
//!   (with optional symmetries), and the object diameter.
//! - [`metrics`]: accuracy at thresholds (the paper's 5/10/15° and 1e-3/5e-3/1e-2 by default),
//!   mAP in the convention of Yi et al. 2018 (mean of the accuracies at step, 2·step, … up to
//!   τ), area under the accuracy curve, medians, per-object breakdowns.
//! - [`report`]: markdown tables and JSON; [`plot`]: accuracy-vs-threshold curves (PNG, SVG).
//! - [`calibration`]: isotonic calibration of a confidence score, reliability diagrams.
//! - [`logistic`]: logistic regression (Newton's method, L2 penalty) over named features.
//! - [`clutter`]: the numbers of a pose on an instance chosen among several, and the
//!   confidence model over them (logistic, then isotonic).
//! - [`cases`]: the scorer of exported registration cases — reads `gt.json` of case folders
//!   and any number of JSONL result files (ours and Open3D's peers write the same lines) and
//!   scores every method on every case (failures and missing lines count as 180° / ∞).
//!
//! Depends on `ic_geometry` only. Poses map model → camera, in any consistent unit.
//!
//! ```
//! use ic_eval::{PoseErrors, Summary};
//! use ic_geometry::{Pose, glam::DVec3};
//!
//! let truth = Pose::from_translation(DVec3::new(0.0, 0.0, 2.5));
//! let estimate = Pose::from_axis_angle(DVec3::Z, 4f64.to_radians(), DVec3::new(0.01, 0.0, 2.5));
//! let errors = PoseErrors::compute(&estimate, &truth, None).unwrap();
//! let summary = Summary::new(&[Some(errors), None], None);
//! assert_eq!(summary.rotation_accuracy[0], (5.0, 0.5)); // one of two within 5°, one failure
//! ```

pub mod calibration;
pub mod cases;
pub mod clutter;
pub mod errors;
pub mod instances;
pub mod logistic;
pub mod metrics;
pub mod object_scores;
pub mod plot;
pub mod report;

pub use calibration::{Calibration, ReliabilityBin, expected_calibration_error, reliability_bins};
pub use clutter::{ClutterConfidence, ClutterFeatures};
pub use errors::{
    PoseErrors, add, add_s, diameter, mspd, mssd, rotation_error_deg, translation_error,
    translation_error_sq,
};
pub use logistic::{Logistic, LogisticOptions};
pub use metrics::{Summary, accuracy, accuracy_curve, auc, map_yi2018, median, per_object};
pub use plot::{
    Curve, plot_accuracy_curves, plot_accuracy_curves_titled, plot_learning_curves, plot_xy,
};
pub use report::{MethodResult, markdown_table, write_json};

use std::path::PathBuf;

/// Errors of writing reports and plots; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("plot: {0}")]
    Plot(String),
}
