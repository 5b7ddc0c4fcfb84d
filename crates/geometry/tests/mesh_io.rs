//! Mesh and point-cloud file I/O: fixtures, round trips, error reporting.

use std::path::{Path, PathBuf};

use glam::Vec3;
use ic_geometry::io::{
    PlyEncoding, load_mesh, read_gltf, read_obj, read_off, read_ply, read_ply_cloud,
    read_ply_points, write_mesh_ply, write_mesh_ply_to, write_ply, write_ply_to,
};
use ic_geometry::{Mesh, MeshDataError, MeshError, PointCloud};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/meshes")
        .join(name)
}

fn bits(v: &[Vec3]) -> Vec<[u32; 3]> {
    v.iter().map(|p| p.to_array().map(f32::to_bits)).collect()
}

fn assert_close(a: Vec3, b: Vec3) {
    assert!(a.abs_diff_eq(b, 1e-6), "{a} vs {b}");
}

/// Vertices and triangles that exercise float formatting: tiny, huge, negative zero, subnormal.
fn awkward_mesh() -> Mesh {
    Mesh::new(
        vec![
            Vec3::new(0.1, -0.0, 1e-30),
            Vec3::new(-3.4e38, f32::MIN_POSITIVE, 1.0e-45),
            Vec3::new(123456.79, -7.0, 0.333_333_34),
            Vec3::new(1.0, 2.0, 3.0),
        ],
        vec![[0, 1, 2], [0, 2, 3], [3, 2, 1]],
    )
    .unwrap()
}

// ------------------------------------------------------------------------------------------
// Fixtures

#[test]
fn off_modelnet_fused_header_fixture_loads_and_ignores_face_colours() {
    let m = load_mesh(fixture("modelnet_fused_header.off")).unwrap();
    assert_eq!(m.vertices.len(), 4);
    assert_eq!(
        m.triangles,
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    );
    assert_eq!(m.vertices[3], Vec3::Z);
}

#[test]
fn off_cube_quads_are_fan_triangulated() {
    let m = load_mesh(fixture("cube.off")).unwrap();
    assert_eq!(m.vertices.len(), 8);
    assert_eq!(m.triangles.len(), 12);
    assert!((m.surface_area() - 6.0).abs() < 1e-12);
    // Quads are outward-facing, so the fan triangles are too.
    let centre = Vec3::splat(0.5);
    for (i, n) in m.face_normals().iter().enumerate() {
        let [a, _, _] = m.triangle(i);
        assert!(
            n.dot(a.as_vec3() - centre) > 0.0,
            "triangle {i} faces inwards"
        );
    }
}

#[test]
fn obj_quads_and_groups_are_triangulated_and_merged() {
    let m = load_mesh(fixture("quads_two_groups.obj")).unwrap();
    assert_eq!(m.triangles.len(), 4);
    assert!((m.surface_area() - 2.0).abs() < 1e-12);
    let zs: Vec<f32> = m.vertices.iter().map(|v| v.z).collect();
    assert_eq!(zs.iter().filter(|&&z| z == 0.0).count(), 4);
    assert_eq!(zs.iter().filter(|&&z| z == 2.0).count(), 4);
    // The same file read from memory gives the same mesh.
    let bytes = std::fs::read(fixture("quads_two_groups.obj")).unwrap();
    assert_eq!(read_obj(&bytes[..], Path::new("mem.obj")).unwrap(), m);
}

#[test]
fn ply_ascii_fixture_gives_mesh_and_coloured_cloud() {
    let m = load_mesh(fixture("square_ascii.ply")).unwrap();
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    let c = read_ply_cloud(fixture("square_ascii.ply")).unwrap();
    assert_eq!(c.points, m.vertices);
    assert_eq!(c.normals, None);
    assert_eq!(
        c.colors,
        Some(vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]])
    );
}

#[test]
fn ply_binary_big_endian_doubles_and_vertex_index_list() {
    let m = load_mesh(fixture("tetra_binary_be_double.ply")).unwrap();
    assert_eq!(m.vertices, vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z]);
    assert_eq!(
        m.triangles,
        vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    );
}

#[test]
fn ply_binary_little_endian_cloud_fixture_with_normals_and_colours() {
    let c = read_ply_cloud(fixture("cloud_binary_le.ply")).unwrap();
    assert_eq!(
        c.points,
        vec![
            Vec3::new(0.1, 0.2, 0.3),
            Vec3::new(-1.5, 2.25, 1e-3),
            Vec3::new(3.0, -4.0, 5.0)
        ]
    );
    assert_eq!(c.normals, Some(vec![Vec3::Z; 3]));
    assert_eq!(c.colors, Some(vec![[0, 0, 0], [1, 2, 3], [2, 4, 6]]));
    // A cloud without faces is not a mesh.
    let e = load_mesh(fixture("cloud_binary_le.ply")).unwrap_err();
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
}

#[test]
fn extension_dispatch_is_case_insensitive() {
    let dir = tempfile::tempdir().unwrap();
    let upper = dir.path().join("CUBE.OFF");
    std::fs::copy(fixture("cube.off"), &upper).unwrap();
    assert_eq!(
        load_mesh(&upper).unwrap(),
        load_mesh(fixture("cube.off")).unwrap()
    );
    let glb = dir.path().join("Scene.GLTF");
    std::fs::copy(fixture("two_nodes.gltf"), &glb).unwrap();
    assert_eq!(load_mesh(&glb).unwrap().triangles.len(), 2);
}

// ------------------------------------------------------------------------------------------
// glTF

/// Expected vertices of `two_nodes.gltf`: the triangle (0,0,0),(1,0,0),(0,1,0) under
/// translate(1,2,3)·scale(2) (indexed), then under a 90° rotation about z (non-indexed).
fn expected_two_nodes() -> Vec<Vec3> {
    vec![
        Vec3::new(1.0, 2.0, 3.0),
        Vec3::new(3.0, 2.0, 3.0),
        Vec3::new(1.0, 4.0, 3.0),
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(-1.0, 0.0, 0.0),
    ]
}

#[test]
fn gltf_node_world_transforms_are_applied_to_every_primitive() {
    let m = load_mesh(fixture("two_nodes.gltf")).unwrap();
    assert_eq!(m.vertices.len(), 6);
    for (a, b) in m.vertices.iter().zip(expected_two_nodes()) {
        assert_close(*a, b);
    }
    assert_eq!(m.triangles, vec![[0, 1, 2], [3, 4, 5]]);
}

fn fixture_json() -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(fixture("two_nodes.gltf")).unwrap()).unwrap()
}

fn fixture_buffer() -> Vec<u8> {
    // The same 44 bytes the fixture embeds: 3 float positions and 3 u16 indices (+2 padding).
    let mut b = Vec::new();
    for v in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for i in [0u16, 1, 2, 0] {
        b.extend_from_slice(&i.to_le_bytes());
    }
    b
}

fn glb(json: &serde_json::Value, bin: &[u8]) -> Vec<u8> {
    let mut json = serde_json::to_vec(json).unwrap();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

#[test]
fn glb_with_binary_chunk_matches_the_embedded_gltf() {
    let mut json = fixture_json();
    json["buffers"][0].as_object_mut().unwrap().remove("uri");
    let bytes = glb(&json, &fixture_buffer());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("two_nodes.glb");
    std::fs::write(&path, &bytes).unwrap();
    assert_eq!(
        load_mesh(&path).unwrap(),
        load_mesh(fixture("two_nodes.gltf")).unwrap()
    );
}

#[test]
fn gltf_external_buffer_is_resolved_next_to_the_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("data.bin"), fixture_buffer()).unwrap();
    let mut json = fixture_json();
    json["buffers"][0]["uri"] = "data.bin".into();
    let path = dir.path().join("external.gltf");
    std::fs::write(&path, serde_json::to_vec(&json).unwrap()).unwrap();
    assert_eq!(load_mesh(&path).unwrap().vertices.len(), 6);
}

fn gltf_error(json: &serde_json::Value) -> String {
    let bytes = serde_json::to_vec(json).unwrap();
    let e = read_gltf(&bytes, None, Path::new("bad.gltf")).unwrap_err();
    assert!(
        matches!(e, MeshError::Format { .. } | MeshError::Data { .. }),
        "{e:?}"
    );
    let s = e.to_string();
    assert!(s.contains("bad.gltf"), "{s}");
    s
}

#[test]
fn gltf_non_triangle_modes_out_of_range_indices_and_cycles_are_errors() {
    let mut lines = fixture_json();
    lines["meshes"][1]["primitives"][0]["mode"] = 1.into();
    let s = gltf_error(&lines);
    assert!(
        s.contains("mesh 1 primitive 0") && s.contains("Lines"),
        "{s}"
    );

    let mut indices = fixture_json();
    indices["accessors"][1]["count"] = 2.into();
    let s = gltf_error(&indices);
    assert!(s.contains("multiple of 3"), "{s}");

    // Index 2 → 7 (byte 40 of the buffer): out of range of the 3 positions.
    let mut buf = fixture_buffer();
    buf[40] = 7;
    let mut json = fixture_json();
    json["buffers"][0].as_object_mut().unwrap().remove("uri");
    let e = read_gltf(&glb(&json, &buf), None, Path::new("bad.glb")).unwrap_err();
    assert!(e.to_string().contains("refers to vertex 7"), "{e}");

    let mut cycle = fixture_json();
    cycle["nodes"][1]["children"] = serde_json::json!([0]);
    let s = gltf_error(&cycle);
    assert!(
        s.contains("not a tree") || s.contains("invalid glTF"),
        "{s}"
    );

    let mut past_end = fixture_json();
    past_end["accessors"][0]["count"] = 4.into();
    let s = gltf_error(&past_end);
    assert!(
        s.contains("past the end") || s.contains("invalid glTF"),
        "{s}"
    );
}

// ------------------------------------------------------------------------------------------
// Round trips

const ENCODINGS: [PlyEncoding; 3] = [
    PlyEncoding::Ascii,
    PlyEncoding::BinaryLittleEndian,
    PlyEncoding::BinaryBigEndian,
];

#[test]
fn mesh_ply_round_trip_is_bit_exact_in_every_encoding() {
    let mesh = awkward_mesh();
    let dir = tempfile::tempdir().unwrap();
    for encoding in ENCODINGS {
        let path = dir.path().join(format!("{encoding:?}.ply"));
        write_mesh_ply(&path, &mesh, encoding).unwrap();
        let back = load_mesh(&path).unwrap();
        assert_eq!(bits(&back.vertices), bits(&mesh.vertices), "{encoding:?}");
        assert_eq!(back.triangles, mesh.triangles, "{encoding:?}");
        // The writer-based variant produces the same bytes.
        let mut bytes = Vec::new();
        write_mesh_ply_to(&mut bytes, &mesh, encoding).unwrap();
        assert_eq!(bytes, std::fs::read(&path).unwrap());
        assert_eq!(read_ply(&bytes[..], &path).unwrap(), back);
    }
    // Only the three outputs: no temporary files left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 3);
}

#[test]
fn cloud_ply_round_trip_with_and_without_attributes() {
    let points = vec![
        Vec3::new(0.1, -0.0, 1e-30),
        Vec3::new(-3.4e38, 1e-45, 7.5),
        Vec3::new(1.0, 2.0, 3.0),
    ];
    let normals = vec![Vec3::X, Vec3::new(0.6, 0.8, 0.0), Vec3::new(0.0, 0.0, -1.0)];
    let colors = vec![[0, 128, 255], [1, 2, 3], [255, 255, 255]];
    let dir = tempfile::tempdir().unwrap();
    for encoding in ENCODINGS {
        for (with_normals, with_colors) in
            [(false, false), (true, false), (false, true), (true, true)]
        {
            let cloud = PointCloud {
                points: points.clone(),
                normals: with_normals.then(|| normals.clone()),
                colors: with_colors.then(|| colors.clone()),
            };
            let path = dir.path().join(format!(
                "cloud_{encoding:?}_{with_normals}_{with_colors}.ply"
            ));
            write_ply(&path, &cloud, encoding).unwrap();
            let back = read_ply_cloud(&path).unwrap();
            assert_eq!(bits(&back.points), bits(&cloud.points), "{encoding:?}");
            assert_eq!(
                back.normals.as_deref().map(bits),
                cloud.normals.as_deref().map(bits)
            );
            assert_eq!(back.colors, cloud.colors);
        }
    }
    // An empty cloud is a valid file too.
    let path = dir.path().join("empty.ply");
    write_ply(&path, &PointCloud::default(), PlyEncoding::Ascii).unwrap();
    assert!(read_ply_cloud(&path).unwrap().is_empty());
}

#[test]
fn ply_header_is_what_meshlab_expects() {
    let cloud = PointCloud {
        points: vec![Vec3::ONE],
        normals: Some(vec![Vec3::Z]),
        colors: Some(vec![[1, 2, 3]]),
    };
    let mut bytes = Vec::new();
    write_ply_to(&mut bytes, &cloud, PlyEncoding::Ascii).unwrap();
    let text = String::from_utf8(bytes).unwrap();
    let expected = "ply\nformat ascii 1.0\ncomment written by ic_geometry\nelement vertex 1\n\
property float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\n\
property float nz\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n\
1 1 1 0 0 1 1 2 3\n";
    assert_eq!(text, expected);
    assert_eq!(
        read_ply_points(text.as_bytes(), Path::new("m.ply")).unwrap(),
        cloud
    );
}

#[test]
fn invalid_clouds_and_meshes_are_rejected_and_nothing_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.ply");
    let nan = PointCloud::from_points(vec![Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0)]);
    let e = write_ply(&path, &nan, PlyEncoding::Ascii).unwrap_err();
    assert!(matches!(e, MeshError::Cloud { .. }), "{e:?}");
    let short = PointCloud {
        points: vec![Vec3::ZERO; 2],
        normals: Some(vec![Vec3::Z]),
        colors: None,
    };
    assert!(matches!(
        write_ply(&path, &short, PlyEncoding::BinaryLittleEndian),
        Err(MeshError::Cloud { .. })
    ));
    let nan_normal = PointCloud {
        points: vec![Vec3::ZERO],
        normals: Some(vec![Vec3::NAN]),
        colors: None,
    };
    assert!(matches!(
        write_ply(&path, &nan_normal, PlyEncoding::Ascii),
        Err(MeshError::Cloud { .. })
    ));
    let broken = Mesh {
        vertices: vec![Vec3::ZERO; 3],
        triangles: vec![[0, 1, 3]],
    };
    let e = write_mesh_ply(&path, &broken, PlyEncoding::Ascii).unwrap_err();
    assert!(
        matches!(
            e,
            MeshError::Data {
                source: MeshDataError::IndexOutOfRange { face: 0, .. },
                ..
            }
        ),
        "{e:?}"
    );
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    // Writing into a missing directory is an I/O error naming the target.
    let missing = dir.path().join("no/such/dir/out.ply");
    let e = write_ply(
        &missing,
        &PointCloud::from_points(vec![Vec3::ONE]),
        PlyEncoding::Ascii,
    )
    .unwrap_err();
    assert!(
        matches!(e, MeshError::Io { .. }) && e.path() == missing,
        "{e:?}"
    );
}

#[test]
fn off_written_by_hand_round_trips_through_read_off() {
    let mesh = awkward_mesh();
    let mut text = format!("OFF{} {} 0\n", mesh.vertices.len(), mesh.triangles.len());
    for v in &mesh.vertices {
        text += &format!("{} {} {}\n", v.x, v.y, v.z);
    }
    for t in &mesh.triangles {
        text += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    let back = read_off(text.as_bytes(), Path::new("rt.off")).unwrap();
    assert_eq!(bits(&back.vertices), bits(&mesh.vertices));
    assert_eq!(back.triangles, mesh.triangles);
}

// ------------------------------------------------------------------------------------------
// Errors name the file and the line or element

fn error_for(name: &str, content: &[u8]) -> MeshError {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, content).unwrap();
    let e = load_mesh(&path).unwrap_err();
    assert_eq!(e.path(), path, "{e:?}");
    assert!(e.to_string().contains(name), "{e}");
    e
}

fn parse_line(e: &MeshError) -> usize {
    match e {
        MeshError::Parse { line, .. } => *line,
        other => panic!("expected a parse error, got {other:?}"),
    }
}

#[test]
fn truncated_and_inconsistent_files_name_file_and_line() {
    let e = error_for("truncated.off", b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 1");
    assert_eq!(parse_line(&e), 5);
    assert!(e.to_string().contains("vertex 2"), "{e}");

    let e = error_for("short.off", b"OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
    assert_eq!(parse_line(&e), 6);
    assert!(e.to_string().contains("1 of 2 faces"), "{e}");

    let e = error_for("face.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2\n");
    assert!(e.to_string().contains("face 0 declares 4 vertices"), "{e}");

    let e = error_for("inf.obj", b"v 0 0 0\nv 1 0 0\nv 0 1e39 0\nf 1 2 3\n");
    assert_eq!(parse_line(&e), 3);
    assert!(e.to_string().contains("vertex 2"), "{e}");

    let e = error_for(
        "range.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 3\nf 1 2 9\n",
    );
    assert_eq!(parse_line(&e), 6);

    let e = error_for("words.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 three\n");
    assert_eq!(parse_line(&e), 4);

    let head = "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
    let mut bytes = head.as_bytes().to_vec();
    for v in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes.push(3);
    for i in [0i32, 1, 3] {
        bytes.extend_from_slice(&i.to_le_bytes());
    }
    let e = error_for("range.ply", &bytes);
    assert!(e.to_string().contains("face 0 refers to vertex 3"), "{e}");
    let e = error_for("cut.ply", &bytes[..bytes.len() - 3]);
    assert!(
        matches!(e, MeshError::Format { .. } | MeshError::Parse { .. }),
        "{e:?}"
    );

    let e = error_for("nofaces.off", b"OFF 3 0 0\n0 0 0\n1 0 0\n0 1 0\n");
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
}

#[test]
fn huge_header_counts_are_errors_not_allocations() {
    let e = read_off(
        &b"OFF\n18446744073709551615 18446744073709551615 0\n0 0 0\n"[..],
        Path::new("h.off"),
    )
    .unwrap_err();
    assert!(e.to_string().contains("vertices"), "{e}");
    let e = read_off(
        &b"OFF 99999999999999999999999 1 0\n"[..],
        Path::new("h.off"),
    )
    .unwrap_err();
    assert_eq!(parse_line(&e), 1);
    let ply = b"ply\nformat ascii 1.0\nelement vertex 1000000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n";
    assert!(read_ply(&ply[..], Path::new("h.ply")).is_err());
}
