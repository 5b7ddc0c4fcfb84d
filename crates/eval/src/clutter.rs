//! How sure a pose on an instance the segmentation network chose among several is.
//!
//! In clutter most wrong poses are good fits of *another* object of the model's size. No one
//! number of the verification tells them from right ones; several together do better
//! (`docs/decisions.md`, "A confidence in clutter from several numbers").
//!
//! - [`ClutterFeatures`]: the numbers of one registration that the confidence may weigh, read
//!   from `incontext`'s registration (or from a line of `incontext eval --candidates`'
//!   `candidates.jsonl`, which holds the same fields); [`ClutterFeatures::value`] turns a
//!   feature's name into its number.
//! - [`ClutterConfidence`]: a [`Logistic`] model over named features, then an isotonic
//!   [`Calibration`] of its output: the probability that the pose is right (ADD-S below 0.1 of
//!   the diameter of a true instance of the object). `models/verify-calibration-clutter.json`,
//!   fitted by `cargo xtask fit-clutter-calibration`.
//!
//! Scores and fractions are in [0, 1]; the depth-based numbers are computed in the pipeline's
//! normalised units, so none of them carries a unit.

use serde::{Deserialize, Serialize};

use crate::{Calibration, logistic::Logistic};

/// The render-and-compare numbers of the returned pose in its instance's crop (as
/// `incontext`'s `verify::Score`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CropScore {
    pub score: f64,
    pub coverage: f64,
    pub agreement: f64,
    pub visible_agreement: f64,
    pub misfit: f64,
    pub violation: f64,
}

/// The model's whole projection at the pose against the depth map (as `incontext`'s
/// `verify::WholeView`; fractions of its visible rendered pixels).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WholeViewFractions {
    pub agreement: f64,
    pub in_front: f64,
    pub missing: f64,
}

/// The instance the pose was registered on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct InstanceNumbers {
    /// The instance's visible extent over the model's diameter.
    pub size_ratio: f64,
    /// Distance of its spreads to the model's views (`None`: not defined).
    pub shape_distance: Option<f64>,
    /// Cut off by the image border.
    pub truncated: bool,
    /// A piece cut from a heap, not one of the network's instances.
    pub cut: bool,
}

/// The segmentation's numbers of the instance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SegmentationNumbers {
    /// Pixels of the instance's mask (at the depth map's resolution).
    pub pixels: usize,
    /// The network's mean score over them (`None` when it gave none).
    pub score: Option<f64>,
}

/// The numbers of one verified registration on a network-chosen instance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ClutterFeatures {
    /// The render-and-compare score capped by four times its margin over the best
    /// non-equivalent pose (`incontext::evidence`).
    pub evidence: f64,
    /// The best score of a verified pose not equivalent to the returned one (0 when none).
    pub rival_score: f64,
    /// Observed object voxels the pose was estimated from.
    pub object_voxels: usize,
    pub verification: CropScore,
    /// `None` when no whole view was computed: the crop's numbers stand in.
    pub whole_view: Option<WholeViewFractions>,
    pub instance: InstanceNumbers,
    pub segmentation: SegmentationNumbers,
}

/// Every feature name [`ClutterFeatures::value`] knows.
pub const FEATURE_NAMES: [&str; 19] = [
    "evidence_x_agreement",
    "evidence",
    "rival_score",
    "score",
    "coverage",
    "agreement",
    "visible_agreement",
    "misfit",
    "violation",
    "whole_agreement",
    "whole_in_front",
    "whole_missing",
    "ln_voxels",
    "cut",
    "size_misfit",
    "shape_distance",
    "truncated",
    "ln_pixels",
    "segmentation_score",
];

/// The shape distance a feature counts at most (and for an undefined one); `incontext`'s
/// instance ranking caps it here too (`RANK_MAX_SHAPE_DISTANCE`).
pub const MAX_SHAPE_DISTANCE: f64 = 3.0;

/// The size ratio an instance of the target typically has (its visible extent over the
/// diameter), from which `size_misfit` counts; `incontext`'s instance ranking counts from it
/// too (`TYPICAL_SIZE_RATIO`).
pub const TYPICAL_SIZE_RATIO: f64 = 0.8;

impl ClutterFeatures {
    /// The number of the feature `name` (one of [`FEATURE_NAMES`]); `None` for another name.
    /// `evidence_x_agreement` is the evidence times the crop agreement clamped to [0, 1];
    /// `ln_voxels` and `ln_pixels` are natural logarithms of counts (at least 1);
    /// `size_misfit` is |ln(size ratio / 0.8)|; `shape_distance` is capped at 3; `cut` and
    /// `truncated` are 0 or 1; `segmentation_score` is 0 when there is none.
    pub fn value(&self, name: &str) -> Option<f64> {
        let v = &self.verification;
        let whole = self.whole_view.unwrap_or(WholeViewFractions {
            agreement: v.agreement,
            in_front: v.violation,
            missing: 0.0,
        });
        let i = &self.instance;
        Some(match name {
            "evidence_x_agreement" => (self.evidence * v.agreement).clamp(0.0, 1.0),
            "evidence" => self.evidence,
            "rival_score" => self.rival_score,
            "score" => v.score,
            "coverage" => v.coverage,
            "agreement" => v.agreement,
            "visible_agreement" => v.visible_agreement,
            "misfit" => v.misfit,
            "violation" => v.violation,
            "whole_agreement" => whole.agreement,
            "whole_in_front" => whole.in_front,
            "whole_missing" => whole.missing,
            "ln_voxels" => (self.object_voxels.max(1) as f64).ln(),
            "cut" => f64::from(u8::from(i.cut)),
            "size_misfit" => (i.size_ratio.max(1e-6) / TYPICAL_SIZE_RATIO).ln().abs(),
            "shape_distance" => i
                .shape_distance
                .filter(|d| d.is_finite())
                .map_or(MAX_SHAPE_DISTANCE, |d| d.min(MAX_SHAPE_DISTANCE)),
            "truncated" => f64::from(u8::from(i.truncated)),
            "ln_pixels" => (self.segmentation.pixels.max(1) as f64).ln(),
            "segmentation_score" => self.segmentation.score.unwrap_or(0.0),
            _ => return None,
        })
    }

    /// The numbers of `names`, in order; an error names the first unknown feature.
    pub fn values(&self, names: &[String]) -> Result<Vec<f64>, String> {
        names
            .iter()
            .map(|n| {
                self.value(n).ok_or_else(|| {
                    format!(
                        "unknown feature {n:?} (known: {})",
                        FEATURE_NAMES.join(", ")
                    )
                })
            })
            .collect()
    }
}

/// The confidence of a pose on a network-chosen instance in clutter: the isotonic
/// `calibration` of the logistic `evidence_model`'s output.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClutterConfidence {
    pub evidence_model: Logistic,
    pub calibration: Calibration,
}

impl ClutterConfidence {
    /// From the JSON of `models/verify-calibration-clutter.json` (`{"evidence_model": {…},
    /// "knots": [[s, p], …], …}`); an error says what is wrong (an unknown feature, a
    /// malformed model or calibration).
    pub fn from_json(text: &str) -> Result<ClutterConfidence, String> {
        #[derive(Deserialize)]
        struct File {
            evidence_model: Logistic,
            knots: Vec<(f64, f64)>,
        }
        let file: File = serde_json::from_str(text).map_err(|e| e.to_string())?;
        file.evidence_model.check()?;
        ClutterFeatures::default().values(&file.evidence_model.features)?;
        Ok(ClutterConfidence {
            evidence_model: file.evidence_model,
            calibration: Calibration::new(file.knots)?,
        })
    }

    /// The model's output for `features`, in (0, 1): what the calibration maps.
    pub fn evidence(&self, features: &ClutterFeatures) -> f64 {
        // `from_json` checked every name, so `values` cannot fail here; a model built by
        // hand with an unknown name gets no evidence.
        features
            .values(&self.evidence_model.features)
            .map_or(0.0, |x| self.evidence_model.probability(&x))
    }

    /// The probability that the pose is right.
    pub fn apply(&self, features: &ClutterFeatures) -> f64 {
        self.calibration.apply(self.evidence(features))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_named_feature_has_a_value_and_missing_parts_fall_back() {
        let f = ClutterFeatures {
            evidence: 0.8,
            rival_score: 0.3,
            object_voxels: 100,
            verification: CropScore {
                score: 0.9,
                coverage: 0.95,
                agreement: 0.5,
                visible_agreement: 0.7,
                misfit: 0.2,
                violation: 0.01,
            },
            whole_view: None,
            instance: InstanceNumbers {
                size_ratio: 0.8,
                shape_distance: Some(f64::INFINITY),
                truncated: true,
                cut: false,
            },
            segmentation: SegmentationNumbers {
                pixels: 1,
                score: None,
            },
        };
        for n in FEATURE_NAMES {
            assert!(f.value(n).is_some_and(f64::is_finite), "{n}");
        }
        assert!((f.value("evidence_x_agreement").unwrap() - 0.4).abs() < 1e-12);
        // No whole view: the crop's agreement and violation stand in.
        assert_eq!(f.value("whole_agreement"), Some(0.5));
        assert_eq!(f.value("whole_in_front"), Some(0.01));
        assert_eq!(f.value("shape_distance"), Some(MAX_SHAPE_DISTANCE));
        assert_eq!(f.value("size_misfit"), Some(0.0));
        assert_eq!(f.value("ln_pixels"), Some(0.0));
        assert_eq!(f.value("truncated"), Some(1.0));
        assert!((f.value("ln_voxels").unwrap() - 100f64.ln()).abs() < 1e-12);
        let e = f.values(&["score".into(), "colour".into()]).unwrap_err();
        assert!(e.contains("colour"), "{e}");
    }

    #[test]
    fn a_candidates_line_reads_as_features_and_a_bad_model_file_is_an_error() {
        let line = r#"{"right":true,"evidence":0.9,"rival_score":0.1,"object_voxels":50,
            "verification":{"score":0.9,"coverage":0.9,"agreement":0.8,"visible_agreement":0.9,"misfit":0.3,"violation":0.0},
            "whole_view":{"agreement":0.7,"in_front":0.02,"missing":0.1,"rendered_pixels":10,"visible_pixels":9},
            "instance":{"size_ratio":0.5,"shape_distance":null,"truncated":false,"cut":true,"rank":3},
            "segmentation":{"pixels":300,"score":0.6,"source":"network"}}"#;
        let f: ClutterFeatures = serde_json::from_str(line).unwrap();
        assert_eq!(f.value("whole_missing"), Some(0.1));
        assert_eq!(f.value("cut"), Some(1.0));
        let good = r#"{"evidence_model":{"features":["evidence","cut"],"mean":[0.5,0.0],
            "scale":[0.2,1.0],"weights":[2.0,-1.0],"bias":0.0},"knots":[[0.0,0.0],[1.0,1.0]]}"#;
        let c = ClutterConfidence::from_json(good).unwrap();
        // σ(2·(0.9 − 0.5)/0.2 − 1) = σ(3), mapped by the identity calibration.
        assert!((c.apply(&f) - 1.0 / (1.0 + (-3.0f64).exp())).abs() < 1e-12);
        let unknown = good.replace("\"cut\"]", "\"colour\"]");
        assert!(
            ClutterConfidence::from_json(&unknown)
                .unwrap_err()
                .contains("colour")
        );
        let short = good.replace("[2.0,-1.0]", "[2.0]");
        assert!(ClutterConfidence::from_json(&short).is_err());
    }
}
