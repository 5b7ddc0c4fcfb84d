//! `cargo xtask gen-data` and `cargo xtask export-cases`: fixed test sets and registration
//! cases written to disk, with the seed and configuration printed and saved.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use ic_data::bop::{BopWriteOptions, BopWriter};
use ic_data::export::{write_object_case, write_room_case};
use ic_data::{
    ClutterConfig, ClutterGenerator, Corpus, CorpusOptions, FolderSplit, ObjectSampleConfig,
    ObjectSampleGenerator, OnBadMesh, Prefetcher, RoomSampleConfig, RoomSampleGenerator, Split,
};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::{Value, json};

/// Where the objects come from.
#[derive(Args, Debug, Clone)]
pub struct CorpusArgs {
    /// Object folder: a ModelNet40 root (`<class>/{train,test}/*.off`), a BOP `models/` folder
    /// (with `models_info.json`) or a flat folder of meshes (ids = numeric file stems). When
    /// absent, procedural objects are used.
    #[arg(long)]
    pub objects: Option<PathBuf>,
    /// Object split.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Flat folders: inclusive id range of the training split.
    #[arg(long, default_value = "0-799")]
    pub train_ids: String,
    /// Flat folders: inclusive id range of the test split.
    #[arg(long, default_value = "800-999")]
    pub test_ids: String,
    /// Flat folders: a JSON split file `{"train": [...], "test": [...]}` instead of id ranges.
    #[arg(long)]
    pub split_file: Option<PathBuf>,
    /// Number of procedural objects when no folder is given.
    #[arg(long, default_value_t = 200)]
    pub procedural: usize,
    /// Stop at the first unreadable mesh instead of skipping it with a warning.
    #[arg(long)]
    pub strict: bool,
}

#[derive(Args, Debug)]
pub struct GenDataArgs {
    #[command(flatten)]
    pub corpus: CorpusArgs,
    /// Output folder (holds `noback/`, `room/`, `clutter/` and `manifest.json`).
    #[arg(long, default_value = "target/data")]
    pub out: PathBuf,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Object-alone samples.
    #[arg(long, default_value_t = 200)]
    pub noback_count: u64,
    /// Room samples (640×480).
    #[arg(long, default_value_t = 50)]
    pub room_count: u64,
    /// Cluttered scenes (`ic_data::clutter`: 640×480, tables, bins and shelves with 3–15
    /// objects of the split at fixed sizes, the target's copies listed in
    /// `test_targets_bop19.json`, the sensor model on), written to `clutter/`.
    #[arg(long, default_value_t = 0)]
    pub clutter_count: u64,
    /// Cluttered scenes: the probability that a scene's sensor casts the projector's
    /// shadows, and (drawn apart) that its depth is registered to a colour camera
    /// (`ic_data::SensorRanges::set_shadows`: no return beside each nearer edge, on one side
    /// and the other, as structured-light sensors give; default 0, as the benchmark's sets).
    #[arg(long, default_value_t = 0.0)]
    pub shadow_probability: f64,
    /// Cluttered scenes: see them through this camera instead of the 640×480 Kinect-like one
    /// (pixels: e.g. `1280 720 640 640` for a RealSense-like 16:9 depth camera; the principal
    /// point at the image's centre), the scenes' geometry kept.
    #[arg(long, num_args = 4, value_names = ["WIDTH", "HEIGHT", "FX", "FY"])]
    pub camera: Option<Vec<f64>>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
}

#[derive(ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum CaseSet {
    Noback,
    Room,
    /// Object views of `--protocol` (default deployment: whole sphere, any orientation,
    /// sensor model, occluders, truncation; no copy rotations, no scale augmentation) with
    /// depth.png, camera.json, mask.png and the normalised model.ply: what
    /// `incontext eval --cases` registers like a user's mesh.
    View,
}

#[derive(Args, Debug)]
pub struct ExportArgs {
    #[arg(long, value_enum)]
    pub set: CaseSet,
    #[command(flatten)]
    pub corpus: CorpusArgs,
    #[arg(long, default_value_t = 20)]
    pub count: u64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long)]
    pub workers: Option<usize>,
    /// Sampling protocol of `--set view`: paper, sphere (the paper's with whole-sphere
    /// viewpoints) or deployment.
    #[arg(long, default_value = "deployment")]
    pub protocol: String,
}

fn parse_range(s: &str, what: &str) -> Result<(u64, u64)> {
    let (a, b) = s
        .split_once('-')
        .with_context(|| format!("{what}: expected FROM-TO, got {s:?}"))?;
    let (a, b): (u64, u64) = (
        a.trim().parse().with_context(|| format!("{what}: {a:?}"))?,
        b.trim().parse().with_context(|| format!("{what}: {b:?}"))?,
    );
    if a > b {
        bail!("{what}: {a} > {b}");
    }
    Ok((a, b))
}

pub(crate) fn open_corpus(args: &CorpusArgs, seed: u64) -> Result<(Corpus, serde_json::Value)> {
    let split: Split = args.split.parse()?;
    let options = CorpusOptions {
        on_bad_mesh: if args.strict {
            OnBadMesh::Stop
        } else {
            OnBadMesh::Skip
        },
        ..CorpusOptions::default()
    };
    let Some(dir) = &args.objects else {
        let c = Corpus::procedural(args.procedural, split, seed, options)?;
        return Ok((
            c,
            json!({"kind": "procedural", "count": args.procedural, "seed": seed}),
        ));
    };
    if !dir.is_dir() {
        bail!("{}: not a folder", dir.display());
    }
    if dir.join("models_info.json").is_file() {
        return Ok((
            Corpus::bop_models(dir, split, options)?,
            json!({"kind": "bop_models", "folder": dir}),
        ));
    }
    let is_modelnet = std::fs::read_dir(dir)
        .with_context(|| format!("listing {}", dir.display()))?
        .filter_map(|e| e.ok())
        .any(|e| e.path().join("train").is_dir() || e.path().join("test").is_dir());
    if is_modelnet {
        return Ok((
            Corpus::modelnet40(dir, split, options)?,
            json!({"kind": "modelnet40", "folder": dir}),
        ));
    }
    let how = match &args.split_file {
        Some(f) => FolderSplit::File(f.clone()),
        None => FolderSplit::IdRange {
            train: parse_range(&args.train_ids, "--train-ids")?,
            test: parse_range(&args.test_ids, "--test-ids")?,
        },
    };
    let c = Corpus::mesh_folder(dir, &how, split, options)?;
    Ok((
        c,
        json!({"kind": "mesh_folder", "folder": dir, "split_rule": format!("{how:?}")}),
    ))
}

fn progress(len: u64, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template(
            "{msg:>10} [{elapsed_precise}] {wide_bar} {pos}/{len} ({per_sec}, eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(what.to_string());
    bar
}

fn workers(w: Option<usize>) -> usize {
    w.unwrap_or_else(|| std::thread::available_parallelism().map_or(2, |n| n.get()))
        .max(1)
}

#[derive(Default)]
struct Stats(Vec<f64>);

impl Stats {
    fn summary(&mut self) -> serde_json::Value {
        let v = &mut self.0;
        if v.is_empty() {
            return json!(null);
        }
        v.sort_by(f64::total_cmp);
        let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
        json!({"min": q(0.0), "p25": q(0.25), "median": q(0.5), "p75": q(0.75), "max": q(1.0), "mean": v.iter().sum::<f64>() / v.len() as f64})
    }
}

fn write_manifest(path: &Path, value: &serde_json::Value) -> Result<()> {
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, serde_json::to_string_pretty(value)?)
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("renaming to {}", path.display()))?;
    Ok(())
}

pub fn gen_data(args: GenDataArgs) -> Result<()> {
    let (corpus, corpus_desc) = open_corpus(&args.corpus, args.seed)?;
    let corpus = Arc::new(corpus);
    let noback_cfg = ObjectSampleConfig {
        keep_images: true,
        ..ObjectSampleConfig::default()
    };
    let room_cfg = RoomSampleConfig::default();
    let workers = workers(args.workers);
    let config = json!({"seed": args.seed, "corpus": corpus_desc, "split": args.corpus.split, "noback": noback_cfg, "room": room_cfg,
        "noback_count": args.noback_count, "room_count": args.room_count, "workers": workers});
    println!(
        "gen-data seed {} config {}",
        args.seed,
        serde_json::to_string(&config)?
    );
    tracing::info!(seed = args.seed, objects = corpus.len(), out = %args.out.display(), "gen-data");
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;

    let mut used = std::collections::BTreeSet::new();
    // Object alone: a BOP dataset (depth + masks + poses) of the rendered views.
    let g = Arc::new(ObjectSampleGenerator::new(
        corpus.clone(),
        noback_cfg,
        args.seed,
    )?);
    let mut writer = BopWriter::create(args.out.join("noback"), BopWriteOptions::default())?;
    let bar = progress(args.noback_count, "noback");
    let (mut inliers, mut voxels) = (Stats::default(), Stats::default());
    let gg = g.clone();
    for s in Prefetcher::new(0, Some(args.noback_count), workers, 4, move |i| {
        gg.sample(i)
    }) {
        let s = s?;
        let obj = corpus.object(
            corpus
                .position(&s.object_id)
                .context("object not in corpus")?,
        )?;
        writer.add(&s.bop_frame(&obj).context("images not kept")?)?;
        inliers.0.push(s.inlier_count() as f64);
        voxels.0.push(s.observed_voxels as f64);
        used.insert(s.object_id.clone());
        bar.inc(1);
    }
    bar.finish();
    let noback = writer.finish()?;

    let g = Arc::new(RoomSampleGenerator::new(
        corpus.clone(),
        room_cfg,
        args.seed,
    )?);
    let mut writer = BopWriter::create(args.out.join("room"), BopWriteOptions::default())?;
    let bar = progress(args.room_count, "room");
    let (mut rates, mut points) = (Stats::default(), Stats::default());
    let gg = g.clone();
    for s in Prefetcher::new(0, Some(args.room_count), workers, 2, move |i| gg.sample(i)) {
        let s = s?;
        let obj = corpus.object(
            corpus
                .position(&s.object_id)
                .context("object not in corpus")?,
        )?;
        writer.add(&s.bop_frame(&obj))?;
        rates.0.push(s.inlier_rate);
        points.0.push(s.scene_points.len() as f64);
        used.insert(s.object_id.clone());
        bar.inc(1);
    }
    bar.finish();
    let room = writer.finish()?;
    let below5 = rates.0.iter().filter(|&&r| r < 0.05).count();
    let mut clutter_cfg = ClutterConfig {
        fixed_sizes: true,
        full_masks: true,
        ..ClutterConfig::default()
    }
    .with_shadows(args.shadow_probability);
    if let Some(c) = &args.camera {
        clutter_cfg = clutter_cfg.with_camera(ic_train::camera_arg(c).context("--camera")?);
    }
    let clutter = if args.clutter_count > 0 {
        let g = Arc::new(ClutterGenerator::new(
            corpus.clone(),
            clutter_cfg.clone(),
            args.seed,
        )?);
        let mut writer = BopWriter::create(
            args.out.join("clutter"),
            BopWriteOptions {
                depth_scale: 0.1,
                ..BopWriteOptions::default()
            },
        )?;
        let bar = progress(args.clutter_count, "clutter");
        let mut counts = Stats::default();
        for s in Prefetcher::new(0, Some(args.clutter_count), workers, 2, move |i| g.scene(i)) {
            let s = s?;
            writer.add_clutter(&s)?;
            counts.0.push(s.objects.len() as f64);
            used.extend(s.objects.iter().map(|o| o.object.id.clone()));
            bar.inc(1);
        }
        bar.finish();
        let w = writer.finish()?;
        json!({"folder": "clutter", "images": w.images, "models": w.objects.len(), "objects_per_image": counts.summary(), "config": clutter_cfg})
    } else {
        Value::Null
    };
    let manifest = json!({
        "config": config,
        "corpus": corpus.info(),
        "objects_used": used,
        "noback": {"folder": "noback", "images": noback.images, "objects": noback.objects, "inliers": inliers.summary(), "observed_voxels": voxels.summary()},
        "room": {"folder": "room", "images": room.images, "objects": room.objects, "inlier_rate": rates.summary(), "below_5_percent": below5, "scene_points": points.summary()},
        "clutter": clutter,
        "units": "BOP files in mm; 1 normalised object unit = 100 mm",
    });
    write_manifest(&args.out.join("manifest.json"), &manifest)?;
    if corpus.skipped() > 0 {
        tracing::warn!(skipped = corpus.skipped(), "unreadable meshes were skipped");
    }
    println!("{}", serde_json::to_string_pretty(&manifest["room"])?);
    println!("wrote {}", args.out.display());
    Ok(())
}

pub fn export_cases(args: ExportArgs) -> Result<()> {
    let (corpus, corpus_desc) = open_corpus(&args.corpus, args.seed)?;
    let corpus = Arc::new(corpus);
    let workers = workers(args.workers);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let bar = progress(
        args.count,
        if args.set == CaseSet::Room {
            "room"
        } else {
            "noback"
        },
    );
    let mut cases = Vec::new();
    let config = match args.set {
        CaseSet::Noback => {
            let cfg = ObjectSampleConfig::default();
            let config = json!({"set": "noback", "seed": args.seed, "corpus": corpus_desc, "split": args.corpus.split, "count": args.count, "sample": cfg});
            println!(
                "export-cases seed {} config {}",
                args.seed,
                serde_json::to_string(&config)?
            );
            let g = Arc::new(ObjectSampleGenerator::new(corpus.clone(), cfg, args.seed)?);
            for s in Prefetcher::new(0, Some(args.count), workers, 4, move |i| g.sample(i)) {
                let s = s?;
                let name = format!("case_{:05}", s.index);
                write_object_case(args.out.join(&name), &s, args.seed)?;
                cases.push(
                    json!({"case": name, "object_id": s.object_id, "inliers": s.inlier_count()}),
                );
                bar.inc(1);
            }
            config
        }
        CaseSet::View => {
            let protocol: ic_data::SamplingProtocol = args.protocol.parse()?;
            let cfg = ObjectSampleConfig {
                copy_rotations: 0,
                scale_augmentation: None,
                keep_images: true,
                ..protocol.config()
            };
            let config = json!({"set": "view", "protocol": protocol.as_str(), "seed": args.seed, "corpus": corpus_desc, "split": args.corpus.split, "count": args.count, "sample": cfg});
            println!(
                "export-cases seed {} config {}",
                args.seed,
                serde_json::to_string(&config)?
            );
            let g = Arc::new(ObjectSampleGenerator::new(corpus.clone(), cfg, args.seed)?);
            for s in Prefetcher::new(0, Some(args.count), workers, 2, move |i| g.sample(i)) {
                let s = s?;
                let name = format!("case_{:05}", s.index);
                let object =
                    corpus.object(corpus.position(&s.object_id).with_context(|| {
                        format!("object {} is not in the corpus", s.object_id)
                    })?)?;
                ic_data::export::write_view_case(
                    args.out.join(&name),
                    &s,
                    &object.mesh,
                    args.seed,
                )?;
                cases.push(json!({"case": name, "object_id": s.object_id, "inliers": s.inlier_count(), "observed_voxels": s.observed_voxels}));
                bar.inc(1);
            }
            config
        }
        CaseSet::Room => {
            let cfg = RoomSampleConfig::default();
            let config = json!({"set": "room", "seed": args.seed, "corpus": corpus_desc, "split": args.corpus.split, "count": args.count, "sample": cfg});
            println!(
                "export-cases seed {} config {}",
                args.seed,
                serde_json::to_string(&config)?
            );
            let g = Arc::new(RoomSampleGenerator::new(corpus.clone(), cfg, args.seed)?);
            for s in Prefetcher::new(0, Some(args.count), workers, 2, move |i| g.sample(i)) {
                let s = s?;
                let name = format!("case_{:05}", s.index);
                write_room_case(args.out.join(&name), &s, args.seed)?;
                cases.push(json!({"case": name, "object_id": s.object_id, "inlier_rate": s.inlier_rate, "scene_points": s.scene_points.len()}));
                bar.inc(1);
            }
            config
        }
    };
    bar.finish();
    write_manifest(
        &args.out.join("manifest.json"),
        &json!({"config": config, "corpus": corpus.info(), "cases": cases}),
    )?;
    tracing::info!(count = cases.len(), out = %args.out.display(), "export-cases done");
    println!("wrote {} cases to {}", cases.len(), args.out.display());
    Ok(())
}
