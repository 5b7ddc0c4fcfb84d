//! A whole `register` at 640×480 with the shipped networks: segmentation network, pose
//! network, hypotheses, ICP and render-and-compare verification, on the demo's scenes (a
//! procedural object in a procedural room, Kinect-like camera, depth in normalised units).
//!
//! - `register_640x480/verified_k24`: the default of `register` (the clutter segmentation
//!   network, and the one-object network when nothing is `ok`; 24 rotated copies, the best 8
//!   refined and verified);
//! - `register_640x480/paper_k1`: `--rotations 1`, the paper's single pass;
//! - `register_640x480/clutter15_verified_k24`: the default of `register` on a table, bin or
//!   shelf of 15 procedural objects (metres, sensor model on; the target chosen among the
//!   instances);
//! - `baseline/sum_300k_points`: the in-run baseline that ratios are taken to.
//!
//! The object (mesh normalised and sampled) is prepared once, outside the timing, as an
//! application registering the same object in many frames would (the pose network then keeps
//! each object's model side, `ic_pose::PoseEstimator`). After the timings, the mean seconds of
//! every stage over the scenes, for K = 1, 12, 24 and 60 rotated copies, on each object's
//! first frame and on the frames after it, are printed and written to
//! `target/register-stages.json`.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use ic_data::{ClutterConfig, ClutterGenerator, Corpus, CorpusOptions, Split};
use ic_geometry::{DepthImage, Intrinsics};
use incontext::{Object, Pipeline, PipelineOptions, StageSeconds};
use std::sync::Arc;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The demo's scenes `seed` (`incontext demo --seed S`): depth (normalised units), camera and
/// the prepared object.
fn scene(seed: u64) -> (DepthImage, Intrinsics, Object) {
    let scene = incontext::demo::DemoScene::new(seed).unwrap();
    let object = Object::from_mesh((*scene.object.mesh).clone(), seed).unwrap();
    (scene.view.depth, scene.view.intrinsics, object)
}

fn baseline(c: &mut Criterion) {
    // SAFETY: the first benchmark, before any pool thread exists.
    unsafe { ic_pose::tune_candle_cpu_pool() };
    let points: Vec<ic_geometry::glam::Vec3> = (0..300_000)
        .map(|i| ic_geometry::glam::Vec3::splat(i as f32 * 1e-5))
        .collect();
    c.bench_function("baseline/sum_300k_points", |b| {
        b.iter(|| {
            black_box(&points)
                .iter()
                .copied()
                .sum::<ic_geometry::glam::Vec3>()
        })
    });
}

/// `register` (the segmentation network choosing the pixels) on the scenes in turn.
fn bench_scenes(
    group: &mut criterion::BenchmarkGroup<'_, criterion::measurement::WallTime>,
    label: &str,
    pipeline: &Pipeline,
    scenes: &[(DepthImage, Intrinsics, Object)],
) {
    let mut i = 0usize;
    group.bench_function(label, |b| {
        b.iter(|| {
            let (depth, k, object) = &scenes[i % scenes.len()];
            i += 1;
            black_box(
                pipeline
                    .register_depth_normalised(object, depth, k, None, 0)
                    .is_ok(),
            )
        })
    });
}

fn register(c: &mut Criterion) {
    let scenes: Vec<_> = (1..=3).map(scene).collect();
    let pipeline = |rotations: usize| {
        let options = PipelineOptions {
            rotations,
            ..PipelineOptions::default()
        };
        Pipeline::builder().options(options).build().unwrap()
    };
    let mut group = c.benchmark_group("register_640x480");
    group.sample_size(10);
    for (label, rotations) in [("verified_k24", 24), ("paper_k1", 1)] {
        bench_scenes(&mut group, label, &pipeline(rotations), &scenes);
    }
    group.finish();
    // The split per stage for each rotation count K, averaged over the scenes: the first
    // pass (each object's first frame: its model side is computed) and the two passes after
    // it (the pose network finds the model side kept, `ic_pose::PoseEstimator`).
    let mut stages = serde_json::Map::new();
    for rotations in [1, 12, 24, 60] {
        let pipeline = pipeline(rotations);
        let mut first = StageSeconds::default();
        let mut later = StageSeconds::default();
        for pass in 0..3 {
            for (depth, k, object) in &scenes {
                let s = pipeline
                    .register_depth_normalised(object, depth, k, None, 0)
                    .unwrap()
                    .seconds;
                let sum = if pass == 0 { &mut first } else { &mut later };
                sum.segmentation_network += s.segmentation_network;
                sum.segmentation_post += s.segmentation_post;
                sum.observed_points += s.observed_points;
                sum.pose_network += s.pose_network;
                sum.ranking += s.ranking;
                sum.icp += s.icp;
                sum.verification += s.verification;
                sum.total += s.total;
            }
        }
        for (label, sum, n) in [
            ("", later, 2.0 * scenes.len() as f64),
            ("_first_frame", first, scenes.len() as f64),
        ] {
            let ms = |v: f64| (v / n * 1e4).round() / 10.0;
            let row = serde_json::json!({
                "segmentation_network_ms": ms(sum.segmentation_network),
                "segmentation_post_ms": ms(sum.segmentation_post),
                "observed_points_ms": ms(sum.observed_points),
                "pose_network_ms": ms(sum.pose_network),
                "ranking_ms": ms(sum.ranking),
                "icp_ms": ms(sum.icp),
                "verification_ms": ms(sum.verification),
                "other_ms": ms(sum.total - sum.segmentation_network - sum.segmentation_post
                    - sum.observed_points - sum.pose_network - sum.ranking - sum.icp - sum.verification),
                "total_ms": ms(sum.total),
            });
            eprintln!("register_640x480 K = {rotations}{label}: stages (mean of {n} runs): {row}");
            stages.insert(format!("k{rotations}{label}"), row);
        }
    }
    let target = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target");
    let _ = std::fs::create_dir_all(&target);
    let path = target.join("register-stages.json");
    std::fs::write(&path, serde_json::to_string_pretty(&stages).unwrap()).unwrap();
    eprintln!("wrote {}", path.display());
}

/// A clutter scene of `ic_data::clutter` with `objects` procedural objects at 640×480 (metres,
/// sensor model on): the depth in the target's normalised units and the prepared target.
fn clutter_scene(seed: u64, objects: usize) -> (DepthImage, Intrinsics, Object) {
    let options = CorpusOptions {
        model_points: 16,
        ..CorpusOptions::default()
    };
    let corpus = Arc::new(Corpus::procedural(24, Split::Test, seed, options).unwrap());
    let cfg = ClutterConfig {
        object_count: (objects, objects),
        fixed_sizes: true,
        multi_target_probability: 0.0,
        ..ClutterConfig::default()
    };
    let s = ClutterGenerator::new(corpus, cfg, seed)
        .unwrap()
        .scene(0)
        .unwrap();
    let target = &s.objects[0];
    let object = Object::from_mesh((*target.object.mesh).clone(), seed).unwrap();
    let scale = target.scale_m as f32;
    let mut depth = s.depth.clone();
    depth.data.iter_mut().for_each(|z| *z /= scale);
    (depth, s.intrinsics, object)
}

/// `register` with its defaults on tables, bins and shelves of 15 objects: the clutter
/// segmentation network (two outputs: objects and instance cores) finds every object so that
/// the target is chosen among them (up to [`PipelineOptions::instance_tries`] registrations),
/// and the one-object network is asked when none of those is `ok`.
fn register_clutter(c: &mut Criterion) {
    let scenes: Vec<_> = (1..=3).map(|s| clutter_scene(s, 15)).collect();
    let pipeline = Pipeline::builder().build().unwrap();
    assert!(pipeline.seg_one_object_source().is_some());
    let mut group = c.benchmark_group("register_640x480");
    group.sample_size(10);
    bench_scenes(&mut group, "clutter15_verified_k24", &pipeline, &scenes);
    group.finish();
    for (depth, k, object) in &scenes {
        match pipeline.register_depth_normalised(object, depth, k, None, 0) {
            Ok(r) => eprintln!(
                "register_640x480 clutter15: {} after {} tries of {} instances, stages {}",
                r.verdict.as_str(),
                r.instance.map_or(0, |i| i.rank + 1),
                r.instance.map_or(0, |i| i.candidates),
                serde_json::to_string(&r.seconds).unwrap()
            ),
            Err(e) => eprintln!("register_640x480 clutter15: {e}"),
        }
    }
}

criterion_group!(benches, baseline, register, register_clutter);
criterion_main!(benches);
