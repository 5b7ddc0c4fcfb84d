//! BOP datasets (<https://bop.felk.cvut.cz/datasets/>): writing generated sets and reading BOP
//! datasets (e.g. TUD-L) back into [`RoomSample`]s.
//!
//! Layout written and read (`<root>/<split>/<scene_id:06>/…`):
//! - `<root>/camera.json`: `fx, fy, cx, cy, width, height, depth_scale`;
//! - `<scene>/scene_camera.json`: per image `cam_K` (9 numbers, row-major) and `depth_scale`;
//! - `<scene>/scene_gt.json`: per image a list of `cam_R_m2c` (9, row-major), `cam_t_m2c` (mm),
//!   `obj_id`; optional when reading (test sets whose ground truth is withheld, e.g. ITODD's:
//!   their targets are then registered and written, not scored);
//! - `<scene>/scene_gt_info.json`: `bbox_obj`, `bbox_visib` (`[x, y, w, h]`), `px_count_all`,
//!   `px_count_valid`, `px_count_visib`, `visib_fract`;
//! - `<scene>/depth/{im_id:06}.png` (16-bit, `stored × depth_scale = mm`; reading also takes
//!   `.tif`, as ITODD stores it),
//!   `<scene>/mask/{im_id:06}_{gt_idx:06}.png` (full silhouette),
//!   `<scene>/mask_visib/{im_id:06}_{gt_idx:06}.png`;
//! - `<root>/models/obj_{obj_id:06}.ply` in mm and `models_info.json` (`diameter`, `min_*`,
//!   `size_*`), plus `ic_object_ids.json` mapping BOP ids to our corpus ids; the reader takes
//!   T-LESS's `models_cad/` when there is no `models/` ([`models_folder`]);
//! - `<root>/test_targets_bop19.json`: what to find in each image (`scene_id`, `im_id`,
//!   `obj_id`, `inst_count`); read when present, else every annotated object is a target
//!   (a split without any `scene_gt.json` needs the file).
//!
//! Cluttered scenes ([`BopWriter::add_clutter`]) are written in millimetres with every object
//! annotated, each model at its size in the scene (one object at two sizes is two models).
//!
//! **Units.** Our scenes are in normalised object units; BOP files are in millimetres. The
//! writer uses one fixed factor, [`BopWriteOptions::unit_mm`], default [`ROOM_UNIT_MM`] = 100
//! (1 unit = 1 dm: a normalised object is 20 cm across, the room of side 40 units is 4 m). The
//! reader normalises each BOP model (mm) into [-1, 1] and converts depth and poses with that
//! model's own `Normalisation` (1 unit = `scale` mm), so our own datasets read back in the
//! units they were written in.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use ic_geometry::glam::DVec3;
use ic_geometry::io::{PlyEncoding, write_mesh_ply};
use ic_geometry::{DepthImage, Image, Intrinsics, Mask, Mesh, Pose, random_subsample_indices};
use serde_json::{Value, json};

use crate::room::{mask_bbox, voxelise_scene};
use crate::seed::sample_rng;
use crate::{
    Corpus, CorpusObject, CorpusOptions, DataError, ObjectSample, ROOM_UNIT_MM, RoomSample, Split,
};

/// The BOP 19 list of what to localise in each test image (`{scene_id, im_id, obj_id,
/// inst_count}`), at the dataset's root.
pub const TEST_TARGETS_FILE: &str = "test_targets_bop19.json";

/// Options of [`BopWriter`].
#[derive(Clone, Debug, PartialEq)]
pub struct BopWriteOptions {
    /// Split folder name (`test`, `train_pbr`, …).
    pub split: String,
    /// Millimetres per normalised unit (default 100: 1 unit = 1 dm).
    pub unit_mm: f64,
    /// BOP depth scale: `stored × depth_scale = mm`. Default 1.0 (1 mm steps; 65.5 m range).
    pub depth_scale: f64,
    /// Images per scene folder (BOP's synthetic sets use 1000).
    pub images_per_scene: usize,
}

impl Default for BopWriteOptions {
    fn default() -> Self {
        BopWriteOptions {
            split: "test".into(),
            unit_mm: ROOM_UNIT_MM,
            depth_scale: 1.0,
            images_per_scene: 1000,
        }
    }
}

/// One image with one annotated object, in normalised units.
#[derive(Clone, Copy, Debug)]
pub struct BopFrame<'a> {
    pub intrinsics: Intrinsics,
    /// Camera-frame z in normalised units.
    pub depth: &'a DepthImage,
    pub mask_visib: &'a Mask,
    pub mask_all: &'a Mask,
    /// Model→camera, normalised units.
    pub pose: Pose,
    pub object: &'a CorpusObject,
}

impl RoomSample {
    /// This sample as a BOP frame (`object` is the corpus object it shows).
    pub fn bop_frame<'a>(&'a self, object: &'a CorpusObject) -> BopFrame<'a> {
        BopFrame {
            intrinsics: self.intrinsics,
            depth: &self.depth,
            mask_visib: &self.mask_visib,
            mask_all: &self.mask_all,
            pose: self.pose,
            object,
        }
    }
}

impl ObjectSample {
    /// This sample as a BOP frame; `None` unless it was generated with `keep_images`, and
    /// when its model was scale-augmented (the corpus object is not the model it shows).
    pub fn bop_frame<'a>(&'a self, object: &'a CorpusObject) -> Option<BopFrame<'a>> {
        if self.model_scale != glam::Vec3::ONE {
            return None;
        }
        let (depth, mask) = (self.depth.as_ref()?, self.mask.as_ref()?);
        Some(BopFrame {
            intrinsics: self.intrinsics,
            depth,
            mask_visib: mask,
            mask_all: mask,
            pose: self.pose,
            object,
        })
    }
}

/// What [`BopWriter::finish`] wrote.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BopSummary {
    pub root: PathBuf,
    pub images: u64,
    pub scenes: usize,
    /// BOP obj_id → corpus object id.
    pub objects: BTreeMap<u32, String>,
}

#[derive(Default)]
struct SceneAcc {
    camera: BTreeMap<u32, Value>,
    gt: BTreeMap<u32, Value>,
    info: BTreeMap<u32, Value>,
}

/// Streams frames into a BOP dataset; images are written as they come, the JSON files and
/// models by [`BopWriter::finish`]. Every file is written atomically.
pub struct BopWriter {
    root: PathBuf,
    options: BopWriteOptions,
    scenes: BTreeMap<u32, SceneAcc>,
    /// BOP obj_id → the corpus object and its millimetres per normalised unit.
    objects: BTreeMap<u32, (Arc<CorpusObject>, f64)>,
    /// (corpus id, mm per unit as bits) → BOP obj_id: one object at two sizes is two models.
    ids: HashMap<(String, u64), u32>,
    images: u64,
    camera: Option<Intrinsics>,
    /// `test_targets_bop19.json` entries: (scene_id, im_id, obj_id, inst_count).
    targets: Vec<(u32, u32, u32, usize)>,
}

fn write_json(path: &Path, value: &Value) -> Result<(), DataError> {
    crate::export::write_json_atomic(path, value)
}

fn create_dir(path: &Path) -> Result<(), DataError> {
    std::fs::create_dir_all(path).map_err(DataError::io(path))
}

impl BopWriter {
    /// Creates `<root>/<split>` and `<root>/models`.
    pub fn create(root: impl AsRef<Path>, options: BopWriteOptions) -> Result<Self, DataError> {
        if !(options.unit_mm.is_finite() && options.unit_mm > 0.0) {
            return Err(DataError::Config {
                field: "unit_mm",
                message: format!("must be positive, got {}", options.unit_mm),
            });
        }
        if !(options.depth_scale.is_finite() && options.depth_scale > 0.0) {
            return Err(DataError::Config {
                field: "depth_scale",
                message: format!("must be positive, got {}", options.depth_scale),
            });
        }
        if options.images_per_scene == 0
            || options.split.is_empty()
            || options.split.contains(['/', '\\'])
        {
            return Err(DataError::Config {
                field: "split/images_per_scene",
                message: "split must be a plain folder name, images_per_scene ≥ 1".into(),
            });
        }
        let root = root.as_ref().to_path_buf();
        create_dir(&root.join(&options.split))?;
        create_dir(&root.join("models"))?;
        Ok(BopWriter {
            root,
            options,
            scenes: BTreeMap::new(),
            objects: BTreeMap::new(),
            ids: HashMap::new(),
            images: 0,
            camera: None,
            targets: Vec::new(),
        })
    }

    /// The BOP id of `object` written at `unit_mm` millimetres per normalised unit
    /// (registering the model on first use).
    fn obj_id(&mut self, object: &CorpusObject, unit_mm: f64) -> u32 {
        let key = (object.id.clone(), unit_mm.to_bits());
        if let Some(&id) = self.ids.get(&key) {
            return id;
        }
        let id = object
            .bop_obj_id
            .filter(|i| !self.objects.contains_key(i))
            .unwrap_or_else(|| {
                (1..)
                    .find(|i| !self.objects.contains_key(i))
                    .unwrap_or(u32::MAX)
            });
        self.ids.insert(key, id);
        self.objects.insert(id, (Arc::new(object.clone()), unit_mm));
        id
    }

    /// The folder of the next image, its `(scene_id, im_id)`, with `depth/`, `mask/` and
    /// `mask_visib/` created.
    fn next_image(&mut self) -> Result<(PathBuf, u32, u32), DataError> {
        let per = self.options.images_per_scene as u64;
        let scene_id = (self.images / per) as u32;
        let im_id = (self.images % per) as u32;
        let scene_dir = self
            .root
            .join(&self.options.split)
            .join(format!("{scene_id:06}"));
        for sub in ["depth", "mask", "mask_visib"] {
            create_dir(&scene_dir.join(sub))?;
        }
        Ok((scene_dir, scene_id, im_id))
    }

    /// Records the camera and the annotations of one written image.
    fn record_image(
        &mut self,
        (scene_id, im_id): (u32, u32),
        k: Intrinsics,
        gt: Vec<Value>,
        info: Vec<Value>,
    ) {
        let acc = self.scenes.entry(scene_id).or_default();
        acc.camera.insert(
            im_id,
            json!({"cam_K": k.k_row_major().concat(), "depth_scale": self.options.depth_scale}),
        );
        acc.gt.insert(im_id, Value::Array(gt));
        acc.info.insert(im_id, Value::Array(info));
        self.camera.get_or_insert(k);
        self.images += 1;
    }

    /// Writes one cluttered scene (metres) as one image with every placed object annotated, in
    /// placement order (the target's instances first): models at their scene size, depth at
    /// `depth_scale`, `mask_visib/` from the instance image, `mask/` from the full
    /// silhouettes when the scene has them (else the visible mask). Objects with no visible
    /// pixel are annotated too, as BOP does. Returns `(scene_id, im_id)`.
    pub fn add_clutter(
        &mut self,
        scene: &crate::clutter::ClutterScene,
    ) -> Result<(u32, u32), DataError> {
        let k = scene.intrinsics;
        scene.depth.check_size(k.width, k.height)?;
        let (scene_dir, scene_id, im_id) = self.next_image()?;
        ic_render::io::write_depth_png(
            scene_dir.join(format!("depth/{im_id:06}.png")),
            &scene.depth,
            self.options.depth_scale,
        )?;
        let (mut gt, mut info) = (Vec::new(), Vec::new());
        let (mut target_id, mut target_count) = (None, 0);
        for (g, o) in scene.objects.iter().enumerate() {
            let unit_mm = o.scale_m * 1000.0;
            let obj_id = self.obj_id(&o.object, unit_mm);
            let visib = scene.mask(o.instance_id);
            let all = o.full_mask.clone().unwrap_or_else(|| visib.clone());
            let (gt_entry, info_entry, px_visib, fract) = annotate(
                &scene_dir,
                (im_id, g),
                obj_id,
                &o.pose,
                1000.0,
                (&all, &visib),
                &scene.depth,
            )?;
            gt.push(gt_entry);
            info.push(info_entry);
            if o.is_target {
                target_id = Some(obj_id);
                // BOP's rule: an instance is a target when at least 10 % of it is visible.
                target_count += usize::from(px_visib > 0 && fract >= 0.1);
            }
        }
        self.record_image((scene_id, im_id), k, gt, info);
        if let Some(obj_id) = target_id.filter(|_| target_count > 0) {
            self.targets.push((scene_id, im_id, obj_id, target_count));
        }
        Ok((scene_id, im_id))
    }

    /// Writes one image; returns its `(scene_id, im_id)`.
    pub fn add(&mut self, frame: &BopFrame<'_>) -> Result<(u32, u32), DataError> {
        let k = frame.intrinsics;
        frame.depth.check_size(k.width, k.height)?;
        frame.mask_visib.check_size(k.width, k.height)?;
        frame.mask_all.check_size(k.width, k.height)?;
        let (scene_dir, scene_id, im_id) = self.next_image()?;
        let u = self.options.unit_mm;
        let obj_id = self.obj_id(frame.object, u);
        let metres = Image {
            width: k.width,
            height: k.height,
            data: frame
                .depth
                .data
                .iter()
                .map(|&z| (z as f64 * u / 1000.0) as f32)
                .collect(),
        };
        ic_render::io::write_depth_png(
            scene_dir.join(format!("depth/{im_id:06}.png")),
            &metres,
            self.options.depth_scale,
        )?;
        let (gt, info, _, _) = annotate(
            &scene_dir,
            (im_id, 0),
            obj_id,
            &frame.pose,
            u,
            (frame.mask_all, frame.mask_visib),
            frame.depth,
        )?;
        self.record_image((scene_id, im_id), k, vec![gt], vec![info]);
        self.targets.push((scene_id, im_id, obj_id, 1));
        Ok((scene_id, im_id))
    }

    /// Writes the JSON files and the models.
    pub fn finish(self) -> Result<BopSummary, DataError> {
        let split_dir = self.root.join(&self.options.split);
        let keyed = |m: &BTreeMap<u32, Value>| {
            Value::Object(m.iter().map(|(k, v)| (k.to_string(), v.clone())).collect())
        };
        for (scene_id, acc) in &self.scenes {
            let dir = split_dir.join(format!("{scene_id:06}"));
            write_json(&dir.join("scene_camera.json"), &keyed(&acc.camera))?;
            write_json(&dir.join("scene_gt.json"), &keyed(&acc.gt))?;
            write_json(&dir.join("scene_gt_info.json"), &keyed(&acc.info))?;
        }
        let targets: Vec<Value> = self
            .targets
            .iter()
            .map(|&(scene_id, im_id, obj_id, n)| {
                json!({"im_id": im_id, "inst_count": n, "obj_id": obj_id, "scene_id": scene_id})
            })
            .collect();
        write_json(&self.root.join(TEST_TARGETS_FILE), &Value::Array(targets))?;
        if let Some(k) = self.camera {
            write_json(
                &self.root.join("camera.json"),
                &json!({"cx": k.cx, "cy": k.cy, "fx": k.fx, "fy": k.fy, "width": k.width, "height": k.height, "depth_scale": self.options.depth_scale}),
            )?;
        }
        let models = self.root.join("models");
        let mut info = serde_json::Map::new();
        let mut names = BTreeMap::new();
        for (obj_id, (object, unit_mm)) in &self.objects {
            let u = *unit_mm as f32;
            let mesh = Mesh {
                vertices: object.mesh.vertices.iter().map(|v| *v * u).collect(),
                triangles: object.mesh.triangles.clone(),
            };
            write_mesh_ply(
                models.join(format!("obj_{obj_id:06}.ply")),
                &mesh,
                PlyEncoding::BinaryLittleEndian,
            )?;
            info.insert(obj_id.to_string(), model_info(&mesh));
            names.insert(*obj_id, object.id.clone());
        }
        write_json(&models.join("models_info.json"), &Value::Object(info))?;
        write_json(
            &models.join("ic_object_ids.json"),
            &json!(
                names
                    .iter()
                    .map(|(k, v)| (k.to_string(), Value::String(v.clone())))
                    .collect::<serde_json::Map<_, _>>()
            ),
        )?;
        Ok(BopSummary {
            root: self.root,
            images: self.images,
            scenes: self.scenes.len(),
            objects: names,
        })
    }
}

/// The depth map of image `im_id` of a BOP scene folder, in metres: `depth/{im_id:06}.png`, or,
/// when there is no PNG, `depth/{im_id:06}.tif` (BOP's ITODD; `stored × depth_scale = mm`
/// either way). Errors name the PNG when neither exists.
fn read_bop_depth(
    scene_dir: &Path,
    im_id: u32,
    depth_scale: f64,
) -> Result<DepthImage, ic_render::ImageIoError> {
    let png = scene_dir.join(format!("depth/{im_id:06}.png"));
    let tif = scene_dir.join(format!("depth/{im_id:06}.tif"));
    if !png.exists() && tif.is_file() {
        return ic_render::io::read_depth_tiff(&tif, depth_scale, None);
    }
    ic_render::io::read_depth_png(&png, depth_scale, None)
}

/// One annotated object of an image (`im_id`, its `gt_index`-th): writes its `mask/` (`all`,
/// the full silhouette) and `mask_visib/` (`visib`) PNGs into `scene_dir` and returns its
/// `scene_gt.json` and `scene_gt_info.json` entries, its visible pixels and visible fraction.
/// `pose` maps the model into the camera in units of `mm_per_unit` millimetres; `depth` only
/// says where the sensor returned.
fn annotate(
    scene_dir: &Path,
    (im_id, gt_index): (u32, usize),
    obj_id: u32,
    pose: &Pose,
    mm_per_unit: f64,
    (all, visib): (&Mask, &Mask),
    depth: &DepthImage,
) -> Result<(Value, Value, usize, f64), DataError> {
    ic_render::io::write_mask_png(
        scene_dir.join(format!("mask/{im_id:06}_{gt_index:06}.png")),
        all,
    )?;
    ic_render::io::write_mask_png(
        scene_dir.join(format!("mask_visib/{im_id:06}_{gt_index:06}.png")),
        visib,
    )?;
    let count = |m: &Mask| m.data.iter().filter(|&&b| b).count();
    let (px_all, px_visib) = (count(all), count(visib));
    let px_valid = all
        .data
        .iter()
        .zip(&depth.data)
        .filter(|(m, z)| **m && **z > 0.0)
        .count();
    let fract = if px_all > 0 {
        px_visib as f64 / px_all as f64
    } else {
        0.0
    };
    let r = pose.rotation_row_major();
    let t = pose.translation * mm_per_unit;
    let gt = json!({"cam_R_m2c": r.concat(), "cam_t_m2c": [t.x, t.y, t.z], "obj_id": obj_id});
    let info = json!({
        "bbox_obj": mask_bbox(all),
        "bbox_visib": mask_bbox(visib),
        "px_count_all": px_all,
        "px_count_valid": px_valid,
        "px_count_visib": px_visib,
        "visib_fract": fract,
    });
    Ok((gt, info, px_visib, fract))
}

/// BOP `models_info` of a mesh: bounding box and diameter (the largest distance between two
/// vertices; computed on at most 4000 evenly strided vertices for large meshes).
fn model_info(mesh: &Mesh) -> Value {
    let b = mesh.bounds().unwrap_or(ic_geometry::Aabb {
        min: DVec3::ZERO,
        max: DVec3::ZERO,
    });
    let step = mesh.vertices.len().div_ceil(4000).max(1);
    let v: Vec<DVec3> = mesh
        .vertices
        .iter()
        .step_by(step)
        .map(|p| p.as_dvec3())
        .collect();
    let mut d2: f64 = 0.0;
    for i in 0..v.len() {
        for j in i + 1..v.len() {
            d2 = d2.max(v[i].distance_squared(v[j]));
        }
    }
    let e = b.extent();
    json!({"diameter": d2.sqrt(), "min_x": b.min.x, "min_y": b.min.y, "min_z": b.min.z, "size_x": e.x, "size_y": e.y, "size_z": e.z})
}

/// One annotated object instance of a BOP dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BopInstance {
    pub scene_id: u32,
    pub im_id: u32,
    /// Index in the image's `scene_gt.json` list (the `{gt_idx:06}` of mask files).
    pub gt_index: usize,
    pub obj_id: u32,
}

/// One entry of `test_targets_bop19.json`: find `inst_count` instances of `obj_id` in the
/// image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct BopTarget {
    pub scene_id: u32,
    pub im_id: u32,
    pub obj_id: u32,
    pub inst_count: usize,
}

struct GtEntry {
    rotation: [[f64; 3]; 3],
    translation_mm: [f64; 3],
}

struct SceneData {
    dir: PathBuf,
    camera: HashMap<u32, ([f64; 9], f64)>,
    /// By image; empty when the scene has no `scene_gt.json`.
    gt: HashMap<u32, Vec<GtEntry>>,
}

/// One test image's depth map in the normalised units of one object's model, for a target
/// without ground truth ([`BopDataset::image`]).
#[derive(Clone, Debug)]
pub struct BopImage {
    /// Depth along the camera's z axis, in the model's normalised units (1 unit =
    /// `normalisation.scale` mm); 0 = no return.
    pub depth: DepthImage,
    /// The image's camera (`cam_K` of `scene_camera.json`), in pixels.
    pub intrinsics: Intrinsics,
    /// The model (corpus id `obj_XXXXXX`, its normalisation).
    pub object: Arc<CorpusObject>,
}

/// Options of [`BopDataset::load`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BopLoadOptions {
    pub voxel_size: f32,
    /// M model points drawn per sample.
    pub model_points: usize,
    /// Seed of the model-point draw (sample `i` uses the stream `(seed, i)`).
    pub seed: u64,
}

impl Default for BopLoadOptions {
    fn default() -> Self {
        BopLoadOptions {
            voxel_size: crate::PAPER_VOXEL_SIZE,
            model_points: 1024,
            seed: 0,
        }
    }
}

/// A BOP dataset opened for reading: `<root>/models` and `<root>/<split>/<scene_id:06>/…`.
pub struct BopDataset {
    root: PathBuf,
    split: String,
    corpus: Arc<Corpus>,
    obj_index: HashMap<u32, usize>,
    scenes: BTreeMap<u32, SceneData>,
    instances: Vec<BopInstance>,
    targets: Vec<BopTarget>,
}

/// The largest BOP JSON file read (`scene_gt.json` of a 1000-image scene with 20 objects each
/// is ≈ 4 MB; 256 MiB bounds a hostile or mistaken path).
const MAX_BOP_JSON_BYTES: u64 = 256 << 20;

fn read_json(path: &Path) -> Result<Value, DataError> {
    let bytes =
        ic_geometry::io::read_bounded(path, MAX_BOP_JSON_BYTES).map_err(DataError::io(path))?;
    serde_json::from_slice(&bytes).map_err(|e| DataError::json(path, e))
}

fn numbers<const K: usize>(
    v: Option<&Value>,
    path: &Path,
    what: &str,
) -> Result<[f64; K], DataError> {
    let arr = v
        .and_then(|v| v.as_array())
        .ok_or_else(|| DataError::json(path, format!("{what}: missing or not a list")))?;
    if arr.len() != K {
        return Err(DataError::json(
            path,
            format!("{what}: expected {K} numbers, found {}", arr.len()),
        ));
    }
    let mut out = [0.0; K];
    for (o, x) in out.iter_mut().zip(arr) {
        *o = x
            .as_f64()
            .ok_or_else(|| DataError::json(path, format!("{what}: {x} is not a number")))?;
    }
    Ok(out)
}

fn im_key(k: &str, path: &Path) -> Result<u32, DataError> {
    k.parse()
        .map_err(|_| DataError::json(path, format!("key {k:?} is not an image id")))
}

/// Reads a `test_targets_bop19.json`: a list of `{scene_id, im_id, obj_id, inst_count}`; entries
/// of scenes that are not in the split folder are skipped (the file covers a whole dataset).
/// A kept entry whose object has no model, or whose image has no camera in its scene's
/// `scene_camera.json`, is an error naming the file and the entry.
fn read_targets(
    path: &Path,
    scenes: &BTreeMap<u32, SceneData>,
    obj_index: &HashMap<u32, usize>,
    models: &Path,
) -> Result<Vec<BopTarget>, DataError> {
    let v = read_json(path)?;
    let list = v
        .as_array()
        .ok_or_else(|| DataError::json(path, "expected a list of targets"))?;
    let mut out = Vec::new();
    for (k, e) in list.iter().enumerate() {
        let field = |name: &str| -> Result<u64, DataError> {
            e.get(name).and_then(Value::as_u64).ok_or_else(|| {
                DataError::json(path, format!("[{k}].{name}: missing or not a whole number"))
            })
        };
        let to_u32 = |name: &str| -> Result<u32, DataError> {
            u32::try_from(field(name)?)
                .map_err(|_| DataError::json(path, format!("[{k}].{name}: too large")))
        };
        let t = BopTarget {
            scene_id: to_u32("scene_id")?,
            im_id: to_u32("im_id")?,
            obj_id: to_u32("obj_id")?,
            inst_count: field("inst_count")?.min(1 << 16) as usize,
        };
        if t.inst_count == 0 {
            return Err(DataError::json(
                path,
                format!("[{k}].inst_count: must be ≥ 1"),
            ));
        }
        let Some(scene) = scenes.get(&t.scene_id) else {
            continue;
        };
        if !obj_index.contains_key(&t.obj_id) {
            return Err(DataError::json(
                path,
                format!(
                    "[{k}].obj_id {}: no such model in {} (obj_{:06}.ply)",
                    t.obj_id,
                    models.display(),
                    t.obj_id
                ),
            ));
        }
        if !scene.camera.contains_key(&t.im_id) {
            return Err(DataError::json(
                path,
                format!(
                    "[{k}]: image {} has no camera in {}",
                    t.im_id,
                    scene.dir.join("scene_camera.json").display()
                ),
            ));
        }
        out.push(t);
    }
    out.sort_by_key(|t| (t.scene_id, t.im_id, t.obj_id));
    out.dedup_by_key(|t| (t.scene_id, t.im_id, t.obj_id));
    Ok(out)
}

/// The folders a BOP dataset's models are read from, in order of preference: `models/` (every
/// BOP dataset but T-LESS), then `models_cad/` (T-LESS, whose download holds `models_cad/`,
/// `models_reconst/` and `models_eval/`: the CAD models are the objects as made, what BOP
/// renders T-LESS's training images from).
pub const MODELS_FOLDERS: [&str; 2] = ["models", "models_cad"];

/// The models folder of the BOP dataset at `root` (the first of [`MODELS_FOLDERS`] that is a
/// folder), or `None`.
pub fn models_folder(root: &Path) -> Option<PathBuf> {
    MODELS_FOLDERS
        .iter()
        .map(|name| root.join(name))
        .find(|p| p.is_dir())
}

impl BopDataset {
    /// Opens `<root>/<split>` with the models of `<root>/models` (T-LESS: `models_cad`; see
    /// [`models_folder`]).
    pub fn open(
        root: impl AsRef<Path>,
        split: &str,
        options: CorpusOptions,
    ) -> Result<Self, DataError> {
        let root = root.as_ref().to_path_buf();
        let models = models_folder(&root).ok_or_else(|| DataError::Layout {
            folder: root.clone(),
            message: format!("no models folder (one of {})", MODELS_FOLDERS.join(", ")),
        })?;
        let corpus = Arc::new(Corpus::bop_models(&models, Split::Test, options)?);
        let obj_index = corpus
            .entries()
            .iter()
            .enumerate()
            .filter_map(|(i, e)| e.bop_obj_id.map(|id| (id, i)))
            .collect();
        let split_dir = root.join(split);
        if !split_dir.is_dir() {
            return Err(DataError::Layout {
                folder: root.clone(),
                message: format!("no split folder {split:?}"),
            });
        }
        let mut scenes = BTreeMap::new();
        let mut instances = Vec::new();
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(&split_dir)
            .map_err(DataError::io(&split_dir))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_dir())
            .collect();
        dirs.sort();
        for dir in dirs {
            let Some(scene_id) = dir
                .file_name()
                .and_then(|n| n.to_str())
                .and_then(|n| n.parse::<u32>().ok())
            else {
                continue;
            };
            let cam_path = dir.join("scene_camera.json");
            let gt_path = dir.join("scene_gt.json");
            let cam_json = read_json(&cam_path)?;
            // A withheld ground truth: the scene's targets are registered, not scored.
            let gt_json = if gt_path.exists() {
                read_json(&gt_path)?
            } else {
                Value::Object(Default::default())
            };
            let mut camera = HashMap::new();
            for (k, v) in cam_json
                .as_object()
                .ok_or_else(|| DataError::json(&cam_path, "expected an object keyed by image id"))?
            {
                let im = im_key(k, &cam_path)?;
                let kk = numbers::<9>(v.get("cam_K"), &cam_path, &format!("{k}.cam_K"))?;
                let scale = v.get("depth_scale").and_then(Value::as_f64).unwrap_or(1.0);
                camera.insert(im, (kk, scale));
            }
            let mut gt = HashMap::new();
            let gt_obj = gt_json
                .as_object()
                .ok_or_else(|| DataError::json(&gt_path, "expected an object keyed by image id"))?;
            let mut ims: Vec<(u32, &Value)> = gt_obj
                .iter()
                .map(|(k, v)| Ok((im_key(k, &gt_path)?, v)))
                .collect::<Result<_, DataError>>()?;
            ims.sort_by_key(|(im, _)| *im);
            for (im, v) in ims {
                let list = v
                    .as_array()
                    .ok_or_else(|| DataError::json(&gt_path, format!("{im}: expected a list")))?;
                let mut entries = Vec::new();
                for (g, e) in list.iter().enumerate() {
                    let r = numbers::<9>(
                        e.get("cam_R_m2c"),
                        &gt_path,
                        &format!("{im}[{g}].cam_R_m2c"),
                    )?;
                    let t = numbers::<3>(
                        e.get("cam_t_m2c"),
                        &gt_path,
                        &format!("{im}[{g}].cam_t_m2c"),
                    )?;
                    let obj_id = e.get("obj_id").and_then(Value::as_u64).ok_or_else(|| {
                        DataError::json(&gt_path, format!("{im}[{g}].obj_id missing"))
                    })? as u32;
                    instances.push(BopInstance {
                        scene_id,
                        im_id: im,
                        gt_index: g,
                        obj_id,
                    });
                    entries.push(GtEntry {
                        rotation: [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
                        translation_mm: t,
                    });
                }
                gt.insert(im, entries);
            }
            scenes.insert(scene_id, SceneData { dir, camera, gt });
        }
        let targets_path = root.join(TEST_TARGETS_FILE);
        if scenes.is_empty() || (instances.is_empty() && !targets_path.is_file()) {
            return Err(DataError::EmptySplit {
                folder: split_dir,
                split: split.to_string(),
                detail: if scenes.is_empty() {
                    "no scene folder".into()
                } else {
                    format!(
                        "no annotated instance in any scene (no scene_gt.json lists one) and no \
                         {TEST_TARGETS_FILE} at the dataset's root to say what to find"
                    )
                },
            });
        }
        let targets = if targets_path.is_file() {
            read_targets(&targets_path, &scenes, &obj_index, &models)?
        } else {
            // Every annotated object of every image, with its instance count.
            let mut counts: BTreeMap<(u32, u32, u32), usize> = BTreeMap::new();
            for i in &instances {
                *counts.entry((i.scene_id, i.im_id, i.obj_id)).or_default() += 1;
            }
            counts
                .into_iter()
                .map(|((scene_id, im_id, obj_id), inst_count)| BopTarget {
                    scene_id,
                    im_id,
                    obj_id,
                    inst_count,
                })
                .collect()
        };
        Ok(BopDataset {
            root,
            split: split.to_string(),
            corpus,
            obj_index,
            scenes,
            instances,
            targets,
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn split(&self) -> &str {
        &self.split
    }

    /// The models, as a corpus (ids `obj_XXXXXX`).
    pub fn corpus(&self) -> &Arc<Corpus> {
        &self.corpus
    }

    /// Every annotated instance, by scene, image, then annotation order.
    pub fn instances(&self) -> &[BopInstance] {
        &self.instances
    }

    /// What to find: the entries of `<root>/test_targets_bop19.json` whose scene is in the
    /// split folder, or (without that file) every annotated object of every image with its
    /// number of instances; by scene, image, object.
    pub fn targets(&self) -> &[BopTarget] {
        &self.targets
    }

    /// The indices in [`BopDataset::instances`] of the annotated instances of `target`'s
    /// object in its image (empty when none is annotated).
    pub fn instances_of(&self, target: &BopTarget) -> Vec<usize> {
        self.instances
            .iter()
            .enumerate()
            .filter(|(_, i)| {
                (i.scene_id, i.im_id, i.obj_id) == (target.scene_id, target.im_id, target.obj_id)
            })
            .map(|(k, _)| k)
            .collect()
    }

    pub fn len(&self) -> usize {
        self.instances.len()
    }

    pub fn is_empty(&self) -> bool {
        self.instances.is_empty()
    }

    /// Image `im_id` of scene `scene_id` in the normalised units of model `obj_id` (1 unit =
    /// the model's `Normalisation::scale` mm): its depth map and camera, what registering a
    /// target needs when the image has no ground truth (e.g. a test set whose annotations are
    /// withheld). Errors name the file: no such scene or model, no camera for the image, an
    /// unreadable depth map.
    pub fn image(&self, scene_id: u32, im_id: u32, obj_id: u32) -> Result<BopImage, DataError> {
        let scene = self
            .scenes
            .get(&scene_id)
            .ok_or_else(|| DataError::Layout {
                folder: self.root.join(&self.split),
                message: format!("no scene {scene_id:06}"),
            })?;
        let &index = self
            .obj_index
            .get(&obj_id)
            .ok_or_else(|| DataError::Layout {
                folder: self.root.join("models"),
                message: format!("obj_id {obj_id} of scene {scene_id} image {im_id} has no model"),
            })?;
        let object = self.corpus.object(index)?;
        let cam_path = scene.dir.join("scene_camera.json");
        let (kk, depth_scale) = *scene
            .camera
            .get(&im_id)
            .ok_or_else(|| DataError::json(&cam_path, format!("no camera for image {im_id}")))?;
        let depth_m = read_bop_depth(&scene.dir, im_id, depth_scale)?;
        let (w, h) = (depth_m.width, depth_m.height);
        let intrinsics = Intrinsics::new(kk[0], kk[4], kk[2], kk[5], w, h)?;
        let to_units = 1000.0 / object.normalisation.scale;
        let depth = Image {
            width: w,
            height: h,
            data: depth_m
                .data
                .iter()
                .map(|&z| (z as f64 * to_units) as f32)
                .collect(),
        };
        Ok(BopImage {
            depth,
            intrinsics,
            object,
        })
    }

    /// Instance `i` as a [`RoomSample`] in the normalised units of its model (1 unit =
    /// the model's `Normalisation::scale` mm): depth, masks (`mask_visib`/, `mask`/; the
    /// visible mask stands in for a missing full one, an empty mask for a missing visible one),
    /// pose, boxes, the voxelised scene with object labels, and M model points.
    pub fn load(&self, i: usize, options: &BopLoadOptions) -> Result<RoomSample, DataError> {
        let inst = *self.instances.get(i).ok_or_else(|| DataError::Config {
            field: "instance index",
            message: format!("{i} is out of range ({} instances)", self.instances.len()),
        })?;
        let BopImage {
            depth,
            intrinsics: k,
            object,
        } = self.image(inst.scene_id, inst.im_id, inst.obj_id)?;
        let scene = &self.scenes[&inst.scene_id];
        let norm = object.normalisation;
        let (w, h) = (depth.width, depth.height);
        let mask_file = |dir: &str| {
            scene
                .dir
                .join(format!("{dir}/{:06}_{:06}.png", inst.im_id, inst.gt_index))
        };
        let read_mask = |p: PathBuf| -> Result<Option<Mask>, DataError> {
            if p.is_file() {
                Ok(Some(ic_render::io::read_mask_png(&p, Some((w, h)))?))
            } else {
                Ok(None)
            }
        };
        let mask_visib =
            read_mask(mask_file("mask_visib"))?.unwrap_or_else(|| Image::filled(w, h, false));
        let mask_all = read_mask(mask_file("mask"))?.unwrap_or_else(|| mask_visib.clone());
        let gt = &scene.gt[&inst.im_id][inst.gt_index];
        let t = gt.translation_mm;
        let pose_mm = Pose::from_row_major(gt.rotation, t)
            .map_err(|e| {
                DataError::json(
                    scene.dir.join("scene_gt.json"),
                    format!("image {} instance {}: {e}", inst.im_id, inst.gt_index),
                )
            })?
            .orthonormalised();
        let pose = norm.pose_to_normalised(&pose_mm);
        let (scene_points, object_labels) =
            voxelise_scene(&k, &depth, &mask_visib, options.voxel_size)?;
        let object_count = object_labels.iter().filter(|&&l| l).count();
        let mut rng = sample_rng(options.seed, i as u64);
        let xi =
            random_subsample_indices(object.model_points.len(), options.model_points, &mut rng)?;
        Ok(RoomSample {
            index: i as u64,
            object_id: object.id.clone(),
            intrinsics: k,
            bbox_visib: mask_bbox(&mask_visib),
            bbox_obj: mask_bbox(&mask_all),
            inlier_rate: if scene_points.is_empty() {
                0.0
            } else {
                object_count as f64 / scene_points.len() as f64
            },
            depth,
            mask_visib,
            mask_all,
            pose,
            scene_points,
            object_labels,
            model_points: xi.iter().map(|&j| object.model_points[j]).collect(),
            normalisation: norm,
            viewpoint: None,
        })
    }
}
