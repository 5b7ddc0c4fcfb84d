//! Stage 4 of `cargo xtask bench`: speed, measured in this process on this machine.
//!
//! - registration time of ours at the [`SIZES`] (the shipped preset's operating point, the
//!   paper's Table 3 sizes and its 1024 × 768 inference size): each of the first `pairs`
//!   object-alone cases' source and target resampled to m and n points (random subset, or
//!   repeats with 0.005 jitter when a cloud is smaller), `PoseEstimator::estimate` with and
//!   without ICP, one warm-up then `repeats` runs per pair, the median of the pairs' medians —
//!   the same cases and protocol as the peers' `--timing --cases DIR --timing-pairs K` mode (one
//!   pair stands for a whole set badly where a method's work depends on the pair, e.g.
//!   FPFH-RANSAC's 22–96 ms across the first ten cases at 384 × 288);
//! - segmentation of one 640×480 depth map (the first room case);
//! - CPU renderer views/s: a room scene at 640×480 and the object alone at 160×120;
//! - training pairs/hour: a few real `Trainer::step`s of the `cpu` preset per head on samples
//!   rendered from training objects, alone and with the sample rendering added (one thread).
//!
//! A model file that is absent is replaced by an untrained network of the same preset, and
//! the row says so: the time does not depend on the weights (ICP's iteration count can).

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use ic_data::export::CaseFolder;
use ic_data::{ObjectSampleConfig, ObjectSampleGenerator, RoomSampleConfig, Split};
use ic_geometry::glam::Vec3;
use ic_geometry::{Intrinsics, ViewSphere};
use ic_pose::{Head, PoseConfig, PoseEstimator, Refine};
use ic_render::{Background, CpuRenderer, Renderer, SceneBuilder, SceneConfig};
use ic_train::PoseTrainer as Trainer;
use serde::Serialize;

use crate::bench::cases::{CaseSet, Objects};
use crate::bench::run::{SEG_MODEL, pose_model};

/// (model, observed) point counts timed: the `cpu` preset's operating point (384 × 288, what
/// `register` feeds the network), the paper's Table 3 sizes (n × n) and the paper's inference
/// size (1024 × 768).
pub const SIZES: [(usize, usize); 5] = [
    (384, 288),
    (512, 512),
    (1024, 768),
    (1024, 1024),
    (2048, 2048),
];

/// The pooled attention keys of the speed table's extra softmax row (`ours-softmax-keysN`)
/// when the shipped weights attend over every point (`ic_pose::NetConfig::pooled_keys`).
pub const BENCH_POOLED_KEYS: usize = 64;

/// How a size is written in tables and in the peers' `--points`: `n`, or `mxn`.
pub fn size_label((m, n): (usize, usize)) -> String {
    if m == n {
        m.to_string()
    } else {
        format!("{m}x{n}")
    }
}

/// A timed quantity: median and every run (seconds).
#[derive(Clone, Debug, Serialize)]
pub struct Timed {
    pub label: String,
    /// The median of `runs`, or over several pairs the median of `pair_medians`.
    pub median_seconds: Option<f64>,
    pub runs: Vec<f64>,
    /// Timed on several pairs: each pair's median, in pair order (every pair counts once).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub pair_medians: Vec<f64>,
    /// E.g. "untrained weights (model file absent)".
    pub note: Option<String>,
    pub error: Option<String>,
}

impl Timed {
    /// Nothing measured yet.
    pub fn new(label: &str) -> Timed {
        Timed {
            label: label.to_string(),
            median_seconds: None,
            runs: Vec::new(),
            pair_medians: Vec::new(),
            note: None,
            error: None,
        }
    }
}

/// Registration time of one method at one size.
#[derive(Clone, Debug, Serialize)]
pub struct RegTiming {
    pub method: String,
    /// Model points.
    pub points: usize,
    /// Observed points.
    pub observed_points: usize,
    #[serde(flatten)]
    pub timed: Timed,
}

/// Training throughput of one head.
#[derive(Clone, Debug, Serialize)]
pub struct TrainTiming {
    pub head: String,
    pub batch: usize,
    pub model_points: usize,
    pub observed_points: usize,
    pub step: Timed,
    pub sample: Timed,
    /// batch · 3600 / median step seconds.
    pub pairs_per_hour_network: Option<f64>,
    /// batch · 3600 / (median step + batch · median sample seconds): one thread rendering its
    /// own samples.
    pub pairs_per_hour_with_rendering: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Speed {
    pub threads: usize,
    pub repeats: usize,
    /// Object-alone cases each registration time is measured on.
    pub pairs: usize,
    pub pair: String,
    pub ours: Vec<RegTiming>,
    pub segmentation: Timed,
    pub render: Vec<Timed>,
    pub training: Vec<TrainTiming>,
    /// The accuracy/speed curve over point counts and k (`--curve-cases`, 0: not measured).
    pub curve: Option<crate::bench::curve::SpeedCurve>,
}

/// SplitMix64: a tiny seeded generator for resampling (xtask has no `rand`).
pub struct SplitMix(pub u64);

impl SplitMix {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }

    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn normal(&mut self) -> f32 {
        let (u, v) = (self.unit().max(1e-300), self.unit());
        ((-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
    }
}

/// The `index`-th case's source and target resampled to m and n points: the speed table and
/// the accuracy/speed curve draw the same points from the same case (the first case keeps the
/// draws of a one-pair run).
pub fn resample_pair(
    (source, target): (&[Vec3], &[Vec3]),
    (m, n): (usize, usize),
    seed: u64,
    index: usize,
) -> (Vec<Vec3>, Vec<Vec3>) {
    let key = if m == n {
        n as u64
    } else {
        (m as u64) << 32 | n as u64
    };
    let pair_key = (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut rng = SplitMix(seed ^ key.wrapping_mul(0x1000_0001) ^ pair_key);
    (resample(source, m, &mut rng), resample(target, n, &mut rng))
}

/// Exactly `n` points: a random subset in file order when there are enough, else all of them
/// plus random repeats jittered by N(0, 0.005²) per coordinate.
pub fn resample(points: &[Vec3], n: usize, rng: &mut SplitMix) -> Vec<Vec3> {
    if points.is_empty() {
        return Vec::new();
    }
    if points.len() >= n {
        let mut idx: Vec<usize> = (0..points.len()).collect();
        for i in 0..n {
            let j = i + rng.below(points.len() - i);
            idx.swap(i, j);
        }
        let mut keep = idx[..n].to_vec();
        keep.sort_unstable();
        return keep.into_iter().map(|i| points[i]).collect();
    }
    let mut out = points.to_vec();
    while out.len() < n {
        let p = points[rng.below(points.len())];
        out.push(p + 0.005 * Vec3::new(rng.normal(), rng.normal(), rng.normal()));
    }
    out
}

/// One warm-up call, then `repeats` timed calls.
pub(crate) fn time_it<T, E: std::fmt::Display>(
    label: &str,
    repeats: usize,
    mut f: impl FnMut() -> Result<T, E>,
) -> Timed {
    let mut timed = Timed::new(label);
    if let Err(e) = f() {
        timed.error = Some(e.to_string());
        return timed;
    }
    for _ in 0..repeats.max(1) {
        let t0 = Instant::now();
        let r = f();
        let s = t0.elapsed().as_secs_f64();
        if let Err(e) = r {
            timed.error = Some(e.to_string());
            return timed;
        }
        timed.runs.push(s);
    }
    timed.median_seconds = Some(ic_eval::median(&timed.runs));
    timed
}

/// One quantity timed on several pairs (each by [`time_it`]): every run, each pair's median and
/// the median of those; the first error ends it.
pub(crate) fn combine_pairs(label: &str, pairs: Vec<Timed>) -> Timed {
    let mut out = Timed::new(label);
    for t in pairs {
        if t.error.is_some() {
            out.error = t.error;
            return out;
        }
        out.runs.extend(&t.runs);
        out.pair_medians.extend(t.median_seconds);
    }
    if !out.pair_medians.is_empty() {
        out.median_seconds = Some(ic_eval::median(&out.pair_medians));
    }
    out
}

/// `est.estimate` timed on each pair (one warm-up and `repeats` runs) and combined by
/// [`combine_pairs`], and the last failed recovery's message: a failure still ran the network,
/// so its time counts.
pub(crate) fn time_estimates(
    est: &PoseEstimator,
    label: &str,
    repeats: usize,
    pairs: &[(Vec<Vec3>, Vec<Vec3>)],
) -> (Timed, Option<String>) {
    let mut failure = None;
    let per_pair = pairs
        .iter()
        .map(|(x, y)| {
            time_it(label, repeats, || {
                if let Err(e) = est.estimate(x, y) {
                    failure = Some(e.to_string());
                }
                Ok::<_, std::convert::Infallible>(())
            })
        })
        .collect();
    (combine_pairs(label, per_pair), failure)
}

pub(crate) fn read_points(path: &Path) -> Result<Vec<Vec3>> {
    Ok(ic_geometry::io::read_ply_cloud(path)
        .with_context(|| format!("reading {}", path.display()))?
        .points)
}

/// The estimator for `head`: the shipped model, or an untrained network (with a note).
pub(crate) fn estimator(
    root: &Path,
    head: Head,
    seed: u64,
) -> Result<(PoseEstimator, Option<String>)> {
    let path = root.join(pose_model(head.as_str()));
    if path.is_file() {
        let e =
            PoseEstimator::load(&path).with_context(|| format!("loading {}", path.display()))?;
        return Ok((e, None));
    }
    let t = Trainer::new(PoseConfig::cpu(head), seed)?;
    Ok((
        t.estimator(),
        Some(format!(
            "untrained cpu-preset weights: {} is absent",
            pose_model(head.as_str()).display()
        )),
    ))
}

#[allow(clippy::too_many_arguments)]
pub fn measure(
    root: &Path,
    noback: &CaseSet,
    room: &CaseSet,
    objects: &Objects,
    seed: u64,
    threads: usize,
    repeats: usize,
    pairs: usize,
    train_steps: usize,
) -> Result<Speed> {
    let folder = CaseFolder::new(&noback.dir);
    let pairs = pairs.clamp(1, noback.count.max(1) as usize);
    let clouds = (0..pairs)
        .map(|i| {
            let case = folder.child(i as u64);
            Ok((read_points(&case.source())?, read_points(&case.target())?))
        })
        .collect::<Result<Vec<_>>>()?;
    let total = (SIZES.len() * 5 + 1 + 2 + 2) as u64;
    let bar = crate::bench::common::progress_bar(total, "speed");

    // Registration at each size.
    let mut ours = Vec::new();
    for head in [Head::Softmax, Head::Ot] {
        let (mut est, note) = estimator(root, head, seed)?;
        // The softmax weights' one-shot pose with the other attention too: over
        // `BENCH_POOLED_KEYS` keys when they were trained with every point, else over every
        // point.
        let mut other = match (head, est.config().net.pooled_keys) {
            (Head::Ot, _) => None,
            (Head::Softmax, None) => Some((
                format!("ours-softmax-keys{BENCH_POOLED_KEYS}"),
                estimator(root, head, seed)?
                    .0
                    .with_pooled_keys(Some(BENCH_POOLED_KEYS))?,
            )),
            (Head::Softmax, Some(_)) => Some((
                "ours-softmax-all-keys".to_string(),
                estimator(root, head, seed)?.0.with_pooled_keys(None)?,
            )),
        };
        for &(m, n) in &SIZES {
            let resampled: Vec<_> = clouds
                .iter()
                .enumerate()
                .map(|(i, (source, target))| resample_pair((source, target), (m, n), seed, i))
                .collect();
            let mut runs: Vec<(String, Refine, bool)> = [Refine::None, Refine::Icp]
                .into_iter()
                .map(|refine| {
                    let icp = if refine == Refine::Icp { "-icp" } else { "" };
                    (format!("ours-{}{icp}", head.as_str()), refine, false)
                })
                .collect();
            if let Some((name, _)) = &other {
                runs.push((name.clone(), Refine::None, true));
            }
            for (method, refine, other_keys) in runs {
                let est = match (&mut other, other_keys) {
                    (Some((_, e)), true) => e,
                    _ => &mut est,
                };
                est.recovery.refine = refine;
                bar.set_message(format!("{method} n={}", size_label((m, n))));
                // A failed recovery (untrained weights can give degenerate matches) still ran
                // the network: time it, and say so.
                let (mut timed, failure) = time_estimates(est, &method, repeats, &resampled);
                timed.note = match (note.clone(), failure) {
                    (n, None) => n,
                    (n, Some(f)) => Some(
                        n.map_or(String::new(), |n| format!("{n}; "))
                            + &format!("the pose recovery failed ({f}), the time still counts it"),
                    ),
                };
                tracing::info!(method, m, n, median = ?timed.median_seconds, "registration time");
                ours.push(RegTiming {
                    method,
                    points: m,
                    observed_points: n,
                    timed,
                });
                bar.inc(1);
            }
        }
    }

    // Segmentation of one 640×480 map.
    bar.set_message("segmentation");
    let segmentation = segmentation_time(root, room, seed, repeats)?;
    tracing::info!(median = ?segmentation.median_seconds, "segmentation time");
    bar.inc(1);

    // Renderer views/s.
    let corpus = Arc::new(objects.corpus(Split::Test, seed)?);
    let mesh = corpus.object(0)?.mesh.clone();
    let mut renderer = CpuRenderer::new();
    let mut render = Vec::new();
    let alone = SceneConfig {
        background: Background::None,
        intrinsics: ObjectSampleConfig::default().intrinsics,
        view: ViewSphere::paper(2.8),
        ..SceneConfig::object_only()
    };
    for (label, cfg) in [
        (
            "CPU renderer, room scene 640×480",
            RoomSampleConfig::default().scene,
        ),
        ("CPU renderer, object alone 160×120", alone),
    ] {
        bar.set_message(label);
        let built = SceneBuilder::new(cfg)?.build(&mesh, seed)?;
        let t = time_it(label, repeats.max(10), || {
            renderer.render(&built.scene, &built.camera)
        });
        tracing::info!(label, median = ?t.median_seconds, "render time");
        render.push(t);
        bar.inc(1);
    }

    // Training steps.
    let train_corpus = Arc::new(objects.corpus(Split::Train, seed)?);
    let mut training = Vec::new();
    for head in [Head::Softmax, Head::Ot] {
        bar.set_message(format!("train step {}", head.as_str()));
        let cfg = PoseConfig::cpu(head);
        let (m, n, b) = (
            cfg.train.model_points,
            cfg.train.observed_points,
            cfg.train.batch_size,
        );
        let g = ObjectSampleGenerator::new(
            train_corpus.clone(),
            ObjectSampleConfig {
                model_points: m,
                observed_points: n,
                ..ObjectSampleConfig::default()
            },
            seed,
        )?;
        // Draw the samples once (this loads and caches their objects, as a training run does
        // once per object), then time drawing them again.
        let count = (train_steps.max(1) + 1) * b;
        let mut samples = (0..count as u64)
            .map(|i| g.sample(i))
            .collect::<Result<Vec<_>, _>>()?;
        let mut sample_runs = Vec::new();
        for i in 0..count as u64 {
            let t0 = Instant::now();
            let again = g.sample(i)?;
            sample_runs.push(t0.elapsed().as_secs_f64());
            samples[i as usize] = again;
        }
        let batches: Vec<Vec<_>> = samples.chunks(b).map(|c| c.to_vec()).collect();
        let mut trainer = Trainer::new(cfg, seed)?;
        let mut k = 0;
        let step = time_it(
            &format!("train step {} batch {b}", head.as_str()),
            train_steps,
            || {
                let r = trainer.step(&batches[k % batches.len()]);
                k += 1;
                r
            },
        );
        let sample = Timed {
            label: format!(
                "render + sample one training pair, {} preset ({m}/{n} points)",
                head.as_str()
            ),
            median_seconds: Some(ic_eval::median(&sample_runs)),
            runs: sample_runs,
            pair_medians: Vec::new(),
            note: Some("objects already loaded (a training run loads each once)".into()),
            error: None,
        };
        let per_hour = |s: f64| b as f64 * 3600.0 / s;
        let net = step.median_seconds;
        let with = net
            .zip(sample.median_seconds)
            .map(|(s, r)| s + b as f64 * r);
        tracing::info!(head = head.as_str(), step = ?net, "training step");
        training.push(TrainTiming {
            head: head.as_str().into(),
            batch: b,
            model_points: m,
            observed_points: n,
            pairs_per_hour_network: net.map(per_hour),
            pairs_per_hour_with_rendering: with.map(per_hour),
            step,
            sample,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(Speed {
        threads,
        repeats,
        pairs,
        pair: format!(
            "the first {} of `{}`: source.ply and target.ply resampled to m and n points",
            if pairs == 1 {
                "case".to_string()
            } else {
                format!("{pairs} cases")
            },
            crate::bench::common::rel(&noback.dir).display()
        ),
        ours,
        segmentation,
        render,
        training,
        curve: None,
    })
}

fn segmentation_time(root: &Path, room: &CaseSet, seed: u64, repeats: usize) -> Result<Timed> {
    let case = CaseFolder::new(&room.dir).child(0);
    let cam: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(case.camera())
            .with_context(|| format!("reading {}", case.camera().display()))?,
    )?;
    let k: Vec<f64> = cam["cam_K"]
        .as_array()
        .context("camera.json: no cam_K")?
        .iter()
        .filter_map(|v| v.as_f64())
        .collect();
    let (w, h) = (
        cam["width"].as_u64().unwrap_or(640) as u32,
        cam["height"].as_u64().unwrap_or(480) as u32,
    );
    let intrinsics = Intrinsics::new(k[0], k[4], k[2], k[5], w, h)?;
    let scale = cam["depth_scale"].as_f64().unwrap_or(1.0);
    let unit_mm = cam["unit_mm"].as_f64().unwrap_or(100.0);
    let mut depth = ic_render::io::read_depth_png(case.depth(), scale, Some((w, h)))?;
    // Metres → normalised units, as the network was trained.
    for z in &mut depth.data {
        *z = (*z as f64 * 1000.0 / unit_mm) as f32;
    }
    let path = root.join(SEG_MODEL);
    let (seg, note) = if path.is_file() {
        (
            ic_seg::Segmenter::load(&path)
                .with_context(|| format!("loading {}", path.display()))?,
            None,
        )
    } else {
        (
            ic_train::SegTrainer::new(ic_seg::SegConfig::cpu(), seed)?.segmenter(),
            Some(format!(
                "untrained cpu-preset weights: {SEG_MODEL} is absent"
            )),
        )
    };
    let label = format!("segmentation {w}×{h}");
    // "Object not found" is an answer, not a failure, for timing.
    let mut t = time_it(&label, repeats, || {
        Ok::<_, std::convert::Infallible>(seg.segment(&depth, &intrinsics).is_ok())
    });
    t.note = note;
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resample_gives_exact_counts_deterministically() {
        let pts: Vec<Vec3> = (0..100).map(|i| Vec3::splat(i as f32)).collect();
        let a = resample(&pts, 30, &mut SplitMix(1));
        assert_eq!(a.len(), 30);
        assert!(
            a.windows(2).all(|w| w[0].x < w[1].x),
            "file order, no repeats"
        );
        assert_eq!(a, resample(&pts, 30, &mut SplitMix(1)));
        let b = resample(&pts, 250, &mut SplitMix(1));
        assert_eq!(b.len(), 250);
        assert_eq!(&b[..100], &pts[..]);
        assert!(b[100..].iter().all(|p| (p.x - p.x.round()).abs() < 0.05));
        assert!(resample(&[], 5, &mut SplitMix(1)).is_empty());
    }

    fn timed(runs: &[f64]) -> Timed {
        Timed {
            median_seconds: Some(ic_eval::median(runs)),
            runs: runs.to_vec(),
            ..Timed::new("x")
        }
    }

    #[test]
    fn several_pairs_report_the_median_of_their_medians_not_of_the_pooled_runs() {
        // Pair medians 2, 7 and 3: median 3; the nine runs pooled would give 7.
        let t = combine_pairs(
            "x",
            vec![
                timed(&[1.0, 2.0, 9.0]),
                timed(&[7.0, 8.0, 7.0]),
                timed(&[3.0, 9.0, 2.0]),
            ],
        );
        assert_eq!(t.pair_medians, [2.0, 7.0, 3.0]);
        assert_eq!(t.median_seconds, Some(3.0));
        assert_eq!(t.runs.len(), 9);
        assert!(t.error.is_none());
        let mut failed = timed(&[]);
        failed.error = Some("boom".into());
        let t = combine_pairs("x", vec![timed(&[1.0]), failed]);
        assert_eq!((t.median_seconds, t.error.as_deref()), (None, Some("boom")));
    }
}
