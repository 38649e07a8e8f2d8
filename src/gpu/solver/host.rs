//! The host copy of the system (`Host`): f64 products and residuals, the largest
//! diagonal entry and the recovery Δx = Δx_p + V P y, plus the mass-spring helpers that derive the
//! right-hand side, diagonal blocks, adjacency and spring data from a `MassSpring`.

use crate::cases::springs::MassSpring;
use crate::core::constraints::Frames;
use crate::core::elimination::{apply_eliminated, relative_residual_from, rotate_block};
use crate::core::sparse::BlockCsr;

/// The host copy of the system, for the true f64 residual and the recovery.
pub(crate) enum HostOp {
    Blocks(BlockCsr),
    Springs(MassSpring),
}

pub(crate) struct Host {
    pub(crate) op: HostOp,
    pub(crate) frames: Frames,
    pub(crate) rhs: Vec<f64>,
    pub(crate) diag: Vec<f64>,
    /// Reusable f64 scratch for the host products: Ĥy (d·n) and the work of the product
    /// (2·d·n); its contents between calls do not matter.
    scratch: Vec<f64>,
}

/// out = Ĥ y in f64 for the host operator; `work` has length 2·d·n (contents ignored).
fn host_apply(op: &HostOp, f: &Frames, diag: &[f64], y: &[f64], out: &mut [f64], work: &mut [f64]) {
    match op {
        HostOp::Blocks(h) => apply_eliminated(h, f, diag, y, out, work),
        HostOp::Springs(ms) => {
            let w = &mut work[..y.len()];
            w.copy_from_slice(y);
            f.apply_mask(w);
            f.from_frame_in_place(w);
            ms.apply(w, out);
            f.to_frame_in_place(out);
            let d = f.dim;
            for (i, &m) in f.mask.iter().enumerate() {
                for a in 0..d {
                    if m & (1 << a) != 0 {
                        out[i * d + a] = diag[i * d + a] * y[i * d + a];
                    }
                }
            }
        }
    }
}

impl Host {
    pub(crate) fn new(op: HostOp, frames: Frames, rhs: Vec<f64>, diag: Vec<f64>) -> Self {
        let scratch = vec![0.0; 3 * rhs.len()];
        Host {
            op,
            frames,
            rhs,
            diag,
            scratch,
        }
    }

    pub(crate) fn ndof(&self) -> usize {
        self.rhs.len()
    }

    /// out = Ĥ y in f64 (no per-call allocation once the scratch has its size).
    pub(crate) fn apply(&mut self, y: &[f64], out: &mut [f64]) {
        let n = y.len();
        let Host {
            op,
            frames,
            diag,
            scratch,
            ..
        } = self;
        if scratch.len() < 3 * n {
            scratch.resize(3 * n, 0.0);
        }
        host_apply(op, frames, diag, y, out, &mut scratch[..2 * n]);
    }

    /// Largest |diagonal entry| of H (its diagonal blocks, before rotation and masking).
    pub(crate) fn diag_max(&self) -> f64 {
        match &self.op {
            HostOp::Blocks(h) => blocks_diag_max(h),
            HostOp::Springs(ms) => {
                let d = ms.dim;
                spring_diag_blocks(ms, &self.frames)
                    .chunks_exact(d * d)
                    .flat_map(|b| (0..d).map(move |a| b[a * d + a].abs()))
                    .filter(|v| v.is_finite())
                    .fold(0.0, f64::max)
            }
        }
    }

    /// ‖b̂ − Ĥy‖ / ‖b̂‖ in f64, as [`Eliminated::relative_residual`].
    pub(crate) fn relative_residual(&mut self, y: &[f64]) -> f64 {
        let n = y.len();
        let Host {
            op,
            frames,
            rhs,
            diag,
            scratch,
        } = self;
        if scratch.len() < 3 * n {
            scratch.resize(3 * n, 0.0);
        }
        let (hy, work) = scratch.split_at_mut(n);
        host_apply(op, frames, diag, y, hy, &mut work[..2 * n]);
        relative_residual_from(rhs, hy)
    }

    /// Δx = Δx_p + V P y in f64 with the f64 frames, whatever precision y was found in:
    /// the constrained components are then exactly the lift's.
    pub(crate) fn recover(&self, y: &[f64]) -> Vec<f64> {
        let f = &self.frames;
        let mut dx = y.to_vec();
        f.apply_mask(&mut dx);
        f.from_frame_in_place(&mut dx);
        if !f.homogeneous {
            for (v, l) in dx.iter_mut().zip(&f.lift) {
                *v += l;
            }
        }
        dx
    }
}

/// b̂ = −P Vᵀ(g + H Δx_p) for the matrix-free system.
pub(crate) fn spring_rhs(ms: &MassSpring, g: &[f64], frames: &Frames) -> Vec<f64> {
    crate::core::elimination::eliminated_rhs(g, frames, |x, y| ms.apply(x, y))
}

/// Diagonal blocks V_iᵀ H_ii V_i of the spring Hessian, computed on the host (O(springs)).
pub(crate) fn spring_diag_blocks(ms: &MassSpring, frames: &Frames) -> Vec<f64> {
    let d = ms.dim;
    let n = ms.n_nodes();
    let mut out = vec![0.0; n * d * d];
    for i in 0..n {
        for a in 0..d {
            out[i * d * d + a * d + a] = ms.masses[i];
        }
    }
    let h2 = ms.h * ms.h;
    for (e, &[i, j]) in ms.edges.iter().enumerate() {
        let k = ms.spring_hessian(e);
        for node in [i, j] {
            for c in 0..d * d {
                out[node * d * d + c] += h2 * k[c];
            }
        }
    }
    let mut tmp = [0.0f64; 9];
    for i in 0..n {
        if let Some(v) = frames.rotation(i) {
            rotate_block(
                d,
                &out[i * d * d..(i + 1) * d * d],
                Some(v),
                Some(v),
                &mut tmp[..d * d],
            );
            out[i * d * d..(i + 1) * d * d].copy_from_slice(&tmp[..d * d]);
        }
    }
    out
}

/// Node adjacency of the springs: per node, (other node, spring) pairs.
pub(crate) fn spring_adjacency(ms: &MassSpring) -> (Vec<u32>, Vec<u32>) {
    let n = ms.n_nodes();
    let mut count = vec![0u32; n + 1];
    for &[i, j] in &ms.edges {
        count[i + 1] += 1;
        count[j + 1] += 1;
    }
    for i in 0..n {
        count[i + 1] += count[i];
    }
    let mut fill = count.clone();
    let mut adj = vec![0u32; 2 * count[n] as usize];
    for (e, &[i, j]) in ms.edges.iter().enumerate() {
        for (a, b) in [(i, j), (j, i)] {
            let k = fill[a] as usize;
            adj[2 * k] = b as u32;
            adj[2 * k + 1] = e as u32;
            fill[a] += 1;
        }
    }
    (count, adj)
}

pub(crate) fn spring_data(ms: &MassSpring) -> Vec<f64> {
    let h2 = ms.h * ms.h;
    ms.rest_lengths
        .iter()
        .zip(&ms.stiffness)
        .flat_map(|(&l, &k)| [l, h2 * k])
        .collect()
}

/// S_i = Σ_j Ĥ_ij for every node i, d·d row-major, in f64 (the difference form's diagonal,
/// see `shaders/matvec.wgsl`); Ĥ_ij = V_iᵀ H_ij V_j where a rotation is involved, unmasked
/// like the device blocks.
pub(crate) fn row_sums(h: &BlockCsr, f: &Frames) -> Vec<f64> {
    let d = h.dim;
    let dd = d * d;
    let mut out = vec![0.0; h.n * dd];
    let mut rb = [0.0f64; 9];
    for i in 0..h.n {
        let s = &mut out[i * dd..(i + 1) * dd];
        let vi = f.rotation(i);
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            let vj = f.rotation(h.col_idx[k]);
            let b = h.block(k);
            let b = if vi.is_none() && vj.is_none() {
                b
            } else {
                rotate_block(d, b, vi, vj, &mut rb[..dd]);
                &rb[..dd]
            };
            for (se, be) in s.iter_mut().zip(b) {
                *se += be;
            }
        }
    }
    out
}

/// Largest finite |diagonal entry| of a block matrix's diagonal blocks.
pub(crate) fn blocks_diag_max(h: &BlockCsr) -> f64 {
    let d = h.dim;
    (0..h.n)
        .filter_map(|i| h.diag_index(i))
        .flat_map(|k| (0..d).map(move |a| h.values[k * d * d + a * d + a].abs()))
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
}
