//! safetensors files with string metadata, written atomically (temporary file + rename), and
//! a header-only metadata reader.

use std::collections::HashMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use candle_core::Tensor;

/// A checkpoint that could not be written or read, with the file it concerns.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: {message}", path.display())]
    Format { path: PathBuf, message: String },
}

fn format_err(path: &Path, message: impl Into<String>) -> CheckpointError {
    CheckpointError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Writes `tensors` (sorted by name) with `metadata` to `path` atomically, creating the
/// parent folder.
pub fn save(
    path: &Path,
    tensors: &[(String, Tensor)],
    metadata: HashMap<String, String>,
) -> Result<(), CheckpointError> {
    let mut sorted: Vec<(&str, &Tensor)> = tensors.iter().map(|(k, t)| (k.as_str(), t)).collect();
    sorted.sort_by(|a, b| a.0.cmp(b.0));
    let bytes = safetensors::serialize(sorted, Some(metadata))
        .map_err(|e| format_err(path, format!("serialising: {e}")))?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| CheckpointError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    write_atomic(path, &bytes).map_err(|source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Writes `bytes` to a temporary file in `path`'s folder, syncs it and renames it over `path`,
/// so a reader sees the old file or the whole new one, never part of it; the temporary file is
/// removed on any failure (and on unwinding). Like `ic_geometry::io::write_atomic_with`, a
/// `path` that is a link, device, FIFO, socket or folder is refused
/// ([`std::io::ErrorKind::InvalidInput`]), checked before writing and again before the rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let file_name = path.file_name().ok_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "the output path has no file name",
        )
    })?;
    check_replaceable(path)?;
    let mut prefix = std::ffi::OsString::from(".");
    prefix.push(file_name);
    prefix.push(".");
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix).suffix(".tmp");
    // The mode of a file created the usual way (0666 less the umask), not tempfile's 0600.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let mut tmp = builder.tempfile_in(dir)?;
    {
        let mut out = std::io::BufWriter::new(tmp.as_file_mut());
        out.write_all(bytes)?;
        out.flush()?;
    }
    tmp.as_file().sync_all()?;
    check_replaceable(path)?;
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}

/// An error unless `path` is absent or a regular file (what a rename may replace).
fn check_replaceable(path: &Path) -> std::io::Result<()> {
    match std::fs::symlink_metadata(path) {
        Ok(meta) if !meta.file_type().is_file() => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "refusing to replace a link, device, FIFO, socket or folder with a file",
        )),
        _ => Ok(()),
    }
}

/// The string metadata of a safetensors file (reads only its header).
pub fn read_metadata(path: &Path) -> Result<HashMap<String, String>, CheckpointError> {
    let mut f = std::fs::File::open(path).map_err(|source| CheckpointError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|_| format_err(path, "not a safetensors file (too short)"))?;
    let len = u64::from_le_bytes(len);
    if len > 100_000_000 {
        return Err(format_err(path, "not a safetensors file (header size)"));
    }
    let mut header = vec![0u8; len as usize];
    f.read_exact(&mut header)
        .map_err(|_| format_err(path, "truncated safetensors header"))?;
    let json: serde_json::Value = serde_json::from_slice(&header)
        .map_err(|e| format_err(path, format!("bad safetensors header: {e}")))?;
    let mut out = HashMap::new();
    if let Some(meta) = json.get("__metadata__").and_then(|m| m.as_object()) {
        for (k, v) in meta {
            if let Some(s) = v.as_str() {
                out.insert(k.clone(), s.to_string());
            }
        }
    }
    Ok(out)
}

/// The variables of `map`, detached, by name (what a checkpoint stores).
pub fn varmap_tensors(map: &candle_nn::VarMap) -> Vec<(String, Tensor)> {
    map.data()
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
        .collect()
}

/// Sets every variable of `map` from `tensors` (read from `path`).
///
/// Errors: a variable missing from the file or stored with another shape.
pub fn load_into_varmap(
    map: &candle_nn::VarMap,
    tensors: &HashMap<String, Tensor>,
    path: &Path,
) -> Result<(), CheckpointError> {
    let data = map.data().lock().unwrap_or_else(|e| e.into_inner());
    for (name, var) in data.iter() {
        let t = tensors
            .get(name)
            .ok_or_else(|| format_err(path, format!("missing tensor {name}")))?;
        if t.shape() != var.shape() {
            return Err(format_err(
                path,
                format!("{name}: shape {:?}, expected {:?}", t.shape(), var.shape()),
            ));
        }
        var.set(t)
            .map_err(|e| format_err(path, format!("{name}: {e}")))?;
    }
    Ok(())
}

/// Every tensor of the safetensors file `path`, on `device`.
pub fn load_tensors(
    path: &Path,
    device: &candle_core::Device,
) -> Result<HashMap<String, Tensor>, CheckpointError> {
    candle_core::safetensors::load(path, device).map_err(|e| format_err(path, e.to_string()))
}

/// Restores a training checkpoint written with `varmap_tensors` + `Adam::state`: the
/// variables of `map` and Adam's moments at step `adam_step`.
pub fn restore_training(
    path: &Path,
    map: &candle_nn::VarMap,
    adam: &mut crate::adam::Adam,
    adam_step: u64,
    device: &candle_core::Device,
) -> Result<(), CheckpointError> {
    let tensors = load_tensors(path, device)?;
    load_into_varmap(map, &tensors, path)?;
    adam.load_state(&tensors, adam_step)
        .map_err(|e| format_err(path, e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn save_then_read_metadata_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/ck.safetensors");
        let t = Tensor::new(&[1f32, 2.0, 3.0], &Device::Cpu).unwrap();
        let meta = HashMap::from([("k".to_string(), "v".to_string())]);
        save(&path, &[("w".into(), t)], meta.clone()).unwrap();
        assert_eq!(read_metadata(&path).unwrap(), meta);
        let loaded = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
        assert_eq!(loaded["w"].to_vec1::<f32>().unwrap(), vec![1.0, 2.0, 3.0]);
    }

    #[test]
    fn garbage_file_is_a_format_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.safetensors");
        std::fs::write(&path, b"\xff\xff\xff\xff\xff\xff\xff\x7fjunk").unwrap();
        let e = read_metadata(&path).unwrap_err();
        assert!(matches!(e, CheckpointError::Format { .. }));
        assert!(e.to_string().contains("bad.safetensors"), "{e}");
    }

    #[test]
    fn save_refuses_to_replace_a_folder_and_leaves_no_temporary_file() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("ckpt.safetensors");
        std::fs::create_dir(&target).unwrap();
        let err = save(&target, &[], HashMap::new()).unwrap_err();
        assert!(err.to_string().contains("ckpt.safetensors"), "{err}");
        let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "only the folder: {names:?}");
    }

    #[cfg(unix)]
    #[test]
    fn saved_file_has_the_mode_of_an_ordinary_new_file() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let plain = dir.path().join("plain");
        std::fs::write(&plain, b"x").unwrap();
        let path = dir.path().join("ckpt.safetensors");
        save(&path, &[], HashMap::new()).unwrap();
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&path), mode(&plain));
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }
}
