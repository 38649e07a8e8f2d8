//! `stickslip run`: a simulation, stopped cleanly by SIGINT or SIGTERM.

use crate::app::cli::args::RunArgs;
use crate::app::cli::error::CliError;

/// `stickslip run`: see [`crate::sim::driver`].
pub fn run_scene(a: &RunArgs, quiet: bool) -> Result<(), CliError> {
    let opts = crate::sim::driver::RunOptions {
        scene: a.scene.clone(),
        out: a.out.clone(),
        solver: a.solver,
        size: a.size,
        steps: a.steps,
        quiet,
        overwrite: a.overwrite,
        ordering: a.ordering,
        newton: a.newton,
        cg_tolerance: a.cg_tolerance,
        preconditioner: a.preconditioner,
        dump_systems: a.dump_systems.clone(),
        end_time: a.end_time,
        resume: a.resume.clone(),
        steps_plot: Some(std::sync::Arc::new(crate::app::steps_plot::StepsSvg)),
    };
    stop_after_the_step_on_signals();
    match crate::sim::driver::run(&opts) {
        Ok(summary) => {
            if !quiet {
                eprintln!(
                    "{}: {} steps of {} s on {} nodes with {}{}{} in {:.2} s ({} Newton, {} linear iterations); output in {}",
                    summary.scene,
                    summary.steps,
                    summary.time_step,
                    summary.nodes,
                    summary.solver,
                    summary
                        .linear_choice
                        .as_ref()
                        .map_or(String::new(), |r| format!(" ({r})")),
                    summary.preconditioner.as_ref().map_or(String::new(), |p| {
                        let why = summary.preconditioner_choice.as_ref();
                        format!(
                            " and {p}{}",
                            why.map_or(String::new(), |r| format!(" ({r})"))
                        )
                    }),
                    summary.wall_seconds,
                    summary.newton_iterations,
                    summary.linear_iterations,
                    summary.out_dir
                );
                if let Some(g) = summary.gpu.as_ref().filter(|g| !g.phases.is_empty()) {
                    eprintln!(
                        "{}",
                        crate::sim::driver::largest_phases(&g.phases, summary.wall_seconds)
                    );
                }
                if let Some(p) = &summary.phases {
                    eprintln!("{}", p.line());
                }
            }
            Ok(())
        }
        Err(crate::sim::driver::RunError::Input(e)) => Err(CliError::Input(e)),
        Err(e @ crate::sim::driver::RunError::Interrupted { .. }) => Err(CliError::Interrupted {
            code: u8::try_from(e.exit_code()).unwrap_or(1),
            message: e.to_string(),
        }),
        Err(e) => Err(CliError::Failed(e.to_string())),
    }
}

/// SIGINT and SIGTERM end a run after the step it is in, with a checkpoint there; a second
/// one ends it at once (the handler restores the default action).
fn stop_after_the_step_on_signals() {
    #[cfg(unix)]
    {
        extern "C" fn on_signal(sig: libc::c_int) {
            crate::sim::driver::request_interrupt(sig);
            // SAFETY: signal(2) is async-signal-safe; it restores the default action.
            unsafe {
                libc::signal(sig, libc::SIG_DFL);
            }
        }
        let handler = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
        // SAFETY: installs a handler that only stores an atomic and calls signal(2).
        unsafe {
            libc::signal(libc::SIGINT, handler);
            libc::signal(libc::SIGTERM, handler);
        }
    }
}
