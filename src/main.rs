//! The `stickslip` binary: everything lives in [`stickslip::cli`].

fn main() -> std::process::ExitCode {
    stickslip::cli::main()
}
