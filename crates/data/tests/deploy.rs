//! Tests of the deployment-like sampling switches (`ic_data::deploy`), the validation split
//! and mixture corpora: every switch changes what it claims and nothing else, and the ground
//! truth stays exact under all of them. Objects are procedural or written to temp folders.

use std::path::Path;
use std::sync::Arc;

use ic_data::deploy::{
    CameraDistance, ImagePlacement, OccluderConfig, ScaleAugmentation, SensorRanges, ViewSampling,
};
use ic_data::*;
use ic_geometry::glam::DVec3;
use ic_geometry::io::{PlyEncoding, write_mesh_ply};
use ic_geometry::sampling::VisibleSurfaceOptions;
use ic_geometry::shapes::random_object;
use ic_geometry::{Intrinsics, Mesh, Pose};
use ic_render::{Camera, CpuRenderer, ObjectRotation, Renderer, Scene};

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

/// The deployment protocol at 320×240 (the same 49° field of view, a quarter of the pixels,
/// so the tests stay fast) with spans of 30–100 % of the image height.
fn small_deployment() -> ObjectSampleConfig {
    ObjectSampleConfig {
        intrinsics: Intrinsics {
            fx: 262.5,
            fy: 262.5,
            cx: 159.5,
            cy: 119.5,
            width: 320,
            height: 240,
        },
        distance: CameraDistance::ImageSpan { min: 0.3, max: 1.0 },
        model_points: 512,
        observed_points: 384,
        // The render's own pose (the copies are tested on their own).
        copy_rotations: 0,
        ..ObjectSampleConfig::deployment()
    }
}

/// Every switch off except the image-span distance (so the deployment path runs), with spans
/// of 30–80 % (a centred object never touches the border).
fn plain() -> ObjectSampleConfig {
    ObjectSampleConfig {
        distance: CameraDistance::ImageSpan { min: 0.3, max: 0.8 },
        rotation: ObjectRotation::Canonical,
        viewpoints: ViewSampling::Paper,
        camera_roll: false,
        placement: None,
        scale_augmentation: None,
        occluder: None,
        sensor: None,
        mask_erosions: 0,
        crop_radius: None,
        ..small_deployment()
    }
}

fn generator(corpus: Arc<Corpus>, cfg: ObjectSampleConfig, seed: u64) -> ObjectSampleGenerator {
    ObjectSampleGenerator::new(corpus, cfg, seed).unwrap()
}

/// The model given to the network: the corpus object's normalised mesh scaled by the sample's
/// `model_scale`.
fn model_mesh(corpus: &Corpus, s: &ObjectSample) -> Mesh {
    let o = corpus
        .object(corpus.position(&s.object_id).unwrap())
        .unwrap();
    Mesh {
        vertices: o.mesh.vertices.iter().map(|&v| v * s.model_scale).collect(),
        triangles: o.mesh.triangles.clone(),
    }
}

/// A full-size ideal render of the sample's model at its true pose (camera at the origin).
fn ideal_render(corpus: &Corpus, s: &ObjectSample) -> ic_render::Rendering {
    let scene = Scene::single(Arc::new(model_mesh(corpus, s)), s.pose, 1);
    CpuRenderer::new()
        .render(&scene, &Camera::new(s.intrinsics, Pose::IDENTITY))
        .unwrap()
}

#[test]
fn sensor_off_gives_the_ideal_depth_at_the_true_pose_and_sensor_on_changes_it() {
    let c = corpus(4, Split::Train);
    let keep = |sensor: Option<SensorRanges>| ObjectSampleConfig {
        keep_images: true,
        sensor,
        occluder: None,
        mask_erosions: 0,
        crop_radius: None,
        ..small_deployment()
    };
    let ideal = generator(c.clone(), keep(None), 3);
    let noisy = generator(c.clone(), keep(Some(SensorRanges::default())), 3);
    for i in 0..4 {
        let a = ideal.sample(i).unwrap();
        let b = noisy.sample(i).unwrap();
        // Same object, pose and scale: the sensor has its own random stream.
        assert_eq!(
            (&a.object_id, a.pose, a.model_scale),
            (&b.object_id, b.pose, b.model_scale)
        );
        assert!(a.sensor.is_none() && b.sensor.is_some());
        let reference = ideal_render(&c, &a);
        let (depth, mask) = (a.depth.as_ref().unwrap(), a.mask.as_ref().unwrap());
        assert_eq!((depth.width, depth.height), (320, 240));
        // The windowed render is the full render: same pixels, same depth (f64 set-up with a
        // shifted principal point: equal to rounding, silhouette ties aside).
        let mut differ = 0;
        let mut object = 0;
        for (k, (&z, &id)) in reference
            .depth
            .data
            .iter()
            .zip(&reference.instances.data)
            .enumerate()
        {
            let ours = depth.data[k];
            object += (id == 1) as usize;
            if (id == 1) != mask.data[k] || (z - ours).abs() > 1e-5 * z.max(1.0) {
                differ += 1;
            }
        }
        assert!(object > 500, "{object} object pixels");
        assert!(
            differ * 500 <= object,
            "{differ} of {object} pixels differ from the ideal render"
        );
        // With the sensor model most object pixels move (noise) or vanish (dropout).
        let (bd, bm) = (b.depth.as_ref().unwrap(), b.mask.as_ref().unwrap());
        let moved = (0..bd.data.len())
            .filter(|&k| reference.instances.data[k] == 1)
            .filter(|&k| {
                !bm.data[k]
                    || (bd.data[k] - reference.depth.data[k]).abs() > 1e-4 * reference.depth.data[k]
            })
            .count();
        assert!(
            moved * 2 > object,
            "{moved} of {object} object pixels changed by the sensor"
        );
        assert!(b.metres_per_unit > 0.0);
    }
}

#[test]
fn whole_sphere_views_cover_all_eight_octants_of_the_model_frame() {
    let c = corpus(3, Split::Train);
    let octants = |viewpoints: ViewSampling| {
        let g = generator(
            c.clone(),
            ObjectSampleConfig {
                viewpoints,
                ..plain()
            },
            5,
        );
        let mut seen = [0usize; 8];
        for i in 0..48 {
            let s = g.sample(i).unwrap();
            // The camera centre in the model frame (canonical object rotation, no roll).
            let eye = s.pose.inverse().translation;
            let d = s.viewpoint;
            let expect = DVec3::new(
                d.elevation_deg.to_radians().cos() * d.azimuth_deg.to_radians().cos(),
                d.elevation_deg.to_radians().cos() * d.azimuth_deg.to_radians().sin(),
                d.elevation_deg.to_radians().sin(),
            ) * d.distance;
            assert!(
                eye.distance(expect) < 1e-6 * d.distance,
                "{eye} vs {expect}"
            );
            seen[(eye.x > 0.0) as usize
                + 2 * (eye.y > 0.0) as usize
                + 4 * (eye.z > 0.0) as usize] += 1;
        }
        seen
    };
    let sphere = octants(ViewSampling::Sphere);
    assert!(sphere.iter().all(|&n| n > 0), "{sphere:?}");
    let paper = octants(ViewSampling::Paper);
    assert_eq!(paper[7], 48, "{paper:?}");
}

#[test]
fn camera_roll_and_uniform_rotation_change_the_pose_only() {
    let c = corpus(3, Split::Train);
    let base = generator(c.clone(), plain(), 8);
    let rolled = generator(
        c.clone(),
        ObjectSampleConfig {
            camera_roll: true,
            ..plain()
        },
        8,
    );
    for i in 0..4 {
        let (a, b) = (base.sample(i).unwrap(), rolled.sample(i).unwrap());
        // Roll about the optical axis: same centre, same distance, rotated image.
        assert!(a.pose.translation.distance(b.pose.translation) < 1e-9);
        let rel = b.pose.rotation * a.pose.rotation.transpose();
        assert!(
            (rel * DVec3::Z).distance(DVec3::Z) < 1e-9,
            "a roll keeps the optical axis"
        );
        // Same visible surface, so about the same number of pixels.
        let ratio = a.visible_pixels as f64 / b.visible_pixels as f64;
        assert!((0.9..1.1).contains(&ratio), "{ratio}");
    }
    let any = generator(
        c,
        ObjectSampleConfig {
            rotation: ObjectRotation::Uniform,
            viewpoints: ViewSampling::Sphere,
            camera_roll: true,
            ..plain()
        },
        8,
    );
    // Uniform rotations: the model's z axis in the camera frame points everywhere.
    let mut octants = [false; 8];
    for i in 0..40 {
        let z = any.sample(i).unwrap().pose.rotation * DVec3::Z;
        octants[(z.x > 0.0) as usize + 2 * (z.y > 0.0) as usize + 4 * (z.z > 0.0) as usize] = true;
    }
    assert!(octants.iter().filter(|&&o| o).count() >= 7, "{octants:?}");
}

#[test]
fn image_span_sets_the_distance_and_small_objects_give_few_voxels() {
    let c = corpus(3, Split::Train);
    let at = |span: f64| ObjectSampleConfig {
        distance: CameraDistance::ImageSpan {
            min: span,
            max: span,
        },
        ..plain()
    };
    let near = generator(c.clone(), at(1.0), 2);
    let far = generator(c.clone(), at(0.15), 2);
    let half_angle = |f: f64| (f * 240.0 / (2.0 * 262.5)).atan();
    for i in 0..4 {
        let (a, b) = (near.sample(i).unwrap(), far.sample(i).unwrap());
        assert_eq!(a.object_id, b.object_id);
        // d = r / sin(half angle), r the bounding sphere radius of the normalised object.
        let o = c.object(c.position(&a.object_id).unwrap()).unwrap();
        let r = o
            .mesh
            .vertices
            .iter()
            .map(|v| v.length() as f64)
            .fold(0.0, f64::max);
        assert!((a.viewpoint.distance - r / half_angle(1.0).sin()).abs() < 1e-4);
        assert!((b.viewpoint.distance - r / half_angle(0.15).sin()).abs() < 1e-4);
        // The far object is pixel-limited: fewer voxels than pixels are lost, and far fewer
        // voxels than the near view.
        assert!(
            b.observed_voxels * 3 < a.observed_voxels,
            "{} vs {}",
            b.observed_voxels,
            a.observed_voxels
        );
        assert!(b.observed_voxels >= 64);
        assert_eq!(
            b.observed_points.len(),
            384,
            "N points even from few voxels"
        );
    }
}

#[test]
fn occluder_hides_the_fraction_it_draws() {
    let c = corpus(4, Split::Train);
    for (lo, hi) in [(0.3, 0.3), (0.1, 0.5)] {
        let occluded = ObjectSampleConfig {
            occluder: Some(OccluderConfig {
                probability: 1.0,
                hidden_fraction: (lo, hi),
                ..OccluderConfig::default()
            }),
            ..plain()
        };
        let free = generator(c.clone(), plain(), 4);
        let hidden = generator(c.clone(), occluded, 4);
        for i in 0..6 {
            let (a, b) = (free.sample(i).unwrap(), hidden.sample(i).unwrap());
            assert_eq!(a.pose, b.pose);
            assert_eq!(a.occluded_fraction, 0.0);
            // Measured independently: pixels lost against the same view without occluder.
            let lost = 1.0 - b.visible_pixels as f64 / a.visible_pixels as f64;
            assert!(
                (lost - b.occluded_fraction).abs() < 0.01,
                "{lost} vs {}",
                b.occluded_fraction
            );
            assert!(
                lost >= lo - 0.01 && lost <= hi + 0.01,
                "{lost} outside [{lo}, {hi}]"
            );
        }
    }
}

#[test]
fn truncation_cuts_objects_at_the_border_only_when_switched_on() {
    let c = corpus(3, Split::Train);
    let centred = generator(c.clone(), plain(), 6);
    let inside = generator(
        c.clone(),
        ObjectSampleConfig {
            placement: Some(ImagePlacement {
                truncation_probability: 0.0,
            }),
            ..plain()
        },
        6,
    );
    let anywhere = generator(
        c.clone(),
        ObjectSampleConfig {
            placement: Some(ImagePlacement {
                truncation_probability: 1.0,
            }),
            ..plain()
        },
        6,
    );
    let (mut cut, mut lost) = (0, 0);
    for i in 0..16 {
        let a = centred.sample(i).unwrap();
        assert!(!a.truncated);
        // Centred: the centre on the optical axis.
        assert!(a.pose.translation.x.abs() < 1e-9 && a.pose.translation.y.abs() < 1e-9);
        let b = inside.sample(i).unwrap();
        assert!(!b.truncated, "sample {i} touches the border");
        let s = anywhere.sample(i).unwrap();
        cut += s.truncated as usize;
        // Cut by the border: a clear part of the object is lost against the centred view
        // (off the axis the object looks a little larger, hence the margin).
        lost += (s.truncated && (s.visible_pixels as f64) < 0.8 * a.visible_pixels as f64) as usize;
    }
    assert!(cut >= 6, "{cut}/16 truncated");
    assert!(lost >= 3, "{lost}/16 lost a fifth of the object");
}

#[test]
fn anisotropic_scale_changes_the_extents_within_twenty_percent() {
    let c = corpus(4, Split::Train);
    let g = generator(
        c.clone(),
        ObjectSampleConfig {
            scale_augmentation: Some(ScaleAugmentation { max_relative: 0.2 }),
            ..plain()
        },
        9,
    );
    let mut changed = 0;
    for i in 0..12 {
        let s = g.sample(i).unwrap();
        let f = s.model_scale;
        // Per-axis factors in [0.8, 1.2], up to the common renormalisation: ratios within
        // [0.8/1.2, 1.2/0.8].
        for (a, b) in [(f.x, f.y), (f.y, f.z), (f.x, f.z)] {
            assert!(
                (0.8 / 1.2 - 1e-6..=1.2 / 0.8 + 1e-6).contains(&(a / b)),
                "{f}"
            );
        }
        changed += ((f.x / f.y - 1.0).abs() > 0.01) as usize;
        // Renormalised: the scaled mesh's longest side spans [-1, 1] again, centred.
        let mesh = model_mesh(&c, &s);
        let b = mesh.bounds().unwrap();
        assert!(
            (b.extent().max_element() - 2.0).abs() < 1e-5,
            "{}",
            b.extent()
        );
        assert!(b.centre().length() < 1e-5);
        // Its extents moved by at most the factors.
        let o = c.object(c.position(&s.object_id).unwrap()).unwrap();
        let e0 = o.mesh.bounds().unwrap().extent();
        let ratio = b.extent() / e0;
        let (lo, hi) = (ratio.min_element(), ratio.max_element());
        assert!(hi / lo <= 1.2 / 0.8 + 1e-6, "{ratio}");
        // The model points given to the network lie in the scaled mesh's box.
        assert!(
            s.model_points
                .iter()
                .all(|p| p.abs().max_element() <= 1.0 + 1e-4)
        );
    }
    assert!(changed >= 10, "{changed}/12 samples changed the aspect");
}

#[test]
fn ground_truth_pairs_stay_within_the_threshold_with_every_augmentation_on() {
    let c = corpus(5, Split::Train);
    let g = generator(c.clone(), small_deployment(), 42);
    let mut inliers = 0;
    for i in 0..8 {
        let s = g.sample(i).unwrap();
        assert_eq!((s.model_points.len(), s.observed_points.len()), (512, 384));
        let pairs = s.assignment.pairs();
        inliers += pairs.len();
        for (i, j) in &pairs {
            let moved = s.pose.apply_f32(s.model_points[*i]);
            assert!(moved.distance(s.observed_points[*j]) < PAPER_MATCH_THRESHOLD);
        }
        assert!(s.observed_points.iter().all(|p| p.is_finite() && p.z > 0.0));
        // The pose is a rotation.
        assert!((s.pose.rotation.determinant() - 1.0).abs() < 1e-9);
    }
    assert!(inliers > 8 * 20, "{inliers} matched pairs in 8 samples");
}

#[test]
fn deployment_samples_are_seeded_and_identical_across_thread_counts() {
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let g = generator(corpus(4, Split::Train), small_deployment(), 77);
                (0..4).map(|i| g.sample(i).unwrap()).collect::<Vec<_>>()
            })
    };
    let (one, two) = (run(1), run(2));
    assert_eq!(one, two);
    let other = generator(corpus(4, Split::Train), small_deployment(), 78);
    assert_ne!(other.sample(0).unwrap(), one[0]);
}

#[test]
fn bad_deployment_configurations_are_typed_errors() {
    let bad = [
        ObjectSampleConfig {
            distance: CameraDistance::ImageSpan { min: 0.0, max: 1.0 },
            ..plain()
        },
        ObjectSampleConfig {
            distance: CameraDistance::ImageSpan { min: 0.5, max: 0.2 },
            ..plain()
        },
        ObjectSampleConfig {
            placement: Some(ImagePlacement {
                truncation_probability: 1.5,
            }),
            ..plain()
        },
        ObjectSampleConfig {
            scale_augmentation: Some(ScaleAugmentation {
                max_relative: f64::NAN,
            }),
            ..plain()
        },
        ObjectSampleConfig {
            occluder: Some(OccluderConfig {
                hidden_fraction: (0.2, 1.0),
                ..OccluderConfig::default()
            }),
            ..plain()
        },
        ObjectSampleConfig {
            sensor: Some(SensorRanges {
                jitter_sigma_px: (0.0, 3.0),
                ..SensorRanges::default()
            }),
            ..plain()
        },
        ObjectSampleConfig {
            crop_radius: Some(-1.0),
            ..plain()
        },
    ];
    for cfg in bad {
        let e = ObjectSampleGenerator::new(corpus(1, Split::Train), cfg, 0).unwrap_err();
        assert!(matches!(e, DataError::Config { .. }), "{e}");
    }
    // The protocols parse, and serialise as configuration.
    assert_eq!(
        "deployment".parse::<SamplingProtocol>().unwrap().config(),
        ObjectSampleConfig::deployment()
    );
    assert!(
        "paper"
            .parse::<SamplingProtocol>()
            .unwrap()
            .config()
            .is_paper_protocol()
    );
    assert!("other".parse::<SamplingProtocol>().is_err());
    let json = serde_json::to_string(&ObjectSampleConfig::deployment()).unwrap();
    let back: ObjectSampleConfig = serde_json::from_str(&json).unwrap();
    assert_eq!(back, ObjectSampleConfig::deployment());
    // An old configuration (no deployment fields) still reads, as the paper's protocol.
    let old: ObjectSampleConfig = serde_json::from_str(r#"{"voxel_size": 0.05}"#).unwrap();
    assert!(old.is_paper_protocol());
}

fn write_meshes(dir: &Path, count: usize) {
    for k in 0..count {
        write_mesh_ply(
            dir.join(format!("{k:05}.ply")),
            &random_object(300 + k as u64),
            PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
    }
}

#[test]
fn split_file_with_val_loads_three_disjoint_splits() {
    let dir = tempfile::tempdir().unwrap();
    write_meshes(dir.path(), 7);
    let file = dir.path().join("split.json");
    std::fs::write(
        &file,
        r#"{"train": ["00000", "00001", "00002"], "val": ["00003", 4], "test": ["00005", "00006"]}"#,
    )
    .unwrap();
    let how = FolderSplit::File(file.clone());
    let ids = |split: Split| {
        Corpus::mesh_folder(dir.path(), &how, split, light())
            .unwrap()
            .entries()
            .iter()
            .map(|e| e.id.clone())
            .collect::<Vec<_>>()
    };
    let (train, val, test) = (ids(Split::Train), ids(Split::Val), ids(Split::Test));
    assert_eq!(train, ["00000", "00001", "00002"]);
    assert_eq!(val, ["00003", "00004"]);
    assert_eq!(test, ["00005", "00006"]);
    assert_eq!("val".parse::<Split>().unwrap(), Split::Val);
    // Overlapping lists are an error naming the file and the object.
    std::fs::write(
        &file,
        r#"{"train": ["00000", "00003"], "val": ["00003"], "test": ["00005"]}"#,
    )
    .unwrap();
    let e = Corpus::mesh_folder(dir.path(), &how, Split::Train, light()).unwrap_err();
    assert!(
        e.to_string().contains("split.json") && e.to_string().contains("00003"),
        "{e}"
    );
    // No val list: the val split is an error, the others still load.
    std::fs::write(&file, r#"{"train": ["00000"], "test": ["00005"]}"#).unwrap();
    assert!(Corpus::mesh_folder(dir.path(), &how, Split::Val, light()).is_err());
    assert!(Corpus::mesh_folder(dir.path(), &how, Split::Test, light()).is_ok());
    // Id ranges: the old two-range split has no val; the three-range split does.
    assert!(Corpus::mesh_folder(dir.path(), &FolderSplit::blobs(), Split::Val, light()).is_err());
    let three = FolderSplit::IdRanges {
        train: (0, 2),
        val: (3, 4),
        test: (5, 6),
    };
    assert_eq!(
        Corpus::mesh_folder(dir.path(), &three, Split::Val, light())
            .unwrap()
            .len(),
        2
    );
    let overlap = FolderSplit::IdRanges {
        train: (0, 3),
        val: (3, 4),
        test: (5, 6),
    };
    assert!(Corpus::mesh_folder(dir.path(), &overlap, Split::Train, light()).is_err());
    // The blob layout with val keeps the test split of the blob layout.
    let FolderSplit::IdRanges { test, .. } = FolderSplit::blobs_with_val() else {
        panic!()
    };
    let FolderSplit::IdRange { test: old_test, .. } = FolderSplit::blobs() else {
        panic!()
    };
    assert_eq!(test, old_test);
    // Procedural val objects differ from train and test objects.
    let p = |split| {
        Corpus::procedural(3, split, 1, light())
            .unwrap()
            .entries()
            .to_vec()
    };
    let (a, b, t) = (p(Split::Train), p(Split::Val), p(Split::Test));
    assert!(b.iter().all(|e| !a.contains(e) && !t.contains(e)));
}

#[test]
fn mixture_draws_sources_in_the_given_proportions_and_is_seeded() {
    let part = |name: &str, seed: u64, weight: f64| MixturePart {
        name: name.into(),
        corpus: Corpus::procedural(2, Split::Train, seed, light()).unwrap(),
        weight,
    };
    let mix = Corpus::mixture(vec![
        part("real", 1, 0.6),
        part("blobs", 2, 0.3),
        part("proc", 3, 0.1),
    ])
    .unwrap();
    assert_eq!(mix.len(), 6);
    assert!(mix.entries()[0].id.starts_with("real/proc_"));
    assert_eq!(mix.source_of(5), Some("proc"));
    let sources = mix.sources();
    assert!((sources[1].probability - 0.3).abs() < 1e-12);
    let draws = |seed: u64| {
        let mut rng = sample_rng(seed, 0);
        (0..6000)
            .map(|_| mix.pick(&mut rng).unwrap().id.clone())
            .collect::<Vec<_>>()
    };
    let a = draws(7);
    assert_eq!(a, draws(7), "seeded");
    assert_ne!(a, draws(8));
    for (name, p) in [("real/", 0.6), ("blobs/", 0.3), ("proc/", 0.1)] {
        let share = a.iter().filter(|id| id.starts_with(name)).count() as f64 / a.len() as f64;
        // 4 standard deviations of a binomial share over 6000 draws.
        let tol = 4.0 * (p * (1.0 - p) / 6000.0f64).sqrt();
        assert!((share - p).abs() < tol, "{name}: {share} vs {p}");
    }
    // An object keeps its model points in a mixture.
    let alone = Corpus::procedural(2, Split::Train, 2, light()).unwrap();
    let id = &alone.entries()[1].id;
    let in_mix = mix
        .object(mix.position(&format!("blobs/{id}")).unwrap())
        .unwrap();
    assert_eq!(in_mix.model_points, alone.object(1).unwrap().model_points);
    // Bad mixtures are typed errors.
    assert!(Corpus::mixture(vec![]).is_err());
    assert!(Corpus::mixture(vec![part("a", 1, 1.0), part("a", 2, 1.0)]).is_err());
    assert!(Corpus::mixture(vec![part("a", 1, 0.0)]).is_err());
    assert!(Corpus::mixture(vec![part("a/b", 1, 1.0)]).is_err());
    let val = MixturePart {
        name: "v".into(),
        corpus: Corpus::procedural(2, Split::Val, 1, light()).unwrap(),
        weight: 1.0,
    };
    assert!(Corpus::mixture(vec![part("a", 1, 1.0), val]).is_err());
    // A sample from a mixture names its source.
    let g = generator(Arc::new(mix), ObjectSampleConfig::default(), 1);
    let s = g.sample(0).unwrap();
    assert!(
        ["real/", "blobs/", "proc/"]
            .iter()
            .any(|p| s.object_id.starts_with(p))
    );
}

#[test]
fn copy_rotations_keep_every_view_within_the_groups_radius_of_the_paper_family() {
    let corpus = corpus(6, Split::Train);
    let reference = ic_geometry::rotations::paper_view_rotation();
    let with = generator(
        corpus.clone(),
        ObjectSampleConfig {
            copy_rotations: 24,
            ..small_deployment()
        },
        5,
    );
    let without = generator(corpus, small_deployment(), 5);
    let mut far_without = 0;
    for i in 0..24 {
        let a = with.sample(i).unwrap();
        let b = without.sample(i).unwrap();
        let angle = |s: &ObjectSample| {
            Pose::new(s.pose.rotation, DVec3::ZERO)
                .rotation_angle_to(&reference)
                .to_degrees()
        };
        assert!(angle(&a) < 63.0, "sample {i}: {}°", angle(&a));
        far_without += (angle(&b) > 63.0) as usize;
        // The same view: the observed points are untouched, the model points and pose are
        // re-expressed together, so the pose maps the model onto the view as before.
        assert_eq!(a.observed_points, b.observed_points);
        for (p, q) in a.model_points.iter().zip(&b.model_points) {
            assert!((a.pose.apply_f32(*p) - b.pose.apply_f32(*q)).length() < 1e-4);
        }
        assert_eq!(a.assignment, b.assignment);
    }
    assert!(
        far_without > 8,
        "whole-sphere views are mostly far from the paper family"
    );
}

/// A box with three different sides has the three half-turns as symmetries; they commute with
/// any per-axis scale, so every sample of it lists three equivalent poses, each turning the
/// model by 180° onto its own surface. With the copy rotations the same three motions appear
/// in the camera frame; without the switch, none are listed.
#[test]
fn symmetry_aware_samples_list_the_equivalent_poses_of_a_box() {
    let dir = tempfile::tempdir().unwrap();
    let half = DVec3::new(1.0, 0.6, 0.3);
    let mesh = ic_geometry::shapes::box_mesh(half.as_vec3()).unwrap();
    write_mesh_ply(
        dir.path().join("00000.ply"),
        &mesh,
        PlyEncoding::BinaryLittleEndian,
    )
    .unwrap();
    let corpus = Arc::new(
        Corpus::mesh_folder(
            dir.path(),
            &FolderSplit::IdRange {
                train: (0, 0),
                test: (1, 1),
            },
            Split::Train,
            light(),
        )
        .unwrap(),
    );
    let cfg = ObjectSampleConfig {
        symmetry_aware: true,
        ..small_deployment()
    };
    assert!(cfg.scale_augmentation.is_some() && cfg.copy_rotations == 0);
    let with = generator(corpus.clone(), cfg.clone(), 3);
    let copied = generator(
        corpus.clone(),
        ObjectSampleConfig {
            copy_rotations: 24,
            ..cfg.clone()
        },
        3,
    );
    let without = generator(
        corpus,
        ObjectSampleConfig {
            symmetry_aware: false,
            ..cfg
        },
        3,
    );
    // Camera-frame motions P'·P⁻¹ of a sample's equivalent poses.
    let motions = |s: &ObjectSample| -> Vec<Pose> {
        s.equivalent_poses
            .iter()
            .map(|p| p.compose(&s.pose.inverse()))
            .collect()
    };
    for i in 0..4 {
        let s = with.sample(i).unwrap();
        assert_eq!(s.equivalent_poses.len(), 3, "sample {i}");
        assert_eq!(s.alternatives.len(), 3);
        let back = s.pose.inverse();
        let scale = s.model_scale.as_dvec3();
        for (p, a) in s.equivalent_poses.iter().zip(&s.alternatives) {
            assert!((p.rotation_angle_to(&s.pose).to_degrees() - 180.0).abs() < 1.0);
            // Back in the corpus box's frame, every moved model point is on the box.
            for x in &s.model_points {
                let w = back.apply(p.apply(x.as_dvec3())) / scale;
                let on = (w.abs() / half).max_element();
                assert!((on - 1.0).abs() < 0.03, "sample {i}: {w:?} is off the box");
            }
            assert!(
                a.inlier_count() * 2 > s.assignment.inlier_count(),
                "sample {i}"
            );
        }
        let c = copied.sample(i).unwrap();
        for (m, n) in motions(&s).iter().zip(&motions(&c)) {
            assert!(m.rotation_angle_to(n) < 1e-6, "sample {i}");
            assert!((m.translation - n.translation).length() < 1e-6);
        }
        let plain = without.sample(i).unwrap();
        assert!(plain.equivalent_poses.is_empty() && plain.alternatives.is_empty());
        assert_eq!((plain.pose, &plain.assignment), (s.pose, &s.assignment));
    }
}

/// Symmetries given to a corpus are what its objects report when they load (no search), and
/// the corpus lists every object's symmetries once known: what a resumed run reloads.
#[test]
fn known_symmetries_replace_the_search_and_found_ones_are_listed() {
    let corpus = corpus(3, Split::Train);
    let id0 = corpus.entries()[0].id.clone();
    let half_turn = Pose::from_axis_angle(DVec3::Z, std::f64::consts::PI, DVec3::ZERO);
    corpus.set_known_symmetries([(id0.clone(), vec![half_turn])].into_iter().collect());
    assert!(corpus.found_symmetries().is_empty());
    assert_eq!(*corpus.object(0).unwrap().symmetries(), vec![half_turn]);
    let searched = corpus.object(1).unwrap().symmetries();
    let found = corpus.found_symmetries();
    assert_eq!(found.len(), 2);
    assert_eq!(found[&id0], vec![half_turn]);
    assert_eq!(found[&corpus.entries()[1].id], *searched);
}
