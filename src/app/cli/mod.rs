//! The command line (docs/cli.md): `solve`, `generate`, `info`, `run`, `bench`,
//! `export` and `recover`. `main.rs` only calls [`main`].
//!
//! Exit codes: 0 success; 1 a solve failed (H not positive definite on the free
//! subspace, CG did not converge, GPU failure) or a subcommand is not available; 2 bad
//! input or usage. Every error is exactly one line on stderr.

pub mod args;
pub mod bench;
pub mod error;
pub mod export;
pub mod generate;
pub mod info;
pub mod run;
pub mod solve;

pub use args::{
    BenchArgs, Cli, Command, ExportArgs, GenerateArgs, MixArg, RecoverArgs, RunArgs, SolveArgs,
    StencilArg, SystemArgs, MAX_GENERATED_NODES, MAX_HARD_SCALE, MAX_THREADS,
};
pub use error::CliError;
pub use generate::{generate, GENERATE_OUTPUTS};
pub use info::check_adapter_name;
pub use solve::solve;

use clap::Parser;
use std::process::ExitCode;

/// Entry point of the binary.
pub fn main() -> ExitCode {
    // A panic is a bug, but the one-line contract holds for it too: no backtrace hint.
    std::panic::set_hook(Box::new(|info| {
        // A panic inside a third-party parser that the reader turns into an input error.
        if crate::io::panic_is_contained() {
            return;
        }
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        eprintln!("error: internal error{at}: {}", msg.replace('\n', " "));
    }));
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            use clap::error::ErrorKind;
            match e.kind() {
                // Help and version are not errors: clap prints them as usual.
                ErrorKind::DisplayHelp
                | ErrorKind::DisplayVersion
                | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
                _ => {
                    // One line, like every other error: clap's first paragraph (which
                    // lists the missing arguments, if any), without tips and usage.
                    let text = e.to_string();
                    let first: Vec<&str> = text
                        .lines()
                        .take_while(|l| !l.trim().is_empty())
                        .map(str::trim)
                        .collect();
                    let first = first.join(" ");
                    let first = first.strip_prefix("error: ").unwrap_or(&first);
                    let first = if first.is_empty() {
                        "invalid usage"
                    } else {
                        first
                    };
                    eprintln!("error: command line: {first} (see --help)");
                    return ExitCode::from(2);
                }
            }
        }
    };
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let line = e.to_string().replace('\n', " ");
            eprintln!("error: {}", crate::io::cut_tokens(&line));
            ExitCode::from(e.exit_code())
        }
    }
}

/// Runs a parsed command line (on a pool of `--threads` workers where given).
pub fn run(cli: &Cli) -> Result<(), CliError> {
    let threads = match &cli.command {
        Command::Solve(a) => a.threads,
        Command::Run(a) => a.threads,
        Command::Bench(a) => a.threads,
        _ => None,
    };
    match threads {
        None => dispatch(cli),
        Some(t) => {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .map_err(|e| CliError::Failed(format!("--threads {t}: {e}")))?;
            // faer (the Cholesky) takes its thread count from its own global setting.
            faer::set_global_parallelism(faer::Par::rayon(t));
            pool.install(|| dispatch(cli))
        }
    }
}

fn dispatch(cli: &Cli) -> Result<(), CliError> {
    match &cli.command {
        Command::Solve(a) => {
            let r = solve(a)?;
            if !cli.quiet {
                eprintln!("{}", r.summary());
                if let Some(w) = r.condition_warning(a.tol) {
                    eprintln!("{w}");
                }
            }
            Ok(())
        }
        Command::Generate(a) => generate(a, cli.quiet),
        Command::Info => info::info(),
        Command::Run(a) => run::run_scene(a, cli.quiet),
        Command::Bench(a) => bench::bench(a, cli.quiet),
        Command::Export(a) => export::export(a, cli.quiet),
        Command::Recover(a) => export::recover(a, cli.quiet),
    }
}
