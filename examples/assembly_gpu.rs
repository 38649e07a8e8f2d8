//! Device assembly against the matrix-free product: times of the element kernels, the
//! gather assembly and one product each way, and the bytes each product moves, on a
//! deformed tetrahedral cuboid.
//!
//!     cargo run --release --example assembly_gpu -- [cells per side] [f32|f64] [reps]
//!
//! (cells per side k: (k+1)³ nodes, 6k³ tetrahedra.) Numbers for docs/design/device-assembly.md.

use std::time::Instant;
use stickslip::gpu::{GpuContext, GpuOptions, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::elements::GpuElements;
use stickslip::sim::energy::{ElementSet, Law, Model, NeoHookean};
use stickslip::sim::mesh;

/// Best wall time of `reps` runs of `f` (each waited for).
fn best(
    reps: usize,
    mut f: impl FnMut() -> Result<(), Box<dyn std::error::Error>>,
) -> Result<f64, Box<dyn std::error::Error>> {
    let mut t = f64::INFINITY;
    for _ in 0..reps {
        let s = Instant::now();
        f()?;
        t = t.min(s.elapsed().as_secs_f64());
    }
    Ok(t)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let k: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(14);
    let precision: Precision = args.get(2).map_or(Ok(Precision::F32), |s| s.parse())?;
    let reps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(5);
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let m = mesh::cuboid([1.0, 1.0, 1.0], [k, k, k]);
    let n = m.n_nodes();
    // A smooth deformation (a twist and a stretch), so the element Hessians are generic.
    let x: Vec<f64> =
        m.x.chunks_exact(3)
            .flat_map(|p| {
                let a = 0.3 * p[2];
                [
                    1.1 * (p[0] * a.cos() - p[1] * a.sin()),
                    p[0] * a.sin() + p[1] * a.cos(),
                    0.95 * p[2],
                ]
            })
            .collect();
    let nh =
        NeoHookean::new(&m, 1e5, 0.4, Law::StableNeoHookean).map_err(|e| format!("mesh: {e}"))?;
    let ne = nh.len();
    let model = Model::new(
        3,
        m.lumped_masses(1e3),
        None,
        vec![ElementSet::NeoHookean(nh)],
    );
    let nb = model.pattern.nnz_blocks();
    let el = GpuElements::new(&ctx, &model, None, precision)?;
    el.set_positions(&x)?;
    el.set_inertia_target(&x)?;
    let asm = GpuAssembly::new(&el, &model)?;
    asm.set_scale(1e-4);
    asm.set_x(&vec![1.0; 3 * n])?;
    println!(
        "adapter '{}', {precision}, {n} nodes, {ne} tetrahedra, {nb} blocks ({:.2} per node, {:.2} tetrahedra per node)",
        ctx.adapter_name(),
        nb as f64 / n as f64,
        ne as f64 / n as f64
    );
    let t_el = best(reps, || {
        el.evaluate(true)?;
        asm.wait()?;
        Ok(())
    })?;
    let t_asm = best(reps, || {
        asm.assemble()?;
        asm.wait()?;
        Ok(())
    })?;
    let t_as = best(reps, || {
        asm.matvec_assembled()?;
        asm.wait()?;
        Ok(())
    })?;
    let t_mf = best(reps, || {
        asm.matvec_matrix_free()?;
        asm.wait()?;
        Ok(())
    })?;
    let b = asm.product_bytes();
    println!("element kernels      {:9.3} ms", t_el * 1e3);
    println!("assembly (H and g)   {:9.3} ms", t_asm * 1e3);
    println!(
        "assembled product    {:9.3} ms  {:12} bytes  {:7.1} bytes/node",
        t_as * 1e3,
        b.assembled,
        b.assembled as f64 / n as f64
    );
    println!(
        "matrix-free product  {:9.3} ms  {:12} bytes  {:7.1} bytes/node",
        t_mf * 1e3,
        b.matrix_free,
        b.matrix_free as f64 / n as f64
    );
    println!(
        "matrix-free / assembled: time {:.2}, bytes {:.2}",
        t_mf / t_as,
        b.matrix_free as f64 / b.assembled as f64
    );
    Ok(())
}
