//! Which f32 rounding costs mixed precision its iterations? A CPU emulation of the GPU's
//! mixed-precision CG (Jacobi PCG on a unit right-hand side, reliable updates each time the
//! recurrence residual drops by δ = 0.1, f64 true residuals and f64 dot products), with the
//! matrix and the vectors rounded to f32 separately:
//!
//! `cargo run --release --example f32_emulation -- [scale] [case ...]`
//!
//! Columns: iterations to a true relative residual of 1e-10 (`fail` on non-positive
//! curvature or 20000 iterations) for f64 CG, f32 matrix + f32 vectors (what the GPU runs),
//! f32 matrix + f64 vectors, f64 matrix + f32 vectors, and f32 off-diagonal blocks with f64
//! diagonal blocks + f32 vectors. Used in docs/precision.md.

use stickslip::app::hard::{self, Size};
use stickslip::core::sparse::BlockCsr;

const TOL: f64 = 1e-10;
const DELTA: f64 = 0.1;
const MAX_ITERS: usize = 20_000;

/// Which quantities are rounded to f32.
#[derive(Clone, Copy)]
struct Rounding {
    matrix: bool,
    vectors: bool,
    /// With `matrix`: keep the diagonal blocks in f64 (1/27 of a 3D mesh matrix's data).
    diag64: bool,
    /// With `matrix`: difference form q_i = Σ_{j≠i} H_ij (p_j − p_i) + S_i p_i with
    /// S_i = Σ_j H_ij summed in f64 before rounding, so the f32 operator keeps the
    /// block row sums (the rigid translations' eigenvalues) to f32 accuracy.
    diff: bool,
    /// Additive coarse correction on the rigid translations: z = D⁻¹r + Z E⁻¹ Zᵀ r.
    coarse: bool,
    /// The matvec sums in f32 like the GPU's kernel (STICKSLIP_EMU_ACC32=1; default f64).
    acc32: bool,
}

impl Rounding {
    fn v(self, x: f64) -> f64 {
        if self.vectors {
            x as f32 as f64
        } else {
            x
        }
    }
}

/// q = H p with the stored matrix `m` (f64 or f64 copies of f32 values), summed in f64
/// (exact products of two f32 numbers), the result rounded like a vector.
fn matvec(h: &BlockCsr, m: &[f64], p: &[f64], rd: Rounding, q: &mut [f64]) {
    let d = h.dim;
    for i in 0..h.n {
        for a in 0..d {
            let mut s = 0.0;
            for k in h.row_ptr[i]..h.row_ptr[i + 1] {
                let j = h.col_idx[k];
                for c in 0..d {
                    let pj = if rd.diff && j != i {
                        rd.v(p[j * d + c] - p[i * d + c])
                    } else {
                        p[j * d + c]
                    };
                    s += m[k * d * d + a * d + c] * pj;
                    if rd.acc32 {
                        s = rd.v(s);
                    }
                }
            }
            q[i * d + a] = rd.v(s);
        }
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Iterations to ‖b − Hy‖ ≤ TOL‖b‖, or `None`.
fn solve(h: &BlockCsr, b: &[f64], zb: &[Vec<f64>], einv: &[f64], rd: Rounding) -> Option<usize> {
    let n = b.len();
    let d = h.dim;
    let mut m: Vec<f64> = if rd.matrix {
        h.values.iter().map(|&v| v as f32 as f64).collect()
    } else {
        h.values.clone()
    };
    if rd.diff {
        let dd = d * d;
        for i in 0..h.n {
            let mut sum = vec![0.0; dd];
            for k in h.row_ptr[i]..h.row_ptr[i + 1] {
                for (se, v) in sum.iter_mut().zip(&h.values[k * dd..(k + 1) * dd]) {
                    *se += v;
                }
            }
            if let Some(kb) = h.diag_index(i) {
                for (me, se) in m[kb * dd..(kb + 1) * dd].iter_mut().zip(&sum) {
                    *me = if rd.matrix { *se as f32 as f64 } else { *se };
                }
            }
        }
    }
    if rd.matrix && rd.diag64 {
        for i in 0..h.n {
            if let Some(kb) = h.diag_index(i) {
                let r = kb * d * d..(kb + 1) * d * d;
                m[r.clone()].copy_from_slice(&h.values[r]);
            }
        }
    }
    let minv: Vec<f64> = (0..n)
        .map(|k| {
            let kb = h.diag_index(k / d)?;
            Some(rd.v(1.0 / h.values[kb * d * d + (k % d) * (d + 1)]))
        })
        .collect::<Option<_>>()?;
    // f64 CG: one segment to TOL; else segments of DELTA.
    let f64_cg = !rd.matrix && !rd.vectors;
    let bn = dot(b, b).sqrt();
    let (mut y, mut rt) = (vec![0.0; n], b.to_vec());
    let (mut p, mut q, mut hy) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
    let (mut rho_prev, mut rn_prev, mut total) = (1.0, 0.0, 0usize);
    loop {
        let rn = dot(&rt, &rt).sqrt();
        if rn <= TOL * bn {
            return Some(total);
        }
        // Reliable update: unit right-hand side, direction rescaled to it.
        let ps = if total == 0 { 0.0 } else { rn_prev / rn };
        p.iter_mut().for_each(|v| *v = rd.v(*v * ps));
        rho_prev = if total == 0 { 1.0 } else { rho_prev * ps * ps };
        let thresh = if f64_cg {
            (TOL * bn / rn).powi(2)
        } else {
            DELTA * DELTA
        };
        let mut x = vec![0.0; n];
        let mut r: Vec<f64> = rt.iter().map(|v| rd.v(v / rn)).collect();
        let mut z: Vec<f64> = r.iter().zip(&minv).map(|(a, m)| rd.v(a * m)).collect();
        let coarse = |r: &[f64], z: &mut [f64]| {
            if !rd.coarse {
                return;
            }
            let nz = zb.len();
            let zr: Vec<f64> = zb.iter().map(|v| dot(v, r)).collect();
            let c: Vec<f64> = (0..nz)
                .map(|a| (0..nz).map(|b| einv[a * nz + b] * zr[b]).sum())
                .collect();
            for k in 0..z.len() {
                let s: f64 = (0..nz).map(|a| zb[a][k] * c[a]).sum();
                z[k] = rd.v(z[k] + s);
            }
        };
        coarse(&r, &mut z);
        loop {
            let rho = dot(&r, &z);
            if dot(&r, &r) <= thresh {
                break;
            }
            let beta = rho / rho_prev;
            for k in 0..n {
                p[k] = rd.v(z[k] + beta * p[k]);
            }
            matvec(h, &m, &p, rd, &mut q);
            let pq = dot(&p, &q);
            // Written to reject NaN too.
            if pq.is_nan() || pq <= 0.0 || total >= MAX_ITERS {
                return None;
            }
            let alpha = rho / pq;
            for k in 0..n {
                x[k] = rd.v(x[k] + alpha * p[k]);
                r[k] = rd.v(r[k] - alpha * q[k]);
                z[k] = rd.v(r[k] * minv[k]);
            }
            coarse(&r, &mut z);
            rho_prev = rho;
            total += 1;
        }
        y.iter_mut().zip(&x).for_each(|(y, x)| *y += rn * x);
        h.matvec(&y, &mut hy);
        for k in 0..n {
            rt[k] = b[k] - hy[k];
        }
        rn_prev = rn;
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scale: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(1);
    let names = args.get(2..).unwrap_or_default();
    let size = Size::from_scale(scale);
    let show = |v: Option<usize>| v.map_or("fail".to_string(), |i| i.to_string());
    println!("| case | DOFs | f64 | f32 matrix, f32 vectors | f32 matrix, f64 vectors | f64 matrix, f32 vectors | f32 off-diagonal + f64 diagonal blocks, f32 vectors | f32 difference form, f32 vectors | f64 + coarse | f32 + coarse | f32 diff + coarse |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for case in hard::suite(size) {
        if !names.is_empty() && !names.contains(&case.name) {
            continue;
        }
        let e = case.eliminated();
        let h = e.assemble();
        // Z: the d rigid translations in frame coordinates, masked; E = ZᵀĤZ.
        let d = h.dim;
        let zb: Vec<Vec<f64>> = (0..d)
            .map(|a| {
                let x: Vec<f64> = (0..h.ndof()).map(|k| f64::from(k % d == a)).collect();
                let mut y = vec![0.0; x.len()];
                e.frames.to_frame(&x, &mut y);
                e.frames.apply_mask(&mut y);
                y
            })
            .collect();
        let mut hz = vec![0.0; h.ndof()];
        let mut em = nalgebra::DMatrix::<f64>::zeros(d, d);
        for b in 0..d {
            h.matvec(&zb[b], &mut hz);
            for a in 0..d {
                em[(a, b)] = dot(&zb[a], &hz);
            }
        }
        let einv: Vec<f64> = match em.clone().try_inverse() {
            Some(m) => m.transpose().iter().copied().collect(),
            None => vec![0.0; d * d],
        };
        let acc32 = std::env::var_os("STICKSLIP_EMU_ACC32").is_some();
        let run_c = |matrix, vectors, diag64, diff, coarse| {
            show(solve(
                &h,
                &e.rhs,
                &zb,
                &einv,
                Rounding {
                    matrix,
                    vectors,
                    diag64,
                    diff,
                    coarse,
                    acc32,
                },
            ))
        };
        let run = |matrix, vectors, diag64, diff| run_c(matrix, vectors, diag64, diff, false);
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            case.name,
            e.rhs.len(),
            run(false, false, false, false),
            run(true, true, false, false),
            run(true, false, false, false),
            run(false, true, false, false),
            run(true, true, true, false),
            run(true, true, false, true),
            run_c(false, false, false, false, true),
            run_c(true, true, false, false, true),
            run_c(true, true, false, true, true)
        );
    }
}
