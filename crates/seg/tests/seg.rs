//! Behaviour of the segmentation network, its training and its checkpoints.

use std::collections::HashMap;

use candle_core::{Device, Tensor};
use ic_geometry::{DepthImage, Intrinsics, Mask};
use ic_nn::adam::is_trainable;
use ic_seg::unet::{Conv2d, max_pool2, upsample2};
use ic_seg::{SegConfig, SegError, SegExample, SegInput, Segmenter, seg_loss};
use ic_train::SegTrainer;

/// The camera of [`scene`]'s 64×48 depth maps: the training camera resized to them, so
/// that a network trained and run on them at 64×48 keeps that input
/// (`Segmenter::input_size_for`).
fn camera() -> Intrinsics {
    ic_seg::TRAINING_CAMERA.resized(64, 48)
}

/// A wall at depth 4 with a box at depth 3 whose position depends on `shift`.
fn scene(shift: u32) -> (DepthImage, Mask) {
    let (w, h) = (64u32, 48u32);
    let mut depth = DepthImage::filled(w, h, 4.0);
    let mut mask = Mask::filled(w, h, false);
    for v in 12 + shift..30 + shift {
        for u in 16 + 2 * shift..36 + 2 * shift {
            let i = (v * w + u) as usize;
            depth.data[i] = 3.0 + 0.02 * (u as f32 - 26.0).abs();
            mask.data[i] = true;
        }
    }
    (depth, mask)
}

fn examples(cfg: &SegConfig) -> Vec<SegExample> {
    (0..2)
        .map(|s| {
            let (d, m) = scene(s * 4);
            SegExample::new(&d, &camera(), &m, cfg).unwrap()
        })
        .collect()
}

fn check_close(a: &Tensor, b: &Tensor, tol: f32) {
    let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert!((x - y).abs() <= tol * (1.0 + y.abs()), "{x} vs {y}");
    }
}

/// Standard-normal values from ChaCha8(`seed`) (candle's `Tensor::randn` on the CPU is
/// unseeded): the tests see the same numbers on every run.
fn seeded_normal(shape: (usize, usize, usize, usize), seed: u64, dev: &Device) -> Tensor {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n = shape.0 * shape.1 * shape.2 * shape.3;
    // Box–Muller from uniform pairs.
    let v: Vec<f32> = (0..n)
        .map(|_| {
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
            ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
        })
        .collect();
    Tensor::from_vec(v, shape, dev).unwrap()
}

#[test]
fn unfolded_convolution_matches_candles_conv2d() {
    let dev = Device::Cpu;
    let map = candle_nn::VarMap::new();
    let vb = ic_nn::seeded_var_builder(&map, 5, &dev);
    let conv = Conv2d::new(vb.pp("c"), 3, 5, 3, true).unwrap();
    let x = seeded_normal((2, 3, 7, 9), 11, &dev);
    let ours = conv.forward(&x).unwrap();
    let data = map.data().lock().unwrap();
    let w = data["c.weight"].as_tensor().clone();
    let b = data["c.bias"].as_tensor().clone();
    let reference = x
        .conv2d(&w, 1, 1, 1, 1)
        .unwrap()
        .broadcast_add(&b.reshape((1, 5, 1, 1)).unwrap())
        .unwrap();
    check_close(&ours, &reference, 1e-5);
}

#[test]
fn pooling_and_upsampling_match_candles_ops() {
    let dev = Device::Cpu;
    let x = seeded_normal((2, 3, 6, 8), 12, &dev);
    check_close(&max_pool2(&x).unwrap(), &x.max_pool2d(2).unwrap(), 0.0);
    check_close(
        &upsample2(&x).unwrap(),
        &x.upsample_nearest2d(12, 16).unwrap(),
        0.0,
    );
}

#[test]
fn every_parameter_receives_a_gradient() {
    let cfg = SegConfig::tiny();
    let trainer = SegTrainer::new(cfg.clone(), 3).unwrap();
    let ex = examples(&cfg);
    let (w, h) = (cfg.net.input_width as usize, cfg.net.input_height as usize);
    let x = Tensor::from_vec(
        ex.iter().flat_map(|e| e.input.clone()).collect::<Vec<_>>(),
        (2, 2, h, w),
        &Device::Cpu,
    )
    .unwrap();
    let y = Tensor::from_vec(
        ex.iter().flat_map(|e| e.target.clone()).collect::<Vec<_>>(),
        (2, 1, h, w),
        &Device::Cpu,
    )
    .unwrap();
    let loss = seg_loss(
        &trainer.net().forward_t(&x, true).unwrap(),
        &y,
        None,
        1.0,
        0.5,
    )
    .unwrap();
    let grads = loss.backward().unwrap();
    let mut seen = 0;
    for (name, var) in trainer.varmap().data().lock().unwrap().iter() {
        if !is_trainable(name) {
            continue;
        }
        seen += 1;
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
        assert!(g.is_finite() && g > 0.0, "{name}: gradient {g}");
    }
    assert!(seen >= 12, "only {seen} parameters");
}

#[test]
fn tiny_network_overfits_a_fixed_batch() {
    overfits(SegConfig::tiny());
}

#[test]
fn tiny_network_with_normals_overfits_a_fixed_batch() {
    let mut cfg = SegConfig::tiny();
    cfg.net.input = ic_seg::SegInput::DepthNormals;
    overfits(cfg);
}

fn overfits(cfg: SegConfig) {
    let ex = examples(&cfg);
    assert_eq!(
        ex[0].input.len(),
        cfg.net.input.channels() * (cfg.net.input_width * cfg.net.input_height) as usize
    );
    let mut trainer = SegTrainer::new(cfg, 11).unwrap();
    let first = trainer.loss(&ex).unwrap();
    let mut last = trainer.step(&ex).unwrap();
    for _ in 0..150 {
        last = trainer.step(&ex).unwrap();
    }
    let after = trainer.loss(&ex).unwrap();
    assert!(
        after < 0.1 * first,
        "loss {first} → {after} (training-mode {})",
        last.loss
    );
    assert!(last.iou > 0.9, "IoU {}", last.iou);
    // And the segmenter finds the box at full resolution.
    let (depth, mask) = scene(0);
    let k = camera();
    let seg = trainer.segmenter().segment(&depth, &k).unwrap();
    let iou = ic_seg::post::iou(&seg.mask, &mask);
    assert!(iou > 0.8, "IoU {iou}");
}

fn outputs(seg: &Segmenter) -> Vec<f32> {
    let (d, _) = scene(2);
    seg.probabilities_small(&[(&d, &camera())])
        .unwrap()
        .remove(0)
}

#[test]
fn checkpoint_round_trips_bit_identically() {
    let cfg = SegConfig::tiny();
    let ex = examples(&cfg);
    let mut trainer = SegTrainer::new(cfg, 2).unwrap();
    for _ in 0..3 {
        trainer.step(&ex).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("seg.safetensors");
    trainer.save_weights(&path).unwrap();
    let loaded = Segmenter::load(&path).unwrap();
    assert_eq!(loaded.config(), trainer.config());
    assert_eq!(outputs(&loaded), outputs(&trainer.segmenter()));
}

#[test]
fn resumed_run_matches_uninterrupted_run() {
    let cfg = SegConfig::tiny();
    let ex = examples(&cfg);
    let mut straight = SegTrainer::new(cfg.clone(), 9).unwrap();
    for _ in 0..4 {
        straight.step(&ex).unwrap();
    }
    let mut first = SegTrainer::new(cfg, 9).unwrap();
    for _ in 0..2 {
        first.step(&ex).unwrap();
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("latest.safetensors");
    first.save(&path).unwrap();
    let mut resumed = SegTrainer::resume(&path).unwrap();
    assert_eq!(resumed.iteration(), 2);
    for _ in 0..2 {
        resumed.step(&ex).unwrap();
    }
    assert_eq!(
        outputs(&resumed.segmenter()),
        outputs(&straight.segmenter())
    );
}

#[test]
fn loading_something_else_is_a_clear_checkpoint_error() {
    let dir = tempfile::tempdir().unwrap();
    // Not a file at all.
    let missing = dir.path().join("missing.safetensors");
    let e = Segmenter::load(&missing).unwrap_err();
    assert!(matches!(e, SegError::Io { .. }), "{e}");
    assert!(e.to_string().contains("missing.safetensors"));
    // A safetensors file without our configuration (e.g. another network's).
    let other = dir.path().join("other.safetensors");
    let t = Tensor::new(&[1f32], &Device::Cpu).unwrap();
    ic_nn::checkpoint::save(&other, &[("w".into(), t)], HashMap::new()).unwrap();
    let e = Segmenter::load(&other).unwrap_err();
    assert!(
        e.to_string().contains("not a segmentation checkpoint"),
        "{e}"
    );
    // Our configuration, weights of another shape.
    let trainer = SegTrainer::new(SegConfig::tiny(), 1).unwrap();
    let good = dir.path().join("good.safetensors");
    trainer.save_weights(&good).unwrap();
    let mut cfg = SegConfig::tiny();
    cfg.net.channels = vec![6, 8];
    let meta = HashMap::from([(
        ic_seg::checkpoint::CONFIG_KEY.to_string(),
        serde_json::to_string(&cfg).unwrap(),
    )]);
    let tensors = ic_nn::checkpoint::varmap_tensors(trainer.varmap());
    let wrong = dir.path().join("wrong.safetensors");
    ic_nn::checkpoint::save(&wrong, &tensors, meta).unwrap();
    let e = Segmenter::load(&wrong).unwrap_err();
    assert!(e.to_string().contains("do not fit"), "{e}");
}

#[test]
fn segment_rejects_a_depth_map_of_another_size_or_without_valid_pixels() {
    let seg = SegTrainer::new(SegConfig::tiny(), 1).unwrap().segmenter();
    let k = camera();
    let small = DepthImage::filled(32, 24, 1.0);
    assert!(seg.segment(&small, &k).is_err());
    let empty = DepthImage::filled(64, 48, 0.0);
    match seg.segment(&empty, &k) {
        Err(SegError::Input(m)) => assert!(m.contains("no valid pixel"), "{m}"),
        other => panic!("{other:?}"),
    }
}

/// A 64×48 view ([`camera`]) of a wall 4 m away, instance id 3 everywhere.
fn wall() -> (DepthImage, ic_geometry::Image<u32>) {
    let (w, h) = (64u32, 48u32);
    let ids = ic_geometry::Image {
        width: w,
        height: h,
        data: vec![3u32; (w * h) as usize],
    };
    (DepthImage::filled(w, h, 4.0), ids)
}

/// Two rounded boxes touching side by side at one depth before a wall (64×48, [`camera`]):
/// instance ids 1 (left, columns 12–31) and 2 (right, columns 32–51), rows 14–33, each
/// nearest along its middle column so they meet at a crease; the wall is id 3.
fn touching_boxes() -> (DepthImage, ic_geometry::Image<u32>) {
    let (mut depth, mut ids) = wall();
    let w = depth.width;
    for v in 14..34 {
        for u in 12..52 {
            let i = (v * w + u) as usize;
            let middle = if u < 32 { 21.5 } else { 41.5 };
            depth.data[i] = 3.0 + 0.01 * (u as f32 - middle).abs();
            ids.data[i] = if u < 32 { 1 } else { 2 };
        }
    }
    (depth, ids)
}

#[test]
fn offset_targets_point_every_object_pixel_to_its_instances_centroid() {
    let cfg = SegConfig::preset("tiny-clutter-offsets").unwrap();
    let (depth, ids) = touching_boxes();
    let ex = SegExample::from_instances(&depth, &camera(), &ids, |i| i != 3, &cfg).unwrap();
    let (w, h) = (cfg.net.input_width as usize, cfg.net.input_height as usize);
    let plane = w * h;
    assert_eq!(ex.target.len(), 4 * plane);
    // At 32×24 the boxes are columns 6–15 and 16–25, rows 7–16: centroids (10.5, 11.5) and
    // (20.5, 11.5).
    let unit = ic_seg::config::OFFSET_UNIT;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (tx, ty) = (ex.target[2 * plane + i], ex.target[3 * plane + i]);
            if ex.target[i] == 1.0 {
                let cx = if x < 16 { 10.5 } else { 20.5 };
                assert!((x as f32 + tx * unit - cx).abs() < 1e-4, "x at ({x}, {y})");
                assert!(
                    (y as f32 + ty * unit - 11.5).abs() < 1e-4,
                    "y at ({x}, {y})"
                );
            } else {
                assert_eq!((tx, ty), (0.0, 0.0), "off the objects at ({x}, {y})");
            }
        }
    }
}

#[test]
fn a_four_output_network_learns_the_centres_and_its_votes_cut_touching_boxes() {
    let mut cfg = SegConfig::preset("tiny-clutter-offsets").unwrap();
    cfg.net.channels = vec![8, 16];
    let (depth, ids) = touching_boxes();
    let ex = vec![SegExample::from_instances(&depth, &camera(), &ids, |i| i != 3, &cfg).unwrap()];
    let mut trainer = SegTrainer::new(cfg, 5).unwrap();
    let first = trainer.loss(&ex).unwrap();
    for _ in 0..300 {
        trainer.step(&ex).unwrap();
    }
    let after = trainer.loss(&ex).unwrap();
    assert!(after < 0.1 * first, "loss {first} → {after}");
    let mut seg = trainer.segmenter();
    // The votes, not the cores: every pixel is a core, so the cores alone give one instance.
    seg.config_mut().post.core_threshold = 0.0;
    let both = |seg: &Segmenter| {
        let mut found = seg.instances(&depth, &camera()).unwrap();
        found.sort_by_key(|i| i.mask.data.iter().position(|&m| m));
        found
    };
    seg.config_mut().post.centres = None;
    assert_eq!(both(&seg).len(), 1, "without the votes the boxes are one");
    seg.config_mut().post.centres = Some(ic_seg::centres::CentreConfig::default());
    let found = both(&seg);
    assert_eq!(found.len(), 2, "the votes cut the boxes apart");
    assert_each_box_found(&found, &ids, "votes");
}

/// `found` (sorted by first pixel) holds [`touching_boxes`]' left and right box, in order,
/// each at IoU > 0.8.
fn assert_each_box_found(
    found: &[ic_seg::post::Instance],
    ids: &ic_geometry::Image<u32>,
    what: &str,
) {
    for (inst, id) in found.iter().zip([1, 2]) {
        let truth = Mask {
            width: ids.width,
            height: ids.height,
            data: ids.data.iter().map(|&i| i == id).collect(),
        };
        let iou = ic_seg::post::iou(&inst.mask, &truth);
        assert!(iou > 0.8, "box {id}: IoU {iou} ({what})");
    }
}

#[test]
fn the_training_targets_through_the_post_processing_give_back_the_touching_boxes() {
    // What `eval-seg --oracle` measures: a perfect network's outputs (the targets) cut the
    // boxes apart with the cores alone, and with the votes too; a wrong-sized output is an
    // error.
    let cfg = SegConfig::preset("tiny-clutter-offsets").unwrap();
    let (depth, ids) = touching_boxes();
    let truth = SegExample::from_instances(&depth, &camera(), &ids, |i| i != 3, &cfg).unwrap();
    let trainer = SegTrainer::new(cfg, 1).unwrap();
    let mut seg = trainer.segmenter();
    for centres in [None, Some(ic_seg::centres::CentreConfig::default())] {
        seg.config_mut().post.centres = centres.clone();
        let (mut found, votes) = seg
            .instances_from_small(&truth.target, &depth, &camera(), true)
            .unwrap();
        assert!(votes.is_some());
        found.sort_by_key(|i| i.mask.data.iter().position(|&m| m));
        assert_eq!(found.len(), 2, "centres {centres:?}");
        assert_each_box_found(&found, &ids, &format!("centres {centres:?}"));
    }
    let short = &truth.target[1..];
    let err = seg
        .instances_from_small(short, &depth, &camera(), false)
        .unwrap_err();
    assert!(err.to_string().contains("network outputs"), "{err}");
}

#[test]
fn instance_balance_weighs_a_small_instance_up_to_the_cap_and_unit_weights_leave_the_loss_as_it_was()
 {
    // 64×48 depth, network 32×24: a large box (id 1, 20×20 → 10×10 network pixels) and a
    // small one (id 2, 4×4 → 2×2) before a wall (id 3).
    let (mut depth, mut ids) = wall();
    let w = depth.width;
    for v in 10..30 {
        for u in 10..30 {
            depth.data[(v * w + u) as usize] = 3.0;
            ids.data[(v * w + u) as usize] = 1;
        }
    }
    for v in 10..14 {
        for u in 40..44 {
            depth.data[(v * w + u) as usize] = 3.0;
            ids.data[(v * w + u) as usize] = 2;
        }
    }
    let mut cfg = SegConfig::preset("tiny-clutter-offsets").unwrap();
    let plain = SegExample::from_instances(&depth, &camera(), &ids, |i| i != 3, &cfg).unwrap();
    assert!(plain.weight.is_empty());
    cfg.train.balance_area = 100.0;
    let ex = SegExample::from_instances(&depth, &camera(), &ids, |i| i != 3, &cfg).unwrap();
    assert_eq!(ex.target, plain.target);
    let nw = cfg.net.input_width as usize;
    let weight_at = |x: usize, y: usize| ex.weight[y * nw + x];
    assert_eq!(weight_at(7, 7), 1.0, "100 pixels: √(100/100)");
    assert_eq!(
        weight_at(20, 5),
        ic_seg::config::BALANCE_CAP as f32,
        "4 pixels: capped"
    );
    assert_eq!(weight_at(0, 0), 1.0, "the wall");
    // The loss with weights all 1 is the unweighted loss; with the balance it differs.
    let trainer = SegTrainer::new(cfg.clone(), 3).unwrap();
    let nh = cfg.net.input_height as usize;
    let x = Tensor::from_vec(ex.input.clone(), (1, 2, nh, nw), &Device::Cpu).unwrap();
    let y = Tensor::from_vec(ex.target.clone(), (1, 4, nh, nw), &Device::Cpu).unwrap();
    let logits = trainer.net().forward_t(&x, false).unwrap();
    let loss = |wt: Option<&Tensor>| -> f32 {
        seg_loss(&logits, &y, wt, 1.0, 0.5)
            .unwrap()
            .to_scalar()
            .unwrap()
    };
    let ones = Tensor::ones((1, 1, nh, nw), candle_core::DType::F32, &Device::Cpu).unwrap();
    let balanced = Tensor::from_vec(ex.weight.clone(), (1, 1, nh, nw), &Device::Cpu).unwrap();
    assert!((loss(Some(&ones)) - loss(None)).abs() < 1e-6);
    assert!((loss(Some(&balanced)) - loss(None)).abs() > 1e-4);
}

#[test]
fn border_weight_marks_where_two_objects_touch_and_nowhere_else() {
    let mut cfg = SegConfig::preset("tiny-clutter").unwrap();
    let (depth, ids) = touching_boxes();
    cfg.train.border_weight = 5.0;
    let ex = SegExample::from_instances(&depth, &camera(), &ids, |i| i != 3, &cfg).unwrap();
    // At 32×24 the boxes are columns 6–15 and 16–25, rows 7–16: they touch between 15 and 16.
    let nw = cfg.net.input_width as usize;
    let at = |x: usize, y: usize| ex.weight[y * nw + x];
    let touching = 1.0 + 5.0 * (-1.0f64 / 8.0).exp();
    assert!(
        (at(15, 10) as f64 - touching).abs() < 1e-5,
        "{}",
        at(15, 10)
    );
    assert!(
        (at(16, 10) as f64 - touching).abs() < 1e-5,
        "{}",
        at(16, 10)
    );
    assert!(
        at(14, 10) < at(15, 10) && at(14, 10) > 1.0,
        "falls off with the distance"
    );
    assert_eq!(at(6, 10), 1.0, "7 pixels from the other box: beyond 3 σ");
    assert_eq!(at(0, 0), 1.0, "the wall");
}

/// `depth` mirrored left to right.
fn mirrored(depth: &DepthImage) -> DepthImage {
    let mut out = depth.clone();
    ic_seg::input::mirror_planes(
        &mut out.data,
        depth.width as usize,
        depth.height as usize,
        None,
    );
    out
}

#[test]
fn mirror_averaging_is_the_mean_of_both_passes_and_commutes_with_a_mirror() {
    // Both inputs: with surface normals, the mirror also negates the normal's x component
    // (input plane 2), which a wrong sign would break.
    for input in [SegInput::Depth, SegInput::DepthNormals] {
        // A four-output network at its own input size (32×24), so that mirroring the depth
        // map mirrors the network's input exactly (the principal point centred, so the
        // mirrored depth is the mirrored scene); a few steps so that its weights are not
        // symmetric.
        let mut cfg = SegConfig::tiny();
        cfg.net.outputs = 4;
        cfg.net.input = input;
        let k = ic_seg::TRAINING_CAMERA.resized(32, 24);
        let mut depth = DepthImage::filled(32, 24, 4.0);
        for v in 6..15 {
            for u in 5..17 {
                depth.data[v * 32 + u] = 3.0 + 0.05 * (u as f32 - 8.0).abs();
            }
        }
        let mut trainer = SegTrainer::new(cfg.clone(), 4).unwrap();
        trainer.step(&examples(&cfg)).unwrap();
        let plain = trainer.segmenter();
        let mut averaging = plain.clone();
        averaging.config_mut().post.mirror_average = true;
        let pass =
            |s: &Segmenter, d: &DepthImage| s.probabilities_small(&[(d, &k)]).unwrap().remove(0);
        // Mirrors each output plane back and negates the x offsets (plane 2).
        let unmirror = |mut o: Vec<f32>| {
            ic_seg::input::mirror_planes(&mut o, 32, 24, Some(2));
            o
        };
        let (a, b) = (
            pass(&plain, &depth),
            unmirror(pass(&plain, &mirrored(&depth))),
        );
        let mean: Vec<f32> = a.iter().zip(&b).map(|(x, y)| 0.5 * (x + y)).collect();
        let averaged = pass(&averaging, &depth);
        let close = |x: &[f32], y: &[f32]| x.iter().zip(y).all(|(p, q)| (p - q).abs() < 1e-5);
        assert!(close(&averaged, &mean), "{input:?}");
        // The averaged network sees a mirrored scene as the mirror of the scene; the plain
        // one does not (else this test could not tell a wrong sign or a missing mirror).
        assert!(
            close(&unmirror(pass(&averaging, &mirrored(&depth))), &averaged),
            "{input:?}"
        );
        assert!(!close(&b, &a), "{input:?}");
    }
}

#[test]
fn every_preset_the_unknown_preset_error_names_exists_validates_and_round_trips() {
    let err = SegConfig::preset("no-such-preset").unwrap_err().to_string();
    let list = err
        .split_once('(')
        .and_then(|(_, rest)| rest.split_once(')'))
        .map(|(list, _)| list)
        .unwrap_or_else(|| panic!("no list of presets in {err:?}"));
    let names: Vec<&str> = list.split('|').map(str::trim).collect();
    assert!(names.len() >= 10, "{names:?}");
    for name in names {
        let cfg = SegConfig::preset(name).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(cfg.preset, name);
        cfg.validate().unwrap_or_else(|e| panic!("{name}: {e}"));
        let json = serde_json::to_string(&cfg).unwrap();
        let back: SegConfig = serde_json::from_str(&json).unwrap();
        assert_eq!(back, cfg, "{name}");
    }
    // The wider clutter presets start from `clutter-offsets` weights (`ic_train::widen`):
    // as many levels, each at least as wide.
    let base = SegConfig::preset("clutter-offsets").unwrap().net.channels;
    for name in ["clutter-wide", "clutter-offsets-fine"] {
        let wide = SegConfig::preset(name).unwrap().net.channels;
        assert_eq!(wide.len(), base.len(), "{name}");
        assert!(
            wide.iter().zip(&base).all(|(w, b)| w >= b),
            "{name}: {wide:?}"
        );
    }
}

#[test]
fn each_extra_input_size_gives_its_own_instances_and_bad_sizes_are_refused() {
    // A two-output network after a few steps (random weights find nothing), run on a scene
    // larger than its 32×24 input so that each input size sees it at another scale.
    let cfg = SegConfig::tiny();
    let mut trainer = SegTrainer::new(cfg.clone(), 4).unwrap();
    for _ in 0..30 {
        trainer.step(&examples(&cfg)).unwrap();
    }
    let mut seg = trainer.segmenter();
    seg.config_mut().post.score_threshold = 0.0;
    let (depth, _) = scene(3);
    let k = camera();
    let own = seg.instances(&depth, &k).unwrap();
    // No extra size: one list, the plain instances.
    let lists = seg.instances_per_input(&depth, &k).unwrap();
    assert_eq!(lists.len(), 1);
    let masks = |l: &[ic_seg::post::Instance]| l.iter().map(|i| i.mask.clone()).collect::<Vec<_>>();
    assert_eq!(masks(&lists[0]), masks(&own));
    // Two extra sizes: the own size's list first, then each size's as its own segmenter.
    seg.config_mut().post.extra_inputs = vec![(64, 48), (16, 16)];
    seg.config().validate().unwrap();
    let lists = seg.instances_per_input(&depth, &k).unwrap();
    assert_eq!(lists.len(), 3);
    assert_eq!(masks(&lists[0]), masks(&own));
    for (list, (w, h)) in lists[1..].iter().zip([(64, 48), (16, 16)]) {
        let alone = seg.at_input(w, h);
        assert!(alone.config().post.extra_inputs.is_empty());
        assert_eq!(masks(list), masks(&alone.instances(&depth, &k).unwrap()));
    }
    // The coarser size sees another image: at least one list differs from the own size's
    // (else this test could not tell a size that is ignored).
    assert!(lists[1..].iter().any(|l| masks(l) != masks(&own)));
    // Refused: a side not divisible for the levels, a zero side, one too large, too many.
    for bad in [
        vec![(33, 24)],
        vec![(0, 24)],
        vec![(4096, 24)],
        vec![(32, 24); ic_seg::config::MAX_EXTRA_INPUTS + 1],
    ] {
        let mut c = seg.config().clone();
        c.post.extra_inputs = bad.clone();
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains("extra input"), "{bad:?}: {err}");
    }
    // Nor may the network's own input be larger than an extra one may.
    let mut c = seg.config().clone();
    c.net.input_width = 4096;
    let err = c.validate().unwrap_err().to_string();
    assert!(err.contains("at most 2048"), "{err}");
    // A file written before the field existed reads with no extra size.
    let mut json = serde_json::to_value(cfg.post.clone()).unwrap();
    json.as_object_mut().unwrap().remove("extra_inputs");
    let post: ic_seg::PostConfig = serde_json::from_value(json).unwrap();
    assert!(post.extra_inputs.is_empty());
}

#[test]
fn the_training_camera_keeps_the_trained_input_and_other_cameras_get_their_aspect_and_angle() {
    let seg = SegTrainer::new(SegConfig::clutter(), 1)
        .unwrap()
        .segmenter();
    let size = |s: &Segmenter, k: &Intrinsics| s.input_size_for(k);
    let trained = (256, 192);
    // The training camera, and the same field of view at any resolution.
    assert_eq!(size(&seg, &ic_seg::TRAINING_CAMERA), trained);
    assert_eq!(
        size(&seg, &ic_seg::TRAINING_CAMERA.resized(1280, 960)),
        trained
    );
    // A 16:9 RealSense-like camera: a network pixel spans the trained 1/210 rad
    // (1280·210/640 = 420, 720·210/640 = 236.25), each side a multiple of 8.
    let realsense = Intrinsics::new(640.0, 640.0, 639.5, 359.5, 1280, 720).unwrap();
    assert_eq!(size(&seg, &realsense), (424, 240));
    // A wide camera of many pixels is brought under 4× the trained area, its aspect kept.
    let wide = Intrinsics::new(300.0, 300.0, 1999.5, 1499.5, 4000, 3000).unwrap();
    assert_eq!(size(&seg, &wide), (512, 384));
    // A narrow telephoto view is brought over 32 pixels on its short side.
    let narrow = Intrinsics::new(5000.0, 5000.0, 319.5, 239.5, 640, 480).unwrap();
    assert_eq!(size(&seg, &narrow), (40, 32));
    // Sized once: the sized segmenter runs at its size for that camera.
    let sized = seg.for_camera(&realsense);
    let net = &sized.config().net;
    assert_eq!((net.input_width, net.input_height), (424, 240));
    assert_eq!(size(&sized, &realsense), (424, 240));
    // Off: always the trained size.
    let mut off = seg.clone();
    off.config_mut().post.camera_input = false;
    assert_eq!(size(&off, &realsense), trained);
    assert_eq!(size(&off.for_camera(&realsense), &realsense), trained);
}
