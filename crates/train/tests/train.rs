//! The training loop end to end on tiny data (procedural objects, the `tiny` presets, a few
//! iterations): a resumed run gives the numbers of an uninterrupted one, the CSV continues
//! without duplicated or missing iterations, and a stop request or a deadline saves a
//! checkpoint. Seconds each.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use ic_data::{Corpus, CorpusOptions, Split};
use ic_train::{Ending, RunControl};

fn pose_args(out: &Path, iterations: u64, resume: bool) -> ic_train::pose::TrainArgs {
    ic_train::pose::TrainArgs {
        preset: "tiny".into(),
        head: None,
        objects: "procedural@3:1".into(),
        protocol: "paper".into(),
        paper_fraction: 0.0,
        paper_objects: None,
        init: None,
        out: out.to_path_buf(),
        iterations: Some(iterations),
        seed: 7,
        resume,
        threads: None,
        data_workers: 1,
        checkpoint_secs: 300,
        batch_size: None,
        emb_dims: None,
        ff_dims: None,
        k: None,
        pooled_keys: None,
        model_points: None,
        observed_points: None,
        learning_rate: None,
        validate_every: Some(2),
        validation_count: Some(2),
        precise_bn: 0,
        lr_decay_to: None,
        lr_floor: 1e-5,
    }
}

fn never() -> &'static AtomicBool {
    static NEVER: AtomicBool = AtomicBool::new(false);
    &NEVER
}

fn control(stop: &AtomicBool) -> RunControl<'_> {
    RunControl {
        stop,
        deadline: None,
        checkpoint_secs: 300,
    }
}

/// The CSV rows without the timing columns (`samples_per_s`/`scenes_per_s`, `elapsed_s`) and,
/// after a resume, without the running averages (they restart with the process).
fn rows(path: &Path, keep: &[usize]) -> Vec<String> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .map(|l| {
            let cols: Vec<&str> = l.split(',').collect();
            keep.iter().map(|&i| cols[i]).collect::<Vec<_>>().join(",")
        })
        .collect()
}

fn iterations_of(path: &Path) -> Vec<u64> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect()
}

/// The same tensors bit for bit and the same metadata (as JSON values: the header's key
/// order follows a hash map's).
#[track_caller]
fn assert_same_checkpoint(a: &Path, b: &Path) {
    let tensors = |p: &Path| {
        let mut t: Vec<(String, Vec<u32>)> =
            candle_core::safetensors::load(p, &candle_core::Device::Cpu)
                .unwrap()
                .into_iter()
                .map(|(k, v)| {
                    let bits = v.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                    (k, bits.iter().map(|x| x.to_bits()).collect())
                })
                .collect();
        t.sort();
        t
    };
    let meta = |p: &Path| -> std::collections::BTreeMap<String, serde_json::Value> {
        ic_nn::checkpoint::read_metadata(p)
            .unwrap()
            .into_iter()
            .map(|(k, v)| (k, serde_json::from_str(&v).unwrap()))
            .collect()
    };
    assert!(
        tensors(a) == tensors(b),
        "{} vs {}: tensors",
        a.display(),
        b.display()
    );
    assert_eq!(meta(a), meta(b), "{} vs {}", a.display(), b.display());
}

#[test]
fn a_paper_fraction_mixes_the_papers_samples_into_a_deployment_run() {
    // The draw: the share asked for, seeded, none at 0 and all at 1.
    let share = |f: f64| {
        (0..4000)
            .filter(|&i| ic_train::pose::is_paper_sample(5, i, f))
            .count()
    };
    assert!((900..1100).contains(&share(0.25)), "{}", share(0.25));
    assert_eq!((share(0.0), share(1.0)), (0, 4000));
    assert_eq!(share(0.25), share(0.25));
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, fraction: f64| {
        let out = dir.path().join(name);
        let args = ic_train::pose::TrainArgs {
            protocol: "deployment".into(),
            paper_fraction: fraction,
            ..pose_args(&out, 1, false)
        };
        ic_train::pose::train(&args, control(never())).map(|_| out)
    };
    let (plain, paper) = (run("plain", 0.0).unwrap(), run("paper", 1.0).unwrap());
    let data = |d: &Path| std::fs::read_to_string(d.join("data.json")).unwrap();
    assert!(!data(&plain).contains("paper_fraction"));
    assert!(
        data(&paper).contains("\"paper_fraction\": 1.0"),
        "{}",
        data(&paper)
    );
    // Paper samples instead of deployment ones: other weights after the same step.
    let weights = |d: &Path| {
        candle_core::safetensors::load(d.join("latest.safetensors"), &candle_core::Device::Cpu)
            .unwrap()
            .into_iter()
            .filter(|(k, _)| !k.starts_with("adam."))
            .map(|(k, v)| (k, v.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
            .collect::<std::collections::BTreeMap<_, _>>()
    };
    assert_ne!(weights(&plain), weights(&paper));
    // --paper-objects: the paper samples come from those objects instead of the run's
    // (recorded in data.json), and only with a paper share.
    let other_objects = {
        let out = dir.path().join("paper-other-objects");
        let args = ic_train::pose::TrainArgs {
            protocol: "deployment".into(),
            paper_fraction: 1.0,
            paper_objects: Some("procedural@5:1".into()),
            ..pose_args(&out, 1, false)
        };
        ic_train::pose::train(&args, control(never())).unwrap();
        out
    };
    assert!(
        data(&other_objects).contains("\"paper_objects\"")
            && data(&other_objects).contains("procedural@5:1"),
        "{}",
        data(&other_objects)
    );
    assert_ne!(weights(&other_objects), weights(&paper));
    let no_share = ic_train::pose::TrainArgs {
        protocol: "deployment".into(),
        paper_objects: Some("procedural@5:1".into()),
        ..pose_args(&dir.path().join("no-share"), 1, false)
    };
    let err = ic_train::pose::train(&no_share, control(never())).unwrap_err();
    assert!(format!("{err:#}").contains("--paper-objects"), "{err:#}");
    // Only with the deployment protocol, and only a share.
    let paper_protocol = ic_train::pose::TrainArgs {
        paper_fraction: 0.5,
        ..pose_args(&dir.path().join("bad"), 1, false)
    };
    let err = ic_train::pose::train(&paper_protocol, control(never())).unwrap_err();
    assert!(format!("{err:#}").contains("--paper-fraction"), "{err:#}");
    let err = run("too-much", 1.5).unwrap_err();
    assert!(
        format!("{err:#}").contains("--paper-fraction 1.5"),
        "{err:#}"
    );
}

#[test]
fn a_resumed_pose_run_matches_an_uninterrupted_one_and_its_csv_continues() {
    let dir = tempfile::tempdir().unwrap();
    let (straight, split) = (dir.path().join("straight"), dir.path().join("split"));
    let a = ic_train::pose::train(&pose_args(&straight, 3, false), control(never())).unwrap();
    assert_eq!((a.ending, a.iteration), (Ending::Finished, 3));
    let b1 = ic_train::pose::train(&pose_args(&split, 2, false), control(never())).unwrap();
    assert_eq!((b1.ending, b1.iteration), (Ending::Finished, 2));
    // A stale row past the checkpoint (a run killed between checkpoints) must go.
    let csv = split.join("train.csv");
    let mut text = std::fs::read_to_string(&csv).unwrap();
    text.push_str("3,9.99999,0.0000,9.99999,0.0000,0.0000,1.000,1.0\n");
    std::fs::write(&csv, text).unwrap();
    let b2 = ic_train::pose::train(&pose_args(&split, 3, true), control(never())).unwrap();
    assert_eq!(
        (b2.ending, b2.iteration, b2.iterations_run),
        (Ending::Finished, 3, 1)
    );

    assert_eq!(iterations_of(&split.join("train.csv")), [1, 2, 3]);
    assert_eq!(iterations_of(&split.join("val.csv")), [2, 3]);
    // loss, accuracy, matched fraction: the same numbers to the last digit written.
    let cols = [0, 1, 2, 5];
    assert_eq!(
        rows(&straight.join("train.csv"), &cols),
        rows(&split.join("train.csv"), &cols)
    );
    let val_cols = [0, 1, 2, 3, 4, 5, 6, 7, 9, 10];
    assert_eq!(
        rows(&straight.join("val.csv"), &val_cols),
        rows(&split.join("val.csv"), &val_cols)
    );
    // The weights (and Adam's moments, iteration, seed) are identical bit for bit.
    for file in ["final.safetensors", "latest.safetensors"] {
        assert_same_checkpoint(&straight.join(file), &split.join(file));
    }
    for file in [
        "data.json",
        "best.json",
        "best.safetensors",
        "symmetries.json",
    ] {
        assert!(split.join(file).is_file(), "{file}");
    }
    // Already done: nothing runs, nothing changes.
    let again = ic_train::pose::train(&pose_args(&split, 3, true), control(never())).unwrap();
    assert_eq!(again.ending, Ending::AlreadyDone);
    assert_eq!(iterations_of(&split.join("train.csv")), [1, 2, 3]);
}

#[test]
fn precise_bn_changes_only_the_running_statistics_not_the_training() {
    let dir = tempfile::tempdir().unwrap();
    let (plain, precise) = (dir.path().join("plain"), dir.path().join("precise"));
    ic_train::pose::train(&pose_args(&plain, 2, false), control(never())).unwrap();
    let args = ic_train::pose::TrainArgs {
        precise_bn: 2,
        ..pose_args(&precise, 2, false)
    };
    ic_train::pose::train(&args, control(never())).unwrap();
    // Training normalises with batch statistics: the same losses to the last digit.
    let cols = [0, 1, 2, 5];
    assert_eq!(
        rows(&plain.join("train.csv"), &cols),
        rows(&precise.join("train.csv"), &cols)
    );
    let load = |p: &Path| {
        candle_core::safetensors::load(p.join("final.safetensors"), &candle_core::Device::Cpu)
            .unwrap()
    };
    let (a, b) = (load(&plain), load(&precise));
    let same = |k: &str| {
        let bits = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        bits(&a[k]) == bits(&b[k])
    };
    let (mut stats, mut changed) = (0, 0);
    for k in a.keys() {
        if k.ends_with("running_mean") || k.ends_with("running_var") {
            stats += 1;
            changed += usize::from(!same(k));
        } else {
            assert!(same(k), "{k}: a weight changed");
        }
    }
    assert!(
        stats > 0 && changed == stats,
        "{changed} of {stats} statistics replaced"
    );
}

#[test]
fn a_learning_rate_decay_is_followed_across_a_resume_to_the_same_weights() {
    let dir = tempfile::tempdir().unwrap();
    let (straight, split) = (dir.path().join("straight"), dir.path().join("split"));
    let decayed =
        |out: &Path, iterations: u64, resume: bool, to: Option<u64>| ic_train::pose::TrainArgs {
            learning_rate: Some(1e-2),
            lr_decay_to: to,
            lr_floor: 1e-4,
            ..pose_args(out, iterations, resume)
        };
    ic_train::pose::train(&decayed(&straight, 4, false, Some(4)), control(never())).unwrap();
    ic_train::pose::train(&decayed(&split, 2, false, Some(4)), control(never())).unwrap();
    // Resumed without the flags (and without --learning-rate, which would end the decay):
    // the checkpoint carries the decay.
    let resumed = ic_train::pose::TrainArgs {
        learning_rate: None,
        ..decayed(&split, 4, true, None)
    };
    ic_train::pose::train(&resumed, control(never())).unwrap();
    assert_same_checkpoint(
        &straight.join("latest.safetensors"),
        &split.join("latest.safetensors"),
    );
    let state =
        ic_train::read_state::<ic_pose::PoseNet>(&straight.join("latest.safetensors")).unwrap();
    let decay = state.lr_decay.expect("the decay is saved");
    assert_eq!((decay.from, decay.to), (0, 4));
    assert_eq!((decay.start, decay.floor), (1e-2, 1e-4));
    // The rate saved with the configuration is the last step's: on the way down, not the floor.
    let cfg = ic_pose::checkpoint::read_config(&straight.join("latest.safetensors")).unwrap();
    assert_eq!(cfg.train.learning_rate, decay.rate(3));
    assert!(decay.rate(3) > 1e-4 && decay.rate(3) < decay.rate(1));
    // Without the decay the run ends elsewhere: the decay changed the training.
    let plain = dir.path().join("plain");
    let args = ic_train::pose::TrainArgs {
        learning_rate: Some(1e-2),
        ..pose_args(&plain, 4, false)
    };
    ic_train::pose::train(&args, control(never())).unwrap();
    let cols = [0, 1];
    assert_ne!(
        rows(&plain.join("train.csv"), &cols),
        rows(&straight.join("train.csv"), &cols)
    );
}

#[test]
fn a_half_cosine_decay_starts_at_its_rate_and_ends_at_its_floor() {
    let d = ic_train::LrDecay {
        from: 10,
        to: 20,
        start: 1e-3,
        floor: 1e-5,
    };
    assert_eq!(d.rate(0), 1e-3);
    assert_eq!(d.rate(10), 1e-3);
    assert!((d.rate(15) - (1e-3 + 1e-5) / 2.0).abs() < 1e-12);
    assert!(d.rate(12) > d.rate(15) && d.rate(15) > d.rate(18));
    assert_eq!(d.rate(20), 1e-5);
    assert_eq!(d.rate(1000), 1e-5);
}

#[test]
fn a_stop_request_or_a_deadline_saves_a_resumable_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    // The stop flag as a signal handler would set it: the run stops after one iteration.
    let stop = AtomicBool::new(true);
    let o = ic_train::pose::train(&pose_args(&out, 3, false), control(&stop)).unwrap();
    assert_eq!((o.ending, o.iteration), (Ending::Interrupted, 1));
    let latest = out.join("latest.safetensors");
    let state = ic_train::read_state::<ic_pose::PoseNet>(&latest).unwrap();
    assert_eq!((state.iteration, state.seed), (1, 7));
    assert!(!out.join("final.safetensors").exists());
    assert_eq!(iterations_of(&out.join("train.csv")), [1]);
    // A deadline already past: one more iteration, then checkpoint and final weights.
    let past = RunControl {
        deadline: Some(Instant::now()),
        ..control(never())
    };
    let o = ic_train::pose::train(&pose_args(&out, 3, true), past).unwrap();
    assert_eq!((o.ending, o.iteration), (Ending::TimeUp, 2));
    assert_eq!(
        ic_train::read_state::<ic_pose::PoseNet>(&latest)
            .unwrap()
            .iteration,
        2
    );
    assert!(ic_pose::PoseEstimator::load(out.join("final.safetensors")).is_ok());
    assert_eq!(iterations_of(&out.join("train.csv")), [1, 2]);
}

fn seg_args(out: &Path, iterations: u64, resume: bool) -> ic_train::seg::TrainArgs {
    ic_train::seg::TrainArgs {
        preset: "tiny".into(),
        scenes: "room".into(),
        room_fraction: 0.0,
        init: None,
        objects: "unused".into(),
        out: out.to_path_buf(),
        iterations: Some(iterations),
        seed: 3,
        resume,
        threads: None,
        data_workers: 1,
        checkpoint_secs: 300,
        validate_every: 2,
        validation_count: 2,
        batch_size: None,
        learning_rate: None,
        lr_decay_to: None,
        lr_floor: 1e-5,
        input: None,
        core_radius: None,
        balance_area: None,
        border_weight: None,
        shadow_probability: None,
    }
}

/// `eval-seg --scenes clutter` on `count` scenes of four procedural objects (seed 5) with the
/// checkpoint `model`, the report at `out`; every option at its default.
fn clutter_eval_args(model: PathBuf, count: u64, out: PathBuf) -> ic_train::seg::EvalArgs {
    ic_train::seg::EvalArgs {
        model,
        scenes: "clutter".into(),
        objects: "procedural@4:1".into(),
        split: "test".into(),
        count,
        seed: 5,
        geometric: false,
        depth_refine_px: None,
        pixel_threshold: None,
        support_height: None,
        support_plane_threshold: None,
        support_grow: false,
        out: Some(out),
        misses: None,
        oracle: false,
        oracle_maps: Vec::new(),
        core_radius: None,
        render_size: None,
        camera: None,
        shadow_probability: 0.0,
        threads: None,
    }
}

/// [`seg_args`] of a tiny two-output network on clutter scenes of four procedural objects.
fn clutter_args(out: &Path, iterations: u64) -> ic_train::seg::TrainArgs {
    ic_train::seg::TrainArgs {
        preset: "tiny-clutter".into(),
        scenes: "clutter".into(),
        objects: "procedural@4:1".into(),
        ..seg_args(out, iterations, false)
    }
}

fn seg_run(out: &Path, iterations: u64, resume: bool) -> ic_train::Outcome {
    let corpus = |split| {
        let options = CorpusOptions {
            model_points: 256,
            ..CorpusOptions::default()
        };
        Arc::new(Corpus::procedural(3, split, 5, options).unwrap())
    };
    ic_train::seg::train_objects(
        &seg_args(out, iterations, resume),
        None,
        corpus(Split::Train),
        corpus(Split::Test),
        control(never()),
    )
    .unwrap()
}

#[test]
fn a_resumed_segmentation_run_matches_an_uninterrupted_one() {
    let dir = tempfile::tempdir().unwrap();
    let (straight, split) = (dir.path().join("straight"), dir.path().join("split"));
    assert_eq!(seg_run(&straight, 3, false).iteration, 3);
    assert_eq!(seg_run(&split, 2, false).iteration, 2);
    let resumed = seg_run(&split, 3, true);
    assert_eq!(
        (resumed.ending, resumed.iterations_run),
        (Ending::Finished, 1)
    );
    assert_eq!(iterations_of(&split.join("train.csv")), [1, 2, 3]);
    let cols = [0, 1, 2];
    assert_eq!(
        rows(&straight.join("train.csv"), &cols),
        rows(&split.join("train.csv"), &cols)
    );
    for file in ["final.safetensors", "latest.safetensors"] {
        assert_same_checkpoint(&straight.join(file), &split.join(file));
    }
    assert!(ic_seg::Segmenter::load(&split.join("best.safetensors")).is_ok());
}

#[test]
fn a_clutter_segmentation_run_trains_two_outputs_and_validates_instances() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("clutter");
    let args = clutter_args(&out, 2);
    let o = ic_train::seg::train(&args, control(never())).unwrap();
    assert_eq!((o.ending, o.iteration), (Ending::Finished, 2));
    let header = std::fs::read_to_string(out.join("val.csv")).unwrap();
    assert!(
        header.starts_with("iteration,target_found_rate,recall,matched_iou_mean"),
        "{header}"
    );
    assert_eq!(iterations_of(&out.join("val.csv")), [2]);
    let seg = ic_seg::Segmenter::load(&out.join("final.safetensors")).unwrap();
    assert_eq!(seg.config().net.outputs, 2);
    // A one-output preset cannot train on clutter scenes (no core map to learn).
    let wrong = ic_train::seg::TrainArgs {
        preset: "tiny".into(),
        out: dir.path().join("wrong"),
        ..args
    };
    let err = ic_train::seg::train(&wrong, control(never())).unwrap_err();
    assert!(
        format!("{err:#}").contains("two- or four-output"),
        "{err:#}"
    );
    // `eval-seg --scenes clutter` scores it, one CSV row per scene, and draws a sheet of
    // each scene whose target it missed; the support instances only add instances.
    let eval = |support_height: Option<f32>, name: &str| {
        let report_path = dir.path().join(format!("{name}.json"));
        let misses = dir.path().join(format!("{name}-misses"));
        let args = ic_train::seg::EvalArgs {
            support_height,
            misses: Some(misses.clone()),
            ..clutter_eval_args(out.join("final.safetensors"), 3, report_path.clone())
        };
        let report = ic_train::seg::eval(&args).unwrap();
        let csv = std::fs::read_to_string(report_path.with_extension("csv")).unwrap();
        let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
        let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
        let (miss, best, pooled) = (
            col("target_miss"),
            col("target_best_iou"),
            col("target_best_iou_pooled"),
        );
        // Without extra input sizes the pooled candidates are the own size's instances.
        for row in csv.lines().skip(1) {
            let cols: Vec<&str> = row.split(',').collect();
            assert_eq!(cols[best], cols[pooled], "{row}");
        }
        assert_eq!(
            report["pooled_target_found_rate"],
            report["instances"]["target_found_rate"]
        );
        let missed: Vec<String> = csv
            .lines()
            .skip(1)
            .filter_map(|row| {
                let cols: Vec<&str> = row.split(',').collect();
                let kind = cols[miss];
                (!kind.is_empty())
                    .then(|| format!("miss-{:04}-{kind}.png", cols[0].parse::<u32>().unwrap()))
            })
            .collect();
        let mut drawn: Vec<String> = std::fs::read_dir(&misses)
            .map(|d| {
                d.map(|e| e.unwrap().file_name().into_string().unwrap())
                    .collect()
            })
            .unwrap_or_default();
        drawn.sort();
        assert_eq!(drawn, missed, "one sheet per missed target");
        for name in &drawn {
            let png = std::fs::read(misses.join(name)).unwrap();
            let size = |at: usize| u32::from_be_bytes(png[at..at + 4].try_into().unwrap());
            assert_eq!(
                (size(16), size(20)),
                (2 * 640, 480),
                "{name}: depth beside instances"
            );
        }
        report["instances"]["predictions_per_image"]
            .as_f64()
            .unwrap()
    };
    let plain = eval(None, "plain");
    let with_support = eval(Some(0.01), "support");
    assert!(with_support >= plain, "{with_support} < {plain}");
    // The same scenes at another size and with the projector's shadows, as asked.
    let report = ic_train::seg::eval(&ic_train::seg::EvalArgs {
        render_size: Some(vec![160, 120]),
        shadow_probability: 1.0,
        ..clutter_eval_args(
            out.join("final.safetensors"),
            2,
            dir.path().join("small-shadowed.json"),
        )
    })
    .unwrap();
    assert_eq!(report["resolution"], serde_json::json!([160, 120]));
    assert_eq!(report["clutter"]["intrinsics"]["width"], 160);
    assert_eq!(report["clutter"]["sensor"]["shadow_probability"], 1.0);
    assert_eq!(report["clutter"]["sensor"]["registration_probability"], 1.0);
    // `--oracle` scores the post-processing on the training targets (at the tiny network's
    // 32×24, which loses the smallest instances): more instances than the two-iteration
    // network finds; room scenes refuse it. `--oracle-maps` with every map of the network is
    // the same as `--oracle`.
    use ic_train::seg::OracleMap;
    let run = |scenes: &str, oracle: bool, maps: &[OracleMap], core_radius: Option<usize>| {
        ic_train::seg::eval(&ic_train::seg::EvalArgs {
            scenes: scenes.into(),
            oracle,
            oracle_maps: maps.to_vec(),
            core_radius,
            ..clutter_eval_args(
                out.join("final.safetensors"),
                4,
                dir.path()
                    .join(format!("{scenes}-{oracle}-{}.json", maps.len())),
            )
        })
    };
    let recall = |r: &serde_json::Value| r["instances"]["recall"].as_f64().unwrap();
    let perfect = run("clutter", true, &[], Some(1)).unwrap();
    let network = run("clutter", false, &[], None).unwrap();
    assert_eq!(
        (&perfect["oracle"], &network["oracle"]),
        (&true.into(), &false.into())
    );
    assert!(
        recall(&perfect) > recall(&network),
        "oracle {} network {}",
        recall(&perfect),
        recall(&network)
    );
    let every_map = run(
        "clutter",
        false,
        &[OracleMap::Object, OracleMap::Core],
        Some(1),
    )
    .unwrap();
    assert_eq!(every_map["instances"], perfect["instances"]);
    let core_only = run("clutter", false, &[OracleMap::Core], Some(1)).unwrap();
    assert_eq!(core_only["oracle_maps"], serde_json::json!(["core"]));
    // The tiny clutter network has no centre offsets to replace.
    let err = run("clutter", false, &[OracleMap::Offsets], None).unwrap_err();
    assert!(format!("{err:#}").contains("output map(s)"), "{err:#}");
    let err = run("room", true, &[], None).unwrap_err();
    assert!(format!("{err:#}").contains("--scenes clutter"), "{err:#}");
    let err = run("clutter", false, &[], Some(1)).unwrap_err();
    assert!(format!("{err:#}").contains("--core-radius"), "{err:#}");
}

#[test]
fn a_clutter_run_mixes_in_room_scenes_in_the_fraction_asked() {
    // The draw is seeded and uniform: about the fraction asked, the same for the same seed.
    let rooms = |seed: u64| {
        (0..4000)
            .filter(|&i| ic_train::seg::is_room_scene(seed, i, 0.25))
            .count()
    };
    let n = rooms(1);
    assert!((900..1100).contains(&n), "{n} room scenes of 4000 at 0.25");
    assert_eq!(rooms(1), n);
    assert_ne!(rooms(2), n);
    assert!((0..100).all(|i| !ic_train::seg::is_room_scene(1, i, 0.0)));
    assert!((0..100).all(|i| ic_train::seg::is_room_scene(1, i, 1.0)));
    // A mixed run trains; the fraction must be one and only go with clutter scenes.
    let dir = tempfile::tempdir().unwrap();
    let args = ic_train::seg::TrainArgs {
        room_fraction: 0.5,
        ..clutter_args(&dir.path().join("mixed"), 2)
    };
    let o = ic_train::seg::train(&args, control(never())).unwrap();
    assert_eq!((o.ending, o.iteration), (Ending::Finished, 2));
    for (scenes, fraction) in [("clutter", 1.5), ("room", 0.5)] {
        let bad = ic_train::seg::TrainArgs {
            preset: if scenes == "room" {
                "tiny"
            } else {
                "tiny-clutter"
            }
            .into(),
            scenes: scenes.into(),
            room_fraction: fraction,
            objects: "procedural@4:1".into(),
            ..seg_args(&dir.path().join(format!("bad-{scenes}")), 2, false)
        };
        let err = ic_train::seg::train(&bad, control(never())).unwrap_err();
        assert!(format!("{err:#}").contains("--room-fraction"), "{err:#}");
    }
}

#[test]
fn a_one_output_checkpoint_starts_a_two_output_network_with_its_head_widened() {
    let dir = tempfile::tempdir().unwrap();
    let room = dir.path().join("room");
    seg_run(&room, 1, false);
    let init = room.join("final.safetensors");
    let args = ic_train::seg::TrainArgs {
        preset: "tiny-clutter".into(),
        scenes: "clutter".into(),
        room_fraction: 0.0,
        ..seg_args(&dir.path().join("clutter"), 1, false)
    };
    let t = ic_train::seg::make_trainer(&args, &dir.path().join("none"), Some(&init)).unwrap();
    assert_eq!(t.config().net.outputs, 2);
    let widened = dir.path().join("widened.safetensors");
    t.save_weights(&widened).unwrap();
    let load = |p: &Path| candle_core::safetensors::load(p, &candle_core::Device::Cpu).unwrap();
    let (a, b) = (load(&init), load(&widened));
    let flat = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for (name, t) in &a {
        if name.starts_with("head.") {
            let w = flat(&b[name]);
            let (first, second) = w.split_at(w.len() / 2);
            assert_eq!((first, second), (&flat(t)[..], &flat(t)[..]), "{name}");
        } else {
            assert_eq!(flat(t), flat(&b[name]), "{name}");
        }
    }
    // Channels that differ are refused, naming the file.
    let wrong = ic_train::seg::TrainArgs {
        preset: "clutter".into(),
        ..args
    };
    let err = ic_train::seg::make_trainer(&wrong, &dir.path().join("none"), Some(&init))
        .err()
        .unwrap();
    assert!(format!("{err:#}").contains("final.safetensors"), "{err:#}");
}

/// A 64×48 depth map of a box (depth 2) on a floor that recedes row by row (3 + 0.02·row),
/// and its camera.
fn box_on_tilted_floor() -> (ic_geometry::DepthImage, ic_geometry::Intrinsics) {
    let (w, h) = (64u32, 48u32);
    let k = ic_geometry::Intrinsics::new(60.0, 60.0, 31.5, 23.5, w, h).unwrap();
    let mut depth = ic_geometry::DepthImage::filled(w, h, 0.0);
    for v in 0..h {
        for u in 0..w {
            let box_ = (20..40).contains(&u) && (10..30).contains(&v);
            depth.data[(v * w + u) as usize] = if box_ { 2.0 } else { 3.0 + 0.02 * v as f32 };
        }
    }
    (depth, k)
}

#[test]
fn a_depth_only_checkpoint_starts_a_network_with_normals_that_computes_the_same_until_trained() {
    let dir = tempfile::tempdir().unwrap();
    let room = dir.path().join("room");
    seg_run(&room, 2, false);
    let init = room.join("final.safetensors");
    let args = ic_train::seg::TrainArgs {
        input: Some("depth-normals".into()),
        ..seg_args(&dir.path().join("normals"), 1, false)
    };
    let t = ic_train::seg::make_trainer(&args, &dir.path().join("none"), Some(&init)).unwrap();
    assert_eq!(t.config().net.input, ic_seg::SegInput::DepthNormals);
    // The normals differ from pixel to pixel of this scene, and their weights are 0.
    let (depth, k) = box_on_tilted_floor();
    let before = ic_seg::Segmenter::load(&init).unwrap();
    let after = t.segmenter();
    let p = |s: &ic_seg::Segmenter| s.probabilities_small(&[(&depth, &k)]).unwrap().remove(0);
    let (a, b) = (p(&before), p(&after));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() < 1e-6, "{x} vs {y}");
    }
    // The new input channels' weights are zeros, the old ones copied.
    let saved = dir.path().join("normals.safetensors");
    t.save_weights(&saved).unwrap();
    let load = |p: &Path| candle_core::safetensors::load(p, &candle_core::Device::Cpu).unwrap();
    let (old, new) = (load(&init), load(&saved));
    // The network's first convolution (by name: the map's order is random).
    let first = "down0.a.conv.weight";
    assert_eq!(old[first].dim(1).unwrap(), 2);
    assert_eq!(new[first].dim(1).unwrap(), 5);
    let narrow = |t: &candle_core::Tensor, from: usize, len: usize| {
        t.narrow(1, from, len)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
    };
    assert_eq!(narrow(&new[first], 0, 2), narrow(&old[first], 0, 2));
    assert!(narrow(&new[first], 2, 3).iter().all(|&v| v == 0.0));
    // A network with normals cannot go back to depth alone.
    let back = ic_train::seg::TrainArgs {
        input: Some("depth".into()),
        ..seg_args(&dir.path().join("back"), 1, false)
    };
    let err = ic_train::seg::make_trainer(&back, &dir.path().join("none"), Some(&saved))
        .err()
        .unwrap();
    assert!(
        format!("{err:#}").contains("normals.safetensors"),
        "{err:#}"
    );
}

#[test]
fn a_resumed_segmentation_run_takes_a_new_learning_rate() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    seg_run(&out, 1, false);
    let latest = out.join("latest.safetensors");
    let args = ic_train::seg::TrainArgs {
        learning_rate: Some(1e-4),
        ..seg_args(&out, 2, true)
    };
    let t = ic_train::seg::make_trainer(&args, &latest, None).unwrap();
    assert_eq!((t.iteration(), t.config().train.learning_rate), (1, 1e-4));
    let kept = ic_train::seg::make_trainer(&seg_args(&out, 2, true), &latest, None).unwrap();
    assert_ne!(kept.config().train.learning_rate, 1e-4);
}

#[test]
fn exported_weights_are_the_checkpoints_weights_without_the_optimiser_state() {
    let dir = tempfile::tempdir().unwrap();
    let (pose, seg) = (dir.path().join("pose"), dir.path().join("seg"));
    // Two iterations, validated at the second: best.safetensors holds the weights of the
    // checkpoint, written as inference files are.
    ic_train::pose::train(&pose_args(&pose, 2, false), control(never())).unwrap();
    seg_run(&seg, 2, false);
    for (run, kind) in [
        (&pose, ic_train::CheckpointKind::Pose),
        (&seg, ic_train::CheckpointKind::Seg),
    ] {
        let out = run.join("exported.safetensors");
        let got = ic_train::export_weights(&run.join("latest.safetensors"), &out).unwrap();
        assert_eq!(got, kind);
        assert_same_checkpoint(&out, &run.join("best.safetensors"));
        let names = candle_core::safetensors::load(&out, &candle_core::Device::Cpu).unwrap();
        assert!(names.keys().all(|n| !n.starts_with("adam.")));
        // A weights-only file is refused, naming it.
        let err = ic_train::export_weights(&out, &run.join("again.safetensors")).unwrap_err();
        let msg = format!("{err:#}");
        assert!(
            msg.contains("exported.safetensors") && msg.contains("not a training checkpoint"),
            "{msg}"
        );
        assert!(!run.join("again.safetensors").exists());
    }
}

/// The shipped networks get their attention keys this way: the same tensors, bit for bit,
/// the configuration changed, from a weights-only or a training checkpoint; a segmentation
/// checkpoint or zero keys is refused and nothing is written.
#[test]
fn pooled_keys_are_written_into_the_configuration_of_the_same_weights() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("pose");
    ic_train::pose::train(&pose_args(&run, 2, false), control(never())).unwrap();
    let best = run.join("best.safetensors");
    let keyed = dir.path().join("keyed.safetensors");
    let load = |p: &Path| candle_core::safetensors::load(p, &candle_core::Device::Cpu).unwrap();
    for source in [best.clone(), run.join("latest.safetensors")] {
        ic_train::set_pooled_keys(&source, &keyed, Some(8)).unwrap();
        let config = ic_pose::checkpoint::read_config(&keyed).unwrap();
        assert_eq!(config.net.pooled_keys, Some(8));
        let (want, got) = (load(&best), load(&keyed));
        assert_eq!(want.len(), got.len());
        for (name, t) in &want {
            let flat = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            assert_eq!(flat(t), flat(&got[name]), "{name}");
        }
    }
    // And back to every point: the original file, bit for bit.
    let back = dir.path().join("back.safetensors");
    ic_train::set_pooled_keys(&keyed, &back, None).unwrap();
    assert_same_checkpoint(&back, &best);
    let refused = dir.path().join("refused.safetensors");
    assert!(ic_train::set_pooled_keys(&best, &refused, Some(0)).is_err());
    let seg = dir.path().join("seg");
    seg_run(&seg, 2, false);
    let err =
        ic_train::set_pooled_keys(&seg.join("best.safetensors"), &refused, Some(8)).unwrap_err();
    assert!(format!("{err:#}").contains("best.safetensors"), "{err:#}");
    assert!(!refused.exists());
}

#[test]
fn averaged_weights_are_the_element_wise_mean_and_one_file_averages_to_itself() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b, seg) = (
        dir.path().join("a"),
        dir.path().join("b"),
        dir.path().join("seg"),
    );
    ic_train::pose::train(&pose_args(&a, 2, false), control(never())).unwrap();
    let mut other = pose_args(&b, 2, false);
    other.seed = 8;
    ic_train::pose::train(&other, control(never())).unwrap();
    let (wa, wb) = (a.join("best.safetensors"), b.join("best.safetensors"));

    // One file: its own weights and configuration, bit for bit.
    let alone = dir.path().join("alone.safetensors");
    let kind = ic_train::average_weights(std::slice::from_ref(&wa), &alone).unwrap();
    assert_eq!(kind, ic_train::CheckpointKind::Pose);
    assert_same_checkpoint(&alone, &wa);

    // Two runs (one given as its training checkpoint): the mean of every tensor.
    let mean = dir.path().join("mean.safetensors");
    ic_train::average_weights(&[wa.clone(), b.join("latest.safetensors")], &mean).unwrap();
    let load = |p: &Path| candle_core::safetensors::load(p, &candle_core::Device::Cpu).unwrap();
    let (ta, tb, tm) = (load(&wa), load(&wb), load(&mean));
    assert_eq!(tm.len(), ta.len());
    let mut differing = 0;
    for (name, m) in &tm {
        let flat = |t: &candle_core::Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let (x, y, z) = (flat(&ta[name]), flat(&tb[name]), flat(m));
        differing += usize::from(x != y);
        for ((x, y), z) in x.iter().zip(&y).zip(&z) {
            let want = ((*x as f64 + *y as f64) / 2.0) as f32;
            assert_eq!(z.to_bits(), want.to_bits(), "{name}: {x} {y} → {z}");
        }
    }
    assert!(
        differing > 10,
        "the two runs must differ ({differing} tensors do)"
    );

    // A segmentation checkpoint among pose ones is refused, naming it; nothing is written.
    seg_run(&seg, 2, false);
    let refused = dir.path().join("refused.safetensors");
    let err = ic_train::average_weights(&[wa, seg.join("best.safetensors")], &refused).unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("seg") && msg.contains("Seg checkpoint"),
        "{msg}"
    );
    assert!(!refused.exists());
    // Nothing to average is an error, not an empty file.
    assert!(ic_train::average_weights(&[], &refused).is_err());
    assert!(!refused.exists());
}

#[test]
fn a_narrower_checkpoint_starts_a_wider_network_that_computes_the_same() {
    let dir = tempfile::tempdir().unwrap();
    let narrow_run = dir.path().join("narrow");
    let narrow_args = clutter_args(&narrow_run, 2);
    ic_train::seg::train(&narrow_args, control(never())).unwrap();
    let init = narrow_run.join("final.safetensors");
    let (depth, k) = box_on_tilted_floor();
    let p = |s: &ic_seg::Segmenter| s.probabilities_small(&[(&depth, &k)]).unwrap().remove(0);
    let before = p(&ic_seg::Segmenter::load(&init).unwrap());

    // Exact without noise: every copy shares its channel's weights.
    let narrow = ic_seg::checkpoint::read_config(&init).unwrap();
    let mut wide = ic_seg::SegConfig::preset("tiny-clutter-wide").unwrap();
    wide.net.input_width = narrow.net.input_width;
    wide.net.input_height = narrow.net.input_height;
    let tensors = candle_core::safetensors::load(&init, &candle_core::Device::Cpu).unwrap();
    let varmap = candle_nn::VarMap::new();
    let vb = candle_nn::VarBuilder::from_varmap(
        &varmap,
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    );
    let _ = ic_seg::unet::UNet::new(vb, &wide.net).unwrap();
    let names: Vec<String> = varmap.data().lock().unwrap().keys().cloned().collect();
    let widened = ic_train::widen::widen_unet(
        &tensors,
        &names,
        &narrow.net.channels,
        &wide.net.channels,
        0.0,
        7,
    )
    .unwrap();
    let vb = candle_nn::VarBuilder::from_tensors(
        widened,
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    );
    let net = ic_seg::unet::UNet::new(vb, &wide.net).unwrap();
    let exact = p(&ic_seg::Segmenter::from_parts(net, wide.clone()));
    assert_eq!(before.len(), exact.len());
    for (x, y) in before.iter().zip(&exact) {
        assert!((x - y).abs() < 1e-5, "{x} vs {y}");
    }

    // The training path: the wider preset from the narrower checkpoint, with the noise that
    // lets the copies part; the outputs stay close.
    let args = ic_train::seg::TrainArgs {
        preset: "tiny-clutter-wide".into(),
        ..narrow_args
    };
    let t = ic_train::seg::make_trainer(&args, &dir.path().join("none"), Some(&init)).unwrap();
    assert_eq!(t.config().net.channels, vec![6, 12]);
    let after = p(&t.segmenter());
    let worst = before
        .iter()
        .zip(&after)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(worst > 0.0 && worst < 0.05, "largest change {worst}");

    // A wider checkpoint does not start a narrower network.
    let wide_file = dir.path().join("wide.safetensors");
    t.save_weights(&wide_file).unwrap();
    let mut narrow_trainer = ic_train::SegTrainer::new(narrow.clone(), 1).unwrap();
    let err = narrow_trainer.load_widening(&wide_file).unwrap_err();
    assert!(err.to_string().contains("wide.safetensors"), "{err}");
}

#[test]
fn a_two_output_checkpoint_starts_a_four_output_network_with_the_same_maps_and_zero_offsets() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("two");
    let two_args = clutter_args(&run, 2);
    ic_train::seg::train(&two_args, control(never())).unwrap();
    let init = run.join("final.safetensors");
    let (depth, k) = box_on_tilted_floor();
    let p = |s: &ic_seg::Segmenter| s.probabilities_small(&[(&depth, &k)]).unwrap().remove(0);
    let before = p(&ic_seg::Segmenter::load(&init).unwrap());
    let args = ic_train::seg::TrainArgs {
        preset: "tiny-clutter-offsets".into(),
        ..two_args
    };
    let t = ic_train::seg::make_trainer(&args, &dir.path().join("none"), Some(&init)).unwrap();
    assert_eq!(t.config().net.outputs, 4);
    let after = p(&t.segmenter());
    assert_eq!(after.len(), 2 * before.len());
    let (maps, offsets) = after.split_at(before.len());
    for (x, y) in before.iter().zip(maps) {
        assert!((x - y).abs() < 1e-6, "{x} vs {y}");
    }
    assert!(
        offsets.iter().all(|&o| o == 0.0),
        "the offsets start at zero"
    );
    // And the four-output network trains on clutter scenes.
    let out = dir.path().join("four");
    let four = ic_train::seg::TrainArgs {
        init: Some(init.clone()),
        ..clutter_args(&out, 2)
    };
    let four = ic_train::seg::TrainArgs {
        preset: "tiny-clutter-offsets".into(),
        ..four
    };
    let outcome = ic_train::seg::train(&four, control(never())).unwrap();
    assert_eq!(outcome.iteration, 2);
    let trained = ic_seg::checkpoint::read_config(&out.join("final.safetensors")).unwrap();
    assert_eq!(trained.net.outputs, 4);
    assert!(trained.post.centres.is_some());
}

#[test]
fn a_four_output_checkpoint_starts_an_offset_branch_network_computing_the_same_and_trains_the_branch()
 {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("four");
    let with_preset = |preset: &str, out: &Path| ic_train::seg::TrainArgs {
        preset: preset.into(),
        ..clutter_args(out, 2)
    };
    ic_train::seg::train(&with_preset("tiny-clutter-offsets", &run), control(never())).unwrap();
    let init = run.join("final.safetensors");
    let (depth, k) = box_on_tilted_floor();
    let p = |s: &ic_seg::Segmenter| s.probabilities_small(&[(&depth, &k)]).unwrap().remove(0);
    let before = p(&ic_seg::Segmenter::load(&init).unwrap());
    assert!(before.iter().skip(before.len() / 2).any(|&o| o != 0.0));
    let coarse = with_preset("tiny-clutter-offsets-coarse", &run);
    let t = ic_train::seg::make_trainer(&coarse, &dir.path().join("none"), Some(&init)).unwrap();
    assert_eq!(t.config().net.offset_level, 1);
    let after = p(&t.segmenter());
    assert_eq!(after.len(), before.len());
    for (x, y) in before.iter().zip(&after) {
        assert!((x - y).abs() < 1e-6, "{x} vs {y}");
    }
    // Trained, the branch's head leaves zero and the checkpoint keeps the branch.
    let out = dir.path().join("coarse");
    let args = ic_train::seg::TrainArgs {
        init: Some(init.clone()),
        ..with_preset("tiny-clutter-offsets-coarse", &out)
    };
    ic_train::seg::train(&args, control(never())).unwrap();
    let file = out.join("final.safetensors");
    assert_eq!(
        ic_seg::checkpoint::read_config(&file)
            .unwrap()
            .net
            .offset_level,
        1
    );
    let tensors = candle_core::safetensors::load(&file, &candle_core::Device::Cpu).unwrap();
    let head = tensors["offsets.head.weight"]
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap();
    assert!(head.iter().any(|&w| w != 0.0), "the branch did not train");
    // A network without the branch does not take one that has it, and says which file.
    let plain = with_preset("tiny-clutter-offsets", &run);
    let mut t = ic_train::seg::make_trainer(&plain, &dir.path().join("none2"), None).unwrap();
    let err = t.load_widening(&file).unwrap_err().to_string();
    assert!(
        err.contains("final.safetensors") && err.contains("offset branch"),
        "{err}"
    );
}

#[test]
fn a_balanced_clutter_run_records_its_loss_weights_and_core_radius_and_a_resume_keeps_them() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("balanced");
    let args = ic_train::seg::TrainArgs {
        balance_area: Some(50.0),
        border_weight: Some(3.0),
        core_radius: Some(2),
        ..clutter_args(&out, 2)
    };
    let o = ic_train::seg::train(&args, control(never())).unwrap();
    assert_eq!((o.ending, o.iteration), (Ending::Finished, 2));
    let cfg = ic_seg::checkpoint::read_config(&out.join("latest.safetensors")).unwrap();
    let t = &cfg.train;
    assert_eq!(
        (t.balance_area, t.border_weight, t.core_radius),
        (50.0, 3.0, 2)
    );
    let with =
        |area: Option<f64>, border: Option<f64>, radius: Option<usize>| ic_train::seg::TrainArgs {
            balance_area: area,
            border_weight: border,
            core_radius: radius,
            resume: true,
            iterations: Some(3),
            ..clutter_args(&out, 3)
        };
    for (args, flag) in [
        (with(Some(60.0), None, None), "--balance-area"),
        (with(None, Some(1.0), None), "--border-weight"),
        (with(None, None, Some(1)), "--core-radius"),
    ] {
        let err = ic_train::seg::train(&args, control(never())).unwrap_err();
        assert!(format!("{err:#}").contains(flag), "{err:#}");
    }
}

#[test]
fn a_clutter_run_records_its_shadow_probability_and_a_resume_may_change_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("shadowed");
    let shadow = |p: Option<f64>, iterations: u64, resume: bool| ic_train::seg::TrainArgs {
        shadow_probability: p,
        resume,
        ..clutter_args(&out, iterations)
    };
    let read = || {
        ic_seg::checkpoint::read_config(&out.join("latest.safetensors"))
            .unwrap()
            .train
            .shadow_probability
    };
    let o = ic_train::seg::train(&shadow(Some(0.5), 2, false), control(never())).unwrap();
    assert_eq!((o.ending, o.iteration), (Ending::Finished, 2));
    assert_eq!(read(), 0.5);
    // A resume without the flag keeps it; with it, the scenes after the resume follow it.
    ic_train::seg::train(&shadow(None, 3, true), control(never())).unwrap();
    assert_eq!(read(), 0.5);
    ic_train::seg::train(&shadow(Some(1.0), 4, true), control(never())).unwrap();
    assert_eq!(read(), 1.0);
    // Not a probability: refused, naming it.
    let err = ic_train::seg::train(&shadow(Some(1.5), 5, true), control(never())).unwrap_err();
    assert!(format!("{err:#}").contains("shadow_probability"), "{err:#}");
}
