//! Stage 1 of `cargo xtask bench`: the fixed case sets, exported once and reused.
//!
//! The cases are the ones `cargo xtask export-cases` writes for the same set, objects, seed and
//! count (the same `ic_data` generators and writers), plus `mask_visib.png` in each room case
//! (the ground-truth visible mask, 8-bit, 255 = object) for the upper-bound runs. A folder is
//! reused when its `bench-manifest.json` equals the one this run would write and every case is
//! there; otherwise it is written again into `<folder>.partial` and renamed into place.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result, bail};
use ic_data::export::{CaseFolder, write_object_case, write_room_case};
use ic_data::{
    Corpus, CorpusOptions, FolderSplit, ObjectSampleConfig, ObjectSampleGenerator, Prefetcher,
    RoomSampleConfig, RoomSampleGenerator, Split,
};
use serde_json::{Value, json};

/// Bump when the folder layout changes, so old folders are rewritten.
const FORMAT: u32 = 1;

/// Which case set.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Set {
    Noback,
    Room,
}

impl Set {
    pub const ALL: [Set; 2] = [Set::Noback, Set::Room];

    pub fn name(self) -> &'static str {
        match self {
            Set::Noback => "noback",
            Set::Room => "room",
        }
    }

    pub fn title(self) -> &'static str {
        match self {
            Set::Noback => "Object alone",
            Set::Room => "Object in the room",
        }
    }
}

/// Where the objects come from.
#[derive(Clone, Debug)]
pub enum Objects {
    /// A flat folder of meshes split by id: 0–799 train, 800–999 test (the blob folder).
    Folder(PathBuf),
    /// `count` procedural objects (when no folder is available: the quick bench on CI).
    Procedural(usize),
}

impl Objects {
    pub fn describe(&self) -> Value {
        match self {
            Objects::Folder(p) => {
                json!({"kind": "mesh_folder", "folder": p, "split_rule": "ids 0-799 train, 800-999 test"})
            }
            Objects::Procedural(n) => json!({"kind": "procedural", "count": n}),
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
    let sample = match set {
        Set::Noback => serde_json::to_value(ObjectSampleConfig::default()),
        Set::Room => serde_json::to_value(RoomSampleConfig::default()),
    }
    .unwrap_or(Value::Null);
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
            && (set == Set::Noback || case.dir().join(CaseFolder::MASK_VISIB).is_file())
    })
}

fn read_json(path: &Path) -> Option<Value> {
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
    let partial = sibling(dir, "partial");
    if partial.exists() {
        std::fs::remove_dir_all(&partial)
            .with_context(|| format!("removing {}", partial.display()))?;
    }
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
    crate::bench::common::write_atomic(
        &partial.join("bench-manifest.json"),
        serde_json::to_string_pretty(&want)?.as_bytes(),
    )?;
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    std::fs::rename(&partial, dir)
        .with_context(|| format!("renaming {} to {}", partial.display(), dir.display()))?;
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
}
