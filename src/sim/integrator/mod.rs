//! Implicit Euler as an incremental potential (IPC style), with Dirichlet conditions
//! eliminated by the per-node change of basis and moving conditions as in docs/method.md
//! ("Time integration", "Moving boundary conditions").
//!
//! One step n → n+1 (h the time step, x̃ = xⁿ + h vⁿ):
//!
//! ```text
//! E(x) = ½ (x − x̃)ᵀ M (x − x̃) + h² Ψ(x) + Σ_{k unsatisfied} [½ k_M m_k ‖r_k(x)‖² − √m_k λ_kᵀ r_k(x)]
//! ```
//!
//! 1. Static conditions are projected at the start (sticky nodes snapped, slip nodes
//!    projected onto their plane or line; a node with several conditions onto their
//!    intersection, which must exist: see [`crate::sim::scene::joint_targets`]); they then hold
//!    through every Newton step because every step is homogeneous (Δx has no constrained
//!    component).
//! 2. Moving condition k has a target set at t^{n+1} (x̂_k for sticky, a moved plane or
//!    line for slip); r_k is the node's offset from it (slip: along the normal only). A node
//!    with ‖r_k‖/h < ε is snapped onto its target and eliminated; the others carry the
//!    penalty. When Newton converges with nodes still unsatisfied, k_M doubles (capped;
//!    with the augmented Lagrangian, λ is updated and k_M doubles only when the residual
//!    did not halve). k_M persists across steps. The step ends only when every moving node
//!    is eliminated and Newton has converged with elimination alone.
//! 3. Newton: eliminated linear solve (oracle / CG / GPU), Armijo backtracking, stop when
//!    ‖Δx‖∞/h < tol. Frames are built once per constraint set and cached, so are the
//!    oracle's symbolic analysis and the GPU solver (keyed by the set).
//! 4. v^{n+1} = (x^{n+1} − xⁿ)/h. Reactions f = +(constrained part of ∇E)/h² per node (the
//!    components along C_i): the force the supports exert on the body, in newtons, so that
//!    Σ m (v^{n+1} − vⁿ) = h (M g + Σ f) holds exactly when Newton has converged (a body
//!    resting on a floor gets an upward f). Sign: M(x − x̃) + h²∇Ψ = ∇E, and at the
//!    constrained minimum ∇E vanishes on free components and equals h² f on constrained
//!    ones. This is −1 times `elimination::reactions` (−(HΔx + g), the load on the
//!    support). Moving nodes are eliminated at the end of every step, so the force that
//!    drives them shows up as their reaction; no penalty force is left at the end of a step.
//!
//! Inversion (classical neo-Hookean elements only; docs/method.md): their energy is +∞
//! for J ≤ 0, so each line search starts at most at [`INVERSION_FRACTION`] of the first
//! step size α along Δx at which an element's J reaches zero (the smallest positive root of
//! det F(x + αΔx), `energy::Model::inversion_bound`), together with the CCD bound below;
//! every iterate then keeps every such element's J positive, and an element already
//! inverted fails the step naming it. Every step reports the smallest J of its end state
//! ([`StepReport::min_j`]) and the laws with an inverted element; `[solver] inversion =
//! "fail"` makes such a step fail.
//!
//! Contact (only when the scene declares obstacles; docs/method.md, "Contact with
//! half-spaces"): E gains h² P_b(x), the distance
//! barrier of [`crate::sim::energy::barrier`] against every half-space at its end-of-step
//! position. Each line search starts from the CCD bound α_C (every node, interior nodes
//! included, covers at most [`CCD_FRACTION`] of its distance to every plane) and backtracks
//! from there, so every Newton iterate keeps every node on the allowed side; the smallest
//! distance over all nodes and iterates of a step is reported. Interior nodes of a solid
//! carry no barrier: when the bound is what stops one (the line search takes α_C and the
//! node sets it), the step fails naming the node and the obstacle, since Newton would only
//! creep towards the plane from there (the body has inverted). A moving half-space that
//! would overtake a node within one step pushes that (unconstrained) node's initial guess
//! ahead of it first (to half its gap at tⁿ): only the starting iterate changes, the
//! minimized energy does not. The contact force
//! c = −∇P_b (newtons) is an external force counted apart from the reactions:
//! Σ m (v^{n+1} − vⁿ) = h (M g + Σ f + Σ c). On a constrained node within d̂, the reaction
//! is taken net of the barrier (f = constrained part of ∇E/h², which includes h²∇P_b).
//!
//! The loop is written once ([`Stepper`], `stepper.rs`) over a backend that holds the
//! iterate: the host backend (`host.rs`: arrays, the library's solver) or the device
//! backend (`device.rs`: device buffers, scalars read back). Everything the loop decides
//! is decided on the host by the same code for both.

mod backend;
mod balance;
mod device;
mod dump;
mod error;
mod forcing;
mod host;
mod linear;
mod report;
mod state;
mod stepper;
mod targets;

pub use balance::{force_balance_of, ForceBalance, POSITION_ULPS};
pub use device::{check_capacity, device_bytes_needed};
pub use dump::{NewtonSystem, StepSelection, SystemSink};
pub use error::{InitError, StepError, Unbalanced};
pub use linear::{LinearSolver, LinearStats, CHOLESKY_MAX_RESIDUAL};
pub use report::{ContactCounters, GpuRunReport, StepReport};
pub use state::{Snapshot, State, CCD_FRACTION, INVERSION_FRACTION, STATIC_PROJECTION_FRACTION};
pub use stepper::Stepper;
pub use targets::{offset, projector};
