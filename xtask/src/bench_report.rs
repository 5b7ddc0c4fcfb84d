//! Stage 5 of `cargo xtask bench`: score every result file with `ic_eval::cases` and write
//! `results.md` (tables, plots, machine, command), `results.json` and the plots under
//! `results/`. Every file is written atomically.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Result;
use ic_eval::cases::{MethodScore, ResultLine, read_case_truths, read_result_lines, score_results};
use ic_eval::plot::{Curve, plot_accuracy_curves_titled};
use serde::Serialize;
use serde_json::{Value, json};

use crate::bench::Config;
use crate::bench_cases::{CaseSet, Set};
use crate::bench_run::{Cli, MethodRun, RunStatus, SEG_MODEL, pose_model};
use crate::bench_speed::{SIZES, Speed, Timed};

/// The machine, as far as the files under /proc say.
#[derive(Clone, Debug, Serialize)]
pub struct Machine {
    pub cpu: String,
    pub cpu_mhz: Option<String>,
    pub cache: Option<String>,
    pub simd: Vec<String>,
    pub logical_cpus: usize,
    pub available_parallelism: usize,
    pub memory_gib: Option<f64>,
    pub os: Option<String>,
    pub kernel: Option<String>,
    pub rustc: Option<String>,
    pub load_average_start: Option<String>,
    pub load_average_end: Option<String>,
}

fn read(path: &str) -> Option<String> {
    std::fs::read_to_string(path).ok()
}

fn load_average() -> Option<String> {
    read("/proc/loadavg").map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
}

impl Machine {
    pub fn probe() -> Machine {
        let cpuinfo = read("/proc/cpuinfo").unwrap_or_default();
        let field = |name: &str| {
            cpuinfo
                .lines()
                .find(|l| l.split(':').next().is_some_and(|k| k.trim() == name))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        };
        let flags = field("flags").unwrap_or_default();
        let simd = ["sse4_2", "avx", "avx2", "fma", "avx512f"]
            .iter()
            .filter(|f| flags.split_whitespace().any(|x| x == **f))
            .map(|f| f.to_string())
            .collect();
        let memory_gib = read("/proc/meminfo").and_then(|m| {
            m.lines()
                .find(|l| l.starts_with("MemTotal:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|kb| kb.parse::<f64>().ok())
                .map(|kb| kb / (1024.0 * 1024.0))
        });
        let os = read("/etc/os-release").and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("PRETTY_NAME="))
                .map(|l| l["PRETTY_NAME=".len()..].trim_matches('"').to_string())
        });
        let rustc = std::process::Command::new("rustc")
            .arg("-V")
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string());
        Machine {
            cpu: field("model name").unwrap_or_else(|| "unknown".into()),
            cpu_mhz: field("cpu MHz"),
            cache: field("cache size"),
            simd,
            logical_cpus: cpuinfo
                .lines()
                .filter(|l| l.starts_with("processor"))
                .count(),
            available_parallelism: std::thread::available_parallelism().map_or(0, |n| n.get()),
            memory_gib,
            os,
            kernel: read("/proc/sys/kernel/osrelease").map(|s| s.trim().to_string()),
            rustc,
            load_average_start: load_average(),
            load_average_end: None,
        }
    }
}

/// The commit of the checkout, read from `.git` (no git process); `None` outside a checkout.
pub fn git_commit(root: &Path) -> Option<String> {
    let git = root.join(".git");
    let head = std::fs::read_to_string(git.join("HEAD")).ok()?;
    let head = head.trim();
    let Some(reference) = head.strip_prefix("ref: ") else {
        return Some(head.to_string());
    };
    if let Ok(c) = std::fs::read_to_string(git.join(reference)) {
        return Some(c.trim().to_string());
    }
    let packed = std::fs::read_to_string(git.join("packed-refs")).ok()?;
    packed
        .lines()
        .find(|l| l.ends_with(reference))
        .and_then(|l| l.split_whitespace().next())
        .map(str::to_string)
}

/// `YYYY-MM-DD HH:MM UTC` of a Unix time (days-to-civil, Howard Hinnant's algorithm).
pub fn utc(unix_seconds: u64) -> String {
    let days = (unix_seconds / 86_400) as i64;
    let secs = unix_seconds % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02} UTC",
        secs / 3600,
        (secs % 3600) / 60
    )
}

/// One case set's scores.
#[derive(Clone, Debug, Serialize)]
pub struct SetReport {
    pub set: Set,
    pub count: u64,
    pub dir: PathBuf,
    pub cases: Vec<Value>,
    pub scores: Vec<MethodScore>,
    /// (label, reason) of methods without scores.
    pub missing: Vec<(String, String)>,
}

/// Everything results.md and results.json are made of.
#[derive(Debug, Serialize)]
pub struct Report {
    pub config: Config,
    pub command: String,
    pub date: String,
    pub commit: Option<String>,
    pub machine: Machine,
    pub models: Vec<Value>,
    pub cli: Option<Cli>,
    pub open3d_version: Option<String>,
    pub notes: Vec<String>,
    pub stages: Vec<(String, f64)>,
    pub runs: Vec<MethodRun>,
    pub sets: Vec<SetReport>,
    pub speed: Option<Speed>,
    pub open3d_timing: Option<Value>,
    pub total_seconds: f64,
}

impl Report {
    pub fn start(root: &Path, config: &Config) -> Report {
        let args: Vec<String> = std::env::args().skip(1).collect();
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        let models = [
            pose_model("softmax"),
            pose_model("ot"),
            PathBuf::from(SEG_MODEL),
        ]
        .iter()
        .map(|m| {
            let meta = std::fs::metadata(root.join(m)).ok();
            json!({"file": m, "present": meta.is_some(), "bytes": meta.map(|m| m.len())})
        })
        .collect();
        let mut config = config.clone();
        config.out = crate::bench::rel(&config.out);
        config.work = crate::bench::rel(&config.work);
        Report {
            config,
            command: format!("cargo xtask {}", args.join(" ")),
            date: utc(now),
            commit: git_commit(root),
            machine: Machine::probe(),
            models,
            cli: None,
            open3d_version: None,
            notes: Vec::new(),
            stages: Vec::new(),
            runs: Vec::new(),
            sets: Vec::new(),
            speed: None,
            open3d_timing: None,
            total_seconds: 0.0,
        }
    }

    pub fn stage(&mut self, name: &str, seconds: f64) {
        tracing::info!(
            stage = name,
            seconds = format!("{seconds:.1}"),
            "stage done"
        );
        self.stages.push((name.to_string(), seconds));
    }

    /// Scores every run that produced a file; a file that cannot be read or scored turns that
    /// method into a missing one with the reason (the others are still reported).
    pub fn score(&mut self, sets: &[CaseSet], runs: Vec<MethodRun>) -> Result<()> {
        let mut files: HashMap<PathBuf, Result<Vec<ResultLine>, String>> = HashMap::new();
        for cs in sets {
            let truths = read_case_truths(&cs.dir)?;
            let mut report = SetReport {
                set: cs.set,
                count: cs.count,
                dir: crate::bench::rel(&cs.dir),
                cases: cs.cases.clone(),
                scores: Vec::new(),
                missing: Vec::new(),
            };
            for run in runs.iter().filter(|r| r.set == cs.set) {
                let file = match &run.status {
                    RunStatus::Ran { file, .. } => file,
                    RunStatus::Missing { reason } => {
                        report
                            .missing
                            .push((run.label.clone(), format!("not run: {reason}")));
                        continue;
                    }
                    RunStatus::Failed { reason } => {
                        report
                            .missing
                            .push((run.label.clone(), format!("failed: {reason}")));
                        continue;
                    }
                };
                let lines = files
                    .entry(file.clone())
                    .or_insert_with(|| read_result_lines(file).map_err(|e| e.to_string()));
                let lines: Vec<ResultLine> = match lines {
                    Ok(l) => l
                        .iter()
                        // The peers share one file; our files hold one method each.
                        .filter(|l| !run.peer || l.method == run.method)
                        .cloned()
                        .map(|mut l| {
                            l.method = run.label.clone();
                            l
                        })
                        .collect(),
                    Err(e) => {
                        report.missing.push((run.label.clone(), e.clone()));
                        continue;
                    }
                };
                if lines.is_empty() {
                    report.missing.push((
                        run.label.clone(),
                        format!("{} holds no line for it", file.display()),
                    ));
                    continue;
                }
                match score_results(&truths, &lines) {
                    Ok(mut s) => report.scores.append(&mut s),
                    Err(e) => report.missing.push((run.label.clone(), e.to_string())),
                }
            }
            self.sets.push(report);
        }
        self.runs = runs;
        self.machine.load_average_end = load_average();
        Ok(())
    }

    fn open3d_median(&self, method: &str, points: usize) -> Option<f64> {
        self.open3d_timing.as_ref()?["results"]
            .as_array()?
            .iter()
            .find(|r| r["method"] == method && r["points"].as_u64() == Some(points as u64))?
            ["median_seconds"]
            .as_f64()
    }
}

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
/// not the ground-truth-mask upper bound) beats every Open3D method.
fn goal_section(report: &Report) -> String {
    let mut s = String::new();
    let mut any_pair = false;
    let mut lines = Vec::new();
    let mut table = String::from(
        "| set | threshold | best of ours | best Open3D | every shipped model of ours beats every Open3D method? |\n|---|---|---|---|---|\n",
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
                "| {} | {deg}° | {bo} {bo_acc:.3} | {bp} {bp_acc:.3} | {verdict} |\n",
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
         in the tables is compared with the best Open3D method.\n\n",
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
            " Scene points: {med:.0} median ({lo:.0}–{hi:.0}); Open3D caps targets at 50 000."
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
        for m in crate::bench_run::PEER_METHODS {
            let name = format!("o3d-{m}");
            let times = SIZES
                .iter()
                .map(|&n| report.open3d_median(&name, n))
                .collect();
            methods.push((name, times, String::new()));
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
        "- Seed {} (case sets, our CLI's point sampling, Open3D's RANSAC, timing pairs); {} \
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
                 point-to-plane ICP from the identity, FPFH + RANSAC, FPFH + RANSAC + ICP, FGR \
                 (benches/peers/README.md gives every parameter)."
            }
            Set::Room => {
                "Ours runs the full pipeline (segmentation → pose) on the depth map; the \
                 \"(gt mask)\" rows use the ground-truth visible mask instead (an upper bound for \
                 the segmentation). Open3D registers the model against the whole scene cloud \
                 (capped at 50 000 points)."
            }
        };
        let _ = writeln!(s, "{what}\n");
        if set.scores.is_empty() {
            s.push_str("No method produced results on this set.\n");
        } else {
            s.push_str(&ic_eval::cases::markdown_cases_table(&set.scores));
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

/// Writes results.md, results.json and the plots under `out`; returns the paths written.
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
    crate::bench::write_atomic(&md, markdown(report, &plots).as_bytes())?;
    let json_path = out.join("results.json");
    let mut text = String::new();
    write_json_value(&results_json(report)?, 0, &mut text);
    text.push('\n');
    crate::bench::write_atomic(&json_path, text.as_bytes())?;
    written.insert(0, json_path);
    written.insert(0, md);
    Ok(written)
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

    #[test]
    fn utc_dates_are_civil() {
        assert_eq!(utc(0), "1970-01-01 00:00 UTC");
        assert_eq!(utc(951_782_400), "2000-02-29 00:00 UTC");
        assert_eq!(utc(1_763_790_000), "2025-11-22 05:40 UTC");
    }

    #[test]
    fn machine_and_commit_do_not_panic() {
        let m = Machine::probe();
        assert!(m.available_parallelism >= 1);
        let _ = git_commit(&crate::workspace_root());
        assert!(git_commit(Path::new("/nonexistent")).is_none());
    }
}
