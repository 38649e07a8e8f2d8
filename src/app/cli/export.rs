//! `stickslip export` and `stickslip recover`: the eliminated system out to an external
//! solver, and its solution back to Δx and the reactions.

use crate::app::cli::args::{ExportArgs, RecoverArgs};
use crate::app::cli::error::{all_finite, write_failed, CliError};
use crate::app::cli::solve::system_inputs;
use crate::app::system_files::read_system;
use crate::core::elimination::Eliminated;
use crate::error::SolveError;
use crate::io::files::{self, Named, OutputDir};
use crate::io::mtx;

/// `stickslip export`: read → frames → eliminate → write Ĥ, b̂ and the layout.
pub fn export(a: &ExportArgs, quiet: bool) -> Result<(), CliError> {
    let inputs = system_inputs(&a.system);
    let names = &crate::app::export::OUTPUT_NAMES;
    OutputDir::check(
        &a.out_dir,
        "--out-dir",
        "export",
        names,
        &inputs,
        a.overwrite,
    )?;
    let sys = read_system(&a.system.files())?;
    let mut out = OutputDir::open(
        &a.out_dir,
        "--out-dir",
        "export",
        names,
        &inputs,
        a.overwrite,
    )?;
    let diag = a.constrained_diagonal;
    let e = Eliminated::new(&sys.h, &sys.g, &sys.frames, diag);
    all_finite("b̂ = −Vᵀ(g + HΔx_p)", &e.rhs)?;
    let shown = a.out_dir.display().to_string();
    out.clean().map_err(|e| write_failed(&shown, e))?;
    for name in crate::app::export::OUTPUT_NAMES {
        if a.no_mtx && name.ends_with(".mtx") {
            continue;
        }
        out.record(name).map_err(|e| write_failed(&shown, e))?;
    }
    let files = crate::app::export::export(&e, diag, &sys.g, &a.out_dir, !a.no_mtx)
        .map_err(|err| write_failed(&a.out_dir.display().to_string(), err))?;
    if !quiet {
        eprintln!(
            "exported {} nodes ({} free of {} DOFs, block size {}) to {}: {}",
            sys.h.n,
            sys.frames.free_dofs(),
            sys.h.ndof(),
            sys.dim,
            a.out_dir.display(),
            files.layout.display()
        );
    }
    Ok(())
}

/// `stickslip recover`: y → Δx = Δx_p + V y and f = −(HΔx + g), checked against the layout.
pub fn recover(a: &RecoverArgs, quiet: bool) -> Result<(), CliError> {
    let inputs = [
        Named::new("--layout", &a.layout),
        Named::new("--solution", &a.solution),
        Named::new("--hessian", &a.hessian),
        Named::new("--gradient", &a.gradient),
    ];
    let outputs: Vec<Named> = std::iter::once(Named::new("--out", &a.out))
        .chain(a.reactions.iter().map(|r| Named::new("--reactions", r)))
        .collect();
    files::check_outputs(&inputs, &outputs)?;
    let layout = crate::app::export::read_layout(std::path::Path::new(&a.layout))?;
    let nd_layout = layout.dim * layout.n_nodes;
    let y = if a.solution.ends_with(".mtx") {
        mtx::read_vector(
            &a.solution,
            "y",
            Some((
                nd_layout,
                &format!(
                    "{nd_layout} = {} × {} nodes (the layout's system)",
                    layout.dim, layout.n_nodes
                ),
            )),
        )?
    } else {
        crate::app::export::read_petsc_vec(std::path::Path::new(&a.solution))?
    };
    let what = format!("the {nd_layout} rows of the layout's system ({})", a.layout);
    let h = mtx::read_hessian_bounded(
        &a.hessian,
        layout.dim,
        &mtx::HessianBounds {
            max_rows: Some((nd_layout, &what)),
            // The layout fixes the size; no bound from the entries.
            constrained_nodes: Some(layout.n_nodes),
        },
    )?;
    let nd = h.ndof();
    let g = mtx::read_vector(
        &a.gradient,
        "g",
        Some((nd, &format!("{nd} = {} × {} nodes", layout.dim, h.n))),
    )?;
    let rec = crate::app::export::recover(
        &layout,
        &y,
        &h,
        &g,
        [&a.layout, &a.solution, &a.hessian, &a.gradient],
    )?;
    // A y that does not solve the exported system (another system's, or zero) would give
    // a Δx that looks like a result: refuse it.
    if rec.relative_residual.is_nan() || rec.relative_residual > a.max_residual {
        return Err(SolveError::NotSolved(format!(
            "{}: y does not solve the exported system: relative residual ‖b̂ − Ĥy‖/‖b̂‖ = \
             {:.3e} > --max-residual {:.1e}; nothing written",
            a.solution, rec.relative_residual, a.max_residual
        ))
        .into());
    }
    all_finite("Δx", &rec.dx)?;
    all_finite("the reactions f = −(HΔx + g)", &rec.reactions)?;
    mtx::write_vector(&a.out, &rec.dx, "dx recovered by stickslip recover")
        .map_err(|e| write_failed(&a.out, e))?;
    if let Some(path) = &a.reactions {
        mtx::write_vector(
            path,
            &rec.reactions,
            "reactions f = -(H dx + g), stickslip recover",
        )
        .map_err(|e| write_failed(path, e))?;
    }
    if !quiet {
        eprintln!(
            "recovered {} nodes; relative residual of y in the exported system {:.3e}",
            h.n, rec.relative_residual
        );
    }
    Ok(())
}
