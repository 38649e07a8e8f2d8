//! The eliminated system (docs/method.md, "The eliminated system"):
//!
//! ```text
//! Ĥ y = b̂,   Ĥ = P VᵀHV P + (I − P) D,   b̂ = −P Vᵀ (g + H Δx_p),   Δx = Δx_p + V y
//! ```
//!
//! `y` lives in the per-node frames; P masks the constrained components; D is a positive
//! diagonal on the constrained components (identity by default), so they decouple and
//! come out exactly zero. Reactions are f = −(HΔx + g).

use crate::core::constraints::Frames;
use crate::core::sparse::BlockCsr;

/// The diagonal D placed on constrained components.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum ConstrainedDiagonal {
    /// D = I.
    #[default]
    Identity,
    /// D = diag(VᵀHV): keeps the spectrum of Ĥ within that of VᵀHV.
    Hessian,
}

/// An eliminated Newton system: borrows H and the frames, owns b̂ and D.
#[derive(Debug, Clone)]
pub struct Eliminated<'a> {
    pub h: &'a BlockCsr,
    pub frames: &'a Frames,
    /// b̂ in frame coordinates (constrained components zero).
    pub rhs: Vec<f64>,
    /// D, length d·n (only constrained entries are used).
    pub diag: Vec<f64>,
}

impl<'a> Eliminated<'a> {
    /// Forms b̂ = −P Vᵀ(g + H Δx_p) and D.
    pub fn new(h: &'a BlockCsr, g: &[f64], frames: &'a Frames, diag: ConstrainedDiagonal) -> Self {
        assert_eq!(
            h.dim, frames.dim,
            "H and the constraints disagree on the dimension"
        );
        assert_eq!(
            h.n, frames.n_nodes,
            "H and the constraints disagree on the node count"
        );
        assert_eq!(g.len(), h.ndof(), "g has the wrong length");
        let nd = h.ndof();
        let rhs = eliminated_rhs(g, frames, |x, y| h.matvec(x, y));
        let d = match diag {
            ConstrainedDiagonal::Identity => vec![1.0; nd],
            ConstrainedDiagonal::Hessian => {
                let mut dd = rotated_diagonal(h, frames);
                // A zero (or negative) diagonal would break positivity; fall back to 1.
                for v in dd.iter_mut() {
                    // NaN compares false: it falls back to 1 as well.
                    if v.is_nan() || *v <= 0.0 || !v.is_finite() {
                        *v = 1.0;
                    }
                }
                dd
            }
        };
        Eliminated {
            h,
            frames,
            rhs,
            diag: d,
        }
    }

    pub fn ndof(&self) -> usize {
        self.h.ndof()
    }

    /// out = Ĥ y, matrix-free: mask, rotate (slip nodes only), block product, rotate back,
    /// mask, and D on constrained components. `work` must have length 2·d·n.
    pub fn apply(&self, y: &[f64], out: &mut [f64], work: &mut [f64]) {
        apply_eliminated(self.h, self.frames, &self.diag, y, out, work);
    }

    /// Ĥ assembled in frame coordinates on H's block pattern: block (i, j) is
    /// P_i V_iᵀ H_ij V_j P_j, plus D on the constrained diagonal entries.
    pub fn assemble(&self) -> BlockCsr {
        let mut m = rotate_blocks(self.h, self.frames);
        let f = self.frames;
        let d = f.dim;
        for i in 0..m.n {
            let mi = f.mask[i];
            if mi == 0 {
                continue;
            }
            for k in m.row_ptr[i]..m.row_ptr[i + 1] {
                let j = m.col_idx[k];
                let mj = f.mask[j];
                let b = &mut m.values[k * d * d..(k + 1) * d * d];
                for r in 0..d {
                    for c in 0..d {
                        if mi & (1 << r) != 0 || mj & (1 << c) != 0 {
                            b[r * d + c] = 0.0;
                        }
                    }
                }
                if i == j {
                    for a in 0..d {
                        if mi & (1 << a) != 0 {
                            b[a * d + a] = self.diag[i * d + a];
                        }
                    }
                }
            }
        }
        // Columns of a constrained component in rows whose node is unconstrained.
        for i in 0..m.n {
            if f.mask[i] != 0 {
                continue;
            }
            for k in m.row_ptr[i]..m.row_ptr[i + 1] {
                let mj = f.mask[m.col_idx[k]];
                if mj == 0 {
                    continue;
                }
                let b = &mut m.values[k * d * d..(k + 1) * d * d];
                for r in 0..d {
                    for c in 0..d {
                        if mj & (1 << c) != 0 {
                            b[r * d + c] = 0.0;
                        }
                    }
                }
            }
        }
        m
    }

    /// Δx = Δx_p + V y (constrained components of y are ignored: they are zero).
    pub fn recover(&self, y: &[f64]) -> Vec<f64> {
        let mut py = y.to_vec();
        self.frames.apply_mask(&mut py);
        let mut dx = vec![0.0; y.len()];
        self.frames.from_frame(&py, &mut dx);
        if !self.frames.homogeneous {
            for (v, l) in dx.iter_mut().zip(&self.frames.lift) {
                *v += l;
            }
        }
        dx
    }

    /// ‖b̂ − Ĥy‖ / ‖b̂‖ in f64 (1 when b̂ = 0 and y ≠ 0, 0 when both vanish).
    pub fn relative_residual(&self, y: &[f64]) -> f64 {
        let n = self.ndof();
        let mut hy = vec![0.0; n];
        let mut work = vec![0.0; 2 * n];
        self.apply(y, &mut hy, &mut work);
        relative_residual_from(&self.rhs, &mut hy)
    }
}

/// out = Ĥ y, matrix-free, for H, the frames and D given separately: the steps of
/// [`Eliminated::apply`] without an [`Eliminated`] (no b̂ needed, D borrowed).
/// `work` must have length 2·d·n; its contents on entry do not matter.
pub fn apply_eliminated(
    h: &BlockCsr,
    f: &Frames,
    diag: &[f64],
    y: &[f64],
    out: &mut [f64],
    work: &mut [f64],
) {
    let n = y.len();
    let (w, q) = work.split_at_mut(n);
    let w = &mut w[..n];
    let q = &mut q[..n];
    if f.has_constraints() {
        // w = V P y
        w.copy_from_slice(y);
        f.apply_mask(w);
        f.from_frame_in_place(w);
        h.matvec(w, q);
        // out = P Vᵀ q + (I − P) D y
        f.to_frame_in_place(q);
        out.copy_from_slice(q);
        let d = f.dim;
        for (i, &m) in f.mask.iter().enumerate() {
            if m != 0 {
                for a in 0..d {
                    if m & (1 << a) != 0 {
                        let k = i * d + a;
                        out[k] = diag[k] * y[k];
                    }
                }
            }
        }
    } else {
        // Nothing to rotate or mask: the plain product.
        h.matvec(y, out);
    }
}

/// ‖b̂ − Ĥy‖ / ‖b̂‖ in f64 from `hy` = Ĥy (1 when b̂ = 0 and the residual is not, 0 when
/// both vanish). Overwrites `hy` with the residual b̂ − Ĥy.
pub fn relative_residual_from(rhs: &[f64], hy: &mut [f64]) -> f64 {
    let m = hy.len().min(rhs.len());
    let hy = &mut hy[..m];
    for (a, b) in hy.iter_mut().zip(rhs) {
        *a = b - *a;
    }
    let rn = norm2(hy);
    let bn = norm2(rhs);
    if bn == 0.0 {
        if rn == 0.0 {
            0.0
        } else {
            1.0
        }
    } else {
        rn / bn
    }
}

/// b̂ = −P Vᵀ(g + H Δx_p), with H given as a product (assembled or matrix-free).
pub fn eliminated_rhs(
    g: &[f64],
    frames: &Frames,
    apply_h: impl FnOnce(&[f64], &mut [f64]),
) -> Vec<f64> {
    let nd = g.len();
    let mut r = g.to_vec();
    if !frames.homogeneous {
        let mut hl = vec![0.0; nd];
        apply_h(&frames.lift, &mut hl);
        for (rk, hk) in r.iter_mut().zip(&hl) {
            *rk += hk;
        }
    }
    let mut rhs = vec![0.0; nd];
    frames.to_frame(&r, &mut rhs);
    for v in rhs.iter_mut() {
        *v = -*v;
    }
    frames.apply_mask(&mut rhs);
    rhs
}

/// f = −(H Δx + g): the constraint (support) forces at the solution.
pub fn reactions(h: &BlockCsr, g: &[f64], dx: &[f64]) -> Vec<f64> {
    let mut f = vec![0.0; dx.len()];
    h.matvec(dx, &mut f);
    for (v, gv) in f.iter_mut().zip(g) {
        *v = -(*v + gv);
    }
    f
}

/// VᵀHV on H's block pattern (no masking): blocks touching a rotated node are rotated,
/// all others copied.
pub fn rotate_blocks(h: &BlockCsr, f: &Frames) -> BlockCsr {
    let mut m = h.clone();
    if !f.has_rotation() {
        return m;
    }
    let d = h.dim;
    for i in 0..h.n {
        let vi = f.rotation(i);
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            let j = h.col_idx[k];
            let vj = f.rotation(j);
            if vi.is_none() && vj.is_none() {
                continue;
            }
            let b = h.block(k);
            let out = &mut m.values[k * d * d..(k + 1) * d * d];
            rotate_block(d, b, vi, vj, out);
        }
    }
    m
}

/// out = V_iᵀ B V_j (either rotation may be the identity).
pub fn rotate_block(d: usize, b: &[f64], vi: Option<&[f64]>, vj: Option<&[f64]>, out: &mut [f64]) {
    let mut t = [0.0f64; 9];
    // t = B V_j
    for r in 0..d {
        for c in 0..d {
            t[r * d + c] = match vj {
                Some(v) => (0..d).map(|k| b[r * d + k] * v[k * d + c]).sum(),
                None => b[r * d + c],
            };
        }
    }
    // out = V_iᵀ t
    for r in 0..d {
        for c in 0..d {
            out[r * d + c] = match vi {
                Some(v) => (0..d).map(|k| v[k * d + r] * t[k * d + c]).sum(),
                None => t[r * d + c],
            };
        }
    }
}

/// diag(VᵀHV), length d·n.
pub fn rotated_diagonal(h: &BlockCsr, f: &Frames) -> Vec<f64> {
    let d = h.dim;
    let mut out = vec![0.0; h.ndof()];
    let mut blk = [0.0f64; 9];
    for i in 0..h.n {
        if let Some(k) = h.diag_index(i) {
            let v = f.rotation(i);
            rotate_block(d, h.block(k), v, v, &mut blk[..d * d]);
            for a in 0..d {
                out[i * d + a] = blk[a * d + a];
            }
        }
    }
    out
}

/// The scaled Euclidean norm, re-exported from the crate's linear-algebra helpers.
pub use crate::core::linalg::norm2;
