//! The device PCG's glue to the multilevel levels built on the device
//! ([`DeviceCg::set_multilevel_on_device`], src/gpu/pcg/mlsetup.rs): what of the PCG's H,
//! pattern and constraint frames the setup reads, and the levels read back.

use super::{DeviceCg, DeviceFrames, Scalars};
use crate::gpu::pcg::mlsetup::{FinestMatrix, FramesOnDevice};
use crate::gpu::pcg::multilevel::{DeviceMultilevel, Finest, LevelValues};
use crate::gpu::GpuError;
use crate::solve::multilevel::reuse::Levels;
use crate::solve::multilevel::Hierarchy;
use std::sync::Arc;

impl DeviceFrames {
    /// The frame words and rotations as the multilevel setup binds them.
    fn on_device(&self) -> FramesOnDevice<'_> {
        FramesOnDevice {
            id: self.id,
            frame: &self._frame,
            rotations: &self._rotations,
        }
    }
}

impl DeviceCg {
    /// The multilevel preconditioner of the system just prepared, built on the device from
    /// the H this PCG reads and the constraint set of `frames`, or the kept levels
    /// refreshed, as `how` says ([`crate::solve::multilevel::reuse::KeptLevels::plan`]):
    /// src/gpu/pcg/mlsetup.rs. Nothing of the system's size crosses the bus. Call after
    /// every `prepare`, as [`DeviceCg::set_multilevel`]; `binding_limit` as there.
    pub fn set_multilevel_on_device(
        &mut self,
        hierarchy: &Arc<Hierarchy>,
        frames: &DeviceFrames,
        how: Levels,
        binding_limit: Option<u64>,
    ) -> Result<(), GpuError> {
        self.own(frames)?;
        let (n, nnz) = (self.n_nodes, self.host_pattern[self.n_nodes] as usize);
        if hierarchy.patterns().first().map(|p| p.n) != Some(n) {
            return Err(GpuError::Mismatch(format!(
                "the multilevel hierarchy is not of this PCG's {n} nodes"
            )));
        }
        if self.ty != Scalars::F64 {
            return Err(GpuError::Unsupported(
                "the multilevel preconditioner runs in f64 only".into(),
            ));
        }
        if self.ml.is_none() {
            self.ml = Some(DeviceMultilevel::new(&self.ctx, self.dim)?);
        }
        let (Some(dm), b) = (self.ml.as_mut(), &self.buf) else {
            return Err(GpuError::Internal("the device V-cycle was not made".into()));
        };
        let too_big = || GpuError::Unsupported("H exceeds the device's u32 indices".into());
        let matrix = FinestMatrix {
            pattern: &b.pattern,
            col_at: u32::try_from(n + 1).map_err(|_| too_big())?,
            diag_at: u32::try_from(n + 1 + nnz).map_err(|_| too_big())?,
            chunks: b.hvals.iter().zip(b.hruns.iter().cloned()).collect(),
            frames: frames.on_device(),
        };
        let finest = Finest {
            r: &b.r,
            z: &b.z,
            q: &b.q,
            state: &b.state,
        };
        dm.compute(hierarchy, how, finest, &matrix, binding_limit)?;
        self.ml_ready = true;
        Ok(())
    }

    /// The multilevel levels on the device, read back: ω (and, built on the device, its
    /// λ̂), the coarse matrices, the cluster inverses (level 0's with the constrained rows
    /// and columns zero), P and Pᵀ per level (tests and diagnostics; empty before the
    /// levels are set).
    pub fn read_multilevel(&self) -> Result<Vec<LevelValues>, GpuError> {
        match &self.ml {
            Some(dm) => dm.read_levels(),
            None => Ok(Vec::new()),
        }
    }
}
