//! The shipped networks: embedded in the binary when they existed at build time (see
//! `build.rs`), else looked up under the workspace's `models/` folder; or any checkpoint given
//! with `--pose-model` / `--seg-model`.

use std::io::Write;
use std::path::{Path, PathBuf};

use ic_pose::{Head, PoseEstimator};
use ic_seg::Segmenter;

use crate::pipeline::{PipelineError, Result};

/// One shipped model: its file name under `models/` and, when it existed at build time, its
/// bytes.
#[derive(Clone, Copy, Debug)]
pub struct Shipped {
    pub file: &'static str,
    pub bytes: Option<&'static [u8]>,
}

impl Shipped {
    /// Where the file lives in the workspace this binary was built from.
    pub fn workspace_path(&self) -> PathBuf {
        let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
        // crates/incontext → the workspace root.
        let root = manifest.ancestors().nth(2).unwrap_or(manifest);
        root.join("models").join(self.file)
    }

    /// Whether this model can be loaded without a flag.
    pub fn available(&self) -> bool {
        self.bytes.is_some() || self.workspace_path().is_file()
    }

    /// "embedded" or the workspace path.
    pub fn describe(&self) -> String {
        match self.bytes {
            Some(_) => format!("models/{} (embedded)", self.file),
            None => self.workspace_path().display().to_string(),
        }
    }
}

/// The softmax-head pose network (`models/pose-cpu-softmax.safetensors`).
pub const POSE_SOFTMAX: Shipped = Shipped {
    file: "pose-cpu-softmax.safetensors",
    #[cfg(ic_embed_pose_softmax)]
    bytes: Some(include_bytes!(
        "../../../models/pose-cpu-softmax.safetensors"
    )),
    #[cfg(not(ic_embed_pose_softmax))]
    bytes: None,
};

/// The second softmax-head pose network (`models/pose-cpu-softmax-scratch.safetensors`, trained
/// from scratch on every viewpoint of real objects): its hypotheses join the main network's in
/// the verified pipeline ([`crate::Pipeline::with_second_pose`]).
pub const POSE_SOFTMAX_SECOND: Shipped = Shipped {
    file: "pose-cpu-softmax-scratch.safetensors",
    #[cfg(ic_embed_pose_softmax_second)]
    bytes: Some(include_bytes!(
        "../../../models/pose-cpu-softmax-scratch.safetensors"
    )),
    #[cfg(not(ic_embed_pose_softmax_second))]
    bytes: None,
};

/// The optimal-transport-head pose network (`models/pose-cpu-ot.safetensors`).
pub const POSE_OT: Shipped = Shipped {
    file: "pose-cpu-ot.safetensors",
    #[cfg(ic_embed_pose_ot)]
    bytes: Some(include_bytes!("../../../models/pose-cpu-ot.safetensors")),
    #[cfg(not(ic_embed_pose_ot))]
    bytes: None,
};

/// The default segmentation network (`models/seg-clutter.safetensors`): every object of a
/// cluttered scene, each instance apart.
pub const SEG: Shipped = Shipped {
    file: "seg-clutter.safetensors",
    #[cfg(ic_embed_seg)]
    bytes: Some(include_bytes!("../../../models/seg-clutter.safetensors")),
    #[cfg(not(ic_embed_seg))]
    bytes: None,
};

/// The one-object segmentation network (`models/seg-cpu.safetensors`, trained on rooms holding
/// one object): the default pipeline's second opinion when the clutter network's instances
/// give no `ok` pose — it keeps a lone object of several parts whole, which the clutter network
/// cuts apart (`docs/decisions.md`, "One network for clutter, one for a lone object").
pub const SEG_ONE_OBJECT: Shipped = Shipped {
    file: "seg-cpu.safetensors",
    #[cfg(ic_embed_seg_one_object)]
    bytes: Some(include_bytes!("../../../models/seg-cpu.safetensors")),
    #[cfg(not(ic_embed_seg_one_object))]
    bytes: None,
};

/// The shipped pose network of a head.
pub fn shipped_pose(head: Head) -> Shipped {
    match head {
        Head::Softmax => POSE_SOFTMAX,
        Head::Ot => POSE_OT,
    }
}

/// A file that holds a checkpoint: the user's, the workspace's, or a temporary copy of the
/// embedded bytes (kept alive as long as the network that memory-maps it).
pub(crate) enum CheckpointFile {
    Path(PathBuf),
    Temp(tempfile::NamedTempFile),
}

impl CheckpointFile {
    pub(crate) fn path(&self) -> &Path {
        match self {
            CheckpointFile::Path(p) => p,
            CheckpointFile::Temp(t) => t.path(),
        }
    }
}

fn check_readable(path: &Path, what: &str) -> Result<()> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => Ok(()),
        Ok(_) => Err(PipelineError::input(format!(
            "{}: the {what} is not a file",
            path.display()
        ))),
        Err(e) => Err(PipelineError::input(format!(
            "{}: cannot read the {what}: {e}",
            path.display()
        ))),
    }
}

/// The file of `shipped`, or an error saying how to get it.
fn shipped_file(shipped: &Shipped, what: &str, flag: &str) -> Result<CheckpointFile> {
    if let Some(bytes) = shipped.bytes {
        let mut tmp = tempfile::Builder::new()
            .prefix("incontext-")
            .suffix(".safetensors")
            .tempfile()
            .map_err(|e| {
                PipelineError::internal(format!("creating a temporary file for the {what}: {e}"))
            })?;
        tmp.write_all(bytes)
            .and_then(|_| tmp.flush())
            .map_err(|e| {
                PipelineError::internal(format!(
                    "writing the embedded {what} to a temporary file: {e}"
                ))
            })?;
        return Ok(CheckpointFile::Temp(tmp));
    }
    let path = shipped.workspace_path();
    if path.is_file() {
        return Ok(CheckpointFile::Path(path));
    }
    Err(PipelineError::input(format!(
        "the {what} models/{} is not built into this binary and {} does not exist; \
         pass {flag} FILE (a checkpoint written by cargo xtask)",
        shipped.file,
        path.display()
    )))
}

/// A pose network loaded with the file that backs it.
pub struct LoadedPose {
    pub estimator: PoseEstimator,
    /// Where it came from (for the run's printed configuration).
    pub source: String,
    /// The memory-mapped file, kept while the network lives; `None` once a temporary copy of
    /// the embedded bytes was removed (Unix keeps the mapping of a removed file).
    pub(crate) _file: Option<CheckpointFile>,
}

impl LoadedPose {
    /// The same network attending over `keys` farthest-point samples of each cloud (`None`:
    /// every point) whatever its checkpoint says ([`ic_pose::NetConfig::pooled_keys`]).
    pub fn with_attention_keys(mut self, keys: Option<usize>) -> Result<Self> {
        self.estimator = self
            .estimator
            .with_pooled_keys(keys)
            .map_err(|e| PipelineError::input(format!("attention keys: {e}")))?;
        Ok(self)
    }

    /// The attention keys the network runs with: `None` when every point.
    pub fn attention_keys(&self) -> Option<usize> {
        self.estimator.config().net.pooled_keys
    }
}

/// Loads `path`, or the shipped network of `head` when `path` is `None`. With both, the
/// checkpoint's head must be `head`.
pub fn load_pose(path: Option<&Path>, head: Option<Head>) -> Result<LoadedPose> {
    let shipped = shipped_pose(head.unwrap_or(Head::Softmax));
    load_pose_from(path, &shipped, head, "pose model", "--pose-model")
}

/// The second pose network ([`crate::Pipeline::with_second_pose`], which checks that its head
/// is the main network's): `path`, or the shipped one of `head` ([`POSE_SOFTMAX_SECOND`] for
/// softmax, none for OT); `None` when there is none or this build has it neither embedded nor
/// in the workspace.
pub fn load_pose_second(path: Option<&Path>, head: Head) -> Result<Option<LoadedPose>> {
    let load = |path| {
        load_pose_from(
            path,
            &POSE_SOFTMAX_SECOND,
            None,
            "second pose model",
            "--second-pose-model",
        )
    };
    match (path, head) {
        (Some(p), _) => load(Some(p)).map(Some),
        (None, Head::Softmax) if POSE_SOFTMAX_SECOND.available() => load(None).map(Some),
        (None, _) => Ok(None),
    }
}

/// Loads `path`, or `shipped` when `path` is `None` (`what` and `flag` name it in errors);
/// with `head`, the checkpoint must have it.
fn load_pose_from(
    path: Option<&Path>,
    shipped: &Shipped,
    head: Option<Head>,
    what: &str,
    flag: &str,
) -> Result<LoadedPose> {
    let (file, source) = match path {
        Some(p) => {
            check_readable(p, what)?;
            (
                CheckpointFile::Path(p.to_path_buf()),
                p.display().to_string(),
            )
        }
        None => (shipped_file(shipped, what, flag)?, shipped.describe()),
    };
    let estimator = PoseEstimator::load(file.path())
        .map_err(|e| PipelineError::from(e).context(format!("loading the {what} {source}")))?;
    let got = estimator.config().net.head;
    if let Some(want) = head
        && got != want
    {
        return Err(PipelineError::input(format!(
            "{source}: the {what} has a {} head, but --head {} was asked for",
            got.as_str(),
            want.as_str()
        )));
    }
    // The temporary copy of the embedded network goes at once: on Unix its memory map stays
    // valid without the file, and a process ended by a signal (which exits without running
    // destructors) then leaves nothing in the temporary folder.
    let file = match file {
        #[cfg(unix)]
        CheckpointFile::Temp(t) => {
            let _ = t.close();
            None
        }
        f => Some(f),
    };
    Ok(LoadedPose {
        estimator,
        source,
        _file: file,
    })
}

/// A segmentation network and where it came from.
pub struct LoadedSeg {
    pub segmenter: Segmenter,
    pub source: String,
}

/// Loads `path`, or the shipped segmentation network ([`SEG`]) when `path` is `None`.
pub fn load_seg(path: Option<&Path>) -> Result<LoadedSeg> {
    load_seg_from(path, &SEG)
}

/// The shipped one-object segmentation network ([`SEG_ONE_OBJECT`]), or `None` when this
/// build has it neither embedded nor in the workspace.
pub fn load_seg_one_object() -> Result<Option<LoadedSeg>> {
    if !SEG_ONE_OBJECT.available() {
        return Ok(None);
    }
    load_seg_from(None, &SEG_ONE_OBJECT).map(Some)
}

fn load_seg_from(path: Option<&Path>, shipped: &Shipped) -> Result<LoadedSeg> {
    let (file, source) = match path {
        Some(p) => {
            check_readable(p, "segmentation model")?;
            (
                CheckpointFile::Path(p.to_path_buf()),
                p.display().to_string(),
            )
        }
        None => (
            shipped_file(shipped, "segmentation model", "--seg-model")?,
            shipped.describe(),
        ),
    };
    // Segmenter::load reads the weights into memory; the file may go afterwards.
    let segmenter = Segmenter::load(file.path()).map_err(|e| {
        PipelineError::from(e).context(format!("loading the segmentation model {source}"))
    })?;
    Ok(LoadedSeg { segmenter, source })
}
