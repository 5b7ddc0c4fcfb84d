//! Wavefront OBJ, read with `tobj` after a validating pre-pass of our own.
//!
//! `tobj` reports errors without line numbers and trusts face indices in ways that can overflow
//! (relative indices before any vertex), so every `v`/`vt`/`vn`/`f`/`l` line is checked here
//! first; `tobj` then only ever sees geometry whose indices resolve.

use std::io::{BufRead, Read};
use std::path::Path;

use glam::Vec3;

use super::{data_error, parse_error, read_all};
use crate::{Mesh, MeshError};

/// Reads an OBJ mesh from `reader`; `path` is only used in error messages. Material libraries
/// (`mtllib`) are not opened.
///
/// All objects and groups are merged into one mesh; polygons are fan-triangulated; point and
/// line elements are ignored. Vertices are de-duplicated per object by their full
/// `v/vt/vn` index triple (tobj's `single_index`), so a vertex with several normals appears once
/// per normal. Unreferenced vertices are dropped. Coordinates are in the file's units (a
/// homogeneous `w`, when present, divides x, y, z).
///
/// # Errors
/// [`MeshError::Parse`] with the line for non-numeric coordinates, non-finite vertices (naming
/// the vertex, 0-based in file order), malformed face tokens, index 0, and negative (relative) or
/// positive indices that do not resolve to a vertex; [`MeshError::Data`] when there are no
/// triangles.
pub fn read_obj<R: Read>(reader: R, path: &Path) -> Result<Mesh, MeshError> {
    let bytes = read_all(reader, path)?;
    parse_obj(&bytes, path)
}

#[derive(Default)]
struct Totals {
    positions: usize,
    texcoords: usize,
    normals: usize,
}

fn utf8_text<'a>(bytes: &'a [u8], path: &Path) -> Result<&'a str, MeshError> {
    std::str::from_utf8(bytes).map_err(|e| {
        let line = 1 + bytes[..e.valid_up_to()]
            .iter()
            .filter(|&&b| b == b'\n')
            .count();
        parse_error(path, line, "the line is not valid UTF-8 text")
    })
}

/// Counts the `v`, `vt` and `vn` lines of the whole file.
fn count_totals(text: &str) -> Totals {
    let mut totals = Totals::default();
    for line in text.split('\n') {
        match line.split_whitespace().next() {
            Some("v") => totals.positions += 1,
            Some("vt") => totals.texcoords += 1,
            Some("vn") => totals.normals += 1,
            _ => {}
        }
    }
    totals
}

fn parse_floats<'a>(
    words: &mut impl Iterator<Item = &'a str>,
    n: usize,
    path: &Path,
    line: usize,
    what: &str,
) -> Result<[f32; 3], MeshError> {
    let mut out = [0f32; 3];
    for value in out.iter_mut().take(n) {
        let word = words
            .next()
            .ok_or_else(|| parse_error(path, line, format!("{what}: expected {n} numbers")))?;
        *value = word
            .parse::<f32>()
            .map_err(|_| parse_error(path, line, format!("{what}: '{word}' is not a number")))?;
    }
    Ok(out)
}

/// Resolves one index of a face corner (1-based, or negative = relative to the elements defined
/// so far). Returns an error message if it cannot refer to an element.
fn check_index(
    value: isize,
    so_far: usize,
    total: usize,
    kind: (&str, &str),
) -> Result<(), String> {
    let (one, many) = kind;
    if value < 0 {
        if (so_far as isize) + value < 0 {
            return Err(format!(
                "relative {one} index {value}, but only {so_far} {many} are defined before this line"
            ));
        }
    } else if value as usize > total {
        return Err(format!(
            "{one} index {value}, but the file has {total} {many}"
        ));
    }
    Ok(())
}

/// Checks the lines that carry geometry, with the same tokenisation as tobj.
fn validate(text: &str, path: &Path) -> Result<(), MeshError> {
    let totals = count_totals(text);
    let mut so_far = Totals::default();
    for (i, line) in text.split('\n').enumerate() {
        let line_no = i + 1;
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => {
                let vertex = so_far.positions;
                let what = format!("vertex {vertex}");
                let mut xyz = parse_floats(&mut words, 3, path, line_no, &what)?;
                let extra: Vec<&str> = words.by_ref().take(4).collect();
                match extra.len() {
                    0 => {}
                    1 => {
                        let w = extra[0].parse::<f32>().map_err(|_| {
                            parse_error(
                                path,
                                line_no,
                                format!("{what}: w '{}' is not a number", extra[0]),
                            )
                        })?;
                        if w == 0.0 {
                            return Err(parse_error(path, line_no, format!("{what} has w = 0")));
                        }
                        for c in &mut xyz {
                            *c /= w;
                        }
                    }
                    3 => {} // vertex colour
                    n => {
                        return Err(parse_error(
                            path,
                            line_no,
                            format!(
                                "{what}: expected 'x y z', 'x y z w' or 'x y z r g b', found {} values",
                                3 + n
                            ),
                        ));
                    }
                }
                if let Some(bad) = xyz.iter().find(|c| !c.is_finite()) {
                    return Err(parse_error(
                        path,
                        line_no,
                        format!("{what} has a non-finite coordinate ({bad})"),
                    ));
                }
                so_far.positions += 1;
            }
            Some("vt") => {
                parse_floats(
                    &mut words,
                    2,
                    path,
                    line_no,
                    &format!("texture coordinate {}", so_far.texcoords),
                )?;
                so_far.texcoords += 1;
            }
            Some("vn") => {
                parse_floats(
                    &mut words,
                    3,
                    path,
                    line_no,
                    &format!("normal {}", so_far.normals),
                )?;
                so_far.normals += 1;
            }
            Some(keyword @ ("f" | "l")) => {
                let mut corners = 0usize;
                for word in words {
                    corners += 1;
                    let mut parts = word.split('/');
                    for (slot, kind) in [
                        ("vertex", "vertices"),
                        ("texture coordinate", "texture coordinates"),
                        ("normal", "normals"),
                    ]
                    .iter()
                    .enumerate()
                    {
                        let Some(part) = parts.next() else { break };
                        if part.is_empty() {
                            if slot == 0 {
                                return Err(parse_error(
                                    path,
                                    line_no,
                                    format!("'{word}' has no vertex index"),
                                ));
                            }
                            continue;
                        }
                        let value = part.parse::<isize>().map_err(|_| {
                            parse_error(
                                path,
                                line_no,
                                format!("'{word}': '{part}' is not an integer index"),
                            )
                        })?;
                        let (count, total) = match slot {
                            0 => (so_far.positions, totals.positions),
                            1 => (so_far.texcoords, totals.texcoords),
                            _ => (so_far.normals, totals.normals),
                        };
                        if value == 0 {
                            if slot == 0 {
                                return Err(parse_error(
                                    path,
                                    line_no,
                                    format!("'{word}': vertex index 0 (OBJ indices start at 1)"),
                                ));
                            }
                            continue; // tobj reads a 0 texture/normal index as "absent"
                        }
                        // tobj ignores texture/normal indices when the file has none.
                        if slot > 0 && value > 0 && total == 0 {
                            continue;
                        }
                        check_index(value, count, total, *kind)
                            .map_err(|m| parse_error(path, line_no, format!("'{word}': {m}")))?;
                    }
                    if parts.next().is_some() {
                        return Err(parse_error(
                            path,
                            line_no,
                            format!("'{word}' has more than three indices"),
                        ));
                    }
                }
                if corners == 0 {
                    return Err(parse_error(
                        path,
                        line_no,
                        format!("'{keyword}' without vertices"),
                    ));
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// A `BufRead` over a byte slice that counts the lines it has handed out, so that tobj's
/// errors (which carry no position) can be given the line they occurred on.
struct LineCounting<'a> {
    bytes: &'a [u8],
    position: usize,
    newlines: usize,
}

impl LineCounting<'_> {
    /// The 1-based number of the line most recently read (possibly partially).
    fn current_line(&self) -> usize {
        let partial = self.position > 0 && self.bytes[self.position - 1] != b'\n';
        (self.newlines + usize::from(partial)).max(1)
    }
}

impl Read for LineCounting<'_> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let available = self.fill_buf()?;
        let n = available.len().min(buf.len());
        buf[..n].copy_from_slice(&available[..n]);
        self.consume(n);
        Ok(n)
    }
}

impl BufRead for LineCounting<'_> {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        Ok(&self.bytes[self.position..])
    }

    fn consume(&mut self, amount: usize) {
        let end = (self.position + amount).min(self.bytes.len());
        self.newlines += self.bytes[self.position..end]
            .iter()
            .filter(|&&b| b == b'\n')
            .count();
        self.position = end;
    }
}

pub(crate) fn parse_obj(bytes: &[u8], path: &Path) -> Result<Mesh, MeshError> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let text = utf8_text(bytes, path)?;
    validate(text, path)?;

    // `..Default::default()` covers fields that exist only with some tobj features enabled.
    #[allow(clippy::needless_update)]
    let options = tobj::LoadOptions {
        triangulate: true,
        single_index: true,
        ignore_points: true,
        ignore_lines: true,
        ..Default::default()
    };
    let mut reader = LineCounting {
        bytes,
        position: 0,
        newlines: 0,
    };
    let loaded = tobj::load_obj_buf(&mut reader, &options, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    });
    let (models, _materials) =
        loaded.map_err(|e| parse_error(path, reader.current_line(), e.to_string()))?;

    let mut mesh = Mesh::default();
    for model in &models {
        let m = &model.mesh;
        let offset = mesh.vertices.len();
        mesh.vertices.extend(
            m.positions
                .chunks_exact(3)
                .map(|p| Vec3::new(p[0], p[1], p[2])),
        );
        let count = mesh.vertices.len() - offset;
        for t in m.indices.chunks_exact(3) {
            if let Some(&bad) = t.iter().find(|&&i| i as usize >= count) {
                // Not expected from tobj; kept so a library change cannot make us panic later.
                return Err(super::format_error(
                    path,
                    format!(
                        "object '{}': triangle refers to vertex {bad} of {count}",
                        model.name
                    ),
                ));
            }
            mesh.triangles
                .push([t[0], t[1], t[2]].map(|i| i + offset as u32));
        }
    }
    if mesh.triangles.is_empty() {
        // Unreferenced vertices are dropped, so "no vertices" would be misleading here.
        return Err(data_error(path, crate::MeshDataError::NoFaces));
    }
    mesh.validate().map_err(|e| data_error(path, e))?;
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::MeshDataError;

    fn parse(text: &str) -> Result<Mesh, MeshError> {
        parse_obj(text.as_bytes(), Path::new("test.obj"))
    }

    fn line_of(err: &MeshError) -> usize {
        match err {
            MeshError::Parse { line, .. } => *line,
            other => panic!("expected a parse error, got {other:?}"),
        }
    }

    #[test]
    fn io_obj_quads_and_objects_are_merged() {
        let m =
            parse("o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\no b\nv 0 0 1\nf -5 -4 -1\n")
                .unwrap();
        assert_eq!(m.triangles.len(), 3);
        assert_eq!(m.vertices.len(), 7);
        assert_eq!(m.triangles[2], [4, 5, 6]);
        assert_eq!(m.vertices[6], Vec3::new(0.0, 0.0, 1.0));
    }

    #[test]
    fn io_obj_errors_carry_lines() {
        let e = parse("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n").unwrap_err();
        assert_eq!(line_of(&e), 4);
        let e = parse("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n").unwrap_err();
        assert_eq!(line_of(&e), 4);
        let e = parse("v 0 0 0\nv 1 zz 0\n").unwrap_err();
        assert_eq!(line_of(&e), 2);
        assert!(e.to_string().contains("vertex 1"), "{e}");
        let e = parse("v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n").unwrap_err();
        assert!(e.to_string().contains("vertex 1 has a non-finite"), "{e}");
        let e = parse("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n").unwrap_err();
        assert!(e.to_string().contains("start at 1"), "{e}");
        let e = parse("v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\n").unwrap_err();
        assert!(
            matches!(
                e,
                MeshError::Data {
                    source: MeshDataError::NoFaces,
                    ..
                }
            ),
            "{e:?}"
        );
        // An error only tobj detects (colour with two components) still gets its line.
        let e = parse("v 0 0 0\nv 1 0 0\nv 0 1 0 1 1\nf 1 2 3\n").unwrap_err();
        assert_eq!(line_of(&e), 3);
    }

    #[test]
    fn io_obj_relative_texcoord_before_any_texcoord_is_an_error() {
        let e = parse("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/-1 2/-1 3/-1\nvt 0 0\n").unwrap_err();
        assert_eq!(line_of(&e), 4);
    }
}
