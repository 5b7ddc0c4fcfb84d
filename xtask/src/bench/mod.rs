//! `cargo xtask bench`: accuracy and speed of our methods beside Open3D's, on fixed case sets,
//! written up as `docs/results.md` and `docs/results.json` (issue 7).
//!
//! 1. cases — the object-alone and room test sets exported from the blob test split (ids
//!    800–999) with a fixed seed into `<work>/cases-{noback,room}` (`cases`; reused when
//!    the manifest matches);
//! 2. ours — `incontext eval --cases DIR --method M --out FILE` for the four methods, and on the
//!    room set the same with `--gt-mask` (the upper bound) when the CLI has it (`run`);
//! 3. peers (`--peers`) — `benches/peers/open3d_peers.py` on the same folders, and its timing
//!    mode; `benches/peers/ppf_peers.py` (OpenCV's point-pair features) on the first
//!    `--ppf-cases` cases of each folder (about 10 s a case, some take minutes), and its timing
//!    mode;
//! 4. speed — registration time at 512/1024/2048 points, segmentation at 640×480, renderer
//!    views/s and training pairs/hour, measured in this process (`speed`);
//! 5. report — every JSONL file scored by `ic_eval::cases`, tables, accuracy plots, the
//!    machine and the command (`report`: `markdown`, `json`).
//!
//! `--quick` is the small version CI can afford (20 + 10 cases, 3 clutter scenes, the first
//! 2 real frames of each folder, written under `target/bench-quick/`). `--criterion [NAMES]`
//! (or just `cargo xtask bench NAME`) runs the criterion benchmarks of `benches/` instead, as
//! before.
//!
//! This module is the one entry point (`bench::run`, called by `main`). Its modules depend one way, each only on those
//! listed before it: `common` (progress bars, paths, atomic writes) ← `cases` ← `run` ← `speed`
//! ← `report` (`report::machine` ← `report` ← `report::markdown`, `report::json`).

pub mod cases;
pub mod common;
pub mod curve;
pub mod report;
pub mod run;
pub mod scenes;
pub mod speed;

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Result, bail};
use clap::Args;

use cases::{CaseSet, Objects, Set};
use common::rel;
use report::{Config, Report};
use run::{MethodRun, RunStatus};

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Criterion benchmarks to run (file stems under benches/); naming any implies --criterion.
    pub names: Vec<String>,
    /// Run the criterion benchmarks (all, or NAMES) and print medians with ratios to the in-run
    /// baseline (target/bench-summary.json), instead of the accuracy and speed bench.
    #[arg(long)]
    pub criterion: bool,
    /// The small version (20 object-alone cases, 10 room scenes, 2 timing repeats) that CI
    /// runs; writes under target/bench-quick/ instead of docs/.
    #[arg(long)]
    pub quick: bool,
    /// Also run the Open3D and OpenCV PPF peers (benches/peers; needs target/peers-venv, see its
    /// README).
    #[arg(long)]
    pub peers: bool,
    /// With --peers: OpenCV's PPF methods run on the first N cases of each set only (about 10 s
    /// a case for the three on one core, some objects take minutes; default 100, about 35 min for
    /// both sets; quick 3). 0: every case (about 2.5 h at the default counts).
    #[arg(long)]
    pub ppf_cases: Option<u64>,
    /// With --peers: timing repeats of the PPF methods (default: --repeats, at most 3; quick 1).
    #[arg(long)]
    pub ppf_repeats: Option<usize>,
    /// Where results.md, results.json and results/ (plots) go. Default: docs/, or
    /// target/bench-quick/ with --quick.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Folder for the cases and the raw result files. Default: target/bench, or
    /// target/bench-quick with --quick.
    #[arg(long)]
    pub work: Option<PathBuf>,
    /// Flat folder of object meshes split by id (0–799 train, 800–999 test). Default:
    /// $INCONTEXT_OBJECTS, else ../shared/data/objects/blobs next to the workspace; with --quick,
    /// procedural objects when neither exists.
    #[arg(long)]
    pub objects: Option<PathBuf>,
    /// Seed of the case sets, our CLI's point sampling, the peers' RANSAC and the timing pairs.
    #[arg(long, default_value_t = 2021)]
    pub seed: u64,
    /// Object-alone cases (default 500, quick 20).
    #[arg(long)]
    pub noback_count: Option<u64>,
    /// Room scenes (default 300, quick 10).
    #[arg(long)]
    pub room_count: Option<u64>,
    /// Real-object views (default 500, quick 10; 0 skips the set).
    #[arg(long)]
    pub real_count: Option<u64>,
    /// Clutter scenes of the real objects' test split (default 300, quick 3; 0 skips them):
    /// the clutter segmentation's instances and `register`'s default on every target.
    #[arg(long)]
    pub clutter_count: Option<u64>,
    /// Folder of real sensor frames (subfolders with model.ply, camera.json and depth PNGs),
    /// each registered and judged against its depth map (quick: the first 2 of each folder).
    /// Default: ../shared/data/real next to the workspace, skipped when absent.
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// Folder of real object meshes with its `split.json` (train / val / test) for the real
    /// set and the clutter scenes. Default: ../shared/data/objects/real_objects next to the workspace; the set is
    /// skipped, with a note in the report, when it is absent.
    #[arg(long)]
    pub real_objects: Option<PathBuf>,
    /// Threads for every method, ours and Open3D's, and for the timings.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Timing repeats after one warm-up (default 10, quick 2).
    #[arg(long)]
    pub repeats: Option<usize>,
    /// Object-alone cases each registration time is measured on, ours and Open3D's (one warm-up
    /// and --repeats runs each; the median of their medians; default 10, quick 1). OpenCV PPF is
    /// timed on the first only (seconds to minutes per run).
    #[arg(long)]
    pub timing_pairs: Option<usize>,
    /// Object-alone cases of the accuracy/speed curve of our one-shot pose over point counts
    /// and the DGCNN's k (default 200, quick 5; 0: no curve).
    #[arg(long)]
    pub curve_cases: Option<usize>,
    /// Timed training steps per head (default 5, quick 1).
    #[arg(long)]
    pub train_steps: Option<usize>,
    /// The incontext binary. Default: `cargo build --release -p incontext`, then
    /// target/release/incontext (with --quick: the dev build, target/debug/incontext).
    #[arg(long)]
    pub incontext: Option<PathBuf>,
    /// Python with open3d and opencv-contrib-python-headless. Default:
    /// target/peers-venv/bin/python.
    #[arg(long)]
    pub python: Option<PathBuf>,
    /// Reuse result files of an earlier run that hold a line for every case, instead of
    /// running those methods again.
    #[arg(long)]
    pub resume: bool,
    /// Skip the speed stage.
    #[arg(long)]
    pub no_speed: bool,
    /// Fail (after writing the report) when `incontext eval --cases` is unusable or a method
    /// that could run did not: what CI uses so the bench cannot rot. Methods whose model file is
    /// absent do not count.
    #[arg(long)]
    pub strict: bool,
}

/// Real frames per folder that `--quick` registers (the first in name order).
const QUICK_FRAMES: usize = 2;

fn default_objects(root: &Path, given: Option<&Path>, quick: bool) -> Result<Objects> {
    let candidate = given
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os("INCONTEXT_OBJECTS").map(PathBuf::from))
        .unwrap_or_else(|| root.join("../shared/data/objects/blobs"));
    if candidate.is_dir() {
        return Ok(Objects::Folder(
            candidate.canonicalize().unwrap_or(candidate),
        ));
    }
    if given.is_some() {
        bail!("--objects {}: not a folder", candidate.display());
    }
    if quick {
        tracing::warn!(
            "{} not found: the quick bench uses 200 procedural objects instead of the blobs",
            candidate.display()
        );
        return Ok(Objects::Procedural(200));
    }
    bail!(
        "the blob meshes are not at {} (pass --objects DIR or set INCONTEXT_OBJECTS; \
         /work/shared/data/README.md says how to rebuild them)",
        candidate.display()
    )
}

/// The real set's objects: `given` (an error when it is not a folder with `split.json`), else
/// the shared folder when present; `None` skips the set.
fn real_objects(root: &Path, given: Option<&Path>) -> Result<Option<Objects>> {
    let dir = given
        .map(Path::to_path_buf)
        .unwrap_or_else(|| root.join("../shared/data/objects/real_objects"));
    let split_file = dir.join("split.json");
    if dir.is_dir() && split_file.is_file() {
        let dir = dir.canonicalize().unwrap_or(dir);
        return Ok(Some(Objects::SplitFile {
            split_file: dir.join("split.json"),
            dir,
        }));
    }
    if given.is_some() {
        bail!(
            "--real-objects {}: not a folder holding split.json",
            dir.display()
        );
    }
    Ok(None)
}

pub fn run(args: BenchArgs) -> Result<()> {
    if args.criterion || !args.names.is_empty() {
        return crate::criterion_bench(&args.names);
    }
    // Before any thread exists: candle and rayon read it once.
    crate::pose::set_threads(Some(args.threads));
    crate::init_tracing();
    let started = Instant::now();
    let root = crate::workspace_root();
    let quick = args.quick;
    let objects = default_objects(&root, args.objects.as_deref(), quick)?;
    let real_count = args.real_count.unwrap_or(if quick { 10 } else { 500 });
    let real = if real_count > 0 {
        real_objects(&root, args.real_objects.as_deref())?
    } else {
        None
    };
    let work = args.work.clone().unwrap_or_else(|| {
        root.join(if quick {
            "target/bench-quick"
        } else {
            "target/bench"
        })
    });
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| root.join(if quick { "target/bench-quick" } else { "docs" }));
    let repeats = args.repeats.unwrap_or(if quick { 2 } else { 10 });
    let config = Config {
        quick,
        peers: args.peers,
        seed: args.seed,
        noback_count: args.noback_count.unwrap_or(if quick { 20 } else { 500 }),
        room_count: args.room_count.unwrap_or(if quick { 10 } else { 300 }),
        real_count: if real.is_some() { real_count } else { 0 },
        real_objects: real.as_ref().map(Objects::describe),
        ppf_cases: args.ppf_cases.unwrap_or(if quick { 3 } else { 100 }),
        ppf_repeats: args
            .ppf_repeats
            .unwrap_or(if quick { 1 } else { repeats.min(3) })
            .max(1),
        threads: args.threads.max(1),
        repeats,
        timing_pairs: args.timing_pairs.unwrap_or(if quick { 1 } else { 10 }),
        curve_cases: args.curve_cases.unwrap_or(if quick { 5 } else { 200 }),
        train_steps: args.train_steps.unwrap_or(if quick { 1 } else { 5 }),
        out: out.clone(),
        work: work.clone(),
        objects: objects.describe(),
        speed: !args.no_speed,
        resume: args.resume,
    };
    if config.noback_count == 0 || config.room_count == 0 {
        bail!("--noback-count and --room-count must be ≥ 1");
    }
    if config.timing_pairs == 0 || config.timing_pairs as u64 > config.noback_count {
        bail!(
            "--timing-pairs {}: must be between 1 and the object-alone case count ({})",
            config.timing_pairs,
            config.noback_count
        );
    }
    println!(
        "bench seed {} config {}",
        config.seed,
        serde_json::to_string(&config)?
    );
    let mut report = Report::start(&root, &config);

    // 1. Cases.
    let mut sets: Vec<CaseSet> = Vec::new();
    if real.is_none() {
        report.notes.push(if real_count == 0 {
            "The real-object set was not run (--real-count 0).".into()
        } else {
            format!(
                "The real-object set was skipped: {} is not there (pass --real-objects DIR, a \
                 folder of meshes with split.json).",
                root.join("../shared/data/objects/real_objects").display()
            )
        });
    }
    // The objects of each set.
    let set_objects = |set: Set| -> Option<&Objects> {
        match set {
            Set::Real => real.as_ref(),
            _ => Some(&objects),
        }
    };
    let mut geometry = std::collections::HashMap::new();
    for set in Set::ALL {
        let Some(set_objs) = set_objects(set) else {
            continue;
        };
        let count = match set {
            Set::Noback => config.noback_count,
            Set::Room => config.room_count,
            Set::Real => config.real_count,
        };
        let t0 = Instant::now();
        let dir = work.join(format!("cases-{}", set.name()));
        let cs = cases::ensure(set, set_objs, config.seed, count, &dir, config.threads)?;
        // One cache per corpus: the object-alone and room sets share their objects.
        let cache = work.join(format!("symmetries-{}.json", set_objs.cache_name()));
        geometry.insert(set, cases::geometry(&cs, set_objs, config.seed, &cache)?);
        report.stage(&format!("cases {}", set.name()), t0.elapsed().as_secs_f64());
        sets.push(cs);
    }

    // 2. Ours.
    let mut runs: Vec<MethodRun> = Vec::new();
    let t0 = Instant::now();
    let cli = run::probe_cli(&root, args.incontext.as_deref(), !quick);
    if let Some(why) = &cli.unusable {
        tracing::warn!("our methods will be reported as missing: {why}");
    }
    for cs in &sets {
        let dir = work.join("runs").join(cs.set.name());
        runs.extend(run::run_ours(
            &root,
            &cli,
            cs,
            &dir,
            config.threads,
            config.seed,
            config.resume,
        )?);
    }
    report.stage("ours", t0.elapsed().as_secs_f64());

    // 2b. Whole scenes: clutter, real frames.
    let t0 = Instant::now();
    let clutter_count = args.clutter_count.unwrap_or(if quick { 3 } else { 300 });
    match (&real, clutter_count) {
        (_, 0) => report
            .notes
            .push("The clutter scenes were not run (--clutter-count 0).".into()),
        (None, _) => report.notes.push(
            "The clutter scenes were skipped: they are made of the real objects, which are \
             not there (--real-objects)."
                .into(),
        ),
        (Some(r), n) => {
            report.clutter = Some(scenes::clutter(
                &root,
                &cli,
                r,
                config.seed,
                n,
                &work,
                config.threads,
                config.resume,
            )?)
        }
    }
    let frames_dir = args
        .frames
        .clone()
        .unwrap_or_else(|| root.join("../shared/data/real"));
    if frames_dir.is_dir() {
        // The quick bench registers the first two frames of each folder (in the dev build a
        // frame takes most of a minute): enough that the command cannot rot.
        let limit = quick.then_some(QUICK_FRAMES);
        report.frames = scenes::frames(
            &root,
            &cli,
            &frames_dir,
            config.seed,
            &work,
            config.threads,
            limit,
        )?;
    } else if args.frames.is_some() {
        bail!("--frames {}: not a folder", frames_dir.display());
    } else {
        report.notes.push(format!(
            "The real frames were skipped: {} is not there (--frames).",
            frames_dir.display()
        ));
    }
    report.cli = Some(run::Cli {
        path: rel(&cli.path),
        ..cli
    });
    report.stage("scenes", t0.elapsed().as_secs_f64());

    // 3. Peers.
    let mut python = None;
    let mut ppf_python = None;
    if config.peers {
        let t0 = Instant::now();
        match run::probe_python(&root, args.python.as_deref()) {
            Ok((py, version)) => {
                report.open3d_version = Some(version);
                for cs in &sets {
                    let dir = work.join("runs").join(cs.set.name());
                    runs.extend(run::run_peers(
                        &root,
                        &py,
                        cs,
                        &dir,
                        config.threads,
                        config.seed,
                        config.resume,
                    )?);
                }
                python = Some(py);
            }
            Err(why) => {
                let note = format!(
                    "Open3D peers skipped: {why}. Install them with: {}",
                    run::PEERS_INSTALL
                );
                eprintln!("{note}");
                report.notes.push(note);
                for cs in &sets {
                    for m in run::PEER_METHODS {
                        runs.push(MethodRun {
                            set: cs.set,
                            label: format!("o3d-{m}"),
                            method: format!("o3d-{m}"),
                            peer: true,
                            gt_mask: false,
                            case_limit: None,
                            status: RunStatus::Missing {
                                reason: format!("the peers' Python is not set up ({why})"),
                            },
                        });
                    }
                }
            }
        }
        match run::probe_ppf_python(&root, args.python.as_deref()) {
            Ok((py, version)) => {
                report.opencv_version = Some(version);
                for cs in &sets {
                    let dir = work.join("runs").join(cs.set.name());
                    let limit = if config.ppf_cases == 0 {
                        cs.count
                    } else {
                        config.ppf_cases
                    };
                    let Some(set_objs) = set_objects(cs.set) else {
                        continue;
                    };
                    runs.extend(run::run_ppf(
                        &root,
                        &py,
                        cs,
                        set_objs,
                        &dir,
                        limit,
                        config.threads,
                        config.seed,
                        config.resume,
                    )?);
                }
                if matches!(objects, Objects::Procedural(_)) {
                    report.notes.push(
                        "The objects are procedural (no mesh files): OpenCV PPF's model normals \
                         were estimated on the model points (`--model-normals estimate`), not \
                         taken from the mesh."
                            .into(),
                    );
                }
                ppf_python = Some(py);
            }
            Err(why) => {
                let note = format!(
                    "OpenCV PPF peers skipped: {why}. Install them with: {}",
                    run::PEERS_INSTALL
                );
                eprintln!("{note}");
                report.notes.push(note);
                for cs in &sets {
                    for m in run::PPF_METHODS {
                        runs.push(MethodRun {
                            set: cs.set,
                            label: format!("opencv-{m}"),
                            method: format!("opencv-{m}"),
                            peer: true,
                            gt_mask: false,
                            case_limit: None,
                            status: RunStatus::Missing {
                                reason: format!("the peers' Python has no OpenCV PPF ({why})"),
                            },
                        });
                    }
                }
            }
        }
        report.stage("peers", t0.elapsed().as_secs_f64());
    } else {
        report.notes.push(
            "The Open3D and OpenCV PPF peers were not run (pass --peers): the tables hold our \
             methods only."
                .into(),
        );
    }

    // 4. Speed.
    if config.speed {
        let t0 = Instant::now();
        let (noback, room) = (&sets[0], &sets[1]);
        debug_assert!(noback.set == Set::Noback && room.set == Set::Room);
        let mut measured = speed::measure(
            &root,
            noback,
            room,
            &objects,
            config.seed,
            config.threads,
            config.repeats,
            config.timing_pairs,
            config.train_steps,
        )?;
        if config.curve_cases > 0 {
            // The quick run draws two sizes and two k only.
            let (sizes, ks): (&[(usize, usize)], &[usize]) = if quick {
                (&[(128, 96), (384, 288)], &[8, 16])
            } else {
                (&curve::CURVE_SIZES, &curve::CURVE_K)
            };
            measured.curve = Some(curve::measure(
                &root,
                noback,
                config.seed,
                config.curve_cases,
                config.timing_pairs,
                config.repeats,
                sizes,
                ks,
            )?);
        }
        report.speed = Some(measured);
        if let Some(py) = &python {
            let file = work.join("runs/open3d-timing.json");
            match run::run_peer_timing(
                &root,
                py,
                noback,
                &file,
                &speed::SIZES,
                config.repeats,
                config.timing_pairs,
                config.threads,
                config.seed,
            ) {
                Ok(v) => report.open3d_timing = Some(v),
                Err(e) => {
                    tracing::error!("Open3D timing failed: {e}");
                    report.notes.push(format!("Open3D timing failed: {e}"));
                }
            }
        }
        if let Some(py) = &ppf_python {
            let file = work.join("runs/ppf-timing.json");
            match run::run_ppf_timing(
                &root,
                py,
                noback,
                &objects,
                &file,
                &speed::SIZES,
                config.ppf_repeats,
                config.threads,
                config.seed,
            ) {
                Ok(v) => report.ppf_timing = Some(v),
                Err(e) => {
                    tracing::error!("OpenCV PPF timing failed: {e}");
                    report.notes.push(format!("OpenCV PPF timing failed: {e}"));
                }
            }
        }
        report.stage("speed", t0.elapsed().as_secs_f64());
    }

    // 5. Score and write.
    let t0 = Instant::now();
    report.score(&sets, runs, &geometry)?;
    report.stage("score", t0.elapsed().as_secs_f64());
    report.total_seconds = started.elapsed().as_secs_f64();
    // results.md (with its plots), then results.json; listed md, json, plots.
    let mut written = report::markdown::write(&report, &out)?;
    written.insert(1, report::json::write(&report, &out)?);
    for set in &report.sets {
        println!("\n## {} ({} cases)\n", set.set.title(), set.count);
        println!("{}", ic_eval::cases::markdown_cases_table(&set.scores));
        for m in &set.missing {
            println!("- {}: {}", m.0, m.1);
        }
    }
    let problems = strict_problems(&report);
    for p in &problems {
        eprintln!("bench problem: {p}");
    }
    if args.strict && !problems.is_empty() {
        bail!(
            "--strict: {} problem(s) (listed above; the report was written)",
            problems.len()
        );
    }
    println!(
        "\nbench took {:.0} s; wrote {}",
        report.total_seconds,
        written
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(())
}

/// What `--strict` refuses: an unusable CLI, a method that failed to run or to be scored,
/// peers that were asked for and could not run, a set without any of our results, a clutter
/// measurement that failed (other than for an absent network or the unusable CLI).
fn strict_problems(report: &Report) -> Vec<String> {
    let mut out = Vec::new();
    let unusable = report.cli.as_ref().and_then(|c| c.unusable.as_ref());
    if let Some(why) = unusable {
        out.push(why.clone());
    }
    if let Some(c) = &report.clutter {
        let mut parts = vec![
            ("clutter segmentation".to_string(), &c.segmentation),
            (
                "clutter segmentation, shadowed".to_string(),
                &c.segmentation_shadowed,
            ),
        ];
        for (camera, result) in &c.segmentation_cameras {
            parts.push((format!("clutter segmentation, {camera}"), result));
        }
        parts.push(("clutter pipeline".to_string(), &c.pipeline));
        for (label, result) in parts {
            if let Err(why) = result
                && !why.ends_with(" is absent")
                && unusable.is_none_or(|u| u != why)
            {
                out.push(format!("{label}: {why}"));
            }
        }
    }
    for set in &report.sets {
        for (label, reason) in &set.missing {
            let absent_model = reason.starts_with("not run:") && reason.contains(" is absent");
            let cli_reason = report
                .cli
                .as_ref()
                .and_then(|c| c.unusable.as_ref())
                .is_some_and(|w| reason.contains(w.as_str()));
            if !absent_model && !cli_reason {
                out.push(format!("{} on {}: {reason}", label, set.set.name()));
            }
        }
        if !set.scores.iter().any(|m| m.method().starts_with("ours-")) {
            out.push(format!("no result of ours on the {} set", set.set.name()));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::report::{Config, Report};
    use crate::bench::scenes::ClutterReport;

    fn clutter(
        segmentation: Result<serde_json::Value, String>,
        shadowed: Result<serde_json::Value, String>,
        pipeline: Result<serde_json::Value, String>,
    ) -> Report {
        let tmp = tempfile::tempdir().unwrap();
        let mut report = Report::start(&crate::workspace_root(), &Config::for_tests(tmp.path()));
        report.clutter = Some(ClutterReport {
            scenes: 3,
            dir: "clutter-data".into(),
            segmentation_cameras: vec![("16:9".into(), segmentation.clone())],
            segmentation,
            segmentation_shadowed: shadowed,
            pipeline,
            pipeline_reused: false,
            seconds: 1.0,
        });
        report
    }

    #[test]
    fn strict_refuses_a_failed_clutter_measurement_but_not_an_absent_network() {
        let ok = || Ok(serde_json::json!({"images": 3}));
        assert!(strict_problems(&clutter(ok(), ok(), ok())).is_empty());
        let absent = || Err(format!("{} is absent", scenes::CLUTTER_SEG_MODEL));
        assert!(strict_problems(&clutter(absent(), absent(), ok())).is_empty());
        let problems = strict_problems(&clutter(
            ok(),
            Err("scene 2: no object could be placed".into()),
            ok(),
        ));
        assert_eq!(
            problems,
            vec!["clutter segmentation, shadowed: scene 2: no object could be placed".to_string()]
        );
        let problems = strict_problems(&clutter(ok(), ok(), Err("exit 2: bad dataset".into())));
        assert_eq!(
            problems,
            vec!["clutter pipeline: exit 2: bad dataset".to_string()]
        );
        // A camera's measurement that failed is refused too, named by its camera.
        let mut report = clutter(ok(), ok(), ok());
        if let Some(c) = &mut report.clutter {
            c.segmentation_cameras[0].1 = Err("scene 1: no object could be placed".into());
        }
        assert_eq!(
            strict_problems(&report),
            vec!["clutter segmentation, 16:9: scene 1: no object could be placed".to_string()]
        );
    }
}
