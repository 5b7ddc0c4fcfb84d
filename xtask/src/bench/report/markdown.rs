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
use crate::bench::run::{PEER_METHODS, PPF_METHODS};
use crate::bench::speed::{SIZES, Speed, Timed};

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
            .filter(|m| m.method().starts_with("ours-") && !m.method().contains("gt mask"))
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
         10° and 15° on both sets (room: the full pipeline, segmentation → pose; the \
         ground-truth-mask rows are an upper bound and do not count). Each of our methods present \
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

fn speed_section(report: &Report, speed: &Speed) -> String {
    let mut s = String::new();
    let icp = |n: usize| report.open3d_median("o3d-icp-p2p", n);
    let _ = writeln!(
        s,
        "Median wall time of one registration (the paper's Table 3), {} thread(s), one warm-up \
         then {} runs, on {} — the same case and resampling for Open3D (its `--timing --cases` \
         mode). Ratios are to Open3D's point-to-point ICP at the same size, measured in the same \
         run (× > 1: slower than ICP). Ours: `PoseEstimator::estimate` (network, weighted \
         Procrustes, optionally ICP) on n model and n observed points; `incontext eval` itself \
         feeds the network the preset's training sizes, so its per-case times in the tables \
         above are smaller.\n",
        speed.threads, speed.repeats, speed.pair
    );
    s.push_str("| method |");
    for n in SIZES {
        let _ = write!(s, " {n} pts |");
    }
    for n in SIZES {
        let _ = write!(s, " × ICP @{n} |");
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
    for m in &seen {
        let times = SIZES
            .iter()
            .map(|&n| {
                speed
                    .ours
                    .iter()
                    .find(|r| &r.method == m && r.points == n)
                    .and_then(|r| r.timed.median_seconds)
            })
            .collect();
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
                .map(|&n| report.open3d_median(&name, n))
                .collect();
            methods.push((name, times, String::new()));
        }
    }
    if let Some(t) = &report.ppf_timing {
        for m in PPF_METHODS {
            let name = format!("opencv-{m}");
            let times = SIZES.iter().map(|&n| report.ppf_median(&name, n)).collect();
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
        for (i, &n) in SIZES.iter().enumerate() {
            let _ = write!(s, " {} |", ratio(times[i], icp(n)));
        }
        let _ = writeln!(s, " {note} |");
    }
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
             on one core; median of {} run(s) after one warm-up. Each time includes training the \
             detector on the n model points (a new model in every case) and the scene normals; \
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
    s
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
        "- Load average (1/5/15 min) at the start: {}; at the end: {}. Other jobs on the \
         machine (e.g. training runs) slow every timing alike; compare ratios, not absolute times.",
        m.load_average_start.as_deref().unwrap_or("?"),
        m.load_average_end.as_deref().unwrap_or("?")
    );
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
                let tmp = plot_dir.join(format!(".{}-{name}.partial.{ext}", set.set.name()));
                plot_accuracy_curves_titled(&tmp, &results, curve, max, Some(&title))?;
                std::fs::rename(&tmp, &path)?;
                files.push(path);
            }
        }
        written.extend(files.iter().cloned());
        plots.push((set.set, files));
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
            quick: true,
            peers: true,
            seed: 1,
            noback_count: 2,
            room_count: 1,
            ppf_cases: 1,
            ppf_repeats: 1,
            threads: 1,
            repeats: 1,
            train_steps: 1,
            out: tmp.path().into(),
            work: tmp.path().into(),
            objects: serde_json::json!({"kind": "procedural", "count": 3}),
            speed: false,
            resume: false,
        };
        let mut report = Report::start(&crate::workspace_root(), &config);
        report.opencv_version = Some("4.11.0".into());
        let runs = vec![
            run("ours-ot", true, None),
            run("o3d-fgr", true, None),
            run("opencv-ppf", true, Some(1)),
        ];
        report.score(&[set], runs).unwrap();
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
        assert!(md.contains("opencv-ppf (1)"), "{md}");
        assert!(md.contains("| opencv-ppf 1.000 (1) |"), "{md}");
        assert!(md.contains("OpenCV 4.11.0 (benches/peers/ppf_peers.py), on the first 1 cases"));
    }
}
