//! The `stickslip` binary: everything lives in [`stickslip::app::cli`].

// mimalloc instead of the system allocator: it asks for transparent huge pages on large
// allocations, and with fewer TLB misses the CG's product over H (tens of MB read in node
// order) runs markedly faster: BENCHMARKS.md, "The allocator". Library users keep their own.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    stickslip::app::cli::main()
}
