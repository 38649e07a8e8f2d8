//! CPU f64 CG iterations (Jacobi, tol 1e-10) on every hard case with each coarse space:
//! `cargo run --release --example coarse_ab -- [scale] [case ...]`. Used in docs/coarse.md.

use std::time::Instant;
use stickslip::app::hard::{self, Size};
use stickslip::solve::cg::{self, CgParams, Preconditioner};
use stickslip::solve::coarse::{Aggregation, CoarseSpace};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scale: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1);
    let names = args.get(2..).unwrap_or_default();
    let size = Size::from_scale(scale);
    println!("| case | DOFs | aggregates | none | translations | aggregates | s none | s translations | s aggregates |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for case in hard::suite(size) {
        if !names.is_empty() && !names.contains(&case.name) {
            continue;
        }
        let e = case.eliminated();
        let agg = Aggregation::build(&case.h);
        let mut its = Vec::new();
        let mut secs = Vec::new();
        for coarse in [
            CoarseSpace::None,
            CoarseSpace::Translations,
            CoarseSpace::Aggregates,
        ] {
            let p = CgParams {
                tol: 1e-10,
                max_iters: 50_000,
                preconditioner: Preconditioner::Jacobi,
                coarse,
                ..Default::default()
            };
            let t = Instant::now();
            let r = cg::solve(&e, &p);
            secs.push(t.elapsed().as_secs_f64());
            its.push(match r {
                Ok((_, info)) => info.iterations.to_string(),
                Err(err) => format!("fail ({err})").chars().take(40).collect(),
            });
        }
        println!(
            "| {} | {} | {} | {} | {} | {} | {:.3} | {:.3} | {:.3} |",
            case.name,
            e.ndof(),
            agg.count,
            its[0],
            its[1],
            its[2],
            secs[0],
            secs[1],
            secs[2]
        );
    }
}
