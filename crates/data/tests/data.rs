//! Integration tests of `ic_data`: determinism, ground truth, room statistics, bad input, BOP
//! round trip and case export. Everything is generated here (procedural objects, temp
//! folders); nothing depends on files outside the repository.

use std::path::Path;
use std::sync::Arc;

use ic_data::bop::{BopDataset, BopLoadOptions, BopWriteOptions, BopWriter};
use ic_data::export::{write_object_case, write_room_case};
use ic_data::*;
use ic_geometry::glam::Vec3;
use ic_geometry::io::{PlyEncoding, read_ply_cloud, write_mesh_ply};
use ic_geometry::sampling::VisibleSurfaceOptions;
use ic_geometry::shapes::random_object;

/// Light model-point sampling so tests stay fast.
fn light() -> CorpusOptions {
    CorpusOptions {
        model_points: 2048,
        visible_surface: VisibleSurfaceOptions {
            views: 16,
            resolution: 96,
            ..VisibleSurfaceOptions::default()
        },
        ..CorpusOptions::default()
    }
}

fn corpus(count: usize, split: Split) -> Arc<Corpus> {
    Arc::new(Corpus::procedural(count, split, 11, light()).unwrap())
}

fn push_points(out: &mut Vec<u8>, pts: &[Vec3]) {
    for p in pts {
        for c in p.to_array() {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
}

fn object_bytes(s: &ObjectSample) -> Vec<u8> {
    let mut out = s.object_id.as_bytes().to_vec();
    push_points(&mut out, &s.model_points);
    push_points(&mut out, &s.observed_points);
    for v in s.pose.to_matrix_row_major().iter().flatten() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    for m in &s.assignment.observed_to_model {
        out.extend_from_slice(&m.map_or(u32::MAX, |i| i).to_le_bytes());
    }
    out
}

fn room_bytes(s: &RoomSample) -> Vec<u8> {
    let mut out = s.object_id.as_bytes().to_vec();
    push_points(&mut out, &s.scene_points);
    push_points(&mut out, &s.model_points);
    out.extend(s.object_labels.iter().map(|&b| b as u8));
    out.extend(s.depth.data.iter().flat_map(|z| z.to_le_bytes()));
    out.extend(s.mask_visib.data.iter().map(|&b| b as u8));
    for v in s.pose.to_matrix_row_major().iter().flatten() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

fn in_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

#[test]
fn same_seed_gives_byte_identical_samples_across_runs_and_thread_counts() {
    let make =
        |c: Arc<Corpus>| ObjectSampleGenerator::new(c, ObjectSampleConfig::default(), 5).unwrap();
    let one = in_pool(1, || {
        let g = make(corpus(6, Split::Train));
        (0..8)
            .map(|i| object_bytes(&g.sample(i).unwrap()))
            .collect::<Vec<_>>()
    });
    let two = in_pool(2, || {
        let g = make(corpus(6, Split::Train));
        (0..8)
            .map(|i| object_bytes(&g.sample(i).unwrap()))
            .collect::<Vec<_>>()
    });
    assert_eq!(one, two);
    // Prefetched with 1 or 3 workers: same items, same order.
    let g = Arc::new(make(corpus(6, Split::Train)));
    for workers in [1, 3] {
        let g = g.clone();
        let got: Vec<Vec<u8>> = Prefetcher::new(0, Some(8), workers, 2, move |i| g.sample(i))
            .map(|s| object_bytes(&s.unwrap()))
            .collect();
        assert_eq!(got, one, "{workers} workers");
    }
    // A different seed gives different samples.
    let other =
        ObjectSampleGenerator::new(corpus(6, Split::Train), ObjectSampleConfig::default(), 6)
            .unwrap();
    assert_ne!(object_bytes(&other.sample(0).unwrap()), one[0]);

    let room_cfg = RoomSampleConfig::default().with_resolution(160, 120);
    let rooms = |threads| {
        in_pool(threads, || {
            let g = RoomSampleGenerator::new(corpus(4, Split::Test), room_cfg.clone(), 9).unwrap();
            (0..3)
                .map(|i| room_bytes(&g.sample(i).unwrap()))
                .collect::<Vec<_>>()
        })
    };
    assert_eq!(rooms(1), rooms(2));
}

#[test]
fn assignment_is_a_partial_permutation_plus_bins_and_matches_are_close() {
    let g = ObjectSampleGenerator::new(corpus(5, Split::Test), ObjectSampleConfig::default(), 1)
        .unwrap();
    let mut rates = Vec::new();
    for i in 0..6 {
        let s = g.sample(i).unwrap();
        let (m, n) = (s.model_points.len(), s.observed_points.len());
        assert_eq!((m, n), (1024, 768));
        let d = s.assignment.dense();
        assert_eq!(d.len(), (m + 1) * (n + 1));
        for i in 0..m {
            let row: f32 = d[i * (n + 1)..(i + 1) * (n + 1)].iter().sum();
            assert_eq!(row, 1.0, "row {i}");
        }
        for j in 0..n {
            let col: f32 = (0..=m).map(|i| d[i * (n + 1) + j]).sum();
            assert_eq!(col, 1.0, "column {j}");
        }
        assert!(d.iter().all(|&v| v == 0.0 || v == 1.0));
        assert_eq!(d[m * (n + 1) + n], 0.0);
        // Matched pairs are within the threshold under the true pose, and mutual.
        let pairs = s.assignment.pairs();
        assert_eq!(pairs.len(), s.inlier_count());
        assert!(!pairs.is_empty());
        for (i, j) in &pairs {
            let moved = s.pose.apply_f32(s.model_points[*i]);
            assert!(moved.distance(s.observed_points[*j]) < PAPER_MATCH_THRESHOLD);
        }
        // Observed points are in front of the camera and the pose puts the model there too.
        assert!(s.observed_points.iter().all(|p| p.z > 0.5));
        rates.push(s.assignment.observed_inlier_rate());
        assert!(s.observed_voxels >= 768, "{} voxels", s.observed_voxels);
    }
    println!("object-alone observed inlier rates: {rates:?}");
}

#[test]
fn room_inlier_rates_fall_in_the_papers_range_at_full_resolution() {
    let g = RoomSampleGenerator::new(corpus(8, Split::Test), RoomSampleConfig::default(), 2024)
        .unwrap();
    let mut rates = Vec::new();
    let mut points = Vec::new();
    let mut objects = Vec::new();
    for i in 0..20 {
        let s = g.sample(i).unwrap();
        assert_eq!((s.depth.width, s.depth.height), (640, 480));
        assert_eq!(s.scene_points.len(), s.object_labels.len());
        assert!(s.bbox_visib[2] > 0 && s.bbox_obj[2] >= s.bbox_visib[2]);
        rates.push(100.0 * s.inlier_rate);
        points.push(s.scene_points.len());
        objects.push(s.object_point_count());
    }
    rates.sort_by(f64::total_cmp);
    points.sort();
    objects.sort();
    println!(
        "room inlier rates (%): {:?}",
        rates
            .iter()
            .map(|r| (r * 10.0).round() / 10.0)
            .collect::<Vec<_>>()
    );
    println!("room scene points: {points:?}");
    println!("room object points: {objects:?}");
    let below5 = rates.iter().filter(|&&r| r < 5.0).count();
    println!("{below5}/20 below 5 % (paper: 79 %)");
    assert!(
        rates.iter().all(|&r| (0.5..=23.5).contains(&r)),
        "{rates:?}"
    );
    assert!(below5 >= 12, "{below5}/20 below 5 %");
    assert!(
        points.iter().all(|&p| (10_000..=320_000).contains(&p)),
        "{points:?}"
    );
}

fn write_meshes(dir: &Path, count: usize, ext_bad: Option<&str>) {
    for k in 0..count {
        let mesh = random_object(100 + k as u64);
        write_mesh_ply(
            dir.join(format!("{k:03}.ply")),
            &mesh,
            PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
    }
    if let Some(name) = ext_bad {
        std::fs::write(dir.join(name), "v 0 0 0\nthis is not an obj\nf 1 2 9\n").unwrap();
    }
}

#[test]
fn unreadable_meshes_are_skipped_with_a_count_or_stop_and_empty_splits_are_errors() {
    let dir = tempfile::tempdir().unwrap();
    write_meshes(dir.path(), 3, Some("003.obj"));
    let split = FolderSplit::IdRange {
        train: (0, 3),
        test: (4, 9),
    };
    let skip = Corpus::mesh_folder(dir.path(), &split, Split::Train, light()).unwrap();
    assert_eq!(skip.len(), 4);
    assert_eq!(skip.preload().unwrap(), 3);
    assert_eq!(skip.skipped(), 1);
    // Generation keeps working, never showing the bad object.
    let g = ObjectSampleGenerator::new(Arc::new(skip), ObjectSampleConfig::default(), 3).unwrap();
    for i in 0..6 {
        assert_ne!(g.sample(i).unwrap().object_id, "003");
    }
    let stop = Corpus::mesh_folder(
        dir.path(),
        &split,
        Split::Train,
        CorpusOptions {
            on_bad_mesh: OnBadMesh::Stop,
            ..light()
        },
    )
    .unwrap();
    let err = stop.preload().unwrap_err().to_string();
    assert!(err.contains("003.obj"), "{err}");

    let empty = Corpus::mesh_folder(dir.path(), &split, Split::Test, light()).unwrap_err();
    assert!(matches!(empty, DataError::EmptySplit { .. }));
    assert!(
        empty
            .to_string()
            .contains(&dir.path().display().to_string()),
        "{empty}"
    );
    let nothing = tempfile::tempdir().unwrap();
    let e = Corpus::modelnet40(nothing.path(), Split::Train, light()).unwrap_err();
    assert!(
        e.to_string()
            .contains(&nothing.path().display().to_string()),
        "{e}"
    );
    assert!(
        Corpus::mesh_folder(dir.path().join("missing"), &split, Split::Train, light()).is_err()
    );
    assert!(Corpus::bop_models(nothing.path(), Split::Test, light()).is_err());

    // Only bad meshes: a typed error, not a panic or an endless loop.
    let bad_only = tempfile::tempdir().unwrap();
    std::fs::write(bad_only.path().join("000.off"), "OFF\n3 1 0\n0 0 0\n").unwrap();
    let c = Arc::new(
        Corpus::mesh_folder(
            bad_only.path(),
            &FolderSplit::blobs(),
            Split::Train,
            light(),
        )
        .unwrap(),
    );
    let g = ObjectSampleGenerator::new(c, ObjectSampleConfig::default(), 0).unwrap();
    assert!(matches!(g.sample(0), Err(DataError::NoUsableObject { .. })));
}

#[test]
fn modelnet_layout_split_file_and_bop_models_are_listed() {
    let root = tempfile::tempdir().unwrap();
    let cube = "OFF\n8 6 0\n-1 -1 -1\n1 -1 -1\n1 1 -1\n-1 1 -1\n-1 -1 1\n1 -1 1\n1 1 1\n-1 1 1\n4 0 3 2 1\n4 4 5 6 7\n4 0 1 5 4\n4 2 3 7 6\n4 1 2 6 5\n4 0 4 7 3\n";
    for class in ["chair", "mug"] {
        for (split, n) in [("train", 2), ("test", 1)] {
            let d = root.path().join(class).join(split);
            std::fs::create_dir_all(&d).unwrap();
            for k in 0..n {
                std::fs::write(d.join(format!("{class}_{k:04}.off")), cube).unwrap();
            }
        }
    }
    let train = Corpus::modelnet40(root.path(), Split::Train, light()).unwrap();
    assert_eq!(train.len(), 4);
    assert_eq!(train.entries()[0].id, "chair/chair_0000");
    let test = Corpus::modelnet40(root.path(), Split::Test, light()).unwrap();
    assert_eq!(test.len(), 2);
    let obj = test.object(0).unwrap();
    assert_eq!(obj.model_points.len(), 2048);
    assert!(
        obj.model_points
            .iter()
            .all(|p| p.abs().max_element() <= 1.0 + 1e-5)
    );

    let flat = tempfile::tempdir().unwrap();
    write_meshes(flat.path(), 4, None);
    let split_file = flat.path().join("split.json");
    std::fs::write(
        &split_file,
        r#"{"train": ["000", "002"], "test": [1, "003"]}"#,
    )
    .unwrap();
    let c = Corpus::mesh_folder(
        flat.path(),
        &FolderSplit::File(split_file.clone()),
        Split::Test,
        light(),
    )
    .unwrap();
    assert_eq!(
        c.entries()
            .iter()
            .map(|e| e.id.as_str())
            .collect::<Vec<_>>(),
        vec!["001", "003"]
    );
    std::fs::write(&split_file, r#"{"train": ["000"]}"#).unwrap();
    let e = Corpus::mesh_folder(
        flat.path(),
        &FolderSplit::File(split_file.clone()),
        Split::Test,
        light(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("split.json"), "{e}");
}

#[test]
fn bop_round_trip_preserves_poses_masks_depth_and_boxes() {
    let objects = corpus(3, Split::Test);
    let g = RoomSampleGenerator::new(
        objects.clone(),
        RoomSampleConfig::default().with_resolution(320, 240),
        77,
    )
    .unwrap();
    let samples: Vec<RoomSample> = (0..3).map(|i| g.sample(i).unwrap()).collect();
    let dir = tempfile::tempdir().unwrap();
    let mut w = BopWriter::create(
        dir.path(),
        BopWriteOptions {
            images_per_scene: 2,
            ..BopWriteOptions::default()
        },
    )
    .unwrap();
    for s in &samples {
        let obj = objects
            .object(objects.position(&s.object_id).unwrap())
            .unwrap();
        w.add(&s.bop_frame(&obj)).unwrap();
    }
    let summary = w.finish().unwrap();
    assert_eq!((summary.images, summary.scenes), (3, 2));
    for f in [
        "camera.json",
        "models/models_info.json",
        "test/000000/scene_gt.json",
        "test/000001/scene_gt_info.json",
        "test/000001/depth/000000.png",
        "test/000000/mask_visib/000001_000000.png",
    ] {
        assert!(dir.path().join(f).is_file(), "{f}");
    }
    let info: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("test/000000/scene_gt_info.json")).unwrap(),
    )
    .unwrap();
    assert!(info["0"][0]["visib_fract"].as_f64().unwrap() > 0.5);
    let models: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("models/models_info.json")).unwrap(),
    )
    .unwrap();
    for (_, m) in models.as_object().unwrap() {
        // Normalised objects span 2 units = 200 mm on their longest side.
        let longest = ["size_x", "size_y", "size_z"]
            .iter()
            .map(|k| m[*k].as_f64().unwrap())
            .fold(0.0, f64::max);
        assert!((longest - 200.0).abs() < 1e-3, "{longest}");
        assert!(m["diameter"].as_f64().unwrap() >= longest);
    }

    let ds = BopDataset::open(dir.path(), "test", light()).unwrap();
    assert_eq!(ds.len(), 3);
    for (i, s) in samples.iter().enumerate() {
        let r = ds.load(i, &BopLoadOptions::default()).unwrap();
        assert_eq!(r.mask_visib, s.mask_visib);
        assert_eq!(r.mask_all, s.mask_all);
        assert_eq!((r.bbox_visib, r.bbox_obj), (s.bbox_visib, s.bbox_obj));
        assert!(r.pose.rotation_angle_to(&s.pose) < 1e-6);
        assert!(
            (r.pose.translation - s.pose.translation).length() < 1e-4,
            "{:?} vs {:?}",
            r.pose,
            s.pose
        );
        // 1 mm depth steps = 0.01 units.
        let dmax = r
            .depth
            .data
            .iter()
            .zip(&s.depth.data)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(dmax <= 0.0051, "{dmax}");
        assert_eq!(r.model_points.len(), 1024);
        let rel = (r.scene_points.len() as f64 - s.scene_points.len() as f64).abs()
            / s.scene_points.len() as f64;
        assert!(
            rel < 0.05,
            "{} vs {}",
            r.scene_points.len(),
            s.scene_points.len()
        );
        assert!((r.inlier_rate - s.inlier_rate).abs() < 0.2 * s.inlier_rate);
    }
    // Object-alone samples need their images kept to be written to BOP.
    let og = ObjectSampleGenerator::new(
        objects.clone(),
        ObjectSampleConfig {
            keep_images: true,
            ..ObjectSampleConfig::default()
        },
        1,
    )
    .unwrap();
    let os = og.sample(0).unwrap();
    let obj = objects
        .object(objects.position(&os.object_id).unwrap())
        .unwrap();
    assert!(os.bop_frame(&obj).is_some());
    assert!(
        ObjectSampleGenerator::new(objects, ObjectSampleConfig::default(), 1)
            .unwrap()
            .sample(0)
            .unwrap()
            .bop_frame(&obj)
            .is_none()
    );
    assert!(BopDataset::open(dir.path(), "train", light()).is_err());
}

fn read_json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn pose_from_gt(gt: &serde_json::Value) -> ic_geometry::Pose {
    let r: [[f64; 3]; 3] = serde_json::from_value(gt["R"].clone()).unwrap();
    let t: [f64; 3] = serde_json::from_value(gt["t"].clone()).unwrap();
    ic_geometry::Pose::from_row_major(r, t).unwrap()
}

#[test]
fn exported_cases_have_the_documented_files_and_ground_truth() {
    let objects = corpus(3, Split::Test);
    let dir = tempfile::tempdir().unwrap();
    let og = ObjectSampleGenerator::new(objects.clone(), ObjectSampleConfig::default(), 4).unwrap();
    let s = og.sample(0).unwrap();
    let case = dir.path().join("noback_0000");
    write_object_case(&case, &s, 4).unwrap();
    let source = read_ply_cloud(case.join("source.ply")).unwrap().points;
    let target = read_ply_cloud(case.join("target.ply")).unwrap().points;
    assert_eq!((source.len(), target.len()), (1024, 768));
    let pose = pose_from_gt(&read_json(&case.join("gt.json")));
    for (i, j) in s.assignment.pairs() {
        assert!(pose.apply_f32(source[i]).distance(target[j]) < 0.05);
    }
    let meta = read_json(&case.join("meta.json"));
    assert_eq!(meta["object_id"], s.object_id.as_str());
    assert_eq!(meta["inliers"], s.inlier_count());

    let rg = RoomSampleGenerator::new(
        objects,
        RoomSampleConfig::default().with_resolution(160, 120),
        4,
    )
    .unwrap();
    let r = rg.sample(0).unwrap();
    let case = dir.path().join("room_0000");
    write_room_case(&case, &r, 4).unwrap();
    let target = read_ply_cloud(case.join("target.ply")).unwrap().points;
    assert_eq!(target.len(), r.scene_points.len());
    let cam = read_json(&case.join("camera.json"));
    assert_eq!(cam["width"], 160);
    assert_eq!(cam["cam_K"].as_array().unwrap().len(), 9);
    let depth = ic_render::io::read_depth_png(
        case.join("depth.png"),
        cam["depth_scale"].as_f64().unwrap(),
        Some((160, 120)),
    )
    .unwrap();
    // mask.png is the visible mask, pixel for pixel.
    let mask = ic_render::io::read_mask_png(case.join("mask.png"), Some((160, 120))).unwrap();
    assert_eq!(mask, r.mask_visib);
    // depth.png is in mm; 1 unit = unit_mm mm.
    let unit_m = cam["unit_mm"].as_f64().unwrap() / 1000.0;
    let (u, v) = (
        r.bbox_visib[0] as usize + r.bbox_visib[2] as usize / 2,
        r.bbox_visib[1] as usize + r.bbox_visib[3] as usize / 2,
    );
    let idx = v * 160 + u;
    assert!((depth.data[idx] as f64 / unit_m - r.depth.data[idx] as f64).abs() < 0.01);
    // The object's scene points lie near the moved model points.
    let pose = pose_from_gt(&read_json(&case.join("gt.json")));
    let moved: Vec<Vec3> = r.model_points.iter().map(|&p| pose.apply_f32(p)).collect();
    let tree = ic_geometry::KdTree::new(&moved).unwrap();
    let near = r
        .object_points()
        .iter()
        .filter(|p| tree.nearest(**p).distance < 0.1)
        .count();
    assert!(near as f64 > 0.9 * r.object_point_count() as f64);
    // No temporary files are left behind.
    assert!(
        std::fs::read_dir(&case).unwrap().all(|e| !e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .contains(".tmp"))
    );
}

#[test]
fn bad_configurations_are_typed_errors() {
    let c = corpus(2, Split::Train);
    let bad = ObjectSampleConfig {
        voxel_size: 0.0,
        ..ObjectSampleConfig::default()
    };
    assert!(matches!(
        ObjectSampleGenerator::new(c.clone(), bad, 0),
        Err(DataError::Config { .. })
    ));
    let bad = RoomSampleConfig {
        distance: (5.0, 1.0),
        ..RoomSampleConfig::default()
    };
    assert!(matches!(
        RoomSampleGenerator::new(c.clone(), bad, 0),
        Err(DataError::Config { .. })
    ));
    assert!(c.object(99).is_err());
    assert!(Corpus::procedural(0, Split::Train, 0, light()).is_err());
    assert!("valid".parse::<Split>().is_err());
}

#[test]
fn bop_round_trip_of_clutter_scenes_keeps_every_object_and_the_targets() {
    let objects = corpus(5, Split::Test);
    let cfg = ic_data::ClutterConfig {
        fixed_sizes: true,
        full_masks: true,
        sensor: None,
        multi_target_probability: 1.0,
        target_copies: (2, 2),
        object_count: (3, 4),
        ..ic_data::ClutterConfig::default().with_resolution(160, 120)
    };
    let g = ic_data::ClutterGenerator::new(objects, cfg, 12).unwrap();
    let scenes: Vec<ic_data::ClutterScene> = (0..2).map(|i| g.scene(i).unwrap()).collect();
    let dir = tempfile::tempdir().unwrap();
    let mut w = BopWriter::create(
        dir.path(),
        BopWriteOptions {
            depth_scale: 0.1,
            ..BopWriteOptions::default()
        },
    )
    .unwrap();
    for s in &scenes {
        w.add_clutter(s).unwrap();
    }
    w.finish().unwrap();
    let ds = BopDataset::open(dir.path(), "test", light()).unwrap();
    // Every placed object is annotated, two or more per image.
    let total: usize = scenes.iter().map(|s| s.objects.len()).sum();
    assert_eq!(ds.len(), total);
    let targets = ds.targets();
    assert_eq!(targets.len(), 2, "{targets:?}");
    let mut k = 0;
    for (im, s) in scenes.iter().enumerate() {
        let t = targets[im];
        assert_eq!((t.scene_id, t.im_id), (0, im as u32));
        // Both copies of the target count when each shows at least a tenth of itself.
        let shown = s
            .targets()
            .filter(|o| {
                let all = o
                    .full_mask
                    .as_ref()
                    .unwrap()
                    .data
                    .iter()
                    .filter(|&&b| b)
                    .count();
                o.visible_pixels > 0 && o.visible_pixels as f64 >= 0.1 * all as f64
            })
            .count();
        assert_eq!(t.inst_count, shown);
        assert_eq!(
            ds.instances_of(&t).len(),
            2,
            "the target's two copies are annotated"
        );
        for o in &s.objects {
            let r = ds.load(k, &BopLoadOptions::default()).unwrap();
            k += 1;
            assert_eq!(r.mask_visib, s.mask(o.instance_id));
            assert_eq!(&r.mask_all, o.full_mask.as_ref().unwrap());
            // The pose in the re-normalised model's units: compare in metres.
            let scale_m = r.normalisation.scale / 1000.0;
            let t_m = r.pose.translation * scale_m;
            let truth = o.pose;
            // The model re-normalised from mm may shift its centre; the rotation is exact.
            assert!(r.pose.rotation_angle_to(&truth) < 1e-6);
            let centre_m = truth.rotation * (r.normalisation.centre / 1000.0);
            assert!(
                (t_m - (truth.translation + centre_m)).length() < 1e-4,
                "{t_m:?} vs {:?}",
                truth.translation
            );
        }
    }
}
