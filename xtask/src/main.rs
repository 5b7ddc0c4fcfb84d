//! `cargo xtask` — the project's only workflow tool (see `.cargo/config.toml`).
//!
//! - `cargo xtask test` runs the whole test suite (the README's test command; CI runs it): the
//!   cargo tests, the Python module's tests (`pytest python/tests` in a fresh venv under
//!   `target/py-venv`), then `cargo xtask bench --quick --strict` (skipped when
//!   `INCONTEXT_SKIP_BENCH` is set).
//! - `cargo xtask bench [--quick] [--peers]` measures accuracy and speed of our methods beside
//!   Open3D's and OpenCV's point-pair features on fixed case sets and writes `docs/results.md`
//!   and `docs/results.json` (see `bench/`; `--quick` is the small version CI runs, written
//!   under `target/bench-quick/`).
//!   `cargo xtask bench --criterion [NAME…]` (or `cargo xtask bench NAME…`) runs the criterion
//!   benchmarks under `benches/` (all by default), then prints each benchmark's median next to
//!   its ratio to the baseline measured in the same run, and writes the same table to
//!   `target/bench-summary.json`.
//!
//! - `cargo xtask gen-data` writes fixed object-alone and room test sets (BOP layout) with a
//!   manifest (seed, configuration, objects used, counts, statistics).
//! - `cargo xtask export-cases --set <noback|room> …` writes registration cases (`source.ply`,
//!   `target.ply`, `gt.json`, `meta.json`; room cases also `depth.png`, `camera.json`).
//!
//! The training and evaluation commands below are thin wrappers of the `ic_train` crate (the
//! user-facing `incontext train pose|seg` calls the same code).
//!
//! - `cargo xtask train-pose --preset cpu|paper --head softmax|ot --objects DIR|MIXTURE --out DIR
//!   [--protocol paper|deployment] [--init WEIGHTS] …` trains the pose network on samples
//!   rendered on the fly (resumable, Ctrl-C saves; validation on the `val` objects with the
//!   same protocol). MIXTURE: `NAME=DIR:WEIGHT,…,procedural:WEIGHT`.
//! - `cargo xtask eval-pose --model FILE --objects DIR|MIXTURE [--split test|val|train]
//!   [--protocol paper|deployment] …` measures a checkpoint (rotation/translation accuracies,
//!   ADD-S, JSON report).
//!
//! - `cargo xtask train-seg --objects DIR --out DIR …` trains the instance-mask network on
//!   room scenes rendered on the fly (resumable, Ctrl-C saves).
//! - `cargo xtask eval-seg --model FILE --objects DIR [--geometric]` measures mask IoU and the
//!   found rate on test-split room scenes, optionally beside the geometry-only alternative.
//! - `cargo xtask verify-report --set NAME=CASES:RESULTS …` scores `incontext eval --cases`
//!   results on view cases: acc@15°, ADD-S, verdict precision/recall, reliability diagram,
//!   and fits the confidence calibration (`--fit-calibration`).
//! - `cargo xtask fit-clutter-calibration --candidates FILE… --out FILE` fits the confidence
//!   of poses on network-segmented instances (a logistic model over the registration's
//!   numbers, then an isotonic calibration) from `incontext eval --dataset … --candidates N`
//!   lines on clutter scenes (`models/verify-calibration-clutter.json`).
//! - `cargo xtask seg-post --model FILE --out FILE [--pixel-threshold …]` rewrites a
//!   segmentation checkpoint's post-processing settings and inference input size (chosen on
//!   validation scenes).
//! - `cargo xtask plot-runs --run NAME=RUN … --out FILE.svg [--metric COLUMN]` draws the
//!   learning curves of training runs (their `train.csv` and `val.csv`) in one plot.

mod bench;
mod clutter;
mod clutter_calibration;
mod curves;
mod data;
mod pose;
mod release;
mod seg;
mod symmetries;
mod verify_report;
mod weights;

// Large element-wise tensor ops are ~10x slower with glibc's malloc (fresh pages each time).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "cargo xtask", about = "incontext developer workflows")]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run the whole test suite: every target of every crate (benches once, in test mode), the
    /// doc tests, the Python module's tests (a fresh venv, the wheel, pytest), then the quick
    /// bench (`bench --quick --strict`; set INCONTEXT_SKIP_BENCH to skip it). This is the
    /// README's test command and what CI runs.
    Test,
    /// Accuracy and speed of our methods, Open3D's and OpenCV PPF's on fixed case sets →
    /// docs/results.md (`--quick`: the small version, under target/bench-quick/);
    /// `--criterion [NAME…]` runs the criterion benchmarks instead.
    Bench(bench::BenchArgs),
    /// Write fixed test sets (object alone and in the room) as BOP datasets with a manifest.
    GenData(data::GenDataArgs),
    /// Write registration cases for other tools (Open3D, TEASER++).
    ExportCases(data::ExportArgs),
    /// Train the pose network (ic_pose) on samples rendered on the fly.
    TrainPose(pose::TrainArgs),
    /// Evaluate a pose checkpoint on fixed test samples.
    EvalPose(pose::EvalArgs),
    /// Train the instance-mask network (ic_seg) on room scenes rendered on the fly.
    TrainSeg(seg::TrainArgs),
    /// Evaluate a segmentation checkpoint on test-split room scenes.
    EvalSeg(seg::EvalArgs),
    /// Write a segmentation checkpoint's weights with new post-processing settings.
    SegPost(seg::PostArgs),
    /// Score `incontext eval --cases` results of view cases: accuracy, ADD-S, verdict
    /// precision and recall, reliability diagram, calibration fit.
    VerifyReport(verify_report::VerifyReportArgs),
    /// Fit the confidence of poses on network-segmented instances (logistic model, then
    /// isotonic calibration) from `incontext eval --dataset … --candidates N` lines on clutter
    /// scenes.
    FitClutterCalibration(clutter_calibration::FitClutterCalibrationArgs),
    /// Render cluttered scenes (tables, bins, shelves with 3–15 objects) as PNG contact
    /// sheets: depth, true instances, and a segmentation checkpoint's instances.
    ClutterPreview(clutter::PreviewArgs),
    /// Find each object's rotational symmetries (discrete and continuous) on its normalised
    /// mesh: a table, and JSON with `--out`.
    Symmetries(symmetries::SymmetriesArgs),
    /// Learning curves of training runs in one SVG or PNG: the training loss above a
    /// validation column, against the iteration (e.g. a run from scratch against a fine-tune).
    PlotRuns(curves::PlotRunsArgs),
    /// Write a training checkpoint's weights and configuration without Adam's moments or the
    /// training state (the file to ship, as a run writes `best.safetensors`).
    ExportWeights(weights::ExportWeightsArgs),
    /// The element-wise mean of several checkpoints' weights (weight averaging along the end
    /// of a run), written as a weights-only file
    AverageWeights(weights::AverageWeightsArgs),
}

impl Cmd {
    /// Whether this command runs long or is timed in its own process, and so runs from the
    /// release build (`release`): training, evaluation, data generation, and the full bench,
    /// whose speed stage (registration times, the accuracy/speed curve, training steps) times
    /// our code in this process — one 384×288 registration ≈ 39 ms in the dev build against
    /// ≈ 23 ms. `bench --quick` (CI's smoke run, whose times nobody compares), `--no-speed` and
    /// the criterion benchmarks (cargo builds those in their own profile) stay; the bench
    /// report's header names the build that timed.
    fn runs_long(&self) -> bool {
        match self {
            Cmd::Bench(a) => !a.criterion && a.names.is_empty() && !a.quick && !a.no_speed,
            Cmd::GenData(_)
            | Cmd::ExportCases(_)
            | Cmd::TrainPose(_)
            | Cmd::EvalPose(_)
            | Cmd::TrainSeg(_)
            | Cmd::EvalSeg(_) => true,
            _ => false,
        }
    }
}

/// Which crate owns each benchmark file under `benches/`.
const BENCHES: &[(&str, &str)] = &[
    ("geometry", "ic_geometry"),
    ("render", "ic_render"),
    ("data", "ic_data"),
    ("pose", "ic_pose"),
    ("sinkhorn", "ic_pose"),
    ("seg", "ic_seg"),
    ("register", "incontext"),
];

fn main() -> std::process::ExitCode {
    // SAFETY: first thing in main, before any other thread exists.
    unsafe { ic_pose::tune_candle_cpu_pool() };
    let command = Cli::parse().command;
    let start = if command.runs_long() {
        release::rerun_in_release()
    } else {
        Ok(())
    };
    let result = start.and_then(|()| match command {
        Cmd::Bench(args) => bench::run(args),
        Cmd::Test => test(),
        Cmd::ClutterPreview(args) => {
            init_tracing();
            clutter::preview(args)
        }
        Cmd::GenData(args) => {
            init_tracing();
            data::gen_data(args)
        }
        Cmd::ExportCases(args) => {
            init_tracing();
            data::export_cases(args)
        }
        Cmd::TrainPose(args) => {
            init_tracing();
            pose::train(args)
        }
        Cmd::EvalPose(args) => {
            init_tracing();
            pose::eval(args)
        }
        Cmd::TrainSeg(args) => {
            init_tracing();
            seg::train(args)
        }
        Cmd::EvalSeg(args) => {
            init_tracing();
            seg::eval(args)
        }
        Cmd::SegPost(args) => {
            init_tracing();
            seg::set_post(args)
        }
        Cmd::VerifyReport(args) => verify_report::run(args),
        Cmd::PlotRuns(args) => curves::run(args),
        Cmd::ExportWeights(args) => weights::run(args),
        Cmd::AverageWeights(args) => weights::average(args),
        Cmd::FitClutterCalibration(args) => clutter_calibration::run(args),
        Cmd::Symmetries(args) => {
            init_tracing();
            symmetries::run(args)
        }
    });
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Logs to stderr; `RUST_LOG` overrides the default `info` level.
fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("xtask lives in the workspace root")
        .to_path_buf()
}

fn cargo(args: &[&str]) -> Result<()> {
    eprintln!("== cargo {}", args.join(" "));
    let status = Command::new(env!("CARGO"))
        .current_dir(workspace_root())
        .args(args)
        .status()
        .context("running cargo")?;
    if !status.success() {
        bail!("cargo {} failed ({status})", args.join(" "));
    }
    Ok(())
}

/// The features `cargo xtask test` builds the workspace with: ic_render's wgpu backend (off
/// by default; its tests fail without an adapter, and CI has Mesa's lavapipe). Every build of
/// the test command (xtask itself, the tests, the Python wheel, the `incontext` binary of the
/// Python tests and the quick bench) resolves this one feature set, so none compiles a
/// dependency again with other features (a separate `cargo test -p ic_render --features gpu`
/// resolved its own graph and recompiled ≈ 95 packages, 4–6.5 minutes of CI on 2 cores).
/// Pinned by the test `xtask_and_python_builds_resolve_the_features_of_the_workspace_tests`,
/// which also checks that `python/tests/conftest.py` names the same features.
pub(crate) const TEST_FEATURES: &str = "ic_render/gpu";

fn test() -> Result<()> {
    // The gates first: formatting, then clippy on every target with warnings as errors (the
    // workspace lints of Cargo.toml included).
    cargo(&["fmt", "--all", "--check"])?;
    cargo(&[
        "clippy",
        "--workspace",
        "--all-targets",
        "--",
        "-D",
        "warnings",
    ])?;
    // Clippy above checks the default build (the wgpu backend off, as users build); the tests
    // run with it on (`TEST_FEATURES`), so its tests run in the same build as every other.
    cargo(&[
        "test",
        "--workspace",
        "--all-targets",
        "--features",
        TEST_FEATURES,
    ])?;
    cargo(&["test", "--workspace", "--doc", "--features", TEST_FEATURES])?;
    python_tests()?;
    // The small accuracy/speed bench (about 11 min on 2 cores: our methods on the small case
    // sets, then the clutter and IC-BIN scenes), so `cargo xtask bench` and
    // `incontext eval --cases` cannot rot; writes under target/bench-quick/ only.
    if std::env::var_os("INCONTEXT_SKIP_BENCH").is_some() {
        eprintln!("== INCONTEXT_SKIP_BENCH is set: skipping `cargo xtask bench --quick`");
        return Ok(());
    }
    let quick_bench = ["run", "-p", "xtask", "--", "bench", "--quick", "--strict"];
    cargo(&quick_bench)
}

/// The Python module (python/): a fresh venv under target/py-venv with the pinned tools of
/// python/requirements-test.txt, the wheel built by maturin in the dev profile (the profile of
/// the cargo tests above, so their artifacts are reused) and installed, then
/// `pytest python/tests`. A missing Python fails the step; set INCONTEXT_PYTHON to choose the
/// interpreter (default `python3`).
fn python_tests() -> Result<()> {
    let root = workspace_root();
    let python = std::env::var("INCONTEXT_PYTHON").unwrap_or_else(|_| "python3".into());
    let venv = root.join("target/py-venv");
    let wheels = root.join("target/py-wheels");
    let run = |program: &Path, args: &[&str]| -> Result<()> {
        eprintln!("== {} {}", program.display(), args.join(" "));
        let status = Command::new(program)
            .current_dir(&root)
            .args(args)
            .env("CARGO", env!("CARGO"))
            .status()
            .with_context(|| format!("running {}", program.display()))?;
        if !status.success() {
            bail!("{} {} failed ({status})", program.display(), args.join(" "));
        }
        Ok(())
    };
    let version = Command::new(&python).arg("--version").output();
    match version {
        Ok(o) if o.status.success() => {}
        _ => bail!(
            "the Python tests need Python 3.9 or later with venv and pip: `{python}` was not \
             found or does not run (install python3 and python3-venv, or set INCONTEXT_PYTHON)"
        ),
    }
    // A fresh venv each run: nothing left from an earlier one can hide a missing dependency.
    for dir in [&venv, &wheels] {
        if dir.exists() {
            std::fs::remove_dir_all(dir)
                .with_context(|| format!("removing the old {}", dir.display()))?;
        }
    }
    let venv_s = venv.to_string_lossy().into_owned();
    run(Path::new(&python), &["-m", "venv", &venv_s])?;
    let bin = venv.join("bin");
    let py = bin.join("python");
    let pip_install = |args: &[&str]| {
        let mut all = vec![
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
        ];
        all.extend_from_slice(args);
        run(&py, &all)
    };
    pip_install(&["-r", "python/requirements-test.txt"])?;
    let py_s = py.to_string_lossy().into_owned();
    let wheels_s = wheels.to_string_lossy().into_owned();
    run(
        &bin.join("maturin"),
        &[
            "build",
            "--profile",
            "dev",
            "--features",
            TEST_FEATURES,
            "--manifest-path",
            "python/Cargo.toml",
            "--interpreter",
            &py_s,
            "--out",
            &wheels_s,
        ],
    )?;
    let wheel = std::fs::read_dir(&wheels)
        .with_context(|| format!("listing {}", wheels.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .find(|p| p.extension().is_some_and(|e| e == "whl"))
        .with_context(|| format!("maturin wrote no wheel into {}", wheels.display()))?;
    let wheel_s = wheel.to_string_lossy().into_owned();
    pip_install(&[&wheel_s])?;
    run(&py, &["-m", "pytest", "python/tests", "-q"])
}

/// The criterion benchmarks (`cargo xtask bench --criterion [NAME…]`).
fn criterion_bench(names: &[String]) -> Result<()> {
    let root = workspace_root();
    let selected: Vec<(&str, &str)> = if names.is_empty() {
        BENCHES
            .iter()
            .copied()
            .filter(|(name, _)| root.join("benches").join(format!("{name}.rs")).exists())
            .collect()
    } else {
        names
            .iter()
            .map(|n| {
                BENCHES
                    .iter()
                    .copied()
                    .find(|(b, _)| b == n)
                    .with_context(|| {
                        format!(
                            "unknown benchmark {n:?}; known: {}",
                            BENCHES.iter().map(|b| b.0).collect::<Vec<_>>().join(", ")
                        )
                    })
            })
            .collect::<Result<_>>()?
    };
    for (name, package) in &selected {
        cargo(&["bench", "-p", package, "--bench", name])?;
    }
    summarise(
        &root.join("target/criterion"),
        &root.join("target/bench-summary.json"),
    )
}

/// Reads every `target/criterion/<group>/<bench>/new/estimates.json` and prints medians, with
/// the ratio to the `baseline/*` benchmark of the same run.
fn summarise(criterion_dir: &Path, out: &Path) -> Result<()> {
    let mut rows = Vec::new();
    for estimates in find_estimates(criterion_dir)? {
        let text = std::fs::read_to_string(&estimates)
            .with_context(|| format!("reading {}", estimates.display()))?;
        let json: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("parsing {}", estimates.display()))?;
        let median_ns = json["median"]["point_estimate"]
            .as_f64()
            .with_context(|| format!("{}: no median", estimates.display()))?;
        let id = estimates
            .parent()
            .and_then(Path::parent)
            .and_then(|p| p.strip_prefix(criterion_dir).ok())
            .unwrap_or(Path::new("?"));
        rows.push((id.display().to_string(), median_ns));
    }
    rows.sort_by(|a, b| a.0.cmp(&b.0));
    let baseline = rows
        .iter()
        .find(|r| r.0.starts_with("baseline"))
        .map(|r| r.1);
    println!("{:<48} {:>14} {:>12}", "benchmark", "median", "× baseline");
    let mut json_rows = Vec::new();
    for (id, ns) in &rows {
        let ratio = baseline.map(|b| ns / b);
        println!(
            "{:<48} {:>14} {:>12}",
            id,
            human(*ns),
            ratio.map_or("-".into(), |r| format!("{r:.1}"))
        );
        json_rows.push(
            serde_json::json!({"benchmark": id, "median_ns": ns, "ratio_to_baseline": ratio}),
        );
    }
    let tmp = out.with_extension("json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(&json_rows)?)?;
    std::fs::rename(&tmp, out)?;
    eprintln!("summary written to {}", out.display());
    Ok(())
}

fn find_estimates(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut found = Vec::new();
    if !dir.exists() {
        return Ok(found);
    }
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).with_context(|| format!("listing {}", d.display()))? {
            let path = entry?.path();
            if path.is_dir() {
                stack.push(path);
            } else if path.file_name().is_some_and(|n| n == "estimates.json")
                && path.parent().is_some_and(|p| p.ends_with("new"))
            {
                found.push(path);
            }
        }
    }
    Ok(found)
}

fn human(ns: f64) -> String {
    match ns {
        n if n >= 1e9 => format!("{:.3} s", n / 1e9),
        n if n >= 1e6 => format!("{:.3} ms", n / 1e6),
        n if n >= 1e3 => format!("{:.3} µs", n / 1e3),
        n => format!("{n:.0} ns"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::{BTreeMap, BTreeSet};

    fn runs_long(args: &[&str]) -> bool {
        Cli::try_parse_from(std::iter::once("xtask").chain(args.iter().copied()))
            .unwrap()
            .command
            .runs_long()
    }

    #[test]
    fn training_evaluation_and_the_full_bench_with_its_speed_stage_run_long() {
        assert!(runs_long(&["bench", "--peers"]));
        assert!(!runs_long(&["bench", "--quick"]), "CI's quick run stays");
        assert!(
            !runs_long(&["bench", "--no-speed"]),
            "nothing timed in process"
        );
        assert!(
            !runs_long(&["bench", "--criterion"]),
            "cargo bench's own profile"
        );
        assert!(
            !runs_long(&["bench", "pose"]),
            "naming a criterion benchmark"
        );
        assert!(runs_long(&["train-seg", "--objects", "o", "--out", "x"]));
        assert!(runs_long(&["gen-data", "--out", "x"]));
        assert!(!runs_long(&["test"]));
    }

    /// Each package's features as `cargo tree` resolves them for `args`
    /// (`name@version` → features).
    fn resolved_features(args: &[&str]) -> BTreeMap<String, BTreeSet<String>> {
        let out = Command::new(env!("CARGO"))
            .current_dir(workspace_root())
            .args(["tree", "--prefix", "none", "--format", "{p} {f}"])
            .args(args)
            .output()
            .expect("running cargo tree");
        assert!(
            out.status.success(),
            "cargo tree {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let mut features: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for line in String::from_utf8_lossy(&out.stdout).lines() {
            let mut words = line.split_whitespace();
            let (Some(name), Some(version)) = (words.next(), words.next()) else {
                continue;
            };
            // After the version: the path of a local package, `(proc-macro)`, the features
            // (comma-separated, no spaces) and `(*)` for a repeated entry.
            let listed = words
                .filter(|w| !w.starts_with('('))
                .flat_map(|w| w.split(','))
                .map(str::to_owned);
            features
                .entry(format!("{name}@{version}"))
                .or_default()
                .extend(listed);
        }
        features
    }

    /// `cargo xtask test` builds xtask, then every test of the workspace (with `TEST_FEATURES`),
    /// then the Python wheel and (for the Python tests and the quick bench) the `incontext`
    /// binary, the last two with `TEST_FEATURES` too:
    /// a dependency the later builds resolve with other features is compiled again with
    /// everything above it (≈ 6 minutes of CI on 2 cores when libc's features differed). The
    /// feature-unification entries of xtask's and the Python module's `Cargo.toml` keep the
    /// three graphs alike; a dependency update that adds a feature to one of them fails here,
    /// naming the package.
    #[test]
    fn xtask_and_python_builds_resolve_the_features_of_the_workspace_tests() {
        // The Python tests' binary names the same features (or pytest would rebuild it).
        let conftest = workspace_root().join("python/tests/conftest.py");
        let text = std::fs::read_to_string(&conftest).expect("reading python/tests/conftest.py");
        assert!(
            text.contains(&format!("TEST_FEATURES = \"{TEST_FEATURES}\"")),
            "{}: TEST_FEATURES must be {TEST_FEATURES:?}, as xtask's",
            conftest.display()
        );
        let features = ["--features", TEST_FEATURES];
        let tests = resolved_features(
            &[
                &["--workspace", "--edges", "normal,build,dev"][..],
                &features,
            ]
            .concat(),
        );
        for (build, args) in [
            ("xtask", vec!["-p", "xtask", "--edges", "normal,build"]),
            // The bench's and the Python tests' `cargo build --workspace --bin incontext`.
            (
                "the workspace's binaries",
                [&["--workspace", "--edges", "normal,build"][..], &features].concat(),
            ),
            (
                "the Python wheel",
                [
                    &["-p", "incontext-python", "--edges", "normal,build"][..],
                    &features,
                ]
                .concat(),
            ),
        ] {
            let args = &args[..];
            let this = resolved_features(args);
            assert!(this.len() > 100, "{build}: {} packages", this.len());
            let differ: Vec<String> = this
                .iter()
                .filter_map(|(package, f)| {
                    let t = tests.get(package)?;
                    (t != f).then(|| {
                        format!(
                            "{package}: {build} {:?}, tests {:?}",
                            f.iter().collect::<Vec<_>>(),
                            t.iter().collect::<Vec<_>>()
                        )
                    })
                })
                .collect();
            assert!(
                differ.is_empty(),
                "{build} resolves other features than `cargo test --workspace --features \
                 {TEST_FEATURES}`; add them to its Cargo.toml's feature-unification entries:\n{}",
                differ.join("\n")
            );
        }
    }
}
