//! The multilevel preconditioner of the CPU CG: one symmetric V-cycle over a hierarchy of
//! node clusters.
//!
//! Level 0 groups the nodes into clusters of about [`CLUSTER_NODES`] (a METIS k-way
//! partition of H's node graph, `partition`); each cluster's dense block of Ĥ (in the
//! node frames, constrained components masked) is inverted. Level l + 1 groups level l's
//! clusters the same way on the graph of the level-l matrix, until one cluster is left.
//! Level l + 1's unknowns are the d translations of each level-l cluster, interpolated by
//! the smoothed prolongation P_l = (I − ω D_l⁻¹A_l) T_l (`smoothed`: T_0 puts a cluster's
//! world translation into each of its nodes' frames, deeper T_l copy it to each child).
//! Each level's matrix is the Galerkin product A_{l+1} = P_lᵀ A_l P_l.
//!
//! One application z = M⁻¹r is a V-cycle: z = ω B_0⁺ r (B_l: the cluster blocks of A_l),
//! the residual restricted to level 1 and corrected there recursively, then
//! z += ω B_0⁺ (r − Ĥz); the coarsest level is solved. Pre- and post-smoothing are the
//! same symmetric step, so M⁻¹ is symmetric, and positive definite while
//! ω λmax(B_l⁺A_l) < 2: ω_l comes from a power estimate of that λmax ([`OMEGA_MAX`]).
//!
//! The CPU V-cycle reads f32 copies (`CycleLevel`): every level's matrix (level 0: Ĥ in
//! the node frames, each block stored by columns; the CG's own product with Ĥ stays f64),
//! P and Pᵀ, and each cluster block as its factor inverse G = L⁺ in 4×4 tiles applied as
//! GᵀG, with every product and sum in f64, four lanes wide. These are about a third of
//! f64 explicit inverses' and matrices' bytes; the iterations stay those of the f64 cycle
//! (docs/design/multilevel.md). Its vectors lie cluster by cluster, as the smoother reads
//! them (`slots`): the smoothing works in place, and only the cycle's input and output
//! are permuted. The f64 matrices stay too, with G in f64 packed by rows:
//! the device V-cycle uploads the matrices and the explicit inverses GᵀG in f64, which
//! [`Multilevel::levels`] computes from those when first asked (a CPU solve never does).
//!
//! Why this design (BENCHMARKS.md, "The multilevel preconditioner", has the numbers): on
//! the twist systems the additive sum of the levels' block inverses (MAS) took about
//! 2.5× the V-cycle's iterations; piecewise-constant levels grew 1.6× in iterations per
//! Newton iteration from 3,321 to 75,625 nodes, a smoothed level 1 over piecewise-constant
//! deeper levels 1.39×, and smoothing at every level far less.
//!
//! The partition ([`Hierarchy`]) depends on H's pattern only and is built once per mesh;
//! the inverses and matrices ([`Multilevel`]) are built for a system, and either rebuilt
//! for every system or kept across the systems of a Newton solve (`reuse`). Every sum runs
//! in a fixed order over a fixed partition, so the bits do not depend on the thread
//! count.
//!
//! The block factorisation drops a pivot at or below [`PIVOT_DROP`] times the largest
//! diagonal entry of its block (with its column): a coarse block is singular when its
//! translations are constrained (a pinned cluster, or slip nodes sharing a normal), and
//! the dropped pivots are exactly those directions, on which the restricted residual
//! vanishes. A negative pivot (Ĥ indefinite there) is dropped too, so the smoother stays
//! semidefinite and CG itself reports the negative curvature.

use crate::core::constraints::Frames;
use crate::core::elimination::Eliminated;
use crate::core::sparse::BlockCsr;

mod dense;
mod level;
mod partition;
pub mod reuse;
mod slots;
mod smoothed;
pub use dense::PIVOT_DROP;
pub use dense::{cholesky_dropping, inverse_from_factor};
pub use level::LAMBDA_STEPS;
use level::{
    block_matvec, factor_level, frame_block, frame_values, frame_values_into, mask_inverse,
    mirror_blocks, power_estimate, power_estimate_from, power_start, solve_level, Factors,
    Inverses, Level,
};
use partition::partition;
pub use partition::CLUSTER_NODES;
use slots::{Slots, TransferSlots};
use smoothed::{identity, node_translation, smoothed_p, SmoothPattern};

/// One level's vectors in a V-cycle, in the level's slots ([`slots`]).
#[derive(Debug, Clone)]
struct LevelWork {
    /// The right-hand side and the correction.
    b: Vec<f64>,
    x: Vec<f64>,
    /// The residual.
    res: Vec<f64>,
}

/// The vectors of every level of a V-cycle ([`Multilevel::workspace`]).
#[derive(Debug, Clone)]
pub struct VcycleWork {
    levels: Vec<LevelWork>,
}

/// The clusters of every level, from H's block pattern alone.
#[derive(Debug, Clone)]
pub struct Hierarchy {
    n: usize,
    /// Level l partitions level l's items; the last level has a single cluster.
    levels: Vec<Level>,
    /// The smoothed prolongation's patterns from each level to the next (one fewer than
    /// the levels).
    smooth: Vec<SmoothPattern>,
    /// Per level, each stored block's transposed partner ([`level::mirror_blocks`]).
    mirror: Vec<Vec<u32>>,
    /// Per level, the CPU V-cycle's layout of its vectors and matrix rows.
    slots: Vec<Slots>,
    /// From each level to the next, P's and Pᵀ's slots.
    transfers: Vec<TransferSlots>,
}

impl Hierarchy {
    /// Partitions the node graph of `h`'s pattern (both triangles stored) and every
    /// coarser level's graph.
    pub fn new(h: &BlockCsr) -> Self {
        let mut levels = Vec::new();
        let (mut row_ptr, mut col_idx) = (h.row_ptr.clone(), h.col_idx.clone());
        let mut n = h.n;
        let mut smooth = Vec::new();
        loop {
            let of = partition(n, &row_ptr, &col_idx);
            let level = Level::new(n, of, row_ptr, col_idx);
            n = level.clusters();
            if n <= 1 {
                levels.push(level);
                break;
            }
            // The next level's matrix is PᵀAP on the pattern the smoothed P gives.
            let sp = SmoothPattern::new(&level.row_ptr, &level.col_idx, &level.of, n);
            row_ptr = sp.a_ptr.clone();
            col_idx = sp.a_col.clone();
            smooth.push(sp);
            levels.push(level);
        }
        let mirror = levels.iter().map(mirror_blocks).collect();
        let slots: Vec<Slots> = levels.iter().map(|lev| Slots::new(lev, h.dim)).collect();
        let transfers = smooth
            .iter()
            .enumerate()
            .map(|(l, sp)| {
                TransferSlots::new(sp, &levels[l], &slots[l], &levels[l + 1], &slots[l + 1])
            })
            .collect();
        Hierarchy {
            n: h.n,
            levels,
            smooth,
            mirror,
            slots,
            transfers,
        }
    }

    /// The hierarchy in `kept` when it was built for `h`'s block pattern, else a new one
    /// for it; either way also left in `kept` for the next system (once per mesh).
    pub fn kept_for(
        kept: &mut Option<std::sync::Arc<Hierarchy>>,
        h: &BlockCsr,
    ) -> std::sync::Arc<Hierarchy> {
        let hierarchy = match kept.take() {
            Some(hi) if hi.fits(h) => hi,
            _ => std::sync::Arc::new(Hierarchy::new(h)),
        };
        *kept = Some(hierarchy.clone());
        hierarchy
    }

    /// Whether this hierarchy was built for `h`'s block pattern.
    pub fn fits(&self, h: &BlockCsr) -> bool {
        self.n == h.n && self.levels[0].row_ptr == h.row_ptr && self.levels[0].col_idx == h.col_idx
    }

    /// Every level's clusters and patterns, finest first: what a device builds the
    /// levels' values on ([`Multilevel::levels`] has the same with the values).
    pub fn patterns(&self) -> Vec<LevelPattern<'_>> {
        self.levels
            .iter()
            .enumerate()
            .map(|(l, lev)| LevelPattern {
                n: lev.n,
                of: &lev.of,
                pos: &lev.pos,
                ptr: &lev.ptr,
                items: &lev.items,
                row_ptr: &lev.row_ptr,
                col_idx: &lev.col_idx,
                to_next: self.smooth.get(l).map(|sp| SmoothView {
                    p_ptr: &sp.p_ptr,
                    p_col: &sp.p_col,
                    q_ptr: &sp.q_ptr,
                    q_col: &sp.q_col,
                    pt_ptr: &sp.pt_ptr,
                    pt: &sp.pt,
                }),
            })
            .collect()
    }

    /// Clusters per level, finest first.
    pub fn cluster_counts(&self) -> Vec<usize> {
        self.levels.iter().map(Level::clusters).collect()
    }

    /// How much each level's arrays hold as the device V-cycle stores them (the arrays of
    /// [`Multilevel::levels`], src/gpu/pcg/multilevel.rs packs them), for `d` components
    /// per item: what a device checks against its limits before anything is built.
    pub fn level_sizes(&self, d: usize) -> Vec<LevelSizes> {
        self.levels
            .iter()
            .enumerate()
            .map(|(l, lev)| {
                let (n, nc) = (lev.n, lev.clusters());
                // of, pos, items; the cluster ranges and the inverses' offsets.
                let mut index_words = 3 * n + 2 * (nc + 1);
                // ω; the cluster inverses apart.
                let mut values = 1;
                let inverses = (0..nc)
                    .map(|c| {
                        let m = (lev.ptr[c + 1] - lev.ptr[c]) * d;
                        m * m
                    })
                    .collect();
                if l > 0 {
                    // The level's matrix (level 0's is the device PCG's own).
                    index_words += n + 1 + lev.col_idx.len();
                    values += lev.col_idx.len() * d * d;
                }
                if let Some(sp) = self.smooth.get(l) {
                    let np = sp.p_col.len();
                    index_words += (n + 1) + np + (nc + 1) + np;
                    values += 2 * np * d * d;
                }
                LevelSizes {
                    index_words,
                    values,
                    inverses,
                    items: n,
                }
            })
            .collect()
    }
}

/// The sizes of one level as the device V-cycle stores it ([`Hierarchy::level_sizes`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LevelSizes {
    /// u32 index words: clusters and items, the matrix pattern below the finest level,
    /// the prolongation's and its transpose's patterns.
    pub index_words: usize,
    /// f64 values: ω, the matrix below the finest level, P and Pᵀ.
    pub values: usize,
    /// f64 values of each cluster's inverse (m² for m unknowns), in cluster order.
    pub inverses: Vec<usize>,
    /// Items of the level (its vectors hold items·d values).
    pub items: usize,
}

/// One level of a [`Hierarchy`], borrowed: its clusters and the patterns of its matrix
/// and of the smoothed prolongation to the next level (no values).
#[derive(Debug, Clone, Copy)]
pub struct LevelPattern<'a> {
    /// Items (nodes at level 0, clusters of the level above deeper down).
    pub n: usize,
    /// Cluster of each item, its position in the cluster, the clusters' item ranges and
    /// the items by cluster.
    pub of: &'a [u32],
    pub pos: &'a [u32],
    pub ptr: &'a [usize],
    pub items: &'a [u32],
    /// The level's matrix's block pattern (level 0: H's).
    pub row_ptr: &'a [usize],
    pub col_idx: &'a [usize],
    /// The patterns of the prolongation to the next level (none at the coarsest).
    pub to_next: Option<SmoothView<'a>>,
}

/// The patterns of one smoothed prolongation P, of Q = A P and of Pᵀ, borrowed: P's row i
/// holds blocks `p_ptr[i]..p_ptr[i + 1]` in cluster columns `p_col`, Q's the same with
/// `q_ptr`/`q_col`, and cluster c's column of P is `pt[pt_ptr[c]..pt_ptr[c + 1]]` as
/// (row item, block index in P) by row: the order the Galerkin sum takes them in.
#[derive(Debug, Clone, Copy)]
pub struct SmoothView<'a> {
    pub p_ptr: &'a [usize],
    pub p_col: &'a [u32],
    pub q_ptr: &'a [usize],
    pub q_col: &'a [u32],
    pub pt_ptr: &'a [usize],
    pub pt: &'a [(u32, u32)],
}

/// How kept levels serve a constraint set ([`Multilevel::fit`], [`frames_fit`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FramesFit {
    /// The constraint set they were built for.
    Same,
    /// More components constrained, every node in its frame or constrained whole.
    Masked,
    /// Another one: build anew.
    No,
}

/// How levels built for (or remasked to) the constraint set `old` serve `new`: as they
/// are (the same constrained components in the same node frames), after masking the
/// components `new` constrains on top (every node keeps its frame, or is constrained
/// whole), or not at all.
pub fn frames_fit(old: &Frames, new: &Frames) -> FramesFit {
    if old.n_nodes != new.n_nodes || old.dim != new.dim {
        return FramesFit::No;
    }
    if old.mask == new.mask && old.rot_index == new.rot_index && old.rotations == new.rotations {
        return FramesFit::Same;
    }
    let full = (1u8 << new.dim) - 1;
    let serves = (0..new.n_nodes).all(|i| {
        let (was, now) = (old.mask[i], new.mask[i]);
        now & was == was && (now == full || old.rotation(i) == new.rotation(i))
    });
    if serves {
        FramesFit::Masked
    } else {
        FramesFit::No
    }
}

/// The smoother's damping is ω_l = min([`OMEGA_MAX`], [`OMEGA_LAMBDA`] / λ̂_l): the V-cycle
/// is SPD when ω_l λmax(B_l⁺A_l) < 2, and the estimate λ̂_l (a lower bound, from
/// [`LAMBDA_STEPS`] power steps) keeps ω_l λmax near 1.3. The cap holds where λ̂ falls
/// short of λmax: 0.8 keeps ω λmax < 2 up to λmax = 2.5, about what non-overlapping
/// cluster blocks give (1.8–2 at level 0 on the twist systems). On those systems λ̂ is
/// 1.2–1.3 below level 0, where the cap sets ω: 0.8 takes 6 % fewer CG iterations than 2/3,
/// while 1 doubled them at 3,321 nodes, λ̂ there short of a coarse level's λmax
/// (docs/design/multilevel.md, "Fixed costs").
pub const OMEGA_MAX: f64 = 0.8;
/// See [`OMEGA_MAX`].
pub const OMEGA_LAMBDA: f64 = 1.3;

/// The preconditioner of one system: the factors and matrices of every level.
#[derive(Debug, Clone)]
pub struct Multilevel {
    dim: usize,
    hierarchy: std::sync::Arc<Hierarchy>,
    factors: Vec<Factors>,
    /// Each level's matrix values (level 0: Ĥ's blocks in the node frames), on the
    /// level's pattern.
    values: Vec<Vec<f64>>,
    /// Whether `values[0]` is the finest matrix the levels serve: a refresh for the CPU
    /// V-cycle alone ([`Multilevel::refresh_cycle`]) rounds Ĥ straight into the cycle's
    /// f32 copy and leaves it behind.
    finest_current: bool,
    /// The smoother's damping per level for the levels as [`Multilevel::levels`] gives
    /// them (f64 explicit inverses and matrices), estimated when first asked.
    view_omega: std::sync::OnceLock<Vec<f64>>,
    /// Each level's explicit cluster inverses for [`Multilevel::levels`], computed from
    /// the factors when first asked (a CPU solve never asks), with `masked` applied.
    inverses: std::sync::OnceLock<Vec<Inverses>>,
    /// The finest level's components masked since the build, in order: cluster, row in
    /// the cluster block and the diagonal 1/D its explicit inverse takes.
    masked: Vec<(usize, usize, f64)>,
    /// Each level's smoothed prolongation, on `hierarchy.smooth`'s patterns.
    p: Vec<Vec<f64>>,
    /// P's blocks transposed, in the restriction's order.
    pt: Vec<Vec<f64>>,
    /// What the CPU V-cycle reads ([`CycleLevel`]), per level.
    cycle: Vec<CycleLevel>,
    /// Pivots dropped, all levels together.
    dropped: usize,
    /// The constraint set the levels serve (built for, or remasked to).
    built_for: Frames,
    /// A number of this build, unique in the process, and the remaskings since.
    generation: (u64, u32),
}

/// One level as the CPU V-cycle reads it: the matrix, P and Pᵀ rounded to f32 (every sum
/// with them in f64), the cluster blocks in their f32 factor form ([`Factors`]) and the
/// damping estimated against exactly these. A V-cycle moves mostly these bytes; rounding
/// them to f32 changes the preconditioner, not the system CG solves (its own product is
/// f64), and keeps it symmetric (the matrices are rounded symmetric, Pᵀ is P's transpose
/// exactly) and positive definite (GᵀG cannot turn indefinite; ω from the rounded
/// operator).
#[derive(Debug, Clone)]
struct CycleLevel {
    values: Vec<f32>,
    p: Vec<f32>,
    pt: Vec<f32>,
    omega: f64,
}

/// Numbers the builds of [`Multilevel`] (a device holding a copy tells it from another).
static BUILDS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// One level of a [`Multilevel`] as the device V-cycle reads it (src/gpu/pcg/multilevel.rs):
/// the clusters, the matrix, the cluster inverses, the damping and the prolongation to
/// the next level, borrowed.
#[derive(Debug, Clone, Copy)]
pub struct LevelView<'a> {
    /// Items (nodes at level 0, clusters of the level above deeper down).
    pub n: usize,
    /// Cluster of each item, its position in the cluster, the clusters' item ranges and
    /// the items by cluster.
    pub of: &'a [u32],
    pub pos: &'a [u32],
    pub ptr: &'a [usize],
    pub items: &'a [u32],
    /// The level's matrix: block pattern and d×d row-major values (level 0: Ĥ in the
    /// node frames, with the constrained diagonal).
    pub row_ptr: &'a [usize],
    pub col_idx: &'a [usize],
    pub values: &'a [f64],
    /// Cluster c's (m×m, symmetric) pseudo-inverse at `inv[inv_start[c]..inv_start[c + 1]]`.
    pub inv_start: &'a [usize],
    pub inv: &'a [f64],
    /// The smoother's damping (1 at the coarsest level, which is solved).
    pub omega: f64,
    /// The prolongation to the next level (none at the coarsest).
    pub to_next: Option<ProlongationView<'a>>,
}

/// The smoothed prolongation P from one level to the next, borrowed: row i's blocks
/// `p[p_ptr[i]..p_ptr[i + 1]]` in columns `p_col`, and Pᵀ cluster by cluster (`pt_ptr`;
/// per block its row item and the block transposed in `pt_values`).
#[derive(Debug, Clone, Copy)]
pub struct ProlongationView<'a> {
    pub p_ptr: &'a [usize],
    pub p_col: &'a [u32],
    pub p: &'a [f64],
    pub pt_ptr: &'a [usize],
    pub pt: &'a [(u32, u32)],
    pub pt_values: &'a [f64],
}

impl Multilevel {
    /// Factors every level of `hierarchy` (built for `e.h`'s pattern) on the system `e`.
    pub fn new(e: &Eliminated, hierarchy: std::sync::Arc<Hierarchy>) -> Self {
        let d = e.h.dim;
        let nl = hierarchy.levels.len();
        let mut values = Vec::with_capacity(nl);
        values.push(frame_values(e));
        let mut p = Vec::with_capacity(nl - 1);
        for (l, sp) in hierarchy.smooth.iter().enumerate() {
            let lev = &hierarchy.levels[l];
            let a = &values[l];
            // A_{l+1} = P_lᵀ A_l P_l with the smoothed prolongation.
            let pv = if l == 0 {
                smoothed_p(d, lev, sp, a, &|i| node_translation(e, i))
            } else {
                smoothed_p(d, lev, sp, a, &|_| identity(d))
            };
            let next = sp.galerkin(d, &lev.row_ptr, &lev.col_idx, &pv, a);
            p.push(pv);
            values.push(next);
        }
        let mut factors = Vec::with_capacity(nl);
        let mut dropped = 0;
        for (lev, a) in hierarchy.levels.iter().zip(&values) {
            let (fac, drop) = factor_level(lev, d, |_, k, _, out| {
                out.copy_from_slice(&a[k * d * d..(k + 1) * d * d]);
            });
            factors.push(fac);
            dropped += drop;
        }
        let pt: Vec<Vec<f64>> = hierarchy
            .smooth
            .iter()
            .zip(&p)
            .map(|(sp, pv)| sp.transpose(d, pv))
            .collect();
        let cycle = (0..nl)
            .map(|l| {
                let mut v32 = Vec::new();
                hierarchy.slots[l].fill(
                    d,
                    &hierarchy.levels[l],
                    &hierarchy.mirror[l],
                    &values[l],
                    &mut v32,
                );
                CycleLevel {
                    values: v32,
                    p: p.get(l)
                        .map_or(Vec::new(), |v| hierarchy.transfers[l].p.f32_values(d, v)),
                    pt: pt
                        .get(l)
                        .map_or(Vec::new(), |v| hierarchy.transfers[l].pt.f32_values(d, v)),
                    omega: 1.0,
                }
            })
            .collect();
        let mut ml = Multilevel {
            dim: d,
            hierarchy,
            factors,
            values,
            finest_current: true,
            pt,
            p,
            view_omega: std::sync::OnceLock::new(),
            inverses: std::sync::OnceLock::new(),
            masked: Vec::new(),
            cycle,
            dropped,
            built_for: e.frames.clone(),
            generation: (BUILDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed), 0),
        };
        for l in 0..nl.saturating_sub(1) {
            ml.cycle[l].omega = ml.cycle_omega(l);
        }
        ml
    }

    /// How these levels serve the constraint set of `frames`: as they are (the same
    /// constrained components in the same node frames), after [`Multilevel::refresh`]
    /// masks the components `frames` constrains on top (every node keeps its frame, or is
    /// constrained whole), or not at all.
    pub fn fit(&self, frames: &Frames) -> FramesFit {
        frames_fit(&self.built_for, frames)
    }

    /// Keeps the levels for a new system `e` of the same pattern whose constraint set
    /// they fit ([`Multilevel::fit`]): the finest matrix becomes `e`'s Ĥ and its
    /// smoothing weight ω_0 is estimated again against it; components constrained since
    /// the build are masked out of the finest cluster blocks (1/D on their diagonal, as
    /// a build gives) and out of the prolongation's rows, as a build would leave them;
    /// the coarse matrices stay. The V-cycle stays symmetric and positive definite: the
    /// coarse correction only adds a semidefinite term, and the smoother is convergent
    /// while ω_0 λmax(B_0⁺Ĥ) < 2, which the new ω_0 keeps as a fresh build does.
    pub fn refresh(&mut self, e: &Eliminated) {
        self.remask(e);
        frame_values_into(e, &mut self.values[0]);
        self.finest_current = true;
        let (d, hi) = (self.dim, &self.hierarchy);
        hi.slots[0].fill(
            d,
            &hi.levels[0],
            &hi.mirror[0],
            &self.values[0],
            &mut self.cycle[0].values,
        );
        self.refreshed();
    }

    /// [`Multilevel::refresh`] for the CPU V-cycle alone: Ĥ's blocks are rotated into
    /// the node frames and rounded into the cycle's f32 copy as they are read, with no
    /// f64 copy of the finest level (a third of a refresh's time at 44,541 nodes). The
    /// device's view ([`Multilevel::levels`]) needs a [`Multilevel::refresh`] first.
    pub fn refresh_cycle(&mut self, e: &Eliminated) {
        self.remask(e);
        self.finest_current = false;
        let (d, hi) = (self.dim, &self.hierarchy);
        hi.slots[0].fill_with(
            d,
            &hi.levels[0],
            &hi.mirror[0],
            |i, k, j, out| frame_block(e, i, k, j, out),
            &mut self.cycle[0].values,
        );
        self.refreshed();
    }

    /// Before a refresh: the components `e` constrains since the levels' constraint set
    /// masked out of them.
    fn remask(&mut self, e: &Eliminated) {
        if self.fit(e.frames) == FramesFit::Masked {
            self.mask_new(e);
        }
    }

    /// After a refresh: the finest smoothing weights estimated again.
    fn refreshed(&mut self) {
        self.view_omega = std::sync::OnceLock::new();
        if self.hierarchy.levels.len() > 1 {
            self.cycle[0].omega = self.cycle_omega(0);
        }
    }

    /// Masks the components `e` constrains that the levels' constraint set left free.
    fn mask_new(&mut self, e: &Eliminated) {
        let d = self.dim;
        let dd = d * d;
        let lev = &self.hierarchy.levels[0];
        let f = &mut self.factors[0];
        // Where each P block sits in the restriction's transposed copy.
        let mut t_of = Vec::new();
        if let Some(sp) = self.hierarchy.smooth.first() {
            t_of = vec![0usize; sp.pt.len()];
            for (t, &(_, pk)) in sp.pt.iter().enumerate() {
                t_of[pk as usize] = t;
            }
        }
        for i in 0..lev.n {
            let new = e.frames.mask[i] & !self.built_for.mask[i];
            if new == 0 {
                continue;
            }
            let c = lev.of[i] as usize;
            let m = (lev.ptr[c + 1] - lev.ptr[c]) * d;
            for a in (0..d).filter(|a| new & (1 << a) != 0) {
                let row = lev.pos[i] as usize * d + a;
                let dg = e.diag[i * d + a];
                // The factor form G: row and column `row` zeroed, 1/√D on the
                // diagonal, as a build gives a component whose block row is D alone.
                // GᵀG is semidefinite whatever G holds, and the component decouples with
                // 1/D; on the others G keeps a lower triangle with the kept pivots'
                // non-zero diagonals, so GᵀG stays definite on the same components: a
                // valid cluster block (the inverse of the masked block exactly when `row`
                // is the cluster's last component).
                f.mask(c, m, row, if dg > 0.0 { 1.0 / dg.sqrt() } else { 0.0 });
                // The explicit inverse: 1/D on the diagonal, as its own build gives.
                let diag = if dg > 0.0 { 1.0 / dg } else { 0.0 };
                self.masked.push((c, row, diag));
                if let Some(inv) = self.inverses.get_mut() {
                    let b = &mut inv[0];
                    mask_inverse(&mut b.inv[b.start[c]..b.start[c + 1]], m, row, diag);
                }
                if let (Some(sp), Some(tr)) = (
                    self.hierarchy.smooth.first(),
                    self.hierarchy.transfers.first(),
                ) {
                    let (p0, p1) = (sp.p_ptr[i], sp.p_ptr[i + 1]);
                    let cy = &mut self.cycle[0];
                    for (pk, &t) in (p0..p1).zip(&t_of[p0..p1]) {
                        self.p[0][pk * dd + a * d..pk * dd + (a + 1) * d].fill(0.0);
                        let q = tr.p.pos[pk] as usize;
                        // The f32 copies hold each block by columns.
                        (0..d).for_each(|c| cy.p[q * dd + c * d + a] = 0.0);
                        for r in 0..d {
                            self.pt[0][t * dd + r * d + a] = 0.0;
                            cy.pt[tr.pt.pos[t] as usize * dd + a * d + r] = 0.0;
                        }
                    }
                }
            }
        }
        self.built_for = e.frames.clone();
        self.generation.1 += 1;
    }

    /// Which values these are: the same generation means the same values but the finest
    /// level's matrix and smoothing weight ([`Multilevel::refresh`] without new masks).
    pub fn generation(&self) -> (u64, u32) {
        self.generation
    }

    /// The smoothing weight of level l from a power estimate of λmax(B_l⁺A_l) with the
    /// levels as [`Multilevel::levels`] gives them.
    fn omega_of(&self, l: usize) -> f64 {
        omega_for(self.lambda_max(l, LAMBDA_STEPS))
    }

    /// The smoothing weight of level l for the CPU V-cycle: a power estimate of
    /// λmax(B_l⁺A_l) with what the cycle applies ([`CycleLevel`]).
    fn cycle_omega(&self, l: usize) -> f64 {
        let d = self.dim;
        let lev = &self.hierarchy.levels[l];
        let sl = &self.hierarchy.slots[l];
        let a = &self.cycle[l].values;
        // The power steps run in slots, from the item-order start gathered (the padding
        // stays zero: the product leaves it alone, the smoothing writes zeros there).
        let mut x = vec![0.0; sl.len()];
        sl.gather(d, lev, &power_start(lev.n * d), &mut x);
        omega_for(power_estimate_from(x, LAMBDA_STEPS, |x, ax, y| {
            sl.product(d, lev, a, None, x, ax);
            sl.smooth(&self.factors[l], 1.0, false, ax, y);
        }))
    }

    /// The hierarchy these factors were built on.
    pub fn hierarchy(&self) -> &std::sync::Arc<Hierarchy> {
        &self.hierarchy
    }

    /// Dimension d of the nodes.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Every level, finest first, as the device V-cycle reads it: f64 matrices and
    /// explicit cluster inverses, and the damping estimated against those (once, when
    /// first asked after a build or a refresh).
    ///
    /// # Panics
    /// After a [`Multilevel::refresh_cycle`] (the f64 finest level is not kept then).
    pub fn levels(&self) -> Vec<LevelView<'_>> {
        self.assert_finest_current();
        let nl = self.hierarchy.levels.len();
        let omega = self
            .view_omega
            .get_or_init(|| (0..nl).map(|l| self.omega_of(l)).collect());
        let inverses = self.inverses();
        (0..nl)
            .map(|l| {
                let lev = &self.hierarchy.levels[l];
                let f = &inverses[l];
                LevelView {
                    n: lev.n,
                    of: &lev.of,
                    pos: &lev.pos,
                    ptr: &lev.ptr,
                    items: &lev.items,
                    row_ptr: &lev.row_ptr,
                    col_idx: &lev.col_idx,
                    values: &self.values[l],
                    inv_start: &f.start,
                    inv: &f.inv,
                    omega: if l + 1 < nl { omega[l] } else { 1.0 },
                    to_next: self.hierarchy.smooth.get(l).map(|sp| ProlongationView {
                        p_ptr: &sp.p_ptr,
                        p_col: &sp.p_col,
                        p: &self.p[l],
                        pt_ptr: &sp.pt_ptr,
                        pt: &sp.pt,
                        pt_values: &self.pt[l],
                    }),
                }
            })
            .collect()
    }

    /// Every level's explicit cluster inverses (computed on the first call, the masks
    /// since the build replayed on the finest level's in their order).
    fn inverses(&self) -> &[Inverses] {
        self.inverses.get_or_init(|| {
            let mut inv: Vec<Inverses> = (self.hierarchy.levels.iter().zip(&self.factors))
                .map(|(lev, f)| f.inverses(lev, self.dim))
                .collect();
            let lev = &self.hierarchy.levels[0];
            for &(c, row, diag) in &self.masked {
                let m = (lev.ptr[c + 1] - lev.ptr[c]) * self.dim;
                let b = &mut inv[0];
                mask_inverse(&mut b.inv[b.start[c]..b.start[c + 1]], m, row, diag);
            }
            inv
        })
    }

    fn assert_finest_current(&self) {
        assert!(
            self.finest_current,
            "the f64 levels were asked after a refresh for the CPU V-cycle alone"
        );
    }

    /// Pivots dropped (singular or indefinite directions), all levels together.
    pub fn dropped_pivots(&self) -> usize {
        self.dropped
    }

    /// Power-iteration estimate of λmax(B_l⁺A_l) after `steps` products (a lower bound),
    /// with the levels as [`Multilevel::levels`] gives them.
    ///
    /// # Panics
    /// After a [`Multilevel::refresh_cycle`] (the f64 finest level is not kept then).
    pub fn lambda_max(&self, l: usize, steps: usize) -> f64 {
        self.assert_finest_current();
        let d = self.dim;
        let lev = &self.hierarchy.levels[l];
        let inverses = self.inverses();
        let mut tmp = Vec::new();
        power_estimate(lev.n * d, steps, |x, ax, y| {
            block_matvec(d, lev, &self.values[l], x, ax);
            solve_level(lev, d, &inverses[l], ax, y, &mut tmp);
        })
    }

    /// The vectors of one V-cycle, every level's (reused across
    /// [`Multilevel::apply_with`] calls: a CG iteration allocates nothing).
    pub fn workspace(&self) -> VcycleWork {
        VcycleWork {
            levels: self
                .hierarchy
                .levels
                .iter()
                .zip(&self.hierarchy.slots)
                .map(|(_, sl)| {
                    let n = sl.len();
                    LevelWork {
                        b: vec![0.0; n],
                        x: vec![0.0; n],
                        res: vec![0.0; n],
                    }
                })
                .collect(),
        }
    }

    /// z = M⁻¹ r: one symmetric V-cycle from zero (with a workspace of its own).
    pub fn apply(&self, r: &[f64], z: &mut [f64]) {
        let mut work = self.workspace();
        self.apply_with(r, z, &mut work);
    }

    /// z = M⁻¹ r in `work` (from [`Multilevel::workspace`]).
    pub fn apply_with(&self, r: &[f64], z: &mut [f64], work: &mut VcycleWork) {
        self.apply_slots(r, z, work, None);
    }

    /// r into level 0's slots, the V-cycle, and its correction back to item order.
    fn apply_slots(
        &self,
        r: &[f64],
        z: &mut [f64],
        work: &mut VcycleWork,
        seconds: Option<&mut [[f64; 6]]>,
    ) {
        let (d, sl) = (self.dim, &self.hierarchy.slots[0]);
        let Some(w) = work.levels.first_mut() else {
            return;
        };
        let mut b = std::mem::take(&mut w.b);
        let mut x = std::mem::take(&mut w.x);
        sl.gather(d, &self.hierarchy.levels[0], r, &mut b);
        self.vcycle(0, &b, &mut x, &mut work.levels, seconds);
        sl.scatter(d, &x, z);
        work.levels[0].b = b;
        work.levels[0].x = x;
    }

    /// [`Multilevel::apply_with`], timed: wall seconds of each level's passes
    /// ([`CYCLE_PASSES`], in order; the coarsest level's solve as its pre-smoothing),
    /// added to `seconds` (one row per level). For profiling (`examples/vcycle_ab.rs`).
    pub fn apply_timed(
        &self,
        r: &[f64],
        z: &mut [f64],
        work: &mut VcycleWork,
        seconds: &mut [[f64; 6]],
    ) {
        self.apply_slots(r, z, work, Some(seconds));
    }

    /// x = one symmetric V-cycle on level l for the right-hand side b: smooth
    /// (x = ω B⁺b), correct from the level below with the restricted residual, smooth
    /// again; the coarsest level is solved with its single cluster. Everything read is
    /// the level's [`CycleLevel`].
    /// `work[0]` is level l's (its `res`, `tmp`), `work[1]` the next level's (its `b` and
    /// `x` receive the restricted residual and the correction).
    fn vcycle(
        &self,
        l: usize,
        b: &[f64],
        x: &mut [f64],
        work: &mut [LevelWork],
        mut seconds: Option<&mut [[f64; 6]]>,
    ) {
        // The clock is read only when timed.
        let mut t = seconds.as_ref().map(|_| std::time::Instant::now());
        let lap = |seconds: &mut Option<&mut [[f64; 6]]>, t: &mut Option<_>, k: usize| {
            lap_pass(seconds.as_deref_mut(), t, l, k);
        };
        let d = self.dim;
        let hi = &self.hierarchy;
        let sl = &hi.slots[l];
        let cy = &self.cycle[l];
        let f = &self.factors[l];
        let Some((w, below)) = work.split_first_mut() else {
            return;
        };
        let Some(next) = below.first_mut() else {
            sl.smooth(f, 1.0, false, b, x);
            lap(&mut seconds, &mut t, 0);
            return;
        };
        sl.smooth(f, cy.omega, false, b, x);
        lap(&mut seconds, &mut t, 0);
        let res = &mut w.res;
        sl.product(d, &hi.levels[l], &cy.values, Some(b), x, res);
        lap(&mut seconds, &mut t, 1);
        // The next level's vectors leave `below` while it recurses (a move, no copy).
        let mut bc = std::mem::take(&mut next.b);
        let mut xc = std::mem::take(&mut next.x);
        let tr = &hi.transfers[l];
        let coarse = (&hi.levels[l + 1], &hi.slots[l + 1]);
        tr.pt.apply(d, coarse, &cy.pt, res, false, &mut bc);
        lap(&mut seconds, &mut t, 2);
        self.vcycle(l + 1, &bc, &mut xc, below, seconds.as_deref_mut());
        // The levels below timed themselves: their seconds are not this level's.
        if let Some(t) = t.as_mut() {
            *t = std::time::Instant::now();
        }
        tr.p.apply(d, (&hi.levels[l], sl), &cy.p, &xc, true, x);
        lap(&mut seconds, &mut t, 3);
        sl.product(d, &hi.levels[l], &cy.values, Some(b), x, res);
        lap(&mut seconds, &mut t, 4);
        sl.smooth(f, cy.omega, true, res, x);
        lap(&mut seconds, &mut t, 5);
        let next = &mut below[0];
        next.b = bc;
        next.x = xc;
    }
}

/// The passes of one level of a V-cycle as [`Multilevel::apply_timed`] times them.
pub const CYCLE_PASSES: [&str; 6] = [
    "pre-smoothing",
    "residual",
    "restriction",
    "prolongation",
    "residual again",
    "post-smoothing",
];

/// Adds the seconds since `t` to pass `k` of level `l` and restarts `t` (when timed).
fn lap_pass(
    seconds: Option<&mut [[f64; 6]]>,
    t: &mut Option<std::time::Instant>,
    l: usize,
    k: usize,
) {
    if let (Some(s), Some(t)) = (seconds, t.as_mut()) {
        s[l][k] += t.elapsed().as_secs_f64();
        *t = std::time::Instant::now();
    }
}

/// ω = min([`OMEGA_MAX`], [`OMEGA_LAMBDA`] / λ̂), [`OMEGA_MAX`] without a usable λ̂.
fn omega_for(lam: f64) -> f64 {
    if lam > 0.0 && lam.is_finite() {
        OMEGA_MAX.min(OMEGA_LAMBDA / lam)
    } else {
        OMEGA_MAX
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// z += P x in item order, with P's f64 blocks (the V-cycle applies f32 copies).
    fn prolong_f64(d: usize, sp: &SmoothPattern, p: &[f64], x: &[f64], z: &mut [f64]) {
        for i in 0..sp.p_ptr.len() - 1 {
            for pk in sp.p_ptr[i]..sp.p_ptr[i + 1] {
                let c = sp.p_col[pk] as usize;
                for a in 0..d {
                    for k in 0..d {
                        z[i * d + a] += p[pk * d * d + a * d + k] * x[c * d + k];
                    }
                }
            }
        }
    }

    /// out = Pᵀ r in item order, with Pᵀ's f64 blocks in the restriction's order.
    fn restrict_f64(d: usize, sp: &SmoothPattern, pt: &[f64], r: &[f64], out: &mut [f64]) {
        for c in 0..sp.pt_ptr.len() - 1 {
            for t in sp.pt_ptr[c]..sp.pt_ptr[c + 1] {
                let i = sp.pt[t].0 as usize;
                for a in 0..d {
                    for k in 0..d {
                        out[c * d + a] += pt[t * d * d + a * d + k] * r[i * d + k];
                    }
                }
            }
        }
    }
    use crate::cases::generate::{random_system, SystemSpec};
    use crate::core::elimination::ConstrainedDiagonal;

    /// yᵀM⁻¹x = xᵀM⁻¹y and xᵀM⁻¹x > 0 on two fixed vectors. The cycle's f32 matrices are
    /// exactly symmetric and its Pᵀ exactly P's transpose, so as a linear map of the
    /// stored numbers M⁻¹ is symmetric, and only the f64 sums' roundings separate the two
    /// sides: a few ulps of the magnitudes summed.
    fn assert_symmetric_positive(m: &Multilevel, n: usize, what: &str) {
        let x: Vec<f64> = (0..n).map(|k| ((k * 7919) % 23) as f64 - 11.0).collect();
        let y: Vec<f64> = (0..n).map(|k| ((k * 104729) % 17) as f64 - 8.0).collect();
        let (mut mx, mut my) = (vec![0.0; n], vec![0.0; n]);
        m.apply(&x, &mut mx);
        m.apply(&y, &mut my);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(u, v)| u * v).sum::<f64>();
        let (a, b) = (dot(&y, &mx), dot(&x, &my));
        let mag: f64 = y.iter().zip(&mx).map(|(u, v)| (u * v).abs()).sum();
        assert!((a - b).abs() <= 1e-12 * mag, "{what}: {a} vs {b}");
        assert!(
            dot(&x, &mx) > 0.0 && dot(&y, &my) > 0.0,
            "{what}: not positive"
        );
    }

    /// Kept levels remasked for a constraint set with a free node made sticky and a
    /// plane-slip node given a second constrained direction stay symmetric and positive
    /// definite, and the masked components decouple: M⁻¹ e_a is a multiple of e_a there.
    #[test]
    fn remasked_levels_stay_symmetric_and_positive_definite() {
        for (dim, nodes, seed) in [(3, 900, 5u64), (2, 1200, 6)] {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            let f = &s.frames;
            let e = Eliminated::new(&s.h, &s.g, f, ConstrainedDiagonal::Identity);
            let mut m = Multilevel::new(&e, std::sync::Arc::new(Hierarchy::new(&s.h)));
            let full = (1u8 << dim) - 1;
            let mut more = f.clone();
            let free = (0..f.n_nodes)
                .find(|&i| f.mask[i] == 0 && f.rotation(i).is_none())
                .expect("a free node");
            more.mask[free] = full;
            let slip = (0..f.n_nodes).find(|&i| f.rotation(i).is_some() && f.mask[i] == 1);
            if let (Some(i), 3) = (slip, dim) {
                more.mask[i] |= 0b010;
            }
            let e2 = Eliminated::new(&s.h, &s.g, &more, ConstrainedDiagonal::Identity);
            assert_eq!(m.fit(&more), FramesFit::Masked);
            m.refresh(&e2);
            let n = e2.ndof();
            assert_symmetric_positive(&m, n, &format!("{dim}D remasked"));
            for a in 0..dim {
                let k = free * dim + a;
                let mut ek = vec![0.0; n];
                ek[k] = 1.0;
                let mut z = vec![0.0; n];
                m.apply(&ek, &mut z);
                // Smoothing gives ω/D, the residual (1 − ω) e_a restricts to nothing (P's
                // row zero), smoothing again adds ω(1 − ω)/D.
                let om = m.cycle[0].omega;
                let want = (2.0 * om - om * om) / e2.diag[k];
                // 1/√D rounded to f32 and squared: a relative 2·2⁻²⁴ or so.
                assert!(
                    (z[k] - want).abs() <= 1e-6 * want,
                    "{dim}D: {} vs {want}",
                    z[k]
                );
                let off = z
                    .iter()
                    .enumerate()
                    .filter(|&(t, _)| t != k)
                    .fold(0.0f64, |w, (_, v)| w.max(v.abs()));
                assert_eq!(off, 0.0, "{dim}D: the masked component couples");
            }
        }
    }

    /// The explicit inverses a device reads are the same bits whether first asked for
    /// before a remasking (the mask applied to them) or after it (the masks replayed on
    /// inverses formed then), and each is (L Lᵀ)⁺ of its cluster's masked block: the
    /// masked component's row holds only 1/D.
    #[test]
    fn explicit_inverses_asked_before_or_after_a_remasking_agree() {
        let s = random_system(&SystemSpec::with_nodes(3, 900, 7));
        let f = &s.frames;
        let e = Eliminated::new(&s.h, &s.g, f, ConstrainedDiagonal::Identity);
        let hier = std::sync::Arc::new(Hierarchy::new(&s.h));
        let mut early = Multilevel::new(&e, hier.clone());
        let mut late = Multilevel::new(&e, hier);
        let before: Vec<Vec<f64>> = early.levels().iter().map(|v| v.inv.to_vec()).collect();
        let free = (0..f.n_nodes)
            .find(|&i| f.mask[i] == 0 && f.rotation(i).is_none())
            .expect("a free node");
        let mut more = f.clone();
        more.mask[free] = 0b111;
        let e2 = Eliminated::new(&s.h, &s.g, &more, ConstrainedDiagonal::Identity);
        early.refresh(&e2);
        late.refresh(&e2);
        let (a, b) = (early.levels(), late.levels());
        for (l, (va, vb)) in a.iter().zip(&b).enumerate() {
            let same = va
                .inv
                .iter()
                .zip(vb.inv)
                .all(|(x, y)| x.to_bits() == y.to_bits());
            assert!(same && va.inv.len() == vb.inv.len(), "level {l}");
        }
        assert_ne!(before[0], a[0].inv, "the finest inverses are masked");
        let lev = &early.hierarchy.levels[0];
        let c = lev.of[free] as usize;
        let m = (lev.ptr[c + 1] - lev.ptr[c]) * 3;
        let blk = &a[0].inv[a[0].inv_start[c]..a[0].inv_start[c + 1]];
        for k in 0..3 {
            let row = lev.pos[free] as usize * 3 + k;
            for j in 0..m {
                let want = if j == row {
                    1.0 / e2.diag[free * 3 + k]
                } else {
                    0.0
                };
                assert_eq!(blk[row * m + j], want, "row {row}, column {j}");
            }
        }
    }

    #[test]
    fn the_preconditioner_is_symmetric_and_positive_definite() {
        for (dim, nodes, seed) in [(3, 900, 3u64), (2, 1500, 4)] {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
            let hier = std::sync::Arc::new(Hierarchy::new(&s.h));
            assert!(
                hier.cluster_counts().len() >= 2,
                "{:?}",
                hier.cluster_counts()
            );
            assert_eq!(*hier.cluster_counts().last().unwrap(), 1);
            let m = Multilevel::new(&e, hier);
            assert_symmetric_positive(&m, e.ndof(), &format!("{dim}D"));
        }
    }

    /// Every coarse level's matrix is P_lᵀ A_l P_l: each column, A_{l+1} e_k, equals
    /// P_lᵀ A_l (P_l e_k) formed with the prolongation, the level's product (level 0: the
    /// matrix-free Ĥ) and the restriction, in 2D and 3D.
    #[test]
    fn every_coarse_level_is_the_galerkin_product_of_the_smoothed_prolongation() {
        for (dim, nodes, seed) in [(2, 300, 7u64), (3, 600, 8)] {
            let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
            let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Hessian);
            let hier = std::sync::Arc::new(Hierarchy::new(&s.h));
            let m = Multilevel::new(&e, hier.clone());
            assert!(
                hier.smooth.len() >= 2,
                "{dim}D: {:?}",
                hier.cluster_counts()
            );
            for (l, sp) in hier.smooth.iter().enumerate() {
                let (n, nc) = (hier.levels[l].n * dim, hier.levels[l].clusters() * dim);
                let next = &hier.levels[l + 1];
                let a = &m.values[l + 1];
                let mut worst = 0.0f64;
                let mut scale = 0.0f64;
                let mut work = vec![0.0; 2 * n];
                for k in 0..nc {
                    let mut ek = vec![0.0; nc];
                    ek[k] = 1.0;
                    let mut pk = vec![0.0; n];
                    prolong_f64(dim, sp, &m.p[l], &ek, &mut pk);
                    let mut hp = vec![0.0; n];
                    if l == 0 {
                        e.apply(&pk, &mut hp, &mut work);
                    } else {
                        block_matvec(dim, &hier.levels[l], &m.values[l], &pk, &mut hp);
                    }
                    let mut col = vec![0.0; nc];
                    restrict_f64(dim, sp, &m.pt[l], &hp, &mut col);
                    // Column k from the stored blocks (row c, block column k / dim).
                    let (kc, kb) = (k / dim, k % dim);
                    for c in 0..next.n {
                        for t in next.row_ptr[c]..next.row_ptr[c + 1] {
                            if next.col_idx[t] != kc {
                                continue;
                            }
                            for r in 0..dim {
                                let stored = a[t * dim * dim + r * dim + kb];
                                worst = worst.max((stored - col[c * dim + r]).abs());
                                scale = scale.max(stored.abs());
                            }
                        }
                    }
                }
                assert!(scale > 0.0, "{dim}D: A_{} is zero", l + 1);
                // Two orders of summing the same products: a few ulps of the largest entry.
                assert!(
                    worst <= 1e-12 * scale,
                    "{dim}D, A_{}: {worst:e} of {scale:e}",
                    l + 1
                );
            }
        }
    }

    #[test]
    fn a_singular_block_drops_its_null_direction() {
        // [[4, 2], [2, 1]] has the null vector (1, −2): one pivot dropped, and the
        // pseudo-inverse solves a right-hand side in its range.
        let mut a = vec![4.0, 2.0, 2.0, 1.0];
        assert_eq!(cholesky_dropping(2, &mut a), 1);
        let inv = inverse_from_factor(2, &a);
        let x = [inv[0] * 2.0 + inv[1], inv[2] * 2.0 + inv[3]];
        assert!((4.0 * x[0] + 2.0 * x[1] - 2.0).abs() < 1e-15);
        assert!((2.0 * x[0] + x[1] - 1.0).abs() < 1e-15);
        // An SPD block keeps every pivot and inverts exactly enough.
        let mut b = vec![4.0, 1.0, 1.0, 3.0];
        assert_eq!(cholesky_dropping(2, &mut b), 0);
        let inv = inverse_from_factor(2, &b);
        let id = [
            4.0 * inv[0] + inv[2],
            4.0 * inv[1] + inv[3],
            inv[0] + 3.0 * inv[2],
            inv[1] + 3.0 * inv[3],
        ];
        for (v, e) in id.iter().zip([1.0, 0.0, 0.0, 1.0]) {
            assert!((v - e).abs() < 1e-15, "{id:?}");
        }
    }
}
