//! AMD against nested dissection on generated systems: analysis time, factor size and
//! (with `--numeric`) the numeric factorization's time, for each ordering in turn.
//!
//!     cargo run --release --example ordering_ab -- [--numeric] DIM:NODES ...
//!
//! e.g. `-- --numeric 2:10000 3:8000 3:27000`. Systems come from `random_system` with
//! `SystemSpec::with_nodes(dim, nodes, 1)` (as `stickslip generate --seed 1`).

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::solve::oracle::CholeskyOracle;
use stickslip::CholeskyOrdering;

fn main() {
    let mut numeric = false;
    let mut cases = Vec::new();
    for a in std::env::args().skip(1) {
        if a == "--numeric" {
            numeric = true;
            continue;
        }
        let parsed = a
            .split_once(':')
            .and_then(|(d, n)| Some((d.parse::<usize>().ok()?, n.parse::<usize>().ok()?)));
        match parsed {
            Some((d, n)) if (d == 2 || d == 3) && n >= 4 => cases.push((d, n)),
            _ => {
                eprintln!("error: '{a}' is not DIM:NODES (DIM 2 or 3, NODES at least 4)");
                std::process::exit(2);
            }
        }
    }
    println!("| dim | nodes | ordering | analysis s | ordering s | nnz(L) | faer stored | supernodes | numeric s |");
    println!("|---|---:|---|---:|---:|---:|---:|---:|---:|");
    for (dim, nodes) in cases {
        let s = random_system(&SystemSpec::with_nodes(dim, nodes, 1));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        for ord in [
            CholeskyOrdering::Amd,
            CholeskyOrdering::NestedDissection,
            CholeskyOrdering::Auto,
        ] {
            let mut oracle = match CholeskyOracle::analyze_with(&e, ord) {
                Ok(o) => o,
                Err(err) => {
                    eprintln!("error: {dim}D {nodes}: {err}");
                    std::process::exit(1);
                }
            };
            let numeric_s = if numeric && ord != CholeskyOrdering::Auto {
                match oracle.solve(&e) {
                    Ok((_, info)) => format!("{:.3}", info.numeric_seconds),
                    Err(err) => {
                        eprintln!("error: {dim}D {nodes}: {err}");
                        std::process::exit(1);
                    }
                }
            } else {
                "-".to_string()
            };
            let shown = if ord == CholeskyOrdering::Auto {
                format!("auto → {}", oracle.ordering().name())
            } else {
                ord.name().to_string()
            };
            let (analysis, ordering) = oracle.analysis_seconds();
            println!(
                "| {dim}D | {} | {shown} | {analysis:.3} | {ordering:.3} | {} | {} | {} | {numeric_s} |",
                s.h.n,
                oracle.factor_nnz_exact(),
                oracle.factor_nnz(),
                oracle.supernodes().map_or("-".into(), |n| n.to_string()),
            );
        }
    }
}
