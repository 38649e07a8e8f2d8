//! The `stickslip` binary: everything lives in [`stickslip::app::cli`].

// mimalloc instead of the system allocator: it asks for transparent huge pages on large
// allocations, and with fewer TLB misses the CG's product over H (tens of MB read in node
// order) runs markedly faster: BENCHMARKS.md, "The allocator". Library users keep their own.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// mimalloc's `mi_option_purge_delay`, which the bindings leave out: mimalloc.h's option
/// enum has it between `mi_option_eager_commit_delay` (14) and `mi_option_use_numa_nodes`.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;
const _: () = assert!(libmimalloc_sys::mi_option_use_numa_nodes == MI_OPTION_PURGE_DELAY + 1);
/// Its default in the bundled mimalloc (its options.c), milliseconds.
const PURGE_DELAY_DEFAULT: std::ffi::c_long = 1000;

/// Freed memory stays with the process instead of going back to the OS after the purge
/// delay: a simulation frees and rebuilds the same large buffers (the multilevel levels)
/// every few seconds, and memory handed back must be faulted in again (BENCHMARKS.md, "The
/// allocator"). Left alone if option 15 does not read the default it was written for (a
/// `MIMALLOC_PURGE_DELAY` other than the default set in the environment stays in force).
fn keep_freed_memory() {
    // SAFETY: mimalloc's option accessors take any option index and have no other
    // preconditions.
    unsafe {
        if libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) == PURGE_DELAY_DEFAULT {
            libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1);
        }
    }
}

fn main() -> std::process::ExitCode {
    keep_freed_memory();
    stickslip::app::cli::main()
}

#[cfg(test)]
mod tests {
    /// The purge delay is switched off: option 15 read the default this was written for.
    /// Fails when a mimalloc upgrade moves the option or its default.
    #[test]
    fn freed_memory_is_kept() {
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
            eprintln!("SKIP freed_memory_is_kept: MIMALLOC_PURGE_DELAY is set");
            return;
        }
        super::keep_freed_memory();
        // SAFETY: as in keep_freed_memory.
        let delay = unsafe { libmimalloc_sys::mi_option_get(super::MI_OPTION_PURGE_DELAY) };
        assert_eq!(delay, -1);
    }
}
