//! The operations' part of the line search's first trial recorded after every chunk of the
//! CG (`sim::device::line_search`): their dispatches for a caller that records them, the
//! result slots they leave, and the trial's own slots (α, and E at x kept before the
//! trial's sums overwrite it).

use super::{
    slot_count, NewtonOps, Op, CHECK_SLOTS, NO_INDEX, S_FRACTION, S_INV_FRACTION, TAIL_SLOTS,
};
use crate::gpu::gate::Dispatch;
use crate::gpu::GpuError;
use crate::sim::device::elements::to_bytes;
use crate::sim::energy::barrier::{Ccd, HalfSpace};

impl NewtonOps {
    /// The slot of the trial's α (`trial` reads it; `step_bound` or the host writes it).
    pub fn alpha_slot(&self) -> usize {
        slot_count(self.energy.len()) + CHECK_SLOTS
    }

    /// Every result slot (what a caller reads back whole).
    pub fn result_slots(&self) -> usize {
        self.alpha_slot() + TAIL_SLOTS
    }

    /// The per-term energy sums and the moving energy at x, copied out of the result slots
    /// before a trial's own sums overwrite them (one slot each, in `energy_at_x`).
    pub fn energy_at_x_buffer(&self) -> (&wgpu::Buffer, u64) {
        (&self.energy_at_x, 32 * (self.energy.len() as u64 + 1))
    }

    fn dispatch(&self, op: &Op, groups: usize) -> Dispatch {
        Dispatch {
            pipeline: self.pipelines[op.entry as usize].clone(),
            group: op.group.clone(),
            launch: self.ctx.launch().reduction(groups as u32, super::WG),
        }
    }

    /// The per-term energy sums at the evaluation positions (into slots 0..terms).
    pub fn energy_dispatches(&self) -> Vec<Dispatch> {
        let mut d: Vec<Dispatch> = self
            .energy
            .iter()
            .map(|o| self.dispatch(o, self.groups))
            .collect();
        d.push(self.dispatch(&self.energy_finish, self.energy.len()));
        d
    }

    /// The moving nodes' penalty energy (none without unsnapped moving nodes).
    pub fn moving_energy_dispatches(&self) -> Vec<Dispatch> {
        match &self.moving {
            Some(m) if m.count > 0 => vec![
                self.dispatch(&m.energy, self.groups),
                self.dispatch(&m.energy_finish, 1),
            ],
            _ => Vec::new(),
        }
    }

    /// ‖Δx‖∞ and g·Δx.
    pub fn direction_dispatches(&self) -> Vec<Dispatch> {
        vec![
            self.dispatch(&self.max_abs.0, self.groups),
            self.dispatch(&self.max_abs.1, 1),
            self.dispatch(&self.dot.0, self.groups),
            self.dispatch(&self.dot.1, 1),
        ]
    }

    /// The CCD bound against `planes` (written for the next submit).
    pub fn ccd_dispatches(
        &self,
        planes: &[HalfSpace],
        fraction: f64,
    ) -> Result<Vec<Dispatch>, GpuError> {
        let slot = slot_count(self.energy.len()) - 3;
        self.write_planes(planes, &self.ccd.0, super::MODE_CCD, slot)?;
        self.write_scalars(S_FRACTION, &[fraction]);
        Ok(vec![
            self.dispatch(&self.ccd.0, self.groups),
            self.dispatch(&self.ccd.1, 1),
        ])
    }

    /// The line search's first α from the CCD bound (with `ccd`) and the inversion bound in
    /// result slot `inversion` (its fraction `fraction`), then the trial point at it.
    pub fn trial_dispatches(&self, ccd: bool, inversion: Option<(usize, f64)>) -> Vec<Dispatch> {
        let mut p = super::OpsParams {
            count: 0,
            mode: (slot_count(self.energy.len()) - 3) as u32,
            slot: self.alpha_slot() as u32,
            aux: u32::from(ccd),
        };
        if let Some((slot, fraction)) = inversion {
            p.count = slot as u32;
            p.aux |= 2;
            self.write_scalars(S_INV_FRACTION, &[fraction]);
        }
        self.set_params(&self.step_bound, p);
        let nd = self.n_nodes * self.dim;
        vec![
            self.dispatch(&self.step_bound, 1),
            self.dispatch(&self.trial, Self::grid(nd)),
        ]
    }

    /// Copies E's per-term sums and the moving energy at x out of the slots the trial's
    /// sums reuse (recorded between the two).
    pub fn record_energy_copy(&self, enc: &mut wgpu::CommandEncoder) {
        let t = self.energy.len() as u64;
        let (r, kept) = (&self.binder.result, &self.energy_at_x);
        enc.copy_buffer_to_buffer(r, 0, kept, 0, t * 32);
        let moving = (slot_count(self.energy.len()) - 1) as u64 * 32;
        enc.copy_buffer_to_buffer(r, moving, kept, t * 32, 32);
    }

    /// Per term its energy sum (+∞ where a barrier node touches a plane) from the four
    /// values of each slot from `first`.
    pub fn decode_energy_terms(&self, result: &[f64], first: usize) -> Vec<f64> {
        (0..self.energy.len())
            .map(|k| {
                let r = &result[4 * (first + k)..];
                if r[1] > 0.0 {
                    f64::INFINITY
                } else {
                    r[0]
                }
            })
            .collect()
    }

    /// The moving energy at x (from the copies) and at the trial point (0 without
    /// unsnapped moving nodes).
    pub fn decode_moving_energies(&self, result: &[f64], at_x: &[f64]) -> (f64, f64) {
        let active = self.moving.as_ref().is_some_and(|m| m.count > 0);
        if !active {
            return (0.0, 0.0);
        }
        let trial = 4 * (slot_count(self.energy.len()) - 1);
        (at_x[4 * self.energy.len()], result[trial])
    }

    /// (‖Δx‖∞, NaN where an entry is NaN; g·Δx).
    pub fn decode_direction(&self, result: &[f64]) -> (f64, f64) {
        let t = self.energy.len();
        let m = &result[4 * (t + 1)..];
        let dmax = if m[1] > 0.0 { f64::NAN } else { m[0] };
        (dmax, result[4 * t])
    }

    /// The CCD bound against `planes` planes, as [`NewtonOps::ccd`] decodes it.
    pub fn decode_ccd(&self, result: &[f64], planes: usize) -> Ccd {
        let r = &result[4 * (slot_count(self.energy.len()) - 3)..];
        let limit = (r[1] < NO_INDEX && planes > 0).then(|| {
            let k = r[1] as usize;
            (k / planes, k % planes)
        });
        Ccd {
            alpha: r[0].max(0.0),
            limit,
        }
    }

    /// The trial's α.
    pub fn decode_alpha(&self, result: &[f64]) -> f64 {
        result[4 * self.alpha_slot()]
    }

    /// The result values as f64 from the bytes of the whole result buffer.
    pub fn result_values(bytes: &[u8]) -> Vec<f64> {
        crate::sim::device::elements::from_bytes(true, bytes)
    }

    /// Writes α for the next trial (the host's).
    pub(super) fn write_alpha(&self, alpha: f64) {
        self.ctx.write_buffer(
            &self.binder.result,
            self.alpha_slot() as u64 * 32,
            &to_bytes(true, &[alpha]),
        );
    }
}
