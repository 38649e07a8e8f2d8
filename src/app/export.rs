//! Carry the eliminated system past one machine: write Ĥ and b̂ (frame coordinates,
//! docs/method.md, "The eliminated system") for PETSc and Matrix Market readers, with a
//! layout file that holds what recovery needs (per-node masks, rotations, the lift), and
//! recover Δx and the reactions from a solution y exactly as the in-process solvers do.
//!
//! PETSc's binary format (big-endian; PetscInt is 32-bit in Debian's build):
//! Mat: `MAT_FILE_CLASSID, M, N, nnz, row lengths[M], column indices[nnz], values[nnz]` f64.
//! Vec: `VEC_FILE_CLASSID, n, values[n]` f64. The `.info` file beside the matrix carries
//! `-matload_block_size d`, so MatLoad keeps the node blocks (point-block Jacobi).

use crate::core::constraints::{Frames, NO_ROTATION};
use crate::core::elimination::{reactions, ConstrainedDiagonal, Eliminated};
use crate::core::sparse::BlockCsr;
use crate::error::InputError;
use crate::io::files::write_atomic;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

pub const MAT_FILE_CLASSID: i32 = 1211216;
pub const VEC_FILE_CLASSID: i32 = 1211214;

/// What recovery needs, written as `layout.json`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Layout {
    pub format: String,
    pub dim: usize,
    pub n_nodes: usize,
    /// Block size recorded for PETSc (= dim).
    pub block_size: usize,
    pub free_dofs: usize,
    pub constrained_dofs: usize,
    /// Per node: bit k set when component k (in the node's frame) is constrained.
    pub mask: Vec<u8>,
    /// The nodes with a rotation and their V_i (row-major, d·d each).
    pub rot_nodes: Vec<u32>,
    pub rotations: Vec<f64>,
    /// Δx_p, the lift (omitted when all zero).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lift: Option<Vec<f64>>,
    /// The diagonal D on constrained components: "identity" or "hessian".
    #[serde(default = "identity_name")]
    pub constrained_diagonal: String,
    /// Fingerprints of H and g: recovery refuses an H or g from another system.
    pub hessian_fingerprint: String,
    pub gradient_fingerprint: String,
    /// Fingerprint of the masks, rotations, lift and constrained diagonal above: a layout
    /// changed after export is refused.
    pub frames_fingerprint: String,
    /// Bytes of the exported PETSc matrix (memory a PETSc run needs, roughly, for Ĥ).
    pub matrix_bytes: u64,
}

const LAYOUT_FORMAT: &str = "stickslip-eliminated-v1";

fn identity_name() -> String {
    "identity".to_string()
}

/// A count that must fit PETSc's 32-bit PetscInt (Debian's build).
fn petsc_int(v: usize, what: &str) -> std::io::Result<i32> {
    i32::try_from(v).map_err(|_| {
        std::io::Error::other(format!(
            "{what} = {v} exceeds PETSc's 32-bit PetscInt (2^31 - 1); split the system or use a 64-bit-index PETSc reader"
        ))
    })
}

/// Every file `export` may write in its folder (`hhat.mtx`, `bhat.mtx` only with the
/// Matrix Market copies): what the command line's owned output folder clears.
pub const OUTPUT_NAMES: [&str; 6] = [
    "hhat.petsc",
    "hhat.petsc.info",
    "bhat.petsc",
    "hhat.mtx",
    "bhat.mtx",
    "layout.json",
];

/// The files one export wrote.
#[derive(Debug, Clone)]
pub struct ExportFiles {
    pub matrix_petsc: PathBuf,
    pub rhs_petsc: PathBuf,
    pub matrix_mtx: Option<PathBuf>,
    pub rhs_mtx: Option<PathBuf>,
    pub layout: PathBuf,
}

/// FNV-1a over the shape, the pattern and the bits of the values.
pub fn fingerprint_matrix(h: &BlockCsr) -> String {
    let mut f = Fnv::new();
    f.u64(h.dim as u64);
    f.u64(h.n as u64);
    for &v in &h.row_ptr {
        f.u64(v as u64);
    }
    for &v in &h.col_idx {
        f.u64(v as u64);
    }
    for &v in &h.values {
        f.u64(v.to_bits());
    }
    format!("{:016x}", f.0)
}

pub fn fingerprint_vector(g: &[f64]) -> String {
    let mut f = Fnv::new();
    f.u64(g.len() as u64);
    for &v in g {
        f.u64(v.to_bits());
    }
    format!("{:016x}", f.0)
}

struct Fnv(u64);
impl Fnv {
    fn new() -> Self {
        Fnv(0xcbf29ce484222325)
    }
    fn u64(&mut self, v: u64) {
        for b in v.to_le_bytes() {
            self.0 ^= b as u64;
            self.0 = self.0.wrapping_mul(0x100000001b3);
        }
    }
}

/// Writes Ĥ (full, scalar CSR with explicit structure of the free components and the
/// constrained diagonal) and b̂ to `dir`, plus the layout. `mtx`: also Matrix Market.
pub fn export(
    e: &Eliminated,
    diag: ConstrainedDiagonal,
    g: &[f64],
    dir: &Path,
    mtx: bool,
) -> std::io::Result<ExportFiles> {
    let hat = e.assemble();
    let f = e.frames;
    let d = hat.dim;
    let nd = hat.ndof();
    petsc_int(nd, "the number of DOFs")?;
    std::fs::create_dir_all(dir)?;
    // Scalar CSR rows of Ĥ, keeping free–free entries and the constrained diagonal.
    let mut row_len: Vec<i32> = Vec::with_capacity(nd);
    let mut cols: Vec<i32> = Vec::new();
    let mut vals: Vec<f64> = Vec::new();
    // Entries on or below the diagonal (the symmetric Matrix Market copy holds those).
    let mut lower = 0usize;
    for i in 0..hat.n {
        for a in 0..d {
            let r = i * d + a;
            let start = cols.len();
            let row_free = f.is_free(i, a);
            for k in hat.row_ptr[i]..hat.row_ptr[i + 1] {
                let j = hat.col_idx[k];
                for b in 0..d {
                    let c = j * d + b;
                    let keep = if r == c {
                        true
                    } else {
                        row_free && f.is_free(j, b)
                    };
                    if keep {
                        // c < nd ≤ i32::MAX, checked above.
                        cols.push(c as i32);
                        vals.push(hat.values[k * d * d + a * d + b]);
                        lower += usize::from(c <= r);
                    }
                }
            }
            row_len.push((cols.len() - start) as i32);
        }
    }
    let nnz = petsc_int(cols.len(), "the number of stored entries")?;
    let matrix_petsc = dir.join("hhat.petsc");
    write_atomic(&matrix_petsc, |w| {
        for v in [MAT_FILE_CLASSID, nd as i32, nd as i32, nnz] {
            w.write_all(&v.to_be_bytes())?;
        }
        for v in &row_len {
            w.write_all(&v.to_be_bytes())?;
        }
        for v in &cols {
            w.write_all(&v.to_be_bytes())?;
        }
        for v in &vals {
            w.write_all(&v.to_be_bytes())?;
        }
        Ok(())
    })?;
    crate::io::files::write_atomic_bytes(
        dir.join("hhat.petsc.info"),
        format!("-matload_block_size {d}\n").as_bytes(),
    )?;
    let rhs_petsc = dir.join("bhat.petsc");
    write_petsc_vec(&rhs_petsc, &e.rhs)?;
    let (matrix_mtx, rhs_mtx) = if mtx {
        let mp = dir.join("hhat.mtx");
        write_atomic(&mp, |w| {
            // Symmetric: lower triangle only.
            writeln!(w, "%%MatrixMarket matrix coordinate real symmetric")?;
            writeln!(
                w,
                "% stickslip eliminated Hessian (node frames), block size {d}"
            )?;
            writeln!(w, "{nd} {nd} {lower}")?;
            let mut k = 0usize;
            for (r, &len) in row_len.iter().enumerate() {
                for _ in 0..len {
                    let c = cols[k] as usize;
                    if c <= r {
                        writeln!(w, "{} {} {:.16e}", r + 1, c + 1, vals[k])?;
                    }
                    k += 1;
                }
            }
            Ok(())
        })?;
        let vp = dir.join("bhat.mtx");
        write_atomic(&vp, |w| {
            writeln!(w, "%%MatrixMarket matrix array real general")?;
            writeln!(w, "{nd} 1")?;
            for v in &e.rhs {
                writeln!(w, "{v:.16e}")?;
            }
            Ok(())
        })?;
        (Some(mp), Some(vp))
    } else {
        (None, None)
    };
    let layout = Layout {
        format: LAYOUT_FORMAT.to_string(),
        dim: d,
        n_nodes: hat.n,
        block_size: d,
        free_dofs: f.free_dofs(),
        constrained_dofs: f.constrained_dofs(),
        mask: f.mask.clone(),
        rot_nodes: f.rot_nodes.clone(),
        rotations: f.rotations.clone(),
        lift: (!f.homogeneous).then(|| f.lift.clone()),
        constrained_diagonal: match diag {
            ConstrainedDiagonal::Identity => "identity",
            ConstrainedDiagonal::Hessian => "hessian",
        }
        .to_string(),
        hessian_fingerprint: fingerprint_matrix(e.h),
        gradient_fingerprint: fingerprint_vector(g),
        frames_fingerprint: String::new(),
        matrix_bytes: 16 + 4 * nd as u64 + 12 * cols.len() as u64,
    };
    let layout = Layout {
        frames_fingerprint: layout.fingerprint_frames(),
        ..layout
    };
    let layout_path = dir.join("layout.json");
    crate::io::files::write_atomic_bytes(
        &layout_path,
        serde_json::to_string(&layout)
            .map_err(std::io::Error::other)?
            .as_bytes(),
    )?;
    Ok(ExportFiles {
        matrix_petsc,
        rhs_petsc,
        matrix_mtx,
        rhs_mtx,
        layout: layout_path,
    })
}

pub fn write_petsc_vec(path: &Path, v: &[f64]) -> std::io::Result<()> {
    let n = petsc_int(v.len(), "the vector length")?;
    write_atomic(path, |w| {
        w.write_all(&VEC_FILE_CLASSID.to_be_bytes())?;
        w.write_all(&n.to_be_bytes())?;
        for x in v {
            w.write_all(&x.to_be_bytes())?;
        }
        Ok(())
    })
}

/// Reads a PETSc binary Vec.
pub fn read_petsc_vec(path: &Path) -> Result<Vec<f64>, InputError> {
    let file = path.display().to_string();
    let cannot = |e: std::io::Error| InputError::new(&file, "", format!("cannot read: {e}"));
    // The header first, then at most the bytes it declares (+1 to see a longer file):
    // a device or a huge file is never read whole.
    let mut f = std::fs::File::open(path).map_err(cannot)?;
    let mut bytes = Vec::new();
    (&mut f).take(8).read_to_end(&mut bytes).map_err(cannot)?;
    if bytes.len() == 8 {
        let id = i32::from_be_bytes(bytes[0..4].try_into().expect("4 bytes"));
        let n = i32::from_be_bytes(bytes[4..8].try_into().expect("4 bytes"));
        let limit = crate::io::input_limit();
        if id == VEC_FILE_CLASSID && n >= 0 && 8 * n as u64 > limit {
            return Err(InputError::new(
                &file,
                "header",
                format!(
                    "declares {n} entries ({}), more than the input limit of {}",
                    crate::io::human_bytes(8 * n as u64),
                    crate::io::human_bytes(limit)
                ),
            ));
        }
        if id == VEC_FILE_CLASSID && n >= 0 {
            f.take(8 * n as u64 + 1)
                .read_to_end(&mut bytes)
                .map_err(cannot)?;
        }
    }
    if bytes.len() < 8 {
        return Err(InputError::new(
            &file,
            "header",
            "too short for a PETSc Vec",
        ));
    }
    let id = i32::from_be_bytes(bytes[0..4].try_into().expect("4 bytes"));
    if id != VEC_FILE_CLASSID {
        return Err(InputError::new(
            &file,
            "header",
            format!("not a PETSc Vec (class id {id}, expected {VEC_FILE_CLASSID})"),
        ));
    }
    let n = i32::from_be_bytes(bytes[4..8].try_into().expect("4 bytes"));
    if n < 0 || bytes.len() != 8 + 8 * n as usize {
        return Err(InputError::new(
            &file,
            "header",
            format!(
                "declares {n} entries but holds {} bytes of values",
                bytes.len() - 8
            ),
        ));
    }
    let v: Vec<f64> = bytes[8..]
        .chunks_exact(8)
        .map(|c| f64::from_be_bytes(c.try_into().expect("8 bytes")))
        .collect();
    if let Some(k) = v.iter().position(|x| !x.is_finite()) {
        return Err(InputError::new(
            &file,
            format!("entry {}", k + 1),
            "value is not finite",
        ));
    }
    Ok(v)
}

/// Reads and checks a layout file.
pub fn read_layout(path: &Path) -> Result<Layout, InputError> {
    let file = path.display().to_string();
    let text = crate::io::read_text(&file)?;
    let l: Layout = serde_json::from_str(crate::io::strip_bom(&text)).map_err(|e| {
        InputError::new(
            &file,
            format!("line {} column {}", e.line(), e.column()),
            e.to_string(),
        )
    })?;
    if l.format != LAYOUT_FORMAT {
        return Err(InputError::new(
            &file,
            "format",
            format!(
                "unknown layout format '{}' (expected {LAYOUT_FORMAT})",
                l.format
            ),
        ));
    }
    let d = l.dim;
    let bad = |entry: &str, problem: String| Err(InputError::new(&file, entry, problem));
    if d != 2 && d != 3 {
        return bad("dim", format!("dimension {d} is not 2 or 3"));
    }
    if l.block_size != d {
        return bad(
            "block_size",
            format!("block size {} differs from dim {d}", l.block_size),
        );
    }
    if l.mask.len() != l.n_nodes {
        return bad(
            "mask",
            format!("{} masks for {} nodes", l.mask.len(), l.n_nodes),
        );
    }
    if let Some(i) = l.mask.iter().position(|&m| m >> d != 0) {
        return bad(
            &format!("mask[{i}]"),
            format!("bits beyond the {d} components"),
        );
    }
    let constrained: usize = l.mask.iter().map(|m| m.count_ones() as usize).sum();
    if constrained != l.constrained_dofs || d * l.n_nodes - constrained != l.free_dofs {
        return bad(
            "free_dofs",
            "free_dofs and constrained_dofs disagree with the masks".to_string(),
        );
    }
    if l.rot_nodes.windows(2).any(|w| w[0] >= w[1]) {
        return bad("rot_nodes", "not strictly increasing".to_string());
    }
    if l.rot_nodes.last().is_some_and(|&r| r as usize >= l.n_nodes) {
        return bad("rot_nodes", "a node index is out of range".to_string());
    }
    if l.rotations.len() != l.rot_nodes.len() * d * d {
        return bad(
            "rotations",
            format!(
                "{} values for {} rotated nodes of dimension {d}",
                l.rotations.len(),
                l.rot_nodes.len()
            ),
        );
    }
    // Each V_i must be orthonormal: recovery applies it as given.
    for (k, v) in l.rotations.chunks_exact(d * d).enumerate() {
        for a in 0..d {
            for b in 0..d {
                let s: f64 = (0..d).map(|r| v[r * d + a] * v[r * d + b]).sum();
                let want = if a == b { 1.0 } else { 0.0 };
                if s.is_nan() || (s - want).abs() > 1e-12 {
                    return bad(
                        &format!("rotations[{k}]"),
                        "the rotation is not orthonormal (|VᵀV − I| > 1e-12)".to_string(),
                    );
                }
            }
        }
    }
    if l.lift
        .as_ref()
        .is_some_and(|v| v.len() != d * l.n_nodes || v.iter().any(|x| !x.is_finite()))
    {
        return bad("lift", format!("expected {} finite values", d * l.n_nodes));
    }
    if l.constrained_diagonal != "identity" && l.constrained_diagonal != "hessian" {
        return bad(
            "constrained_diagonal",
            format!("'{}' is not identity or hessian", l.constrained_diagonal),
        );
    }
    if l.fingerprint_frames() != l.frames_fingerprint {
        return bad(
            "frames_fingerprint",
            "the masks, rotations, lift or constrained diagonal differ from what export \
             wrote (the file was changed after export)"
                .to_string(),
        );
    }
    Ok(l)
}

impl Layout {
    /// FNV-1a over what recovery applies: dimension, node count, masks, rotated nodes,
    /// the bits of the rotations and of the lift, and the constrained diagonal.
    pub fn fingerprint_frames(&self) -> String {
        let mut f = Fnv::new();
        f.u64(self.dim as u64);
        f.u64(self.n_nodes as u64);
        f.u64(self.mask.len() as u64);
        for &m in &self.mask {
            f.u64(u64::from(m));
        }
        f.u64(self.rot_nodes.len() as u64);
        for &r in &self.rot_nodes {
            f.u64(u64::from(r));
        }
        for v in &self.rotations {
            f.u64(v.to_bits());
        }
        match &self.lift {
            None => f.u64(0),
            Some(l) => {
                f.u64(1 + l.len() as u64);
                for v in l {
                    f.u64(v.to_bits());
                }
            }
        }
        for b in self.constrained_diagonal.bytes() {
            f.u64(u64::from(b));
        }
        format!("{:016x}", f.0)
    }

    /// The frames this layout describes.
    pub fn frames(&self) -> Frames {
        let d = self.dim;
        let mut f = Frames::unconstrained(d, self.n_nodes);
        f.mask = self.mask.clone();
        f.rot_nodes = self.rot_nodes.clone();
        f.rotations = self.rotations.clone();
        f.rot_index = vec![NO_ROTATION; self.n_nodes];
        for (k, &node) in self.rot_nodes.iter().enumerate() {
            f.rot_index[node as usize] = k as u32;
        }
        if let Some(l) = &self.lift {
            f.lift = l.clone();
            f.homogeneous = false;
        }
        f
    }
}

/// Δx = Δx_p + V y and f = −(HΔx + g), after checking that H, g and y belong to the
/// exported system. `names` = (layout, solution, hessian, gradient) file names for errors.
pub fn recover(
    layout: &Layout,
    y: &[f64],
    h: &BlockCsr,
    g: &[f64],
    names: [&str; 4],
) -> Result<Recovered, InputError> {
    let nd = layout.dim * layout.n_nodes;
    if y.len() != nd {
        return Err(InputError::new(
            names[1],
            "",
            format!(
                "solution has {} entries, the layout's system has {nd} ({} nodes × {})",
                y.len(),
                layout.n_nodes,
                layout.dim
            ),
        ));
    }
    if h.dim != layout.dim
        || h.n != layout.n_nodes
        || fingerprint_matrix(h) != layout.hessian_fingerprint
    {
        return Err(InputError::new(
            names[0],
            "hessian_fingerprint",
            format!(
                "the layout was exported from another system than {}",
                names[2]
            ),
        ));
    }
    if fingerprint_vector(g) != layout.gradient_fingerprint {
        return Err(InputError::new(
            names[0],
            "gradient_fingerprint",
            format!(
                "the layout was exported from another system than {}",
                names[3]
            ),
        ));
    }
    let frames = layout.frames();
    let diag = if layout.constrained_diagonal == "hessian" {
        ConstrainedDiagonal::Hessian
    } else {
        ConstrainedDiagonal::Identity
    };
    let e = Eliminated::new(h, g, &frames, diag);
    let dx = e.recover(y);
    let f = reactions(h, g, &dx);
    Ok(Recovered {
        relative_residual: e.relative_residual(y),
        dx,
        reactions: f,
    })
}

/// What [`recover`] returns.
#[derive(Debug, Clone)]
pub struct Recovered {
    pub dx: Vec<f64>,
    pub reactions: Vec<f64>,
    /// ‖b̂ − Ĥy‖/‖b̂‖ of y in the exported system (with the exported D).
    pub relative_residual: f64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cases::generate::{random_system, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    #[test]
    fn export_round_trip_through_files() {
        let s = random_system(&SystemSpec::small(3, 77));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let dir = std::env::temp_dir().join(format!("stickslip-export-{}", std::process::id()));
        let files = export(&e, ConstrainedDiagonal::Identity, &s.g, &dir, true).unwrap();
        let layout = read_layout(&files.layout).unwrap();
        assert_eq!(layout.frames(), s.frames);
        let b = read_petsc_vec(&files.rhs_petsc).unwrap();
        assert_eq!(b, e.rhs);
        let (y, _) = crate::solve::oracle::solve(&e).unwrap();
        let rec = recover(&layout, &y, &s.h, &s.g, ["l", "y", "h", "g"]).unwrap();
        assert_eq!(rec.dx, e.recover(&y));
        assert_eq!(rec.reactions, reactions(&s.h, &s.g, &rec.dx));
        assert_eq!(rec.relative_residual, e.relative_residual(&y));
        // The Matrix Market copy holds exactly the lower triangle of the PETSc matrix.
        let text = std::fs::read_to_string(files.matrix_mtx.as_ref().unwrap()).unwrap();
        let size: Vec<usize> = text
            .lines()
            .find(|l| !l.starts_with('%'))
            .unwrap()
            .split_whitespace()
            .map(|t| t.parse().unwrap())
            .collect();
        let entries = text.lines().filter(|l| !l.starts_with('%')).count() - 1;
        assert_eq!(size[2], entries);
        // A layout from another system is refused.
        let other = random_system(&SystemSpec::small(3, 78));
        if other.h.n == s.h.n {
            assert!(recover(&layout, &y, &other.h, &other.g, ["l", "y", "h", "g"]).is_err());
        }
        assert!(recover(&layout, &y[1..], &s.h, &s.g, ["l", "y", "h", "g"]).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
