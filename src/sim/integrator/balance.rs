//! Whether an iterate is a stationary point of the step's energy E: its force balance.
//!
//! ‖Δx‖∞/h < tol alone accepts any iterate where ∇²E is large against ∇E: a huge time
//! step, or a node deep in a barrier, makes every Newton step short although the forces
//! do not balance. A step is therefore also required to balance its forces: the largest
//! free component of ∇E at a node, against the largest sum of the sizes of the forces
//! that ∇E adds up at a node. Both are measured in the same units, so the test does not
//! depend on h, the material, the mass or the barrier's stiffness.

use super::state::State;
use crate::core::constraints::Frames;
use crate::sim::energy::barrier::{Barrier, HalfSpace};
use crate::sim::energy::{AssemblyWork, Model};

// A step's iterate is stationary when its largest unbalanced free force is at most
// `[solver] force_tolerance` (default 1e-4) of the step's force scale
// ([`ForceBalance::scale`]). Rounding leaves ∇E at about ε of the forces it sums. Every
// step of the built-in scenes passes ‖Δx‖∞/h < tol at 1.6e-5 of its force scale or less
// (the default scene's first step; the others stay below 4e-6), so the default adds no
// Newton iteration there; a step with a huge h or a node deep in a barrier passes
// ‖Δx‖∞/h < tol at about 1 and goes on.

/// How far an iterate is from balancing its forces.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ForceBalance {
    /// max_i ‖P_i V_iᵀ ∇_i E‖: the largest unbalanced force on a node's free components
    /// (a force × h², as ∇E is).
    pub residual: f64,
    /// The node of `residual`.
    pub node: usize,
    /// max_i of the sizes of the forces ∇_i E sums: ‖m_i(x_i − x̃_i)‖ + h²(Σ_e ‖∇_iΨ_e‖ +
    /// m_i‖g‖ + Σ_planes ‖∇_i B‖), over every node.
    pub scale: f64,
    /// max_i |x_i|: where the positions' own rounding lies.
    pub x_max: f64,
}

/// A Newton step Δx with ‖Δx‖∞ at most this many ε of max |x| moves no position by more
/// than a few ulps: the iterate is as stationary as f64 positions can make it, whatever
/// its forces (a body at rest with no load balances only rounding, and its force scale is
/// rounding too).
pub const POSITION_ULPS: f64 = 64.0;

impl ForceBalance {
    /// Whether an iterate whose Newton step is `dmax` (‖Δx‖∞) long is stationary: its
    /// forces balance to `tol` of its force scale, or the step is below the positions'
    /// resolution ([`POSITION_ULPS`]).
    pub fn stationary(&self, dmax: f64, tol: f64) -> bool {
        self.residual <= tol * self.scale || dmax <= POSITION_ULPS * f64::EPSILON * self.x_max
    }
}

/// The force balance of the iterate x of a step (x̃ its inertial target, g = ∇E(x) with
/// every moving node snapped, so no penalty term) under the constraint set `frames`.
pub(super) fn force_balance(
    state: &State,
    x: &[f64],
    xt: &[f64],
    g: &[f64],
    frames: &Frames,
    work: &mut AssemblyWork,
) -> ForceBalance {
    let sc = state.scene;
    let contact = state.contact.as_ref().map(|c| (&c.barrier, &c.planes[..]));
    force_balance_of(&sc.model, contact, sc.time_step, x, xt, g, frames, work)
}

/// [`ForceBalance`] of the iterate x of a step of length `h` of `model` (with `contact`:
/// the barrier and its half-spaces), x̃ its inertial target, g = ∇E(x) without penalty
/// terms, under the constraint set `frames`. The residual's node is the first strict
/// maximum in node order (node 0 when every residual is zero); NaN entries count for
/// nothing, as in `f64::max`.
#[allow(clippy::too_many_arguments)]
pub fn force_balance_of(
    model: &Model,
    contact: Option<(&Barrier, &[HalfSpace])>,
    h: f64,
    x: &[f64],
    xt: &[f64],
    g: &[f64],
    frames: &Frames,
    work: &mut AssemblyWork,
) -> ForceBalance {
    let d = model.dim;
    let n = model.n_nodes;
    let h2 = h * h;
    let mut free = vec![0.0; n * d];
    frames.to_frame(g, &mut free);
    frames.apply_mask(&mut free);
    let norm = |v: &[f64]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
    let (node, residual) =
        free.chunks_exact(d)
            .map(norm)
            .enumerate()
            .fold(
                (0, 0.0),
                |best, (i, r)| if r > best.1 { (i, r) } else { best },
            );
    let mut sizes = vec![0.0; n];
    model.add_potential_force_scale(x, h2, &mut sizes, work);
    if let Some((barrier, planes)) = contact {
        barrier.add_force_scale(x, planes, h2, &mut sizes);
    }
    let mut inertia = [0.0; 3];
    for (i, s) in sizes.iter_mut().enumerate() {
        for a in 0..d {
            inertia[a] = model.mass[i] * (x[i * d + a] - xt[i * d + a]);
        }
        *s += norm(&inertia[..d]);
    }
    let scale = sizes.iter().copied().fold(0.0, f64::max);
    ForceBalance {
        residual,
        node,
        scale,
        x_max: x.iter().fold(0.0, |m: f64, v| m.max(v.abs())),
    }
}
