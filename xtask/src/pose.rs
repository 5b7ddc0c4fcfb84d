//! `cargo xtask train-pose` and `cargo xtask eval-pose`: training and evaluation of the
//! `ic_pose` network on object-alone samples rendered on the fly by `ic_data`.
//!
//! Objects (`--objects`): one folder or a weighted mixture of folders and procedural objects
//! (see [`crate::data::ObjectsSpec`]). A folder with `split.json` uses its `train`/`val`/`test`
//! lists; a folder of numeric stems (the blobs) uses 000–749 train, 750–799 val (the fixed
//! validation set that picks the best checkpoint), 800–999 test (left untouched for
//! `eval-pose`). `--protocol paper` (default) samples as the paper; `--protocol deployment`
//! as deployment (`ic_data::ObjectSampleConfig::deployment`); validation uses the same
//! protocol on the `val` objects.

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::data::ObjectsSpec;
use crate::run;
use anyhow::{Context, Result, bail};
use ic_data::{
    CorpusOptions, ObjectSample, ObjectSampleConfig, ObjectSampleGenerator, Prefetcher,
    SamplingProtocol, Split,
};
use ic_pose::{Head, PoseConfig, PoseEstimator, Refine, Trainer};
use indicatif::ProgressBar;

/// Seed of the validation sample stream (fixed whatever the run's seed).
const VALIDATION_SEED: u64 = 0x7661_6c69;

#[derive(clap::Args)]
pub struct TrainArgs {
    /// `cpu` (≈ 1.5 h on one core) or `paper` (GPU, `cuda` feature); `tiny` for smoke tests.
    /// Ignored with `--init` (the configuration comes from the checkpoint).
    #[arg(long, default_value = "cpu")]
    preset: String,
    /// `softmax` (default) or `ot`; with `--init`, must match the checkpoint's head if given.
    #[arg(long)]
    head: Option<String>,
    /// A folder (`split.json`, or numeric stems split as the blobs) or a weighted mixture,
    /// e.g. `real=../shared/data/objects/real_objects:0.6,blobs=../shared/data/objects/blobs:0.3,procedural:0.1`.
    #[arg(long)]
    objects: String,
    /// `paper` (the paper's sampling; old runs reproduce) or `deployment` (whole sphere, roll,
    /// 10–100 % image span, truncation, scale augmentation, occluders, sensor model).
    #[arg(long, default_value = "paper")]
    protocol: String,
    /// Start from these weights (e.g. models/pose-cpu-ot.safetensors) and their configuration
    /// (the preset's overrides still apply; the network must keep its shape). Fresh Adam
    /// moments, iteration 0. Ignored when `--resume` finds a checkpoint.
    #[arg(long)]
    init: Option<PathBuf>,
    /// Output folder: latest.safetensors (resumable), best.safetensors (weights), CSV logs.
    #[arg(long)]
    out: PathBuf,
    #[arg(long)]
    iterations: Option<u64>,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Continue from `<out>/latest.safetensors` (configuration and seed come from it).
    #[arg(long)]
    resume: bool,
    /// Compute threads (RAYON_NUM_THREADS); the data prefetcher adds `--data-workers` threads.
    #[arg(long)]
    threads: Option<usize>,
    #[arg(long, default_value_t = 1)]
    data_workers: usize,
    /// Save `latest.safetensors` every this many seconds.
    #[arg(long, default_value_t = 300)]
    checkpoint_secs: u64,
    // Overrides of the preset.
    #[arg(long)]
    batch_size: Option<usize>,
    #[arg(long)]
    emb_dims: Option<usize>,
    #[arg(long)]
    ff_dims: Option<usize>,
    #[arg(long)]
    k: Option<usize>,
    #[arg(long)]
    model_points: Option<usize>,
    #[arg(long)]
    observed_points: Option<usize>,
    #[arg(long)]
    learning_rate: Option<f64>,
    #[arg(long)]
    validate_every: Option<u64>,
    #[arg(long)]
    validation_count: Option<usize>,
}

#[derive(clap::Args)]
pub struct EvalArgs {
    /// A checkpoint (weights-only or training).
    #[arg(long)]
    model: PathBuf,
    /// As for train-pose: a folder or a weighted mixture.
    #[arg(long)]
    objects: String,
    /// `test` (blobs: ids 800–999), `val` (750–799, the validation objects held out of
    /// training) or `train` (000–749); folders with `split.json` use its lists.
    #[arg(long, default_value = "test")]
    split: String,
    /// `paper` or `deployment` (as for train-pose).
    #[arg(long, default_value = "paper")]
    protocol: String,
    #[arg(long, default_value_t = 500)]
    count: u64,
    #[arg(long, default_value_t = 2021)]
    seed: u64,
    /// `icp` (the default of `PoseEstimator`) or `none` (the one-shot estimate).
    #[arg(long, default_value = "icp")]
    refine: String,
    /// Drop correspondences below this probability.
    #[arg(long)]
    min_probability: Option<f32>,
    /// Unweighted Procrustes.
    #[arg(long)]
    unweighted: bool,
    /// Before evaluating, replace the batch-norm running statistics by their mean over this
    /// many batches of training-split samples (precise BN; 0 = keep the checkpoint's).
    #[arg(long, default_value_t = 0)]
    recalibrate_bn: usize,
    /// With --recalibrate-bn: write the recalibrated weights here (weights-only checkpoint).
    #[arg(long)]
    save_recalibrated: Option<PathBuf>,
    /// Where to write the JSON (default `<model>.eval-<split>.json`).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    threads: Option<usize>,
}

pub(crate) static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

pub(crate) fn install_signal_handlers() {
    // SAFETY: the handler only stores into an atomic, which is async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
}

pub(crate) fn set_threads(threads: Option<usize>) {
    if let Some(t) = threads {
        // SAFETY: called first thing in the command, before any other thread exists.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", t.max(1).to_string()) };
    }
}

fn sample_config(cfg: &PoseConfig, protocol: SamplingProtocol) -> ObjectSampleConfig {
    ObjectSampleConfig {
        model_points: cfg.train.model_points,
        observed_points: cfg.train.observed_points,
        ..protocol.config()
    }
}

/// The objects of `split` under `spec`, with a line saying what they are.
fn open_objects(spec: &ObjectsSpec, split: Split) -> Result<Arc<ic_data::Corpus>> {
    let corpus = spec.corpus(split, CorpusOptions::default())?;
    let sources = corpus.sources();
    if sources.is_empty() {
        eprintln!("{split} objects: {}", corpus.len());
    } else {
        let parts: Vec<String> = sources
            .iter()
            .map(|s| format!("{} {} (p {:.3})", s.name, s.objects, s.probability))
            .collect();
        eprintln!("{split} objects: {} = {}", corpus.len(), parts.join(" + "));
    }
    Ok(Arc::new(corpus))
}

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Metrics {
    pub count: usize,
    pub failures: usize,
    pub rotation_median_deg: f64,
    pub rotation_mean_deg: f64,
    pub rotation_acc_5: f64,
    pub rotation_acc_10: f64,
    pub rotation_acc_15: f64,
    /// acc@15° of the rotation error up to the object's symmetry: the smallest error to the
    /// true pose or any pose equivalent to it (`ObjectSample::equivalent_poses`; the same as
    /// `rotation_acc_15` without symmetry-aware samples). The selection score.
    pub rotation_acc_15_sym: f64,
    /// Fraction of samples with an equivalent pose (symmetric objects).
    pub symmetric_fraction: f64,
    /// Median of ‖t̂ − t‖² (normalised units²), as the paper.
    pub translation_sq_median: f64,
    /// Median of ‖t̂ − t‖.
    pub translation_l2_median: f64,
    pub translation_acc_1e3: f64,
    pub translation_acc_5e3: f64,
    pub translation_acc_1e2: f64,
    /// Arg-max correspondence accuracy over matched observed points.
    pub correspondence_accuracy: f64,
    /// Median ADD-S (normalised units: mean distance of the model points moved by the
    /// estimate to the closest model point moved by the truth).
    pub add_s_median: f64,
    /// Fraction with ADD-S below 0.1 × the model's diameter (the usual ADD-S accuracy).
    pub add_s_acc_01d: f64,
    /// Median observed voxels per sample (before drawing N).
    pub observed_voxels_median: f64,
    pub seconds_per_case: f64,
}

/// Evaluates `estimator` on `samples` (a failed estimate counts as 180° / infinite error).
fn evaluate<'a>(
    estimator: &PoseEstimator,
    samples: impl Iterator<Item = Result<ObjectSample>> + 'a,
    mut progress: impl FnMut(usize),
) -> Result<Metrics> {
    let clock = Instant::now();
    let (mut rot, mut trans) = (Vec::<f64>::new(), Vec::<f64>::new());
    let (mut rot_sym, mut symmetric) = (Vec::<f64>::new(), 0usize);
    let (mut add_s, mut add_s_rel, mut voxels) = (Vec::new(), Vec::new(), Vec::new());
    let (mut right, mut total) = (0usize, 0usize);
    let mut failures = 0;
    for (i, s) in samples.enumerate() {
        let s = s?;
        voxels.push(s.observed_voxels as f64);
        symmetric += !s.equivalent_poses.is_empty() as usize;
        let diameter = ic_eval::diameter(&s.model_points);
        let out = estimator.infer(&s.model_points, &s.observed_points)?;
        let matches = out.matches()?.remove(0);
        if let Some(acc) =
            ic_pose::correspondence_accuracy(std::slice::from_ref(&matches), &[&s.assignment])
        {
            let n = s.assignment.inlier_count();
            right += (acc * n as f64).round() as usize;
            total += n;
        }
        match ic_pose::recover_pose(
            &s.model_points,
            &s.observed_points,
            &matches,
            &estimator.recovery,
        ) {
            Ok(r) => {
                rot.push(ic_eval::rotation_error_deg(&r.pose, &s.pose));
                rot_sym.push(
                    s.equivalent_poses
                        .iter()
                        .map(|p| ic_eval::rotation_error_deg(&r.pose, p))
                        .fold(ic_eval::rotation_error_deg(&r.pose, &s.pose), f64::min),
                );
                trans.push(ic_eval::translation_error_sq(&r.pose, &s.pose));
                let a = ic_eval::add_s(&r.pose, &s.pose, &s.model_points)?;
                add_s.push(a);
                add_s_rel.push(a / diameter.max(1e-12));
            }
            Err(e) => {
                tracing::debug!("sample {}: {e}", s.index);
                failures += 1;
                rot.push(180.0);
                rot_sym.push(180.0);
                trans.push(f64::INFINITY);
                add_s.push(f64::INFINITY);
                add_s_rel.push(f64::INFINITY);
            }
        }
        progress(i + 1);
    }
    let n = rot.len();
    let frac = ic_eval::accuracy;
    let mut m = Metrics {
        count: n,
        failures,
        rotation_mean_deg: rot.iter().sum::<f64>() / n.max(1) as f64,
        rotation_acc_5: frac(&rot, 5.0),
        rotation_acc_10: frac(&rot, 10.0),
        rotation_acc_15: frac(&rot, 15.0),
        rotation_acc_15_sym: frac(&rot_sym, 15.0),
        symmetric_fraction: symmetric as f64 / n.max(1) as f64,
        translation_acc_1e3: frac(&trans, 1e-3),
        translation_acc_5e3: frac(&trans, 5e-3),
        translation_acc_1e2: frac(&trans, 1e-2),
        correspondence_accuracy: right as f64 / total.max(1) as f64,
        add_s_median: ic_eval::median(&add_s),
        add_s_acc_01d: frac(&add_s_rel, 0.1),
        observed_voxels_median: ic_eval::median(&voxels),
        seconds_per_case: clock.elapsed().as_secs_f64() / n.max(1) as f64,
        ..Default::default()
    };
    m.rotation_median_deg = ic_eval::median(&rot);
    let l2: Vec<f64> = trans.iter().map(|t| t.sqrt()).collect();
    m.translation_sq_median = ic_eval::median(&trans);
    m.translation_l2_median = ic_eval::median(&l2);
    Ok(m)
}

fn apply_overrides(cfg: &mut PoseConfig, a: &TrainArgs) {
    if let Some(v) = a.iterations {
        cfg.train.iterations = v;
    }
    if let Some(v) = a.batch_size {
        cfg.train.batch_size = v;
    }
    if let Some(v) = a.emb_dims {
        cfg.net.emb_dims = v;
    }
    if let Some(v) = a.ff_dims {
        cfg.net.ff_dims = v;
    }
    if let Some(v) = a.k {
        cfg.net.k = v;
    }
    if let Some(v) = a.model_points {
        cfg.train.model_points = v;
    }
    if let Some(v) = a.observed_points {
        cfg.train.observed_points = v;
    }
    if let Some(v) = a.learning_rate {
        cfg.train.learning_rate = v;
    }
    if let Some(v) = a.validate_every {
        cfg.train.validate_every = v;
    }
    if let Some(v) = a.validation_count {
        cfg.train.validation_count = v;
    }
}

/// Keeps the CSV rows up to `iteration` (after a resume, the rows written past the last
/// checkpoint are dropped so the log matches an uninterrupted run) and opens it for append.
pub(crate) fn open_csv(
    path: &Path,
    header: &str,
    keep_up_to: Option<u64>,
) -> Result<std::fs::File> {
    let mut keep = String::new();
    if let (Some(limit), Ok(text)) = (keep_up_to, std::fs::read_to_string(path)) {
        for (i, line) in text.lines().enumerate() {
            let it: Option<u64> = line.split(',').next().and_then(|s| s.parse().ok());
            if i == 0 || it.is_some_and(|it| it <= limit) {
                keep.push_str(line);
                keep.push('\n');
            }
        }
    }
    if keep.is_empty() {
        keep = format!("{header}\n");
    }
    std::fs::write(path, &keep).with_context(|| format!("writing {}", path.display()))?;
    std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))
}

pub fn train(args: TrainArgs) -> Result<()> {
    set_threads(args.threads);
    install_signal_handlers();
    let protocol: SamplingProtocol = args.protocol.parse()?;
    let objects: ObjectsSpec = args.objects.parse()?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let latest = args.out.join("latest.safetensors");
    let best_path = args.out.join("best.safetensors");
    let resuming = args.resume && latest.exists();
    let mut trainer = if resuming {
        let mut t = Trainer::resume(&latest)?;
        eprintln!(
            "resuming {} at iteration {}",
            latest.display(),
            t.iteration()
        );
        if args.init.is_some() {
            eprintln!("--init ignored: resuming the run's own checkpoint");
        }
        if let Some(it) = args.iterations {
            t.set_iterations(it);
        }
        if let Some(lr) = args.learning_rate {
            eprintln!("learning rate {} from iteration {}", lr, t.iteration());
            t.set_learning_rate(lr);
        }
        t
    } else {
        if args.resume {
            eprintln!("--resume: no {} yet, starting fresh", latest.display());
        }
        match &args.init {
            Some(init) => {
                let mut cfg = ic_pose::checkpoint::read_config(init)
                    .with_context(|| format!("--init {}", init.display()))?;
                if let Some(h) = &args.head {
                    let head: Head = h.parse()?;
                    if head != cfg.net.head {
                        bail!(
                            "--head {h}: {} has the {} head",
                            init.display(),
                            cfg.net.head.as_str()
                        );
                    }
                }
                apply_overrides(&mut cfg, &args);
                let mut t = Trainer::new(cfg, args.seed)?;
                t.load_weights(init)
                    .with_context(|| format!("--init {}", init.display()))?;
                eprintln!(
                    "initialised from {} (preset {:?}, head {}); fresh optimiser at iteration 0",
                    init.display(),
                    t.config().preset,
                    t.config().net.head.as_str()
                );
                t
            }
            None => {
                let head: Head = args.head.as_deref().unwrap_or("softmax").parse()?;
                let mut cfg = PoseConfig::preset(&args.preset, head)?;
                apply_overrides(&mut cfg, &args);
                Trainer::new(cfg, args.seed)?
            }
        }
    };
    let cfg = trainer.config().clone();
    let seed = trainer.seed();
    eprintln!("seed {seed}");
    eprintln!("config {}", serde_json::to_string_pretty(&cfg)?);
    eprintln!(
        "threads: compute {}, data {}",
        std::env::var("RAYON_NUM_THREADS").unwrap_or_else(|_| "all".into()),
        args.data_workers
    );

    let train_corpus = open_objects(&objects, Split::Train)?;
    let val_corpus = open_objects(&objects, Split::Val)?;
    let scfg = sample_config(&cfg, protocol);
    let data = serde_json::json!({
        "protocol": protocol.as_str(),
        "objects": objects.describe(),
        "init": args.init,
        "sample": scfg,
        "validation_seed": VALIDATION_SEED,
    });
    eprintln!("data {}", serde_json::to_string(&data)?);
    check_data_record(&args.out.join("data.json"), &data, resuming)?;
    // The objects' symmetries found by earlier parts of the run (the search takes ≈ 0.3 s per
    // object as it is first drawn); saved again with every checkpoint.
    let symmetries_path = args.out.join("symmetries.json");
    let mut symmetries = read_symmetry_cache(&symmetries_path)?;
    if !symmetries.is_empty() {
        eprintln!(
            "symmetries of {} objects from {}",
            symmetries.len(),
            symmetries_path.display()
        );
    }
    train_corpus.set_known_symmetries(symmetries.clone());
    val_corpus.set_known_symmetries(symmetries.clone());
    let generator = Arc::new(ObjectSampleGenerator::new(
        train_corpus.clone(),
        scfg.clone(),
        seed,
    )?);
    let val_gen = ObjectSampleGenerator::new(val_corpus.clone(), scfg, VALIDATION_SEED)?;
    let val_set: Vec<ObjectSample> = (0..cfg.train.validation_count as u64)
        .map(|i| val_gen.sample(i))
        .collect::<Result<_, _>>()?;

    let b = cfg.train.batch_size;
    let start = trainer.iteration();
    let total = cfg.train.iterations;
    if start >= total {
        eprintln!("already at iteration {start} of {total}");
        return Ok(());
    }
    let mut csv = open_csv(
        &args.out.join("train.csv"),
        "iteration,loss,accuracy,loss_avg,accuracy_avg,matched_fraction,samples_per_s,elapsed_s",
        args.resume.then_some(start),
    )?;
    let mut val_csv = open_csv(
        &args.out.join("val.csv"),
        "iteration,rotation_median_deg,rotation_acc_5,rotation_acc_10,rotation_acc_15,translation_sq_median,translation_acc_1e2,correspondence_accuracy,elapsed_s,add_s_acc_01d,rotation_acc_15_sym",
        args.resume.then_some(start),
    )?;
    let best_json = args.out.join("best.json");
    let mut best_score = run::previous_best_score(&best_json, args.resume);

    let gen2 = generator.clone();
    let batches = Prefetcher::new(
        start * b as u64,
        Some((total - start) * b as u64),
        args.data_workers,
        2 * b,
        move |i| gen2.sample(i),
    )
    .batches(b);

    let bar = run::progress_bar(total, start)?;
    let clock = Instant::now();
    let mut last_ckpt = Instant::now();
    let (mut loss_avg, mut acc_avg) = (f64::NAN, f64::NAN);
    let mut done = start;
    for batch in batches {
        let batch = batch?;
        let stats = trainer.step(&batch)?;
        done = trainer.iteration();
        let loss = stats.loss as f64;
        if !loss.is_finite() {
            trainer.save(&args.out.join("nonfinite.safetensors"))?;
            bail!("non-finite loss at iteration {done}");
        }
        loss_avg = run::ema(loss_avg, loss);
        let acc = stats.accuracy.unwrap_or(f64::NAN);
        if acc.is_finite() {
            acc_avg = run::ema(acc_avg, acc);
        }
        let elapsed = clock.elapsed().as_secs_f64();
        let sps = ((done - start) * b as u64) as f64 / elapsed;
        writeln!(
            csv,
            "{done},{loss:.5},{acc:.4},{loss_avg:.5},{acc_avg:.4},{:.4},{sps:.3},{elapsed:.1}",
            stats.matched as f64 / (b * cfg.train.observed_points) as f64
        )?;
        bar.set_position(done);
        bar.set_message(format!(
            "loss {loss_avg:.3} acc {acc_avg:.3} {sps:.2} samples/s ({:.0} pairs/h)",
            sps * 3600.0
        ));
        let last = done >= total;
        if !run::interactive() && (done % 10 == 0 || last) {
            eprintln!(
                "iteration {done}/{total}: loss {loss_avg:.3} acc {acc_avg:.3} {:.0} pairs/h, {elapsed:.0} s",
                sps * 3600.0
            );
        }
        if done % cfg.train.validate_every == 0 || last {
            let est = trainer.estimator();
            let m = evaluate(&est, val_set.iter().cloned().map(Ok), |_| {})?;
            writeln!(
                val_csv,
                "{done},{:.3},{:.4},{:.4},{:.4},{:.6},{:.4},{:.4},{elapsed:.1},{:.4},{:.4}",
                m.rotation_median_deg,
                m.rotation_acc_5,
                m.rotation_acc_10,
                m.rotation_acc_15,
                m.translation_sq_median,
                m.translation_acc_1e2,
                m.correspondence_accuracy,
                m.add_s_acc_01d,
                m.rotation_acc_15_sym
            )?;
            // Up to symmetry: a can turned about its axis is not an error.
            let score = m.rotation_acc_15_sym - 1e-4 * m.rotation_median_deg;
            let line = format!(
                "iteration {done}: validation rot median {:.2}°, acc@5/10/15 {:.3}/{:.3}/{:.3}, acc@15 up to symmetry {:.3}, ADD-S<0.1d {:.3}, corr acc {:.3}",
                m.rotation_median_deg,
                m.rotation_acc_5,
                m.rotation_acc_10,
                m.rotation_acc_15,
                m.rotation_acc_15_sym,
                m.add_s_acc_01d,
                m.correspondence_accuracy
            );
            run::report(&bar, line);
            if score > best_score {
                best_score = score;
                trainer.save_weights(&best_path)?;
                run::write_best(&best_json, done, score, &m)?;
            }
        }
        let stop = run::checkpoint(last, &mut last_ckpt, args.checkpoint_secs, || {
            csv.flush()?;
            val_csv.flush()?;
            symmetries.extend(train_corpus.found_symmetries());
            symmetries.extend(val_corpus.found_symmetries());
            write_symmetry_cache(&symmetries_path, &symmetries)?;
            Ok(trainer.save(&latest)?)
        })?;
        if stop {
            bar.abandon_with_message(format!("interrupted; checkpoint saved at iteration {done}"));
            eprintln!("interrupted: saved {} (iteration {done})", latest.display());
            return Ok(());
        }
    }
    bar.finish();
    trainer.save_weights(&args.out.join("final.safetensors"))?;
    eprintln!(
        "done: {} iterations in {:.0} s; best weights {}",
        done - start,
        clock.elapsed().as_secs_f64(),
        best_path.display()
    );
    Ok(())
}

/// Writes `path` (the run's data: protocol, objects, sample configuration) for a fresh run;
/// when resuming, warns if the data now differ from the record (the run then no longer
/// matches an uninterrupted one) and keeps the record.
/// The symmetry cache of a run (`<out>/symmetries.json`): object id → motions, valid only
/// for the search settings it records (`ic_data::TRAINING_SYMMETRY_OPTIONS`); absent or made
/// with other settings → empty.
fn read_symmetry_cache(path: &Path) -> Result<HashMap<String, Vec<ic_geometry::Pose>>> {
    let Ok(text) = std::fs::read_to_string(path) else {
        return Ok(HashMap::new());
    };
    let doc: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
    if doc["options"] != serde_json::to_value(ic_data::TRAINING_SYMMETRY_OPTIONS)? {
        eprintln!(
            "{}: made with other search settings; searching again",
            path.display()
        );
        return Ok(HashMap::new());
    }
    serde_json::from_value(doc["objects"].clone())
        .with_context(|| format!("reading {}: objects", path.display()))
}

fn write_symmetry_cache(
    path: &Path,
    symmetries: &HashMap<String, Vec<ic_geometry::Pose>>,
) -> Result<()> {
    let sorted: std::collections::BTreeMap<_, _> = symmetries.iter().collect();
    let bytes = serde_json::to_vec(&serde_json::json!({
        "what": "rotational symmetries of the run's objects (normalised frame), by id",
        "options": ic_data::TRAINING_SYMMETRY_OPTIONS,
        "objects": sorted,
    }))?;
    ic_geometry::io::write_atomic_with(path, |w| std::io::Write::write_all(w, &bytes), |e| e)
        .with_context(|| format!("writing {}", path.display()))
}

fn check_data_record(path: &Path, data: &serde_json::Value, resuming: bool) -> Result<()> {
    if resuming && let Ok(text) = std::fs::read_to_string(path) {
        let old: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?;
        // `init` only matters for a fresh start.
        let strip = |v: &serde_json::Value| {
            let mut v = v.clone();
            if let Some(o) = v.as_object_mut() {
                o.remove("init");
            }
            v
        };
        if strip(&old) != strip(data) {
            eprintln!(
                "WARNING: the data differ from {} (protocol, objects or sample settings): the resumed run is not the uninterrupted one",
                path.display()
            );
        }
        return Ok(());
    }
    std::fs::write(path, serde_json::to_string_pretty(data)?)
        .with_context(|| format!("writing {}", path.display()))
}

/// Seed of the sample stream used to recalibrate batch norm (training split).
const RECALIBRATION_SEED: u64 = 0x0062_726e;

pub fn eval(args: EvalArgs) -> Result<()> {
    set_threads(args.threads);
    let protocol: SamplingProtocol = args.protocol.parse()?;
    let objects: ObjectsSpec = args.objects.parse()?;
    let split: Split = args.split.parse()?;
    let mut est = if args.recalibrate_bn > 0 {
        let cfg = ic_pose::checkpoint::read_config(&args.model)?;
        let mut trainer = Trainer::new(cfg.clone(), 0)?;
        trainer.load_weights(&args.model)?;
        let corpus = open_objects(&objects, Split::Train)?;
        let generator =
            ObjectSampleGenerator::new(corpus, sample_config(&cfg, protocol), RECALIBRATION_SEED)?;
        let b = cfg.train.batch_size;
        let batches: Vec<Vec<ObjectSample>> = (0..args.recalibrate_bn as u64)
            .map(|k| {
                (0..b as u64)
                    .map(|i| generator.sample(k * b as u64 + i))
                    .collect()
            })
            .collect::<Result<_, _>>()?;
        trainer.recalibrate_batch_norm(&batches)?;
        eprintln!(
            "batch norm recalibrated on {} batches of {b} training-split samples (seed {RECALIBRATION_SEED:#x})",
            args.recalibrate_bn
        );
        if let Some(out) = &args.save_recalibrated {
            trainer.save_weights(out)?;
            eprintln!("written {}", out.display());
        }
        let mut e = trainer.estimator();
        e.recovery = PoseEstimator::load(&args.model)?.recovery;
        e
    } else {
        PoseEstimator::load(&args.model)?
    };
    est.recovery.refine = match args.refine.as_str() {
        "none" => Refine::None,
        "icp" => Refine::Icp,
        other => bail!("--refine {other:?}: expected none or icp"),
    };
    if let Some(p) = args.min_probability {
        est.recovery.min_probability = p;
    }
    if args.unweighted {
        est.recovery.weighted = false;
    }
    let cfg = est.config().clone();
    let corpus = open_objects(&objects, split)?;
    let generator = Arc::new(ObjectSampleGenerator::new(
        corpus,
        sample_config(&cfg, protocol),
        args.seed,
    )?);
    let samples = Prefetcher::new(0, Some(args.count), 1, 8, move |i| generator.sample(i))
        .map(|r| r.map_err(anyhow::Error::from));
    let bar = ProgressBar::new(args.count);
    let m = evaluate(&est, samples, |i| {
        bar.set_position(i as u64);
        if i % 50 == 0 && !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
            eprintln!("{i}/{} cases", args.count);
        }
    })?;
    bar.finish_and_clear();
    let report = serde_json::json!({
        "model": args.model,
        "split": split.as_str(),
        "protocol": protocol.as_str(),
        "objects": objects.describe(),
        "seed": args.seed,
        "refine": args.refine,
        "recovery": est.recovery,
        "config": cfg,
        "metrics": m,
    });
    let text = serde_json::to_string_pretty(&report)?;
    println!("{text}");
    let out = args.out.unwrap_or_else(|| {
        // The paper protocol keeps the old names.
        let mut p = args.model.clone().into_os_string();
        match protocol {
            SamplingProtocol::Paper => p.push(format!(".eval-{split}-{}.json", args.refine)),
            _ => p.push(format!(".eval-{protocol}-{split}-{}.json", args.refine)),
        }
        PathBuf::from(p)
    });
    std::fs::write(&out, text).with_context(|| format!("writing {}", out.display()))?;
    eprintln!("written {}", out.display());
    Ok(())
}
