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
    let path: PathBuf = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/meshes").join(name);
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
    check("p.ply", read_ply_points(bytes, Path::new("p.ply")).map(drop));
    check("f.glb", read_gltf(bytes, None, Path::new("f.glb")).map(drop));
    errors
}

#[derive(Clone, Debug)]
enum Mutation {
    Flip { at: usize, mask: u8 },
    Set { at: usize, byte: u8 },
    Insert { at: usize, byte: u8 },
    Delete { at: usize, len: usize },
    Truncate { at: usize },
    Duplicate { at: usize, len: usize },
    /// Replaces the number token around `at` with an awkward one.
    Token { at: usize, which: usize },
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
        (at.clone(), 1u8..).prop_map(|(at, mask)| Mutation::Flip { at, mask }),
        (at.clone(), any::<u8>()).prop_map(|(at, byte)| Mutation::Set { at, byte }),
        (at.clone(), any::<u8>()).prop_map(|(at, byte)| Mutation::Insert { at, byte }),
        (at.clone(), 1usize..16).prop_map(|(at, len)| Mutation::Delete { at, len }),
        at.clone().prop_map(|at| Mutation::Truncate { at }),
        (at.clone(), 1usize..64).prop_map(|(at, len)| Mutation::Duplicate { at, len }),
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

const FIXTURES: [&str; 6] = [
    "cube.off",
    "modelnet_fused_header.off",
    "quads_two_groups.obj",
    "square_ascii.ply",
    "tetra_binary_be_double.ply",
    "cloud_binary_le.ply",
];

/// 256 cases per property by default (fast); set `IC_FUZZ_CASES` for a longer campaign.
fn config() -> ProptestConfig {
    let cases = std::env::var("IC_FUZZ_CASES").ok().and_then(|s| s.parse().ok()).unwrap_or(256);
    ProptestConfig { cases, failure_persistence: None, ..ProptestConfig::default() }
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
    fn fuzz_mutated_glb_never_panics(mutations in proptest::collection::vec(mutation(), 1..4)) {
        let mut bytes = fixture("two_nodes.gltf");
        for m in &mutations {
            apply(&mut bytes, m);
        }
        run_all_readers(&bytes);
    }
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
    assert!(e.to_string().contains("POSITION refers to accessor 7"), "{e}");
    // With no accessors at all.
    json["accessors"] = serde_json::json!([]);
    let bytes = serde_json::to_vec(&json).unwrap();
    assert!(read_gltf(&bytes, None, Path::new("f.gltf")).is_err());
}
