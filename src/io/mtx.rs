//! Matrix Market reading and writing.
//!
//! Read: H (coordinate real or integer, symmetric or general, dn × dn), g and p (array or
//! coordinate, a column or a row vector), B (coordinate, m × dn). Written: Δx and
//! reactions as `array real general` dn × 1 with 17 significant digits, and H (symmetric
//! coordinate, lower triangle) plus g for `stickslip generate`.
//!
//! The reader is a line-based parser of our own rather than
//! `nalgebra_sparse::io::load_coo_from_matrix_market_str`: that one (pest) builds a token
//! tree of the whole file first. On a generated 97,336-node 3D H (6.49M stored entries,
//! 221 MB) it took 12.4 s and about 3 GB of memory, against 0.6 s for this parser (plus
//! 1.0 s to build and validate the blocks), and its errors carry neither line numbers
//! nor 1-based entries; this one reports every fault by line or entry.
//! [`read_coo_nalgebra`] keeps the library path for comparison (and the timing test).
//!
//! Nothing is allocated from a size line alone: the entry list is reserved for no more
//! than the text can hold, vectors are checked against their expected length on the size
//! line ([`read_vector`]), H against the other inputs ([`read_hessian_bounded`]), and
//! every size line against [`MAX_DIMENSION`] and the machine's memory
//! ([`MIN_BYTES_PER_ROW`]). Duplicate coordinate entries sum, and the sums are checked
//! for finiteness where they are formed (vectors here, H in `BlockCsr::validate`, B in
//! `bcjson::constraints_from_matrix`).

use crate::core::sparse::BlockCsr;
use crate::error::InputError;
use std::fmt::Write as _;
use std::io::Write as _;

/// A matrix read from a Matrix Market file: entries 0-based, duplicates kept (they sum).
#[derive(Debug, Clone, PartialEq)]
pub struct Coo {
    pub nrows: usize,
    pub ncols: usize,
    /// True when the file said `symmetric`: `entries` then hold the lower triangle only.
    pub symmetric: bool,
    pub entries: Vec<(usize, usize, f64)>,
    /// 1-based line number of the size line (for shape errors).
    pub size_line: usize,
}

fn err(file: &str, entry: impl Into<String>, problem: impl Into<String>) -> InputError {
    InputError::new(file, entry, problem)
}

/// Text from the file quoted in a message: at most 60 characters, with control
/// characters and unusual spaces (tab, no-break space, BOM) shown as escapes, since they
/// are often the fault.
fn quote(s: &str) -> String {
    super::escaped(s.trim_matches(' '), 60)
}

/// Largest row or column count accepted (2³¹ − 1: indices are 32-bit on the GPU and in PETSc).
pub const MAX_DIMENSION: usize = i32::MAX as usize;

/// The least memory a system row costs once read (H's diagonal block and its triplet,
/// g, Δx, b̂, y, the lift, the reactions: well over 64 bytes). A size line declaring
/// more rows than the machine's memory holds at this rate is refused before reading on.
pub const MIN_BYTES_PER_ROW: u64 = 64;

/// The most rows (or columns) a size line may declare on a machine with `memory` bytes.
pub fn max_rows_for_memory(memory: u64) -> usize {
    usize::try_from(memory / MIN_BYTES_PER_ROW)
        .unwrap_or(usize::MAX)
        .min(MAX_DIMENSION)
}

/// The header and size line of a Matrix Market file: what it declares, before any entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    pub nrows: usize,
    pub ncols: usize,
    /// The stored entries the size line announces (coordinate), or rows × columns (array).
    pub entries: usize,
    pub coordinate: bool,
    /// The file said `symmetric` (entries then hold the lower triangle only).
    pub symmetric: bool,
    /// 1-based line number of the size line.
    pub size_line: usize,
}

impl Header {
    /// The length of the vector the file declares (n × 1 or 1 × n), None for a matrix.
    pub fn vector_len(&self) -> Option<usize> {
        if self.ncols == 1 {
            Some(self.nrows)
        } else if self.nrows == 1 {
            Some(self.ncols)
        } else {
            None
        }
    }
}

/// Reads the header and the size line from `lines` (numbered, 1-based), leaving the
/// iterator after the size line. Checks the banner, the size line's form and
/// MAX_DIMENSION.
fn parse_header<'a>(
    file: &str,
    lines: &mut impl Iterator<Item = (usize, &'a str)>,
) -> Result<Header, InputError> {
    let (hl, header) = loop {
        match lines.next() {
            Some((_, l)) if l.trim().is_empty() => continue,
            Some(x) => break x,
            None => {
                return Err(err(
                    file,
                    "",
                    "the file is empty (expected a Matrix Market header)",
                ))
            }
        }
    };
    let toks: Vec<String> = header
        .split_whitespace()
        .take(6)
        .map(|t| t.to_ascii_lowercase())
        .collect();
    if toks.first().map(String::as_str) != Some("%%matrixmarket") {
        return Err(err(
            file,
            format!("line {hl}"),
            "not a Matrix Market file: the first line must start with %%MatrixMarket",
        ));
    }
    if toks.len() != 5 || toks[1] != "matrix" {
        return Err(err(
            file,
            format!("line {hl}"),
            "malformed header: expected '%%MatrixMarket matrix coordinate|array real|integer general|symmetric'",
        ));
    }
    let coordinate = match toks[2].as_str() {
        "coordinate" => true,
        "array" => false,
        other => {
            return Err(err(
                file,
                format!("line {hl}"),
                format!(
                    "unknown format '{}' (expected coordinate or array)",
                    quote(other)
                ),
            ))
        }
    };
    match toks[3].as_str() {
        "real" | "integer" | "double" => {}
        other => {
            return Err(err(
                file,
                format!("line {hl}"),
                format!(
                    "unsupported field '{}' (expected real or integer)",
                    quote(other)
                ),
            ))
        }
    }
    let symmetric = match toks[4].as_str() {
        "general" => false,
        "symmetric" => true,
        other => {
            return Err(err(
                file,
                format!("line {hl}"),
                format!(
                    "unsupported symmetry '{}' (expected general or symmetric)",
                    quote(other)
                ),
            ))
        }
    };
    if symmetric && !coordinate {
        return Err(err(
            file,
            format!("line {hl}"),
            "symmetric array storage is not supported (use coordinate, or array general)",
        ));
    }
    // Size line: the first line that is neither a comment nor blank.
    let (sl, size) = lines
        .find(|(_, l)| is_data(l))
        .ok_or_else(|| err(file, "", "the size line is missing after the header"))?;
    let want = if coordinate { 3 } else { 2 };
    let dims: Vec<&str> = size.split_whitespace().take(want + 1).collect();
    let parsed: Option<Vec<usize>> = dims.iter().map(|t| t.parse::<usize>().ok()).collect();
    let dims = match parsed {
        Some(d) if d.len() == want => d,
        _ => {
            return Err(err(
                file,
                format!("line {sl}"),
                format!(
                    "malformed size line '{}': expected {}",
                    quote(size),
                    if want == 3 {
                        "'rows columns entries'"
                    } else {
                        "'rows columns'"
                    }
                ),
            ))
        }
    };
    let (nrows, ncols) = (dims[0], dims[1]);
    // Indices travel as 32-bit integers (GPU buffers, PETSc's PetscInt); larger sizes are
    // refused here, before anything is allocated from them.
    if nrows > MAX_DIMENSION || ncols > MAX_DIMENSION {
        return Err(err(
            file,
            format!("line {sl}"),
            format!(
                "the size line declares {nrows} × {ncols}; at most {MAX_DIMENSION} rows and columns are supported"
            ),
        ));
    }
    if symmetric && nrows != ncols {
        return Err(err(
            file,
            format!("line {sl}"),
            format!("a symmetric matrix must be square, the size line says {nrows} × {ncols}"),
        ));
    }
    let entries = if coordinate {
        dims[2]
    } else {
        nrows
            .checked_mul(ncols)
            .ok_or_else(|| err(file, format!("line {sl}"), "the matrix is too large"))?
    };
    Ok(Header {
        nrows,
        ncols,
        entries,
        coordinate,
        symmetric,
        size_line: sl,
    })
}

/// Refuses a size line declaring more rows or columns than this machine's memory holds
/// at [`MIN_BYTES_PER_ROW`].
fn check_memory(file: &str, h: &Header) -> Result<(), InputError> {
    let Some(mem) = super::memory_bytes() else {
        return Ok(());
    };
    let big = h.nrows.max(h.ncols);
    if big > max_rows_for_memory(mem) {
        return Err(err(
            file,
            format!("line {}", h.size_line),
            format!(
                "the size line declares {} × {}; a system of {big} rows needs at least {} ({MIN_BYTES_PER_ROW} bytes a row), more than this machine's {} of memory",
                h.nrows,
                h.ncols,
                super::human_bytes((big as u64).saturating_mul(MIN_BYTES_PER_ROW)),
                super::human_bytes(mem)
            ),
        ));
    }
    Ok(())
}

/// A line that is neither blank nor a comment.
fn is_data(l: &str) -> bool {
    let t = l.trim_start();
    !t.is_empty() && !t.starts_with('%')
}

/// Parses a Matrix Market matrix (coordinate or array; real, integer or double; general
/// or symmetric). Values are checked for finiteness here, so every later stage sees
/// finite numbers only (sums of duplicates are checked where they are summed). A leading
/// byte-order mark is skipped.
pub fn parse(file: &str, text: &str) -> Result<Coo, InputError> {
    parse_checked(file, text, |_| Ok(()))
}

/// A value token of line `line`: a finite or infinite f64, but not one cut short after
/// its decimal point.
fn parse_value(file: &str, line: usize, tok: &str) -> Result<f64, InputError> {
    // "4." reads as 4 (in Rust and C alike), but in a data file it is most often a
    // number cut short by a write that stopped mid-way: refused.
    if tok.ends_with('.') {
        return Err(err(
            file,
            format!("line {line}"),
            format!(
                "'{}' is not a complete number (no digit after the decimal point; \
                 was the file cut short?)",
                quote(tok)
            ),
        ));
    }
    tok.parse::<f64>().map_err(|_| {
        err(
            file,
            format!("line {line}"),
            format!("cannot read '{}' as a number", quote(tok)),
        )
    })
}

/// A 1-based `what` (row, column) index token of line `line`, in 1..=n, made 0-based.
fn parse_index(
    file: &str,
    line: usize,
    tok: &str,
    n: usize,
    what: &str,
) -> Result<usize, InputError> {
    match tok.parse::<usize>() {
        Ok(i) if i >= 1 && i <= n => Ok(i - 1),
        Ok(i) => Err(err(
            file,
            format!("line {line}"),
            format!("{what} index {i} is out of range 1..={n}"),
        )),
        Err(_) => Err(err(
            file,
            format!("line {line}"),
            format!(
                "cannot read {what} index '{}' as a positive integer",
                quote(tok)
            ),
        )),
    }
}

/// [`parse`], calling `check` on the header before any entry is read or stored, so that
/// a size line the other inputs contradict is refused before it costs anything.
pub fn parse_checked(
    file: &str,
    text: &str,
    check: impl FnOnce(&Header) -> Result<(), InputError>,
) -> Result<Coo, InputError> {
    let text = super::strip_bom(text);
    let mut lines = text.lines().enumerate().map(|(k, l)| (k + 1, l));
    let h = parse_header(file, &mut lines)?;
    // The caller's check first: another input's size names the fault more precisely.
    check(&h)?;
    check_memory(file, &h)?;
    let Header {
        nrows,
        ncols,
        entries: expected,
        coordinate,
        symmetric,
        size_line: sl,
    } = h;
    let data = lines.filter(|(_, l)| is_data(l));
    // A size line can announce more entries than the file holds: reserve no more than
    // the text can hold (a coordinate entry takes at least 6 bytes, an array value 2).
    let fit = text.len() / if coordinate { 6 } else { 2 } + 1;
    let mut entries: Vec<(usize, usize, f64)> = Vec::new();
    let want = expected.min(fit);
    entries
        .try_reserve_exact(want)
        .map_err(|_| super::out_of_memory(file, "the entries", want * 24))?;
    let value = |line: usize, tok: &str| parse_value(file, line, tok);
    if coordinate {
        for (ln, l) in data {
            let mut it = l.split_ascii_whitespace();
            let (Some(a), Some(b), Some(v), None) = (it.next(), it.next(), it.next(), it.next())
            else {
                return Err(err(
                    file,
                    format!("line {ln}"),
                    format!(
                        "malformed entry '{}': expected 'row column value'",
                        quote(l)
                    ),
                ));
            };
            let idx = |t: &str, n: usize, what: &str| parse_index(file, ln, t, n, what);
            let r = idx(a, nrows, "row")?;
            let c = idx(b, ncols, "column")?;
            let v = value(ln, v)?;
            if !v.is_finite() {
                return Err(err(
                    file,
                    format!("entry ({}, {})", r + 1, c + 1),
                    format!("value {v} is not finite"),
                ));
            }
            if symmetric && c > r {
                return Err(err(
                    file,
                    format!("entry ({}, {})", r + 1, c + 1),
                    "entry above the diagonal in a symmetric file (symmetric Matrix Market stores the lower triangle only)",
                ));
            }
            if entries.len() == expected {
                return Err(err(
                    file,
                    format!("line {ln}"),
                    format!("more entries than the {expected} the size line (line {sl}) announces"),
                ));
            }
            entries.push((r, c, v));
        }
    } else {
        // Column-major, one value per line (several per line are accepted).
        for (ln, l) in data {
            for tok in l.split_ascii_whitespace() {
                let k = entries.len();
                if k == expected {
                    return Err(err(
                        file,
                        format!("line {ln}"),
                        format!(
                            "more values than the {expected} the size line (line {sl}) announces"
                        ),
                    ));
                }
                let (r, c) = (k % nrows, k / nrows);
                let v = value(ln, tok)?;
                if !v.is_finite() {
                    return Err(err(
                        file,
                        format!("entry ({}, {})", r + 1, c + 1),
                        format!("value {v} is not finite"),
                    ));
                }
                entries.push((r, c, v));
            }
        }
    }
    if entries.len() != expected {
        return Err(err(
            file,
            format!("line {sl}"),
            format!(
                "the size line announces {expected} entries but the file holds {}",
                entries.len()
            ),
        ));
    }
    Ok(Coo {
        nrows,
        ncols,
        symmetric,
        entries,
        size_line: sl,
    })
}

/// The header of the Matrix Market file at `path`, read from its first MiB only (the
/// size line comes after the comments): a cheap look at what another input declares,
/// e.g. g's length before H's blocks are allocated. Errors say why it could not be read;
/// the full read reports them again, so a caller may ignore them.
pub fn read_header(path: &str) -> Result<Header, InputError> {
    let bytes = super::read_limited_prefix(path, 1 << 20)?;
    // Cut at the last complete line (the prefix may end inside a line or a character).
    let end = bytes
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(bytes.len(), |k| k + 1);
    let text = std::str::from_utf8(&bytes[..end])
        .map_err(|_| err(path, "", "the header is not UTF-8 text"))?;
    let text = super::strip_bom(text);
    let mut lines = text.lines().enumerate().map(|(k, l)| (k + 1, l));
    parse_header(path, &mut lines)
}

/// The same read through `nalgebra_sparse` (pest). Kept to compare speed and results;
/// symmetric files come back with both triangles.
pub fn read_coo_nalgebra(file: &str, text: &str) -> Result<Coo, InputError> {
    let m = nalgebra_sparse::io::load_coo_from_matrix_market_str::<f64>(text)
        .map_err(|e| err(file, "", e.to_string()))?;
    let entries = m.triplet_iter().map(|(r, c, v)| (r, c, *v)).collect();
    Ok(Coo {
        nrows: m.nrows(),
        ncols: m.ncols(),
        symmetric: false,
        entries,
        size_line: 0,
    })
}

/// What the other inputs say about H's size, checked on H's size line before any entry
/// is stored or any block allocated ([`read_hessian_bounded`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct HessianBounds<'a> {
    /// The most rows H may have, and what fixes it for messages, e.g.
    /// `(81, "the 81 rows of g (g.mtx)")` from g's size line ([`read_header`]), or the
    /// layout's d·n in `recover`. H declaring more is refused; fewer is left to the
    /// reader of the other input, which names its own file.
    pub max_rows: Option<(usize, &'a str)>,
    /// How many nodes the constraints can fix completely: the number of constraints in
    /// bc.json, or the rows of B. A solvable system needs an entry of H in the diagonal
    /// block of every node that keeps a free direction (Ĥ is positive definite there),
    /// so H can declare at most its stored entries plus this many nodes; a size line
    /// beyond that is corrupt. None: not known, and only the loose legacy ratio
    /// (64 rows per stored entry) applies.
    pub constrained_nodes: Option<usize>,
}

/// Checks H's declared shape against `dim` and `bounds` (`entries`: the stored entries).
fn check_hessian_size(
    file: &str,
    h: &Header,
    dim: usize,
    bounds: &HessianBounds,
) -> Result<(), InputError> {
    let sl = format!("line {}", h.size_line);
    if h.nrows != h.ncols {
        return Err(err(
            file,
            sl,
            format!("H is {} × {}, expected a square matrix", h.nrows, h.ncols),
        ));
    }
    if h.nrows == 0 {
        return Err(err(file, sl, "H is empty (0 × 0)"));
    }
    let nd = h.nrows;
    if nd % dim != 0 {
        return Err(err(
            file,
            sl,
            format!(
                "H has {nd} rows, not a multiple of the dimension {dim} (rows are node-major, {dim} per node)"
            ),
        ));
    }
    let n = nd / dim;
    match bounds.constrained_nodes {
        Some(c) => {
            if n > h.entries.saturating_add(c) {
                return Err(err(
                    file,
                    sl,
                    format!(
                        "H declares {nd} rows ({n} nodes) but stores only {} entries and the constraints fix at most {c} nodes; every node that is not fully constrained needs an entry in its diagonal block",
                        h.entries
                    ),
                ));
            }
        }
        None => {
            // Every row of a Hessian holds at least its diagonal (mass), so a size line
            // far beyond the entries is a corrupt file, not a system.
            if nd / 64 > h.entries {
                return Err(err(
                    file,
                    sl,
                    format!(
                        "the size line declares {nd} rows but the file holds only {} entries (a Hessian has an entry on every row's diagonal)",
                        h.entries
                    ),
                ));
            }
        }
    }
    if let Some((max, what)) = bounds.max_rows {
        if nd > max {
            return Err(err(
                file,
                sl,
                format!("H declares {nd} rows, more than {what}"),
            ));
        }
    }
    Ok(())
}

/// Builds H as a block matrix: square, a multiple of `dim`, finite, symmetric.
/// Every node gets a diagonal block (explicit zeros
/// where the file has none) so the constrained diagonal D always has a place.
/// The size line is checked as by [`read_hessian`] (no bounds from other inputs).
pub fn hessian_from_coo(file: &str, coo: &Coo, dim: usize) -> Result<BlockCsr, InputError> {
    let h = Header {
        nrows: coo.nrows,
        ncols: coo.ncols,
        entries: coo.entries.len(),
        coordinate: true,
        symmetric: coo.symmetric,
        size_line: coo.size_line,
    };
    check_hessian_size(file, &h, dim, &HessianBounds::default())?;
    build_hessian(file, coo, dim)
}

/// The blocks of an H whose size has been checked.
fn build_hessian(file: &str, coo: &Coo, dim: usize) -> Result<BlockCsr, InputError> {
    let nd = coo.nrows;
    // Every buffer sized by the input is allocated fallibly: too large for memory (or
    // for `ulimit -v`) is this file's error, not an abort.
    let e = coo.entries.len() + nd;
    let oom = |what: &str, bytes: usize| super::out_of_memory(file, what, bytes);
    let mut t = Vec::new();
    t.try_reserve_exact(e)
        .map_err(|_| oom("the entries", e.saturating_mul(24)))?;
    t.extend_from_slice(&coo.entries);
    t.extend((0..nd).map(|k| (k, k, 0.0)));
    let h = BlockCsr::try_from_triplets(dim, nd, &t, coo.symmetric)
        .map_err(|_| oom("the Hessian's blocks", e.saturating_mul(16 + 8 * dim * dim)))?;
    // Finiteness after duplicates are summed (1e308 twice is inf), and symmetry.
    h.validate(file)?;
    Ok(h)
}

/// Reads H from `path`, with no bounds from the other inputs: prefer
/// [`read_hessian_bounded`], which refuses a corrupt size line before allocating.
pub fn read_hessian(path: &str, dim: usize) -> Result<BlockCsr, InputError> {
    read_hessian_bounded(path, dim, &HessianBounds::default())
}

/// Reads H from `path`, checking its size line against `dim` and `bounds` before any
/// entry is stored, so a small file declaring a huge system fails at once (its size
/// line named) instead of allocating for the declared size.
pub fn read_hessian_bounded(
    path: &str,
    dim: usize,
    bounds: &HessianBounds,
) -> Result<BlockCsr, InputError> {
    let text = super::read_text(path)?;
    hessian_from_text(path, &text, dim, bounds)
}

/// [`read_hessian_bounded`] on text already read; `file` names it in errors.
pub fn hessian_from_text(
    file: &str,
    text: &str,
    dim: usize,
    bounds: &HessianBounds,
) -> Result<BlockCsr, InputError> {
    let coo = parse_checked(file, text, |h| check_hessian_size(file, h, dim, bounds))?;
    build_hessian(file, &coo, dim)
}

/// The length of a vector of shape `nrows × ncols`, and whether it is a column; checked
/// against `expected`.
fn vector_shape(
    file: &str,
    h: &Header,
    name: &str,
    expected: Option<(usize, &str)>,
) -> Result<(usize, bool), InputError> {
    let sl = format!("line {}", h.size_line);
    let (len, column) = if h.ncols == 1 {
        (h.nrows, true)
    } else if h.nrows == 1 {
        (h.ncols, false)
    } else {
        return Err(err(
            file,
            sl,
            format!(
                "{name} is {} × {}, expected a vector (n × 1 or 1 × n)",
                h.nrows, h.ncols
            ),
        ));
    };
    if h.symmetric && len > 1 {
        return Err(err(
            file,
            sl,
            format!("{name} cannot be stored as symmetric"),
        ));
    }
    if let Some((want, desc)) = expected {
        if len != want {
            return Err(err(
                file,
                sl,
                format!("{name} has {len} rows, expected {desc}"),
            ));
        }
    }
    Ok((len, column))
}

/// A vector from a parsed file: n × 1 or 1 × n, array or coordinate (missing coordinate
/// entries are 0, duplicates sum, and a sum that overflows is an error naming the entry).
/// `name` and `expected` describe it for messages, e.g. `("g", Some((12, "12 = 3 × 4 nodes")))`.
pub fn vector_from_coo(
    file: &str,
    coo: &Coo,
    name: &str,
    expected: Option<(usize, &str)>,
) -> Result<Vec<f64>, InputError> {
    let h = Header {
        nrows: coo.nrows,
        ncols: coo.ncols,
        entries: coo.entries.len(),
        coordinate: true,
        symmetric: coo.symmetric,
        size_line: coo.size_line,
    };
    let (len, column) = vector_shape(file, &h, name, expected)?;
    let mut v: Vec<f64> = Vec::new();
    v.try_reserve_exact(len)
        .map_err(|_| super::out_of_memory(file, name, len.saturating_mul(8)))?;
    v.resize(len, 0.0);
    for &(r, c, x) in &coo.entries {
        v[if column { r } else { c }] += x;
    }
    // Each value was finite as read; duplicates (coordinate files) can sum past f64.
    if let Some(k) = v.iter().position(|x| !x.is_finite()) {
        let (r, c) = if column { (k + 1, 1) } else { (1, k + 1) };
        return Err(err(
            file,
            format!("entry ({r}, {c})"),
            format!(
                "the duplicate entries for it sum to {}, which is not finite",
                v[k]
            ),
        ));
    }
    Ok(v)
}

/// Reads a vector from `path` (see [`vector_from_coo`]); the shape and `expected` are
/// checked on the size line, before any entry is read.
pub fn read_vector(
    path: &str,
    name: &str,
    expected: Option<(usize, &str)>,
) -> Result<Vec<f64>, InputError> {
    let text = super::read_text(path)?;
    vector_from_text(path, &text, name, expected)
}

/// [`read_vector`] on text already read; `file` names it in errors.
pub fn vector_from_text(
    file: &str,
    text: &str,
    name: &str,
    expected: Option<(usize, &str)>,
) -> Result<Vec<f64>, InputError> {
    let coo = parse_checked(file, text, |h| {
        vector_shape(file, h, name, expected).map(|_| ())
    })?;
    vector_from_coo(file, &coo, name, expected)
}

/// Reads a general (non-symmetric) coordinate matrix such as B, where every row holds
/// a nonzero: a size line declaring more rows than stored entries is refused before
/// any entry is read.
pub fn read_matrix(path: &str, name: &str) -> Result<Coo, InputError> {
    let text = super::read_text(path)?;
    matrix_from_text(path, &text, name)
}

/// [`read_matrix`] on text already read; `path` names it in errors.
pub fn matrix_from_text(path: &str, text: &str, name: &str) -> Result<Coo, InputError> {
    parse_checked(path, text, |h| {
        if h.symmetric {
            return Err(err(
                path,
                "line 1",
                format!("{name} must be stored as general, not symmetric"),
            ));
        }
        if h.nrows > h.entries {
            return Err(err(
                path,
                format!("line {}", h.size_line),
                format!(
                    "{name} declares {} rows but holds {} entries; every row needs a nonzero",
                    h.nrows, h.entries
                ),
            ));
        }
        Ok(())
    })
}

/// Writes `v` as `array real general` n × 1 with 17 significant digits (exact f64).
pub fn write_vector(
    path: impl AsRef<std::path::Path>,
    v: &[f64],
    comment: &str,
) -> std::io::Result<()> {
    super::files::write_atomic(path, |w| {
        writeln!(w, "%%MatrixMarket matrix array real general")?;
        for c in comment.lines() {
            writeln!(w, "% {c}")?;
        }
        writeln!(w, "{} 1", v.len())?;
        let mut s = String::with_capacity(32);
        for x in v {
            s.clear();
            let _ = writeln!(s, "{x:.16e}");
            w.write_all(s.as_bytes())?;
        }
        Ok(())
    })
}

/// Writes H as `coordinate real symmetric`: the lower triangle, nonzeros plus the whole
/// diagonal, 17 significant digits.
pub fn write_hessian(
    path: impl AsRef<std::path::Path>,
    h: &BlockCsr,
    comment: &str,
) -> std::io::Result<()> {
    let d = h.dim;
    let keep = |i: usize, k: usize, r: usize, c: usize| -> Option<(usize, usize, f64)> {
        let (gr, gc) = (i * d + r, h.col_idx[k] * d + c);
        let v = h.values[k * d * d + r * d + c];
        (gr >= gc && (v != 0.0 || gr == gc)).then_some((gr, gc, v))
    };
    let mut count = 0usize;
    for i in 0..h.n {
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            for r in 0..d {
                for c in 0..d {
                    count += keep(i, k, r, c).is_some() as usize;
                }
            }
        }
    }
    super::files::write_atomic(path, |w| {
        writeln!(w, "%%MatrixMarket matrix coordinate real symmetric")?;
        for c in comment.lines() {
            writeln!(w, "% {c}")?;
        }
        writeln!(w, "{} {} {count}", h.ndof(), h.ndof())?;
        let mut s = String::with_capacity(64);
        for i in 0..h.n {
            for r in 0..d {
                // Row-major within a block row so the file is sorted by row.
                for k in h.row_ptr[i]..h.row_ptr[i + 1] {
                    for c in 0..d {
                        if let Some((gr, gc, v)) = keep(i, k, r, c) {
                            s.clear();
                            let _ = writeln!(s, "{} {} {v:.16e}", gr + 1, gc + 1);
                            w.write_all(s.as_bytes())?;
                        }
                    }
                }
            }
        }
        Ok(())
    })
}

/// Writes a general coordinate matrix (0-based entries; written 1-based).
pub fn write_coo(
    path: impl AsRef<std::path::Path>,
    nrows: usize,
    ncols: usize,
    entries: &[(usize, usize, f64)],
    comment: &str,
) -> std::io::Result<()> {
    super::files::write_atomic(path, |w| {
        writeln!(w, "%%MatrixMarket matrix coordinate real general")?;
        for c in comment.lines() {
            writeln!(w, "% {c}")?;
        }
        writeln!(w, "{nrows} {ncols} {}", entries.len())?;
        for &(r, c, v) in entries {
            writeln!(w, "{} {} {v:.16e}", r + 1, c + 1)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn symmetric_coordinate_and_array_vectors() {
        let h = "%%MatrixMarket matrix coordinate real symmetric\n% c\n4 4 5\n1 1 2\n2 2 2\n3 1 -1\n3 3 2\n4 4 2.5e0\n";
        let coo = parse("H.mtx", h).unwrap();
        let m = hessian_from_coo("H.mtx", &coo, 2).unwrap();
        assert_eq!(m.get(0, 2), -1.0);
        assert_eq!(m.get(2, 0), -1.0);
        assert_eq!(m.get(3, 3), 2.5);
        let g = "%%MatrixMarket matrix array real general\n1 4\n1\n2\n3\n4\n";
        let v = read_vec_str(g, Some((4, "4"))).unwrap();
        assert_eq!(v, vec![1.0, 2.0, 3.0, 4.0]);
        let e = read_vec_str(g, Some((6, "6 = 2 × 3 nodes"))).unwrap_err();
        assert_eq!(
            e.to_string(),
            "g.mtx: line 2: g has 4 rows, expected 6 = 2 × 3 nodes"
        );
    }

    fn read_vec_str(s: &str, want: Option<(usize, &str)>) -> Result<Vec<f64>, InputError> {
        let coo = parse("g.mtx", s)?;
        vector_from_coo("g.mtx", &coo, "g", want)
    }

    #[test]
    fn faults_name_the_entry() {
        let bad = [
            ("%%MatrixMarket matrix coordinate real general\n2 2 1\n1 2 NaN\n", "g.mtx: entry (1, 2): value NaN is not finite"),
            ("%%MatrixMarket matrix coordinate real general\n2 2 1\n3 1 1\n", "g.mtx: line 3: row index 3 is out of range 1..=2"),
            ("%%MatrixMarket matrix coordinate real general\n2 2 2\n1 1 1\n", "g.mtx: line 2: the size line announces 2 entries but the file holds 1"),
            ("%%MatrixMarket matrix coordinate real general\n2 2 1\n1 1 x\n", "g.mtx: line 3: cannot read 'x' as a number"),
            ("hello\n", "g.mtx: line 1: not a Matrix Market file: the first line must start with %%MatrixMarket"),
        ];
        for (text, want) in bad {
            assert_eq!(parse("g.mtx", text).unwrap_err().to_string(), want);
        }
    }

    #[test]
    fn written_files_read_back_exactly() {
        let s =
            crate::cases::generate::random_system(&crate::cases::generate::SystemSpec::small(3, 5));
        let dir = std::env::temp_dir().join(format!("stickslip-mtx-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let hp = dir.join("H.mtx");
        let gp = dir.join("g.mtx");
        write_hessian(&hp, &s.h, "test").unwrap();
        write_vector(&gp, &s.g, "test").unwrap();
        let h = read_hessian(hp.to_str().unwrap(), 3).unwrap();
        let g = read_vector(gp.to_str().unwrap(), "g", Some((s.g.len(), ""))).unwrap();
        assert_eq!(g, s.g);
        // The lower triangle is exact; the upper one is its mirror, and the generator's
        // H is symmetric only to round-off (s·a_r·a_c multiplies in different orders).
        for r in 0..s.h.ndof() {
            for c in 0..s.h.ndof() {
                if r >= c {
                    assert_eq!(h.get(r, c), s.h.get(r, c));
                } else {
                    assert!((h.get(r, c) - s.h.get(r, c)).abs() <= 1e-15 * s.h.max_abs());
                }
            }
        }
        let text = std::fs::read_to_string(&hp).unwrap();
        let a = parse("H.mtx", &text).unwrap();
        let b = read_coo_nalgebra("H.mtx", &text).unwrap();
        // nalgebra mirrors the off-diagonal entries itself.
        let off = a.entries.iter().filter(|e| e.0 != e.1).count();
        assert_eq!(b.entries.len(), a.entries.len() + off);
        std::fs::remove_dir_all(&dir).ok();
    }
}

#[cfg(test)]
mod timing {
    /// Reader speed on a big file: `STICKSLIP_MTX_TIMING=path/H.mtx cargo test --release
    /// --lib io::mtx::timing -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn reader_speed() {
        let Ok(path) = std::env::var("STICKSLIP_MTX_TIMING") else {
            return;
        };
        let t = std::time::Instant::now();
        let text = std::fs::read_to_string(&path).unwrap();
        let read = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let a = super::parse(&path, &text).unwrap();
        let ours = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let h = super::hessian_from_coo(&path, &a, 3).unwrap();
        let blocks = t.elapsed().as_secs_f64();
        println!(
            "{} entries, {} MB: read_to_string {read:.2} s, parse {ours:.2} s, blocks+validate {blocks:.2} s ({} nodes)",
            a.entries.len(),
            text.len() >> 20,
            h.n
        );
        if std::env::var("STICKSLIP_MTX_TIMING_NALGEBRA").is_ok() {
            let t = std::time::Instant::now();
            let b = super::read_coo_nalgebra(&path, &text).unwrap();
            println!(
                "nalgebra_sparse (pest): {:.2} s for {} entries",
                t.elapsed().as_secs_f64(),
                b.entries.len()
            );
        }
    }
}
