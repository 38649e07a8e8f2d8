//! The multilevel preconditioner's levels built on the device (src/gpu/pcg/mlsetup.rs,
//! what the device Newton loop runs) against the same levels built on the host
//! ([`Multilevel::new`], what the CPU CG runs), on seeded systems with sticky, prescribed,
//! plane- and line-slip (rotated) nodes, large enough for two coarse levels or more; then
//! after a refresh (kept levels, a new H) and after a remask (kept levels, a free node
//! made sticky and a plane-slip node given a second constrained direction).
//!
//! The device does the host's operations in the host's order but for the power
//! estimates' dot products (a two-pass tree against a sequential sum), and a GPU may
//! contract a·b + c into one rounding. Bounds, each relative to the largest magnitude of
//! the array compared (level by level):
//! - ω (every level but the coarsest, which is 1 on both) and the arrays built from it:
//!   each dot product sums N ≤ 3·729 terms of one sign mostly (xᵀAx and yᵀAx of a positive
//!   start vector), so each side is within N·u ≈ 2.4e-13 of the exact sum and λ̂ within
//!   twice that; P = T − ωD⁻¹AT, Pᵀ, A_{l+1} = PᵀAP inherit it (P twice) plus a few
//!   roundings per entry, and each level adds its own ω: 1e-11 over three levels is that
//!   bound with room (the printed figures are far below it).
//! - the cluster pseudo-inverses: B⁺ of a block B known to a relative ε moves by up to
//!   κ(B)·ε·‖B⁺‖ (−B⁺ΔBB⁺ to first order), with ε the matrices' 1e-11 below the finest
//!   level and a few roundings per entry (4·m·u) at level 0, whose blocks come from H in
//!   the same order on both sides; κ is bounded per cluster by ‖B‖_F‖B⁺‖_F from the host's
//!   block and inverse, and the entries are held to 10× that first-order bound.
//!
//! On lavapipe, which rounds each f64 operation as the host does, level 0's inverses (H's
//! blocks through the same operations in the same order) are held to the last bit.
//!
//! The device memory the levels and their setup take is what the memory checks count
//! before anything is built ([`multilevel_bytes`], [`multilevel_setup_bytes`]), split
//! buffers included.
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use std::sync::Arc;
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::constraints::Frames;
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::core::sparse::BlockCsr;
use stickslip::gpu::blocks::HostBlocks;
use stickslip::gpu::kernels::Real;
use stickslip::gpu::pcg::{
    multilevel_bytes, multilevel_setup_bytes, DeviceCg, DeviceFrames, LevelValues,
};
use stickslip::gpu::{CoarseSpace, GpuContext};
use stickslip::solve::multilevel::reuse::Levels;
use stickslip::solve::multilevel::{Hierarchy, LevelView, Multilevel, LAMBDA_STEPS};

mod common;
use common::gpu::gpu;

/// The values' bound relative to each array's largest entry (module docs).
const VALUES_TOL: f64 = 1e-11;
const U: f64 = f64::EPSILON / 2.0;

/// max |a − b| over max |b|, and how many entries agree bit for bit (as values: ±0 alike).
fn rel_max(a: &[f64], b: &[f64]) -> (f64, usize) {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let diff = a
        .iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
    let same = a.iter().zip(b).filter(|(x, y)| x == y).count();
    (if scale > 0.0 { diff / scale } else { diff }, same)
}

/// The host's level-0 inverses as the device V-cycle holds them: constrained rows and
/// columns zero.
fn masked_inverses(v: &LevelView<'_>, d: usize, mask: &[u8]) -> Vec<f64> {
    let mut inv = v.inv.to_vec();
    for c in 0..v.ptr.len() - 1 {
        let items = &v.items[v.ptr[c]..v.ptr[c + 1]];
        let m = items.len() * d;
        let block = &mut inv[v.inv_start[c]..v.inv_start[c + 1]];
        for (p, &i) in items.iter().enumerate() {
            for a in (0..d).filter(|a| mask[i as usize] & (1 << a) != 0) {
                for k in 0..m {
                    block[(p * d + a) * m + k] = 0.0;
                    block[k * m + p * d + a] = 0.0;
                }
            }
        }
    }
    inv
}

/// Cluster c's dense block of the level's matrix (m×m row-major) from the host's values.
fn cluster_block(v: &LevelView<'_>, d: usize, c: usize) -> Vec<f64> {
    let items = &v.items[v.ptr[c]..v.ptr[c + 1]];
    let m = items.len() * d;
    let mut b = vec![0.0; m * m];
    for (p, &i) in items.iter().enumerate() {
        let i = i as usize;
        for k in v.row_ptr[i]..v.row_ptr[i + 1] {
            let j = v.col_idx[k];
            if v.of[j] as usize != c {
                continue;
            }
            let q = v.pos[j] as usize;
            for r in 0..d {
                for s in 0..d {
                    b[(p * d + r) * m + q * d + s] = v.values[k * d * d + r * d + s];
                }
            }
        }
    }
    b
}

/// Per cluster: the device inverse within 10× the first-order bound κ_F·ε·‖B⁺‖_max of the
/// host's (module docs). Returns the largest ratio of the difference to the bound.
fn check_inverses(v: &LevelView<'_>, d: usize, dev: &[f64], host: &[f64], eps: f64) -> f64 {
    let fro = |x: &[f64]| x.iter().map(|a| a * a).sum::<f64>().sqrt();
    let mut worst = 0.0f64;
    for c in 0..v.ptr.len() - 1 {
        let r = v.inv_start[c]..v.inv_start[c + 1];
        let b = cluster_block(v, d, c);
        let kappa = fro(&b) * fro(&v.inv[r.clone()]);
        let inv_max = host[r.clone()].iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let diff = dev[r.clone()]
            .iter()
            .zip(&host[r])
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        let bound = 10.0 * kappa * eps * inv_max;
        if diff > 0.0 {
            worst = worst.max(diff / bound);
        }
        assert!(
            diff <= bound,
            "cluster {c}: inverse differs by {diff:e}, bound {bound:e} (κ_F {kappa:e})"
        );
    }
    worst
}

/// Every level of `dev` against `host`'s (constraint set `frames`), within the bounds of
/// the module docs; prints the figures under `what`.
fn compare(what: &str, host: &Multilevel, dev: &[LevelValues], frames: &Frames, exact0: bool) {
    let d = host.dim();
    let views = host.levels();
    assert_eq!(views.len(), dev.len(), "{what}: levels");
    for (l, (v, g)) in views.iter().zip(dev).enumerate() {
        let omega = ((g.omega - v.omega) / v.omega).abs();
        assert!(
            omega <= VALUES_TOL,
            "{what}, level {l}: ω {} vs {}",
            g.omega,
            v.omega
        );
        // λ̂ itself below the coarsest level (ω is capped at 2/3 where λ̂ < 1.95).
        let lambda = match (l + 1 < views.len(), g.lambda) {
            (true, Some(dev)) => {
                let want = host.lambda_max(l, LAMBDA_STEPS);
                let rel = ((dev - want) / want).abs();
                assert!(rel <= VALUES_TOL, "{what}, level {l}: λ̂ {dev} vs {want}");
                format!(", λ̂ {dev:.6} (Δ {rel:.1e})")
            }
            (true, None) => panic!("{what}, level {l}: no λ̂ from the device"),
            _ => String::new(),
        };
        let host_inv = if l == 0 {
            masked_inverses(v, d, &frames.mask)
        } else {
            v.inv.to_vec()
        };
        let (inv, inv_same) = rel_max(&g.inverses, &host_inv);
        if l == 0 && exact0 {
            assert_eq!(
                inv_same,
                host_inv.len(),
                "{what}: level 0's inverses not bitwise"
            );
        }
        // Level 0's blocks are H's in the same operations: a few roundings per entry.
        let eps = if l == 0 { 4.0 * 64.0 * U } else { VALUES_TOL };
        let ratio = check_inverses(v, d, &g.inverses, &host_inv, eps);
        let mut line = format!(
            "{what}, level {l} ({} items): ω {:.6} (Δ {omega:.1e}){lambda}; inverses Δ \
             {inv:.1e} ({inv_same}/{} bitwise, ≤ {ratio:.1e} of the bound)",
            v.n,
            g.omega,
            host_inv.len()
        );
        if l > 0 {
            let (a, same) = rel_max(&g.matrix, v.values);
            assert!(a <= VALUES_TOL, "{what}, A_{l}: {a:e}");
            line += &format!("; A Δ {a:.1e} ({same}/{} bitwise)", v.values.len());
        }
        if let Some(pr) = &v.to_next {
            let (p, same) = rel_max(&g.p, pr.p);
            let (pt, _) = rel_max(&g.pt, pr.pt_values);
            assert!(
                p <= VALUES_TOL && pt <= VALUES_TOL,
                "{what}, P_{l}: {p:e}, {pt:e}"
            );
            line += &format!("; P Δ {p:.1e} ({same}/{} bitwise)", pr.p.len());
        }
        eprintln!("{line}");
    }
}

/// The device PCG of `h` (f64, b̂ given) and its frames of `f`.
fn device(ctx: &GpuContext, blocks: &HostBlocks, f: &Frames) -> (DeviceCg, DeviceFrames) {
    let cg = DeviceCg::new(ctx, blocks.matrix(), None, false, false).expect("device PCG");
    let frames = cg.frames(f, CoarseSpace::None).expect("frames");
    (cg, frames)
}

/// H + ½ blockdiag(H): SPD, of the same pattern, with a new ω_0.
fn stiffer_diagonal(h: &BlockCsr) -> BlockCsr {
    let mut h2 = h.clone();
    let dd = h.dim * h.dim;
    for i in 0..h.n {
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            if h.col_idx[k] == i {
                h2.values[k * dd..(k + 1) * dd]
                    .iter_mut()
                    .for_each(|v| *v *= 1.5);
            }
        }
    }
    h2
}

#[test]
fn device_built_levels_equal_the_host_built_ones() {
    let Some((ctx, _g)) = gpu() else { return };
    // lavapipe rounds every f64 operation as the host does (no contraction into fused
    // multiply-adds): level 0's inverses, H's blocks through the same operations in the
    // same order, are then the host's bit for bit.
    let exact = ctx.adapter_name().starts_with("llvmpipe");
    for (dim, nodes, seed) in [(2, 900, 21u64), (3, 729, 22)] {
        let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
        let f = &s.frames;
        let full = (1u8 << dim) - 1;
        assert!(f.rot_nodes.len() > 1, "{dim}D: slip nodes");
        assert!(f.mask.contains(&full), "{dim}D: fixed nodes");
        let hier = Arc::new(Hierarchy::new(&s.h));
        let counts = hier.cluster_counts();
        assert!(counts.len() >= 3, "{dim}D: levels {counts:?}");
        eprintln!("{dim}D, {} nodes: clusters per level {counts:?}", s.h.n);
        let e = Eliminated::new(&s.h, &s.g, f, ConstrainedDiagonal::Identity);
        let mut host = Multilevel::new(&e, hier.clone());
        let blocks = HostBlocks::upload(ctx, &s.h, Real::F64, None).expect("upload");
        let (mut cg, frames) = device(ctx, &blocks, f);
        let (t0, a0) = (ctx.traffic(), ctx.allocated_bytes());
        cg.set_multilevel_on_device(&hier, &frames, Levels::Built, None)
            .expect("built on the device");
        let (t1, a1) = (ctx.traffic(), ctx.allocated_bytes());
        // The device memory the first build took is what the memory checks count.
        let planned = multilevel_bytes(ctx, &hier.level_sizes(dim), dim, None).expect("fits")
            + multilevel_setup_bytes(ctx, &hier, dim, blocks.chunk_count(), None).expect("fits");
        assert_eq!(a1 - a0, planned, "{dim}D: allocated against planned");
        let built = cg.read_multilevel().expect("read back");
        compare(&format!("{dim}D built"), &host, &built, f, exact);

        // Kept levels refreshed for a new H: ω_0 anew, everything else as it was.
        let h2 = stiffer_diagonal(&s.h);
        blocks.write(ctx, &h2).expect("new values");
        let e2 = Eliminated::new(&h2, &s.g, f, ConstrainedDiagonal::Identity);
        host.refresh(&e2);
        let t2 = ctx.traffic();
        cg.set_multilevel_on_device(&hier, &frames, Levels::Kept, None)
            .expect("refreshed on the device");
        let t3 = ctx.traffic();
        let kept = cg.read_multilevel().expect("read back");
        compare(&format!("{dim}D kept"), &host, &kept, f, exact);
        for (a, b) in kept.iter().zip(&built).skip(1) {
            assert_eq!(a.omega, b.omega);
            assert_eq!(a.matrix, b.matrix);
            assert_eq!(a.inverses, b.inverses);
        }
        assert_eq!(kept[0].inverses, built[0].inverses);
        assert_eq!(kept[0].p, built[0].p);

        // A free node made sticky and a plane-slip node given a second constrained
        // direction in its frame: the kept levels remasked.
        let mut more = f.clone();
        let free = (0..f.n_nodes)
            .find(|&i| f.mask[i] == 0 && f.rotation(i).is_none())
            .expect("a free node");
        more.mask[free] = full;
        let slip = (0..f.n_nodes).find(|&i| f.rotation(i).is_some() && f.mask[i] == 1);
        if let (Some(i), 3) = (slip, dim) {
            more.mask[i] |= 0b010;
        }
        let e3 = Eliminated::new(&h2, &s.g, &more, ConstrainedDiagonal::Identity);
        assert_eq!(
            host.fit(&more),
            stickslip::solve::multilevel::FramesFit::Masked
        );
        host.refresh(&e3);
        let frames3 = cg.frames(&more, CoarseSpace::None).expect("frames");
        let t4 = ctx.traffic();
        cg.set_multilevel_on_device(&hier, &frames3, Levels::Remasked, None)
            .expect("remasked on the device");
        let t5 = ctx.traffic();
        let remasked = cg.read_multilevel().expect("read back");
        compare(&format!("{dim}D remasked"), &host, &remasked, &more, exact);

        // Built again for the grown constraint set: a fresh build's levels.
        let fresh = Multilevel::new(&e3, hier.clone());
        let t6 = ctx.traffic();
        let clock = std::time::Instant::now();
        cg.set_multilevel_on_device(&hier, &frames3, Levels::Built, None)
            .expect("built again on the device");
        let record = clock.elapsed();
        let t7 = ctx.traffic();
        let rebuilt = cg.read_multilevel().expect("read back");
        compare(&format!("{dim}D rebuilt"), &fresh, &rebuilt, &more, exact);
        eprintln!(
            "{dim}D: a build recorded and submitted in {:.1} ms",
            record.as_secs_f64() * 1e3
        );

        // A refresh, a remask or a build on the same hierarchy moves no byte; the first
        // build only its buffers' one-off index words and parameters (nothing comes back).
        assert_eq!(t3, t2, "{dim}D: a refresh moved bytes");
        assert_eq!(t5, t4, "{dim}D: a remask moved bytes");
        assert_eq!(t7, t6, "{dim}D: a build on the same hierarchy moved bytes");
        assert_eq!(t1.device_to_host_bytes, t0.device_to_host_bytes);
        eprintln!(
            "{dim}D: the first build uploaded {} bytes once (H's values are {} bytes); the \
             refresh, the remask and the second build none",
            t1.host_to_device_bytes - t0.host_to_device_bytes,
            8 * h2.values.len()
        );
    }
}

/// H in several values chunks and the cluster inverses in several buffers (the binding
/// limit lowered, as on an adapter whose storage bindings are smaller than the system):
/// the same levels bit for bit as with one buffer each, built and refreshed. Each entry is
/// the same operations in the same order; only the dispatches are cut.
#[test]
fn split_buffers_give_the_same_levels() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = random_system(&SystemSpec::with_nodes(3, 729, 23));
    let f = &s.frames;
    let hier = Arc::new(Hierarchy::new(&s.h));
    let level0: usize = hier.level_sizes(3)[0].inverses.iter().sum();
    let largest = hier.level_sizes(3)[0]
        .inverses
        .iter()
        .copied()
        .max()
        .unwrap_or(0);
    let limit = (8 * level0 as u64 / 3).max(8 * largest as u64);
    let h2 = stiffer_diagonal(&s.h);
    let run = |forced: Option<u64>| {
        let blocks = HostBlocks::upload(ctx, &s.h, Real::F64, forced).expect("upload");
        let (mut cg, frames) = device(ctx, &blocks, f);
        let a0 = ctx.allocated_bytes();
        cg.set_multilevel_on_device(&hier, &frames, Levels::Built, forced)
            .expect("built on the device");
        let planned = multilevel_bytes(ctx, &hier.level_sizes(3), 3, forced).expect("fits")
            + multilevel_setup_bytes(ctx, &hier, 3, blocks.chunk_count(), forced).expect("fits");
        assert_eq!(
            ctx.allocated_bytes() - a0,
            planned,
            "allocated against planned"
        );
        let built = cg.read_multilevel().expect("read back");
        blocks.write(ctx, &h2).expect("new values");
        cg.set_multilevel_on_device(&hier, &frames, Levels::Kept, forced)
            .expect("refreshed on the device");
        let kept = cg.read_multilevel().expect("read back");
        (
            blocks.chunk_count(),
            cg.multilevel_inverse_buffers(),
            built,
            kept,
        )
    };
    let (_, _, whole, whole_kept) = run(None);
    let (chunks, buffers, split, split_kept) = run(Some(limit));
    eprintln!("H in {chunks} buffers, inverse buffers per level {buffers:?}");
    assert!(chunks >= 2 && buffers[0] >= 3, "{chunks}, {buffers:?}");
    let bits = |v: &[LevelValues]| -> Vec<Vec<u64>> {
        v.iter()
            .map(|l| {
                std::iter::once(l.omega)
                    .chain(l.matrix.iter().copied())
                    .chain(l.inverses.iter().copied())
                    .chain(l.p.iter().copied())
                    .chain(l.pt.iter().copied())
                    .map(f64::to_bits)
                    .collect()
            })
            .collect()
    };
    assert_eq!(bits(&whole), bits(&split));
    assert_eq!(bits(&whole_kept), bits(&split_kept));
}
