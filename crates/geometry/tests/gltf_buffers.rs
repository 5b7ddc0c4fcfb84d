//! Where glTF buffers may come from: external buffer files must stay inside the model's folder
//! and be regular files; `data:` URIs and percent-encoded file names keep working.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use ic_geometry::io::{load_mesh, read_gltf};
use ic_geometry::{Mesh, MeshError};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/meshes")
        .join(name)
}

/// `two_nodes.gltf`: two meshes sharing one 44-byte buffer, embedded as a data URI.
fn fixture_json() -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(fixture("two_nodes.gltf")).unwrap()).unwrap()
}

/// The 44 bytes the fixture embeds: 3 float positions and 3 u16 indices (+2 padding).
fn fixture_buffer() -> Vec<u8> {
    let mut b = Vec::new();
    for v in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0] {
        b.extend_from_slice(&i.to_le_bytes());
    }
    b
}

/// Writes `dir/name` as the fixture with its buffer URI replaced by `uri`.
fn write_gltf(dir: &Path, name: &str, uri: &str) -> PathBuf {
    let mut json = fixture_json();
    json["buffers"][0]["uri"] = uri.into();
    let path = dir.join(name);
    std::fs::write(&path, serde_json::to_vec(&json).unwrap()).unwrap();
    path
}

/// [`load_mesh`], aborting the whole test process if it has not returned after 10 s: a loader
/// that follows a URI to `/dev/zero` or a FIFO would otherwise read (and allocate) forever.
fn load_within_10_s(path: &Path) -> Result<Mesh, MeshError> {
    let (tx, rx) = mpsc::channel();
    let owned = path.to_path_buf();
    std::thread::spawn(move || {
        let _ = tx.send(load_mesh(&owned));
    });
    match rx.recv_timeout(Duration::from_secs(10)) {
        Ok(result) => result,
        Err(mpsc::RecvTimeoutError::Disconnected) => panic!("loading {} panicked", path.display()),
        Err(mpsc::RecvTimeoutError::Timeout) => {
            eprintln!("loading {} did not finish within 10 s", path.display());
            std::process::abort();
        }
    }
}

/// The error of loading `path`: a [`MeshError::Format`] naming the file, whose message is
/// returned.
fn refused(path: &Path) -> String {
    let e = load_within_10_s(path).expect_err("the file must be refused");
    assert!(matches!(e, MeshError::Format { .. }), "{e:?}");
    assert_eq!(e.path(), path);
    let s = e.to_string();
    assert!(s.contains(&path.display().to_string()), "{s}");
    s
}

#[test]
fn gltf_buffer_uri_outside_the_model_folder_is_refused() {
    let root = tempfile::tempdir().unwrap();
    let folder = root.path().join("model");
    std::fs::create_dir(&folder).unwrap();
    // A valid buffer, but next to the folder rather than in it.
    std::fs::write(root.path().join("outside.bin"), fixture_buffer()).unwrap();
    let path = write_gltf(&folder, "scene.gltf", "../outside.bin");
    let s = refused(&path);
    assert!(
        s.contains("buffer 0")
            && s.contains("\"../outside.bin\" points outside the model's folder"),
        "{s}"
    );
    // Percent-encoded dots climb just the same.
    let path = write_gltf(&folder, "encoded.gltf", "%2E%2E/outside.bin");
    assert!(refused(&path).contains("outside the model's folder"));
}

#[test]
fn gltf_buffer_uri_climbing_to_dev_zero_is_refused_without_reading_it() {
    let folder = tempfile::tempdir().unwrap();
    let climb = "../".repeat(64);
    let path = write_gltf(folder.path(), "zero.gltf", &format!("{climb}dev/zero"));
    let start = std::time::Instant::now();
    let s = refused(&path);
    assert!(s.contains("outside the model's folder"), "{s}");
    // Refused from the URI alone: nothing was opened, let alone read.
    assert!(
        start.elapsed() < Duration::from_secs(1),
        "{:?}",
        start.elapsed()
    );
}

#[test]
fn gltf_absolute_and_file_scheme_buffer_uris_are_refused() {
    let elsewhere = tempfile::tempdir().unwrap();
    let bin = elsewhere.path().join("buffer.bin");
    std::fs::write(&bin, fixture_buffer()).unwrap();
    let folder = tempfile::tempdir().unwrap();
    let absolute = bin.to_str().unwrap().replace('\\', "/");
    let path = write_gltf(folder.path(), "absolute.gltf", &absolute);
    let s = refused(&path);
    assert!(s.contains("absolute path"), "{s}");
    let path = write_gltf(folder.path(), "file.gltf", &format!("file://{absolute}"));
    let s = refused(&path);
    assert!(s.contains("has a scheme"), "{s}");
    let path = write_gltf(folder.path(), "http.gltf", "http://example.com/buffer.bin");
    assert!(refused(&path).contains("has a scheme"));
}

#[cfg(unix)]
#[test]
fn gltf_buffer_symlink_to_dev_zero_is_refused() {
    let folder = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink("/dev/zero", folder.path().join("zero.bin")).unwrap();
    let path = write_gltf(folder.path(), "scene.gltf", "zero.bin");
    let s = refused(&path);
    assert!(s.contains("buffer 0") && s.contains("zero.bin"), "{s}");
}

#[cfg(unix)]
#[test]
fn gltf_buffer_that_is_a_fifo_is_refused_without_opening_it() {
    let folder = tempfile::tempdir().unwrap();
    let fifo = folder.path().join("pipe.bin");
    match std::process::Command::new("mkfifo").arg(&fifo).status() {
        Ok(status) if status.success() => {}
        other => {
            eprintln!("skipped: mkfifo is not available ({other:?})");
            return;
        }
    }
    // Opening a FIFO without a writer blocks: the loader must look at the file type first.
    let path = write_gltf(folder.path(), "scene.gltf", "pipe.bin");
    let s = refused(&path);
    assert!(
        s.contains("not a regular file") && s.contains("FIFO"),
        "{s}"
    );
}

#[test]
fn gltf_percent_encoded_buffer_names_load_and_non_utf8_ones_are_errors() {
    let folder = tempfile::tempdir().unwrap();
    std::fs::write(folder.path().join("my mesh.bin"), fixture_buffer()).unwrap();
    let path = write_gltf(folder.path(), "scene.gltf", "my%20mesh.bin");
    assert_eq!(
        load_within_10_s(&path).unwrap(),
        load_mesh(fixture("two_nodes.gltf")).unwrap()
    );
    // Percent-decoding to bytes that are not UTF-8 is an error (it used to panic).
    let path = write_gltf(folder.path(), "latin1.gltf", "my%A0mesh.bin");
    let s = refused(&path);
    assert!(s.contains("not UTF-8"), "{s}");
}

#[test]
fn gltf_data_uri_buffers_load_with_either_media_type() {
    let expected = load_mesh(fixture("two_nodes.gltf")).unwrap();
    let mut json = fixture_json();
    let uri = json["buffers"][0]["uri"].as_str().unwrap().to_string();
    assert!(uri.starts_with("data:application/octet-stream;base64,"));
    for prefix in [
        "data:application/octet-stream;base64,",
        "data:application/gltf-buffer;base64,",
    ] {
        json["buffers"][0]["uri"] = uri
            .replacen("data:application/octet-stream;base64,", prefix, 1)
            .into();
        let bytes = serde_json::to_vec(&json).unwrap();
        assert_eq!(
            read_gltf(&bytes, None, Path::new("embedded.gltf")).unwrap(),
            expected
        );
    }
    // Data shorter than the declared byteLength is an error naming the file and buffer.
    json["buffers"][0]["byteLength"] = 48.into();
    let bytes = serde_json::to_vec(&json).unwrap();
    let e = read_gltf(&bytes, None, Path::new("short.gltf")).unwrap_err();
    let s = e.to_string();
    assert!(matches!(e, MeshError::Format { .. }), "{e:?}");
    assert!(
        s.contains("short.gltf") && s.contains("buffer 0") && s.contains("48"),
        "{s}"
    );
    // Not base64.
    json["buffers"][0]["byteLength"] = 44.into();
    json["buffers"][0]["uri"] = "data:application/octet-stream,AAAA".into();
    let bytes = serde_json::to_vec(&json).unwrap();
    let e = read_gltf(&bytes, None, Path::new("plain.gltf")).unwrap_err();
    assert!(e.to_string().contains("not base64"), "{e}");
}

#[test]
fn gltf_external_buffers_need_the_model_folder() {
    let bytes = serde_json::to_vec(&{
        let mut json = fixture_json();
        json["buffers"][0]["uri"] = "data.bin".into();
        json
    })
    .unwrap();
    let e = read_gltf(&bytes, None, Path::new("memory.gltf")).unwrap_err();
    assert!(matches!(e, MeshError::Format { .. }), "{e:?}");
    assert!(e.to_string().contains("folder is unknown"), "{e}");
}
