//! Reports: markdown tables and JSON.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::{EvalError, Summary};

/// One method's named results: its summary and the raw errors (for curves).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MethodResult {
    pub method: String,
    pub summary: Summary,
    /// Per-sample rotation errors in degrees (failures as `inf`).
    pub rotation_errors_deg: Vec<f64>,
    /// Per-sample squared translation errors (failures as `inf`).
    pub translation_sq_errors: Vec<f64>,
    /// Median seconds per registration, when timed.
    pub seconds_median: Option<f64>,
}

/// The markdown table of the paper's metrics, one row per method. States the mAP formula.
pub fn markdown_table(results: &[MethodResult]) -> String {
    let mut s = String::from(
        "| method | n | fail | rot. median (°) | acc@5° | acc@10° | acc@15° | mAP@15° | ‖Δt‖² median | acc@1e-3 | acc@5e-3 | acc@1e-2 | mAP@1e-2 | s/reg. |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in results {
        let m = &r.summary;
        let acc = |v: &[(f64, f64)]| {
            v.iter()
                .map(|(_, a)| format!("{a:.3}"))
                .collect::<Vec<_>>()
                .join(" | ")
        };
        s.push_str(&format!(
            "| {} | {} | {} | {:.2} | {} | {:.3} | {:.2e} | {} | {:.3} | {} |\n",
            r.method,
            m.count,
            m.failures,
            m.rotation_median_deg,
            acc(&m.rotation_accuracy),
            m.rotation_map_15,
            m.translation_sq_median,
            acc(&m.translation_accuracy),
            m.translation_map_1e2,
            r.seconds_median.map_or("–".into(), |t| format!("{t:.4}")),
        ));
    }
    s.push_str(
        "\nmAP in the convention of Yi et al. 2018: mAP(τ) = mean of the accuracies at the thresholds \
         step, 2·step, …, τ (rotation: step 5°; squared translation error: step 1e-3).\n",
    );
    s
}

/// Writes the results as pretty JSON, atomically.
pub fn write_json(path: &Path, results: &[MethodResult]) -> Result<(), EvalError> {
    let text = serde_json::to_string_pretty(results).map_err(|e| EvalError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    ic_geometry::io::write_atomic_with(
        path,
        |w| {
            std::io::Write::write_all(w, text.as_bytes()).map_err(|e| EvalError::Io {
                path: path.to_path_buf(),
                source: e,
            })
        },
        |e| EvalError::Io {
            path: path.to_path_buf(),
            source: e,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PoseErrors;

    #[test]
    fn table_has_one_row_per_method_and_states_the_formula() {
        let e = PoseErrors {
            rotation_deg: 3.0,
            translation_sq: 4e-4,
            translation: 0.02,
            add: None,
            add_s: None,
        };
        let r = MethodResult {
            method: "ours-ot".into(),
            summary: Summary::new(&[Some(e), None], None),
            rotation_errors_deg: vec![3.0, f64::INFINITY],
            translation_sq_errors: vec![4e-4, f64::INFINITY],
            seconds_median: Some(0.05),
        };
        let t = markdown_table(std::slice::from_ref(&r));
        assert!(t.contains("| ours-ot | 2 | 1 |"), "{t}");
        assert!(t.contains("Yi et al. 2018"));
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("r.json");
        write_json(&p, &[r]).unwrap();
        let back: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        assert_eq!(back[0]["method"], "ours-ot");
    }
}
