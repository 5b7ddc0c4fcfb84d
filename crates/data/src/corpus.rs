//! Object corpora and their splits: a ModelNet40 folder, a flat folder of meshes, a BOP
//! `models/` folder, the procedural stream of `ic_geometry::shapes::random_object`, or a
//! weighted mixture of these ([`Corpus::mixture`]).
//!
//! A [`Corpus`] only lists objects when it is built; each mesh is loaded, normalised into
//! [-1, 1] (the [`Normalisation`] is kept) and its visible-surface model points are sampled the
//! first time the object is used, then cached for the life of the corpus (thread-safe; each
//! object is loaded once even when several threads ask for it at the same time).
//!
//! Everything about an object is a function of the object alone (its file, or its procedural
//! seed), never of the order or thread in which objects are loaded, so samples are identical
//! whatever the thread count.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};

use glam::Vec3;
use ic_geometry::sampling::{VisibleSurfaceOptions, sample_visible_surface};
use ic_geometry::{Mesh, Normalisation};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::DataError;
use crate::seed::mix;

/// Training, validation or test objects (disjoint sets of objects: the paper uses disjoint
/// training and test objects; validation objects select checkpoints and are never trained on).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Train,
    Test,
    Val,
}

impl Split {
    pub fn as_str(&self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
            Split::Val => "val",
        }
    }
}

impl fmt::Display for Split {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Split {
    type Err = DataError;
    fn from_str(s: &str) -> Result<Self, DataError> {
        match s {
            "train" => Ok(Split::Train),
            "test" => Ok(Split::Test),
            "val" | "validation" => Ok(Split::Val),
            _ => Err(DataError::Config {
                field: "split",
                message: format!("expected train, val or test, got {s:?}"),
            }),
        }
    }
}

/// How a flat folder of meshes is split into train, validation and test objects.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FolderSplit {
    /// Ids are the numeric file stems (`000.obj` → 0); inclusive ranges per split. The blob
    /// folder of the project uses train 0–799, test 800–999 ([`FolderSplit::blobs`]). There
    /// is no validation range: [`Split::Val`] is an error (use [`FolderSplit::IdRanges`]).
    IdRange { train: (u64, u64), test: (u64, u64) },
    /// Inclusive id ranges for all three splits ([`FolderSplit::blobs_with_val`]).
    IdRanges {
        train: (u64, u64),
        val: (u64, u64),
        test: (u64, u64),
    },
    /// A JSON file `{"train": ["000", …], "val": [...], "test": ["800", …]}` listing file
    /// stems (strings or numbers). `val` is needed only to load the validation split. The
    /// lists present must be disjoint (checked whenever a split is loaded).
    File(PathBuf),
    /// Every mesh of the folder, whatever the split: a user's handful of objects, where the
    /// training and validation views differ but the objects do not (`incontext train`).
    All,
}

impl FolderSplit {
    /// The split of the 1000-blob folder: 000–799 train, 800–999 test.
    pub fn blobs() -> Self {
        FolderSplit::IdRange {
            train: (0, 799),
            test: (800, 999),
        }
    }

    /// The blob folder with validation objects carved out of the train range, as every pose
    /// and segmentation model of the project was trained: 000–749 train, 750–799 val,
    /// 800–999 test (the test split of [`FolderSplit::blobs`], unchanged).
    pub fn blobs_with_val() -> Self {
        FolderSplit::IdRanges {
            train: (0, 749),
            val: (750, 799),
            test: (800, 999),
        }
    }
}

/// The stems listed for `split` in a split file, after checking that the lists present are
/// disjoint.
fn split_file_ids(
    path: &Path,
    split: Split,
) -> Result<std::collections::HashSet<String>, DataError> {
    // A split file lists at most a few hundred thousand stems; 64 MiB bounds a wrong path.
    let bytes = ic_geometry::io::read_bounded(path, 64 << 20).map_err(DataError::io(path))?;
    let json: serde_json::Value =
        serde_json::from_slice(&bytes).map_err(|e| DataError::json(path, e))?;
    let read = |name: &str| -> Result<Option<Vec<String>>, DataError> {
        let Some(v) = json.get(name) else {
            return Ok(None);
        };
        let list = v.as_array().ok_or_else(|| {
            DataError::json(path, format!("{name:?} is not a list of file stems"))
        })?;
        let mut out = Vec::with_capacity(list.len());
        for (i, v) in list.iter().enumerate() {
            out.push(match v {
                serde_json::Value::String(s) => s.clone(),
                serde_json::Value::Number(n) => n.to_string(),
                _ => {
                    return Err(DataError::json(
                        path,
                        format!("{name}[{i}] is not a string or number"),
                    ));
                }
            });
        }
        Ok(Some(out))
    };
    let mut seen: HashMap<String, &'static str> = HashMap::new();
    let mut wanted = None;
    for other in [Split::Train, Split::Val, Split::Test] {
        let Some(list) = read(other.as_str())? else {
            continue;
        };
        for id in &list {
            // Numeric stems compare as numbers ("007" and 7 are the same object).
            let key = id
                .parse::<u64>()
                .map_or_else(|_| id.clone(), |n| n.to_string());
            if let Some(first) = seen.insert(key, other.as_str())
                && first != other.as_str()
            {
                return Err(DataError::json(
                    path,
                    format!("{id:?} is listed in both {first} and {other}"),
                ));
            }
        }
        if other == split {
            wanted = Some(list);
        }
    }
    let list = wanted.ok_or_else(|| {
        DataError::json(path, format!("no {:?} list of file stems", split.as_str()))
    })?;
    Ok(list.into_iter().collect())
}

/// What to do with a mesh that cannot be loaded or is unusable.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnBadMesh {
    /// Log a warning, count it ([`Corpus::skipped`]) and draw another object.
    #[default]
    Skip,
    /// Fail with the mesh's error.
    Stop,
}

/// How objects are prepared.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CorpusOptions {
    pub on_bad_mesh: OnBadMesh,
    /// Visible-surface model points cached per object (the paper's M = 1024 are drawn from
    /// these for every sample). Default 4096.
    pub model_points: usize,
    /// Settings of the visible-surface sampler.
    pub visible_surface: VisibleSurfaceOptions,
}

impl Default for CorpusOptions {
    fn default() -> Self {
        CorpusOptions {
            on_bad_mesh: OnBadMesh::Skip,
            model_points: 4096,
            visible_surface: VisibleSurfaceOptions::default(),
        }
    }
}

/// Where an object comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum ObjectSource {
    File(PathBuf),
    /// `ic_geometry::shapes::random_object(seed)`.
    Procedural(u64),
}

/// One listed object: its id (file stem, `class/stem` for ModelNet, `obj_000001` for BOP,
/// `proc_<seed>` for procedural objects, `<source>/<id>` in a mixture), its source and, for
/// BOP models, its BOP `obj_id`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectEntry {
    pub id: String,
    pub source: ObjectSource,
    pub bop_obj_id: Option<u32>,
    /// Seed of the object's model-point sampling: a function of the object's id in its own
    /// corpus (kept when the object joins a mixture, so its points do not change).
    pub model_seed: u64,
}

impl ObjectEntry {
    fn new(id: String, source: ObjectSource, bop_obj_id: Option<u32>) -> Self {
        let model_seed = match &source {
            ObjectSource::File(_) => mix(0x006d_6f64_656c, fnv1a(id.as_bytes())),
            ObjectSource::Procedural(s) => mix(*s, 1),
        };
        ObjectEntry {
            id,
            source,
            bop_obj_id,
            model_seed,
        }
    }
}

/// A loaded, normalised object with its cached model points.
#[derive(Clone, Debug)]
pub struct CorpusObject {
    pub id: String,
    /// Index of the entry in its corpus.
    pub index: usize,
    pub bop_obj_id: Option<u32>,
    /// The mesh normalised into [-1, 1] (longest side).
    pub mesh: Arc<Mesh>,
    /// How the original mesh was normalised (`normalised = (original − centre)/scale`).
    pub normalisation: Normalisation,
    /// Visible-surface samples of the normalised mesh (model frame), dense enough to draw M
    /// points from.
    pub model_points: Vec<Vec3>,
    /// The mesh's rotational symmetries, found on first use ([`CorpusObject::symmetries`]).
    symmetries: OnceLock<Arc<Vec<ic_geometry::Pose>>>,
}

/// The settings of the symmetry search of [`CorpusObject::symmetries`]: fewer samples and
/// axes than `ic_geometry::symmetry`'s defaults (≈ 0.3 s per object on one core instead of
/// ≈ 2.5 s; on the 48 `real_objects` test objects the two disagree on 2 borderline ones).
pub const TRAINING_SYMMETRY_OPTIONS: ic_geometry::symmetry::SymmetryOptions =
    ic_geometry::symmetry::SymmetryOptions {
        samples: 600,
        tolerance: 0.01,
        axes: 200,
        seed: 0,
    };

impl CorpusObject {
    /// The motions (normalised model frame, non-identity) that map the mesh onto itself within
    /// 1 % of its diameter ([`TRAINING_SYMMETRY_OPTIONS`]), computed once per object and
    /// cached; empty for an object without symmetry, or (with a warning) when the search fails.
    pub fn symmetries(&self) -> Arc<Vec<ic_geometry::Pose>> {
        self.symmetries
            .get_or_init(|| {
                match ic_geometry::symmetry::find_symmetries(&self.mesh, &TRAINING_SYMMETRY_OPTIONS)
                {
                    Ok(s) => Arc::new(s.motions),
                    Err(e) => {
                        tracing::warn!(id = %self.id, "no symmetry search: {e}");
                        Arc::new(Vec::new())
                    }
                }
            })
            .clone()
    }
}

/// What kind of corpus this is (for manifests).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CorpusKind {
    ModelNet40,
    MeshFolder,
    BopModels,
    Procedural,
    Mixture,
}

/// A serialisable description of a corpus (for manifests).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CorpusInfo {
    pub kind: CorpusKind,
    pub folder: Option<PathBuf>,
    pub split: Split,
    pub objects: usize,
    pub skipped: usize,
    /// The sources of a mixture (empty otherwise).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sources: Vec<SourceInfo>,
}

/// One source of a mixture corpus, for manifests.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SourceInfo {
    pub name: String,
    pub kind: CorpusKind,
    pub folder: Option<PathBuf>,
    /// Probability of drawing from this source (the weights given, normalised to sum 1).
    pub probability: f64,
    pub objects: usize,
}

/// One source of [`Corpus::mixture`]: a corpus, its name (the prefix of its objects' ids) and
/// its weight (any positive number; weights are normalised).
#[derive(Debug)]
pub struct MixturePart {
    pub name: String,
    pub corpus: Corpus,
    pub weight: f64,
}

/// The entries `range` of a mixture corpus that came from one source.
#[derive(Clone, Debug)]
struct Group {
    info: SourceInfo,
    range: std::ops::Range<usize>,
    /// Cumulative probability up to and including this group.
    cumulative: f64,
}

type Slot = Arc<OnceLock<Result<Arc<CorpusObject>, (PathBuf, String)>>>;

/// A list of objects of one split, loaded lazily and cached. See the module documentation.
pub struct Corpus {
    kind: CorpusKind,
    folder: Option<PathBuf>,
    split: Split,
    entries: Vec<ObjectEntry>,
    options: CorpusOptions,
    cache: Mutex<HashMap<usize, Slot>>,
    skipped: AtomicUsize,
    /// Mixture sources (empty for a single-source corpus).
    groups: Vec<Group>,
    /// Symmetries known before their objects load (a run's saved ones), by object id.
    known_symmetries: Mutex<HashMap<String, Arc<Vec<ic_geometry::Pose>>>>,
}

impl fmt::Debug for Corpus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Corpus")
            .field("kind", &self.kind)
            .field("folder", &self.folder)
            .field("split", &self.split)
            .field("objects", &self.entries.len())
            .finish()
    }
}

const MESH_EXTENSIONS: &[&str] = &["obj", "off", "ply", "gltf", "glb"];

fn has_mesh_extension(path: &Path) -> bool {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .is_some_and(|e| MESH_EXTENSIONS.contains(&e.as_str()))
}

fn read_dir_sorted(dir: &Path) -> Result<Vec<PathBuf>, DataError> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(DataError::io(dir))? {
        out.push(entry.map_err(DataError::io(dir))?.path());
    }
    out.sort();
    Ok(out)
}

impl Corpus {
    fn from_entries(
        kind: CorpusKind,
        folder: Option<PathBuf>,
        split: Split,
        entries: Vec<ObjectEntry>,
        options: CorpusOptions,
    ) -> Result<Self, DataError> {
        if options.model_points == 0 {
            return Err(DataError::Config {
                field: "model_points",
                message: "must be ≥ 1".into(),
            });
        }
        Ok(Corpus {
            kind,
            folder,
            split,
            entries,
            options,
            cache: Mutex::new(HashMap::new()),
            skipped: AtomicUsize::new(0),
            groups: Vec::new(),
            known_symmetries: Mutex::new(HashMap::new()),
        })
    }

    /// A ModelNet40 folder: `<root>/<class>/{train,test}/*.off`. Ids are `class/stem`.
    pub fn modelnet40(
        root: impl AsRef<Path>,
        split: Split,
        options: CorpusOptions,
    ) -> Result<Self, DataError> {
        let root = root.as_ref();
        let mut entries = Vec::new();
        let mut classes = 0;
        for class_dir in read_dir_sorted(root)? {
            if !class_dir.is_dir() {
                continue;
            }
            let split_dir = class_dir.join(split.as_str());
            if !split_dir.is_dir() {
                continue;
            }
            classes += 1;
            let class = class_dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            for file in read_dir_sorted(&split_dir)? {
                if file.is_file() && has_mesh_extension(&file) {
                    let stem = file
                        .file_stem()
                        .map(|s| s.to_string_lossy().into_owned())
                        .unwrap_or_default();
                    entries.push(ObjectEntry::new(
                        format!("{class}/{stem}"),
                        ObjectSource::File(file),
                        None,
                    ));
                }
            }
        }
        if entries.is_empty() {
            return Err(DataError::EmptySplit {
                folder: root.to_path_buf(),
                split: split.to_string(),
                detail: format!(
                    "expected <class>/{}/*.off; found {classes} class folder(s) with that split",
                    split
                ),
            });
        }
        Self::from_entries(
            CorpusKind::ModelNet40,
            Some(root.to_path_buf()),
            split,
            entries,
            options,
        )
    }

    /// A flat folder of meshes (`.obj`, `.off`, `.ply`, `.gltf`, `.glb`); ids are file stems.
    pub fn mesh_folder(
        dir: impl AsRef<Path>,
        how: &FolderSplit,
        split: Split,
        options: CorpusOptions,
    ) -> Result<Self, DataError> {
        let dir = dir.as_ref();
        let files: Vec<PathBuf> = read_dir_sorted(dir)?
            .into_iter()
            .filter(|p| p.is_file() && has_mesh_extension(p))
            .collect();
        let stem = |p: &Path| {
            p.file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default()
        };
        let keep: Box<dyn Fn(&str) -> bool> = match how {
            FolderSplit::IdRange { train, test } => {
                let (lo, hi) = match split {
                    Split::Train => *train,
                    Split::Test => *test,
                    Split::Val => {
                        return Err(DataError::Config {
                            field: "split",
                            message: format!(
                                "{}: an id-range split without a val range has no validation objects",
                                dir.display()
                            ),
                        });
                    }
                };
                Box::new(move |s: &str| s.parse::<u64>().is_ok_and(|id| (lo..=hi).contains(&id)))
            }
            FolderSplit::IdRanges { train, val, test } => {
                for (a, b, an, bn) in [
                    (train, val, "train", "val"),
                    (train, test, "train", "test"),
                    (val, test, "val", "test"),
                ] {
                    if a.0 <= b.1 && b.0 <= a.1 {
                        return Err(DataError::Config {
                            field: "split",
                            message: format!("id ranges {an} {a:?} and {bn} {b:?} overlap"),
                        });
                    }
                }
                let (lo, hi) = match split {
                    Split::Train => *train,
                    Split::Val => *val,
                    Split::Test => *test,
                };
                Box::new(move |s: &str| s.parse::<u64>().is_ok_and(|id| (lo..=hi).contains(&id)))
            }
            FolderSplit::All => Box::new(|_: &str| true),
            FolderSplit::File(path) => {
                let ids = split_file_ids(path, split)?;
                Box::new(move |s: &str| {
                    ids.contains(s) || s.parse::<u64>().is_ok_and(|n| ids.contains(&n.to_string()))
                })
            }
        };
        let entries: Vec<ObjectEntry> = files
            .iter()
            .filter(|p| keep(&stem(p)))
            .map(|p| ObjectEntry::new(stem(p), ObjectSource::File(p.clone()), None))
            .collect();
        if entries.is_empty() {
            return Err(DataError::EmptySplit {
                folder: dir.to_path_buf(),
                split: split.to_string(),
                detail: format!(
                    "{} mesh file(s) in the folder, none selected by {how:?}",
                    files.len()
                ),
            });
        }
        Self::from_entries(
            CorpusKind::MeshFolder,
            Some(dir.to_path_buf()),
            split,
            entries,
            options,
        )
    }

    /// A BOP `models/` folder (`obj_XXXXXX.ply`, millimetres; `models_info.json` lists the ids
    /// when present). BOP has no object split: every model is listed, under `split`.
    pub fn bop_models(
        dir: impl AsRef<Path>,
        split: Split,
        options: CorpusOptions,
    ) -> Result<Self, DataError> {
        let dir = dir.as_ref();
        let info_path = dir.join("models_info.json");
        let mut ids: Vec<u32> = Vec::new();
        if info_path.is_file() {
            let text = std::fs::read_to_string(&info_path).map_err(DataError::io(&info_path))?;
            let json: serde_json::Value =
                serde_json::from_str(&text).map_err(|e| DataError::json(&info_path, e))?;
            let obj = json
                .as_object()
                .ok_or_else(|| DataError::json(&info_path, "expected an object keyed by obj_id"))?;
            for k in obj.keys() {
                ids.push(k.parse().map_err(|_| {
                    DataError::json(&info_path, format!("key {k:?} is not an integer obj_id"))
                })?);
            }
        } else {
            for p in read_dir_sorted(dir)? {
                let name = p
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default();
                if let Some(num) = name
                    .strip_prefix("obj_")
                    .and_then(|r| r.strip_suffix(".ply"))
                    && let Ok(id) = num.parse()
                {
                    ids.push(id);
                }
            }
        }
        ids.sort_unstable();
        ids.dedup();
        if ids.is_empty() {
            return Err(DataError::EmptySplit {
                folder: dir.to_path_buf(),
                split: split.to_string(),
                detail: "no obj_XXXXXX.ply models (and no models_info.json entries)".into(),
            });
        }
        let entries = ids
            .into_iter()
            .map(|id| {
                ObjectEntry::new(
                    format!("obj_{id:06}"),
                    ObjectSource::File(dir.join(format!("obj_{id:06}.ply"))),
                    Some(id),
                )
            })
            .collect();
        Self::from_entries(
            CorpusKind::BopModels,
            Some(dir.to_path_buf()),
            split,
            entries,
            options,
        )
    }

    /// `count` procedural objects of `split` (`random_object` with seeds derived from `seed`,
    /// the split and the object number, so train, val and test objects differ).
    pub fn procedural(
        count: usize,
        split: Split,
        seed: u64,
        options: CorpusOptions,
    ) -> Result<Self, DataError> {
        if count == 0 {
            return Err(DataError::Config {
                field: "procedural count",
                message: "must be ≥ 1".into(),
            });
        }
        let tag = match split {
            Split::Train => 0x7261_696e,
            Split::Test => 0x7465_7374,
            Split::Val => 0x0076_616c,
        };
        let entries = (0..count)
            .map(|k| {
                let s = mix(mix(seed, tag), k as u64);
                ObjectEntry::new(format!("proc_{s:016x}"), ObjectSource::Procedural(s), None)
            })
            .collect();
        Self::from_entries(CorpusKind::Procedural, None, split, entries, options)
    }

    /// A weighted mixture of corpora of one split: [`Corpus::pick`] first draws a source with
    /// probability proportional to its weight, then an object of that source uniformly. Ids
    /// become `<name>/<id>`; an object's mesh and model points are those it has in its own
    /// corpus. Names must be distinct, non-empty and free of `/`; weights positive and
    /// finite; the parts must share one split and one [`CorpusOptions`].
    pub fn mixture(parts: Vec<MixturePart>) -> Result<Self, DataError> {
        let bad = |message: String| {
            Err(DataError::Config {
                field: "mixture",
                message,
            })
        };
        let Some(first) = parts.first() else {
            return bad("no source given".into());
        };
        let (split, options) = (first.corpus.split, first.corpus.options);
        let total: f64 = parts.iter().map(|p| p.weight).sum();
        let mut names = std::collections::HashSet::new();
        for p in &parts {
            if p.name.is_empty() || p.name.contains('/') || !names.insert(p.name.as_str()) {
                return bad(format!(
                    "source name {:?} is empty, holds '/' or is used twice",
                    p.name
                ));
            }
            if !(p.weight.is_finite() && p.weight > 0.0) {
                return bad(format!(
                    "source {:?}: weight must be positive, got {}",
                    p.name, p.weight
                ));
            }
            if p.corpus.split != split || p.corpus.options != options {
                return bad(format!(
                    "source {:?}: every source must have the same split and options",
                    p.name
                ));
            }
            if !p.corpus.groups.is_empty() {
                return bad(format!("source {:?} is itself a mixture", p.name));
            }
        }
        let mut entries = Vec::new();
        let mut groups = Vec::new();
        let mut cumulative = 0.0;
        let count = parts.len();
        for (k, p) in parts.into_iter().enumerate() {
            let start = entries.len();
            let probability = p.weight / total;
            cumulative = if k + 1 == count {
                1.0
            } else {
                cumulative + probability
            };
            groups.push(Group {
                info: SourceInfo {
                    name: p.name.clone(),
                    kind: p.corpus.kind.clone(),
                    folder: p.corpus.folder.clone(),
                    probability,
                    objects: p.corpus.len(),
                },
                range: start..start + p.corpus.len(),
                cumulative,
            });
            entries.extend(p.corpus.entries.into_iter().map(|e| ObjectEntry {
                id: format!("{}/{}", p.name, e.id),
                ..e
            }));
        }
        let mut corpus = Self::from_entries(CorpusKind::Mixture, None, split, entries, options)?;
        corpus.groups = groups;
        Ok(corpus)
    }

    /// The sources of a mixture (empty for a single-source corpus).
    pub fn sources(&self) -> Vec<SourceInfo> {
        self.groups.iter().map(|g| g.info.clone()).collect()
    }

    /// The mixture source holding entry `index` (`None` for a single-source corpus).
    pub fn source_of(&self, index: usize) -> Option<&str> {
        self.groups
            .iter()
            .find(|g| g.range.contains(&index))
            .map(|g| g.info.name.as_str())
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    pub fn split(&self) -> Split {
        self.split
    }

    pub fn entries(&self) -> &[ObjectEntry] {
        &self.entries
    }

    pub fn options(&self) -> &CorpusOptions {
        &self.options
    }

    /// Number of objects found unusable so far (each counted once).
    pub fn skipped(&self) -> usize {
        self.skipped.load(Ordering::Relaxed)
    }

    /// A description for manifests.
    pub fn info(&self) -> CorpusInfo {
        CorpusInfo {
            kind: self.kind.clone(),
            folder: self.folder.clone(),
            split: self.split,
            objects: self.len(),
            skipped: self.skipped(),
            sources: self.sources(),
        }
    }

    fn folder_display(&self) -> PathBuf {
        self.folder
            .clone()
            .unwrap_or_else(|| PathBuf::from("<procedural>"))
    }

    /// The object at `index`, loaded and cached on first use. Fails with the object's error
    /// (whatever the [`OnBadMesh`] policy: the policy applies to [`Corpus::pick`]).
    pub fn object(&self, index: usize) -> Result<Arc<CorpusObject>, DataError> {
        let entry = self.entries.get(index).ok_or_else(|| DataError::Config {
            field: "object index",
            message: format!(
                "{index} is out of range (the corpus holds {} objects)",
                self.entries.len()
            ),
        })?;
        let slot = {
            let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
            cache.entry(index).or_default().clone()
        };
        let result = slot.get_or_init(|| {
            let r = load_object(entry, index, &self.options);
            if let Ok(object) = &r {
                let known = self
                    .known_symmetries
                    .lock()
                    .unwrap_or_else(|e| e.into_inner());
                if let Some(s) = known.get(&object.id) {
                    let _ = object.symmetries.set(s.clone());
                }
            }
            if let Err((path, message)) = &r {
                self.skipped.fetch_add(1, Ordering::Relaxed);
                tracing::warn!(path = %path.display(), "unusable mesh: {message}");
            }
            r
        });
        result
            .clone()
            .map_err(|(path, message)| DataError::BadMesh { path, message })
    }

    /// Symmetries to use instead of searching (e.g. the ones a run saved with
    /// [`Corpus::found_symmetries`], computed with [`TRAINING_SYMMETRY_OPTIONS`] on the same
    /// meshes), by object id; objects loaded later take them.
    pub fn set_known_symmetries(&self, known: HashMap<String, Vec<ic_geometry::Pose>>) {
        let mut k = self
            .known_symmetries
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        k.extend(known.into_iter().map(|(id, s)| (id, Arc::new(s))));
    }

    /// The symmetries of every loaded object whose search has run (or was given), by id.
    pub fn found_symmetries(&self) -> HashMap<String, Vec<ic_geometry::Pose>> {
        let cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        cache
            .values()
            .filter_map(|slot| slot.get()?.as_ref().ok())
            .filter_map(|o| Some((o.id.clone(), o.symmetries.get()?.as_ref().clone())))
            .collect()
    }

    /// The object with this id, if listed.
    pub fn position(&self, id: &str) -> Option<usize> {
        self.entries.iter().position(|e| e.id == id)
    }

    /// Draws an object uniformly. An unusable object is skipped (warning, counted) and another
    /// drawn under [`OnBadMesh::Skip`]; its error is returned under [`OnBadMesh::Stop`]. The
    /// draws depend only on `rng` and on which objects are unusable, so the result is the same
    /// whether or not the corpus was preloaded.
    ///
    /// In a mixture a source is drawn first (one `f64` from `rng`), then an object of that
    /// source as above; a source whose objects are all unusable is an error.
    pub fn pick<R: Rng + ?Sized>(&self, rng: &mut R) -> Result<Arc<CorpusObject>, DataError> {
        let (range, folder) = if self.groups.is_empty() {
            (0..self.entries.len(), self.folder_display())
        } else {
            let u: f64 = rng.random();
            let g = self
                .groups
                .iter()
                .find(|g| u < g.cumulative)
                .unwrap_or(&self.groups[self.groups.len() - 1]);
            let folder = g
                .info
                .folder
                .clone()
                .unwrap_or_else(|| PathBuf::from(format!("<{}>", g.info.name)));
            (g.range.clone(), folder)
        };
        let (start, n) = (range.start, range.len());
        let mut last = 0;
        for _ in 0..64 {
            let i = rng.random_range(0..n);
            last = i;
            match self.object(start + i) {
                Ok(o) => return Ok(o),
                Err(e) if self.options.on_bad_mesh == OnBadMesh::Stop => return Err(e),
                Err(_) => {}
            }
        }
        for k in 1..n {
            if let Ok(o) = self.object(start + (last + k) % n) {
                return Ok(o);
            }
        }
        Err(DataError::NoUsableObject {
            folder,
            split: self.split.to_string(),
            skipped: self.skipped(),
        })
    }

    /// Loads every object now (in parallel). Returns the number of usable objects; fails on the
    /// first bad mesh under [`OnBadMesh::Stop`], or when none is usable.
    pub fn preload(&self) -> Result<usize, DataError> {
        use rayon::prelude::*;
        let results: Vec<Result<Arc<CorpusObject>, DataError>> = (0..self.entries.len())
            .into_par_iter()
            .map(|i| self.object(i))
            .collect();
        let mut good = 0;
        for r in results {
            match r {
                Ok(_) => good += 1,
                Err(e) if self.options.on_bad_mesh == OnBadMesh::Stop => return Err(e),
                Err(_) => {}
            }
        }
        if good == 0 {
            return Err(DataError::NoUsableObject {
                folder: self.folder_display(),
                split: self.split.to_string(),
                skipped: self.skipped(),
            });
        }
        Ok(good)
    }
}

fn load_object(
    entry: &ObjectEntry,
    index: usize,
    options: &CorpusOptions,
) -> Result<Arc<CorpusObject>, (PathBuf, String)> {
    // The sampling seed comes from the id, so it does not depend on the load order.
    let seed = entry.model_seed;
    let (path, mut mesh) = match &entry.source {
        ObjectSource::File(path) => {
            let mesh =
                ic_geometry::io::load_mesh(path).map_err(|e| (path.clone(), e.to_string()))?;
            (path.clone(), mesh)
        }
        ObjectSource::Procedural(s) => (
            PathBuf::from(format!("<procedural {s:#x}>")),
            ic_geometry::shapes::random_object(*s),
        ),
    };
    let normalisation = mesh
        .normalise()
        .map_err(|e| (path.clone(), e.to_string()))?;
    let cloud = sample_visible_surface(&mesh, options.model_points, seed, options.visible_surface)
        .map_err(|e| (path.clone(), e.to_string()))?;
    if cloud.points.is_empty() {
        return Err((path, "no visible surface could be sampled".into()));
    }
    Ok(Arc::new(CorpusObject {
        id: entry.id.clone(),
        index,
        bop_obj_id: entry.bop_obj_id,
        mesh: Arc::new(mesh),
        normalisation,
        model_points: cloud.points,
        symmetries: OnceLock::new(),
    }))
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}
