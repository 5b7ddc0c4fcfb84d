//! `results.json` of `cargo xtask bench`: the whole [`Report`], with each method's per-case
//! numbers as compact arrays; pretty-printed with plain arrays on one line, written atomically.

use std::path::{Path, PathBuf};

use anyhow::Result;
use serde_json::{Value, json};

use super::Report;
use crate::bench::common::write_atomic;

/// Writes `out/results.json`; returns its path.
pub fn write(report: &Report, out: &Path) -> Result<PathBuf> {
    let json_path = out.join("results.json");
    let mut text = String::new();
    write_json_value(&results_json(report)?, 0, &mut text);
    text.push('\n');
    write_atomic(&json_path, text.as_bytes())?;
    Ok(json_path)
}

fn round_sig(x: f64, digits: i32) -> Value {
    if !x.is_finite() {
        return Value::Null;
    }
    if x == 0.0 {
        return json!(0.0);
    }
    let scale = 10f64.powi(digits - 1 - x.abs().log10().floor() as i32);
    json!((x * scale).round() / scale)
}

/// results.json: the report, with each method's per-case numbers as compact arrays (rotation
/// error in degrees, squared translation error with null for ∞, seconds) in the order of the
/// set's `cases`, and the failures as {case: reason}.
fn results_json(report: &Report) -> Result<Value> {
    let mut v = serde_json::to_value(report)?;
    let sets: Vec<Value> = report
        .sets
        .iter()
        .map(|set| {
            let methods: Vec<Value> = set
                .scores
                .iter()
                .map(|m| {
                    let failures: serde_json::Map<String, Value> = m
                        .cases
                        .iter()
                        .filter_map(|c| match &c.outcome {
                            ic_eval::cases::CaseOutcome::Failed { error } => {
                                Some((c.case.clone(), json!(error)))
                            }
                            ic_eval::cases::CaseOutcome::Missing => {
                                Some((c.case.clone(), json!("no result line")))
                            }
                            _ => None,
                        })
                        .collect();
                    json!({
                        "method": m.method(),
                        "summary": m.result.summary,
                        "scored": m.scored,
                        "failed": m.failed,
                        "missing": m.missing,
                        "rotation_auc_15": m.rotation_auc_15,
                        "translation_auc_1e2": m.translation_auc_1e2,
                        "translation_l2_median": m.translation_l2_median,
                        "seconds_median": m.result.seconds_median,
                        "object": m.object,
                        "add_s_rel": m.cases.iter().map(|c| c.object.map_or(Value::Null, |o| round_sig(o.add_s, 4))).collect::<Vec<_>>(),
                        "mssd_rel": m.cases.iter().map(|c| c.object.map_or(Value::Null, |o| round_sig(o.mssd, 4))).collect::<Vec<_>>(),
                        "mspd_px": m.cases.iter().map(|c| c.object.and_then(|o| o.mspd_px).map_or(Value::Null, |x| round_sig(x, 4))).collect::<Vec<_>>(),
                        "rotation_deg": m.result.rotation_errors_deg.iter().map(|&x| round_sig(x, 5)).collect::<Vec<_>>(),
                        "translation_sq": m.result.translation_sq_errors.iter().map(|&x| round_sig(x, 4)).collect::<Vec<_>>(),
                        "seconds": m.cases.iter().map(|c| c.seconds.map_or(Value::Null, |s| round_sig(s, 4))).collect::<Vec<_>>(),
                        "failures": failures,
                    })
                })
                .collect();
            json!({
                "set": set.set,
                "count": set.count,
                "dir": set.dir,
                "cases": set.cases,
                "methods": methods,
                "missing": set.missing,
                "asymmetric_cases": set.asymmetric_cases,
                "stage_split": set.stage_split,
            })
        })
        .collect();
    v["sets"] = Value::Array(sets);
    Ok(v)
}

/// Pretty JSON, except that arrays of plain values stay on one line (the per-case arrays).
fn write_json_value(v: &Value, indent: usize, out: &mut String) {
    let pad = |n: usize| " ".repeat(n);
    match v {
        Value::Object(map) if !map.is_empty() => {
            out.push_str("{\n");
            for (i, (k, x)) in map.iter().enumerate() {
                out.push_str(&pad(indent + 2));
                out.push_str(&Value::String(k.clone()).to_string());
                out.push_str(": ");
                write_json_value(x, indent + 2, out);
                out.push_str(if i + 1 < map.len() { ",\n" } else { "\n" });
            }
            out.push_str(&pad(indent));
            out.push('}');
        }
        Value::Array(items)
            if !items.is_empty() && items.iter().any(|x| x.is_object() || x.is_array()) =>
        {
            out.push_str("[\n");
            for (i, x) in items.iter().enumerate() {
                out.push_str(&pad(indent + 2));
                write_json_value(x, indent + 2, out);
                out.push_str(if i + 1 < items.len() { ",\n" } else { "\n" });
            }
            out.push_str(&pad(indent));
            out.push(']');
        }
        Value::Array(items) => {
            out.push('[');
            for (i, x) in items.iter().enumerate() {
                if i > 0 {
                    out.push_str(", ");
                }
                out.push_str(&x.to_string());
            }
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_json_is_valid_and_keeps_plain_arrays_on_one_line() {
        let v = json!({"a": [1, 2.5, null], "b": {"c": [{"d": []}], "e": {}}, "f": "x"});
        let mut s = String::new();
        write_json_value(&v, 0, &mut s);
        let back: Value = serde_json::from_str(&s).unwrap();
        assert_eq!(back, v);
        assert!(s.contains("\"a\": [1, 2.5, null]"), "{s}");
        assert_eq!(round_sig(3.686887, 3), json!(3.69));
        assert_eq!(round_sig(0.0023719566, 2), json!(0.0024));
        assert_eq!(round_sig(f64::INFINITY, 2), Value::Null);
    }
}
