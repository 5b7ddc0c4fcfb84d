//! Stanford PLY: reading meshes and point clouds (via `ply-rs-bw`), writing both (by hand, so
//! the header is exactly what MeshLab and CloudCompare expect).

use std::io::{Cursor, Read, Write};
use std::path::Path;

use glam::Vec3;
use ply_rs_bw::parser::{ParseError, Parser, Reader};
use ply_rs_bw::ply::{
    ElementDef, Encoding, Header, Property, PropertyAccess, PropertyAccessResult, PropertyType,
    ScalarType,
};

use super::{PlyEncoding, data_error, format_error, io_error, parse_error, read_all, write_atomic};
use crate::{GeometryError, Mesh, MeshError, PointCloud};

/// Reads a PLY mesh from `reader`; `path` is only used in error messages.
///
/// Accepts ascii, binary little-endian and binary big-endian files. The `vertex` element must
/// have scalar `x`, `y`, `z` properties of any numeric type (float and double included; doubles
/// are rounded to f32); the `face` element must have a list property `vertex_indices` (or
/// `vertex_index`) of an integer type. Polygons are fan-triangulated; other elements and
/// properties are skipped. Coordinates are in the file's units.
///
/// # Errors
/// [`MeshError::Parse`] (ascii, with the line) or [`MeshError::Format`] (binary, naming the
/// element, e.g. "vertex 3", "face 12") for malformed or truncated data, non-finite coordinates,
/// faces with fewer than three or out-of-range/negative indices, and headers whose counts the
/// rest of the file cannot hold; [`MeshError::Data`] when there are no faces.
pub fn read_ply<R: Read>(reader: R, path: &Path) -> Result<Mesh, MeshError> {
    let bytes = read_all(reader, path)?;
    let contents = parse_ply(&bytes, path, true)?;
    Mesh::new(contents.cloud.points, contents.triangles).map_err(|e| data_error(path, e))
}

/// Reads the `vertex` element of a PLY file from `reader` as a point cloud: `x y z`, plus
/// normals when the vertices have `nx ny nz`, and colours when they have `red green blue`
/// (integer channels are taken as 0–255, float channels as 0–1). Faces, if any, are ignored.
///
/// # Errors
/// As [`read_ply`], except that a file without faces is fine (an empty cloud is too).
pub fn read_ply_points<R: Read>(reader: R, path: &Path) -> Result<PointCloud, MeshError> {
    let bytes = read_all(reader, path)?;
    Ok(parse_ply(&bytes, path, false)?.cloud)
}

/// Reads a point cloud from the PLY file at `path`; see [`read_ply_points`].
pub fn read_ply_cloud(path: impl AsRef<Path>) -> Result<PointCloud, MeshError> {
    let path = path.as_ref();
    let file =
        super::open_regular(path, super::MAX_MESH_FILE_BYTES).map_err(|e| io_error(path, e))?;
    read_ply_points(file, path)
}

/// Writes `cloud` to `path` as PLY (atomically: a temporary file in the same directory is
/// renamed over `path` once complete).
///
/// The vertex element has `float x y z`, then `float nx ny nz` when the cloud has normals and
/// `uchar red green blue` when it has colours. Values are written as stored (no unit change).
///
/// # Errors
/// [`MeshError::Cloud`] when the cloud is invalid (attribute lengths differ from the point
/// count, non-finite points or normals); [`MeshError::Io`] when writing fails.
pub fn write_ply(
    path: impl AsRef<Path>,
    cloud: &PointCloud,
    encoding: PlyEncoding,
) -> Result<(), MeshError> {
    let path = path.as_ref();
    check_cloud(cloud, path)?;
    write_atomic(path, |w| write_cloud_unchecked(w, cloud, encoding))
}

/// Writes `cloud` as PLY to any writer; see [`write_ply`].
pub fn write_ply_to<W: Write>(
    mut writer: W,
    cloud: &PointCloud,
    encoding: PlyEncoding,
) -> Result<(), MeshError> {
    let path = Path::new("<writer>");
    check_cloud(cloud, path)?;
    write_cloud_unchecked(&mut writer, cloud, encoding).map_err(|e| io_error(path, e))
}

/// Writes `mesh` to `path` as PLY (atomically): `float x y z` vertices and a
/// `list uchar int vertex_indices` face element with one triangle per face.
///
/// # Errors
/// [`MeshError::Data`] when the mesh does not pass [`Mesh::validate`]; [`MeshError::Format`]
/// when it has more vertices than a PLY `int` index can address; [`MeshError::Io`].
pub fn write_mesh_ply(
    path: impl AsRef<Path>,
    mesh: &Mesh,
    encoding: PlyEncoding,
) -> Result<(), MeshError> {
    let path = path.as_ref();
    check_mesh(mesh, path)?;
    write_atomic(path, |w| write_mesh_unchecked(w, mesh, encoding))
}

/// Writes `mesh` as PLY to any writer; see [`write_mesh_ply`].
pub fn write_mesh_ply_to<W: Write>(
    mut writer: W,
    mesh: &Mesh,
    encoding: PlyEncoding,
) -> Result<(), MeshError> {
    let path = Path::new("<writer>");
    check_mesh(mesh, path)?;
    write_mesh_unchecked(&mut writer, mesh, encoding).map_err(|e| io_error(path, e))
}

// ---------------------------------------------------------------------------------------------
// Writing

fn check_cloud(cloud: &PointCloud, path: &Path) -> Result<(), MeshError> {
    let cloud_error = |source| MeshError::Cloud {
        path: path.to_path_buf(),
        source,
    };
    cloud.validate().map_err(cloud_error)?;
    if let Some(normals) = &cloud.normals {
        if let Some(index) = normals.iter().position(|n| !n.is_finite()) {
            return Err(cloud_error(GeometryError::NonFinitePoint {
                what: "point-cloud normals",
                index,
            }));
        }
    }
    Ok(())
}

fn check_mesh(mesh: &Mesh, path: &Path) -> Result<(), MeshError> {
    mesh.validate().map_err(|e| data_error(path, e))?;
    if mesh.vertices.len() > i32::MAX as usize {
        return Err(format_error(path, "too many vertices for PLY int indices"));
    }
    Ok(())
}

fn write_header(
    w: &mut dyn Write,
    encoding: PlyEncoding,
    vertex_count: usize,
    normals: bool,
    colors: bool,
    face_count: Option<usize>,
) -> std::io::Result<()> {
    let format = match encoding {
        PlyEncoding::Ascii => "ascii",
        PlyEncoding::BinaryLittleEndian => "binary_little_endian",
        PlyEncoding::BinaryBigEndian => "binary_big_endian",
    };
    writeln!(
        w,
        "ply\nformat {format} 1.0\ncomment written by ic_geometry"
    )?;
    writeln!(
        w,
        "element vertex {vertex_count}\nproperty float x\nproperty float y\nproperty float z"
    )?;
    if normals {
        writeln!(w, "property float nx\nproperty float ny\nproperty float nz")?;
    }
    if colors {
        writeln!(
            w,
            "property uchar red\nproperty uchar green\nproperty uchar blue"
        )?;
    }
    if let Some(faces) = face_count {
        writeln!(
            w,
            "element face {faces}\nproperty list uchar int vertex_indices"
        )?;
    }
    writeln!(w, "end_header")
}

/// Appends `v` to `buf` in the encoding (ascii: shortest exact decimal, space-separated).
fn put_f32(buf: &mut Vec<u8>, v: f32, encoding: PlyEncoding) {
    match encoding {
        PlyEncoding::Ascii => {
            if !buf.is_empty() && *buf.last().unwrap_or(&b'\n') != b'\n' {
                buf.push(b' ');
            }
            // `Display` for f32 prints the shortest decimal that parses back to the same bits.
            let _ = write!(buf, "{v}");
        }
        PlyEncoding::BinaryLittleEndian => buf.extend_from_slice(&v.to_le_bytes()),
        PlyEncoding::BinaryBigEndian => buf.extend_from_slice(&v.to_be_bytes()),
    }
}

fn put_u8(buf: &mut Vec<u8>, v: u8, encoding: PlyEncoding) {
    match encoding {
        PlyEncoding::Ascii => {
            if !buf.is_empty() && *buf.last().unwrap_or(&b'\n') != b'\n' {
                buf.push(b' ');
            }
            let _ = write!(buf, "{v}");
        }
        _ => buf.push(v),
    }
}

fn put_i32(buf: &mut Vec<u8>, v: i32, encoding: PlyEncoding) {
    match encoding {
        PlyEncoding::Ascii => {
            if !buf.is_empty() && *buf.last().unwrap_or(&b'\n') != b'\n' {
                buf.push(b' ');
            }
            let _ = write!(buf, "{v}");
        }
        PlyEncoding::BinaryLittleEndian => buf.extend_from_slice(&v.to_le_bytes()),
        PlyEncoding::BinaryBigEndian => buf.extend_from_slice(&v.to_be_bytes()),
    }
}

fn end_record(buf: &mut Vec<u8>, encoding: PlyEncoding) {
    if encoding == PlyEncoding::Ascii {
        buf.push(b'\n');
    }
}

/// Flushes the record buffer to the writer once it is large, to bound memory.
fn maybe_flush(w: &mut dyn Write, buf: &mut Vec<u8>) -> std::io::Result<()> {
    if buf.len() >= 1 << 16 {
        w.write_all(buf)?;
        buf.clear();
    }
    Ok(())
}

fn write_cloud_unchecked(
    w: &mut dyn Write,
    cloud: &PointCloud,
    encoding: PlyEncoding,
) -> std::io::Result<()> {
    write_header(
        w,
        encoding,
        cloud.len(),
        cloud.normals.is_some(),
        cloud.colors.is_some(),
        None,
    )?;
    let mut buf = Vec::with_capacity(1 << 16);
    for (i, p) in cloud.points.iter().enumerate() {
        for c in p.to_array() {
            put_f32(&mut buf, c, encoding);
        }
        if let Some(normals) = &cloud.normals {
            for c in normals[i].to_array() {
                put_f32(&mut buf, c, encoding);
            }
        }
        if let Some(colors) = &cloud.colors {
            for c in colors[i] {
                put_u8(&mut buf, c, encoding);
            }
        }
        end_record(&mut buf, encoding);
        maybe_flush(w, &mut buf)?;
    }
    w.write_all(&buf)?;
    w.flush()
}

fn write_mesh_unchecked(
    w: &mut dyn Write,
    mesh: &Mesh,
    encoding: PlyEncoding,
) -> std::io::Result<()> {
    write_header(
        w,
        encoding,
        mesh.vertices.len(),
        false,
        false,
        Some(mesh.triangles.len()),
    )?;
    let mut buf = Vec::with_capacity(1 << 16);
    for v in &mesh.vertices {
        for c in v.to_array() {
            put_f32(&mut buf, c, encoding);
        }
        end_record(&mut buf, encoding);
        maybe_flush(w, &mut buf)?;
    }
    for t in &mesh.triangles {
        put_u8(&mut buf, 3, encoding);
        for &i in t {
            put_i32(&mut buf, i as i32, encoding);
        }
        end_record(&mut buf, encoding);
        maybe_flush(w, &mut buf)?;
    }
    w.write_all(&buf)?;
    w.flush()
}

// ---------------------------------------------------------------------------------------------
// Reading

/// A scalar property value as f64 (lists give `None`).
fn scalar_f64(p: &Property) -> Option<f64> {
    Some(match *p {
        Property::Char(v) => v.into(),
        Property::UChar(v) => v.into(),
        Property::Short(v) => v.into(),
        Property::UShort(v) => v.into(),
        Property::Int(v) => v.into(),
        Property::UInt(v) => v.into(),
        Property::Float(v) => v.into(),
        Property::Double(v) => v,
        _ => return None,
    })
}

/// One `vertex` record: only the properties we use are kept.
#[derive(Clone, Copy, Default)]
struct VertexRecord {
    position: [f64; 3],
    normal: [f32; 3],
    color: [u8; 3],
}

impl PropertyAccess for VertexRecord {
    fn new() -> Self {
        VertexRecord::default()
    }

    fn set_property(&mut self, name: &str, property: Property) -> PropertyAccessResult {
        let slot = |names: [&str; 3]| names.iter().position(|&n| n == name);
        if let Some(axis) = slot(["x", "y", "z"]) {
            match scalar_f64(&property) {
                Some(v) => self.position[axis] = v,
                None => return PropertyAccessResult::UnsupportedType,
            }
        } else if let Some(axis) = slot(["nx", "ny", "nz"]) {
            if let Some(v) = scalar_f64(&property) {
                self.normal[axis] = v as f32;
            }
        } else if let Some(channel) = slot(["red", "green", "blue"]) {
            if let Some(v) = property.to_u8_color_lossy() {
                self.color[channel] = v;
            }
        } else {
            return PropertyAccessResult::Ignored;
        }
        PropertyAccessResult::Set
    }
}

/// One `face` record: the vertex indices, or the first negative one.
#[derive(Default)]
struct FaceRecord {
    indices: Vec<u32>,
    negative: Option<i64>,
}

fn to_indices<T: Copy + Into<i64>>(values: &[T], face: &mut FaceRecord) {
    face.indices.reserve(values.len());
    for &v in values {
        let v: i64 = v.into();
        if v < 0 {
            face.negative.get_or_insert(v);
            face.indices.push(0);
        } else {
            face.indices.push(v as u32);
        }
    }
}

impl PropertyAccess for FaceRecord {
    fn new() -> Self {
        FaceRecord::default()
    }

    fn set_property(&mut self, name: &str, property: Property) -> PropertyAccessResult {
        if name != "vertex_indices" && name != "vertex_index" {
            return PropertyAccessResult::Ignored;
        }
        match property {
            Property::ListChar(v) => to_indices(&v, self),
            Property::ListUChar(v) => to_indices(&v, self),
            Property::ListShort(v) => to_indices(&v, self),
            Property::ListUShort(v) => to_indices(&v, self),
            Property::ListInt(v) => to_indices(&v, self),
            Property::ListUInt(v) => self.indices = v,
            _ => return PropertyAccessResult::UnsupportedType,
        }
        PropertyAccessResult::Set
    }
}

/// An element we do not need: everything is parsed (to advance) and dropped.
struct Skipped;

impl PropertyAccess for Skipped {
    fn new() -> Self {
        Skipped
    }
}

#[derive(Debug)]
pub(crate) struct PlyContents {
    pub cloud: PointCloud,
    pub triangles: Vec<[u32; 3]>,
}

/// Where errors in the payload are reported: lines for ascii, element numbers for binary.
struct Locator<'a> {
    path: &'a Path,
    ascii: bool,
}

impl Locator<'_> {
    /// An error about record `index` of an element whose first record is on `first_line`.
    fn at(&self, first_line: usize, index: usize, message: String) -> MeshError {
        if self.ascii {
            parse_error(self.path, first_line + index, message)
        } else {
            format_error(self.path, message)
        }
    }

    /// Converts a ply-rs error while reading element `name` starting at `first_line`.
    fn payload(&self, e: ParseError, name: &str, first_line: usize) -> MeshError {
        let message = tidy(&e);
        match (self.ascii, e.line()) {
            (true, Some(line)) => {
                parse_error(self.path, line, format!("element '{name}': {message}"))
            }
            (false, Some(line)) if line >= first_line => format_error(
                self.path,
                format!("{name} {}: {message}", line - first_line),
            ),
            _ => format_error(self.path, format!("element '{name}': {message}")),
        }
    }
}

/// ply-rs messages, made one-line: no "Line N:" prefix (we report the line ourselves), no
/// embedded line breaks, and peg's debug dump reduced to the column.
fn tidy(e: &ParseError) -> String {
    let full = e.to_string();
    let full = match e.line() {
        Some(l) => full.strip_prefix(&format!("Line {l}: ")).unwrap_or(&full),
        None => &full,
    };
    let parts: Vec<String> = full
        .split("\n\t")
        .map(|part| {
            if let Some(debug) = part.strip_prefix("Error: ParseError {") {
                let column = debug
                    .split("column: ")
                    .nth(1)
                    .and_then(|c| c.split(|ch: char| !ch.is_ascii_digit()).next())
                    .unwrap_or("?");
                format!("unexpected syntax at column {column}")
            } else {
                part.replace(['\r', '\n'], "").trim().to_string()
            }
        })
        .collect();
    parts.join("; ")
}

fn header_error(path: &Path, e: ParseError) -> MeshError {
    match e.line() {
        Some(line) => parse_error(path, line, tidy(&e)),
        None => format_error(path, tidy(&e)),
    }
}

/// Bytes one record of `element` takes at least in a binary file.
fn min_binary_size(element: &ElementDef) -> usize {
    let scalar = |t: &ScalarType| match t {
        ScalarType::Char | ScalarType::UChar => 1,
        ScalarType::Short | ScalarType::UShort => 2,
        ScalarType::Int | ScalarType::UInt | ScalarType::Float => 4,
        ScalarType::Double => 8,
    };
    element
        .properties
        .values()
        .map(|p| match &p.data_type {
            PropertyType::Scalar(t) => scalar(t),
            PropertyType::List(count, _) => scalar(count),
        })
        .sum()
}

/// Rejects headers whose element counts the rest of the file cannot hold (so nothing is
/// allocated or looped over on the strength of a forged count).
fn check_counts(header: &Header, remaining: usize, path: &Path) -> Result<(), MeshError> {
    let mut needed: usize = 0;
    for (name, element) in &header.elements {
        if element.count == 0 {
            continue;
        }
        let per_record = match header.encoding {
            // At least one character and a line break per record (the last may lack it).
            Encoding::Ascii => 1,
            _ => min_binary_size(element),
        };
        if element.properties.is_empty() {
            return Err(format_error(
                path,
                format!(
                    "element '{name}' declares {} records but has no properties",
                    element.count
                ),
            ));
        }
        needed = element
            .count
            .checked_mul(per_record)
            .and_then(|n| n.checked_add(needed))
            .ok_or_else(|| {
                format_error(
                    path,
                    format!("element '{name}': count {} is absurd", element.count),
                )
            })?;
        if needed > remaining.saturating_add(1) {
            return Err(format_error(
                path,
                format!(
                    "the header declares {} '{name}' records, but the {remaining} bytes after the header cannot hold them",
                    element.count
                ),
            ));
        }
    }
    Ok(())
}

fn scalar_property(element: &ElementDef, name: &str) -> Option<bool> {
    element
        .properties
        .get(name)
        .map(|p| matches!(p.data_type, PropertyType::Scalar(_)))
}

pub(crate) fn parse_ply(
    bytes: &[u8],
    path: &Path,
    want_faces: bool,
) -> Result<PlyContents, MeshError> {
    let mut reader = Reader::new(Cursor::new(bytes));
    let header = Parser::<Skipped>::new()
        .read_header(&mut reader)
        .map_err(|e| header_error(path, e))?;
    let remaining = bytes
        .len()
        .saturating_sub(reader.get_ref().position() as usize);
    check_counts(&header, remaining, path)?;
    let locate = Locator {
        path,
        ascii: header.encoding == Encoding::Ascii,
    };

    let vertex_def = header
        .elements
        .get("vertex")
        .ok_or_else(|| format_error(path, "the file has no 'vertex' element"))?;
    for axis in ["x", "y", "z"] {
        match scalar_property(vertex_def, axis) {
            Some(true) => {}
            Some(false) => {
                return Err(format_error(
                    path,
                    format!("vertex property '{axis}' is a list"),
                ));
            }
            None => {
                return Err(format_error(
                    path,
                    format!("the vertex element has no '{axis}' property"),
                ));
            }
        }
    }
    let all_scalar = |names: [&str; 3]| {
        names
            .iter()
            .all(|n| scalar_property(vertex_def, n) == Some(true))
    };
    let has_normals = all_scalar(["nx", "ny", "nz"]);
    let has_colors = all_scalar(["red", "green", "blue"]);
    let face_def = header.elements.get("face");
    if want_faces {
        if let Some(face_def) = face_def {
            let indices = face_def
                .properties
                .get("vertex_indices")
                .or_else(|| face_def.properties.get("vertex_index"));
            match indices.map(|p| &p.data_type) {
                Some(PropertyType::List(_, t))
                    if !matches!(t, ScalarType::Float | ScalarType::Double) => {}
                Some(_) => {
                    return Err(format_error(
                        path,
                        "the face indices must be a list of integers",
                    ));
                }
                None => {
                    return Err(format_error(
                        path,
                        "the face element has no 'vertex_indices' list",
                    ));
                }
            }
        }
    }

    let mut vertices: Option<(Vec<VertexRecord>, usize)> = None;
    let mut faces: Option<(Vec<FaceRecord>, usize)> = None;
    for (name, element) in &header.elements {
        if vertices.is_some() && (faces.is_some() || !want_faces || face_def.is_none()) {
            break; // nothing further is needed
        }
        let first_line = reader.line().max(1);
        if name == "vertex" {
            let records = Parser::<VertexRecord>::new()
                .read_payload_for_element(&mut reader, element, &header)
                .map_err(|e| locate.payload(e, name, first_line))?;
            vertices = Some((records, first_line));
        } else if name == "face" && want_faces {
            let records = Parser::<FaceRecord>::new()
                .read_payload_for_element(&mut reader, element, &header)
                .map_err(|e| locate.payload(e, name, first_line))?;
            faces = Some((records, first_line));
        } else {
            Parser::<Skipped>::new()
                .read_payload_for_element(&mut reader, element, &header)
                .map_err(|e| locate.payload(e, name, first_line))?;
        }
    }

    let (records, vertex_line) = vertices.unwrap_or_default();
    let mut points = Vec::with_capacity(records.len());
    for (i, r) in records.iter().enumerate() {
        let p = Vec3::from_array(r.position.map(|c| c as f32));
        if let Some(bad) = r
            .position
            .iter()
            .zip(p.to_array())
            .find(|(_, f)| !f.is_finite())
            .map(|(d, _)| *d)
        {
            return Err(locate.at(
                vertex_line,
                i,
                format!("vertex {i} has a non-finite coordinate ({bad})"),
            ));
        }
        points.push(p);
    }
    let normals = has_normals.then(|| records.iter().map(|r| Vec3::from_array(r.normal)).collect());
    let colors = has_colors.then(|| records.iter().map(|r| r.color).collect());
    drop(records);

    let vertex_count = points.len();
    let mut triangles = Vec::new();
    if let Some((records, face_line)) = faces {
        triangles.reserve(records.len());
        for (i, face) in records.iter().enumerate() {
            if let Some(v) = face.negative {
                return Err(locate.at(
                    face_line,
                    i,
                    format!("face {i} has a negative vertex index ({v})"),
                ));
            }
            let n = face.indices.len();
            if n < 3 {
                return Err(locate.at(
                    face_line,
                    i,
                    format!("face {i} has {n} vertices, need at least 3"),
                ));
            }
            if let Some(&bad) = face.indices.iter().find(|&&v| v as usize >= vertex_count) {
                return Err(locate.at(
                    face_line,
                    i,
                    format!(
                        "face {i} refers to vertex {bad}, but the file has {vertex_count} vertices"
                    ),
                ));
            }
            let first = face.indices[0];
            for pair in face.indices[1..].windows(2) {
                triangles.push([first, pair[0], pair[1]]);
            }
        }
    }

    Ok(PlyContents {
        cloud: PointCloud {
            points,
            normals,
            colors,
        },
        triangles,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &[u8], faces: bool) -> Result<PlyContents, MeshError> {
        parse_ply(text, Path::new("test.ply"), faces)
    }

    #[test]
    fn io_ply_ascii_mesh_with_quad_and_extra_element() {
        let text = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\n\
element face 1\nproperty list uchar int vertex_indices\nelement edge 1\nproperty int a\nend_header\n\
0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n7\n";
        let c = parse(text, true).unwrap();
        assert_eq!(c.cloud.points.len(), 4);
        assert_eq!(c.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn io_ply_errors_name_line_or_element() {
        let head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
element face 1\nproperty list uchar int vertex_indices\nend_header\n";
        let e = parse(
            format!("{head}0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n").as_bytes(),
            true,
        )
        .unwrap_err();
        match &e {
            MeshError::Parse { line, message, .. } => {
                assert_eq!(*line, 13);
                assert!(message.contains("face 0 refers to vertex 5"), "{message}");
            }
            other => panic!("{other:?}"),
        }
        let e = parse(
            format!("{head}0 0 0\n1 a 0\n0 1 0\n3 0 1 2\n").as_bytes(),
            true,
        )
        .unwrap_err();
        assert!(matches!(e, MeshError::Parse { line: 11, .. }), "{e:?}");
        let e = parse(
            format!("{head}0 0 0\n1 1e39 0\n0 1 0\n3 0 1 2\n").as_bytes(),
            true,
        )
        .unwrap_err();
        assert!(matches!(e, MeshError::Parse { line: 11, .. }), "{e:?}");
        assert!(e.to_string().contains("vertex 1"), "{e}");
        let e = parse(
            format!("{head}0 0 0\n1 0 0\n0 1 0\n3 0 -1 2\n").as_bytes(),
            true,
        );
        assert!(e.is_err());
        let e = parse(format!("{head}0 0 0\n1 0 0\n").as_bytes(), true).unwrap_err();
        assert!(e.to_string().contains("test.ply"), "{e}");
    }

    #[test]
    fn io_ply_forged_binary_count_is_rejected_before_reading() {
        let text = b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n\0\0\0\0";
        let e = parse(text, false).unwrap_err();
        assert!(e.to_string().contains("cannot hold"), "{e}");
        let text = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nelement junk 4000000000\nend_header\n\0\0\0\0\0\0\0\0\0\0\0\0";
        let e = parse(text, false).unwrap_err();
        assert!(e.to_string().contains("no properties"), "{e}");
    }
}
