//! Robustness of the mesh readers against arbitrary bytes.
//!
//! The property tests feed random bytes and random mutations (byte flips, insertions,
//! deletions, truncations, and token replacements with awkward numbers) of the valid fixtures
//! to every reader and require an `Ok` or an `Err` — never a panic, never a huge allocation.
//! Inputs that once broke a reader are kept below as named regression tests.

use std::path::{Path, PathBuf};

use ic_geometry::MeshError;
use ic_geometry::io::{read_gltf, read_obj, read_off, read_ply, read_ply_points};
use proptest::prelude::*;

fn fixture(name: &str) -> Vec<u8> {
    let path: PathBuf = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/meshes")
        .join(name);
    std::fs::read(path).unwrap()
}

/// Runs every reader on `bytes`; each must return (either way) without panicking. Returns the
/// error messages, which must name the file.
fn run_all_readers(bytes: &[u8]) -> Vec<String> {
    let mut errors = Vec::new();
    let mut check = |name: &str, result: Result<(), MeshError>| {
        if let Err(e) = result {
            let s = e.to_string();
            assert!(s.contains(name), "error does not name the file: {s}");
            errors.push(s);
        }
    };
    check("f.off", read_off(bytes, Path::new("f.off")).map(drop));
    check("f.obj", read_obj(bytes, Path::new("f.obj")).map(drop));
    check("f.ply", read_ply(bytes, Path::new("f.ply")).map(drop));
    check(
        "p.ply",
        read_ply_points(bytes, Path::new("p.ply")).map(drop),
    );
    check(
        "f.glb",
        read_gltf(bytes, None, Path::new("f.glb")).map(drop),
    );
    errors
}

#[derive(Clone, Debug)]
enum Mutation {
    Flip {
        at: usize,
        mask: u8,
    },
    Set {
        at: usize,
        byte: u8,
    },
    Insert {
        at: usize,
        byte: u8,
    },
    Delete {
        at: usize,
        len: usize,
    },
    Truncate {
        at: usize,
    },
    Duplicate {
        at: usize,
        len: usize,
    },
    /// Replaces the number token around `at` with an awkward one.
    Token {
        at: usize,
        which: usize,
    },
}

const AWKWARD: [&str; 14] = [
    "-1",
    "0",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "99999999999999999999999",
    "-9223372036854775808",
    "nan",
    "inf",
    "1e39",
    "-0",
    "3.5",
    "",
    "2147483647",
];

fn mutation() -> impl Strategy<Value = Mutation> {
    let at = any::<usize>();
    prop_oneof![
        (at, 1u8..).prop_map(|(at, mask)| Mutation::Flip { at, mask }),
        (at, any::<u8>()).prop_map(|(at, byte)| Mutation::Set { at, byte }),
        (at, any::<u8>()).prop_map(|(at, byte)| Mutation::Insert { at, byte }),
        (at, 1usize..16).prop_map(|(at, len)| Mutation::Delete { at, len }),
        at.prop_map(|at| Mutation::Truncate { at }),
        (at, 1usize..64).prop_map(|(at, len)| Mutation::Duplicate { at, len }),
        (at, 0..AWKWARD.len()).prop_map(|(at, which)| Mutation::Token { at, which }),
    ]
}

fn apply(bytes: &mut Vec<u8>, m: &Mutation) {
    let n = bytes.len();
    if n == 0 {
        if let Mutation::Insert { byte, .. } = m {
            bytes.push(*byte);
        }
        return;
    }
    match *m {
        Mutation::Flip { at, mask } => bytes[at % n] ^= mask,
        Mutation::Set { at, byte } => bytes[at % n] = byte,
        Mutation::Insert { at, byte } => bytes.insert(at % (n + 1), byte),
        Mutation::Delete { at, len } => {
            let start = at % n;
            bytes.drain(start..(start + len).min(n));
        }
        Mutation::Truncate { at } => bytes.truncate(at % n),
        Mutation::Duplicate { at, len } => {
            let start = at % n;
            let chunk = bytes[start..(start + len).min(n)].to_vec();
            let pos = (start + len).min(n);
            bytes.splice(pos..pos, chunk);
        }
        Mutation::Token { at, which } => {
            let is_num = |b: u8| b.is_ascii_digit() || b == b'.' || b == b'-' || b == b'e';
            let mut start = at % n;
            if !is_num(bytes[start]) {
                return;
            }
            while start > 0 && is_num(bytes[start - 1]) {
                start -= 1;
            }
            let mut end = start;
            while end < n && is_num(bytes[end]) {
                end += 1;
            }
            bytes.splice(start..end, AWKWARD[which].bytes());
        }
    }
}

const FIXTURES: [&str; 7] = [
    "two_nodes.glb",
    "cube.off",
    "modelnet_fused_header.off",
    "quads_two_groups.obj",
    "square_ascii.ply",
    "tetra_binary_be_double.ply",
    "cloud_binary_le.ply",
];

/// 256 cases per property by default (fast); set `IC_FUZZ_CASES` for a longer campaign.
fn config() -> ProptestConfig {
    let cases = std::env::var("IC_FUZZ_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(256);
    ProptestConfig {
        cases,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn fuzz_random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        run_all_readers(&bytes);
    }

    #[test]
    fn fuzz_random_text_never_panics(text in "(OFF|ply|v |f |vt |vn |[0-9 .\n#/-]|format |element |property |end_header\n){0,80}") {
        run_all_readers(text.as_bytes());
    }

    #[test]
    fn fuzz_mutated_fixtures_never_panic(
        which in 0..FIXTURES.len(),
        mutations in proptest::collection::vec(mutation(), 1..6),
    ) {
        let mut bytes = fixture(FIXTURES[which]);
        for m in &mutations {
            apply(&mut bytes, m);
        }
        run_all_readers(&bytes);
    }

    #[test]
    fn fuzz_mutated_glb_never_panics(
        binary in any::<bool>(),
        mutations in proptest::collection::vec(mutation(), 1..4),
    ) {
        let mut bytes = fixture(if binary { "two_nodes.glb" } else { "two_nodes.gltf" });
        for m in &mutations {
            apply(&mut bytes, m);
        }
        run_all_readers(&bytes);
    }

    /// Well-formed OBJ lines with small (possibly zero, negative, out-of-range) indices: the
    /// pre-pass must stop everything tobj would mishandle.
    #[test]
    fn fuzz_structured_obj_never_panics(lines in proptest::collection::vec(obj_line(), 0..24)) {
        let text = lines.concat();
        if let Ok(mesh) = read_obj(text.as_bytes(), Path::new("s.obj")) {
            prop_assert!(mesh.validate().is_ok());
        }
    }

    /// Well-formed OFF structure with random counts and indices.
    #[test]
    fn fuzz_structured_off_never_panics(
        counts in (0usize..6, 0usize..6, any::<bool>()),
        vertices in proptest::collection::vec((-2i8..3, -2i8..3, -2i8..3), 0..6),
        faces in proptest::collection::vec(proptest::collection::vec(-2i64..8, 0..6), 0..6),
    ) {
        let (nv, nf, fused) = counts;
        let mut text = if fused { format!("OFF{nv} {nf} 0\n") } else { format!("OFF\n{nv} {nf} 0\n") };
        for (x, y, z) in vertices {
            text += &format!("{x} {y} {z}\n");
        }
        for f in faces {
            text += &f.len().to_string();
            for i in f {
                text += &format!(" {i}");
            }
            text += "\n";
        }
        if let Ok(mesh) = read_off(text.as_bytes(), Path::new("s.off")) {
            prop_assert!(mesh.validate().is_ok());
        }
    }
}

fn obj_index() -> impl Strategy<Value = String> {
    prop_oneof![
        (-5i64..6).prop_map(|i| i.to_string()),
        (-5i64..6, -5i64..6).prop_map(|(v, t)| format!("{v}/{t}")),
        (-5i64..6, -5i64..6).prop_map(|(v, n)| format!("{v}//{n}")),
        (-5i64..6, -5i64..6, -5i64..6).prop_map(|(v, t, n)| format!("{v}/{t}/{n}")),
        Just("-9223372036854775808/1".to_string()),
        Just("1/-9223372036854775808".to_string()),
    ]
}

fn obj_line() -> impl Strategy<Value = String> {
    prop_oneof![
        3 => (-3i8..4, -3i8..4, -3i8..4).prop_map(|(x, y, z)| format!("v {x} {y} {z}\n")),
        1 => Just("v 1 2 3 0.5\n".to_string()),
        1 => Just("v 1 2 3 0.1 0.2 0.3\n".to_string()),
        1 => Just("vt 0.5 0.5\n".to_string()),
        1 => Just("vn 0 0 1\n".to_string()),
        4 => proptest::collection::vec(obj_index(), 0..6).prop_map(|c| format!("f {}\n", c.join(" "))),
        1 => proptest::collection::vec(obj_index(), 0..3).prop_map(|c| format!("l {}\n", c.join(" "))),
        1 => Just("o next\n".to_string()),
        1 => Just("g\n".to_string()),
        1 => Just("usemtl red\n".to_string()),
    ]
}

// ------------------------------------------------------------------------------------------
// Regressions: inputs that the property tests (or review) showed to be dangerous.

#[test]
fn all_readers_accept_the_unmutated_fixtures_or_reject_them_cleanly() {
    for name in FIXTURES {
        run_all_readers(&fixture(name));
    }
}

/// Found by `fuzz_mutated_glb_never_panics`: gltf-json 1.4's validation indexes
/// `accessors[POSITION]` before checking the index and panicked on `"POSITION": -1 → 4294967295`
/// style mutations. We check that reference ourselves before running its validation.
#[test]
fn gltf_position_accessor_index_out_of_range_is_an_error_not_a_panic() {
    let text = String::from_utf8(fixture("two_nodes.gltf")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = 7.into();
    let bytes = serde_json::to_vec(&json).unwrap();
    let e = read_gltf(&bytes, None, Path::new("f.gltf")).unwrap_err();
    assert!(
        e.to_string().contains("POSITION refers to accessor 7"),
        "{e}"
    );
    // With no accessors at all.
    json["accessors"] = serde_json::json!([]);
    let bytes = serde_json::to_vec(&json).unwrap();
    assert!(read_gltf(&bytes, None, Path::new("f.gltf")).is_err());
}

/// Relative texture index before any `vt` line: tobj would compute `usize::MAX - 3` and then
/// overflow `vt * 2 + 1` (a panic with overflow checks, an out-of-bounds slice without).
#[test]
fn obj_relative_texcoord_index_before_any_texcoord_is_an_error_not_an_overflow() {
    let text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1/-4 2/-4 3/-4\nvt 0 0\n";
    match read_obj(&text[..], Path::new("f.obj")) {
        Err(MeshError::Parse { line: 4, .. }) => {}
        other => panic!("{other:?}"),
    }
    let text = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//-9223372036854775808 2//1 3//1\n";
    assert!(matches!(
        read_obj(&text[..], Path::new("f.obj")),
        Err(MeshError::Parse { line: 5, .. })
    ));
}

#[test]
fn off_header_count_larger_than_file_is_an_error_not_an_allocation() {
    let text = b"OFF\n4000000000000 4000000000000 0\n0 0 0\n";
    let e = read_off(&text[..], Path::new("f.off")).unwrap_err();
    assert!(matches!(e, MeshError::Parse { line: 3, .. }), "{e:?}");
    assert!(
        e.to_string()
            .contains("ends after 1 of 4000000000000 vertices"),
        "{e}"
    );
}

#[test]
fn off_face_vertex_count_larger_than_the_line_is_an_error_not_an_allocation() {
    let text = b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n18446744073709551615 0 1 2\n";
    let e = read_off(&text[..], Path::new("f.off")).unwrap_err();
    assert!(e.to_string().contains("lists only 3"), "{e}");
}

#[test]
fn ply_header_count_larger_than_file_is_an_error_not_an_allocation() {
    let text =
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\n\
property float y\nproperty float z\nend_header\n\0\0\0\0";
    let e = read_ply_points(&text[..], Path::new("f.ply")).unwrap_err();
    assert!(e.to_string().contains("cannot hold"), "{e}");
}

/// An element with no properties takes zero bytes per record, so a binary reader would loop
/// (and push records) `count` times without consuming input.
#[test]
fn ply_binary_element_without_properties_is_an_error_not_an_endless_loop() {
    let text = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n\
property float y\nproperty float z\nelement face 18446744073709551615\nend_header\n\0\0\0\0\0\0\0\0\0\0\0\0";
    let e = read_ply(&text[..], Path::new("f.ply")).unwrap_err();
    assert!(
        e.to_string().contains("no properties") || e.to_string().contains("cannot hold"),
        "{e}"
    );
}

#[test]
fn ply_face_list_with_huge_binary_length_is_an_error_not_an_allocation() {
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
property float y\nproperty float z\nelement face 1\nproperty list uint int vertex_indices\nend_header\n"
        .to_vec();
    bytes.extend_from_slice(&[0u8; 36]);
    bytes.extend_from_slice(&u32::MAX.to_le_bytes());
    bytes.extend_from_slice(&[0u8; 12]);
    assert!(read_ply(&bytes[..], Path::new("f.ply")).is_err());
}

/// glTF requires the node hierarchy to be a forest; a cycle would otherwise recurse forever and
/// shared children would multiply the work exponentially.
#[test]
fn gltf_node_cycle_is_an_error_not_an_endless_traversal() {
    let text = String::from_utf8(fixture("two_nodes.gltf")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json["nodes"][1]["children"] = serde_json::json!([0]);
    let bytes = serde_json::to_vec(&json).unwrap();
    assert!(read_gltf(&bytes, None, Path::new("f.gltf")).is_err());
    json["nodes"][1]["children"] = serde_json::json!([]);
    json["nodes"][2]["children"] = serde_json::json!([1]);
    let bytes = serde_json::to_vec(&json).unwrap();
    let e = read_gltf(&bytes, None, Path::new("f.gltf")).unwrap_err();
    assert!(e.to_string().contains("not a tree"), "{e}");
}

#[test]
fn glb_truncated_binary_chunk_is_an_error() {
    let bytes = fixture("two_nodes.glb");
    for cut in [0, 4, 12, 20, bytes.len() / 2, bytes.len() - 1] {
        assert!(
            read_gltf(&bytes[..cut], None, Path::new("f.glb")).is_err(),
            "cut at {cut}"
        );
    }
    assert!(read_gltf(&bytes, None, Path::new("f.glb")).is_ok());
}

/// Found by `fuzz_mutated_glb_never_panics` and `fuzz_mutated_fixtures_never_panic`: gltf 1.4
/// subtracts the 12-byte header size from the declared GLB length unchecked ("attempt to
/// subtract with overflow" for a declared length below 12). The header is now checked first.
#[test]
fn glb_declared_length_below_header_size_is_an_error_not_an_overflow() {
    let mut bytes = fixture("two_nodes.glb");
    for declared in [0u32, 1, 11] {
        bytes[8..12].copy_from_slice(&declared.to_le_bytes());
        let e = read_gltf(&bytes, None, Path::new("f.glb")).unwrap_err();
        assert!(e.to_string().contains("less than the header"), "{e}");
    }
    let e = read_gltf(b"glTF\x02\0\0\0\x05", None, Path::new("f.glb")).unwrap_err();
    assert!(e.to_string().contains("truncated"), "{e}");
}
