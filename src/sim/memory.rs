//! Scene-sized host allocations that may fail: a scene too large for the address space
//! (`ulimit -v`, a 32-bit limit, overcommit refused) is refused with the bytes it needs
//! ([`AllocError`]) instead of aborting the process.
//!
//! Two tools: [`try_vec`] allocates one buffer fallibly, and [`probe`] asks the system
//! for an estimate of what a scene will allocate ([`scene_bytes`]) before any of it is
//! built, and gives it back at once, so that a scene that cannot fit fails before its
//! first mesh array rather than inside an infallible allocation later.

/// An allocation the system refused: what it was for and the bytes it needed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("needs {} for {what}{}; the allocation failed", show_bytes(*.bytes), nodes_text(.nodes))]
pub struct AllocError {
    /// What the memory was for, e.g. "the Hessian".
    pub what: String,
    pub bytes: u64,
    /// The scene's node count, when known.
    pub nodes: Option<usize>,
}

impl AllocError {
    /// The same error, saying the scene's node count.
    pub fn with_nodes(mut self, nodes: usize) -> Self {
        self.nodes = Some(nodes);
        self
    }
}

/// A scene that does not fit: its name and the allocation the system refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("scene \"{scene}\" {error}")]
pub struct SceneTooLarge {
    pub scene: String,
    pub error: AllocError,
}

fn nodes_text(nodes: &Option<usize>) -> String {
    nodes.map_or(String::new(), |n| {
        format!(" ({} nodes)", thousands(n as u64))
    })
}

/// `1,934,000,000` style digits.
pub fn thousands(v: u64) -> String {
    let s = v.to_string();
    let mut out = String::new();
    for (k, c) in s.chars().enumerate() {
        if k > 0 && (s.len() - k) % 3 == 0 {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// Bytes for a message: `1.9 GB (1,934,000,000 bytes)` (decimal units).
pub fn show_bytes(b: u64) -> String {
    let (v, unit) = match b {
        0..=999_999 => return format!("{} bytes", thousands(b)),
        1_000_000..=999_999_999 => (b as f64 / 1e6, "MB"),
        1_000_000_000..=999_999_999_999 => (b as f64 / 1e9, "GB"),
        _ => (b as f64 / 1e12, "TB"),
    };
    format!("{v:.1} {unit} ({} bytes)", thousands(b))
}

/// A vector of `n` copies of `v`, or the error naming `what` when the system refuses the
/// memory (or `n` elements overflow the address space).
pub fn try_vec<T: Clone>(n: usize, v: T, what: &str) -> Result<Vec<T>, AllocError> {
    let bytes = (n as u64).saturating_mul(std::mem::size_of::<T>() as u64);
    let mut out = Vec::new();
    out.try_reserve_exact(n).map_err(|_| AllocError {
        what: what.to_string(),
        bytes,
        nodes: None,
    })?;
    out.resize(n, v);
    Ok(out)
}

/// Ends the process as an infallible allocation that the system refuses does
/// ([`std::alloc::handle_alloc_error`]), for the callers that promise their sizes fit.
pub fn abort_on(e: &AllocError) -> ! {
    let bytes = usize::try_from(e.bytes)
        .unwrap_or(usize::MAX)
        .min(isize::MAX as usize - 7);
    let layout =
        std::alloc::Layout::from_size_align(bytes, 8).unwrap_or(std::alloc::Layout::new::<u64>());
    std::alloc::handle_alloc_error(layout)
}

/// Asks the system for `bytes` of address space and gives them back: Err when it refuses
/// (the pages are never touched, so a probe costs no memory).
pub fn probe(bytes: u64, what: &str) -> Result<(), AllocError> {
    let err = || AllocError {
        what: what.to_string(),
        bytes,
        nodes: None,
    };
    let n = usize::try_from(bytes).map_err(|_| err())?;
    let mut v: Vec<u8> = Vec::new();
    v.try_reserve_exact(n).map_err(|_| err())?;
    Ok(())
}

/// What [`scene_bytes`] is for, in messages.
pub const SCENE_WHAT: &str = "its meshes, model and Newton systems";

/// Bytes a run of a scene with `nodes` nodes in `dim` dimensions allocates on the host at
/// its peak, beyond the process itself: the meshes, the model (element sets, the gather
/// tables of the assembly, masses, the Hessian's block pattern), the check of the
/// initial stiffness, the stepper's state, and the CPU Newton loop's Hessian, gradient,
/// eliminated system and CG vectors. Measured on the generated meshes (the growth of the
/// peak virtual size of `run --steps 1 --threads 1 --solver cg` with the node count: about
/// 2.1 kB per node on `compress` in 2D and 10.4 kB on `twist` in 3D), rounded up. A
/// Cholesky factor's fill is not included: it is the linear solver's, and its 3D scenes
/// are capped at 400,000 nodes.
pub fn scene_bytes(dim: usize, nodes: usize) -> u64 {
    let per_node: u64 = if dim == 2 { 3_000 } else { 11_000 };
    (nodes as u64).saturating_mul(per_node)
}

/// Why a scene could not be loaded: bad input, or a scene too large for the memory the
/// process may allocate.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LoadError {
    #[error("{0}")]
    Input(#[from] crate::error::InputError),
    #[error("{0}")]
    Memory(#[from] SceneTooLarge),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refused_allocations_are_errors_with_their_bytes() {
        // More than the address space: refused, never attempted.
        let e = try_vec(usize::MAX / 4, 0.0f64, "the Hessian").expect_err("too large");
        assert_eq!(e.bytes, u64::MAX);
        let e = probe(u64::MAX / 2, SCENE_WHAT).expect_err("too large");
        let line = SceneTooLarge {
            scene: "twist".into(),
            error: e.with_nodes(447_000),
        }
        .to_string();
        assert!(
            line.starts_with(
                "scene \"twist\" needs 9223372.0 TB (9,223,372,036,854,775,807 bytes) "
            ),
            "{line}"
        );
        assert!(
            line.ends_with(
                "for its meshes, model and Newton systems (447,000 nodes); the allocation failed"
            ),
            "{line}"
        );
        // What fits is allocated.
        assert_eq!(try_vec(3, 1u8, "x").expect("small"), vec![1, 1, 1]);
        probe(1 << 20, "x").expect("a megabyte");
    }

    #[test]
    fn byte_counts_read_in_decimal_units() {
        assert_eq!(show_bytes(999), "999 bytes");
        assert_eq!(show_bytes(1_934_000_000), "1.9 GB (1,934,000,000 bytes)");
        assert_eq!(thousands(447_000), "447,000");
    }
}
