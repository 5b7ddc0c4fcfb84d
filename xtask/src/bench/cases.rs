//! Stage 1 of `cargo xtask bench`: the fixed case sets, exported once and reused.
//!
//! The cases are the ones `cargo xtask export-cases` writes for the same set, objects, seed and
//! count (the same `ic_data` generators and writers), plus `mask_visib.png` in each room case
//! (the ground-truth visible mask, 8-bit, 255 = object) for the upper-bound runs. A folder is
//! reused when its `bench-manifest.json` equals the one this run would write and every case is
//! there; otherwise it is written again into `<folder>.partial` and renamed into place.
//!
//! Three sets: `noback` and `room` (the paper's protocol on the blob test objects) and `real`
//! (the real-objects issue's protocol: `export-cases --set view` on the `real_objects` test
//! split — whole-sphere views, camera roll, the sensor model, occluders, truncation).
//!
//! [`geometry`] gives each case what the object metrics (ADD-S, MSSD, MSPD) need: its model
//! points, its camera and its object's symmetries (found on the corpus mesh, cached per set).

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use ic_data::export::{CaseFolder, write_object_case, write_room_case, write_view_case};
use ic_data::{
    Corpus, CorpusOptions, FolderSplit, ObjectSampleConfig, ObjectSampleGenerator, Prefetcher,
    RoomSampleConfig, RoomSampleGenerator, SamplingProtocol, Split,
};
use ic_eval::object_scores::CaseGeometry;
use ic_geometry::Pose;
use ic_geometry::symmetry::{SymmetryOptions, find_symmetries};
use serde_json::{Value, json};

/// Bump when the folder layout changes, so old folders are rewritten.
const FORMAT: u32 = 1;

/// Which case set.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Set {
    Noback,
    Room,
    Real,
}

impl Set {
    pub const ALL: [Set; 3] = [Set::Noback, Set::Room, Set::Real];

    pub fn name(self) -> &'static str {
        match self {
            Set::Noback => "noback",
            Set::Room => "room",
            Set::Real => "real",
        }
    }

    pub fn title(self) -> &'static str {
        match self {
            Set::Noback => "Object alone",
            Set::Room => "Object in the room",
            Set::Real => "Real objects, whole-sphere views",
        }
    }

    /// The sampling of its cases.
    fn sample_config(self) -> Value {
        match self {
            Set::Noback => serde_json::to_value(ObjectSampleConfig::default()),
            Set::Room => serde_json::to_value(RoomSampleConfig::default()),
            Set::Real => serde_json::to_value(view_config()),
        }
        .unwrap_or(Value::Null)
    }
}

/// The views of the real set: `export-cases --set view`'s (deployment protocol, the corpus
/// mesh itself, images kept).
fn view_config() -> ObjectSampleConfig {
    ObjectSampleConfig {
        copy_rotations: 0,
        scale_augmentation: None,
        keep_images: true,
        ..SamplingProtocol::Deployment.config()
    }
}

/// Where the objects come from.
#[derive(Clone, Debug)]
pub enum Objects {
    /// A flat folder of meshes split by id: 0–799 train, 800–999 test (the blob folder).
    Folder(PathBuf),
    /// `count` procedural objects (when no folder is available: the quick bench on CI).
    Procedural(usize),
    /// A flat folder of meshes with a JSON split file (`real_objects/` and its `split.json`).
    SplitFile { dir: PathBuf, split_file: PathBuf },
}

impl Objects {
    pub fn describe(&self) -> Value {
        match self {
            Objects::Folder(p) => {
                json!({"kind": "mesh_folder", "folder": p, "split_rule": "ids 0-799 train, 800-999 test"})
            }
            Objects::Procedural(n) => json!({"kind": "procedural", "count": n}),
            Objects::SplitFile { dir, split_file } => {
                json!({"kind": "mesh_folder", "folder": dir, "split_file": split_file})
            }
        }
    }

    /// A short name for files cached per corpus: the folder's name, or `procedural-N`.
    pub fn cache_name(&self) -> String {
        match self {
            Objects::Folder(dir) | Objects::SplitFile { dir, .. } => dir
                .file_name()
                .map_or_else(|| "objects".into(), |n| n.to_string_lossy().into_owned()),
            Objects::Procedural(n) => format!("procedural-{n}"),
        }
    }

    pub fn corpus(&self, split: Split, seed: u64) -> Result<Corpus> {
        Ok(match self {
            Objects::Folder(dir) => {
                Corpus::mesh_folder(dir, &FolderSplit::blobs(), split, CorpusOptions::default())
                    .with_context(|| format!("opening the objects in {}", dir.display()))?
            }
            Objects::Procedural(n) => {
                Corpus::procedural(*n, split, seed, CorpusOptions::default())?
            }
            Objects::SplitFile { dir, split_file } => Corpus::mesh_folder(
                dir,
                &FolderSplit::File(split_file.clone()),
                split,
                CorpusOptions::default(),
            )
            .with_context(|| {
                format!(
                    "opening the objects in {} (split {})",
                    dir.display(),
                    split_file.display()
                )
            })?,
        })
    }
}

/// A case set on disk.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CaseSet {
    pub set: Set,
    pub dir: PathBuf,
    pub count: u64,
    /// Whether this run wrote it (false: reused).
    pub written: bool,
    /// Per-case facts from the manifest (object id, inlier rate, scene points).
    pub cases: Vec<Value>,
}

fn manifest_for(set: Set, objects: &Objects, seed: u64, count: u64) -> Value {
    let sample = set.sample_config();
    json!({
        "format": FORMAT,
        "set": set.name(),
        "seed": seed,
        "count": count,
        "split": "test",
        "objects": objects.describe(),
        "sample": sample,
        "extra_files": if set == Set::Room { json!([CaseFolder::MASK_VISIB]) } else { json!([]) },
    })
}

fn case_name(i: u64) -> String {
    CaseFolder::name_of(i)
}

fn complete(dir: &Path, set: Set, count: u64) -> bool {
    let cases = CaseFolder::new(dir);
    (0..count).all(|i| {
        let case = cases.child(i);
        [case.gt(), case.source(), case.target(), case.meta()]
            .iter()
            .all(|f| f.is_file())
            && match set {
                Set::Noback => true,
                Set::Room => case.dir().join(CaseFolder::MASK_VISIB).is_file(),
                Set::Real => [case.mask(), case.depth(), case.camera(), case.model()]
                    .iter()
                    .all(|f| f.is_file()),
            }
    })
}

/// The JSON in `path`, when it is there and parses.
pub fn read_json(path: &Path) -> Option<Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

/// Makes sure `dir` holds the `count` cases of `set` (see the module documentation).
pub fn ensure(
    set: Set,
    objects: &Objects,
    seed: u64,
    count: u64,
    dir: &Path,
    workers: usize,
) -> Result<CaseSet> {
    let want = manifest_for(set, objects, seed, count);
    let have = read_json(&dir.join("bench-manifest.json"));
    if have.as_ref() == Some(&want) && complete(dir, set, count) {
        let cases = read_json(&dir.join("manifest.json"))
            .and_then(|m| m["cases"].as_array().cloned())
            .unwrap_or_default();
        tracing::info!(set = set.name(), dir = %dir.display(), count, "reusing the exported cases");
        return Ok(CaseSet {
            set,
            dir: dir.to_path_buf(),
            count,
            written: false,
            cases,
        });
    }
    if dir.exists() && have.is_none() && std::fs::read_dir(dir)?.next().is_some() {
        bail!(
            "{} exists but was not written by the bench (no bench-manifest.json); move it away \
             or pass another --work folder",
            dir.display()
        );
    }
    let partial = clear_partial(dir)?;
    std::fs::create_dir_all(&partial).with_context(|| format!("creating {}", partial.display()))?;
    tracing::info!(set = set.name(), count, seed, dir = %dir.display(), "exporting cases");
    let corpus = Arc::new(objects.corpus(Split::Test, seed)?);
    let bar = crate::bench::common::progress_bar(count, &format!("cases {}", set.name()));
    let mut cases = Vec::new();
    match set {
        Set::Noback => {
            let g = Arc::new(ObjectSampleGenerator::new(
                corpus.clone(),
                ObjectSampleConfig::default(),
                seed,
            )?);
            for s in Prefetcher::new(0, Some(count), workers, 4, move |i| g.sample(i)) {
                let s = s?;
                let name = case_name(s.index);
                write_object_case(partial.join(&name), &s, seed)?;
                cases.push(json!({"case": name, "object_id": s.object_id, "inliers": s.inlier_count(), "inlier_rate": s.assignment.observed_inlier_rate()}));
                bar.inc(1);
            }
        }
        Set::Room => {
            let g = Arc::new(RoomSampleGenerator::new(
                corpus.clone(),
                RoomSampleConfig::default(),
                seed,
            )?);
            for s in Prefetcher::new(0, Some(count), workers, 2, move |i| g.sample(i)) {
                let s = s?;
                let name = case_name(s.index);
                let case_dir = partial.join(&name);
                write_room_case(&case_dir, &s, seed)?;
                ic_render::io::write_mask_png(
                    case_dir.join(CaseFolder::MASK_VISIB),
                    &s.mask_visib,
                )?;
                cases.push(json!({"case": name, "object_id": s.object_id, "inlier_rate": s.inlier_rate, "scene_points": s.scene_points.len(), "object_points": s.object_point_count()}));
                bar.inc(1);
            }
        }
        Set::Real => {
            let g = Arc::new(ObjectSampleGenerator::new(
                corpus.clone(),
                view_config(),
                seed,
            )?);
            for s in Prefetcher::new(0, Some(count), workers, 2, move |i| g.sample(i)) {
                let s = s?;
                let name = case_name(s.index);
                let object =
                    corpus.object(corpus.position(&s.object_id).with_context(|| {
                        format!("object {} is not in the corpus", s.object_id)
                    })?)?;
                write_view_case(partial.join(&name), &s, &object.mesh, seed)?;
                cases.push(json!({"case": name, "object_id": s.object_id, "inliers": s.inlier_count(), "inlier_rate": s.assignment.observed_inlier_rate(), "observed_voxels": s.observed_voxels}));
                bar.inc(1);
            }
        }
    }
    bar.finish_and_clear();
    // The same manifest.json as `cargo xtask export-cases`, and the bench's own.
    let config = json!({"set": set.name(), "seed": seed, "corpus": objects.describe(), "split": "test", "count": count, "sample": want["sample"]});
    crate::bench::common::write_atomic(
        &partial.join("manifest.json"),
        serde_json::to_string_pretty(
            &json!({"config": config, "corpus": corpus.info(), "cases": cases}),
        )?
        .as_bytes(),
    )?;
    install_partial(&partial, dir, &want)?;
    if corpus.skipped() > 0 {
        tracing::warn!(
            skipped = corpus.skipped(),
            "unreadable meshes were skipped while exporting"
        );
    }
    Ok(CaseSet {
        set,
        dir: dir.to_path_buf(),
        count,
        written: true,
        cases,
    })
}

/// An object id and its symmetry motions (model frame).
type ObjectMotions = (String, Vec<Pose>);

/// What the object metrics need for every case of `cs`, by case name: the case's model points
/// and camera ([`CaseGeometry::read`]) and its object's symmetry motions, found on the corpus
/// mesh (`find_symmetries`, default options) and cached in `cache` (JSON: options and the
/// symmetries by object id; reused when the options match).
pub fn geometry(
    cs: &CaseSet,
    objects: &Objects,
    seed: u64,
    cache: &Path,
) -> Result<HashMap<String, Arc<CaseGeometry>>> {
    let options = SymmetryOptions::default();
    let mut known: BTreeMap<String, Vec<Pose>> = read_json(cache)
        .filter(|v| v["options"] == json!(options) && v["objects"] == objects.describe())
        .and_then(|v| serde_json::from_value(v["symmetries"].clone()).ok())
        .unwrap_or_default();
    let folders = CaseFolder::list(&cs.dir)?;
    let ids: Vec<Option<String>> = folders
        .iter()
        .map(|c| c.read_object_id())
        .collect::<Result<_, _>>()?;
    let missing: Vec<&String> = {
        let mut v: Vec<&String> = ids
            .iter()
            .flatten()
            .filter(|id| !known.contains_key(*id))
            .collect();
        v.sort();
        v.dedup();
        v
    };
    if !missing.is_empty() {
        let corpus = objects.corpus(Split::Test, seed)?;
        let bar = crate::bench::common::progress_bar(
            missing.len() as u64,
            &format!("symmetries {}", cs.set.name()),
        );
        tracing::info!(
            set = cs.set.name(),
            objects = missing.len(),
            "finding symmetries"
        );
        // Seconds per object: spread over the machine's cores (nothing here is timed).
        let next = std::sync::atomic::AtomicUsize::new(0);
        let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
        let found: Vec<Result<Vec<ObjectMotions>>> = std::thread::scope(|scope| {
            let handles: Vec<_> = (0..workers.min(missing.len()))
                .map(|_| {
                    scope.spawn(|| -> Result<Vec<ObjectMotions>> {
                        let mut out = Vec::new();
                        loop {
                            let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            let Some(id) = missing.get(i) else {
                                return Ok(out);
                            };
                            let object =
                                corpus.object(corpus.position(id).with_context(|| {
                                    format!("object {id} is not in the corpus")
                                })?)?;
                            let s = find_symmetries(&object.mesh, &options)
                                .with_context(|| format!("the symmetries of object {id}"))?;
                            out.push(((*id).clone(), s.motions));
                            bar.inc(1);
                        }
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .unwrap_or_else(|_| bail!("a symmetry worker panicked"))
                })
                .collect()
        });
        for part in found {
            known.extend(part?);
        }
        bar.finish_and_clear();
        let doc = json!({
            "options": options, "objects": objects.describe(), "symmetries": known,
        });
        let text = serde_json::to_string(&doc)?;
        crate::bench::common::write_atomic(cache, text.as_bytes())?;
        // What a later run reads from the cache, bit for bit (serde_json's text round trip of
        // a float is not exact).
        known = serde_json::from_value(serde_json::from_str::<Value>(&text)?["symmetries"].take())?;
    }
    let mut out = HashMap::new();
    for (case, id) in folders.iter().zip(&ids) {
        let motions = id
            .as_ref()
            .and_then(|id| known.get(id))
            .cloned()
            .unwrap_or_default();
        let g = CaseGeometry::read(case, motions)
            .with_context(|| format!("the model of {}", case.dir().display()))?;
        out.insert(case.name(), Arc::new(g));
    }
    Ok(out)
}

/// `<dir>.partial`, the folder a bench output is written into before it replaces `dir`,
/// removed if an interrupted run left it.
pub fn clear_partial(dir: &Path) -> Result<PathBuf> {
    let partial = sibling(dir, "partial");
    if partial.exists() {
        std::fs::remove_dir_all(&partial)
            .with_context(|| format!("removing {}", partial.display()))?;
    }
    Ok(partial)
}

/// Writes `manifest` as `partial`'s `bench-manifest.json` (what a later run compares to reuse
/// the folder), then puts `partial` in the place of `dir`.
pub fn install_partial(partial: &Path, dir: &Path, manifest: &Value) -> Result<()> {
    crate::bench::common::write_atomic(
        &partial.join("bench-manifest.json"),
        serde_json::to_string_pretty(manifest)?.as_bytes(),
    )?;
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    std::fs::rename(partial, dir)
        .with_context(|| format!("renaming {} to {}", partial.display(), dir.display()))
}

/// `dir` with `.suffix` added to its last component.
pub fn sibling(dir: &Path, suffix: &str) -> PathBuf {
    let mut name = dir.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".{suffix}"));
    dir.with_file_name(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two procedural object-alone cases: written once, reused with the same manifest,
    /// rewritten when the count changes; the room set writes the ground-truth mask.
    #[test]
    fn exports_reuses_and_rewrites_case_sets() {
        let tmp = crate::bench::common::tests::TempDir::new("cases");
        let dir = tmp.path().join("cases-noback");
        let objects = Objects::Procedural(3);
        let a = ensure(Set::Noback, &objects, 5, 2, &dir, 1).unwrap();
        assert!(a.written && complete(&dir, Set::Noback, 2));
        let gt = std::fs::read(dir.join("case_00001/gt.json")).unwrap();
        let b = ensure(Set::Noback, &objects, 5, 2, &dir, 1).unwrap();
        assert!(!b.written && b.cases.len() == 2);
        let c = ensure(Set::Noback, &objects, 5, 3, &dir, 2).unwrap();
        assert!(c.written && complete(&dir, Set::Noback, 3));
        // Same seed, same case, whatever the worker count.
        assert_eq!(std::fs::read(dir.join("case_00001/gt.json")).unwrap(), gt);
        assert!(!sibling(&dir, "partial").exists());
        // A foreign folder is not overwritten.
        let foreign = tmp.path().join("mine");
        std::fs::create_dir_all(foreign.join("x")).unwrap();
        assert!(ensure(Set::Noback, &objects, 5, 1, &foreign, 1).is_err());
    }

    /// Two real-set views of a folder of two meshes with a split file: written with the
    /// depth, mask, camera and model a view case needs, reused with the same manifest; their
    /// geometry finds the box's symmetries on its mesh (cached and read back) and none of the
    /// random object's.
    #[test]
    fn real_views_are_exported_with_their_geometry_and_cached_symmetries() {
        use ic_geometry::glam::Vec3;
        use ic_geometry::io::{PlyEncoding, write_mesh_ply};
        let tmp = crate::bench::common::tests::TempDir::new("cases-real");
        let meshes = tmp.path().join("meshes");
        std::fs::create_dir_all(&meshes).unwrap();
        let cuboid = ic_geometry::shapes::box_mesh(Vec3::new(0.05, 0.03, 0.02)).unwrap();
        write_mesh_ply(
            meshes.join("00001.ply"),
            &cuboid,
            PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
        write_mesh_ply(
            meshes.join("00002.ply"),
            &ic_geometry::shapes::random_object(7),
            PlyEncoding::BinaryLittleEndian,
        )
        .unwrap();
        let split_file = meshes.join("split.json");
        std::fs::write(
            &split_file,
            r#"{"train": [], "val": [], "test": ["00001", "00002"]}"#,
        )
        .unwrap();
        let objects = Objects::SplitFile {
            dir: meshes.clone(),
            split_file,
        };
        let dir = tmp.path().join("cases-real");
        let a = ensure(Set::Real, &objects, 3, 2, &dir, 1).unwrap();
        assert!(a.written && complete(&dir, Set::Real, 2), "{a:?}");
        assert!(!ensure(Set::Real, &objects, 3, 2, &dir, 1).unwrap().written);
        let cache = tmp.path().join("symmetries-real.json");
        let g = geometry(&a, &objects, 3, &cache).unwrap();
        assert_eq!(g.len(), 2);
        let cached = read_json(&cache).unwrap();
        let motions = |id: &str| cached["symmetries"][id].as_array().map_or(0, Vec::len);
        // A box with three different sides: three half turns.
        assert_eq!(motions("00001"), 3, "{cached}");
        assert_eq!(motions("00002"), 0, "{cached}");
        for (name, geo) in &g {
            let case = CaseFolder::new(dir.join(name));
            let id = case.read_object_id().unwrap().unwrap();
            assert_eq!(geo.symmetries.len(), motions(&id), "{name}");
            assert!(geo.intrinsics.is_some() && geo.diameter > 0.0);
        }
        // A second call reads the cache (the same result without the corpus).
        let again = geometry(&a, &objects, 3, &cache).unwrap();
        assert_eq!(again["case_00000"], g["case_00000"]);
    }
}
