//! The host copy of the system (`Host`): f64 products and residuals, the largest
//! diagonal entry and the recovery Δx = Δx_p + V P y.

use crate::core::constraints::Frames;
use crate::core::elimination::{apply_eliminated, relative_residual_from, Eliminated};
use crate::core::sparse::BlockCsr;

/// The host copy of the system, for the true f64 residual and the recovery.
pub(crate) struct Host {
    pub(crate) h: BlockCsr,
    pub(crate) frames: Frames,
    pub(crate) rhs: Vec<f64>,
    pub(crate) diag: Vec<f64>,
    /// Reusable f64 scratch for the host products: Ĥy (d·n) and the work of the product
    /// (2·d·n); its contents between calls do not matter.
    scratch: Vec<f64>,
}

impl Host {
    pub(crate) fn new(h: BlockCsr, frames: Frames, rhs: Vec<f64>, diag: Vec<f64>) -> Self {
        let scratch = vec![0.0; 3 * rhs.len()];
        Host {
            h,
            frames,
            rhs,
            diag,
            scratch,
        }
    }

    pub(crate) fn ndof(&self) -> usize {
        self.rhs.len()
    }

    /// The eliminated system the host holds.
    pub(crate) fn eliminated(&self) -> Eliminated<'_> {
        Eliminated {
            h: &self.h,
            frames: &self.frames,
            rhs: self.rhs.clone(),
            diag: self.diag.clone(),
        }
    }

    /// out = Ĥ y in f64 (no per-call allocation once the scratch has its size).
    pub(crate) fn apply(&mut self, y: &[f64], out: &mut [f64]) {
        let n = y.len();
        if self.scratch.len() < 3 * n {
            self.scratch.resize(3 * n, 0.0);
        }
        let work = &mut self.scratch[..2 * n];
        apply_eliminated(&self.h, &self.frames, &self.diag, y, out, work);
    }

    /// ‖b̂ − Ĥy‖ / ‖b̂‖ in f64, as [`Eliminated::relative_residual`].
    pub(crate) fn relative_residual(&mut self, y: &[f64]) -> f64 {
        let n = y.len();
        if self.scratch.len() < 3 * n {
            self.scratch.resize(3 * n, 0.0);
        }
        let (hy, work) = self.scratch.split_at_mut(n);
        apply_eliminated(&self.h, &self.frames, &self.diag, y, hy, &mut work[..2 * n]);
        relative_residual_from(&self.rhs, hy)
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

/// Largest finite |diagonal entry| of a block matrix's diagonal blocks.
pub(crate) fn blocks_diag_max(h: &BlockCsr) -> f64 {
    let d = h.dim;
    (0..h.n)
        .filter_map(|i| h.diag_index(i))
        .flat_map(|k| (0..d).map(move |a| h.values[k * d * d + a * d + a].abs()))
        .filter(|v| v.is_finite())
        .fold(0.0, f64::max)
}
