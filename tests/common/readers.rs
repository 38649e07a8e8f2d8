//! The four input readers driven on arbitrary bytes, as the command line drives them:
//! each call must return (a value or a one-line error), never panic. Shared by the
//! seeded property tests (tests/fuzz_readers.rs) and the cargo-fuzz targets (fuzz/).

use stickslip::error::InputError;
use stickslip::io::{bcjson, mtx};

/// An error as the command line prints it: one line, bounded (tokens are cut at 80
/// characters, paths at 4096).
pub fn one_line<T>(r: Result<T, InputError>) -> Option<T> {
    match r {
        Ok(v) => Some(v),
        Err(e) => {
            let line = e.to_string();
            assert!(!line.contains('\n'), "not one line: {line:?}");
            assert!(line.len() <= 8192, "{} bytes: {}", line.len(), &line[..200]);
            None
        }
    }
}

/// Text as `io::read_text` hands it on: UTF-8 without NUL bytes, else refused there.
fn text(bytes: &[u8]) -> Option<&str> {
    let t = std::str::from_utf8(bytes).ok()?;
    (!t.contains('\0')).then_some(t)
}

/// Matrix Market: H (2D and 3D blocks, bounded by a g of 3000 rows and 64 constrained
/// nodes as `solve` bounds it), g and p (against the length H gives), B (general, then
/// turned into per-node constraints and frames).
pub fn matrix_market(bytes: &[u8]) {
    let Some(t) = text(bytes) else { return };
    for dim in [2, 3] {
        let bounds = mtx::HessianBounds {
            max_rows: Some((3000, "the 3000 rows of g")),
            constrained_nodes: Some(64),
        };
        if let Some(h) = one_line(mtx::hessian_from_text("H.mtx", t, dim, &bounds)) {
            assert_eq!(h.dim, dim);
        }
    }
    one_line(mtx::vector_from_text(
        "g.mtx",
        t,
        "g",
        Some((12, "12 = 2 × 6 nodes")),
    ));
    if let Some(b) = one_line(mtx::matrix_from_text("B.mtx", t, "B")) {
        for dim in [2, 3] {
            let n = b.ncols / dim;
            if b.ncols % dim != 0 || n > 100_000 {
                continue;
            }
            if let Some(cs) = one_line(bcjson::constraints_from_matrix("B.mtx", &b, None, dim, n)) {
                frames(dim, n, &cs);
            }
        }
    }
}

/// Per-node frames of parsed constraints (the rank and consistency checks): Ok or an
/// error naming the constraint.
fn frames(dim: usize, n: usize, cs: &[stickslip::core::constraints::Constraint]) {
    if let Err(e) = stickslip::core::constraints::Frames::build(dim, n, cs) {
        let line = e.to_string();
        assert!(!line.contains('\n'), "{line:?}");
    }
}

/// Constraint JSON with the dimension from the file, or 2 or 3 from the command line;
/// then the frames on as many nodes as the constraints name (up to 100,000).
pub fn constraint_json(bytes: &[u8]) {
    let Some(t) = text(bytes) else { return };
    for dim in [None, Some(2), Some(3)] {
        let Some(f) = one_line(bcjson::parse("bc.json", t, dim)) else {
            continue;
        };
        let Some(d) = dim.or(f.dim) else { continue };
        let n = f.constraints.iter().map(|c| c.node + 1).max().unwrap_or(1);
        if n <= 100_000 {
            frames(d, n, &f.constraints);
        }
    }
}

/// A scene file, parsed and resolved (meshes built, conditions applied, obstacles
/// checked). Scenes asking for large meshes are skipped: they are slow, not wrong.
pub fn scene_toml(bytes: &[u8]) {
    let Some(t) = text(bytes) else { return };
    let big = t.lines().filter(|l| l.contains("cells")).any(|l| {
        l.split(|c: char| !c.is_ascii_digit())
            .any(|d| d.len() > 2 && d.parse::<u64>().map_or(true, |v| v > 64))
    });
    if big || t.len() > 16_384 {
        return;
    }
    one_line(stickslip::sim::scene::parse(t, "scene.toml", 1.0));
}

/// A Gmsh MSH 4.1 file (ASCII or binary) read as a 2D and as a 3D mesh.
pub fn gmsh(bytes: &[u8]) {
    for dim in [2, 3] {
        if let Ok(m) = stickslip::sim::mesh::gmsh(dim, bytes) {
            // What was read is a usable mesh: every element's nodes exist.
            let n = m.n_nodes();
            assert!(m.elements.iter().flatten().all(|&i| i < n));
        }
    }
}
