//! glTF 2.0 (`.gltf` with embedded or external buffers, and binary `.glb`).
//!
//! The document is parsed with the `gltf` crate. Buffers are loaded here ([`load_buffers`]):
//! external buffer files must lie inside the model's folder and are read with a size bound, so
//! that a hostile URI can neither escape the folder nor make us read a device such as
//! `/dev/zero`. Accessors are decoded with checked arithmetic, so that a malformed file gives an
//! error rather than a panic.

use std::path::{Component, Path, PathBuf};

use ::gltf::accessor::{DataType, Dimensions};
use ::gltf::mesh::{Mode, Semantic};
use glam::{DMat4, Vec3};

use super::{data_error, format_error};
use crate::{Mesh, MeshError};

/// Reads a glTF or GLB mesh from `bytes`; `path` is only used in error messages and
/// `base_dir` resolves external buffer files (`None`: only embedded `data:` URIs and the GLB
/// binary chunk are allowed). External buffers must be relative URIs (percent-encoded) of regular
/// files inside `base_dir`, symbolic links resolved; absolute paths, `file:`/`http:` URIs and
/// `..` leading out of `base_dir` are refused. Images are not loaded.
///
/// Every primitive of every mesh reachable from the default scene (or the first scene; or, with
/// no scenes at all, every mesh untransformed) is merged, with its node's world transform
/// (product of the node matrices / TRS from the root) applied. Only `TRIANGLES` primitives are
/// accepted; both indexed and non-indexed ones. Positions must be `VEC3` of `FLOAT`. Units are
/// the file's (glTF specifies metres, but nothing is rescaled). Under a mirroring transform
/// (negative determinant) triangle order is swapped so faces stay counter-clockwise.
///
/// # Errors
/// [`MeshError::Format`] naming the mesh/primitive for invalid JSON/GLB containers, buffers that
/// cannot be loaded or are refused (named `buffer <index>`), out-of-bounds buffer views,
/// unsupported modes, accessor types and sparse accessors, index counts not a multiple of three, out-of-range indices, non-finite transformed vertices and node
/// graphs that are not trees; [`MeshError::Data`] when there are no triangles.
pub fn read_gltf(bytes: &[u8], base_dir: Option<&Path>, path: &Path) -> Result<Mesh, MeshError> {
    let fail = |m: String| format_error(path, m);
    check_glb_header(bytes).map_err(fail)?;
    let gltf = ::gltf::Gltf::from_slice_without_validation(bytes)
        .map_err(|e| fail(format!("invalid glTF: {e}")))?;
    let ::gltf::Gltf { document, blob } = gltf;
    validate(document.as_json()).map_err(fail)?;
    let buffers = load_buffers(&document, base_dir, blob).map_err(fail)?;
    let buffers: Vec<&[u8]> = buffers.iter().map(|b| &b[..]).collect();

    let mut out = Mesh::default();
    let scene = document
        .default_scene()
        .or_else(|| document.scenes().next());
    match scene {
        Some(scene) => {
            let node_count = document.nodes().count();
            let mut visited = vec![false; node_count];
            // Depth-first in document order: the stack holds siblings reversed.
            let mut stack: Vec<(::gltf::Node, DMat4)> =
                scene.nodes().map(|n| (n, DMat4::IDENTITY)).collect();
            stack.reverse();
            while let Some((node, parent)) = stack.pop() {
                let seen = visited
                    .get_mut(node.index())
                    .ok_or_else(|| fail(format!("node {} does not exist", node.index())))?;
                if *seen {
                    return Err(fail(format!(
                        "node {} is reached twice: the node hierarchy is not a tree",
                        node.index()
                    )));
                }
                *seen = true;
                let local =
                    DMat4::from_cols_array_2d(&node.transform().matrix().map(|c| c.map(f64::from)));
                let world = parent * local;
                if let Some(mesh) = node.mesh() {
                    append_mesh(&mut out, &mesh, &world, &buffers, path)?;
                }
                let first_child = stack.len();
                stack.extend(node.children().map(|c| (c, world)));
                stack[first_child..].reverse();
            }
        }
        None => {
            for mesh in document.meshes() {
                append_mesh(&mut out, &mesh, &DMat4::IDENTITY, &buffers, path)?;
            }
        }
    }
    out.validate().map_err(|e| data_error(path, e))?;
    Ok(out)
}

/// The bytes of every buffer of `document`, in order, replacing `gltf::import_buffers` (which
/// follows any path, absolute or `../`, and reads it unbounded: `"uri": "../../dev/zero"` never
/// returned). Sources:
///
/// - the GLB binary chunk `blob`, for a buffer without URI (only one buffer can use it);
/// - a `data:` URI with base64 payload (`data:application/octet-stream;base64,…`,
///   `data:application/gltf-buffer;base64,…`; any media type is accepted);
/// - a relative URI reference, percent-decoded (`my%20mesh.bin` is `my mesh.bin`), resolved
///   against `base_dir` ([`resolve_buffer_file`]) and read with
///   [`read_bounded`](super::read_bounded): regular files only, and at most
///   [`MAX_MESH_FILE_BYTES`](super::MAX_MESH_FILE_BYTES) for all external buffers together (a
///   model cannot make us hold more by naming the same large file many times).
///
/// Each buffer must hold at least its declared `byteLength` bytes (more is allowed: padding).
///
/// # Errors
/// A message starting with `buffer <index>:` when the GLB chunk is missing, a data URI is not
/// base64, a URI has a scheme other than `data:` (`http:`, `file:`, a drive letter …), is
/// absolute, is not UTF-8 once percent-decoded, points outside `base_dir` (also through
/// symbolic links) or is external while `base_dir` is `None`; when the file cannot be read or
/// is not a regular file; and when the data is shorter than `byteLength`.
fn load_buffers(
    document: &::gltf::Document,
    base_dir: Option<&Path>,
    mut blob: Option<Vec<u8>>,
) -> Result<Vec<Vec<u8>>, String> {
    use ::gltf::buffer::Source;
    let mut buffers = Vec::new();
    let mut budget = super::MAX_MESH_FILE_BYTES;
    for buffer in document.buffers() {
        let i = buffer.index();
        let data = match buffer.source() {
            Source::Bin => blob.take().ok_or_else(|| {
                format!("buffer {i}: refers to the GLB binary chunk, but there is none")
            })?,
            Source::Uri(uri) => match uri.strip_prefix("data:") {
                Some(data) => decode_data_uri(data).map_err(|e| format!("buffer {i}: {e}"))?,
                None => {
                    let base_dir = base_dir.ok_or_else(|| {
                        format!(
                            "buffer {i}: the external URI \"{}\" cannot be resolved: the \
                             model's folder is unknown",
                            shown(uri)
                        )
                    })?;
                    let file = resolve_buffer_file(base_dir, uri)
                        .map_err(|e| format!("buffer {i}: {e}"))?;
                    let data = super::read_bounded(&file, budget).map_err(|e| {
                        let why = if e.kind() == std::io::ErrorKind::FileTooLarge {
                            format!(
                                "{e}; all external buffers together may hold at most {} bytes",
                                super::MAX_MESH_FILE_BYTES
                            )
                        } else {
                            e.to_string()
                        };
                        format!("buffer {i}: cannot read \"{}\": {why}", file.display())
                    })?;
                    budget -= data.len() as u64;
                    data
                }
            },
        };
        if data.len() < buffer.length() {
            return Err(format!(
                "buffer {i}: {} bytes of data, but its byteLength is {}",
                data.len(),
                buffer.length()
            ));
        }
        buffers.push(data);
    }
    Ok(buffers)
}

/// Decodes the part of a `data:` URI after `data:`: `[<media type>][;<parameters>];base64,<data>`.
fn decode_data_uri(rest: &str) -> Result<Vec<u8>, String> {
    let (header, payload) = rest
        .split_once(',')
        .ok_or("the data URI has no ',' before its data")?;
    if !header.ends_with(";base64") {
        return Err(format!(
            "the data URI (\"data:{},…\") is not base64-encoded",
            shown(header)
        ));
    }
    base64::decode(payload).map_err(|e| format!("the data URI is not valid base64: {e}"))
}

/// The file an external buffer URI (a relative URI reference, not `data:`) names: the URI is
/// percent-decoded and joined to `base_dir` (the model's folder; `""` is the working
/// directory), and the result, canonicalised (symbolic links and `..` resolved), must lie inside
/// the canonicalised `base_dir`. URIs with a scheme (`file:`, `http:`, `C:` …) and absolute
/// paths are refused.
fn resolve_buffer_file(base_dir: &Path, uri: &str) -> Result<PathBuf, String> {
    let quoted = shown(uri);
    // RFC 3986: a scheme is the part before a ':' in the first segment.
    let first_segment = uri.split(['/', '?', '#']).next().unwrap_or("");
    if first_segment.contains(':') {
        return Err(format!(
            "the URI \"{quoted}\" has a scheme; only relative paths and data: URIs are read"
        ));
    }
    let relative = String::from_utf8(percent_decode(uri))
        .map_err(|_| format!("the URI \"{quoted}\" is not UTF-8 once percent-decoded"))?;
    let relative = Path::new(&relative);
    if relative.is_absolute() || relative.has_root() {
        return Err(format!(
            "the URI \"{quoted}\" is an absolute path; only paths relative to the model's folder \
             are read"
        ));
    }
    // `..` climbing above the folder is refused before touching the file system; symbolic
    // links are caught below, on the canonical path.
    let mut depth = 0usize;
    for c in relative.components() {
        match c {
            Component::ParentDir => {
                depth = depth.checked_sub(1).ok_or_else(|| outside(&quoted))?;
            }
            Component::Normal(_) => depth += 1,
            _ => {}
        }
    }
    let base_dir = if base_dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        base_dir
    };
    let folder = base_dir.canonicalize().map_err(|e| {
        format!(
            "cannot resolve the model's folder \"{}\": {e}",
            base_dir.display()
        )
    })?;
    let joined = base_dir.join(relative);
    let file = joined.canonicalize().map_err(|e| {
        format!(
            "cannot open the URI \"{quoted}\" (\"{}\"): {e}",
            shown(&joined.to_string_lossy())
        )
    })?;
    if !file.starts_with(&folder) {
        return Err(outside(&quoted));
    }
    Ok(file)
}

fn outside(uri: &str) -> String {
    format!("the URI \"{uri}\" points outside the model's folder")
}

/// `uri` for an error message: at most 200 characters (a hostile one can be megabytes long).
fn shown(uri: &str) -> std::borrow::Cow<'_, str> {
    match uri.char_indices().nth(200) {
        Some((end, _)) => format!("{}…", &uri[..end]).into(),
        None => uri.into(),
    }
}

/// Percent-decodes a URI: `%XY` (two hex digits) becomes the byte `0xXY`; a `%` not followed by
/// two hex digits is kept as it is.
fn percent_decode(uri: &str) -> Vec<u8> {
    let bytes = uri.as_bytes();
    let hex = |b: u8| (b as char).to_digit(16).map(|d| d as u8);
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'%' {
            if let (Some(h), Some(l)) = (
                bytes.get(i + 1).copied().and_then(hex),
                bytes.get(i + 2).copied().and_then(hex),
            ) {
                out.push(h << 4 | l);
                i += 3;
                continue;
            }
        }
        out.push(bytes[i]);
        i += 1;
    }
    out
}

/// gltf 1.4 computes `declared_length - 12` for a GLB without checking it (an overflow panic
/// for lengths below 12), so the header is checked here first.
fn check_glb_header(bytes: &[u8]) -> Result<(), String> {
    if !bytes.starts_with(b"glTF") {
        return Ok(());
    }
    let length = bytes
        .get(8..12)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .ok_or("the GLB header is truncated")?;
    if length < 12 {
        return Err(format!(
            "the GLB header declares a total length of {length} bytes, less than the header itself"
        ));
    }
    Ok(())
}

/// Runs the `gltf` crate's validation, after first checking the one reference its validation
/// dereferences unchecked (gltf-json 1.4 indexes `accessors[POSITION]` directly and panics when
/// it is out of range).
fn validate(root: &::gltf::json::Root) -> Result<(), String> {
    use ::gltf::json::mesh::Semantic as JsonSemantic;
    use ::gltf::json::validation::{Checked, Validate};
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            if let Some(index) = primitive
                .attributes
                .get(&Checked::Valid(JsonSemantic::Positions))
            {
                if index.value() >= root.accessors.len() {
                    return Err(format!(
                        "mesh {m} primitive {p}: POSITION refers to accessor {}, but there are {}",
                        index.value(),
                        root.accessors.len()
                    ));
                }
            }
        }
    }
    let mut errors = Vec::new();
    root.validate(root, ::gltf::json::Path::new, &mut |path, error| {
        if errors.len() < 5 {
            errors.push(format!("{}: {error}", path()));
        }
    });
    if errors.is_empty() {
        Ok(())
    } else {
        Err(format!("invalid glTF: {}", errors.join("; ")))
    }
}

/// The bytes of an accessor's elements: (data from the first element to the end of its view,
/// stride, count). Every element `i < count` lies within `data[i*stride .. i*stride+size]`.
fn accessor_data<'a>(
    accessor: &::gltf::Accessor,
    element_size: usize,
    buffers: &[&'a [u8]],
) -> Result<(&'a [u8], usize, usize), String> {
    if accessor.sparse().is_some() {
        return Err("sparse accessors are not supported".into());
    }
    let view = accessor.view().ok_or("the accessor has no buffer view")?;
    let buffer = buffers
        .get(view.buffer().index())
        .ok_or_else(|| format!("buffer {} is missing", view.buffer().index()))?;
    let stride = view.stride().unwrap_or(element_size);
    if stride < element_size {
        return Err(format!(
            "byte stride {stride} is smaller than the element size {element_size}"
        ));
    }
    let view_end = view
        .offset()
        .checked_add(view.length())
        .filter(|&end| end <= buffer.len())
        .ok_or_else(|| format!("buffer view {} lies outside its buffer", view.index()))?;
    let start = view
        .offset()
        .checked_add(accessor.offset())
        .ok_or("accessor offset overflows")?;
    let count = accessor.count();
    if count > 0 {
        let end = (count - 1)
            .checked_mul(stride)
            .and_then(|n| n.checked_add(start))
            .and_then(|n| n.checked_add(element_size))
            .ok_or("accessor size overflows")?;
        if end > view_end {
            return Err(format!(
                "accessor {} ({count} elements) extends past the end of buffer view {}",
                accessor.index(),
                view.index()
            ));
        }
    }
    let data = if count > 0 {
        &buffer[start..view_end]
    } else {
        &[][..]
    };
    Ok((data, stride, count))
}

fn read_positions(accessor: &::gltf::Accessor, buffers: &[&[u8]]) -> Result<Vec<Vec3>, String> {
    if accessor.data_type() != DataType::F32 || accessor.dimensions() != Dimensions::Vec3 {
        return Err(format!(
            "POSITION must be VEC3 of FLOAT, found {:?} of {:?}",
            accessor.dimensions(),
            accessor.data_type()
        ));
    }
    let (data, stride, count) = accessor_data(accessor, 12, buffers)?;
    Ok((0..count)
        .map(|i| {
            let at = i * stride;
            let f = |k: usize| {
                let b = &data[at + 4 * k..at + 4 * k + 4];
                f32::from_le_bytes([b[0], b[1], b[2], b[3]])
            };
            Vec3::new(f(0), f(1), f(2))
        })
        .collect())
}

fn read_indices(accessor: &::gltf::Accessor, buffers: &[&[u8]]) -> Result<Vec<u32>, String> {
    if accessor.dimensions() != Dimensions::Scalar {
        return Err(format!(
            "indices must be SCALAR, found {:?}",
            accessor.dimensions()
        ));
    }
    let size = match accessor.data_type() {
        DataType::U8 => 1,
        DataType::U16 => 2,
        DataType::U32 => 4,
        other => {
            return Err(format!(
                "indices must be unsigned integers, found {other:?}"
            ));
        }
    };
    let (data, stride, count) = accessor_data(accessor, size, buffers)?;
    Ok((0..count)
        .map(|i| {
            let b = &data[i * stride..i * stride + size];
            match size {
                1 => u32::from(b[0]),
                2 => u32::from(u16::from_le_bytes([b[0], b[1]])),
                _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            }
        })
        .collect())
}

fn append_mesh(
    out: &mut Mesh,
    mesh: &::gltf::Mesh,
    world: &DMat4,
    buffers: &[&[u8]],
    path: &Path,
) -> Result<(), MeshError> {
    for primitive in mesh.primitives() {
        let name = format!("mesh {} primitive {}", mesh.index(), primitive.index());
        let fail = |m: String| format_error(path, format!("{name}: {m}"));
        if primitive.mode() != Mode::Triangles {
            return Err(fail(format!(
                "mode {:?} is not supported (only triangles)",
                primitive.mode()
            )));
        }
        let positions = primitive
            .get(&Semantic::Positions)
            .ok_or_else(|| fail("no POSITION attribute".into()))?;
        let positions = read_positions(&positions, buffers).map_err(fail)?;
        let count = positions.len();
        let indices = match primitive.indices() {
            Some(accessor) => read_indices(&accessor, buffers).map_err(fail)?,
            None => (0..count as u32).collect(),
        };
        if indices.len() % 3 != 0 {
            return Err(fail(format!(
                "{} indices is not a multiple of 3",
                indices.len()
            )));
        }
        let offset = out.vertices.len();
        if offset + count > u32::MAX as usize {
            return Err(fail("more than 2^32 vertices in total".into()));
        }
        for (i, p) in positions.iter().enumerate() {
            let q = world.transform_point3(p.as_dvec3()).as_vec3();
            if !q.is_finite() {
                return Err(fail(format!(
                    "vertex {i} is not finite after the node transform ({q})"
                )));
            }
            out.vertices.push(q);
        }
        // A mirroring transform turns counter-clockwise triangles clockwise: swap to keep them CCW.
        let mirrored = world.determinant() < 0.0;
        for (t, tri) in indices.chunks_exact(3).enumerate() {
            if let Some(&bad) = tri.iter().find(|&&i| i as usize >= count) {
                return Err(fail(format!(
                    "triangle {t} refers to vertex {bad}, but there are {count}"
                )));
            }
            let tri = if mirrored {
                [tri[0], tri[2], tri[1]]
            } else {
                [tri[0], tri[1], tri[2]]
            };
            out.triangles.push(tri.map(|i| i + offset as u32));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_uris_are_shortened_in_messages() {
        let uri = format!("{}/x.bin", "a/".repeat(1_000_000));
        let e = resolve_buffer_file(Path::new(""), &uri).unwrap_err();
        assert!(e.len() < 500, "{} characters", e.len());
        assert_eq!(shown("é.bin"), "é.bin");
    }

    #[test]
    fn percent_decoding_keeps_stray_percent_signs() {
        assert_eq!(percent_decode("my%20mesh.bin"), b"my mesh.bin");
        assert_eq!(percent_decode("%41%6a%2F"), b"Aj/");
        assert_eq!(percent_decode("100%.bin%2"), b"100%.bin%2");
        assert_eq!(percent_decode("%zz%FF"), b"%zz\xff");
    }

    #[test]
    fn buffer_files_resolve_against_the_working_directory_for_an_empty_folder() {
        // `load_mesh("scene.gltf")` passes `Path::new("")` (the parent of a bare file name);
        // tests run in the crate's folder, which holds Cargo.toml.
        let file = resolve_buffer_file(Path::new(""), "Cargo.toml").unwrap();
        assert_eq!(file, Path::new("Cargo.toml").canonicalize().unwrap());
        let e = resolve_buffer_file(Path::new(""), "../../Cargo.toml").unwrap_err();
        assert!(e.contains("outside the model's folder"), "{e}");
        let e =
            resolve_buffer_file(Path::new(""), "src/%2E%2E/%2E%2E/%2E%2E/Cargo.toml").unwrap_err();
        assert!(e.contains("outside the model's folder"), "{e}");
        for uri in [
            "file:///etc/hostname",
            "http://example.com/a.bin",
            "C:/a.bin",
            "C:a.bin",
        ] {
            let e = resolve_buffer_file(Path::new(""), uri).unwrap_err();
            assert!(e.contains("has a scheme"), "{uri}: {e}");
        }
        for uri in ["/etc/hostname", "%2Fetc/hostname"] {
            let e = resolve_buffer_file(Path::new(""), uri).unwrap_err();
            assert!(e.contains("absolute path"), "{uri}: {e}");
        }
    }
}
