//! `results.md` of `cargo xtask bench`: the goal's verdicts, the tables of each case set, the
//! speed section, the machine and the command, and the accuracy plots under `results/` that it
//! shows. Reads the [`Report`]; written atomically.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Result;
use ic_eval::cases::MethodScore;
use ic_eval::plot::{Curve, plot_accuracy_curves_titled};
use serde_json::Value;

use super::{Report, SetReport};
use crate::bench::cases::Set;
use crate::bench::common::write_atomic;
use crate::bench::curve::SpeedCurve;
use crate::bench::run::{MethodRun, PEER_METHODS, PPF_METHODS, RunStatus};
use crate::bench::speed::{SIZES, Speed, Timed, size_label};

fn fmt_s(v: Option<f64>) -> String {
    match v {
        Some(s) if s >= 1.0 => format!("{s:.2} s"),
        Some(s) if s >= 1e-3 => format!("{:.1} ms", s * 1e3),
        Some(s) => format!("{:.0} µs", s * 1e6),
        None => "–".into(),
    }
}

fn ratio(a: Option<f64>, b: Option<f64>) -> String {
    match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => format!("{:.2}×", a / b),
        _ => "–".into(),
    }
}

fn accuracy_at(s: &MethodScore, deg: f64) -> f64 {
    ic_eval::accuracy(&s.result.rotation_errors_deg, deg)
}

/// The goal's verdicts: for each set and 10°/15°, whether each of our methods (full pipeline,
/// not the ground-truth-mask upper bound) beats every Open3D method. The best OpenCV PPF method
/// is shown beside them (it is not part of the goal's definition).
fn goal_section(report: &Report) -> String {
    let mut s = String::new();
    let mut any_pair = false;
    let mut lines = Vec::new();
    let mut table = String::from(
        "| set | threshold | best of ours | best Open3D | every shipped model of ours beats every Open3D method? | best OpenCV PPF (its cases) |\n|---|---|---|---|---|---|\n",
    );
    for set in &report.sets {
        let ours: Vec<&MethodScore> = set
            .scores
            .iter()
            // In the room the mask rows are an upper bound; on the real views every method,
            // the peers included, gets the object's true mask.
            .filter(|m| {
                m.method().starts_with("ours-")
                    && (set.set != Set::Room || !m.method().contains("gt mask"))
            })
            .collect();
        let peers: Vec<&MethodScore> = set
            .scores
            .iter()
            .filter(|m| m.method().starts_with("o3d-"))
            .collect();
        if ours.is_empty() || peers.is_empty() {
            lines.push(format!(
                "- {}: not decided — {}.",
                set.set.title(),
                if ours.is_empty() {
                    "none of our methods produced results"
                } else {
                    "the Open3D peers were not run"
                }
            ));
            continue;
        }
        any_pair = true;
        for deg in [10.0, 15.0] {
            let best = |v: &[&MethodScore]| {
                v.iter()
                    .map(|m| (m.method().to_string(), accuracy_at(m, deg)))
                    .max_by(|a, b| a.1.total_cmp(&b.1))
                    .unwrap_or_default()
            };
            let (bo, bo_acc) = best(&ours);
            let (bp, bp_acc) = best(&peers);
            let ppf: Vec<&MethodScore> = set
                .scores
                .iter()
                .filter(|m| m.method().starts_with("opencv-"))
                .collect();
            let ppf_cell = if ppf.is_empty() {
                "not run".to_string()
            } else {
                let (bc, bc_acc) = best(&ppf);
                let n = ppf
                    .iter()
                    .map(|m| m.result.summary.count)
                    .max()
                    .unwrap_or(0);
                format!("{bc} {bc_acc:.3} ({n})")
            };
            let losers: Vec<String> = ours
                .iter()
                .filter(|m| accuracy_at(m, deg) <= bp_acc)
                .map(|m| format!("{} ({:.3})", m.method(), accuracy_at(m, deg)))
                .collect();
            let verdict = if losers.is_empty() {
                "yes".to_string()
            } else if losers.len() == ours.len() {
                "**no** — none of ours does".to_string()
            } else {
                format!("**no** — not {}", losers.join(", "))
            };
            table.push_str(&format!(
                "| {} | {deg}° | {bo} {bo_acc:.3} | {bp} {bp_acc:.3} | {verdict} | {ppf_cell} |\n",
                set.set.name()
            ));
            if bo_acc <= bp_acc {
                lines.push(format!(
                    "- **{} at {deg}°: we do not beat Open3D.** Our best, {bo}, reaches {bo_acc:.3}; {bp} reaches {bp_acc:.3}.",
                    set.set.title()
                ));
            }
        }
    }
    s.push_str(
        "The goal: every shipped model of ours beats every Open3D method in rotation accuracy at \
         10° and 15° on every set (room: the full pipeline, segmentation → pose, the \
         ground-truth-mask rows are an upper bound and do not count; real views: every method \
         gets the object's true mask). Each of our methods present \
         in the tables is compared with the best Open3D method. The last column, not part of the \
         goal, gives the best OpenCV point-pair-feature method on the cases it ran on (the first \
         ones of the set; its accuracy is over those only).\n\n",
    );
    if any_pair {
        s.push_str(&table);
        s.push('\n');
    }
    for l in &lines {
        s.push_str(l);
        s.push('\n');
    }
    let missing_ours: Vec<String> = report
        .sets
        .iter()
        .flat_map(|set| {
            set.missing
                .iter()
                .filter(|m| m.0.starts_with("ours-") && !m.0.contains("gt mask"))
                .map(move |m| format!("{} on {}", m.0, set.set.name()))
        })
        .collect();
    if !missing_ours.is_empty() {
        s.push_str(&format!(
            "- Not compared because they have no results (see *Missing methods*): {}.\n",
            missing_ours.join(", ")
        ));
    }
    s
}

fn stats(values: &mut [f64]) -> Option<(f64, f64, f64)> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    Some((values[0], ic_eval::median(values), values[values.len() - 1]))
}

/// The clutter benchmark: the segmentation's instances and the whole pipeline on every
/// target, against the real-clutter issue's figures.
fn clutter_section(report: &Report) -> String {
    let Some(c) = &report.clutter else {
        return String::new();
    };
    let mut s = format!(
        "\n## Clutter ({} scenes)\n\n{} scenes of the unseen `real_objects` test objects: \
         tables, bins and shelves holding 3–15 objects at their real sizes, the target among them \
         (sometimes several copies), the sensor model on, 640×480 (`ic_data::clutter`, written \
         as a BOP dataset to `{}`). Goals of the real-clutter issue: the target's instance \
         found (IoU ≥ 0.5 with its visible mask) in ≥ 95 % of scenes, the pipeline's ADD-S < \
         0.1·d in ≥ 85 %.\n\n",
        c.scenes,
        c.scenes,
        c.dir.display()
    );
    let instance_row = |sensor: &str, v: &Value| {
        let f = |k: &str| v[k].as_f64().unwrap_or(f64::NAN);
        format!(
            "| {sensor} | {} | {} | {:.3} | {:.3} | {:.3} | {} | {} | {:.1} |\n",
            v["images"],
            v["true_instances"],
            f("target_found_rate"),
            f("recall"),
            f("matched_iou_mean"),
            v["over_segmented"],
            v["under_segmented"],
            f("predictions_per_image"),
        )
    };
    match &c.segmentation {
        Ok(v) => {
            let _ = write!(
                s,
                "Segmentation (`{}`, every true instance with enough visible pixels), on the \
                 scenes as drawn, on the same scenes with the projector's shadows and the \
                 registration's holes in every one (the bands without a return of real \
                 structured-light maps, `docs/decisions.md`), and on the same scenes seen \
                 through other cameras (the network's input sized from each, `docs/decisions.md`, \
                 \"Any camera\"):\n\n\
                 | sensor or camera | images | true instances | target found | recall | matched IoU (mean) | \
                 over-segmented | under-segmented | predictions per image |\n\
                 |---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
                crate::bench::scenes::CLUTTER_SEG_MODEL,
            );
            s.push_str(&instance_row("as drawn", v));
            let rows = std::iter::once(("+ shadows", &c.segmentation_shadowed)).chain(
                c.segmentation_cameras
                    .iter()
                    .map(|(label, r)| (label.as_str(), r)),
            );
            for (label, result) in rows {
                match result {
                    Ok(w) => s.push_str(&instance_row(label, w)),
                    Err(why) => {
                        let _ = writeln!(
                            s,
                            "| {label} | not measured ({why}) | – | – | – | – | – | – | – |"
                        );
                    }
                }
            }
            s.push('\n');
            let m = &v["target_misses"];
            if m.is_object() {
                // "n" as drawn, "n / m" when the shadowed scenes were measured too.
                let w = c
                    .segmentation_shadowed
                    .as_ref()
                    .ok()
                    .map(|w| &w["target_misses"]);
                let both = |k: &str| match w {
                    Some(w) => format!("{} / {}", m[k], w[k]),
                    None => m[k].to_string(),
                };
                let _ = writeln!(
                    s,
                    "Targets missed ({}): {} not seen as an object (under half of the target in \
                     any instance), {} merged with other objects, {} cut in pieces, {} \
                     borderline (`eval-seg` writes a row per scene, `docs/decisions.md` says \
                     which targets).\n",
                    if w.is_some() {
                        "as drawn / + shadows"
                    } else {
                        "as drawn"
                    },
                    both("not_object"),
                    both("merged"),
                    both("split"),
                    both("borderline"),
                );
            }
        }
        Err(why) => {
            let _ = writeln!(s, "Segmentation: not measured ({why}).\n");
        }
    }
    match &c.pipeline {
        Ok(v) => {
            let results = v["datasets"]
                .as_object()
                .and_then(|d| d.values().next())
                .and_then(|d| d["results"].as_array().cloned())
                .unwrap_or_default();
            let _ = write!(
                s,
                "The whole pipeline (`incontext eval --dataset`, `register`'s default: the \
                 clutter segmentation with the one-object network's second opinion, ranking by \
                 size, hypothesise and verify); errors to the nearest true instance of the \
                 target{}:\n\n| method | targets | failed | ADD-S < 0.1·d | acc@5° | acc@10° | \
                 acc@15° | rot. median (°) | median s |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
                if c.pipeline_reused {
                    " (reused, `--resume`: read back from `runs/clutter.json`, written \
                     earlier on the same scenes, not run again)"
                } else {
                    ""
                }
            );
            for r in &results {
                let sm = &r["summary"];
                let acc = |i: usize| sm["rotation_accuracy"][i][1].as_f64().unwrap_or(f64::NAN);
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1} | {:.2} |",
                    r["method"].as_str().unwrap_or("?"),
                    sm["count"],
                    sm["failures"],
                    sm["add_s_accuracy"].as_f64().unwrap_or(f64::NAN),
                    acc(0),
                    acc(1),
                    acc(2),
                    sm["rotation_median_deg"].as_f64().unwrap_or(f64::NAN),
                    r["seconds_median"].as_f64().unwrap_or(f64::NAN),
                );
            }
        }
        Err(why) => {
            let _ = writeln!(s, "The pipeline: not run ({why}).");
        }
    }
    s
}

/// The real frames without ground truth: how many poses agree with the depth map.
fn frames_section(report: &Report) -> String {
    if report.frames.is_empty() {
        return String::new();
    }
    let mut s = String::from(
        "\n## Real frames\n\nReal sensor frames without ground truth (`incontext eval \
         --frames`): each frame registered as `register` does (the best instance) and as \
         `register --all` does (every instance found); a pose agrees with the frame when, \
         rendered, most of its visible pixels lie within 10 mm of the measured depth and few in \
         front of it (the rule is in each summary). The real-clutter issue asks the best pose to \
         agree in at least 5 of 6 IC-BIN frames.\n\n\
         | frames | method | frames | best pose agrees | instances found (`--all`) | agreeing | \
         frames where every instance agrees | median s |\n|---|---|---:|---:|---:|---:|---:|---:|\n",
    );
    for f in &report.frames {
        match &f.summary {
            Ok(v) => {
                for (m, r) in v["methods"].as_object().into_iter().flatten() {
                    let _ = writeln!(
                        s,
                        "| {} | {m} | {} | {} | {} | {} | {} | {:.2} |",
                        f.name,
                        r["frames"],
                        r["best_agrees"],
                        r["instances_found"],
                        r["instances_agreeing"],
                        r["frames_where_every_instance_agrees"],
                        r["seconds_median"].as_f64().unwrap_or(f64::NAN),
                    );
                }
            }
            Err(why) => {
                let _ = writeln!(s, "| {} | – | not run: {why} | | | | | |", f.name);
            }
        }
    }
    s
}

/// Rotation accuracy on the cases whose object has no symmetry, when some objects of the set
/// have one (empty otherwise).
fn asymmetric_table(set: &SetReport) -> String {
    let asym: std::collections::HashSet<&str> =
        set.asymmetric_cases.iter().map(String::as_str).collect();
    if asym.is_empty() || asym.len() as u64 == set.count {
        return String::new();
    }
    let mut s = format!(
        "\nOn the {} cases whose object has no symmetry (`ic_geometry::symmetry` on its mesh; \
         {} of {} cases are of symmetric objects, left out here), rotation accuracy:\n\n\
         | method | cases | acc@5° | acc@10° | acc@15° | rot. median (°) |\n|---|---:|---:|---:|---:|---:|\n",
        asym.len(),
        set.count as usize - asym.len(),
        set.count
    );
    for m in &set.scores {
        let errs: Vec<f64> = m
            .cases
            .iter()
            .zip(&m.result.rotation_errors_deg)
            .filter(|(c, _)| asym.contains(c.case.as_str()))
            .map(|(_, e)| *e)
            .collect();
        if errs.is_empty() {
            continue;
        }
        let acc = |t: f64| ic_eval::accuracy(&errs, t);
        let _ = writeln!(
            s,
            "| {} | {} | {:.3} | {:.3} | {:.3} | {:.2} |",
            m.method(),
            errs.len(),
            acc(5.0),
            acc(10.0),
            acc(15.0),
            ic_eval::median(&errs)
        );
    }
    s
}

/// Where our methods' time goes on the set (median ms per stage over the lines with a pose).
fn stage_table(set: &SetReport) -> String {
    const STAGES: [(&str, &str); 8] = [
        ("segmentation_network", "segmentation net"),
        ("segmentation_post", "segmentation post"),
        ("observed_points", "observed points"),
        ("pose_network", "pose network"),
        ("ranking", "ranking"),
        ("icp", "ICP"),
        ("verification", "verification"),
        ("total", "total"),
    ];
    if set.stage_split.is_empty() {
        return String::new();
    }
    let mut s = String::from(
        "\nTime split of ours (median ms per registration and stage, over the cases with a pose; \
         `details.stage_seconds` of `incontext eval --details`; the medians do not add up to \
         the total's):\n\n| method | cases |",
    );
    for (_, title) in STAGES {
        let _ = write!(s, " {title} |");
    }
    s.push_str("\n|---|---:|");
    s.push_str(&"---:|".repeat(STAGES.len()));
    s.push('\n');
    for split in &set.stage_split {
        let _ = write!(s, "| {} | {} |", split.label, split.cases);
        for (key, _) in STAGES {
            match split.median_seconds.get(key) {
                Some(v) => {
                    let _ = write!(s, " {:.1} |", v * 1e3);
                }
                None => s.push_str(" – |"),
            }
        }
        s.push('\n');
    }
    s
}

fn set_facts(set: &SetReport) -> String {
    let mut objects: Vec<&str> = set
        .cases
        .iter()
        .filter_map(|c| c["object_id"].as_str())
        .collect();
    objects.sort_unstable();
    objects.dedup();
    let mut s = format!(
        "{} cases of {} distinct test objects, in `{}`.",
        set.count,
        objects.len(),
        set.dir.display()
    );
    let mut rates: Vec<f64> = set
        .cases
        .iter()
        .filter_map(|c| c["inlier_rate"].as_f64())
        .collect();
    if let Some((lo, med, hi)) = stats(&mut rates) {
        let what = if set.set == Set::Room {
            "object points among the scene points"
        } else {
            "observed points with a model point within 0.05 (inlier rate)"
        };
        s.push_str(&format!(
            " {what}: {:.1} % median ({:.1}–{:.1} %).",
            med * 100.0,
            lo * 100.0,
            hi * 100.0
        ));
    }
    let mut points: Vec<f64> = set
        .cases
        .iter()
        .filter_map(|c| c["scene_points"].as_f64())
        .collect();
    if let Some((lo, med, hi)) = stats(&mut points) {
        s.push_str(&format!(
            " Scene points: {med:.0} median ({lo:.0}–{hi:.0}); the peers cap targets at 50 000."
        ));
    }
    s
}

/// A method's median seconds at (model, observed) points, when timed.
type SizedTime<'a> = dyn Fn(&str, (usize, usize)) -> Option<f64> + 'a;

/// The speed goals of the benchmark issue, each a ratio measured in this run at equal
/// threads: the one-shot pose at the operating point ≤ 0.5× FGR, at 1024×768 ≤ 1.0× FGR, the
/// `cpu` preset's training step ≥ 60 000 pairs/h.
fn speed_goals(
    speed: &Speed,
    ours_at: &SizedTime,
    fgr: &dyn Fn((usize, usize)) -> Option<f64>,
) -> String {
    let mut s = format!(
        "\nSpeed goals ({} thread(s), this run):\n\n| goal | measured | met? |\n|---|---|---|\n",
        speed.threads
    );
    // The shipped heads, and the softmax weights with the other attention when timed.
    let mut goal_methods = vec!["ours-softmax", "ours-ot"];
    for r in &speed.ours {
        let other =
            r.method.starts_with("ours-softmax-keys") || r.method == "ours-softmax-all-keys";
        if other && !goal_methods.contains(&r.method.as_str()) {
            goal_methods.push(&r.method);
        }
    }
    for (size, bound) in [((384, 288), 0.5), ((1024, 768), 1.0)] {
        for &m in &goal_methods {
            let (t, f) = (ours_at(m, size), fgr(size));
            let measured = match (t, f) {
                (Some(t), Some(f)) => format!(
                    "{} vs FGR {} = {:.2}×",
                    fmt_s(Some(t)),
                    fmt_s(Some(f)),
                    t / f
                ),
                (Some(t), None) => format!("{} (FGR not timed)", fmt_s(Some(t))),
                _ => "not timed".into(),
            };
            let met = match (t, f) {
                (Some(t), Some(f)) if t <= bound * f => "yes",
                (Some(_), Some(_)) => "**no**",
                _ => "–",
            };
            let _ = writeln!(
                s,
                "| {m} one-shot at {} ≤ {bound}× FGR | {measured} | {met} |",
                size_label(size)
            );
        }
    }
    for t in &speed.training {
        let p = t.pairs_per_hour_network;
        let _ = writeln!(
            s,
            "| training step, {} head, ≥ 60 000 pairs/h | {} | {} |",
            t.head,
            p.map_or("not timed".into(), |p| format!("{p:.0} pairs/h")),
            match p {
                Some(p) if p >= 60_000.0 => "yes",
                Some(_) => "**no**",
                None => "–",
            }
        );
    }
    s
}

fn speed_section(report: &Report, speed: &Speed) -> String {
    let mut s = String::new();
    let icp = |n: usize| report.open3d_median("o3d-icp-p2p", (n, n));
    let fgr = |size: (usize, usize)| report.open3d_median("o3d-fgr", size);
    let _ = writeln!(
        s,
        "Median wall time of one registration, {} thread(s), one warm-up then {} runs per pair, \
         on {} (`m×n`; one number: n × n; over several pairs the median of the pairs' medians) — \
         the same cases for Open3D (its `--timing --cases DIR --timing-pairs K` mode) and the \
         first of them for OpenCV PPF. The sizes: the shipped \
         `cpu` preset's operating point (384×288, what `register` feeds the network), the \
         paper's Table 3 (512, 1024, 2048) and its inference size (1024×768). Ratios are to \
         Open3D's FGR at the same size, measured in the same run (× < 1: faster than FGR). \
         Ours: `PoseEstimator::estimate` (network, weighted Procrustes, optionally ICP): the \
         one-shot pose of one network pass; `register`'s default adds the rotation sweep and \
         verification (the tables' `-verify` rows and their time split).\n",
        speed.threads, speed.repeats, speed.pair
    );
    s.push_str("| method |");
    for size in SIZES {
        let _ = write!(s, " {} pts |", size_label(size));
    }
    for size in SIZES {
        let _ = write!(s, " × FGR @{} |", size_label(size));
    }
    s.push_str(" note |\n|---|");
    s.push_str(&"---:|".repeat(SIZES.len() * 2));
    s.push_str("---|\n");
    let mut methods: Vec<(String, Vec<Option<f64>>, String)> = Vec::new();
    let mut seen: Vec<String> = Vec::new();
    for r in &speed.ours {
        if !seen.contains(&r.method) {
            seen.push(r.method.clone());
        }
    }
    let ours_at = |m: &str, (a, b): (usize, usize)| {
        speed
            .ours
            .iter()
            .find(|r| r.method == m && r.points == a && r.observed_points == b)
            .and_then(|r| r.timed.median_seconds)
    };
    for m in &seen {
        let times = SIZES.iter().map(|&size| ours_at(m, size)).collect();
        let r = speed.ours.iter().find(|r| &r.method == m);
        let note = r
            .and_then(|r| r.timed.note.clone().or(r.timed.error.clone()))
            .unwrap_or_default();
        methods.push((m.clone(), times, note));
    }
    if report.open3d_timing.is_some() {
        for m in PEER_METHODS {
            let name = format!("o3d-{m}");
            let times = SIZES
                .iter()
                .map(|&size| report.open3d_median(&name, size))
                .collect();
            methods.push((name, times, String::new()));
        }
    }
    if let Some(t) = &report.ppf_timing {
        for m in PPF_METHODS {
            let name = format!("opencv-{m}");
            let times = SIZES
                .iter()
                .map(|&size| report.ppf_median(&name, size))
                .collect();
            let errors: Vec<String> = t["results"]
                .as_array()
                .into_iter()
                .flatten()
                .filter(|r| r["method"] == name.as_str())
                .filter_map(|r| {
                    r["error"]
                        .as_str()
                        .map(|e| format!("{} pts: {e}", r["points"]))
                })
                .collect();
            let note = if errors.is_empty() {
                "training the detector on the model included".to_string()
            } else {
                errors.join("; ")
            };
            methods.push((name, times, note));
        }
    }
    for (m, times, note) in &methods {
        let _ = write!(s, "| {m} |");
        for t in times {
            let _ = write!(s, " {} |", fmt_s(*t));
        }
        for (i, &size) in SIZES.iter().enumerate() {
            let _ = write!(s, " {} |", ratio(times[i], fgr(size)));
        }
        let _ = writeln!(s, " {note} |");
    }
    s.push_str(&speed_goals(speed, &ours_at, &fgr));
    if report.open3d_timing.is_none() {
        s.push_str("\nOpen3D was not timed in this run (pass --peers), so there are no ratios.\n");
    }
    if let Some(t) = &report.open3d_timing {
        let _ = writeln!(
            s,
            "\nOpen3D {} ran with {} thread(s) (Python {}).",
            t["open3d_version"].as_str().unwrap_or("?"),
            t["threads"],
            t["machine"]["python"].as_str().unwrap_or("?")
        );
    }
    if let Some(t) = &report.ppf_timing {
        let _ = writeln!(
            s,
            "\nOpenCV {} PPF: cv2.setNumThreads({}), but the PyPI wheel runs its PPF and ICP loops \
             on one core; median of {} run(s) after one warm-up, on the first pair only. Each \
             time includes training the detector on the n model points (a new model in every \
             case) and the scene normals; \
             `opencv-ppf-icp` adds its ICP to the PPF stage of `opencv-ppf`.",
            t["opencv_version"].as_str().unwrap_or("?"),
            t["threads"],
            t["repeats"]
        );
    }
    let icp1024 = icp(1024);
    s.push_str(
        "\n| quantity | median | rate | × Open3D ICP @1024 pts | note |\n|---|---:|---:|---:|---|\n",
    );
    let row = |s: &mut String, t: &Timed, rate: String| {
        let note = t.note.clone().or(t.error.clone()).unwrap_or_default();
        let _ = writeln!(
            s,
            "| {} | {} | {rate} | {} | {note} |",
            t.label,
            fmt_s(t.median_seconds),
            ratio(t.median_seconds, icp1024)
        );
    };
    row(&mut s, &speed.segmentation, "–".into());
    for t in &speed.render {
        let rate = t
            .median_seconds
            .map_or("–".into(), |m| format!("{:.1} views/s", 1.0 / m));
        row(&mut s, t, rate);
    }
    for t in &speed.training {
        let rate = t
            .pairs_per_hour_network
            .map_or("–".into(), |p| format!("{p:.0} pairs/h"));
        row(&mut s, &t.step, rate);
        let rate = t
            .pairs_per_hour_with_rendering
            .map_or("–".into(), |p| format!("{p:.0} pairs/h incl. rendering"));
        row(&mut s, &t.sample, rate);
    }
    s.push_str(
        "\nTraining: `Trainer::step` of the `cpu` preset on real samples (forward, loss, backward, \
         Adam); pairs/h = batch · 3600 / step time, and with the sample rendering of one thread \
         added (training uses separate data workers). Segmentation: `Segmenter::segment` on the \
         first room case (network on the preset's input size, up-sampling, components). The \
         renderer is the CPU rasteriser the training uses.\n",
    );
    if let Some(curve) = &speed.curve {
        s.push_str(&curve_section(curve, fgr(CURVE_REFERENCE), speed.threads));
    }
    s
}

/// The FGR time the curve compares with: Open3D's at the operating point (384×288).
const CURVE_REFERENCE: (usize, usize) = (384, 288);

/// The accuracy/speed curve: a table (accuracy, time and ratio to FGR at the operating point
/// per size and k), the best point at ≤ 0.5× FGR, and the plot's link.
fn curve_section(curve: &SpeedCurve, fgr: Option<f64>, threads: usize) -> String {
    let mut s = String::new();
    let (ks, sizes) = (curve.ks(), curve.sizes());
    let _ = writeln!(
        s,
        "\n### Accuracy against speed\n\nOur one-shot pose (`PoseEstimator::estimate`, no ICP) \
         with the shipped softmax weights (trained at 384×288 points, k = {}) at other point \
         counts (m model × n observed) and other neighbours k of the DGCNN's graph: rotation \
         accuracy at 15° on the first {} object-alone cases (each resampled as the speed table \
         does), median time on the first {} of them ({} thread(s), {} runs each), and the ratio \
         to Open3D's FGR at {} in this run. Each cell: acc@15° · time (× FGR).{}\n",
        curve.trained_k,
        curve.cases,
        curve.pairs,
        threads,
        curve.repeats,
        size_label(CURVE_REFERENCE),
        curve
            .note
            .as_ref()
            .map_or(String::new(), |n| format!(" Note: {n}."))
    );
    s.push_str("| m×n |");
    for k in &ks {
        let _ = write!(s, " k = {k} |");
    }
    s.push_str("\n|---|");
    s.push_str(&"---:|".repeat(ks.len()));
    s.push('\n');
    for &size in &sizes {
        let _ = write!(s, "| {}×{} |", size.0, size.1);
        for &k in &ks {
            match curve.at(size, k) {
                Some(p) => {
                    let t = p.time.median_seconds;
                    let _ = write!(
                        s,
                        " {:.3} · {} ({}) |",
                        p.rotation_acc_15,
                        fmt_s(t),
                        ratio(t, fgr)
                    );
                }
                None => s.push_str(" – |"),
            }
        }
        s.push('\n');
    }
    if let Some(fgr) = fgr {
        let best = curve
            .points
            .iter()
            .filter(|p| p.time.median_seconds.is_some_and(|t| t <= 0.5 * fgr))
            .max_by(|a, b| a.rotation_acc_15.total_cmp(&b.rotation_acc_15));
        let shipped = curve.at(CURVE_REFERENCE, curve.trained_k);
        let _ = writeln!(
            s,
            "\nAt ≤ 0.5× FGR ({}): {}; the shipped operating point (384×288, k = {}): {}.",
            fmt_s(Some(0.5 * fgr)),
            best.map_or("no point of the curve".to_string(), |p| format!(
                "best acc@15° {:.3} at {}×{}, k = {} ({})",
                p.rotation_acc_15,
                p.points,
                p.observed_points,
                p.k,
                fmt_s(p.time.median_seconds)
            )),
            curve.trained_k,
            shipped.map_or("not measured".to_string(), |p| format!(
                "{:.3} ({})",
                p.rotation_acc_15,
                fmt_s(p.time.median_seconds)
            ))
        );
    }
    let _ = writeln!(s, "\n![speed-accuracy.svg](results/speed-accuracy.svg)");
    s
}

/// The curve as a plot: acc@15° against milliseconds, a line per k through the sizes, and
/// FGR's time at the operating point and half of it as vertical lines.
fn plot_curve(path: &Path, curve: &SpeedCurve, fgr: Option<f64>) -> Result<()> {
    let mut series: Vec<(String, Vec<(f64, f64)>)> = curve
        .ks()
        .iter()
        .map(|&k| {
            let pts = curve
                .points
                .iter()
                .filter(|p| p.k == k)
                .filter_map(|p| Some((p.time.median_seconds? * 1e3, p.rotation_acc_15)))
                .collect();
            let trained = if k == curve.trained_k {
                " (trained)"
            } else {
                ""
            };
            (format!("k = {k}{trained}"), pts)
        })
        .collect();
    if let Some(f) = fgr {
        let ms = f * 1e3;
        series.push((
            format!("FGR @{}", size_label(CURVE_REFERENCE)),
            vec![(ms, 0.0), (ms, 1.0)],
        ));
        series.push(("0.5× FGR".into(), vec![(0.5 * ms, 0.0), (0.5 * ms, 1.0)]));
    }
    ic_eval::plot::plot_xy(
        path,
        "One-shot accuracy against time (sizes m×n along each line)",
        ("median time per registration (ms)", "rotation acc@15°"),
        1.0,
        &series,
    )?;
    Ok(())
}

/// The header line naming the result files a `--resume` run took from an earlier run (whose
/// times were measured then, under that run's load), by set; `None` when every file ran now.
fn reused_line(runs: &[MethodRun]) -> Option<String> {
    let reused: Vec<&MethodRun> = runs
        .iter()
        .filter(|r| matches!(r.status, RunStatus::Ran { reused: true, .. }))
        .collect();
    if reused.is_empty() {
        return None;
    }
    let mut by_set: Vec<(Set, Vec<&str>)> = Vec::new();
    for r in &reused {
        match by_set.iter_mut().find(|(s, _)| *s == r.set) {
            Some((_, labels)) => labels.push(&r.label),
            None => by_set.push((r.set, vec![&r.label])),
        }
    }
    let sets: Vec<String> = by_set
        .iter()
        .map(|(set, labels)| format!("{}: {}", set.name(), labels.join(", ")))
        .collect();
    Some(format!(
        "- Reused (`--resume`): {} of {} method rows come from result files an earlier run of this \
         command wrote, not run again ({}); their accuracy is the same, their times were measured \
         then, under that run's load. A peer's file that an earlier run left part-way is \
         completed, not restarted.",
        reused.len(),
        runs.len(),
        sets.join("; ")
    ))
}

fn markdown(report: &Report, plots: &[(Set, Vec<PathBuf>)]) -> String {
    let c = &report.config;
    let m = &report.machine;
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# Benchmark results\n\nGenerated by `cargo xtask bench` — do not edit by hand; run the \
         command below again.\n"
    );
    let _ = writeln!(s, "- Command: `{}`", report.command);
    let _ = writeln!(
        s,
        "- Date: {}; commit {} (read from `.git`; uncommitted changes are not recorded); the \
         whole run took {:.0} s.",
        report.date,
        report.commit.as_deref().unwrap_or("unknown"),
        report.total_seconds
    );
    let _ = writeln!(
        s,
        "- Machine: {} ({} logical CPUs, {} usable; {}{}{}), {} memory, {}, kernel {}; {}.",
        m.cpu,
        m.logical_cpus,
        m.available_parallelism,
        m.cpu_mhz
            .as_ref()
            .map_or(String::new(), |f| format!("{f} MHz, ")),
        m.cache
            .as_ref()
            .map_or(String::new(), |f| format!("cache {f}, ")),
        if m.simd.is_empty() {
            "no SIMD flags".to_string()
        } else {
            m.simd.join(" ")
        },
        m.memory_gib.map_or("?".into(), |g| format!("{g:.1} GiB")),
        m.os.as_deref().unwrap_or("unknown OS"),
        m.kernel.as_deref().unwrap_or("?"),
        m.rustc.as_deref().unwrap_or("rustc ?"),
    );
    let _ = writeln!(
        s,
        "- Build: {}; the speed table, the accuracy/speed curve and the training steps are timed \
         in this process, the other times in the `incontext` binary.",
        if report.release_build {
            "release"
        } else {
            "dev (debug assertions and overflow checks on: our code is timed slower than in a \
             release build, which the full run uses)"
        }
    );
    let _ = writeln!(
        s,
        "- Load average (1/5/15 min) at the start: {}; at the end: {}. Other jobs on the \
         machine (e.g. training runs) slow every timing alike; compare ratios, not absolute times.",
        m.load_average_start.as_deref().unwrap_or("?"),
        m.load_average_end.as_deref().unwrap_or("?")
    );
    if let Some(line) = reused_line(&report.runs) {
        let _ = writeln!(s, "{line}");
    }
    let _ = writeln!(
        s,
        "- Seed {} (case sets, our CLI's point sampling, the peers' RANSAC, timing pairs); {} \
         object-alone cases and {} room scenes{}; {} thread(s) for every method; objects: {}.",
        c.seed,
        c.noback_count,
        c.room_count,
        if c.quick { " (`--quick`)" } else { "" },
        c.threads,
        match &c.objects["folder"] {
            Value::String(f) => format!("`{f}` (test split, ids 800–999)"),
            _ => format!("{}", c.objects),
        }
    );
    let models: Vec<String> = report
        .models
        .iter()
        .map(|v| {
            format!(
                "`{}` {}",
                v["file"].as_str().unwrap_or("?"),
                if v["present"] == true {
                    "present"
                } else {
                    "**absent**"
                }
            )
        })
        .collect();
    let _ = writeln!(s, "- Models: {}.", models.join(", "));
    if let Some(v) = &report.open3d_version {
        let _ = writeln!(s, "- Open3D {v} (benches/peers/open3d_peers.py).");
    }
    if let Some(v) = &report.opencv_version {
        let _ = writeln!(
            s,
            "- OpenCV {v} (benches/peers/ppf_peers.py), on the first {} cases of each set.",
            if c.ppf_cases == 0 {
                "all".to_string()
            } else {
                c.ppf_cases.to_string()
            }
        );
    }
    for n in &report.notes {
        let _ = writeln!(s, "- {n}");
    }

    s.push_str("\n## Goal\n\n");
    s.push_str(&goal_section(report));

    for set in &report.sets {
        let _ = writeln!(s, "\n## {} ({} cases)\n", set.set.title(), set.count);
        let _ = writeln!(s, "{}\n", set_facts(set));
        let what = match set.set {
            Set::Noback => {
                "Methods: ours (`incontext eval --cases`): the pose network with the softmax or OT \
                 head, one-shot (weighted Procrustes) or refined by ICP; Open3D: point-to-point and \
                 point-to-plane ICP from the identity, FPFH + RANSAC, FPFH + RANSAC + ICP, FGR; \
                 OpenCV: point-pair features (Drost et al. 2010) with the parameters of OpenCV's \
                 sample, the same refined by OpenCV's ICP, and a variant tuned on validation cases \
                 of training objects (benches/peers/README.md gives every parameter)."
            }
            Set::Room => {
                "Ours runs the full pipeline (segmentation → pose) on the depth map; the \
                 \"(gt mask)\" rows use the ground-truth visible mask instead (an upper bound for \
                 the segmentation). Open3D and OpenCV PPF register the model against the whole \
                 scene cloud (capped at 50 000 points)."
            }
            Set::Real => {
                "Unseen objects of the `real_objects` test split (scans and CAD, normalised), \
                 seen as a user would: viewpoints on the whole sphere, camera roll, 10–100 % of \
                 the image height, the sensor model (noise, quantisation, dropout, flying \
                 pixels), occluders and truncation (`export-cases --set view`). Every method \
                 gets the object's visible points (the ground-truth mask): ours from the depth \
                 map and the mask (`--gt-mask`; `-verify` is `register`'s default, `-sweep` the \
                 one-shot rotation sweep without ICP), the peers `target.ply`. Many of these \
                 objects are symmetric (cans, bowls, boxes): the rotation columns count a pose \
                 off by a symmetry as wrong, ADD-S and MSSD/MSPD do not."
            }
        };
        let _ = writeln!(s, "{what}\n");
        if set.scores.is_empty() {
            s.push_str("No method produced results on this set.\n");
        } else {
            s.push_str(&ic_eval::cases::markdown_cases_table(&set.scores));
            let limited: Vec<String> = report
                .runs
                .iter()
                .filter(|r| r.set == set.set)
                .filter_map(|r| r.case_limit.filter(|&l| l < set.count).map(|l| (r, l)))
                .filter(|(r, _)| set.scores.iter().any(|m| m.method() == r.label))
                .map(|(r, l)| format!("{} ({l})", r.label))
                .collect();
            if !limited.is_empty() {
                let _ = writeln!(
                    s,
                    "\nScored on the first cases of the set only (`--ppf-cases`; the `cases` \
                     column gives how many): {}. Their accuracies are over those cases and \
                     compare with the others' only roughly.",
                    limited.join(", ")
                );
            }
        }
        s.push_str(&asymmetric_table(set));
        s.push_str(&stage_table(set));
        if let Some((_, files)) = plots.iter().find(|p| p.0 == set.set) {
            s.push('\n');
            for f in files
                .iter()
                .filter(|f| f.extension().is_some_and(|e| e == "svg"))
            {
                let name = f.file_name().unwrap_or_default().to_string_lossy();
                let _ = writeln!(s, "![{name}](results/{name})");
            }
            s.push_str("\n(PNG versions next to the SVGs.)\n");
        }
        let failing: Vec<String> = set
            .scores
            .iter()
            .filter(|m| m.failed + m.missing > 0)
            .map(|m| {
                let reasons: Vec<String> = m
                    .failure_reasons(3)
                    .iter()
                    .map(|(r, n)| format!("{n}× {}", r.lines().next().unwrap_or("")))
                    .collect();
                format!("- {}: {}", m.method(), reasons.join("; "))
            })
            .collect();
        if !failing.is_empty() {
            s.push_str("\nFailures (most frequent reasons):\n\n");
            for f in failing {
                let _ = writeln!(s, "{f}");
            }
        }
    }

    let missing: Vec<String> = report
        .sets
        .iter()
        .flat_map(|set| {
            set.missing.iter().map(move |(l, r)| {
                format!(
                    "- {} on {}: {}",
                    l,
                    set.set.name(),
                    r.lines().next().unwrap_or("")
                )
            })
        })
        .collect();
    if !missing.is_empty() {
        s.push_str("\n## Missing methods\n\n");
        for l in missing {
            let _ = writeln!(s, "{l}");
        }
    }

    s.push_str(&clutter_section(report));
    s.push_str(&frames_section(report));

    s.push_str("\n## Speed\n\n");
    match &report.speed {
        Some(speed) => s.push_str(&speed_section(report, speed)),
        None => s.push_str("Not measured in this run (`--no-speed`).\n"),
    }

    s.push_str("\n## Stages\n\n| stage | seconds |\n|---|---:|\n");
    for (name, secs) in &report.stages {
        let _ = writeln!(s, "| {name} | {secs:.1} |");
    }
    let _ = writeln!(
        s,
        "\nRaw result lines (one JSON line per case and method) and logs are under `{}`; \
         `results.json` next to this file holds every number above and the per-case errors.",
        c.work.display()
    );
    s
}

/// Writes the accuracy plots under `out/results/` and `out/results.md`; returns the paths
/// written, `results.md` first.
pub fn write(report: &Report, out: &Path) -> Result<Vec<PathBuf>> {
    let plot_dir = out.join("results");
    std::fs::create_dir_all(&plot_dir)?;
    let mut written = Vec::new();
    let mut plots = Vec::new();
    for set in &report.sets {
        let results: Vec<ic_eval::MethodResult> =
            set.scores.iter().map(|m| m.result.clone()).collect();
        if results.is_empty() {
            continue;
        }
        let mut files = Vec::new();
        for (curve, name, max, what) in [
            (Curve::Rotation, "rotation", 30.0, "Rotation accuracy"),
            (
                Curve::TranslationSq,
                "translation",
                1e-2,
                "Translation accuracy (squared L2)",
            ),
        ] {
            let title = format!(
                "{what}, {} ({} cases)",
                set.set.title().to_lowercase(),
                set.count
            );
            for ext in ["svg", "png"] {
                let path = plot_dir.join(format!("{}-{name}.{ext}", set.set.name()));
                plot_accuracy_curves_titled(&path, &results, curve, max, Some(&title))?;
                files.push(path);
            }
        }
        written.extend(files.iter().cloned());
        plots.push((set.set, files));
    }
    if let Some(curve) = report.speed.as_ref().and_then(|s| s.curve.as_ref()) {
        let fgr = report.open3d_median("o3d-fgr", CURVE_REFERENCE);
        for ext in ["svg", "png"] {
            let path = plot_dir.join(format!("speed-accuracy.{ext}"));
            plot_curve(&path, curve, fgr)?;
            written.push(path);
        }
    }
    let md = out.join("results.md");
    write_atomic(&md, markdown(report, &plots).as_bytes())?;
    written.insert(0, md);
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::cases::CaseSet;
    use crate::bench::report::Config;
    use crate::bench::run::{MethodRun, RunStatus};
    use ic_eval::cases::ResultLine;
    use ic_geometry::Pose;
    use ic_geometry::glam::DVec3;

    /// Two cases; a PPF peer with lines for the first only and `case_limit` 1 is scored on that
    /// one case (not failed on the second), an Open3D peer with the same lines is not; the
    /// tables say so, and the goal table shows the best PPF method beside Open3D's.
    #[test]
    fn limited_peers_are_scored_on_their_cases_and_shown() {
        let tmp = crate::bench::common::tests::TempDir::new("report");
        let cases = tmp.path().join("cases");
        let truth = Pose::from_translation(DVec3::new(0.0, 0.0, 2.8));
        for name in ["case_00000", "case_00001"] {
            let d = cases.join(name);
            std::fs::create_dir_all(&d).unwrap();
            let gt = serde_json::json!({"R": truth.rotation_row_major(), "t": [0.0, 0.0, 2.8]});
            std::fs::write(d.join("gt.json"), gt.to_string()).unwrap();
        }
        let file = tmp.path().join("peers.jsonl");
        let text: String = ["opencv-ppf", "o3d-fgr", "ours-ot"]
            .iter()
            .map(|m| {
                serde_json::to_string(&ResultLine::from_pose("case_00000", m, &truth, 1.0)).unwrap()
                    + "\n"
            })
            .collect();
        std::fs::write(&file, text).unwrap();
        let set = CaseSet {
            set: Set::Noback,
            dir: cases,
            count: 2,
            written: false,
            cases: Vec::new(),
        };
        let run = |label: &str, peer: bool, case_limit: Option<u64>| MethodRun {
            set: Set::Noback,
            label: label.into(),
            method: label.into(),
            peer,
            gt_mask: false,
            case_limit,
            status: RunStatus::Ran {
                file: file.clone(),
                wall_seconds: 1.0,
                reused: false,
            },
        };
        let config = Config {
            peers: true,
            noback_count: 2,
            ..Config::for_tests(tmp.path())
        };
        let mut report = Report::start(&crate::workspace_root(), &config);
        report.opencv_version = Some("4.11.0".into());
        let runs = vec![
            run("ours-ot", true, None),
            run("o3d-fgr", true, None),
            run("opencv-ppf", true, Some(1)),
        ];
        report
            .score(&[set], runs, &std::collections::HashMap::new())
            .unwrap();
        let scores = &report.sets[0].scores;
        let by = |m: &str| scores.iter().find(|s| s.method() == m).unwrap();
        let ppf = by("opencv-ppf");
        assert_eq!(
            (ppf.result.summary.count, ppf.scored, ppf.missing),
            (1, 1, 0)
        );
        let fgr = by("o3d-fgr");
        assert_eq!(
            (fgr.result.summary.count, fgr.scored, fgr.missing),
            (2, 1, 1)
        );
        let md = markdown(&report, &[]);
        assert!(!md.contains("Reused (`--resume`)"), "{md}");
        assert!(md.contains("opencv-ppf (1)"), "{md}");
        assert!(md.contains("| opencv-ppf 1.000 (1) |"), "{md}");
        assert!(md.contains("OpenCV 4.11.0 (benches/peers/ppf_peers.py), on the first 1 cases"));
        // A row taken from an earlier run's file is named in the header.
        if let RunStatus::Ran { reused, .. } = &mut report.runs[1].status {
            *reused = true;
        }
        let md = markdown(&report, &[]);
        assert!(
            md.contains("- Reused (`--resume`): 1 of 3 method rows come from result files an earlier run of this command wrote, not run again (noback: o3d-fgr)"),
            "{md}"
        );
    }

    /// A real set whose cases have their geometry: the object columns, the accuracy on the
    /// asymmetric objects' cases and our time split (from `details.stage_seconds`) reach the
    /// tables; the clutter and frames sections render the commands' summaries, and say why a
    /// part did not run.
    #[test]
    fn object_metrics_time_split_and_scene_sections_reach_the_report() {
        use crate::bench::scenes::{ClutterReport, FramesReport};
        use ic_eval::object_scores::CaseGeometry;
        use ic_geometry::glam::Vec3;
        use std::collections::HashMap;
        use std::sync::Arc;

        let tmp = crate::bench::common::tests::TempDir::new("report-real");
        let cases = tmp.path().join("cases");
        let truth = Pose::from_translation(DVec3::new(0.0, 0.0, 2.8));
        let half = Pose::from_axis_angle(DVec3::Z, std::f64::consts::PI, DVec3::ZERO);
        let mut geometry = HashMap::new();
        let box_points: Vec<Vec3> = (0..8)
            .map(|i| {
                Vec3::new(
                    (i & 1) as f32 - 0.5,
                    ((i >> 1) & 1) as f32 * 0.6 - 0.3,
                    ((i >> 2) & 1) as f32 * 0.4 - 0.2,
                )
            })
            .collect();
        for (i, name) in ["case_00000", "case_00001"].iter().enumerate() {
            let d = cases.join(name);
            std::fs::create_dir_all(&d).unwrap();
            let gt = serde_json::json!({"R": truth.rotation_row_major(), "t": [0.0, 0.0, 2.8]});
            std::fs::write(d.join("gt.json"), gt.to_string()).unwrap();
            // case 0: a symmetric object (a half turn about z), case 1: none.
            let symmetries = if i == 0 { vec![half] } else { vec![] };
            geometry.insert(
                name.to_string(),
                Arc::new(CaseGeometry::new(box_points.clone(), symmetries, None)),
            );
        }
        // Both off by the half turn: right up to symmetry on case 0 only.
        let file = tmp.path().join("ours.jsonl");
        let turned = truth.compose(&half);
        let text: String = ["case_00000", "case_00001"]
            .iter()
            .map(|c| {
                let mut v =
                    serde_json::to_value(ResultLine::from_pose(c, "ours-softmax-verify", &turned, 0.5))
                        .unwrap();
                v["details"] = serde_json::json!({"stage_seconds": {"pose_network": 0.2, "icp": 0.1, "total": 0.4}});
                v.to_string() + "\n"
            })
            .collect();
        std::fs::write(&file, text).unwrap();
        let set = CaseSet {
            set: Set::Real,
            dir: cases,
            count: 2,
            written: false,
            cases: Vec::new(),
        };
        let run = MethodRun {
            set: Set::Real,
            label: "ours-softmax-verify (gt mask)".into(),
            method: "ours-softmax-verify".into(),
            peer: false,
            gt_mask: true,
            case_limit: None,
            status: RunStatus::Ran {
                file,
                wall_seconds: 1.0,
                reused: false,
            },
        };
        let config = Config {
            noback_count: 1,
            real_count: 2,
            ..Config::for_tests(tmp.path())
        };
        let mut report = Report::start(&crate::workspace_root(), &config);
        report
            .score(&[set], vec![run], &HashMap::from([(Set::Real, geometry)]))
            .unwrap();
        let set = &report.sets[0];
        assert_eq!(set.asymmetric_cases, vec!["case_00001".to_string()]);
        let object = set.scores[0].object.as_ref().unwrap();
        assert!((object.ar_mssd - 0.5).abs() < 1e-12, "{object:?}");
        report.clutter = Some(ClutterReport {
            scenes: 2,
            dir: "clutter-data".into(),
            segmentation: Ok(serde_json::json!({
                "images": 2, "true_instances": 9, "target_found_rate": 0.5, "recall": 0.75,
                "matched_iou_mean": 0.8, "over_segmented": 1, "under_segmented": 2,
                "target_misses": {"not_object": 1, "merged": 0, "split": 0, "borderline": 0},
                "predictions_per_image": 5.0,
            })),
            segmentation_shadowed: Ok(serde_json::json!({
                "images": 2, "true_instances": 9, "target_found_rate": 0.0, "recall": 0.5,
                "matched_iou_mean": 0.7, "over_segmented": 3, "under_segmented": 4,
                "target_misses": {"not_object": 1, "merged": 1, "split": 0, "borderline": 0},
                "predictions_per_image": 6.0,
            })),
            segmentation_cameras: vec![
                (
                    "16:9, 1280×720".into(),
                    Ok(serde_json::json!({
                        "images": 2, "true_instances": 8, "target_found_rate": 1.0, "recall": 0.25,
                        "matched_iou_mean": 0.6, "over_segmented": 5, "under_segmented": 6,
                        "predictions_per_image": 7.0,
                    })),
                ),
                ("wide".into(), Err("no scene".into())),
            ],
            pipeline: Err("`incontext eval --cases` is not available".into()),
            pipeline_reused: false,
            seconds: 1.0,
        });
        report.frames = vec![FramesReport {
            name: "cups".into(),
            dir: "cups".into(),
            summary: Ok(serde_json::json!({"methods": {"ours-softmax-verify": {
                "frames": 6, "best_agrees": 5, "instances_found": 7, "instances_agreeing": 6,
                "frames_where_every_instance_agrees": 4, "seconds_median": 1.5,
            }}})),
        }];
        let md = markdown(&report, &[]);
        assert!(md.contains("| ADD-S < 0.1·d | AR_MSSD | AR_MSPD |"), "{md}");
        // Off by the symmetry: right in ADD-S on both, in MSSD on the symmetric one only.
        assert!(md.contains("| 1.000 | 0.500 | – |"), "{md}");
        assert!(
            md.contains("On the 1 cases whose object has no symmetry"),
            "{md}"
        );
        assert!(
            md.contains("| ours-softmax-verify (gt mask) | 1 | 0.000 | 0.000 | 0.000 | 180.00 |"),
            "{md}"
        );
        assert!(
            md.contains(
                "| ours-softmax-verify (gt mask) | 2 | – | – | – | 200.0 | – | 100.0 | – | 400.0 |"
            ),
            "{md}"
        );
        assert!(md.contains("## Clutter (2 scenes)"), "{md}");
        assert!(
            md.contains("| as drawn | 2 | 9 | 0.500 | 0.750 | 0.800 | 1 | 2 | 5.0 |"),
            "{md}"
        );
        assert!(
            md.contains("| + shadows | 2 | 9 | 0.000 | 0.500 | 0.700 | 3 | 4 | 6.0 |"),
            "{md}"
        );
        assert!(
            md.contains("| 16:9, 1280×720 | 2 | 8 | 1.000 | 0.250 | 0.600 | 5 | 6 | 7.0 |"),
            "{md}"
        );
        assert!(
            md.contains("| wide | not measured (no scene) | – |"),
            "{md}"
        );
        assert!(
            md.contains(
                "Targets missed (as drawn / + shadows): 1 / 1 not seen as an object (under half"
            ),
            "{md}"
        );
        assert!(md.contains("The pipeline: not run (`incontext eval --cases` is not available)."));
        assert!(
            md.contains("| cups | ours-softmax-verify | 6 | 5 | 7 | 6 | 4 | 1.50 |"),
            "{md}"
        );
    }

    #[test]
    fn a_reused_clutter_pipeline_and_the_timing_build_are_said_in_the_report() {
        let tmp = tempfile::tempdir().unwrap();
        let mut report = Report::start(&crate::workspace_root(), &Config::for_tests(tmp.path()));
        let pipeline = serde_json::json!({"datasets": {"clutter": {"results": [{
            "method": "ours-softmax-verify", "seconds_median": 4.0,
            "summary": {"count": 10, "failures": 1, "add_s_accuracy": 0.7,
                        "rotation_accuracy": [[5, 0.2], [10, 0.3], [15, 0.4]],
                        "rotation_median_deg": 90.0},
        }]}}});
        let clutter = |reused| crate::bench::scenes::ClutterReport {
            scenes: 2,
            dir: "clutter-data".into(),
            segmentation: Err("absent".into()),
            segmentation_shadowed: Err("absent".into()),
            segmentation_cameras: vec![("16:9".into(), Err("absent".into()))],
            pipeline: Ok(pipeline.clone()),
            pipeline_reused: reused,
            seconds: 1.0,
        };
        report.clutter = Some(clutter(false));
        let md = markdown(&report, &[]);
        assert!(
            md.contains(
                "| ours-softmax-verify | 10 | 1 | 0.700 | 0.200 | 0.300 | 0.400 | 90.0 | 4.00 |"
            ),
            "{md}"
        );
        assert!(!md.contains("(reused, `--resume`"), "{md}");
        report.clutter = Some(clutter(true));
        let md = markdown(&report, &[]);
        assert!(
            md.contains("target (reused, `--resume`: read back from `runs/clutter.json`"),
            "{md}"
        );
        // Tests run in a dev build.
        report.release_build = false;
        assert!(markdown(&report, &[]).contains("- Build: dev (debug assertions"));
        report.release_build = true;
        assert!(markdown(&report, &[]).contains("- Build: release;"));
    }

    #[test]
    fn curve_section_names_the_best_point_under_half_fgr_and_the_shipped_one() {
        use crate::bench::curve::{CurvePoint, SpeedCurve};
        let point = |m: usize, n: usize, k: usize, acc: f64, ms: f64| CurvePoint {
            points: m,
            observed_points: n,
            k,
            rotation_acc_15: acc,
            rotation_acc_5: acc / 2.0,
            rotation_median_deg: 5.0,
            failures: 0,
            time: Timed {
                median_seconds: Some(ms * 1e-3),
                runs: vec![ms * 1e-3],
                ..Timed::new("")
            },
        };
        let curve = SpeedCurve {
            head: "softmax".into(),
            trained_k: 16,
            cases: 200,
            pairs: 10,
            repeats: 5,
            points: vec![
                point(128, 96, 8, 0.40, 4.0),
                point(256, 192, 8, 0.60, 9.0),
                point(384, 288, 8, 0.70, 15.0),
                point(128, 96, 16, 0.45, 5.0),
                point(256, 192, 16, 0.65, 11.0),
                point(384, 288, 16, 0.75, 20.0),
            ],
            note: None,
        };
        // FGR 20 ms: half is 10 ms, reached by 128×96 (both k) and 256×192 at k = 8 only.
        let s = curve_section(&curve, Some(0.020), 2);
        assert!(
            s.contains("| 256×192 | 0.600 · 9.0 ms (0.45×) | 0.650 · 11.0 ms (0.55×) |"),
            "{s}"
        );
        assert!(
            s.contains("best acc@15° 0.600 at 256×192, k = 8 (9.0 ms)"),
            "{s}"
        );
        assert!(s.contains("(384×288, k = 16): 0.750 (20.0 ms)"), "{s}");
        // Without Open3D's time: the table without ratios and no verdict.
        let s = curve_section(&curve, None, 2);
        assert!(
            s.contains("0.750 · 20.0 ms (–)") && !s.contains("0.5× FGR ("),
            "{s}"
        );
        let tmp = crate::bench::common::tests::TempDir::new("curve-plot");
        let svg = tmp.path().join("c.svg");
        plot_curve(&svg, &curve, Some(0.020)).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.contains("k = 16 (trained)") && text.contains("0.5× FGR"));
    }
}
