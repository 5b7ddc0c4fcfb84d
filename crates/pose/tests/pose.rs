//! Behaviour tests of the pose network on tiny configurations (fast).

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use glam::{DVec3, Vec3};
use ic_data::Assignment;
use ic_geometry::Pose;
use ic_pose::adam::is_trainable;
use ic_pose::checkpoint::{self, CONFIG_KEY};
use ic_pose::{
    Head, Match, PairBatch, PoseConfig, PoseError, PoseEstimator, RecoveryOptions, nll_loss,
    recover_pose,
};
use ic_train::PoseTrainer as Trainer;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A synthetic pair: M random model points, N observed points of which the first `matched`
/// are moved model points (ground truth known) and the rest noise.
struct Pair {
    model: Vec<Vec3>,
    observed: Vec<Vec3>,
    assignment: Assignment,
    pose: Pose,
}

fn pair(seed: u64, m: usize, n: usize, matched: usize) -> Pair {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let model: Vec<Vec3> = (0..m)
        .map(|_| {
            Vec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
        })
        .collect();
    let pose = Pose::from_axis_angle(
        DVec3::new(rng.random(), rng.random(), rng.random()).normalize(),
        rng.random_range(0.0..3.0),
        DVec3::new(0.1, -0.2, 2.5),
    );
    let mut observed = Vec::with_capacity(n);
    let mut truth = Vec::with_capacity(n);
    for j in 0..n {
        if j < matched {
            let i = (j * 7 + 3) % m;
            observed.push(pose.apply_f32(model[i]));
            truth.push(Some(i as u32));
        } else {
            observed.push(Vec3::new(
                rng.random(),
                rng.random(),
                2.5 + rng.random::<f32>(),
            ));
            truth.push(None);
        }
    }
    Pair {
        assignment: Assignment {
            model_count: m,
            observed_count: n,
            observed_to_model: truth,
        },
        model,
        observed,
        pose,
    }
}

fn tiny(head: Head) -> PoseConfig {
    PoseConfig::tiny(head)
}

type PairRefs<'a> = (Vec<(&'a [Vec3], &'a [Vec3])>, Vec<&'a Assignment>);

fn refs(pairs: &[Pair]) -> PairRefs<'_> {
    (
        pairs
            .iter()
            .map(|p| (&p.model[..], &p.observed[..]))
            .collect(),
        pairs.iter().map(|p| &p.assignment).collect(),
    )
}

fn gradients_of(trainer: &Trainer, pairs: &[Pair]) -> (f32, HashMap<String, f32>) {
    let (pp, aa) = refs(pairs);
    let batch = PairBatch::new(&pp, trainer.config().net.k, &Device::Cpu).unwrap();
    let out = trainer.net().forward_t(&batch, true).unwrap();
    let loss = nll_loss(&out, &aa).unwrap();
    let grads = loss.backward().unwrap();
    let mut norms = HashMap::new();
    for (name, var) in trainer.varmap().data().lock().unwrap().iter() {
        if !is_trainable(name) {
            continue;
        }
        let g = grads
            .get(var.as_tensor())
            .map(|g| {
                g.abs()
                    .unwrap()
                    .sum_all()
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            })
            .unwrap_or(0.0);
        norms.insert(name.clone(), g);
    }
    (loss.to_scalar::<f32>().unwrap(), norms)
}

#[test]
fn every_parameter_receives_a_gradient() {
    for (head, pooled) in [
        (Head::Softmax, None),
        (Head::Ot, None),
        (Head::Softmax, Some(6)),
    ] {
        let mut cfg = tiny(head);
        cfg.net.pooled_keys = pooled;
        let trainer = Trainer::new(cfg, 3).unwrap();
        let pairs = vec![pair(1, 32, 24, 18), pair(2, 32, 24, 20)];
        let (loss, norms) = gradients_of(&trainer, &pairs);
        assert!(loss.is_finite() && loss > 0.0, "{head:?}: loss {loss}");
        assert!(
            norms.len() > 20,
            "{head:?}: only {} parameters",
            norms.len()
        );
        for (name, g) in &norms {
            assert!(g.is_finite() && *g > 0.0, "{head:?}: {name} gradient {g}");
        }
    }
}

#[test]
fn degenerate_inputs_give_finite_loss_and_gradients() {
    for head in [Head::Softmax, Head::Ot] {
        let trainer = Trainer::new(tiny(head), 4).unwrap();
        // All points identical, some "matched".
        let same = Pair {
            model: vec![Vec3::splat(0.3); 32],
            observed: vec![Vec3::new(0.0, 0.0, 2.0); 24],
            assignment: Assignment {
                model_count: 32,
                observed_count: 24,
                observed_to_model: (0..24).map(|j| (j % 3 == 0).then_some(j as u32)).collect(),
            },
            pose: Pose::IDENTITY,
        };
        // No match at all.
        let mut none = pair(5, 32, 24, 0);
        none.assignment.observed_to_model = vec![None; 24];
        for pairs in [vec![same], vec![none]] {
            let (loss, norms) = gradients_of(&trainer, &pairs);
            assert!(loss.is_finite(), "{head:?}: loss {loss}");
            for (name, g) in &norms {
                assert!(g.is_finite(), "{head:?}: {name} gradient {g}");
            }
        }
    }
}

fn overfit(head: Head) -> (f32, f32) {
    overfit_with(head, None)
}

fn overfit_with(head: Head, pooled_keys: Option<usize>) -> (f32, f32) {
    let mut cfg = tiny(head);
    cfg.net.pooled_keys = pooled_keys;
    cfg.net.emb_dims = 32;
    cfg.net.ff_dims = 64;
    cfg.train.learning_rate = 3e-3;
    let mut trainer = Trainer::new(cfg, 7).unwrap();
    let matched = if head == Head::Ot { 20 } else { 24 };
    let pairs = vec![pair(11, 32, 24, matched), pair(12, 32, 24, matched)];
    let (pp, aa) = refs(&pairs);
    let first = trainer.step_pairs(&pp, &aa).unwrap().loss;
    let mut last = first;
    for _ in 0..300 {
        last = trainer.step_pairs(&pp, &aa).unwrap().loss;
    }
    (first, last)
}

#[test]
fn tiny_model_overfits_one_batch_softmax() {
    let (first, last) = overfit(Head::Softmax);
    assert!(last < 0.1 * first, "softmax loss {first} → {last}");
}

#[test]
fn tiny_model_with_pooled_keys_overfits_one_batch() {
    // 8 of the 32 model and 24 observed points as keys: the queries still see the other
    // cloud through them.
    let (first, last) = overfit_with(Head::Softmax, Some(8));
    assert!(last < 0.1 * first, "pooled softmax loss {first} → {last}");
}

/// Pooled keys change nothing when there are not fewer points than keys, change the output
/// when there are, and a configuration without the setting (every checkpoint written before
/// it) reads as every point.
#[test]
fn pooled_keys_are_full_attention_when_not_fewer_than_the_points() {
    let trainer = Trainer::new(tiny(Head::Softmax), 21).unwrap();
    let p = pair(61, 32, 24, 20);
    let with_keys =
        |keys: Option<usize>| log_p(&trainer.estimator().with_pooled_keys(keys).unwrap(), &p);
    let full = with_keys(None);
    assert_eq!(
        with_keys(Some(32)),
        full,
        "32 keys of 32 model and 24 observed points"
    );
    let pooled = with_keys(Some(8));
    assert!(pooled.iter().all(|v| v.is_finite()));
    let moved = full
        .iter()
        .zip(&pooled)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(moved > 1e-3, "8 keys of 24–32 points left log P unchanged");
    assert!(trainer.estimator().with_pooled_keys(Some(0)).is_err());
    let mut json = serde_json::to_value(tiny(Head::Softmax)).unwrap();
    assert!(
        json["net"].get("pooled_keys").is_none(),
        "unset is not written"
    );
    json["net"]["pooled_keys"] = 16.into();
    let read: PoseConfig = serde_json::from_value(json.clone()).unwrap();
    assert_eq!(read.net.pooled_keys, Some(16));
    json["net"].as_object_mut().unwrap().remove("pooled_keys");
    let read: PoseConfig = serde_json::from_value(json).unwrap();
    assert_eq!(read.net.pooled_keys, None);
    let mut zero = tiny(Head::Softmax);
    zero.net.pooled_keys = Some(0);
    assert!(zero.validate().is_err());
}

#[test]
fn tiny_model_overfits_one_batch_ot() {
    let (first, last) = overfit(Head::Ot);
    assert!(last < 0.1 * first, "ot loss {first} → {last}");
}

fn log_p(est: &PoseEstimator, p: &Pair) -> Vec<f32> {
    est.infer(&p.model, &p.observed)
        .unwrap()
        .log_p
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

#[test]
fn saved_and_reloaded_weights_give_bit_identical_outputs() {
    let dir = tempfile::tempdir().unwrap();
    for head in [Head::Softmax, Head::Ot] {
        let mut trainer = Trainer::new(tiny(head), 9).unwrap();
        let pairs = vec![pair(21, 32, 24, 20), pair(22, 32, 24, 20)];
        let (pp, aa) = refs(&pairs);
        for _ in 0..3 {
            trainer.step_pairs(&pp, &aa).unwrap();
        }
        let path = dir.path().join(format!("{}.safetensors", head.as_str()));
        trainer.save_weights(&path).unwrap();
        let loaded = PoseEstimator::load(&path).unwrap();
        let probe = pair(23, 40, 30, 25);
        let a = log_p(&trainer.estimator(), &probe);
        let b = log_p(&loaded, &probe);
        assert_eq!(a.len(), b.len());
        assert!(
            a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
            "{head:?}"
        );
        assert_eq!(loaded.config(), trainer.config());
    }
}

#[test]
fn with_neighbours_runs_the_same_weights_on_a_graph_of_that_k() {
    // The same seed gives the same weights whatever k (no weight depends on it).
    let mut k6 = tiny(Head::Softmax);
    k6.net.k = 6;
    let trained_k6 = Trainer::new(k6, 9).unwrap().estimator();
    let k4 = Trainer::new(tiny(Head::Softmax), 9).unwrap().estimator();
    let probe = pair(23, 40, 30, 25);
    let at4 = log_p(&k4, &probe);
    let moved = k4.with_neighbours(6).unwrap();
    assert_eq!(moved.config().net.k, 6);
    let (a, b) = (log_p(&moved, &probe), log_p(&trained_k6, &probe));
    assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
    assert!(a.iter().zip(&at4).any(|(x, y)| x != y), "k changed nothing");
    assert!(matches!(
        moved.with_neighbours(0),
        Err(PoseError::Config(_))
    ));
}

fn weights(t: &Trainer) -> Vec<(String, Vec<u32>)> {
    let mut out: Vec<(String, Vec<u32>)> = t
        .varmap()
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| {
            let bits = v
                .as_tensor()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
                .iter()
                .map(|x| x.to_bits())
                .collect();
            (k.clone(), bits)
        })
        .collect();
    out.sort();
    out
}

#[test]
fn resumed_run_matches_an_uninterrupted_one() {
    let dir = tempfile::tempdir().unwrap();
    for head in [Head::Softmax, Head::Ot] {
        let batches: Vec<Vec<Pair>> = (0..4)
            .map(|i| vec![pair(100 + 2 * i, 32, 24, 20), pair(101 + 2 * i, 32, 24, 18)])
            .collect();
        let run = |t: &mut Trainer, range: std::ops::Range<usize>| -> Vec<u32> {
            range
                .map(|i| {
                    let (pp, aa) = refs(&batches[i]);
                    t.step_pairs(&pp, &aa).unwrap().loss.to_bits()
                })
                .collect()
        };
        let mut full = Trainer::new(tiny(head), 5).unwrap();
        let full_losses = run(&mut full, 0..4);

        let mut first = Trainer::new(tiny(head), 5).unwrap();
        let mut losses = run(&mut first, 0..2);
        let path = dir.path().join("latest.safetensors");
        first.save(&path).unwrap();
        drop(first);
        let mut resumed = Trainer::resume(&path).unwrap();
        assert_eq!(resumed.iteration(), 2);
        assert_eq!(resumed.seed(), 5);
        losses.extend(run(&mut resumed, 2..4));
        assert_eq!(losses, full_losses, "{head:?}");
        assert!(
            weights(&resumed) == weights(&full),
            "{head:?}: weights differ"
        );
    }
}

#[test]
fn estimator_rejects_bad_inputs_and_mismatched_checkpoints() {
    let dir = tempfile::tempdir().unwrap();
    let trainer = Trainer::new(tiny(Head::Ot), 1).unwrap();
    let path = dir.path().join("w.safetensors");
    trainer.save_weights(&path).unwrap();
    let est = PoseEstimator::load(&path).unwrap();
    let p = pair(1, 32, 24, 20);
    assert!(est.estimate(&p.model, &p.observed).is_ok());
    assert!(matches!(
        est.estimate(&p.model[..2], &p.observed),
        Err(PoseError::TooFewPoints { .. })
    ));
    let mut bad = p.observed.clone();
    bad[5].y = f32::NAN;
    assert!(matches!(
        est.estimate(&p.model, &bad),
        Err(PoseError::NonFinite { index: 5, .. })
    ));
    // A checkpoint whose configuration does not match its tensors.
    let mut cfg = trainer.config().clone();
    cfg.net.emb_dims = 32;
    let tensors: Vec<(String, Tensor)> = candle_core::safetensors::load(&path, &Device::Cpu)
        .unwrap()
        .into_iter()
        .collect();
    let wrong = dir.path().join("wrong.safetensors");
    let meta = HashMap::from([(CONFIG_KEY.to_string(), serde_json::to_string(&cfg).unwrap())]);
    checkpoint::save(&wrong, &tensors, meta).unwrap();
    assert!(matches!(
        PoseEstimator::load(&wrong),
        Err(PoseError::Checkpoint { .. })
    ));
    // Not a checkpoint at all.
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"nope").unwrap();
    assert!(matches!(
        PoseEstimator::load(&junk),
        Err(PoseError::Checkpoint { .. })
    ));
}

#[test]
fn perfect_matches_recover_the_pose() {
    let p = pair(42, 64, 48, 48);
    let matches: Vec<Match> = p
        .assignment
        .observed_to_model
        .iter()
        .enumerate()
        .map(|(j, i)| Match {
            observed: j as u32,
            model: i.unwrap(),
            probability: 0.9,
            outlier: false,
        })
        .collect();
    let one_shot = RecoveryOptions {
        refine: ic_pose::Refine::None,
        ..RecoveryOptions::default()
    };
    let r = recover_pose(&p.model, &p.observed, &matches, &one_shot).unwrap();
    assert!(r.pose.rotation_angle_to(&p.pose).to_degrees() < 1e-3);
    assert!((r.pose.translation - p.pose.translation).length() < 1e-4);
    assert_eq!(r.inlier_count, 48);
}

/// The OT head can keep only a few degenerate matches out of the bins (all on one model
/// point: Procrustes has rank < 2); recovery then falls back to the most probable matches
/// regardless of the bins instead of failing.
#[test]
fn degenerate_kept_matches_fall_back_to_the_most_probable() {
    let p = pair(43, 64, 48, 48);
    let mut matches: Vec<Match> = p
        .assignment
        .observed_to_model
        .iter()
        .enumerate()
        .map(|(j, i)| Match {
            observed: j as u32,
            model: i.unwrap(),
            probability: 0.5,
            outlier: true,
        })
        .collect();
    // Three "inliers", all the same observed and model point.
    for m in matches.iter_mut().take(3) {
        *m = Match {
            observed: 0,
            model: p.assignment.observed_to_model[0].unwrap(),
            probability: 0.9,
            outlier: false,
        };
    }
    let one_shot = RecoveryOptions {
        refine: ic_pose::Refine::None,
        ..RecoveryOptions::default()
    };
    let r = recover_pose(&p.model, &p.observed, &matches, &one_shot).expect("fallback");
    assert!(r.pose.rotation_angle_to(&p.pose).to_degrees() < 1e-2);
    assert_eq!(r.inlier_count, 16, "the 16 most probable matches");
}

/// The OT loss on a hand-made log P̄ (M = 2, N = 3): observed 0 ↔ model 1 matched, observed 1
/// and 2 unmatched, model 0 unmatched.
#[test]
fn ot_loss_balanced_averages_matches_and_bins_separately() {
    // log P̄ is [1, M+1, N+1] = [1, 3, 4]; entry (i, j) = −(1 + 4i + j) so each is distinct.
    let values: Vec<f32> = (0..12).map(|k| -(1.0 + k as f32)).collect();
    let log_p = Tensor::from_vec(values, (1, 3, 4), &Device::Cpu).unwrap();
    let assignment = Assignment {
        model_count: 2,
        observed_count: 3,
        observed_to_model: vec![Some(1), None, None],
    };
    let out = |loss| ic_pose::HeadOutput {
        head: Head::Ot,
        log_p: log_p.clone(),
        model_points: 2,
        observed_points: 3,
        loss,
    };
    let nll = |o: &ic_pose::HeadOutput| {
        ic_pose::nll_loss(o, &[&assignment])
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    // Matched: (1, 0) → 5. Bins: observed 1, 2 in row M = 2: (2, 1) → 10, (2, 2) → 11; model 0
    // in column N = 3: (0, 3) → 4.
    let balanced = nll(&out(ic_pose::OtLoss::Balanced));
    // The mean of the matched mean (5) and the bin mean ((10 + 11 + 4) / 3).
    assert!(
        (balanced - (5.0 + (10.0 + 11.0 + 4.0) / 3.0) / 2.0).abs() < 1e-5,
        "{balanced}"
    );
    let paper = nll(&out(ic_pose::OtLoss::Paper));
    assert!(
        (paper - (5.0 + 10.0 + 11.0 + 4.0) / 4.0).abs() < 1e-5,
        "{paper}"
    );
}

#[test]
fn rotation_sweep_matches_the_explicit_batch_of_rotated_copies() {
    // The sweep encodes the observed cloud once and shares the model's k-NN graph; the
    // log-probabilities and poses must be those of the plain batch of (R·x, y) pairs.
    // With pooled keys too: each copy's keys are its own farthest points, as in the batch.
    let rotations = ic_geometry::rotations::rotation_group(12).unwrap();
    for (head, pooled) in [
        (Head::Softmax, None),
        (Head::Ot, None),
        (Head::Softmax, Some(10)),
    ] {
        let mut trainer = Trainer::new(tiny(head), 5).unwrap();
        let train = vec![pair(31, 32, 24, 20), pair(32, 32, 24, 20)];
        let (pp, aa) = refs(&train);
        for _ in 0..3 {
            trainer.step_pairs(&pp, &aa).unwrap();
        }
        let est = trainer.estimator().with_pooled_keys(pooled).unwrap();
        let p = pair(33, 40, 30, 25);
        let copies: Vec<Vec<Vec3>> = rotations
            .iter()
            .map(|r| p.model.iter().map(|&q| r.rotate_f32(q)).collect())
            .collect();
        let pairs: Vec<(&[Vec3], &[Vec3])> = copies
            .iter()
            .map(|c| (c.as_slice(), p.observed.as_slice()))
            .collect();
        let k = est.config().net.k;
        let plain = est
            .net()
            .forward_t(&PairBatch::new(&pairs, k, &Device::Cpu).unwrap(), false)
            .unwrap();
        let sweep =
            ic_pose::network::SweepBatch::new(&p.model, &rotations, &p.observed, k, &Device::Cpu)
                .unwrap();
        let swept = est.net().forward_sweep(&sweep).unwrap();
        let a = plain.log_p.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let b = swept.log_p.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(a.len(), b.len());
        let worst = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{head:?}: log P differs by {worst}");
        // Each estimate is the copy's pose mapped back to the unrotated model.
        let one_by_one = est.estimate_batch(&pairs).unwrap();
        let swept = est
            .estimate_rotations(
                &p.model,
                &rotations,
                &p.observed,
                &ic_pose::SweepOptions::default(),
            )
            .unwrap();
        for ((a, b), r) in one_by_one.iter().zip(&swept).zip(&rotations) {
            let (a, b) = (a.as_ref().unwrap(), &b.as_ref().unwrap().estimate);
            let expected = a.pose.compose(r);
            let angle = expected.rotation_angle_to(&b.pose).to_degrees();
            assert!(angle < 1e-2, "{head:?}: {angle}°");
            assert!((expected.translation - b.pose.translation).length() < 1e-4);
        }
    }
}

#[test]
fn pruned_sweep_keeps_copy_zero_and_matches_the_full_sweep_on_the_kept_copies() {
    let rotations = ic_geometry::rotations::rotation_group(12).unwrap();
    let trainer = Trainer::new(tiny(Head::Softmax), 8).unwrap();
    let est = trainer.estimator();
    let p = pair(41, 40, 30, 25);
    let k = est.config().net.k;
    let sweep =
        ic_pose::SweepBatch::new(&p.model, &rotations, &p.observed, k, &Device::Cpu).unwrap();
    let (full, all) = est.net().forward_sweep_pruned(&sweep, 12).unwrap();
    assert_eq!(all, (0..12).collect::<Vec<_>>());
    let (some, kept) = est.net().forward_sweep_pruned(&sweep, 4).unwrap();
    assert_eq!(kept.len(), 4);
    assert_eq!(kept[0], 0, "the unrotated copy is always kept");
    assert!(kept.windows(2).all(|w| w[0] < w[1]));
    let per_copy = 30 * 40;
    let full = full.log_p.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let some = some.log_p.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    for (slot, &copy) in kept.iter().enumerate() {
        let a = &full[copy * per_copy..(copy + 1) * per_copy];
        let b = &some[slot * per_copy..(slot + 1) * per_copy];
        let worst = a
            .iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "copy {copy}: {worst}");
    }
    // Pruning is deterministic.
    assert_eq!(est.net().forward_sweep_pruned(&sweep, 4).unwrap().1, kept);
}

/// A kept model side gives the estimates of a fresh sweep, for other observed clouds too; the
/// estimator keeps sides within its memory budget, least recently used out first, and one
/// wrapping a network in training keeps none.
#[test]
fn kept_model_sides_give_the_fresh_sweeps_estimates_and_stay_within_their_budget() {
    let rotations = ic_geometry::rotations::rotation_group(12).unwrap();
    let trainer = Trainer::new(tiny(Head::Softmax), 9).unwrap();
    let fresh = trainer.estimator();
    let keeping = trainer.estimator().keeping_model_sides(usize::MAX);
    let p = pair(51, 40, 30, 25);
    let q = pair(52, 40, 30, 25);
    for keep in [usize::MAX, 5] {
        let options = ic_pose::SweepOptions {
            keep,
            ..ic_pose::SweepOptions::default()
        };
        for observed in [&p.observed, &q.observed, &p.observed] {
            let a = fresh
                .estimate_rotations(&p.model, &rotations, observed, &options)
                .unwrap();
            let b = keeping
                .estimate_rotations(&p.model, &rotations, observed, &options)
                .unwrap();
            assert_eq!(a.len(), b.len());
            let mut posed = 0;
            for (a, b) in a.iter().zip(&b) {
                // An untrained network may give a copy degenerate correspondences: both alike.
                let (Ok(a), Ok(b)) = (a, b) else {
                    assert_eq!(a.is_ok(), b.is_ok());
                    continue;
                };
                posed += 1;
                assert_eq!(a.rotation, b.rotation);
                let angle = a
                    .estimate
                    .pose
                    .rotation_angle_to(&b.estimate.pose)
                    .to_degrees();
                assert!(angle < 1e-3, "keep {keep}: {angle}°");
                assert!(
                    (a.estimate.pose.translation - b.estimate.pose.translation).length() < 1e-5
                );
            }
            assert!(posed >= a.len() / 2, "{posed} of {} copies posed", a.len());
        }
    }
    assert_eq!(fresh.kept_model_sides(), (0, 0));
    let (count, one) = keeping.kept_model_sides();
    assert_eq!(count, 1, "one model, one rotation set");
    // A budget of two such sides: the third sweep evicts the least recently used.
    let bounded = trainer.estimator().keeping_model_sides(2 * one);
    let sweep = |r: &[ic_geometry::Pose]| {
        bounded
            .estimate_rotations(&p.model, r, &p.observed, &ic_pose::SweepOptions::default())
            .unwrap();
    };
    // Three rotation sets of 12 (orders differ, so the copies differ): each side is `one`.
    let a = rotations.clone();
    let b: Vec<_> = rotations.iter().rev().copied().collect();
    let c: Vec<_> = rotations.iter().cycle().skip(1).take(12).copied().collect();
    sweep(&a);
    sweep(&b);
    assert_eq!(bounded.kept_model_sides(), (2, 2 * one));
    sweep(&c);
    assert_eq!(bounded.kept_model_sides(), (2, 2 * one), "`a` evicted");
    sweep(&b);
    assert_eq!(
        bounded.kept_model_sides(),
        (2, 2 * one),
        "`b` found, nothing added"
    );
    // A side larger than the whole budget is not kept and evicts nothing.
    let tight = trainer.estimator().keeping_model_sides(one - 1);
    tight
        .estimate_rotations(&p.model, &a, &p.observed, &ic_pose::SweepOptions::default())
        .unwrap();
    assert_eq!(tight.kept_model_sides(), (0, 0));
}

/// Of a pair's candidate ground truths (the true pose's, then a symmetric equivalent's), the
/// one the output already fits is chosen, per pair; its loss is the lower one; a pair with a
/// single candidate keeps it; a candidate that counts nothing never wins.
#[test]
fn nearest_assignments_pick_the_equivalent_ground_truth_the_output_fits() {
    // Softmax, 2 pairs, N = 2 observed × M = 2 model points. Pair 0 believes observed j ↔
    // model 1 − j (the "turned" truth), pair 1 believes j ↔ j.
    let p = |x: f32| x.ln();
    let log_p = Tensor::from_vec(
        vec![
            p(0.1),
            p(0.9),
            p(0.8),
            p(0.2), // pair 0
            p(0.7),
            p(0.3),
            p(0.4),
            p(0.6), // pair 1
        ],
        (2, 2, 2),
        &Device::Cpu,
    )
    .unwrap();
    let out = ic_pose::HeadOutput {
        head: Head::Softmax,
        log_p,
        model_points: 2,
        observed_points: 2,
        loss: ic_pose::OtLoss::Balanced,
    };
    let a = |v: [Option<u32>; 2]| Assignment {
        model_count: 2,
        observed_count: 2,
        observed_to_model: v.to_vec(),
    };
    let straight = a([Some(0), Some(1)]);
    let turned = a([Some(1), Some(0)]);
    let empty = a([None, None]);
    let chosen = ic_pose::nearest_assignments(
        &out,
        &[vec![&straight, &turned, &empty], vec![&straight, &turned]],
    )
    .unwrap();
    assert_eq!(chosen, [1, 0]);
    let loss = |a0: &Assignment, a1: &Assignment| {
        nll_loss(&out, &[a0, a1])
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    };
    assert!(loss(&turned, &straight) < loss(&straight, &straight));
    assert!(loss(&turned, &straight) < loss(&turned, &turned));
    assert_eq!(
        ic_pose::nearest_assignments(&out, &[vec![&turned], vec![&straight]]).unwrap(),
        [0, 0]
    );
}
