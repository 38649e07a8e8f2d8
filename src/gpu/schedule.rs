//! The chunk schedule of the device PCG: how many iterations one submit records before
//! the next status read, and what that read says. A read costs a round trip; an
//! iteration recorded past convergence costs an iteration.

use super::kernels::slots;
use crate::solve::cg::CgError;

/// One status read after a chunk: the CG's scalars and flags at the slots of
/// [`slots`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChunkStatus {
    /// r·r of the last reduction.
    pub rr: f64,
    /// ρ = r·z of the last iteration that went on (a converged one keeps the ρ its α
    /// used: what a resumed segment's β divides by).
    pub rho: f64,
    /// p·q of the last α (the curvature when it was not positive).
    pub pq: f64,
    /// ‖b̂‖², summed at the start of a run.
    pub bb: f64,
    /// Iterations of this run.
    pub iterations: usize,
    /// The relative tolerance the solve runs to (set by the host, or by the device from
    /// the tolerance rule at the first start).
    pub eta: f64,
    pub converged: bool,
    /// The chunk's verification computed the true residual of the converged recurrence
    /// (then `rr` is the true r·r) ...
    pub verified: bool,
    /// ... and it met the tolerance on the device: Δx was recovered in the same submit.
    pub true_ok: bool,
    /// E = ZᵀĤZ of the translations (D², row-major, unsymmetrized: the first D² of 9)
    /// and its rows' absolute sums (from entry 9), as `prepare` left them.
    pub coarse: [f64; 12],
    /// Non-positive curvature met.
    pub halt: bool,
    /// A non-finite ρ or r·r.
    pub breakdown: bool,
    /// `prepare` could not factor the aggregates' coarse matrix on the device (a pivot not
    /// positive and finite): E⁺ must come from the host.
    pub coarse_failed: bool,
}

impl ChunkStatus {
    /// From `scal` (as f64, its first [`slots::STATUS_SCAL`] values at least) and
    /// `state` ([`slots::N_STATE`] words).
    pub fn read(scal: &[f64], state: &[u32]) -> Self {
        let flag = |k: u32| state[k as usize] != 0;
        ChunkStatus {
            rr: scal[slots::SCAL_RR as usize],
            rho: scal[slots::SCAL_RHO as usize],
            pq: scal[slots::SCAL_PQ as usize],
            bb: scal[slots::SCAL_BB as usize],
            iterations: state[slots::STATE_ITERS as usize] as usize,
            eta: scal[slots::SCAL_ETA as usize],
            converged: flag(slots::STATE_CONVERGED),
            verified: flag(slots::STATE_VERIFIED),
            true_ok: flag(slots::STATE_TRUE_OK),
            coarse: std::array::from_fn(|k| scal[slots::SCAL_E as usize + k]),
            halt: flag(slots::STATE_HALT),
            breakdown: flag(slots::STATE_BREAKDOWN),
            coarse_failed: flag(slots::STATE_COARSE_FAILED),
        }
    }

    /// The errors a status can carry: a non-finite value, or non-positive curvature (met
    /// in the α of the iteration after those counted). `done_before`: iterations of the
    /// same solve's earlier runs.
    pub fn error(&self, done_before: usize) -> Result<(), CgError> {
        if self.breakdown {
            return Err(CgError::Breakdown {
                iteration: done_before + self.iterations,
            });
        }
        if self.halt {
            return Err(CgError::NonPositiveCurvature {
                iteration: done_before + self.iterations + 1,
                curvature: self.pq,
            });
        }
        Ok(())
    }
}

/// `state`'s words from their little-endian bytes.
pub fn state_words(bytes: &[u8]) -> Vec<u32> {
    bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Iterations of the next chunk from the status history `hist` ((iterations, ln r·r) at
/// each status read of the run): the iterations the fall of ln r·r predicts to reach
/// `thresh` (on r·r), within [floor, min(2·prev, cap)]; doubling without a fall.
pub fn next_chunk(
    hist: &[(usize, f64)],
    thresh: f64,
    prev: usize,
    floor: usize,
    cap: usize,
) -> usize {
    let grow = (2 * prev).min(cap).max(floor);
    // Without a fall over the later half (the CG residual is not monotone), the fall since
    // the first status read: a better guess than doubling, which overshoots a bump.
    let whole = || {
        let (&(i0, l0), &(i1, l1)) = (hist.first()?, hist.last()?);
        let rate = (l0 - l1) / (i1.checked_sub(i0)?) as f64;
        (rate > 0.0 && rate.is_finite()).then_some(rate)
    };
    let rate = late_rate(hist).or_else(whole);
    let (Some(rate), Some(&(_, lr))) = (rate, hist.last()) else {
        return grow;
    };
    // Written to reject NaN too.
    if thresh.is_nan() || thresh <= 0.0 {
        return grow;
    }
    let need = (lr - thresh.ln()) / rate;
    if !need.is_finite() {
        return grow;
    }
    // CG converges superlinearly, so the rate so far overestimates what is left: a long
    // prediction is cut to 3/4 and the next status read corrects it (dt-1e2 at 107k
    // DOFs: 42 iterations recorded past convergence of 462 before this cut).
    let need = need.max(0.0).ceil();
    let take = if need > SHORT_PREDICTION {
        (0.75 * need).ceil()
    } else {
        need
    };
    (take as usize).clamp(floor, grow)
}

/// The dispatches a PCG's first solve records before its first status read: 32
/// iterations of Jacobi with the aggregates (five dispatches each). An iteration recorded
/// past convergence costs its dispatches, gated or not, so an iteration of more
/// dispatches (the multilevel V-cycle's 25) is worth a shorter first chunk: the status
/// read after it predicts the rest from the fall of the residual ([`next_chunk`]).
pub const FIRST_SOLVE_DISPATCHES: usize = 160;

/// Iterations of a solve's first chunk, for an iteration of `dispatches` dispatches: as
/// long as the longest recent solve took (`recent_longest`), a quarter more (Newton's
/// systems change little from one to the next, the forcing sequence's tolerances do), or
/// without one, [`FIRST_SOLVE_DISPATCHES`] worth of iterations, at most `first_solve`;
/// within [floor, cap], and at most `max` (the solve's iteration limit).
pub fn first_chunk(
    recent_longest: Option<usize>,
    dispatches: usize,
    (floor, first_solve, cap): (usize, usize, usize),
    max: usize,
) -> usize {
    let k = match recent_longest {
        Some(n) => n + n / 4 + 2,
        None => (FIRST_SOLVE_DISPATCHES / dispatches.max(1)).min(first_solve),
    };
    k.clamp(floor, cap.max(floor)).min(max)
}

/// The fall of ln r·r per iteration over the later half of a status history: early CG
/// iterations are not representative, and a single chunk's rate is noisy (the CG residual
/// is not monotone). None without two points or without a fall.
pub fn late_rate(hist: &[(usize, f64)]) -> Option<f64> {
    let &(it, lr) = hist.last()?;
    let &(it0, lr0) = hist.iter().rev().find(|&&(i, _)| 2 * i <= it)?;
    let rate = (lr0 - lr) / (it - it0) as f64;
    // Written to reject NaN too.
    (rate > 0.0 && rate.is_finite()).then_some(rate)
}

/// Predictions of at most this many iterations are taken whole (see `next_chunk`).
const SHORT_PREDICTION: f64 = 8.0;

#[cfg(test)]
mod tests {
    use super::{first_chunk, next_chunk, slots, ChunkStatus, FIRST_SOLVE_DISPATCHES};
    use crate::solve::cg::CgError;

    /// The slots are read where the table puts them, and a flag becomes its error with the
    /// iteration counted over the solve's runs.
    #[test]
    fn a_status_reads_the_slots_and_maps_its_flags_to_errors() {
        let mut scal = vec![0.0; slots::STATUS_SCAL as usize];
        scal[slots::SCAL_RR as usize] = 2.0;
        scal[slots::SCAL_PQ as usize] = -3.0;
        scal[slots::SCAL_BB as usize] = 5.0;
        let mut state = vec![0u32; slots::N_STATE as usize];
        state[slots::STATE_ITERS as usize] = 7;
        let st = ChunkStatus::read(&scal, &state);
        assert_eq!((st.rr, st.pq, st.bb, st.iterations), (2.0, -3.0, 5.0, 7));
        assert!(!st.converged && !st.halt && !st.breakdown && !st.coarse_failed);
        assert!(st.error(10).is_ok());
        state[slots::STATE_COARSE_FAILED as usize] = 1;
        let st = ChunkStatus::read(&scal, &state);
        assert!(st.coarse_failed && st.error(10).is_ok());
        state[slots::STATE_HALT as usize] = 1;
        match ChunkStatus::read(&scal, &state).error(10) {
            Err(CgError::NonPositiveCurvature {
                iteration,
                curvature,
            }) => assert_eq!((iteration, curvature), (18, -3.0)),
            other => panic!("{other:?}"),
        }
        state[slots::STATE_BREAKDOWN as usize] = 1;
        match ChunkStatus::read(&scal, &state).error(10) {
            Err(CgError::Breakdown { iteration }) => assert_eq!(iteration, 17),
            other => panic!("{other:?}"),
        }
        state[slots::STATE_CONVERGED as usize] = 1;
        assert!(ChunkStatus::read(&scal, &state).converged);
    }

    #[test]
    fn chunks_follow_the_predicted_remaining_iterations() {
        // No history, or too little of it: double within [floor, cap].
        assert_eq!(next_chunk(&[], 1e-12, 8, 8, 256), 16);
        assert_eq!(next_chunk(&[(8, 0.0)], 1e-12, 8, 8, 256), 16);
        // ln r·r falls by 0.1 per iteration; 10 more iterations reach the threshold.
        let t = (-6.0f64).exp();
        let h = [(8, -0.8), (24, -2.4), (50, -5.0)];
        // A short prediction is taken whole, a long one cut to 3/4.
        assert_eq!(next_chunk(&h, t, 26, 2, 256), 8);
        assert_eq!(next_chunk(&h, (-5.8f64).exp(), 26, 2, 256), 8);
        assert_eq!(next_chunk(&h, (-5.3f64).exp(), 26, 2, 256), 3);
        // Never below the floor, never above double the previous chunk.
        assert_eq!(next_chunk(&h, (-5.1f64).exp(), 26, 8, 256), 8);
        assert_eq!(next_chunk(&h, (-50.0f64).exp(), 26, 8, 256), 52);
        assert_eq!(next_chunk(&h, (-9.0f64).exp(), 26, 2, 256), 30);
        // No progress: plain doubling.
        assert_eq!(next_chunk(&[(8, -1.0), (24, -1.0)], t, 16, 8, 256), 32);
        // A bump over the later half: the fall since the first read, 0.05 per iteration.
        let bump = [(0, 0.0), (10, -2.0), (20, -1.5), (30, -1.5)];
        assert_eq!(next_chunk(&bump, (-2.0f64).exp(), 10, 2, 256), 8);
    }
    /// A first solve's first chunk holds about as many dispatches whatever an iteration
    /// dispatches (within the bounds); a later one follows the recent solves alone.
    #[test]
    fn first_chunks_are_sized_by_the_dispatches_of_an_iteration() {
        let b = (8, 32, 256);
        // Jacobi (three dispatches) and Jacobi with the aggregates (five): the first-solve
        // length; the multilevel V-cycle (25): the floor.
        assert_eq!(first_chunk(None, 3, b, 1000), 32);
        assert_eq!(first_chunk(None, 5, b, 1000), 32);
        assert_eq!(first_chunk(None, 25, b, 1000), 8);
        // Between the bounds the dispatches recorded stay within an iteration's of the
        // budget.
        for d in [6, 8, 10, 12, 16] {
            let k = first_chunk(None, d, b, 1000);
            assert!(k < 32 && k > 8, "{d} dispatches: {k}");
            assert!(k * d <= FIRST_SOLVE_DISPATCHES && (k + 1) * d > FIRST_SOLVE_DISPATCHES);
        }
        // Learned from recent solves: a quarter more plus two, whatever the dispatches.
        assert_eq!(first_chunk(Some(15), 25, b, 1000), 20);
        assert_eq!(first_chunk(Some(15), 5, b, 1000), 20);
        assert_eq!(first_chunk(Some(1), 25, b, 1000), 8);
        assert_eq!(first_chunk(Some(400), 5, b, 1000), 256);
        // Never past the solve's limit, and no division by zero dispatches.
        assert_eq!(first_chunk(None, 5, b, 5), 5);
        assert_eq!(first_chunk(None, 0, b, 1000), 32);
    }
}
