//! The line search's first trial, recorded after every chunk of the device CG and gated on
//! the chunk's verification having met the tolerance ([`crate::gpu::gate`]): ‖Δx‖∞ and
//! g·Δx, E at x, the CCD and inversion bounds, the first step α_C as the line search takes
//! it, the trial point x + α_C Δx and E there, and the force balance at x. When the solve
//! converges within a chunk all of it comes back with the CG's status, so a Newton
//! iteration whose first trial is accepted waits on the device once; when it does not,
//! the gated work costs two small dispatches and the loop asks for what it needs.
//!
//! Every quantity is the one the loop would compute with its own calls (the same kernels
//! on the same data); only the time and the round trips differ.

use crate::gpu::gate::{Dispatch, Gate};
use crate::gpu::kernels::slots;
use crate::gpu::{GpuContext, GpuError, Phase};
use crate::sim::device::checks::{BalanceFrames, NewtonChecks};
use crate::sim::device::elements::GpuElements;
use crate::sim::device::newton_ops::NewtonOps;
use crate::sim::energy::barrier::{Ccd, HalfSpace};
use crate::sim::energy::{InversionLimit, Inverted};
use crate::sim::integrator::ForceBalance;

/// Gated dispatches one tail may hold per pass (element terms and their chunks, the
/// reductions, the checks' per-set passes).
const CAPACITY: usize = 256;

/// What the first trial takes from the scene and the loop.
pub struct TailInputs<'a> {
    pub ops: &'a NewtonOps,
    pub checks: &'a NewtonChecks,
    pub elements: &'a GpuElements,
    /// The obstacles' half-spaces and the CCD's fraction (with contact).
    pub ccd: Option<(&'a [HalfSpace], f64)>,
    /// The inversion bound's largest step and the fraction of it the first step takes
    /// (with classical neo-Hookean elements).
    pub inversion: Option<(f64, f64)>,
    /// The force balance's frames and the time step.
    pub balance: Option<(&'a BalanceFrames, f64)>,
}

/// The first trial's results.
#[derive(Debug, Clone, PartialEq)]
pub struct LineScalars {
    /// ‖Δx‖∞ (NaN where an entry is) and g·Δx.
    pub dmax: f64,
    pub slope: f64,
    /// Per element term its energy at x and at the trial point, and the moving energy at
    /// both.
    pub terms_at_x: Vec<f64>,
    pub moving_at_x: f64,
    pub terms_at_trial: Vec<f64>,
    pub moving_at_trial: f64,
    pub ccd: Option<Ccd>,
    pub inversion: Option<Result<Option<InversionLimit>, Inverted>>,
    /// The trial's α (α_C).
    pub alpha: f64,
    pub balance: Option<ForceBalance>,
}

/// The two gates of the first trial (E at x and the bounds, then the trial's energy and
/// the force balance: E at x is copied out between them).
pub struct LineSearchTail {
    before: Gate,
    after: Gate,
}

impl LineSearchTail {
    /// Gated on STATE_TRUE_OK of the device CG's `state`.
    pub fn new(ctx: &GpuContext, state: &wgpu::Buffer) -> Result<Self, GpuError> {
        let flag = slots::STATE_TRUE_OK;
        Ok(LineSearchTail {
            before: Gate::new(ctx, state, flag, CAPACITY)?,
            after: Gate::new(ctx, state, flag, CAPACITY)?,
        })
    }

    /// Records the first trial into `enc` (its inputs' scalars written for the next
    /// submit).
    pub fn record(&self, enc: &mut wgpu::CommandEncoder, inp: &TailInputs) -> Result<(), GpuError> {
        let ops = inp.ops;
        let mut before: Vec<Dispatch> = ops.energy_dispatches();
        before.extend(ops.moving_energy_dispatches());
        before.extend(ops.direction_dispatches());
        if let Some((max, _)) = inp.inversion {
            before.extend(inp.checks.inversion_dispatches(max));
        }
        if let Some((planes, fraction)) = inp.ccd {
            before.extend(ops.ccd_dispatches(planes, fraction)?);
        }
        let inversion = inp
            .inversion
            .map(|(_, fraction)| (inp.checks.inversion_slot(), fraction));
        before.extend(ops.trial_dispatches(inp.ccd.is_some(), inversion));
        self.before
            .record(enc, "line search: first trial", Phase::LineSearch, &before)?;
        ops.record_energy_copy(enc);
        let mut after = inp.elements.dispatches(true, true);
        after.extend(ops.energy_dispatches());
        after.extend(ops.moving_energy_dispatches());
        if let Some((frames, h)) = inp.balance {
            after.extend(inp.checks.balance_dispatches(frames, h)?);
        }
        self.after.record(
            enc,
            "line search: energy at the trial",
            Phase::LineSearch,
            &after,
        )
    }

    /// The first trial's results from the values of the loop's whole result buffer and of
    /// its copies of E at x ([`NewtonOps::energy_at_x_buffer`]).
    pub fn decode(inp: &TailInputs, result: &[f64], at_x: &[f64]) -> Result<LineScalars, GpuError> {
        let ops = inp.ops;
        let terms = ops.kinds().len();
        if result.len() < 4 * ops.result_slots() || at_x.len() < 4 * (terms + 1) {
            return Err(GpuError::Mismatch(format!(
                "{} and {} result values, the first trial's slots need {} and {}",
                result.len(),
                at_x.len(),
                4 * ops.result_slots(),
                4 * (terms + 1)
            )));
        }
        let (dmax, slope) = ops.decode_direction(result);
        let (moving_at_x, moving_at_trial) = ops.decode_moving_energies(result, at_x);
        let slot = |k: usize| &result[4 * k..4 * k + 4];
        let inversion = match inp.inversion {
            Some(_) => Some(
                inp.checks
                    .decode_inversion_bound(slot(inp.checks.inversion_slot()))?,
            ),
            None => None,
        };
        let balance = match inp.balance {
            Some(_) => Some(
                inp.checks
                    .decode_force_balance(slot(inp.checks.balance_slot()))?,
            ),
            None => None,
        };
        Ok(LineScalars {
            dmax,
            slope,
            terms_at_x: ops.decode_energy_terms(at_x, 0),
            moving_at_x,
            terms_at_trial: ops.decode_energy_terms(result, 0),
            moving_at_trial,
            ccd: inp
                .ccd
                .map(|(planes, _)| ops.decode_ccd(result, planes.len())),
            inversion,
            alpha: ops.decode_alpha(result),
            balance,
        })
    }
}
