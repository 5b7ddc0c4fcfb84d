//! `cargo xtask train-seg` and `cargo xtask eval-seg`: the instance-mask network (`ic_seg`)
//! trained on room scenes rendered on the fly by `ic_data`, and measured on the test split
//! beside the geometry-only alternative.
//!
//! Objects as for the pose network: ids 000–749 train, 750–799 the fixed validation set,
//! 800–999 (the test split) only for `eval-seg`.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use crate::run;
use anyhow::{Context, Result, bail};
use ic_data::{
    Corpus, CorpusOptions, FolderSplit, Prefetcher, RoomSampleConfig, RoomSampleGenerator,
    RoomView, Split,
};
use ic_geometry::Mask;
use ic_render::CpuRenderer;
use ic_seg::post::iou;
use ic_seg::{GeometricConfig, SegConfig, SegError, SegExample, SegTrainer, Segmenter};
use indicatif::ProgressBar;

use crate::pose::{install_signal_handlers, open_csv, set_threads};

/// Seed of the validation scene stream (fixed whatever the run's seed).
const VALIDATION_SEED: u64 = 0x7365_6776;

#[derive(clap::Args)]
pub struct TrainArgs {
    /// `cpu` or `tiny` (smoke tests).
    #[arg(long, default_value = "cpu")]
    preset: String,
    /// Folder of meshes with numeric stems (the blob folder: 000–999).
    #[arg(long)]
    objects: PathBuf,
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
    /// Compute threads (RAYON_NUM_THREADS); the scene renderers add `--data-workers` threads.
    #[arg(long)]
    threads: Option<usize>,
    #[arg(long, default_value_t = 1)]
    data_workers: usize,
    #[arg(long, default_value_t = 300)]
    checkpoint_secs: u64,
    #[arg(long, default_value_t = 250)]
    validate_every: u64,
    #[arg(long, default_value_t = 48)]
    validation_count: u64,
    #[arg(long)]
    batch_size: Option<usize>,
    #[arg(long)]
    learning_rate: Option<f64>,
}

#[derive(clap::Args)]
pub struct EvalArgs {
    #[arg(long)]
    model: PathBuf,
    #[arg(long)]
    objects: PathBuf,
    /// `test` (800–999) or `val` (750–799).
    #[arg(long, default_value = "test")]
    split: String,
    #[arg(long, default_value_t = 300)]
    count: u64,
    #[arg(long, default_value_t = 2021)]
    seed: u64,
    /// Also run the geometry-only alternative (RANSAC planes + Euclidean clustering).
    #[arg(long)]
    geometric: bool,
    /// Override the depth-edge refinement band (pixels at 640 wide; 0 = off).
    #[arg(long)]
    depth_refine_px: Option<usize>,
    /// Override the pixel probability threshold.
    #[arg(long)]
    pixel_threshold: Option<f32>,
    /// Where to write the JSON (default `<model>.eval-<split>.json`).
    #[arg(long)]
    out: Option<PathBuf>,
    #[arg(long)]
    threads: Option<usize>,
}

fn corpus(objects: &std::path::Path, split: Split, holdout: bool) -> Result<Arc<Corpus>> {
    let fs = if holdout {
        FolderSplit::IdRange {
            train: (0, 749),
            test: (750, 799),
        }
    } else {
        FolderSplit::blobs()
    };
    Ok(Arc::new(Corpus::mesh_folder(
        objects,
        &fs,
        split,
        CorpusOptions::default(),
    )?))
}

/// IoU and found-rate over views, as `eval-seg` and the validation report them.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct MaskMetrics {
    pub count: usize,
    /// Views where an instance was returned and its IoU with the visible mask is ≥ 0.5.
    pub found_rate: f64,
    /// Views where nothing scored above the threshold.
    pub not_found: usize,
    pub iou_median: f64,
    pub iou_mean: f64,
    /// Fraction of views with IoU ≥ 0.9.
    pub iou_at_least_0_9: f64,
    pub seconds_median: f64,
}

/// Per-view IoUs, times and misses of one method, as the views come.
#[derive(Default)]
struct MaskTally {
    ious: Vec<f64>,
    seconds: Vec<f64>,
    not_found: usize,
}

impl MaskTally {
    /// Records one view: `found` is the method's mask (or its error) for `truth`, computed
    /// since `started`. Object-not-found counts IoU 0; any other error stops the evaluation.
    fn add(&mut self, truth: &Mask, started: Instant, found: Result<Mask, SegError>) -> Result<()> {
        match found {
            Ok(mask) => self.ious.push(iou(&mask, truth)),
            Err(SegError::ObjectNotFound { .. }) => {
                self.not_found += 1;
                self.ious.push(0.0);
            }
            Err(e) => return Err(e.into()),
        }
        self.seconds.push(started.elapsed().as_secs_f64());
        Ok(())
    }

    fn metrics(&self) -> MaskMetrics {
        let ious = &self.ious;
        let n = ious.len();
        MaskMetrics {
            count: n,
            found_rate: ious.iter().filter(|&&i| i >= 0.5).count() as f64 / n.max(1) as f64,
            not_found: self.not_found,
            iou_median: ic_eval::median(ious),
            iou_mean: ious.iter().sum::<f64>() / n.max(1) as f64,
            iou_at_least_0_9: ious.iter().filter(|&&i| i >= 0.9).count() as f64 / n.max(1) as f64,
            seconds_median: ic_eval::median(&self.seconds),
        }
    }
}

/// The network's masks on `views` (a view where nothing is found counts IoU 0).
fn evaluate_network(seg: &Segmenter, views: &[RoomView]) -> Result<MaskMetrics> {
    let mut tally = MaskTally::default();
    for v in views {
        let t = Instant::now();
        let found = seg.segment(&v.depth, &v.intrinsics).map(|s| s.mask);
        tally.add(&v.mask_visib, t, found)?;
    }
    Ok(tally.metrics())
}

pub fn train(args: TrainArgs) -> Result<()> {
    set_threads(args.threads);
    install_signal_handlers();
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let latest = args.out.join("latest.safetensors");
    let best_path = args.out.join("best.safetensors");
    let mut trainer = if args.resume && latest.exists() {
        let mut t = SegTrainer::resume(&latest)?;
        eprintln!(
            "resuming {} at iteration {}",
            latest.display(),
            t.iteration()
        );
        if let Some(it) = args.iterations {
            t.set_iterations(it);
        }
        t
    } else {
        if args.resume {
            eprintln!("--resume: no {} yet, starting fresh", latest.display());
        }
        let mut cfg = SegConfig::preset(&args.preset)?;
        if let Some(v) = args.iterations {
            cfg.train.iterations = v;
        }
        if let Some(v) = args.batch_size {
            cfg.train.batch_size = v;
        }
        if let Some(v) = args.learning_rate {
            cfg.train.learning_rate = v;
        }
        SegTrainer::new(cfg, args.seed)?
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
    let room = RoomSampleConfig::default()
        .with_resolution(cfg.train.render_width, cfg.train.render_height);
    let train_corpus = corpus(&args.objects, Split::Train, true)?;
    let val_corpus = corpus(&args.objects, Split::Test, true)?;
    eprintln!(
        "objects: {} train, {} validation (held out of the train split)",
        train_corpus.len(),
        val_corpus.len()
    );
    let generator = Arc::new(RoomSampleGenerator::new(train_corpus, room.clone(), seed)?);
    let val_gen = RoomSampleGenerator::new(val_corpus, room, VALIDATION_SEED)?;
    let mut renderer = CpuRenderer::new();
    let val_views: Vec<RoomView> = (0..args.validation_count)
        .map(|i| val_gen.view_with(&mut renderer, i))
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
        "iteration,loss,iou,loss_avg,iou_avg,scenes_per_s,elapsed_s",
        args.resume.then_some(start),
    )?;
    let mut val_csv = open_csv(
        &args.out.join("val.csv"),
        "iteration,iou_median,iou_mean,found_rate,not_found,elapsed_s",
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
        move |i| gen2.view_with(&mut CpuRenderer::new(), i),
    )
    .batches(b);
    let bar = run::progress_bar(total, start)?;
    let clock = Instant::now();
    let mut last_ckpt = Instant::now();
    let (mut loss_avg, mut iou_avg) = (f64::NAN, f64::NAN);
    let mut done = start;
    for batch in batches {
        let views = batch?;
        let examples: Vec<SegExample> = views
            .iter()
            .map(|v| SegExample::new(&v.depth, &v.mask_visib, &cfg))
            .collect::<Result<_, _>>()?;
        let stats = trainer.step(&examples)?;
        done = trainer.iteration();
        let loss = stats.loss as f64;
        if !loss.is_finite() {
            trainer.save(&args.out.join("nonfinite.safetensors"))?;
            bail!("non-finite loss at iteration {done}");
        }
        loss_avg = run::ema(loss_avg, loss);
        iou_avg = run::ema(iou_avg, stats.iou);
        let elapsed = clock.elapsed().as_secs_f64();
        let sps = ((done - start) * b as u64) as f64 / elapsed;
        writeln!(
            csv,
            "{done},{loss:.5},{:.4},{loss_avg:.5},{iou_avg:.4},{sps:.3},{elapsed:.1}",
            stats.iou
        )?;
        bar.set_position(done);
        bar.set_message(format!(
            "loss {loss_avg:.3} IoU {iou_avg:.3} {sps:.2} scenes/s"
        ));
        let last = done >= total;
        if !run::interactive() && (done % 10 == 0 || last) {
            eprintln!(
                "iteration {done}/{total}: loss {loss_avg:.3} IoU {iou_avg:.3} {sps:.2} scenes/s, {elapsed:.0} s"
            );
        }
        if done % args.validate_every == 0 || last {
            let m = evaluate_network(&trainer.segmenter(), &val_views)?;
            writeln!(
                val_csv,
                "{done},{:.4},{:.4},{:.4},{},{elapsed:.1}",
                m.iou_median, m.iou_mean, m.found_rate, m.not_found
            )?;
            let line = format!(
                "iteration {done}: validation IoU median {:.3} mean {:.3}, found {:.3}",
                m.iou_median, m.iou_mean, m.found_rate
            );
            run::report(&bar, line);
            let score = m.iou_mean + m.found_rate;
            if score > best_score {
                best_score = score;
                trainer.save_weights(&best_path)?;
                run::write_best(&best_json, done, score, &m)?;
            }
        }
        let stop = run::checkpoint(last, &mut last_ckpt, args.checkpoint_secs, || {
            csv.flush()?;
            val_csv.flush()?;
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

pub fn eval(args: EvalArgs) -> Result<()> {
    set_threads(args.threads);
    let mut seg = Segmenter::load(&args.model)?;
    if let Some(px) = args.depth_refine_px {
        seg.config_mut().post.depth_refine_px = px;
    }
    if let Some(t) = args.pixel_threshold {
        seg.config_mut().post.pixel_threshold = t;
    }
    let (split, holdout) = match args.split.as_str() {
        "test" => (Split::Test, false),
        "val" => (Split::Test, true),
        other => bail!("--split {other:?}: expected test or val"),
    };
    let generator = Arc::new(RoomSampleGenerator::new(
        corpus(&args.objects, split, holdout)?,
        RoomSampleConfig::default(),
        args.seed,
    )?);
    eprintln!(
        "seed {}; {} scenes of the {} split at 640×480",
        args.seed, args.count, args.split
    );
    let views = Prefetcher::new(0, Some(args.count), 1, 4, move |i| {
        generator.view_with(&mut CpuRenderer::new(), i)
    });
    let bar = ProgressBar::new(args.count);
    let geo_cfg = GeometricConfig::default();
    let (mut network, mut geometric) = (MaskTally::default(), MaskTally::default());
    for (i, v) in views.enumerate() {
        let v = v?;
        let t = Instant::now();
        let found = seg.segment(&v.depth, &v.intrinsics).map(|s| s.mask);
        network.add(&v.mask_visib, t, found)?;
        if args.geometric {
            let t = Instant::now();
            let cfg = GeometricConfig {
                seed: i as u64,
                ..geo_cfg.clone()
            };
            let found =
                ic_seg::segment_geometric(&v.depth, &v.intrinsics, v.model_extent, 1.0, &cfg)
                    .map(|g| g.mask);
            geometric.add(&v.mask_visib, t, found)?;
        }
        bar.set_position(i as u64 + 1);
        if (i + 1) % 50 == 0 && !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
            eprintln!("{}/{} scenes", i + 1, args.count);
        }
    }
    bar.finish_and_clear();
    let network_metrics = network.metrics();
    let mut report = serde_json::json!({
        "per_scene_iou": network.ious,
        "model": args.model,
        "split": args.split,
        "seed": args.seed,
        "resolution": [640, 480],
        "config": seg.config(),
        "network": network_metrics,
    });
    if args.geometric {
        report["geometric"] = serde_json::to_value(geometric.metrics())?;
        report["geometric_config"] = serde_json::to_value(&geo_cfg)?;
        report["per_scene_iou_geometric"] = serde_json::to_value(&geometric.ious)?;
    }
    let text = serde_json::to_string_pretty(&report)?;
    println!("{text}");
    let out = args.out.unwrap_or_else(|| {
        let mut p = args.model.clone().into_os_string();
        p.push(format!(".eval-{}.json", args.split));
        PathBuf::from(p)
    });
    ic_geometry::io::write_atomic_with(&out, |w| w.write_all(text.as_bytes()), |e| e)
        .with_context(|| format!("writing {}", out.display()))?;
    eprintln!("written {}", out.display());
    Ok(())
}

#[derive(clap::Args)]
pub struct PostArgs {
    /// A segmentation checkpoint (weights-only or training).
    #[arg(long)]
    model: PathBuf,
    /// The weights-only checkpoint to write, with the post-processing settings replaced.
    #[arg(long)]
    out: PathBuf,
    #[arg(long)]
    pixel_threshold: Option<f32>,
    #[arg(long)]
    score_threshold: Option<f32>,
    #[arg(long)]
    depth_refine_px: Option<usize>,
    #[arg(long)]
    depth_jump: Option<f32>,
    #[arg(long)]
    min_pixels: Option<usize>,
}

/// `cargo xtask seg-post`: writes the weights of `--model` with new post-processing settings
/// (thresholds chosen on validation scenes after training), atomically. The weights are
/// copied bit for bit; only the configuration in the metadata changes.
pub fn set_post(args: PostArgs) -> Result<()> {
    let mut cfg = ic_seg::checkpoint::read_config(&args.model)?;
    let p = &mut cfg.post;
    if let Some(v) = args.pixel_threshold {
        p.pixel_threshold = v;
    }
    if let Some(v) = args.score_threshold {
        p.score_threshold = v;
    }
    if let Some(v) = args.depth_refine_px {
        p.depth_refine_px = v;
    }
    if let Some(v) = args.depth_jump {
        p.depth_jump = v;
    }
    if let Some(v) = args.min_pixels {
        p.min_pixels = v;
    }
    cfg.validate()?;
    // Only the network's tensors: a training checkpoint's Adam moments are left behind.
    let seg = Segmenter::load(&args.model)?;
    drop(seg);
    let tensors = candle_core::safetensors::load(&args.model, &candle_core::Device::Cpu)
        .with_context(|| format!("reading {}", args.model.display()))?;
    let weights: Vec<(String, candle_core::Tensor)> = tensors
        .into_iter()
        .filter(|(k, _)| !k.starts_with("adam."))
        .collect();
    let meta = std::collections::HashMap::from([(
        ic_seg::checkpoint::CONFIG_KEY.to_string(),
        serde_json::to_string(&cfg)?,
    )]);
    ic_nn::checkpoint::save(&args.out, &weights, meta)?;
    eprintln!("post-processing {}", serde_json::to_string(&cfg.post)?);
    eprintln!("written {}", args.out.display());
    Ok(())
}
