//! Object corpora and their splits: a ModelNet40 folder, a flat folder of meshes, a BOP
//! `models/` folder, or the procedural stream of `ic_geometry::shapes::random_object`.
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

/// Training or test objects (the paper uses disjoint objects for the two).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn as_str(&self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
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
            _ => Err(DataError::Config {
                field: "split",
                message: format!("expected train or test, got {s:?}"),
            }),
        }
    }
}

/// How a flat folder of meshes is split into train and test objects.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FolderSplit {
    /// Ids are the numeric file stems (`000.obj` → 0); inclusive ranges per split. The blob
    /// folder of the project uses train 0–799, test 800–999 ([`FolderSplit::blobs`]).
    IdRange { train: (u64, u64), test: (u64, u64) },
    /// A JSON file `{"train": ["000", …], "test": ["800", …]}` listing file stems.
    File(PathBuf),
}

impl FolderSplit {
    /// The split of the 1000-blob folder: 000–799 train, 800–999 test.
    pub fn blobs() -> Self {
        FolderSplit::IdRange {
            train: (0, 799),
            test: (800, 999),
        }
    }
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
/// `proc_<seed>` for procedural objects), its source and, for BOP models, its BOP `obj_id`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectEntry {
    pub id: String,
    pub source: ObjectSource,
    pub bop_obj_id: Option<u32>,
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
}

/// What kind of corpus this is (for manifests).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CorpusKind {
    ModelNet40,
    MeshFolder,
    BopModels,
    Procedural,
}

/// A serialisable description of a corpus (for manifests).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CorpusInfo {
    pub kind: CorpusKind,
    pub folder: Option<PathBuf>,
    pub split: Split,
    pub objects: usize,
    pub skipped: usize,
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
                    entries.push(ObjectEntry {
                        id: format!("{class}/{stem}"),
                        source: ObjectSource::File(file),
                        bop_obj_id: None,
                    });
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
                let (lo, hi) = if split == Split::Train { *train } else { *test };
                Box::new(move |s: &str| s.parse::<u64>().is_ok_and(|id| (lo..=hi).contains(&id)))
            }
            FolderSplit::File(path) => {
                let text = std::fs::read_to_string(path).map_err(DataError::io(path))?;
                let json: serde_json::Value =
                    serde_json::from_str(&text).map_err(|e| DataError::json(path, e))?;
                let list = json
                    .get(split.as_str())
                    .and_then(|v| v.as_array())
                    .ok_or_else(|| {
                        DataError::json(path, format!("no {:?} list of file stems", split.as_str()))
                    })?;
                let mut ids = std::collections::HashSet::new();
                for (i, v) in list.iter().enumerate() {
                    let s = match v {
                        serde_json::Value::String(s) => s.clone(),
                        serde_json::Value::Number(n) => n.to_string(),
                        _ => {
                            return Err(DataError::json(
                                path,
                                format!("{}[{i}] is not a string or number", split.as_str()),
                            ));
                        }
                    };
                    ids.insert(s);
                }
                Box::new(move |s: &str| {
                    ids.contains(s) || s.parse::<u64>().is_ok_and(|n| ids.contains(&n.to_string()))
                })
            }
        };
        let entries: Vec<ObjectEntry> = files
            .iter()
            .filter(|p| keep(&stem(p)))
            .map(|p| ObjectEntry {
                id: stem(p),
                source: ObjectSource::File(p.clone()),
                bop_obj_id: None,
            })
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
            .map(|id| ObjectEntry {
                id: format!("obj_{id:06}"),
                source: ObjectSource::File(dir.join(format!("obj_{id:06}.ply"))),
                bop_obj_id: Some(id),
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
    /// the split and the object number, so train and test objects differ).
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
        let tag = if split == Split::Train {
            0x7261_696e
        } else {
            0x7465_7374
        };
        let entries = (0..count)
            .map(|k| {
                let s = mix(mix(seed, tag), k as u64);
                ObjectEntry {
                    id: format!("proc_{s:016x}"),
                    source: ObjectSource::Procedural(s),
                    bop_obj_id: None,
                }
            })
            .collect();
        Self::from_entries(CorpusKind::Procedural, None, split, entries, options)
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

    /// The object with this id, if listed.
    pub fn position(&self, id: &str) -> Option<usize> {
        self.entries.iter().position(|e| e.id == id)
    }

    /// Draws an object uniformly. An unusable object is skipped (warning, counted) and another
    /// drawn under [`OnBadMesh::Skip`]; its error is returned under [`OnBadMesh::Stop`]. The
    /// draws depend only on `rng` and on which objects are unusable, so the result is the same
    /// whether or not the corpus was preloaded.
    pub fn pick<R: Rng + ?Sized>(&self, rng: &mut R) -> Result<Arc<CorpusObject>, DataError> {
        let n = self.entries.len();
        let mut last = 0;
        for _ in 0..64 {
            let i = rng.random_range(0..n);
            last = i;
            match self.object(i) {
                Ok(o) => return Ok(o),
                Err(e) if self.options.on_bad_mesh == OnBadMesh::Stop => return Err(e),
                Err(_) => {}
            }
        }
        for k in 1..n {
            if let Ok(o) = self.object((last + k) % n) {
                return Ok(o);
            }
        }
        Err(DataError::NoUsableObject {
            folder: self.folder_display(),
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
    let (path, mut mesh, seed) = match &entry.source {
        ObjectSource::File(path) => {
            let mesh =
                ic_geometry::io::load_mesh(path).map_err(|e| (path.clone(), e.to_string()))?;
            // The sampling seed comes from the id, so it does not depend on the load order.
            (
                path.clone(),
                mesh,
                mix(0x006d_6f64_656c, fnv1a(entry.id.as_bytes())),
            )
        }
        ObjectSource::Procedural(s) => (
            PathBuf::from(format!("<procedural {s:#x}>")),
            ic_geometry::shapes::random_object(*s),
            mix(*s, 1),
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
    }))
}

fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}
