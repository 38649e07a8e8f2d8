//! `stickslip generate`: a seeded random system written as files.

use crate::app::cli::args::{GenerateArgs, MixArg, StencilArg};
use crate::app::cli::error::{write_failed, CliError};
use crate::cases::generate::{random_system, ConstraintMix, Stencil, SystemSpec};
use crate::error::InputError;
use crate::io::files::OutputDir;
use crate::io::{bcjson, mtx};
use std::time::Instant;

/// Every file `generate` may write in its folder.
pub const GENERATE_OUTPUTS: [&str; 5] = ["H.mtx", "g.mtx", "bc.json", "B.mtx", "p.mtx"];

/// `stickslip generate`: a seeded system as H.mtx, g.mtx, bc.json (and B.mtx, p.mtx).
pub fn generate(args: &GenerateArgs, quiet: bool) -> Result<(), CliError> {
    let t = Instant::now();
    if args.nodes == 0 {
        return Err(InputError::new("command line", "--nodes", "must be at least 1").into());
    }
    let mut out = OutputDir::open(
        &args.out_dir,
        "--out-dir",
        "generate",
        &GENERATE_OUTPUTS,
        &[],
        args.overwrite,
    )?;
    let dim = usize::from(args.dim);
    let mut spec = SystemSpec::with_nodes(dim, args.nodes, args.seed);
    spec.stencil = match args.stencil {
        StencilArg::Mesh => Stencil::Mesh,
        StencilArg::Face => Stencil::Face,
    };
    spec.mix = match args.mix {
        MixArg::Realistic => ConstraintMix::Realistic,
        MixArg::Random => ConstraintMix::Random,
        MixArg::None => ConstraintMix::None,
    };
    let s = random_system(&spec);
    let dir = &args.out_dir;
    let shown = dir.display().to_string();
    out.clean().map_err(|e| write_failed(&shown, e))?;
    let comment = format!(
        "stickslip generate --dim {dim} --nodes {} --seed {} --stencil {:?} --mix {:?}: {} nodes on a {}x{}{} grid",
        args.nodes,
        args.seed,
        args.stencil,
        args.mix,
        s.h.n,
        spec.grid[0],
        spec.grid[1],
        if dim == 3 { format!("x{}", spec.grid[2]) } else { String::new() }
    )
    .to_lowercase();
    // Recorded before they exist: a killed run's files are cleared by the next one.
    for name in GENERATE_OUTPUTS {
        if args.matrix_form || !matches!(name, "B.mtx" | "p.mtx") {
            out.record(name).map_err(|e| write_failed(&shown, e))?;
        }
    }
    let path = |name: &str| dir.join(name);
    let shown = |name: &str| path(name).display().to_string();
    mtx::write_hessian(path("H.mtx"), &s.h, &comment)
        .map_err(|e| write_failed(&shown("H.mtx"), e))?;
    mtx::write_vector(path("g.mtx"), &s.g, &comment)
        .map_err(|e| write_failed(&shown("g.mtx"), e))?;
    bcjson::write(path("bc.json"), dim, &s.constraints)
        .map_err(|e| write_failed(&shown("bc.json"), e))?;
    if args.matrix_form {
        let (b, p) = bcjson::constraints_to_matrix(dim, &s.constraints);
        mtx::write_coo(path("B.mtx"), p.len(), s.h.ndof(), &b, &comment)
            .map_err(|e| write_failed(&shown("B.mtx"), e))?;
        mtx::write_vector(path("p.mtx"), &p, &comment)
            .map_err(|e| write_failed(&shown("p.mtx"), e))?;
    }
    if !quiet {
        eprintln!(
            "stickslip: wrote {} nodes (dim {dim}, {} blocks, {} constraints, {} free dofs) to {} in {:.2} s",
            s.h.n,
            s.h.nnz_blocks(),
            s.constraints.len(),
            s.frames.free_dofs(),
            dir.display(),
            t.elapsed().as_secs_f64()
        );
    }
    Ok(())
}
