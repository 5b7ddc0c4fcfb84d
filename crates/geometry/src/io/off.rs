//! Object File Format (OFF), as used by ModelNet and Princeton's shape benchmark.

use std::io::Read;
use std::path::Path;

use glam::Vec3;

use super::{data_error, parse_error, read_all};
use crate::{Mesh, MeshError};

/// Reads an OFF mesh from `reader`; `path` is only used in error messages.
///
/// Accepts:
/// - the header keyword `OFF` (also `COFF`, `NOFF`, `CNOFF`, `STOFF`…: extra per-vertex values
///   such as colours or normals are ignored), followed by `vertex_count face_count [edge_count]`
///   either on the same line, on a later line, or fused with the keyword — ModelNet40's
///   `OFF490 518 0`;
/// - `#` comments anywhere and blank lines;
/// - one vertex per line (`x y z`, further values ignored) and one face per line
///   (`n i0 i1 … i(n−1)`, 0-based indices, any further values — face colours — ignored);
///   polygons with `n > 3` are fan-triangulated.
///
/// Coordinates are returned in the file's units.
///
/// # Errors
/// [`MeshError::Parse`] with the line for malformed headers, counts, non-numeric tokens,
/// non-finite coordinates (naming the vertex), faces with fewer than three vertices, negative or
/// out-of-range indices (naming the face) and files that end before the declared counts;
/// [`MeshError::Data`] when the result is not a valid mesh (e.g. no faces).
pub fn read_off<R: Read>(reader: R, path: &Path) -> Result<Mesh, MeshError> {
    let bytes = read_all(reader, path)?;
    parse_off(&bytes, path)
}

/// Yields the non-empty, comment-stripped lines of a text file with their 1-based numbers.
struct ContentLines<'a> {
    bytes: &'a [u8],
    offset: usize,
    line: usize,
    path: &'a Path,
}

impl<'a> ContentLines<'a> {
    fn new(bytes: &'a [u8], path: &'a Path) -> Self {
        ContentLines {
            bytes,
            offset: 0,
            line: 0,
            path,
        }
    }

    /// Bytes not yet consumed.
    fn remaining(&self) -> usize {
        self.bytes.len() - self.offset
    }

    /// The next line with content, or `None` at the end of the file.
    fn next_line(&mut self) -> Result<Option<(usize, &'a str)>, MeshError> {
        while self.offset < self.bytes.len() {
            let rest = &self.bytes[self.offset..];
            let end = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
            let raw = &rest[..end];
            self.offset += (end + 1).min(rest.len());
            self.line += 1;
            let text = std::str::from_utf8(raw).map_err(|_| {
                parse_error(self.path, self.line, "the line is not valid UTF-8 text")
            })?;
            let text = match text.find('#') {
                Some(i) => &text[..i],
                None => text,
            };
            let text = text.trim();
            if !text.is_empty() {
                return Ok(Some((self.line, text)));
            }
        }
        Ok(None)
    }

    /// The line number to report when the file ends too early.
    fn last_line(&self) -> usize {
        self.line.max(1)
    }
}

/// Length of the OFF keyword at the start of `s` (`[ST][C][N]OFF`), if present.
fn off_keyword_len(s: &str) -> Option<usize> {
    let mut rest = s;
    for prefix in ["ST", "C", "N"] {
        rest = rest.strip_prefix(prefix).unwrap_or(rest);
    }
    rest.strip_prefix("OFF").map(|after| s.len() - after.len())
}

fn parse_count(
    path: &Path,
    line: usize,
    token: Option<&str>,
    what: &str,
) -> Result<usize, MeshError> {
    let token =
        token.ok_or_else(|| parse_error(path, line, format!("missing the {what} count")))?;
    if token.starts_with('-') {
        return Err(parse_error(
            path,
            line,
            format!("negative {what} count {token}"),
        ));
    }
    token.parse::<usize>().map_err(|_| {
        parse_error(
            path,
            line,
            format!("the {what} count '{token}' is not a non-negative integer"),
        )
    })
}

pub(crate) fn parse_off(bytes: &[u8], path: &Path) -> Result<Mesh, MeshError> {
    let bytes = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let mut lines = ContentLines::new(bytes, path);

    // Header keyword, possibly fused with the counts ("OFF490 518 0").
    let (header_line, header) = lines.next_line()?.ok_or_else(|| {
        parse_error(
            path,
            lines.last_line(),
            "empty file: expected the 'OFF' header",
        )
    })?;
    let keyword = off_keyword_len(header).ok_or_else(|| {
        let shown: String = header.chars().take(40).collect();
        parse_error(
            path,
            header_line,
            format!("expected the 'OFF' header, found '{shown}'"),
        )
    })?;
    let mut counts_line = header_line;
    let mut counts = header[keyword..].trim();
    if counts.is_empty() {
        let (l, text) = lines.next_line()?.ok_or_else(|| {
            parse_error(
                path,
                lines.last_line(),
                "the file ends before the vertex and face counts",
            )
        })?;
        counts_line = l;
        counts = text;
    }
    let mut tokens = counts.split_ascii_whitespace();
    let vertex_count = parse_count(path, counts_line, tokens.next(), "vertex")?;
    let face_count = parse_count(path, counts_line, tokens.next(), "face")?;
    if let Some(edges) = tokens.next() {
        parse_count(path, counts_line, Some(edges), "edge")?;
    }

    // Never reserve more than the rest of the file could hold (a vertex line is at least
    // "0 0 0\n", a face line at least "3 0 1 2\n").
    let mut vertices = Vec::with_capacity(vertex_count.min(lines.remaining() / 6));
    for vertex in 0..vertex_count {
        let (line, text) = lines.next_line()?.ok_or_else(|| {
            parse_error(
                path,
                lines.last_line(),
                format!("the file ends after {vertex} of {vertex_count} vertices"),
            )
        })?;
        let mut tokens = text.split_ascii_whitespace();
        let mut xyz = [0f32; 3];
        for (axis, value) in xyz.iter_mut().enumerate() {
            let token = tokens.next().ok_or_else(|| {
                parse_error(
                    path,
                    line,
                    format!("vertex {vertex} has {axis} coordinates, expected 3"),
                )
            })?;
            *value = token.parse::<f32>().map_err(|_| {
                parse_error(
                    path,
                    line,
                    format!("vertex {vertex}: '{token}' is not a number"),
                )
            })?;
            if !value.is_finite() {
                return Err(parse_error(
                    path,
                    line,
                    format!("vertex {vertex} has a non-finite coordinate ({token})"),
                ));
            }
        }
        vertices.push(Vec3::from_array(xyz));
    }

    let mut triangles = Vec::with_capacity(face_count.min(lines.remaining() / 8));
    for face in 0..face_count {
        let (line, text) = lines.next_line()?.ok_or_else(|| {
            parse_error(
                path,
                lines.last_line(),
                format!("the file ends after {face} of {face_count} faces"),
            )
        })?;
        let mut tokens = text.split_ascii_whitespace();
        let n_token = tokens.next().unwrap_or_default();
        let n = n_token.parse::<usize>().map_err(|_| {
            parse_error(
                path,
                line,
                format!("face {face}: '{n_token}' is not a vertex count"),
            )
        })?;
        if n < 3 {
            return Err(parse_error(
                path,
                line,
                format!("face {face} has {n} vertices, need at least 3"),
            ));
        }
        let mut listed = 0usize;
        let mut next_index = || -> Result<u32, MeshError> {
            let token = tokens.next().ok_or_else(|| {
                parse_error(
                    path,
                    line,
                    format!("face {face} declares {n} vertices but lists only {listed}"),
                )
            })?;
            listed += 1;
            let index = token.parse::<i64>().map_err(|_| {
                parse_error(
                    path,
                    line,
                    format!("face {face}: vertex index '{token}' is not an integer"),
                )
            })?;
            if index < 0 {
                return Err(parse_error(
                    path,
                    line,
                    format!("face {face} has a negative vertex index ({index})"),
                ));
            }
            if index as u64 >= vertex_count as u64 || index > u32::MAX as i64 {
                return Err(parse_error(
                    path,
                    line,
                    format!(
                        "face {face} refers to vertex {index}, but the file has {vertex_count} vertices"
                    ),
                ));
            }
            Ok(index as u32)
        };
        let first = next_index()?;
        let mut previous = next_index()?;
        for _ in 2..n {
            let current = next_index()?;
            triangles.push([first, previous, current]);
            previous = current;
        }
        // Anything after the indices (face colours) is ignored.
    }

    Mesh::new(vertices, triangles).map_err(|e| data_error(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::MeshDataError;

    fn parse(text: &str) -> Result<Mesh, MeshError> {
        parse_off(text.as_bytes(), Path::new("test.off"))
    }

    fn line_of(err: &MeshError) -> usize {
        match err {
            MeshError::Parse { line, .. } => *line,
            other => panic!("expected a parse error, got {other:?}"),
        }
    }

    #[test]
    fn io_off_plain_fused_and_separate_headers() {
        let body = "0 0 0\n1 0 0\n0 1 0\n1 1 0\n4 0 1 3 2\n";
        for header in [
            "OFF\n4 1 0\n",
            "OFF 4 1 0\n",
            "OFF4 1 0\n",
            "# c\n\nOFF\n# counts\n4 1\n",
        ] {
            let m = parse(&format!("{header}{body}")).unwrap();
            assert_eq!(m.vertices.len(), 4);
            assert_eq!(m.triangles, vec![[0, 1, 3], [0, 3, 2]]);
        }
    }

    #[test]
    fn io_off_errors_name_line_and_element() {
        let e = parse("OFF\n3 1 0\n0 0 0\n1 x 0\n0 1 0\n3 0 1 2\n").unwrap_err();
        assert_eq!(line_of(&e), 4);
        assert!(e.to_string().contains("vertex 1"), "{e}");

        let e = parse("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 nan\n3 0 1 2\n").unwrap_err();
        assert_eq!(line_of(&e), 5);
        assert!(
            e.to_string().contains("vertex 2") && e.to_string().contains("non-finite"),
            "{e}"
        );

        let e = parse("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n").unwrap_err();
        assert_eq!(line_of(&e), 6);
        assert!(e.to_string().contains("face 0 refers to vertex 3"), "{e}");

        let e = parse("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n").unwrap_err();
        assert!(e.to_string().contains("negative"), "{e}");

        let e = parse("OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").unwrap_err();
        assert!(e.to_string().contains("after 1 of 2 faces"), "{e}");

        let e = parse("OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n").unwrap_err();
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

        let e = parse("OFF\n-3 1 0\n").unwrap_err();
        assert!(e.to_string().contains("negative vertex count"), "{e}");

        let e = parse("PLY\n").unwrap_err();
        assert_eq!(line_of(&e), 1);
    }
}
