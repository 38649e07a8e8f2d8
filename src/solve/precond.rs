//! The point-wise preconditioners of the CPU CG, built once per system: Jacobi (1/diag Ĥ)
//! and block Jacobi (each node's d×d diagonal block of Ĥ, in its frame, inverted), with
//! the coarse correction of [`crate::solve::coarse`] added when asked.

use crate::core::elimination::{rotate_block, Eliminated};
use crate::solve::coarse::{Coarse, CoarseSpace};
use crate::solve::multilevel::{Hierarchy, Multilevel};
use crate::solve::options::Preconditioner;
use std::sync::Arc;

/// A preconditioner applied as z = M⁻¹ r.
#[derive(Debug, Clone)]
pub struct BuiltPreconditioner {
    kind: Preconditioner,
    dim: usize,
    /// Jacobi: 1/diag (length dn). BlockJacobi: d·d inverse blocks per node.
    data: Vec<f64>,
    /// The coarse correction added to M⁻¹ (see [`crate::solve::coarse`]).
    coarse: Option<Coarse>,
    /// The multilevel Schwarz factors ([`Preconditioner::Multilevel`]).
    multilevel: Option<Arc<Multilevel>>,
}

impl BuiltPreconditioner {
    /// Builds the preconditioner from the diagonal blocks of Ĥ (the multilevel one on a
    /// hierarchy partitioned for this call: [`BuiltPreconditioner::multilevel`] reuses one).
    pub fn new(e: &Eliminated, kind: Preconditioner) -> Self {
        if kind == Preconditioner::Multilevel {
            return Self::multilevel(e, Arc::new(Hierarchy::new(e.h)));
        }
        let d = e.h.dim;
        let n = e.h.n;
        let blocks = diagonal_blocks(e);
        let data = match kind {
            Preconditioner::None | Preconditioner::Multilevel => Vec::new(),
            Preconditioner::Jacobi => (0..n * d)
                .map(|k| {
                    let (i, a) = (k / d, k % d);
                    jacobi_inverse(blocks[i * d * d + a * d + a])
                })
                .collect(),
            Preconditioner::BlockJacobi => {
                let mut out = vec![0.0; n * d * d];
                for i in 0..n {
                    let b = &blocks[i * d * d..(i + 1) * d * d];
                    let inv = block_jacobi_inverse(d, b);
                    out[i * d * d..(i + 1) * d * d].copy_from_slice(&inv[..d * d]);
                }
                out
            }
        };
        BuiltPreconditioner {
            kind,
            dim: d,
            data,
            coarse: None,
            multilevel: None,
        }
    }

    /// The multilevel Schwarz preconditioner of `e` on `hierarchy` (partitioned for `e.h`'s
    /// pattern, once per mesh; a hierarchy of another pattern is rebuilt).
    pub fn multilevel(e: &Eliminated, hierarchy: Arc<Hierarchy>) -> Self {
        let hierarchy = if hierarchy.fits(e.h) {
            hierarchy
        } else {
            Arc::new(Hierarchy::new(e.h))
        };
        Self::with_levels(Arc::new(Multilevel::new(e, hierarchy)))
    }

    /// The multilevel Schwarz preconditioner on levels built (or kept) beforehand
    /// ([`crate::solve::multilevel::reuse::KeptLevels`]).
    pub fn with_levels(levels: Arc<Multilevel>) -> Self {
        BuiltPreconditioner {
            kind: Preconditioner::Multilevel,
            dim: levels.dim(),
            data: Vec::new(),
            coarse: None,
            multilevel: Some(levels),
        }
    }

    /// The multilevel factors, for [`Preconditioner::Multilevel`].
    pub fn multilevel_factors(&self) -> Option<&Multilevel> {
        self.multilevel.as_deref()
    }

    /// Adds the coarse correction of `space` on `e` (nothing for [`CoarseSpace::None`], or
    /// when every translation is constrained). `node_scale`: e is an equilibrated SĤS.
    /// The multilevel preconditioner has coarse levels of its own and takes none: added
    /// to its V-cycle, the aggregates cost iterations (BENCHMARKS.md, "The multilevel
    /// preconditioner").
    pub fn with_coarse(
        mut self,
        e: &Eliminated,
        space: CoarseSpace,
        node_scale: Option<&[f64]>,
    ) -> Self {
        if self.kind == Preconditioner::Multilevel {
            return self;
        }
        self.coarse = match space {
            CoarseSpace::None => None,
            CoarseSpace::Translations => {
                let mut work = vec![0.0; 2 * e.ndof()];
                Coarse::translations(e.frames, node_scale, |v, out| e.apply(v, out, &mut work))
            }
            CoarseSpace::Aggregates => Coarse::aggregates(e.h, e.frames, node_scale),
        };
        self
    }

    /// The coarse correction, when there is one.
    pub fn coarse(&self) -> Option<&Coarse> {
        self.coarse.as_ref()
    }

    pub fn kind(&self) -> Preconditioner {
        self.kind
    }

    /// z = M⁻¹ r.
    pub fn apply(&self, r: &[f64], z: &mut [f64]) {
        self.apply_pointwise(r, z);
        if let Some(c) = &self.coarse {
            c.add_correction(r, z);
        }
    }

    fn apply_pointwise(&self, r: &[f64], z: &mut [f64]) {
        match self.kind {
            Preconditioner::None => z.copy_from_slice(r),
            Preconditioner::Multilevel => match &self.multilevel {
                Some(m) => m.apply(r, z),
                None => z.copy_from_slice(r),
            },
            Preconditioner::Jacobi => {
                for ((zi, ri), di) in z.iter_mut().zip(r).zip(&self.data) {
                    *zi = ri * di;
                }
            }
            Preconditioner::BlockJacobi => {
                let d = self.dim;
                for i in 0..r.len() / d {
                    let m = &self.data[i * d * d..(i + 1) * d * d];
                    for a in 0..d {
                        let mut s = 0.0;
                        for b in 0..d {
                            s += m[a * d + b] * r[i * d + b];
                        }
                        z[i * d + a] = s;
                    }
                }
            }
        }
    }

    /// The raw data (1/diag, or inverse blocks), for the GPU upload.
    pub fn data(&self) -> &[f64] {
        &self.data
    }
}

/// The d×d diagonal blocks of Ĥ, row-major, n·d·d values.
pub fn diagonal_blocks(e: &Eliminated) -> Vec<f64> {
    let d = e.h.dim;
    let n = e.h.n;
    let f = e.frames;
    let mut out = vec![0.0; n * d * d];
    for i in 0..n {
        let b = &mut out[i * d * d..(i + 1) * d * d];
        if let Some(k) = e.h.diag_index(i) {
            let v = f.rotation(i);
            rotate_block(d, e.h.block(k), v, v, b);
        }
        let m = f.mask[i];
        if m != 0 {
            for r in 0..d {
                for c in 0..d {
                    if m & (1 << r) != 0 || m & (1 << c) != 0 {
                        b[r * d + c] = 0.0;
                    }
                }
                if m & (1 << r) != 0 {
                    b[r * d + r] = e.diag[i * d + r];
                }
            }
        }
    }
    out
}

/// A positive, finite value (NaN and ±∞ fail), tested as the device does.
fn positive_finite(v: f64) -> bool {
    v > 0.0 && 1.0 / v > 0.0
}

/// Jacobi's inverse of a diagonal entry: 1/v where v is positive and finite, else 1. The
/// one block-Jacobi specification, with [`block_jacobi_inverse`]; the device kernels
/// (shaders/common.wgsl) do the same operations in the same order.
pub fn jacobi_inverse(v: f64) -> f64 {
    if positive_finite(v) {
        1.0 / v
    } else {
        1.0
    }
}

/// B⁻¹ of the d×d block `b` (row-major; the result in the first d² of 9): through the
/// Cholesky factor when every pivot is positive and finite, else the Jacobi diagonal of
/// [`jacobi_inverse`] (B is not SPD where H is indefinite: CG then meets the negative
/// curvature itself rather than through the preconditioner).
pub fn block_jacobi_inverse(d: usize, b: &[f64]) -> [f64; 9] {
    let mut out = [0.0; 9];
    let mut l = [0.0; 9];
    for j in 0..d {
        let mut s = b[j * d + j];
        for m in 0..j {
            s -= l[j * d + m] * l[j * d + m];
        }
        if !positive_finite(s) {
            for a in 0..d {
                out[a * d + a] = jacobi_inverse(b[a * d + a]);
            }
            return out;
        }
        let ljj = s.sqrt();
        l[j * d + j] = ljj;
        for a in j + 1..d {
            let mut t = b[a * d + j];
            for m in 0..j {
                t -= l[a * d + m] * l[j * d + m];
            }
            l[a * d + j] = t / ljj;
        }
    }
    // Column c of B⁻¹: L u = e_c, then Lᵀ x = u.
    for c in 0..d {
        let mut u = [0.0; 3];
        for a in 0..d {
            let mut s = if a == c { 1.0 } else { 0.0 };
            for m in 0..a {
                s -= l[a * d + m] * u[m];
            }
            u[a] = s / l[a * d + a];
        }
        for a in (0..d).rev() {
            let mut s = u[a];
            for m in a + 1..d {
                s -= l[m * d + a] * u[m];
            }
            u[a] = s / l[a * d + a];
        }
        for a in 0..d {
            out[a * d + c] = u[a];
        }
    }
    out
}
