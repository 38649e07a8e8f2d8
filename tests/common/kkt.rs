//! The constrained problem solved directly: the dense KKT system
//! [H Bᵀ; B 0][Δx; λ] = [−g; p] by an SVD pseudo-inverse (singular where rows are
//! redundant; Δx and Bᵀλ are still unique), the reference the elimination is checked with.

use nalgebra::{DMatrix, DVector};
use stickslip::core::constraints::{node_rows, Constraint};

/// The global B (rows as given, not normalized) and p.
pub fn global_b(dim: usize, n: usize, cs: &[Constraint]) -> (DMatrix<f64>, DVector<f64>) {
    let mut rows = Vec::new();
    for c in cs {
        let (r, v) = node_rows(dim, c);
        for (row, val) in r.into_iter().zip(v) {
            rows.push((c.node, row, val));
        }
    }
    let mut b = DMatrix::zeros(rows.len(), dim * n);
    let mut p = DVector::zeros(rows.len());
    for (k, (node, row, val)) in rows.into_iter().enumerate() {
        for a in 0..dim {
            b[(k, node * dim + a)] = row[a];
        }
        p[k] = val;
    }
    (b, p)
}

pub struct Kkt {
    pub dx: DVector<f64>,
    pub bt_lambda: DVector<f64>,
}

pub fn dense_kkt(h: &DMatrix<f64>, g: &[f64], b: &DMatrix<f64>, p: &DVector<f64>) -> Kkt {
    let nd = h.nrows();
    let m = b.nrows();
    let mut k = DMatrix::zeros(nd + m, nd + m);
    k.view_mut((0, 0), (nd, nd)).copy_from(h);
    k.view_mut((0, nd), (nd, m)).copy_from(&b.transpose());
    k.view_mut((nd, 0), (m, nd)).copy_from(b);
    let mut rhs = DVector::zeros(nd + m);
    for i in 0..nd {
        rhs[i] = -g[i];
    }
    for i in 0..m {
        rhs[nd + i] = p[i];
    }
    // Pseudo-inverse through faer's SVD (accurate on rank-deficient matrices, which
    // nalgebra 0.34's SVD is not always: see constraints.rs).
    let nk = nd + m;
    let kf = faer::Mat::<f64>::from_fn(nk, nk, |i, j| k[(i, j)]);
    let svd = kf.svd().expect("SVD");
    let (u, sv, v) = (svd.U(), svd.S(), svd.V());
    let smax = (0..nk).map(|j| sv[j]).fold(0.0f64, f64::max);
    let mut sol = DVector::zeros(nk);
    for j in 0..nk {
        if sv[j] > 1e-12 * smax {
            let c: f64 = (0..nk).map(|i| u[(i, j)] * rhs[i]).sum::<f64>() / sv[j];
            for i in 0..nk {
                sol[i] += c * v[(i, j)];
            }
        }
    }
    let dx = sol.rows(0, nd).into_owned();
    let lambda = sol.rows(nd, m).into_owned();
    Kkt {
        bt_lambda: b.transpose() * lambda,
        dx,
    }
}
