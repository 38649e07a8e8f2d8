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
/// allocator"). Left alone if option 15 is not the purge delay this was written for.
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
