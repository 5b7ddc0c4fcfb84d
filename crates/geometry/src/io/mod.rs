//! Mesh and point-cloud file formats.
//!
//! Reading: [`load_mesh`](crate::io::load_mesh) picks the reader from the file extension
//! (case-insensitive): `.obj` ([`read_obj`](crate::io::read_obj)), `.off`
//! ([`read_off`](crate::io::read_off)), `.ply` ([`read_ply`](crate::io::read_ply)), `.gltf` and
//! `.glb` ([`read_gltf`](crate::io::read_gltf)). Point clouds are read back from PLY with
//! [`read_ply_cloud`](crate::io::read_ply_cloud).
//!
//! Writing: [`write_ply`](crate::io::write_ply) (point cloud, optionally with normals and
//! colours) and [`write_mesh_ply`](crate::io::write_mesh_ply) (vertices and triangles). Writes
//! are atomic: the data goes to a temporary file in the target directory, which is renamed over
//! the target only once complete.
//!
//! Units: coordinates are returned exactly as stored in the file (after the node transforms of
//! a glTF scene); nothing is scaled or centred at load time — see [`crate::Mesh::normalise`].
//!
//! Every reader returns a [`MeshError`] naming the file and, where known, the line (text
//! formats) or the element ("vertex 3", "face 12"). No input bytes make them panic, and no
//! count read from a header is trusted for allocation beyond what the file could hold.

mod gltf;
mod obj;
mod off;
mod ply;

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use crate::{Mesh, MeshDataError, MeshError};

pub use self::gltf::read_gltf;
pub use self::obj::read_obj;
pub use self::off::read_off;
pub use self::ply::{
    read_ply, read_ply_cloud, read_ply_points, write_mesh_ply, write_mesh_ply_to, write_ply,
    write_ply_to,
};

/// The payload encoding of a PLY file that we write.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum PlyEncoding {
    /// Human-readable text; floats are written in their shortest exact decimal form, so they
    /// read back bit-identical.
    Ascii,
    /// Binary, little-endian (the most widely supported binary flavour).
    #[default]
    BinaryLittleEndian,
    /// Binary, big-endian.
    BinaryBigEndian,
}

/// Loads a triangle mesh, choosing the format from the extension of `path` (case-insensitive):
/// `.obj`, `.off`, `.ply`, `.gltf` or `.glb`.
///
/// Polygons are fan-triangulated. Coordinates are in the file's own units (no scaling). For
/// glTF, all triangle primitives of all nodes of the default scene are merged, each with its
/// node's world transform applied.
///
/// # Errors
/// [`MeshError::UnsupportedFormat`] for any other extension; [`MeshError::Io`] when the file
/// cannot be read; otherwise the errors of the format's reader.
pub fn load_mesh(path: impl AsRef<Path>) -> Result<Mesh, MeshError> {
    let path = path.as_ref();
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match extension.as_str() {
        "obj" => read_obj(open(path)?, path),
        "off" => read_off(open(path)?, path),
        "ply" => read_ply(open(path)?, path),
        "gltf" | "glb" => {
            let bytes = std::fs::read(path).map_err(|e| io_error(path, e))?;
            read_gltf(&bytes, path.parent(), path)
        }
        _ => Err(MeshError::UnsupportedFormat {
            path: path.to_path_buf(),
            extension,
        }),
    }
}

fn open(path: &Path) -> Result<std::fs::File, MeshError> {
    std::fs::File::open(path).map_err(|e| io_error(path, e))
}

pub(crate) fn io_error(path: &Path, source: std::io::Error) -> MeshError {
    MeshError::Io {
        path: path.to_path_buf(),
        source,
    }
}

pub(crate) fn parse_error(path: &Path, line: usize, message: impl Into<String>) -> MeshError {
    MeshError::Parse {
        path: path.to_path_buf(),
        line,
        message: message.into(),
    }
}

pub(crate) fn format_error(path: &Path, message: impl Into<String>) -> MeshError {
    MeshError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

pub(crate) fn data_error(path: &Path, source: MeshDataError) -> MeshError {
    MeshError::Data {
        path: path.to_path_buf(),
        source,
    }
}

/// Reads everything from `reader`.
pub(crate) fn read_all(mut reader: impl Read, path: &Path) -> Result<Vec<u8>, MeshError> {
    let mut bytes = Vec::new();
    reader
        .read_to_end(&mut bytes)
        .map_err(|e| io_error(path, e))?;
    Ok(bytes)
}

/// Writes `path` atomically: `write` fills a temporary file next to `path`, which is flushed,
/// synced and then renamed over `path`. On any failure the temporary file is removed and
/// `path` is left untouched, so a crash never leaves a half-written file behind.
///
/// Generic over the caller's error type: `io_error` turns the I/O failures of the temporary
/// file into it (every crate that writes files uses this one function).
pub fn write_atomic_with<E>(
    path: &Path,
    write: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> Result<(), E>,
    io_error: impl Fn(std::io::Error) -> E,
) -> Result<(), E> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);

    let file_name = path.file_name().ok_or_else(|| {
        io_error(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "the output path has no file name",
        ))
    })?;
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let (file, tmp) = loop {
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let mut name = std::ffi::OsString::from(".");
        name.push(file_name);
        name.push(format!(".{}.{n}.tmp", std::process::id()));
        let tmp = dir.join(name);
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => break (f, tmp),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(io_error(e)),
        }
    };
    let result = (|| {
        let mut out = std::io::BufWriter::new(file);
        write(&mut out)?;
        let file = out.into_inner().map_err(|e| io_error(e.into_error()))?;
        file.sync_all().map_err(&io_error)?;
        drop(file);
        std::fs::rename(&tmp, path).map_err(&io_error)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// [`write_atomic_with`] for the mesh and cloud writers of this module.
pub(crate) fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<(), MeshError> {
    write_atomic_with(
        path,
        |w| write(w).map_err(|e| io_error(path, e)),
        |e| io_error(path, e),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn io_unsupported_extension_names_the_file_and_extension() {
        let err = load_mesh("models/chair.STL").unwrap_err();
        match &err {
            MeshError::UnsupportedFormat { path, extension } => {
                assert_eq!(path, Path::new("models/chair.STL"));
                assert_eq!(extension, "stl");
            }
            other => panic!("unexpected {other:?}"),
        }
        assert!(err.to_string().contains("chair.STL"));
        assert!(matches!(
            load_mesh("no_extension"),
            Err(MeshError::UnsupportedFormat { .. })
        ));
    }

    #[test]
    fn io_missing_file_is_an_io_error_with_the_path() {
        let err = load_mesh("/definitely/not/here.off").unwrap_err();
        assert!(matches!(err, MeshError::Io { .. }));
        assert_eq!(err.path(), Path::new("/definitely/not/here.off"));
    }

    #[test]
    fn io_atomic_write_leaves_no_temporary_file_on_failure() {
        let dir =
            std::env::temp_dir().join(format!("ic_geometry_io_atomic_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let target = dir.join("out.bin");
        std::fs::write(&target, b"old").unwrap();
        let err = write_atomic(&target, |w| {
            w.write_all(b"partial")?;
            Err(std::io::Error::other("disk full"))
        });
        assert!(err.is_err());
        assert_eq!(std::fs::read(&target).unwrap(), b"old");
        let leftovers: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(leftovers.len(), 1, "{leftovers:?}");
        write_atomic(&target, |w| w.write_all(b"new")).unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"new");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
