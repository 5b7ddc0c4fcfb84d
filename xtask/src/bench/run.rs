//! Stages 2 and 3 of `cargo xtask bench`: our methods through `incontext eval --cases`, the
//! Open3D peers through `benches/peers/open3d_peers.py` and OpenCV's point-pair-feature peers
//! through `benches/peers/ppf_peers.py`, each as a subprocess writing JSONL.
//!
//! Nothing here scores: the files go to `ic_eval::cases`. A method that cannot run (its model
//! file is absent, the CLI lacks the command, Python lacks Open3D or OpenCV) is recorded with the
//! reason and the bench goes on.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

use crate::bench::cases::{CaseSet, Objects, Set};

/// Our methods, as `incontext eval --method` names them, with the head they need.
pub const OUR_METHODS: [(&str, &str); 6] = [
    ("ours-softmax", "softmax"),
    ("ours-softmax-icp", "softmax"),
    ("ours-softmax-verify", "softmax"),
    ("ours-ot", "ot"),
    ("ours-ot-icp", "ot"),
    ("ours-ot-verify", "ot"),
];

/// Open3D methods of the peers' script (their lines say `o3d-<name>`).
pub const PEER_METHODS: [&str; 5] = [
    "icp-p2p",
    "icp-p2l",
    "fpfh-ransac",
    "fpfh-ransac-icp",
    "fgr",
];

/// OpenCV methods of the PPF peers' script (their lines say `opencv-<name>`). They take
/// about 10 s a case on one core (some objects take minutes), so they run on the first
/// `--ppf-cases` cases of each set only.
pub const PPF_METHODS: [&str; 3] = ["ppf", "ppf-icp", "ppf-tuned"];

/// Our methods on a set: [`OUR_METHODS`], and on the real views also the one-shot rotation
/// sweep (the real-objects issue's one-shot figure).
pub fn our_methods(set: Set) -> &'static [(&'static str, &'static str)] {
    const REAL: [(&str, &str); 7] = [
        ("ours-softmax", "softmax"),
        ("ours-softmax-icp", "softmax"),
        ("ours-softmax-sweep", "softmax"),
        ("ours-softmax-verify", "softmax"),
        ("ours-ot", "ot"),
        ("ours-ot-icp", "ot"),
        ("ours-ot-verify", "ot"),
    ];
    match set {
        Set::Real => &REAL,
        _ => &OUR_METHODS,
    }
}

/// The shipped model a head uses, relative to the workspace root.
pub fn pose_model(head: &str) -> PathBuf {
    PathBuf::from(format!("models/pose-cpu-{head}.safetensors"))
}

pub const SEG_MODEL: &str = "models/seg-cpu.safetensors";

/// How one method on one set ended up.
#[derive(Clone, Debug, serde::Serialize)]
#[serde(tag = "status", rename_all = "snake_case")]
pub enum RunStatus {
    /// Ran (or reused); the lines are in `file`.
    Ran {
        file: PathBuf,
        wall_seconds: f64,
        reused: bool,
    },
    /// Not run, and why.
    Missing { reason: String },
    /// Started but did not finish; the reason (and whatever lines it wrote are not scored).
    Failed { reason: String },
}

/// One method (label) on one set.
#[derive(Clone, Debug, serde::Serialize)]
pub struct MethodRun {
    pub set: Set,
    /// The name in the tables (ours with the ground-truth mask get " (gt mask)").
    pub label: String,
    /// The method name in the JSONL lines.
    pub method: String,
    pub peer: bool,
    pub gt_mask: bool,
    /// Scored on the first this many cases of the set only (the slow PPF peers); `None`: all.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub case_limit: Option<u64>,
    #[serde(flatten)]
    pub status: RunStatus,
}

/// What the `incontext` binary can do.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Cli {
    pub path: PathBuf,
    /// `None` when `incontext eval --cases` is usable; else why not.
    pub unusable: Option<String>,
    pub gt_mask: bool,
    /// Whether the CLI takes the global `--seed` and `--threads`.
    pub seed_flag: bool,
    pub threads_flag: bool,
    /// Whether `eval --cases` takes `--details` (each line's stage seconds).
    pub details_flag: bool,
}

/// Builds (unless `given`; `release`: the release build, what users run, else the dev build
/// the tests share) and probes the `incontext` binary.
pub fn probe_cli(root: &Path, given: Option<&Path>, release: bool) -> Cli {
    let path = match given {
        Some(p) => p.to_path_buf(),
        None => {
            let (bin, args): (_, &[&str]) = if release {
                (
                    root.join("target/release/incontext"),
                    &[
                        "build",
                        "--release",
                        "-p",
                        "incontext",
                        "--bin",
                        "incontext",
                    ],
                )
            } else {
                // `--workspace` and `TEST_FEATURES`: the features `cargo xtask test` resolves,
                // whose build of this binary is then reused (`-p incontext` alone resolves
                // fewer and rebuilds candle and the engine).
                (
                    root.join("target/debug/incontext"),
                    &[
                        "build",
                        "--workspace",
                        "--features",
                        crate::TEST_FEATURES,
                        "--bin",
                        "incontext",
                    ],
                )
            };
            if let Err(e) = crate::cargo(args) {
                return Cli {
                    path: bin,
                    unusable: Some(format!("`cargo {}` failed: {e:#}", args.join(" "))),
                    gt_mask: false,
                    seed_flag: false,
                    threads_flag: false,
                    details_flag: false,
                };
            }
            bin
        }
    };
    let out = Command::new(&path)
        .args(["eval", "--help"])
        .stdin(Stdio::null())
        .output();
    match out {
        Err(e) => Cli {
            unusable: Some(format!("{} cannot be run: {e}", path.display())),
            path,
            gt_mask: false,
            seed_flag: false,
            threads_flag: false,
            details_flag: false,
        },
        Ok(o) => {
            let help = String::from_utf8_lossy(&o.stdout).into_owned()
                + &String::from_utf8_lossy(&o.stderr);
            let usable = o.status.success() && help.contains("--cases");
            Cli {
                unusable: (!usable).then(|| {
                    format!(
                        "`{} eval --cases` is not available yet (the CLI has no eval command \
                         with --cases)",
                        path.display()
                    )
                }),
                gt_mask: usable && help.contains("--gt-mask"),
                seed_flag: help.contains("--seed"),
                threads_flag: help.contains("--threads"),
                details_flag: usable && help.contains("--details"),
                path,
            }
        }
    }
}

/// Counts non-empty lines (progress, and whether a result file is complete).
pub fn count_lines(path: &Path) -> usize {
    std::fs::read_to_string(path)
        .map(|t| t.lines().filter(|l| !l.trim().is_empty()).count())
        .unwrap_or(0)
}

/// Runs `cmd` with stdout+stderr going to `log`, showing a bar of the lines in `out` (of
/// `expected`). Returns the wall time, or the failure with the log's tail.
fn run_with_progress(
    mut cmd: Command,
    log: &Path,
    out: &Path,
    expected: u64,
    label: &str,
) -> Result<f64, String> {
    let log_file = std::fs::File::create(log).map_err(|e| format!("{}: {e}", log.display()))?;
    let err_file = log_file
        .try_clone()
        .map_err(|e| format!("{}: {e}", log.display()))?;
    cmd.stdin(Stdio::null()).stdout(log_file).stderr(err_file);
    tracing::debug!(?cmd, "running");
    let start = Instant::now();
    let mut child = cmd.spawn().map_err(|e| format!("cannot start: {e}"))?;
    let bar = crate::bench::common::progress_bar(expected, label);
    let status = loop {
        match child.try_wait() {
            Ok(Some(s)) => break s,
            Ok(None) => {
                bar.set_position(count_lines(out) as u64);
                std::thread::sleep(Duration::from_millis(500));
            }
            Err(e) => return Err(format!("waiting for the process: {e}")),
        }
    };
    bar.set_position(count_lines(out) as u64);
    bar.finish_and_clear();
    let wall = start.elapsed().as_secs_f64();
    if status.success() {
        Ok(wall)
    } else {
        Err(format!(
            "exited with {status}; last lines of {}:\n{}",
            log.display(),
            tail(log, 8)
        ))
    }
}

fn tail(path: &Path, lines: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let v: Vec<&str> = text.lines().collect();
    v[v.len().saturating_sub(lines)..].join("\n")
}

/// Runs our four methods on `cases` (and, for the room set, the same with the ground-truth
/// mask when the CLI supports it).
pub fn run_ours(
    root: &Path,
    cli: &Cli,
    cases: &CaseSet,
    runs: &Path,
    threads: usize,
    seed: u64,
    resume: bool,
) -> Result<Vec<MethodRun>> {
    let mut out = Vec::new();
    // Room: the full pipeline and the upper bound; real views: the object's true mask, as the
    // peers get its points.
    let variants: &[bool] = match cases.set {
        Set::Noback => &[false],
        Set::Room => &[false, true],
        Set::Real => &[true],
    };
    std::fs::create_dir_all(runs).with_context(|| format!("creating {}", runs.display()))?;
    for &gt_mask in variants {
        for &(method, head) in our_methods(cases.set) {
            let label = if gt_mask {
                format!("{method} (gt mask)")
            } else {
                method.to_string()
            };
            let mut run = MethodRun {
                set: cases.set,
                label: label.clone(),
                method: method.to_string(),
                peer: false,
                gt_mask,
                case_limit: None,
                status: RunStatus::Missing {
                    reason: String::new(),
                },
            };
            let model = pose_model(head);
            let missing = if let Some(why) = &cli.unusable {
                Some(why.clone())
            } else if !root.join(&model).is_file() {
                Some(format!("{} is absent", model.display()))
            } else if gt_mask && !cli.gt_mask {
                Some("`incontext eval` has no --gt-mask option yet".into())
            } else if cases.set == Set::Room && !gt_mask && !root.join(SEG_MODEL).is_file() {
                Some(format!(
                    "{SEG_MODEL} is absent (the full pipeline segments first)"
                ))
            } else {
                None
            };
            if let Some(reason) = missing {
                tracing::warn!(set = cases.set.name(), method = %label, "{reason}");
                run.status = RunStatus::Missing { reason };
                out.push(run);
                continue;
            }
            let stem = if gt_mask {
                format!("{method}-gt-mask")
            } else {
                method.to_string()
            };
            let file = runs.join(format!("{stem}.jsonl"));
            if resume && count_lines(&file) as u64 == cases.count {
                tracing::info!(set = cases.set.name(), method = %label, file = %file.display(), "reusing");
                run.status = RunStatus::Ran {
                    file,
                    wall_seconds: 0.0,
                    reused: true,
                };
                out.push(run);
                continue;
            }
            let _ = std::fs::remove_file(&file);
            let mut cmd = Command::new(&cli.path);
            cmd.current_dir(root)
                .env("RAYON_NUM_THREADS", threads.to_string());
            if cli.seed_flag {
                cmd.args(["--seed", &seed.to_string()]);
            }
            if cli.threads_flag {
                cmd.args(["--threads", &threads.to_string()]);
            }
            cmd.arg("eval")
                .arg("--cases")
                .arg(&cases.dir)
                .args(["--method", method])
                .arg("--out")
                .arg(&file);
            if cli.details_flag {
                // Each line's stage seconds, for the report's time split.
                cmd.arg("--details");
            }
            if gt_mask {
                cmd.arg("--gt-mask");
            }
            eprintln!(
                "== {} {}: incontext eval --method {method}{}",
                cases.set.name(),
                label,
                if gt_mask { " --gt-mask" } else { "" }
            );
            run.status = match run_with_progress(
                cmd,
                &runs.join(format!("{stem}.log")),
                &file,
                cases.count,
                &format!("{} {label}", cases.set.name()),
            ) {
                Ok(wall) => RunStatus::Ran {
                    file,
                    wall_seconds: wall,
                    reused: false,
                },
                Err(reason) => {
                    tracing::error!(set = cases.set.name(), method = %label, "{reason}");
                    RunStatus::Failed { reason }
                }
            };
            out.push(run);
        }
    }
    Ok(out)
}

/// The Python that runs the peers (`given`, else `target/peers-venv/bin/python`) if it runs
/// `code`, which prints the library's version; else the reason.
fn probe_import(
    root: &Path,
    given: Option<&Path>,
    what: &str,
    code: &str,
) -> Result<(PathBuf, String), String> {
    let python = given
        .map(Path::to_path_buf)
        .unwrap_or_else(|| root.join("target/peers-venv/bin/python"));
    if !python.exists() {
        return Err(format!("{} does not exist", python.display()));
    }
    match Command::new(&python)
        .args(["-c", code])
        .stdin(Stdio::null())
        .output()
    {
        Ok(o) if o.status.success() => Ok((
            python,
            String::from_utf8_lossy(&o.stdout).trim().to_string(),
        )),
        Ok(o) => Err(format!(
            "{} cannot import {what}: {}",
            python.display(),
            String::from_utf8_lossy(&o.stderr)
                .lines()
                .last()
                .unwrap_or("")
        )),
        Err(e) => Err(format!("{} cannot be run: {e}", python.display())),
    }
}

/// The Python that runs the Open3D peers, if it can import open3d; else the reason.
pub fn probe_python(root: &Path, given: Option<&Path>) -> Result<(PathBuf, String), String> {
    probe_import(
        root,
        given,
        "open3d",
        "import open3d; print(open3d.__version__)",
    )
}

/// The Python that runs the PPF peers, if it has OpenCV with the contrib module
/// `ppf_match_3d`; else the reason.
pub fn probe_ppf_python(root: &Path, given: Option<&Path>) -> Result<(PathBuf, String), String> {
    probe_import(
        root,
        given,
        "cv2.ppf_match_3d (opencv-contrib-python-headless)",
        "import cv2; cv2.ppf_match_3d; print(cv2.__version__)",
    )
}

/// The command that installs the peers' environment (Open3D and OpenCV).
pub const PEERS_INSTALL: &str = "python3 -m venv target/peers-venv && \
    target/peers-venv/bin/pip install -r benches/peers/requirements.txt \
    (on a minimal Debian also: apt-get install libusb-1.0-0)";

/// One peer script's run over a case set: what differs between the Open3D and PPF runners.
struct ScriptRun<'a> {
    /// The script, relative to the workspace root.
    script: &'a str,
    /// The stem of its `.jsonl` and `.log` files in `runs`.
    stem: &'a str,
    /// Its methods, and the prefix of their names in the lines (`o3d`, `opencv`).
    methods: &'a [&'a str],
    prefix: &'a str,
    /// Options after the common ones; `check_args` are those the `--check` needs too.
    extra: Vec<String>,
    check_args: Vec<String>,
    /// Lines expected in the file when it is complete.
    expected: u64,
    case_limit: Option<u64>,
    /// Its name in the "reusing" log line, the banner and the progress label.
    reuse_name: &'a str,
    banner: String,
    progress: &'a str,
}

/// Runs `run.script` on `cases` (one process, one file, resumed or reused where asked), then
/// the script's --check; one [`MethodRun`] per method.
#[allow(clippy::too_many_arguments)]
fn run_script(
    root: &Path,
    python: &Path,
    cases: &CaseSet,
    runs: &Path,
    threads: usize,
    seed: u64,
    resume: bool,
    run: ScriptRun<'_>,
) -> Result<Vec<MethodRun>> {
    std::fs::create_dir_all(runs).with_context(|| format!("creating {}", runs.display()))?;
    let file = runs.join(format!("{}.jsonl", run.stem));
    let script = root.join(run.script);
    let reused = resume && count_lines(&file) as u64 == run.expected;
    let status = if reused {
        tracing::info!(
            set = cases.set.name(),
            file = %file.display(),
            "reusing the {} results",
            run.reuse_name
        );
        Ok(0.0)
    } else {
        let mut cmd = Command::new(python);
        cmd.current_dir(root)
            .arg(&script)
            .arg("--cases")
            .arg(&cases.dir)
            .arg("--out")
            .arg(&file)
            .args(["--threads", &threads.to_string()])
            .args(["--seed", &seed.to_string()])
            .args(["--max-target-points", "50000"])
            .args(&run.extra);
        if resume {
            cmd.arg("--resume");
        }
        eprintln!("{}", run.banner);
        run_with_progress(
            cmd,
            &runs.join(format!("{}.log", run.stem)),
            &file,
            run.expected,
            &format!("{} {}", cases.set.name(), run.progress),
        )
    };
    let status = status.and_then(|wall| {
        script_check(root, python, &script, &cases.dir, &file, &run.check_args).map(|()| wall)
    });
    Ok(run
        .methods
        .iter()
        .map(|m| MethodRun {
            set: cases.set,
            label: format!("{}-{m}", run.prefix),
            method: format!("{}-{m}", run.prefix),
            peer: true,
            gt_mask: false,
            case_limit: run.case_limit,
            status: match &status {
                Ok(wall) => RunStatus::Ran {
                    file: file.clone(),
                    wall_seconds: *wall,
                    reused,
                },
                Err(reason) => RunStatus::Failed {
                    reason: reason.clone(),
                },
            },
        })
        .collect())
}

/// A peer script's timing mode on the first `pairs` cases of `cases` resampled to each size
/// (with one pair the case folder itself is passed, which every version of the scripts takes);
/// `extra` are the script's own options (after the common ones), `name` its name in the banner
/// and `progress` in the progress line. The parsed JSON.
#[allow(clippy::too_many_arguments)]
fn script_timing(
    root: &Path,
    python: &Path,
    script: &str,
    extra: &[String],
    name: &str,
    progress: &str,
    cases: &CaseSet,
    out: &Path,
    sizes: &[(usize, usize)],
    repeats: usize,
    pairs: usize,
    threads: usize,
    seed: u64,
) -> Result<serde_json::Value, String> {
    let first = ic_data::export::CaseFolder::new(&cases.dir)
        .child(0)
        .dir()
        .to_path_buf();
    let (cases_arg, pairs_args) = if pairs <= 1 {
        (first, Vec::new())
    } else {
        (
            cases.dir.clone(),
            vec!["--timing-pairs".to_string(), pairs.to_string()],
        )
    };
    let sizes_arg = sizes
        .iter()
        .map(|&s| crate::bench::speed::size_label(s))
        .collect::<Vec<_>>()
        .join(",");
    let mut cmd = Command::new(python);
    cmd.current_dir(root)
        .arg(root.join(script))
        .arg("--timing")
        .args(["--points", &sizes_arg])
        .args(["--repeats", &repeats.to_string()])
        .args(["--threads", &threads.to_string()])
        .args(["--seed", &seed.to_string()])
        .args(extra)
        .arg("--cases")
        .arg(&cases_arg)
        .args(&pairs_args)
        .arg("--out")
        .arg(out);
    eprintln!("== {name} timing at {sizes_arg} points, {repeats} repeats");
    let log = crate::bench::cases::sibling(out, "log");
    run_with_progress(cmd, &log, out, 0, progress)?;
    let text = std::fs::read_to_string(out).map_err(|e| format!("{}: {e}", out.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: {e}", out.display()))
}

/// Runs the five Open3D methods on `cases` (one process, one file), then the script's --check.
pub fn run_peers(
    root: &Path,
    python: &Path,
    cases: &CaseSet,
    runs: &Path,
    threads: usize,
    seed: u64,
    resume: bool,
) -> Result<Vec<MethodRun>> {
    let run = ScriptRun {
        script: "benches/peers/open3d_peers.py",
        stem: "open3d",
        methods: &PEER_METHODS,
        prefix: "o3d",
        extra: Vec::new(),
        check_args: Vec::new(),
        expected: cases.count * PEER_METHODS.len() as u64,
        case_limit: None,
        reuse_name: "Open3D",
        banner: format!(
            "== {} Open3D peers ({})",
            cases.set.name(),
            PEER_METHODS.join(", ")
        ),
        progress: "open3d",
    };
    run_script(root, python, cases, runs, threads, seed, resume, run)
}

/// Open3D's timing mode on the first `pairs` cases of `cases` resampled to each size; the
/// parsed JSON.
#[allow(clippy::too_many_arguments)]
pub fn run_peer_timing(
    root: &Path,
    python: &Path,
    cases: &CaseSet,
    out: &Path,
    sizes: &[(usize, usize)],
    repeats: usize,
    pairs: usize,
    threads: usize,
    seed: u64,
) -> Result<serde_json::Value, String> {
    script_timing(
        root,
        python,
        "benches/peers/open3d_peers.py",
        &[],
        "Open3D",
        "open3d timing",
        cases,
        out,
        sizes,
        repeats,
        pairs,
        threads,
        seed,
    )
}

/// The peers' script's `--check` of `file` (one well-formed line per case and method); `extra`
/// are the script's options that select the cases and methods.
fn script_check(
    root: &Path,
    python: &Path,
    script: &Path,
    cases: &Path,
    file: &Path,
    extra: &[String],
) -> Result<(), String> {
    let o = Command::new(python)
        .current_dir(root)
        .arg(script)
        .arg("--check")
        .arg("--cases")
        .arg(cases)
        .arg("--out")
        .arg(file)
        .args(extra)
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("--check cannot start: {e}"))?;
    if o.status.success() {
        Ok(())
    } else {
        Err(format!(
            "--check failed:\n{}",
            String::from_utf8_lossy(&o.stdout)
        ))
    }
}

/// How the PPF script finds the model's normals: the mesh folder the cases were exported
/// from, or (procedural objects have no mesh file) normals estimated on the model points.
fn ppf_normals_args(objects: &Objects) -> Vec<String> {
    match objects {
        Objects::Folder(dir) | Objects::SplitFile { dir, .. } => {
            vec!["--objects".into(), dir.display().to_string()]
        }
        Objects::Procedural(_) => vec!["--model-normals".into(), "estimate".into()],
    }
}

/// Runs OpenCV's three PPF methods on the first `limit` cases of `cases` (one process, one
/// file), then the script's --check. Their lines are scored on those cases only.
#[allow(clippy::too_many_arguments)]
pub fn run_ppf(
    root: &Path,
    python: &Path,
    cases: &CaseSet,
    objects: &Objects,
    runs: &Path,
    limit: u64,
    threads: usize,
    seed: u64,
    resume: bool,
) -> Result<Vec<MethodRun>> {
    let limit = limit.min(cases.count);
    let limit_args = vec!["--limit".to_string(), limit.to_string()];
    let mut extra = limit_args.clone();
    extra.extend(ppf_normals_args(objects));
    let run = ScriptRun {
        script: "benches/peers/ppf_peers.py",
        stem: "ppf",
        methods: &PPF_METHODS,
        prefix: "opencv",
        extra,
        check_args: limit_args,
        expected: limit * PPF_METHODS.len() as u64,
        case_limit: Some(limit),
        reuse_name: "PPF",
        banner: format!(
            "== {} OpenCV PPF peers ({}) on the first {limit} cases",
            cases.set.name(),
            PPF_METHODS.join(", ")
        ),
        progress: "opencv ppf",
    };
    run_script(root, python, cases, runs, threads, seed, resume, run)
}

/// The PPF script's timing mode on the first case of `cases` resampled to each size (Open3D's
/// first pair; one only, as one PPF run takes seconds to minutes); the parsed JSON.
#[allow(clippy::too_many_arguments)]
pub fn run_ppf_timing(
    root: &Path,
    python: &Path,
    cases: &CaseSet,
    objects: &Objects,
    out: &Path,
    sizes: &[(usize, usize)],
    repeats: usize,
    threads: usize,
    seed: u64,
) -> Result<serde_json::Value, String> {
    script_timing(
        root,
        python,
        "benches/peers/ppf_peers.py",
        &ppf_normals_args(objects),
        "OpenCV PPF",
        "opencv ppf timing",
        cases,
        out,
        sizes,
        repeats,
        1,
        threads,
        seed,
    )
}
