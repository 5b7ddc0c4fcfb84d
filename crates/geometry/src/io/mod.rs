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
            let bytes = read_bounded(path, MAX_MESH_FILE_BYTES).map_err(|e| io_error(path, e))?;
            read_gltf(&bytes, path.parent(), path)
        }
        _ => Err(MeshError::UnsupportedFormat {
            path: path.to_path_buf(),
            extension,
        }),
    }
}

fn open(path: &Path) -> Result<std::io::Take<std::fs::File>, MeshError> {
    open_regular(path, MAX_MESH_FILE_BYTES).map_err(|e| io_error(path, e))
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

/// The largest mesh file [`load_mesh`] reads (2 GiB): far above the largest scans in use
/// (≈ 300 MB), and a bound on what a hostile or mistaken path can make us read.
pub const MAX_MESH_FILE_BYTES: u64 = 2 << 30;

/// Opens `path` for reading only when it is a regular file (after following symbolic links) of
/// at most `max_bytes` bytes, and returns a reader that stops after `max_bytes + 1` bytes (a
/// file that grows while it is read is still bounded: see [`read_bounded`]).
///
/// Device nodes (`/dev/zero`, `/dev/urandom`), FIFOs, sockets and folders are refused with an
/// [`std::io::ErrorKind::InvalidInput`] error saying what the path is; a file above the limit
/// with [`std::io::ErrorKind::FileTooLarge`]. Messages do not repeat the path: callers name it.
pub fn open_regular(path: &Path, max_bytes: u64) -> std::io::Result<std::io::Take<std::fs::File>> {
    let meta = std::fs::metadata(path)?;
    check_regular(&meta, max_bytes)?;
    let file = std::fs::File::open(path)?;
    // Checked again on the open handle: the path may have been swapped in between.
    check_regular(&file.metadata()?, max_bytes)?;
    Ok(file.take(max_bytes.saturating_add(1)))
}

fn check_regular(meta: &std::fs::Metadata, max_bytes: u64) -> std::io::Result<()> {
    let ft = meta.file_type();
    if !ft.is_file() {
        let what = describe_file_type(&ft);
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("not a regular file ({what})"),
        ));
    }
    if meta.len() > max_bytes {
        return Err(too_large(meta.len(), max_bytes));
    }
    Ok(())
}

/// What a non-regular file is, for messages: "a symbolic link", "a folder", "a character
/// device", "a block device", "a FIFO", "a socket" or "a special file".
pub fn describe_file_type(ft: &std::fs::FileType) -> &'static str {
    if ft.is_symlink() {
        "a symbolic link"
    } else if ft.is_dir() {
        "a folder"
    } else {
        file_type_name(ft)
    }
}

#[cfg(unix)]
fn file_type_name(ft: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if ft.is_char_device() {
        "a character device"
    } else if ft.is_block_device() {
        "a block device"
    } else if ft.is_fifo() {
        "a FIFO"
    } else if ft.is_socket() {
        "a socket"
    } else {
        "a special file"
    }
}

#[cfg(not(unix))]
fn file_type_name(_: &std::fs::FileType) -> &'static str {
    "a special file"
}

fn too_large(len: u64, max_bytes: u64) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::FileTooLarge,
        format!(
            "the file is too large ({} bytes; at most {} bytes are read)",
            len, max_bytes
        ),
    )
}

/// Reads a whole regular file of at most `max_bytes` bytes ([`open_regular`]); a file that
/// grew past the limit while being read is refused too.
pub fn read_bounded(path: &Path, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    let mut reader = open_regular(path, max_bytes)?;
    let mut bytes = Vec::new();
    reader.read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(too_large(bytes.len() as u64, max_bytes));
    }
    Ok(bytes)
}

/// Reads everything from `reader`.
pub(crate) fn read_all(mut reader: impl Read, path: &Path) -> Result<Vec<u8>, MeshError> {
    let mut bytes = Vec::new();
    reader
        .read_to_end(&mut bytes)
        .map_err(|e| io_error(path, e))?;
    if bytes.len() as u64 > MAX_MESH_FILE_BYTES {
        return Err(io_error(
            path,
            too_large(bytes.len() as u64, MAX_MESH_FILE_BYTES),
        ));
    }
    Ok(bytes)
}

/// Temporary files of the writes in flight ([`write_atomic_with`]); renames happen under this
/// lock, so [`abandon_pending_writes`] sees every temporary file that may still be renamed.
static PENDING: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

fn pending() -> std::sync::MutexGuard<'static, Vec<PathBuf>> {
    PENDING.lock().unwrap_or_else(|e| e.into_inner())
}

/// Held while the process exits after a signal: no write in flight can rename its temporary
/// file into place any more.
pub struct PendingWritesGuard {
    _lock: std::sync::MutexGuard<'static, Vec<PathBuf>>,
}

/// For a signal handler that is about to exit the process (e.g. on Ctrl-C or SIGTERM): removes
/// the temporary file of every [`write_atomic_with`] in flight and returns a guard that stops
/// them from renaming anything; exit while holding it. Files already renamed stay complete;
/// none is left half-written and no temporary file is left behind. Not async-signal-safe: call
/// it from a handler that runs on an ordinary thread (the `ctrlc` crate's).
pub fn abandon_pending_writes() -> PendingWritesGuard {
    let mut lock = pending();
    for tmp in lock.drain(..) {
        let _ = std::fs::remove_file(tmp);
    }
    PendingWritesGuard { _lock: lock }
}

/// Fault injection for tests: `INCONTEXT_TEST_WRITE_DELAY_MS=N` sleeps N ms between writing a
/// temporary file and renaming it, so a test can interrupt a write in flight.
fn test_write_delay() -> Option<std::time::Duration> {
    static DELAY: std::sync::OnceLock<Option<std::time::Duration>> = std::sync::OnceLock::new();
    *DELAY.get_or_init(|| {
        std::env::var("INCONTEXT_TEST_WRITE_DELAY_MS")
            .ok()
            .and_then(|v| v.parse::<u64>().ok())
            .map(std::time::Duration::from_millis)
    })
}

/// Creates the folder that will hold `path` (and its parents) when missing; nothing for a bare
/// file name. The writers that create their output's folder call this before
/// [`write_atomic_with`], which itself never creates folders.
pub fn create_parent_dir(path: &Path) -> std::io::Result<()> {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => std::fs::create_dir_all(dir),
        _ => Ok(()),
    }
}

/// Writes `path` atomically: `write` fills a temporary file next to `path`, which is flushed,
/// synced and then renamed over `path`. On any failure the temporary file is removed and
/// `path` is left untouched, so a crash never leaves a half-written file behind (and
/// [`abandon_pending_writes`] removes the temporary file when the process is interrupted).
///
/// An existing `path` must be a regular file: a symbolic link, device node (`/dev/null`),
/// FIFO, socket or folder is refused ([`std::io::ErrorKind::InvalidInput`]), since the rename
/// would replace it.
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
    check_replaceable(path).map_err(&io_error)?;
    let (file, tmp) = loop {
        let n = COUNTER.fetch_add(1, Ordering::Relaxed);
        let mut name = std::ffi::OsString::from(".");
        name.push(file_name);
        name.push(format!(".{}.{n}.tmp", std::process::id()));
        let tmp = dir.join(name);
        // The temporary file is created and recorded under one lock: a signal handler that
        // abandons the pending writes either runs first (and holds the lock until the process
        // exits, so no file is created) or sees this one.
        let mut lock = pending();
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => {
                lock.push(tmp.clone());
                break (f, tmp);
            }
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
        if let Some(delay) = test_write_delay() {
            std::thread::sleep(delay);
        }
        let mut lock = pending();
        // Checked again just before the rename: the path may have changed meanwhile.
        let renamed = check_replaceable(path)
            .and_then(|_| std::fs::rename(&tmp, path))
            .map_err(&io_error);
        lock.retain(|p| p != &tmp);
        if renamed.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        renamed
    })();
    if result.is_err() {
        let mut lock = pending();
        let _ = std::fs::remove_file(&tmp);
        lock.retain(|p| p != &tmp);
    }
    result
}

/// Fails when `path` exists and is not a regular file (see [`write_atomic_with`]).
fn check_replaceable(path: &Path) -> std::io::Result<()> {
    match std::fs::symlink_metadata(path) {
        Ok(meta) if !meta.file_type().is_file() => {
            let what = describe_file_type(&meta.file_type());
            Err(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("refusing to replace {what} with a file"),
            ))
        }
        _ => Ok(()),
    }
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
