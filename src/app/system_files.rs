//! The system a command reads (`solve`, `export`, `bench --systems`): H, g and the
//! constraints (JSON, or B and p) read from files with one-line errors naming the file,
//! then the per-node frames.

use crate::core::constraints::{Constraint, Frames};
use crate::error::InputError;
use crate::io::{bcjson, mtx};
use std::time::Instant;

/// The files of one system (the `--hessian`, `--gradient`, `--constraints`,
/// `--constraint-matrix` and `--constraint-values` options) and `--dim`.
#[derive(Debug, Clone)]
pub struct SystemFiles {
    pub hessian: String,
    pub gradient: String,
    pub constraints: Option<String>,
    pub constraint_matrix: Option<String>,
    pub constraint_values: Option<String>,
    pub dim: Option<u8>,
}

/// H, g, the constraints and their frames, read and checked.
pub struct LoadedSystem {
    pub dim: usize,
    pub h: crate::core::sparse::BlockCsr,
    pub g: Vec<f64>,
    pub constraints: Vec<Constraint>,
    pub frames: Frames,
    pub read_seconds: f64,
    pub frames_seconds: f64,
}

/// Steps 1–2 shared by `solve` and `export`: read H, g and the constraints (JSON or B/p)
/// with one-line errors, then build the per-node frames.
pub fn read_system(sys: &SystemFiles) -> Result<LoadedSystem, InputError> {
    let t_start = Instant::now();
    // 1. Read. bc.json first: it may fix the dimension that H's blocks need.
    let cli_dim = sys.dim.map(usize::from);
    let bc = match &sys.constraints {
        Some(path) => Some(bcjson::read(path, cli_dim)?),
        None => None,
    };
    let dim = match (cli_dim, bc.as_ref().and_then(|b| b.dim)) {
        (Some(d), _) | (None, Some(d)) => d,
        (None, None) => {
            let file = sys.constraints.as_deref().unwrap_or("command line");
            return Err(InputError::new(
                file,
                "dim",
                "the dimension is not given: add \"dim\": 2 or 3 to the file, or pass --dim",
            ));
        }
    };
    // B before H: its rows bound the nodes H may leave without entries.
    let b = match (&bc, &sys.constraint_matrix) {
        (None, Some(bpath)) => Some(mtx::read_matrix(bpath, "B")?),
        _ => None,
    };
    // H's size line is checked before any of its entries is stored: no more rows than
    // g declares, and no more nodes than its entries plus the nodes the constraints fix.
    let g_rows = mtx::read_header(&sys.gradient)
        .ok()
        .and_then(|h| h.vector_len());
    let g_what = g_rows.map(|r| format!("the {r} rows of g ({})", sys.gradient));
    let constrained_nodes = match (&bc, &b) {
        (Some(bc), _) => bc.constraints.len(),
        (None, Some(b)) => b.nrows,
        (None, None) => 0,
    };
    let h = mtx::read_hessian_bounded(
        &sys.hessian,
        dim,
        &mtx::HessianBounds {
            max_rows: g_rows.zip(g_what.as_deref()),
            constrained_nodes: Some(constrained_nodes),
        },
    )?;
    let (nd, n) = (h.ndof(), h.n);
    let g = mtx::read_vector(
        &sys.gradient,
        "g",
        Some((nd, &format!("{nd} = {dim} × {n} nodes"))),
    )?;
    let (constraints, cfile): (Vec<Constraint>, &str) = match (&bc, &b) {
        (Some(bc), _) => (
            bc.constraints.clone(),
            sys.constraints.as_deref().unwrap_or_default(),
        ),
        (None, Some(b)) => {
            // B was read above (read_matrix refuses more rows than entries).
            let bpath = sys.constraint_matrix.as_deref().unwrap_or_default();
            let p = match &sys.constraint_values {
                Some(ppath) => Some((
                    ppath.as_str(),
                    mtx::read_vector(
                        ppath,
                        "p",
                        Some((b.nrows, &format!("{} (the rows of B)", b.nrows))),
                    )?,
                )),
                None => None,
            };
            let cs = bcjson::constraints_from_matrix(
                bpath,
                b,
                p.as_ref().map(|(f, v)| (*f, v.as_slice())),
                dim,
                n,
            )?;
            (cs, bpath)
        }
        (None, None) => {
            return Err(InputError::new(
                "command line",
                "--constraints",
                "no constraints given: pass --constraints or --constraint-matrix",
            ))
        }
    };
    let read_seconds = t_start.elapsed().as_secs_f64();

    // 2. Constraints → per-node frames, masks and the lift Δx_p.
    let t = Instant::now();
    // With B and p, a contradiction is in p's values as much as in B: name both files.
    let vfile = match (&bc, &sys.constraint_values) {
        (None, Some(ppath)) => format!(" (values from {ppath})"),
        _ => String::new(),
    };
    let frames = Frames::build(dim, n, &constraints)
        .map_err(|e| InputError::new(cfile, e.label, format!("{}{vfile}", e.problem)))?;
    Ok(LoadedSystem {
        dim,
        h,
        g,
        constraints,
        frames,
        read_seconds,
        frames_seconds: t.elapsed().as_secs_f64(),
    })
}
