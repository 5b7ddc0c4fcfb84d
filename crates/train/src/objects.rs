//! `--objects`: which meshes a training run draws from, as one folder or a weighted mixture of
//! folders and procedural objects, and how each is split into train / val / test objects.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use ic_data::{Corpus, CorpusOptions, FolderSplit, Split};
use serde_json::json;

/// Number of procedural training objects of a `procedural` source (validation: 50, test: 200).
const PROCEDURAL_TRAIN: usize = 500;
/// Seed of the procedural objects of `--objects …procedural…` (fixed, so the objects of a
/// split are the same in every run).
const PROCEDURAL_SEED: u64 = 0x7072_6f63;

/// One source of `--objects`.
#[derive(Clone, Debug, PartialEq)]
pub enum SourceKind {
    /// A folder: with `split.json` (`train`/`val`/`test` lists of file stems), else numeric
    /// stems split as the blobs (000–749 train, 750–799 val, 800–999 test).
    Folder(PathBuf),
    /// `ic_geometry::shapes::random_object` composites: `count` training objects, 50
    /// validation and 200 test objects (disjoint seeds).
    Procedural { count: usize },
}

#[derive(Clone, Debug, PartialEq)]
pub struct SourceSpec {
    pub name: String,
    pub kind: SourceKind,
    pub weight: f64,
}

/// `--objects`: one folder (the old form), or a weighted mixture
/// `NAME=SOURCE:WEIGHT,NAME=SOURCE:WEIGHT,…` where SOURCE is a folder, `procedural` or
/// `procedural@COUNT`; `NAME=` is optional (default: the folder's name, or `procedural`) and
/// so is `:WEIGHT` (default 1; weights are normalised). Example:
/// `real=../shared/data/objects/real_objects:0.6,blobs=../shared/data/objects/blobs:0.3,procedural:0.1`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjectsSpec {
    pub text: String,
    pub sources: Vec<SourceSpec>,
    /// One source given without name and weight: a plain corpus, ids unprefixed (as before
    /// mixtures existed, so old runs reproduce).
    pub plain: bool,
    /// Every mesh of each folder belongs to every split (`FolderSplit::All`): a user's own
    /// handful of objects, validated on other views of the same objects.
    pub every_split: bool,
}

impl std::str::FromStr for ObjectsSpec {
    type Err = anyhow::Error;
    fn from_str(text: &str) -> Result<Self> {
        let mut sources = Vec::new();
        let mut plain = false;
        let parts: Vec<&str> = text.split(',').map(str::trim).collect();
        for part in &parts {
            if part.is_empty() {
                bail!("--objects {text:?}: empty source");
            }
            let (name, rest) = match part.split_once('=') {
                Some((n, r)) => (Some(n.trim().to_string()), r.trim()),
                None => (None, *part),
            };
            let (source, weight) = match rest.rsplit_once(':') {
                Some((s, w)) if w.trim().parse::<f64>().is_ok() => {
                    (s.trim(), Some(w.trim().parse::<f64>()?))
                }
                _ => (rest, None),
            };
            if let Some(w) = weight
                && !(w.is_finite() && w > 0.0)
            {
                bail!("--objects: weight of {source:?} must be positive, got {w}");
            }
            let kind = if source == "procedural" {
                SourceKind::Procedural {
                    count: PROCEDURAL_TRAIN,
                }
            } else if let Some(n) = source.strip_prefix("procedural@") {
                let count: usize = n
                    .parse()
                    .with_context(|| format!("--objects: {source:?}: expected procedural@COUNT"))?;
                if count == 0 {
                    bail!("--objects: {source:?}: the count must be ≥ 1");
                }
                SourceKind::Procedural { count }
            } else {
                SourceKind::Folder(PathBuf::from(source))
            };
            if parts.len() == 1 && name.is_none() && weight.is_none() {
                plain = true;
            }
            let name = name.unwrap_or_else(|| match &kind {
                SourceKind::Folder(p) => p
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "objects".into()),
                SourceKind::Procedural { .. } => "procedural".into(),
            });
            sources.push(SourceSpec {
                name,
                kind,
                weight: weight.unwrap_or(1.0),
            });
        }
        Ok(ObjectsSpec {
            text: text.to_string(),
            sources,
            plain,
            every_split: false,
        })
    }
}

impl ObjectsSpec {
    /// Every mesh of `dir`, in every split (see [`ObjectsSpec::every_split`]).
    pub fn every_mesh_of(dir: impl Into<PathBuf>) -> ObjectsSpec {
        let dir = dir.into();
        ObjectsSpec {
            text: dir.display().to_string(),
            sources: vec![SourceSpec {
                name: dir
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_else(|| "objects".into()),
                kind: SourceKind::Folder(dir),
                weight: 1.0,
            }],
            plain: true,
            every_split: true,
        }
    }

    /// The corpus of `split` (a mixture unless the spec is one plain folder).
    pub fn corpus(&self, split: Split, options: CorpusOptions) -> Result<Corpus> {
        let mut parts = Vec::new();
        for s in &self.sources {
            let corpus = match &s.kind {
                SourceKind::Folder(dir) => {
                    if !dir.is_dir() {
                        bail!("--objects: {}: not a folder", dir.display());
                    }
                    let file = dir.join("split.json");
                    let how = if self.every_split {
                        FolderSplit::All
                    } else if file.is_file() {
                        FolderSplit::File(file)
                    } else {
                        FolderSplit::blobs_with_val()
                    };
                    Corpus::mesh_folder(dir, &how, split, options)
                        .with_context(|| format!("the {split} objects of {}", dir.display()))?
                }
                SourceKind::Procedural { count } => {
                    let n = match split {
                        Split::Train => *count,
                        Split::Val => 50,
                        Split::Test => 200,
                    };
                    Corpus::procedural(n, split, PROCEDURAL_SEED, options)?
                }
            };
            parts.push(ic_data::MixturePart {
                name: s.name.clone(),
                corpus,
                weight: s.weight,
            });
        }
        if self.plain {
            return Ok(parts.remove(0).corpus);
        }
        Ok(Corpus::mixture(parts)?)
    }

    /// A description for logs and manifests.
    pub fn describe(&self) -> serde_json::Value {
        let total: f64 = self.sources.iter().map(|s| s.weight).sum();
        json!({
            "spec": self.text,
            "sources": self.sources.iter().map(|s| json!({
                "name": s.name,
                "source": match &s.kind {
                    SourceKind::Folder(p) => json!(p),
                    SourceKind::Procedural { count } => json!(format!("procedural ({count} train objects, seed {PROCEDURAL_SEED:#x})")),
                },
                "probability": s.weight / total,
            })).collect::<Vec<_>>(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn objects_spec_parses_the_old_folder_form_and_weighted_mixtures() {
        let one: ObjectsSpec = "../shared/data/objects/blobs".parse().unwrap();
        assert!(one.plain);
        assert_eq!(one.sources[0].name, "blobs");
        let mix: ObjectsSpec = "real=../a/real_objects:0.6, blobs=../a/blobs:0.3,procedural:0.1"
            .parse()
            .unwrap();
        assert!(!mix.plain);
        let got: Vec<(&str, f64)> = mix
            .sources
            .iter()
            .map(|s| (s.name.as_str(), s.weight))
            .collect();
        assert_eq!(got, [("real", 0.6), ("blobs", 0.3), ("procedural", 0.1)]);
        assert_eq!(
            mix.sources[2].kind,
            SourceKind::Procedural {
                count: PROCEDURAL_TRAIN
            }
        );
        let p: ObjectsSpec = "procedural@40".parse().unwrap();
        assert_eq!(p.sources[0].kind, SourceKind::Procedural { count: 40 });
        // A colon that is not followed by a number belongs to the path.
        let odd: ObjectsSpec = "/data/a:b".parse().unwrap();
        assert_eq!(odd.sources[0].kind, SourceKind::Folder("/data/a:b".into()));
        for bad in ["a:0", "a:-1", "a,,b", "procedural@x", "procedural@0"] {
            assert!(bad.parse::<ObjectsSpec>().is_err(), "{bad}");
        }
        // Procedural sources build corpora of every split without files; a lone weighted
        // source is a mixture (prefixed ids).
        let c = "procedural@3:1"
            .parse::<ObjectsSpec>()
            .unwrap()
            .corpus(Split::Val, CorpusOptions::default())
            .unwrap();
        assert_eq!(c.len(), 50);
        assert!(c.entries()[0].id.starts_with("procedural/"));
    }
}
