//! Seeded property tests of the input readers (Matrix Market, constraint JSON, scene
//! TOML, Gmsh): valid samples mutated at random (bytes cut, repeated, replaced by
//! troublesome tokens such as `1e999`, `-0`, `4.`, `nan`, huge counts) and random bytes.
//! Every input must give a value or a one-line error, never a panic. The seed is fixed,
//! so a run is reproducible; `STICKSLIP_FUZZ_CASES` sets the cases per reader (default
//! 1,500; the long runs outside CI use cargo-fuzz, see fuzz/).

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};

mod common;
use common::readers;

/// Tokens that have broken readers elsewhere: overflow, signs, cut numbers, non-finite
/// spellings, separators, section markers.
const TOKENS: &[&str] = &[
    "0",
    "-0",
    "1",
    "-1",
    "4.",
    ".5",
    "1e308",
    "1e309",
    "-1e999",
    "4e",
    "nan",
    "inf",
    "-inf",
    "2147483647",
    "2147483648",
    "18446744073709551616",
    "99999999999999999999999999",
    "1e-320",
    "0x10",
    "\n",
    "\r\n",
    " ",
    "\t",
    "%",
    "%%MatrixMarket",
    "matrix",
    "coordinate",
    "array",
    "symmetric",
    "general",
    "real",
    "integer",
    "pattern",
    "complex",
    "{",
    "}",
    "[",
    "]",
    ",",
    ":",
    "\"",
    "=",
    "[[",
    "]]",
    "\"node\"",
    "\"kind\"",
    "\"rows\"",
    "\"plane\"",
    "\"sticky\"",
    "\"line\"",
    "null",
    "true",
    "\u{feff}",
    "\u{a0}",
    "é",
    "$Nodes",
    "$EndNodes",
    "$Elements",
    "$EndElements",
    "$MeshFormat",
    "4.1 0 8",
    "4.1 1 8",
    "\u{0}",
];

/// One mutation of a sample: (kind, position, length, token).
type Mutation = (u8, u32, u16, u8);

/// Applies the mutations in order: cut a range, insert a token, replace a range with a
/// token, repeat a range, flip a byte, truncate.
fn mutate(sample: &[u8], muts: &[Mutation]) -> Vec<u8> {
    let mut b = sample.to_vec();
    for &(kind, pos, len, tok) in muts {
        let at = if b.is_empty() {
            0
        } else {
            pos as usize % (b.len() + 1)
        };
        let end = (at + len as usize % 64).min(b.len());
        let token = TOKENS[tok as usize % TOKENS.len()].as_bytes();
        match kind % 6 {
            0 => {
                b.drain(at..end);
            }
            1 => {
                b.splice(at..at, token.iter().copied());
            }
            2 => {
                b.splice(at..end, token.iter().copied());
            }
            3 => {
                let piece = b[at..end].to_vec();
                b.splice(at..at, piece);
            }
            4 => {
                if at < b.len() {
                    b[at] ^= 1 << (tok % 8);
                }
            }
            _ => b.truncate(at),
        }
    }
    b
}

/// Mutated samples and, one case in eight, raw random bytes.
fn inputs(samples: Vec<Vec<u8>>) -> impl Strategy<Value = Vec<u8>> {
    let n = samples.len();
    prop_oneof![
        7 => (0..n, prop::collection::vec(any::<Mutation>(), 0..8))
            .prop_map(move |(k, m)| mutate(&samples[k], &m)),
        1 => prop::collection::vec(any::<u8>(), 0..512),
    ]
}

fn cases() -> u32 {
    std::env::var("STICKSLIP_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1500)
}

/// Runs `check` on `cases()` inputs from `samples`, with a fixed seed per reader.
fn fuzz(name: &str, seed: u8, samples: Vec<Vec<u8>>, check: fn(&[u8])) {
    let config = Config {
        cases: cases(),
        failure_persistence: None,
        ..Config::default()
    };
    let rng = TestRng::from_seed(RngAlgorithm::ChaCha, &[seed; 32]);
    let mut runner = TestRunner::new_with_rng(config, rng);
    let result = runner.run(&inputs(samples), |bytes| {
        check(&bytes);
        Ok(())
    });
    if let Err(e) = result {
        panic!("{name}: {e}");
    }
    eprintln!("{name}: {} inputs, no panic", cases());
}

fn bytes(v: &[&str]) -> Vec<Vec<u8>> {
    v.iter().map(|s| s.as_bytes().to_vec()).collect()
}

#[test]
fn matrix_market_reader() {
    fuzz(
        "Matrix Market",
        1,
        bytes(&[
            "%%MatrixMarket matrix coordinate real symmetric\n% H\n6 6 7\n1 1 2\n2 2 2\n3 1 -1\n3 3 2\n4 4 2\n5 5 2.5e0\n6 6 1\n",
            "%%MatrixMarket matrix coordinate real general\n4 4 6\n1 1 2\n1 3 -1\n3 1 -1\n2 2 2\n3 3 2\n4 4 2\n",
            "%%MatrixMarket matrix coordinate integer symmetric\n4 4 4\n1 1 2\n2 2 2\n3 3 2\n4 4 2\n",
            "%%MatrixMarket matrix array real general\n12 1\n1\n2\n3\n4\n5\n6\n7\n8\n9\n10\n11\n12\n",
            "%%MatrixMarket matrix array real general\n1 12\n1\n2\n3\n4\n5\n6\n7\n8\n9\n10\n11\n12\n",
            "%%MatrixMarket matrix coordinate real general\n12 1 2\n3 1 1.5\n12 1 -2\n",
            "%%MatrixMarket matrix coordinate real general\n3 6 4\n1 1 1\n2 3 1\n2 4 1\n3 5 0.5\n",
        ]),
        readers::matrix_market,
    );
}

#[test]
fn constraint_json_reader() {
    fuzz(
        "constraint JSON",
        2,
        bytes(&[
            r#"{"dim": 3, "constraints": [
  {"node": 0, "kind": "sticky"},
  {"node": 1, "kind": "sticky", "displacement": [0.0, 0.1, 0.0]},
  {"node": 4, "kind": "plane", "normal": [0, 1, 0]},
  {"node": 5, "kind": "plane", "normal": [2, 3, 0], "offset": 0.0},
  {"node": 7, "kind": "line",  "direction": [1, 1, 0]},
  {"node": 9, "kind": "rows",  "rows": [[1, 0, 0], [0, 1, 1]], "values": [0, 0]}]}"#,
            r#"{"dim": 2, "constraints": [{"node": 1, "kind": "sticky", "displacement": [1, 2]}, {"node": 2, "kind": "plane", "normal": [1e-300, 1], "offset": 3}, {"node": 2, "kind": "line", "direction": [1, 0], "offset": [0, 3]}]}"#,
            r#"{"constraints": [{"node": 3, "kind": "rows", "rows": [[1, 1], [2, 2]], "values": [1, 2]}]}"#,
        ]),
        readers::constraint_json,
    );
}

#[test]
fn scene_toml_reader() {
    let mut samples: Vec<Vec<u8>> = stickslip::sim::scene::BUILTIN
        .iter()
        .map(|(_, t)| t.as_bytes().to_vec())
        .collect();
    samples.push(
        b"dimension = 2\ntime_step = 0.01\nsteps = 3\n[[bodies]]\nmesh = { kind = \"rectangle\", size = [1.0, 0.5], cells = [4, 2] }\nmaterial = { model = \"neo-hookean\", young = 1e4, poisson = 0.3, density = 100 }\n[[boundary]]\nkind = \"plane\"\nnormal = [0.0, 1.0]\nregion = { box = { min = [-1, -1], max = [2, 0.01] } }\n"
            .to_vec(),
    );
    fuzz("scene TOML", 3, samples, readers::scene_toml);
}

/// The unit square (four triangles around a centre node, tags out of order), ASCII and
/// binary, and one tetrahedron.
fn gmsh_samples() -> Vec<Vec<u8>> {
    let ascii = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n2 5 1 5\n2 1 0 2\n4\n5\n0 1 0\n0.5 0.5 0\n2 1 0 3\n3\n1\n2\n1 1 0\n0 0 0\n1 0 0\n$EndNodes\n$Elements\n2 5 1 5\n1 1 1 1\n5 1 2\n2 1 2 4\n1 1 2 5\n2 2 3 5\n3 3 4 5\n4 4 1 5\n$EndElements\n";
    let tet = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 4 1 4\n3 1 0 4\n1\n2\n3\n4\n0 0 0\n0 1 0\n1 0 0\n0 0 1\n$EndNodes\n$Elements\n1 1 1 1\n3 1 4 1\n1 1 2 3 4\n$EndElements\n";
    let mut bin: Vec<u8> = b"$MeshFormat\n4.1 1 8\n".to_vec();
    bin.extend(1i32.to_le_bytes());
    bin.extend(b"\n$EndMeshFormat\n$Nodes\n");
    for v in [1u64, 5, 1, 5] {
        bin.extend(v.to_le_bytes());
    }
    for v in [2i32, 1, 0] {
        bin.extend(v.to_le_bytes());
    }
    bin.extend(5u64.to_le_bytes());
    let nodes = [
        (5u64, [0.5, 0.5]),
        (4, [0.0, 1.0]),
        (3, [1.0, 1.0]),
        (2, [1.0, 0.0]),
        (1, [0.0, 0.0]),
    ];
    for (t, _) in &nodes {
        bin.extend(t.to_le_bytes());
    }
    for (_, p) in &nodes {
        for v in [p[0], p[1], 0.0f64] {
            bin.extend(v.to_le_bytes());
        }
    }
    bin.extend(b"\n$EndNodes\n$Elements\n");
    for v in [1u64, 4, 1, 4] {
        bin.extend(v.to_le_bytes());
    }
    for v in [2i32, 1, 2] {
        bin.extend(v.to_le_bytes());
    }
    bin.extend(4u64.to_le_bytes());
    for (k, e) in [[1u64, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5]]
        .iter()
        .enumerate()
    {
        bin.extend((k as u64 + 1).to_le_bytes());
        for t in e {
            bin.extend(t.to_le_bytes());
        }
    }
    bin.extend(b"\n$EndElements\n");
    vec![ascii.as_bytes().to_vec(), tet.as_bytes().to_vec(), bin]
}

#[test]
fn gmsh_reader() {
    fuzz("Gmsh", 4, gmsh_samples(), readers::gmsh);
}

/// The samples themselves read as what they are (so the mutations start from inputs the
/// readers accept).
#[test]
fn samples_are_valid() {
    let m = stickslip::sim::mesh::gmsh(2, &gmsh_samples()[0]).expect("square");
    assert_eq!(m.n_nodes(), 5);
    assert!(stickslip::sim::mesh::gmsh(3, &gmsh_samples()[1]).is_ok());
    assert!(stickslip::sim::mesh::gmsh(2, &gmsh_samples()[2]).is_ok());
    for (name, t) in stickslip::sim::scene::BUILTIN {
        assert!(stickslip::sim::scene::parse(t, name, 1.0).is_ok(), "{name}");
    }
}

/// Inputs the fuzzing found that once panicked inside mshio (its format-line parser; with
/// overflow checks, a section declaring zero nodes or elements): each is now an error.
#[test]
fn inputs_that_once_panicked_are_errors() {
    // The binary square with 0 in the node count, then in the element count.
    let bin = gmsh_samples()[2].clone();
    for section in [&b"$Nodes\n"[..], &b"$Elements\n"[..]] {
        let at = bin
            .windows(section.len())
            .position(|w| w == section)
            .unwrap()
            + section.len();
        let mut b = bin.clone();
        b[at + 8..at + 16].copy_from_slice(&0u64.to_le_bytes());
        let e = stickslip::sim::mesh::gmsh(2, &b).unwrap_err();
        assert!(e.contains("declares no"), "{e}");
    }
    // The ASCII square with 0 in a count, after a long run of blank space (mshio skips
    // any amount of it).
    let square = String::from_utf8(gmsh_samples()[0].clone()).unwrap();
    for section in ["$Nodes\n", "$Elements\n"] {
        let at = square.find(section).unwrap() + section.len();
        let line_end = at + square[at..].find('\n').unwrap();
        let mut header: Vec<&str> = square[at..line_end].split(' ').collect();
        header[1] = "0";
        let text = format!(
            "{}{}{}{}",
            &square[..at],
            " \n\t".repeat(200),
            header.join(" "),
            &square[line_end..]
        );
        for dim in [2, 3] {
            let e = stickslip::sim::mesh::gmsh(dim, text.as_bytes()).unwrap_err();
            assert!(e.contains("declares no"), "{section}: {e}");
        }
    }
    // The fuzzer's crash inputs, kept as seeds (some hold a second $Elements section that
    // mshio reaches only because a malformed binary $Nodes section runs over the first):
    // each is refused before mshio runs, never by a panic contained inside it.
    let seeds = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/seeds/gmsh");
    let mut crashes = 0;
    for e in std::fs::read_dir(&seeds).unwrap().flatten() {
        if e.file_name().to_string_lossy().starts_with("crash-") {
            let bytes = std::fs::read(e.path()).unwrap();
            for dim in [2, 3] {
                // Each declares zero nodes or elements in a section mshio reaches, where
                // its tag arithmetic underflows.
                let msg = stickslip::sim::mesh::gmsh(dim, &bytes).unwrap_err();
                assert!(
                    msg.contains("declares no"),
                    "{}: {msg}",
                    e.file_name().to_string_lossy()
                );
            }
            readers::gmsh(&bytes);
            crashes += 1;
        }
    }
    assert!(
        crashes >= 5,
        "{crashes} crash inputs in {}",
        seeds.display()
    );
    let square = String::from_utf8(gmsh_samples()[0].clone()).unwrap();
    for (format, want) in [
        ("4.1 0 99999999999999999999", "data size"),
        ("4.1 1 3", "data size"),
        ("4.1 1 16", "data size"),
        ("4.1 7 8", "file type"),
        ("4.1 0", "format line"),
    ] {
        let text = square.replace("4.1 0 8", format);
        for dim in [2, 3] {
            let e = stickslip::sim::mesh::gmsh(dim, text.as_bytes()).unwrap_err();
            assert!(e.contains(want), "{format}: {e}");
        }
    }
}
