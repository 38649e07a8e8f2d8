//! The `stickslip` binary: everything lives in [`stickslip::app::cli`].

fn main() -> std::process::ExitCode {
    stickslip::app::cli::main()
}
