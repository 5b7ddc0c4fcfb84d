//! Stage 2b of `cargo xtask bench`: whole scenes, where the object is to be found before it is
//! registered.
//!
//! - **Clutter** (the real-clutter issue's benchmark): `--clutter-count` scenes of the
//!   `real_objects` test objects (tables, bins and shelves with 3–15 objects, the sensor model
//!   on; `ic_data::clutter` as `gen-data --clutter-count` writes them, a BOP dataset under
//!   `<work>/clutter-data/`). The shipped clutter segmentation network is scored on every
//!   object's instance (`ic_train::seg::scene_instances`: target found, recall, matched IoU,
//!   over- and under-segmentation), once on the scenes as the benchmark's sensor draws them and
//!   once on the same scenes with the projector's shadows and the registration's holes in every
//!   one (`ClutterConfig::with_shadows(1.0)`: those draws come last, so the scenes are the same
//!   but for the bands without a return that real structured-light maps have), and once
//!   through each of [`OTHER_CAMERAS`] (a 16:9 and a wide one: the same scenes, another
//!   image), and `incontext eval --dataset` runs `register`'s default method on every target (ADD-S to the
//!   nearest true instance, rotation, time).
//! - **Real frames** (`../shared/data/real/*/`, no ground truth): `incontext eval --frames`
//!   registers each frame as `register` and `register --all` do and judges each pose by
//!   rendering it against the depth map (agreement within 10 mm, pixels in front).
//!
//! Nothing here is a case folder: the results are the commands' own summaries, kept as JSON.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use ic_data::clutter::{ClutterConfig, ClutterGenerator};
use ic_data::{Corpus, Split};
use serde_json::{Value, json};

use crate::bench::cases::{Objects, clear_partial, install_partial, read_json};
use crate::bench::run::Cli;

/// The clutter segmentation network the pipeline runs by default.
pub const CLUTTER_SEG_MODEL: &str = "models/seg-clutter.safetensors";

/// The method of the clutter benchmark: `register`'s default.
pub const CLUTTER_METHOD: &str = "ours-softmax-verify";

/// The scenes of the benchmark: `gen-data --clutter-count`'s (the target's copies listed,
/// every object's full mask kept, objects at their fixed real sizes).
fn clutter_config() -> ClutterConfig {
    ClutterConfig {
        fixed_sizes: true,
        full_masks: true,
        ..ClutterConfig::default()
    }
}

/// The other cameras the clutter network is also scored through, on the same scenes (their
/// geometry and camera pose kept; the network's input sized from each camera, `docs/decisions.md`,
/// "Any camera"): label, width, height, fx, fy (pixels; the principal point centred).
pub const OTHER_CAMERAS: [(&str, u32, u32, f64, f64); 2] = [
    (
        "16:9 RealSense-like, 1280×720, fx 640",
        1280,
        720,
        640.0,
        640.0,
    ),
    (
        "wide Kinect v2-like, 512×424, fx 365",
        512,
        424,
        365.0,
        365.0,
    ),
];

/// The clutter benchmark's results.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ClutterReport {
    pub scenes: u64,
    pub dir: PathBuf,
    /// `ic_eval::instances::InstanceSummary` of the clutter network, or why it is missing.
    pub segmentation: Result<Value, String>,
    /// The same on the same scenes with the projector's shadows and the registration's holes
    /// in every one, or why it is missing.
    pub segmentation_shadowed: Result<Value, String>,
    /// The same on the same scenes seen through each of [`OTHER_CAMERAS`] (its label), or why
    /// it is missing.
    pub segmentation_cameras: Vec<(String, Result<Value, String>)>,
    /// The `incontext --json eval --dataset` report (its `datasets.clutter.results`), or why
    /// it is missing.
    pub pipeline: Result<Value, String>,
    /// Whether `pipeline` was read back from an earlier run's `runs/clutter.json` (`--resume`)
    /// instead of run again.
    pub pipeline_reused: bool,
    pub seconds: f64,
}

/// One folder of real frames and `incontext eval --frames`' summary.
#[derive(Clone, Debug, serde::Serialize)]
pub struct FramesReport {
    pub name: String,
    pub dir: PathBuf,
    pub summary: Result<Value, String>,
}

/// `incontext` with the bench's seed and threads.
fn incontext(root: &Path, cli: &Cli, seed: u64, threads: usize) -> Command {
    let mut cmd = Command::new(&cli.path);
    cmd.current_dir(root)
        .env("RAYON_NUM_THREADS", threads.to_string())
        .stdin(Stdio::null());
    cmd.args(["--json", "--seed", &seed.to_string()]);
    cmd.args(["--threads", &threads.to_string()]);
    cmd
}

/// Runs `cmd`, its stderr to `log`; its stdout parsed as JSON.
fn run_json(mut cmd: Command, log: &Path) -> Result<Value, String> {
    let err = std::fs::File::create(log).map_err(|e| format!("{}: {e}", log.display()))?;
    let out = cmd
        .stderr(err)
        .output()
        .map_err(|e| format!("cannot start {:?}: {e}", cmd.get_program()))?;
    if !out.status.success() {
        let tail: String = std::fs::read_to_string(log)
            .unwrap_or_default()
            .lines()
            .rev()
            .take(5)
            .collect::<Vec<_>>()
            .join(" / ");
        return Err(format!("exit {}: {tail}", out.status));
    }
    serde_json::from_slice(&out.stdout).map_err(|e| format!("its JSON on stdout: {e}"))
}

/// Writes (or reuses: the same manifest) the clutter scenes as a BOP dataset under `dir`.
fn ensure_clutter_data(
    objects: &Objects,
    seed: u64,
    count: u64,
    dir: &Path,
    workers: usize,
) -> Result<()> {
    let Objects::SplitFile {
        dir: meshes,
        split_file,
    } = objects
    else {
        bail!("the clutter scenes need a mesh folder with split.json");
    };
    let want = json!({"seed": seed, "count": count, "objects": objects.describe(), "config": clutter_config()});
    if read_json(&dir.join("bench-manifest.json")).as_ref() == Some(&want)
        && dir.join("clutter/test_targets_bop19.json").is_file()
    {
        tracing::info!(dir = %dir.display(), "reusing the clutter scenes");
        return Ok(());
    }
    let partial = clear_partial(dir)?;
    crate::data::gen_data(crate::data::GenDataArgs {
        corpus: crate::data::CorpusArgs {
            objects: Some(meshes.clone()),
            split: "test".into(),
            train_ids: "0-799".into(),
            test_ids: "800-999".into(),
            split_file: Some(split_file.clone()),
            procedural: 0,
            strict: false,
        },
        out: partial.clone(),
        seed,
        noback_count: 0,
        room_count: 0,
        clutter_count: count,
        shadow_probability: 0.0,
        camera: None,
        workers: Some(workers),
    })?;
    install_partial(&partial, dir, &want)
}

/// The clutter network's instances against every object's on the same scenes; with
/// `shadows`, every scene also has the projector's shadows and the registration's holes; with
/// `camera`, the scenes are seen through it instead of the benchmark's camera.
fn clutter_segmentation(
    root: &Path,
    corpus: Arc<Corpus>,
    seed: u64,
    count: u64,
    shadows: bool,
    camera: Option<ic_geometry::Intrinsics>,
) -> Result<Value> {
    let seg = ic_seg::Segmenter::load(&root.join(CLUTTER_SEG_MODEL))
        .with_context(|| format!("loading {CLUTTER_SEG_MODEL}"))?;
    let mut config = clutter_config().with_shadows(if shadows { 1.0 } else { 0.0 });
    if let Some(k) = camera {
        config = config.with_camera(k);
    }
    let g = ClutterGenerator::new(corpus, config, seed)?;
    let label = match (shadows, camera) {
        (_, Some(k)) => format!("clutter segmentation, {}×{} camera", k.width, k.height),
        (true, None) => "clutter segmentation, shadowed".into(),
        (false, None) => "clutter segmentation".into(),
    };
    let bar = crate::bench::common::progress_bar(count, &label);
    let mut matches = Vec::new();
    for i in 0..count {
        let scene = g.scene(i)?;
        matches.push(ic_train::seg::scene_instances(&seg, &scene)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(serde_json::to_value(ic_eval::instances::summarise(
        &matches,
    ))?)
}

/// The clutter benchmark (see the module documentation). A part that cannot run is reported
/// with the reason; only the scenes' export is fatal.
#[allow(clippy::too_many_arguments)]
pub fn clutter(
    root: &Path,
    cli: &Cli,
    objects: &Objects,
    seed: u64,
    count: u64,
    work: &Path,
    threads: usize,
    resume: bool,
) -> Result<ClutterReport> {
    let t0 = Instant::now();
    let dir = work.join("clutter-data");
    ensure_clutter_data(objects, seed, count, &dir, threads)?;
    let (segmentation, segmentation_shadowed, segmentation_cameras) =
        if root.join(CLUTTER_SEG_MODEL).is_file() {
            let corpus = Arc::new(objects.corpus(Split::Test, seed)?);
            let run = |shadows, camera| {
                clutter_segmentation(root, corpus.clone(), seed, count, shadows, camera)
                    .map_err(|e| format!("{e:#}"))
            };
            let cameras = OTHER_CAMERAS
                .iter()
                .map(|&(label, w, h, fx, fy)| {
                    let k =
                        ic_geometry::Intrinsics::centred(w, h, fx, fy).map_err(|e| e.to_string());
                    (label.to_string(), k.and_then(|k| run(false, Some(k))))
                })
                .collect();
            (run(false, None), run(true, None), cameras)
        } else {
            let why = format!("{CLUTTER_SEG_MODEL} is absent");
            let cameras = OTHER_CAMERAS
                .iter()
                .map(|c| (c.0.to_string(), Err(why.clone())))
                .collect();
            (Err(why.clone()), Err(why), cameras)
        };
    let runs = work.join("runs/clutter");
    let saved = work.join("runs/clutter.json");
    let earlier = resume.then(|| read_json(&saved)).flatten();
    let pipeline_reused = cli.unusable.is_none() && earlier.is_some();
    let pipeline = match (&cli.unusable, earlier) {
        (Some(why), _) => Err(why.clone()),
        (None, Some(v)) => {
            tracing::info!(file = %saved.display(), "reusing the clutter pipeline's results");
            Ok(v)
        }
        (None, None) => {
            std::fs::create_dir_all(work.join("runs"))?;
            eprintln!("== clutter: incontext eval --dataset ({count} scenes, {CLUTTER_METHOD})");
            let mut cmd = incontext(root, cli, seed, threads);
            cmd.arg("eval")
                .arg("--dataset")
                .arg(dir.join("clutter"))
                .args(["--method", CLUTTER_METHOD])
                .arg("--out")
                .arg(&runs);
            let r = run_json(cmd, &work.join("runs/clutter.log"));
            if let Ok(v) = &r {
                crate::bench::common::write_atomic(&saved, serde_json::to_string(v)?.as_bytes())?;
            }
            r
        }
    };
    Ok(ClutterReport {
        scenes: count,
        dir: crate::bench::common::rel(&dir),
        segmentation,
        segmentation_shadowed,
        segmentation_cameras,
        pipeline,
        pipeline_reused,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// `incontext eval --frames` on every folder of `real` holding `model.ply` (sorted by name);
/// with `limit`, on the first frames of each (`eval --frames --limit`).
pub fn frames(
    root: &Path,
    cli: &Cli,
    real: &Path,
    seed: u64,
    work: &Path,
    threads: usize,
    limit: Option<usize>,
) -> Result<Vec<FramesReport>> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(real)
        .with_context(|| format!("listing {}", real.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("model.ply").is_file())
        .collect();
    dirs.sort();
    let mut out = Vec::new();
    for dir in dirs {
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let summary = match &cli.unusable {
            Some(why) => Err(why.clone()),
            None => {
                eprintln!("== frames {name}: incontext eval --frames");
                let out_dir = work.join("runs").join(format!("frames-{name}"));
                std::fs::create_dir_all(work.join("runs"))?;
                let mut cmd = incontext(root, cli, seed, threads);
                cmd.arg("eval")
                    .arg("--frames")
                    .arg(&dir)
                    .arg("--out")
                    .arg(&out_dir);
                if let Some(n) = limit {
                    cmd.arg("--limit").arg(n.to_string());
                }
                run_json(cmd, &work.join("runs").join(format!("frames-{name}.log")))
            }
        };
        out.push(FramesReport {
            name,
            dir: dir.clone(),
            summary,
        });
    }
    Ok(out)
}
