// Per-element (and per-node) energies, gradients and Hessians of the incremental potential
// (src/sim/energy), one invocation per element or node, written to per-element arrays that a
// device assembly scatters later (src/sim/device/elements.rs has the layouts):
//   energy[e], gradient[e·nl + a·D + c], hessian[e·nl² + (a·D + c)·nl + b·D + k],
// nl = (nodes per element)·D, node-major and row-major like the CPU's element buffers.
//
// - neohookean_elements: neo-Hookean triangles (D = 2) or tetrahedra (D = 3), per element
//   the classical law μ/2 (I_C − D) − μ ln J + λ/2 (ln J)² (flags[e] = 1 where J ≤ 0, its
//   energy being +∞ there) or the stable law of Smith, de Goes, Kim (2018); the Hessian is
//   (∂F/∂x)ᵀ proj(∂²Ψ/∂F²) (∂F/∂x), proj through the analytic eigensystem of ∂²Ψ/∂F²
//   (Smith, de Goes, Kim 2019) on a signed SVD of F (src/sim/energy/eigensystem.rs).
// - spring_elements: k/(2 l₀)(l − l₀)², transverse stiffness clamped at zero.
// - inertia_nodes, gravity_nodes, barrier_nodes: per node; gravity has no Hessian.
// `params.project` = 0 keeps every eigenvalue (the unprojected Hessian, for tests).
// Vulkan's log is f32-only: logarithms are computed in `real` (ln in shaders/common.wgsl, ln1p
// here).

override D: u32 = 3u;
// Unit roundoff of `real` (2^-52 for f64, 2^-23 for f32; both exact in f32), set per
// pipeline: the Jacobi sweeps stop at it.
override EPS: f32 = 2.220446049250313e-16;

// Mirrors `ElementParams` in src/sim/device/elements.rs (eight u32, 32 bytes, size-asserted there).
struct ElementParams {
    // Elements or nodes of the dispatch.
    count: u32,
    // Nonzero: clamp negative eigenvalues (PSD projection).
    project: u32,
    // Half-spaces in `consts` (barrier only).
    n_planes: u32,
    // Nonzero: energies (and barrier flags) only, gradients and Hessians left unwritten.
    energy_only: u32,
    // Node kernels: the mesh node of item 0. A node term too large for one storage binding
    // runs in chunks of consecutive nodes, each writing its own outputs from index 0 while
    // reading the positions and node data of the whole mesh. Element kernels: unused (their
    // chunks carry their own node indices and rest data).
    first: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: ElementParams;
// Positions, node-major (node i at i·D .. i·D + D).
@group(0) @binding(1) var<storage, read> x: array<real>;
// Element-to-node indices, nodes per element each.
@group(0) @binding(2) var<storage, read> nodes: array<u32>;
// Per element: neo-Hookean (Dm⁻¹ row-major D×D, rest volume, μ, λ, law: 1 classical,
// 0 stable), springs (l₀, k).
// Per node (node kernels): (lumped mass, contact weight), for every node of the mesh.
@group(0) @binding(3) var<storage, read> rest: array<real>;
// Gravity (3 entries), then per half-space (normal xyz, offset, d̂, κ).
@group(0) @binding(4) var<storage, read> consts: array<real>;
// The inertia target x̃, node-major.
@group(0) @binding(5) var<storage, read> x_tilde: array<real>;
@group(0) @binding(6) var<storage, read_write> energy: array<real>;
@group(0) @binding(7) var<storage, read_write> gradient: array<real>;
@group(0) @binding(8) var<storage, read_write> hessian: array<real>;
// Barrier: 1 where a weighted node touches or crosses a half-space; classical neo-Hookean
// elements: 1 where J ≤ 0 (energy +∞ there; WGSL has no portable infinity, so the host
// reads this instead).
@group(0) @binding(9) var<storage, read_write> flags: array<u32>;

// ln(1 + x) for x > −1, accurate relative to the result also for small x.
fn ln1p(x: real) -> real {
    if (x > real(-0.29) && x < real(0.41)) {
        return ln_series(x / (real(2.0) + x));
    }
    return ln(real(1.0) + x);
}

// tan θ of the Jacobi rotation with cot 2θ = zeta, |θ| ≤ π/4 (the smaller root); for
// |zeta| beyond 1/√EPS, 1/(2 zeta) is exact to rounding and zeta² cannot overflow.
fn jacobi_tan(zeta: real) -> real {
    let az = abs(zeta);
    let sg = select(real(-1.0), real(1.0), zeta >= real(0.0));
    if (az * az * real(EPS) > real(1.0)) {
        return real(0.5) / zeta;
    }
    return sg / (az + sqrt(real(1.0) + az * az));
}

// F = U diag(s) Vᵀ, U and V rotations (row-major D×D), |s| descending, the last carrying
// the sign of det F.
struct Svd {
    u: array<real, 9>,
    s: array<real, 3>,
    v: array<real, 9>,
}

// One-sided (Hestenes) Jacobi: right rotations orthogonalize the columns of B = F V to
// working precision (each σ then has an absolute error of a few ε‖F‖, like a backward-stable
// SVD), the columns are sorted by length, U's first columns are the normalized columns and
// the last is the cross product (D = 3) or perpendicular (D = 2), so U is a rotation and
// the last σ = uᵀ(F v) takes the sign of det F.
fn signed_svd(f: array<real, 9>) -> Svd {
    var b = f;
    var v = array<real, 9>();
    for (var k = 0u; k < D; k++) {
        v[k * D + k] = real(1.0);
    }
    let eps = real(EPS);
    for (var sweep = 0u; sweep < 40u; sweep++) {
        var rotated = false;
        for (var p = 0u; p + 1u < D; p++) {
            for (var q = p + 1u; q < D; q++) {
                var al = real(0.0);
                var be = real(0.0);
                var ga = real(0.0);
                for (var r = 0u; r < D; r++) {
                    al += b[r * D + p] * b[r * D + p];
                    be += b[r * D + q] * b[r * D + q];
                    ga += b[r * D + p] * b[r * D + q];
                }
                if (ga != real(0.0) && abs(ga) > eps * sqrt(al) * sqrt(be)) {
                    rotated = true;
                    let t = jacobi_tan((be - al) / (real(2.0) * ga));
                    let c = real(1.0) / sqrt(real(1.0) + t * t);
                    let s = c * t;
                    for (var r = 0u; r < D; r++) {
                        let bp = b[r * D + p];
                        let bq = b[r * D + q];
                        b[r * D + p] = c * bp - s * bq;
                        b[r * D + q] = s * bp + c * bq;
                        let vp = v[r * D + p];
                        let vq = v[r * D + q];
                        v[r * D + p] = c * vp - s * vq;
                        v[r * D + q] = s * vp + c * vq;
                    }
                }
            }
        }
        if (!rotated) {
            break;
        }
    }
    // Sort the columns by length, descending; an odd permutation flips det V, undone by
    // negating the last column of V and B.
    var len = array<real, 3>();
    for (var k = 0u; k < D; k++) {
        for (var r = 0u; r < D; r++) {
            len[k] += b[r * D + k] * b[r * D + k];
        }
    }
    var odd = false;
    for (var sweep = 0u; sweep + 1u < D; sweep++) {
        for (var k = 0u; k + 1u < D; k++) {
            if (len[k] < len[k + 1u]) {
                let l = len[k];
                len[k] = len[k + 1u];
                len[k + 1u] = l;
                for (var r = 0u; r < D; r++) {
                    let tb = b[r * D + k];
                    b[r * D + k] = b[r * D + k + 1u];
                    b[r * D + k + 1u] = tb;
                    let tv = v[r * D + k];
                    v[r * D + k] = v[r * D + k + 1u];
                    v[r * D + k + 1u] = tv;
                }
                odd = !odd;
            }
        }
    }
    if (odd) {
        for (var r = 0u; r < D; r++) {
            b[r * D + D - 1u] = -b[r * D + D - 1u];
            v[r * D + D - 1u] = -v[r * D + D - 1u];
        }
    }
    var out: Svd;
    out.v = v;
    let n0 = sqrt(len[0]);
    if (n0 == real(0.0)) {
        for (var k = 0u; k < D; k++) {
            out.u[k * D + k] = real(1.0);
        }
        return out;
    }
    var u0 = array<real, 3>();
    for (var r = 0u; r < D; r++) {
        u0[r] = b[r * D] / n0;
    }
    out.s[0] = n0;
    var u1 = array<real, 3>();
    if (D == 2u) {
        u1[0] = -u0[1];
        u1[1] = u0[0];
    } else {
        // Gram–Schmidt of the second column against the first (orthogonal to rounding
        // already; this makes U orthonormal to rounding whatever the column lengths).
        var dot = real(0.0);
        for (var r = 0u; r < 3u; r++) {
            dot += u0[r] * b[r * 3u + 1u];
        }
        var w = array<real, 3>();
        var nw = real(0.0);
        for (var r = 0u; r < 3u; r++) {
            w[r] = b[r * 3u + 1u] - dot * u0[r];
            nw += w[r] * w[r];
        }
        if (nw == real(0.0)) {
            // Rank one: any unit vector perpendicular to u0 (via the axis least aligned
            // with it).
            var k = 0u;
            for (var a = 1u; a < 3u; a++) {
                if (abs(u0[a]) < abs(u0[k])) {
                    k = a;
                }
            }
            nw = real(0.0);
            for (var r = 0u; r < 3u; r++) {
                w[r] = select(real(0.0), real(1.0), r == k) - u0[k] * u0[r];
                nw += w[r] * w[r];
            }
        }
        nw = sqrt(nw);
        for (var r = 0u; r < 3u; r++) {
            u1[r] = w[r] / nw;
        }
    }
    for (var r = 0u; r < D; r++) {
        out.u[r * D] = u0[r];
        out.u[r * D + 1u] = u1[r];
        out.s[1] += u1[r] * b[r * D + 1u];
    }
    if (D == 3u) {
        let u2 = array<real, 3>(
            u0[1] * u1[2] - u0[2] * u1[1],
            u0[2] * u1[0] - u0[0] * u1[2],
            u0[0] * u1[1] - u0[1] * u1[0],
        );
        for (var r = 0u; r < 3u; r++) {
            out.u[r * 3u + 2u] = u2[r];
            out.s[2] += u2[r] * b[r * 3u + 2u];
        }
    }
    return out;
}

// Eigenvalues and eigenvectors (vecs[r·D + k]: component r of vector k) of a symmetric
// D×D matrix, by cyclic Jacobi rotations until every off-diagonal entry is below EPS times
// its diagonal pair (its effect on Σ λ w wᵀ is then at rounding level).
struct Eigen {
    vals: array<real, 3>,
    vecs: array<real, 9>,
}

fn sym_eigen(a: array<real, 9>) -> Eigen {
    var m = a;
    var w = array<real, 9>();
    for (var k = 0u; k < D; k++) {
        w[k * D + k] = real(1.0);
    }
    let eps = real(EPS);
    for (var sweep = 0u; sweep < 40u; sweep++) {
        var rotated = false;
        for (var p = 0u; p + 1u < D; p++) {
            for (var q = p + 1u; q < D; q++) {
                let apq = m[p * D + q];
                let app = m[p * D + p];
                let aqq = m[q * D + q];
                if (apq != real(0.0) && abs(apq) > eps * (abs(app) + abs(aqq))) {
                    rotated = true;
                    let t = jacobi_tan((aqq - app) / (real(2.0) * apq));
                    let c = real(1.0) / sqrt(real(1.0) + t * t);
                    let s = c * t;
                    m[p * D + p] = app - t * apq;
                    m[q * D + q] = aqq + t * apq;
                    m[p * D + q] = real(0.0);
                    m[q * D + p] = real(0.0);
                    for (var r = 0u; r < D; r++) {
                        if (r != p && r != q) {
                            let arp = m[r * D + p];
                            let arq = m[r * D + q];
                            m[r * D + p] = c * arp - s * arq;
                            m[p * D + r] = c * arp - s * arq;
                            m[r * D + q] = s * arp + c * arq;
                            m[q * D + r] = s * arp + c * arq;
                        }
                        let wp = w[r * D + p];
                        let wq = w[r * D + q];
                        w[r * D + p] = c * wp - s * wq;
                        w[r * D + q] = s * wp + c * wq;
                    }
                }
            }
        }
        if (!rotated) {
            break;
        }
    }
    var out: Eigen;
    for (var k = 0u; k < D; k++) {
        out.vals[k] = m[k * D + k];
    }
    out.vecs = w;
    return out;
}

fn clamp_mode(l: real) -> real {
    if (params.project != 0u) {
        return max(l, real(0.0));
    }
    return l;
}

// h += l z zᵀ with z = (∂F/∂x)ᵀ vec(Q): z[a·D + c] = Σ_j Q[c][j] g[a][j].
fn add_mode(h: ptr<function, array<real, 144>>, l: real, q: array<real, 9>, g: array<real, 12>) {
    if (l == real(0.0)) {
        return;
    }
    let nl = (D + 1u) * D;
    var z = array<real, 12>();
    for (var a = 0u; a <= D; a++) {
        for (var c = 0u; c < D; c++) {
            var s = real(0.0);
            for (var j = 0u; j < D; j++) {
                s += q[c * D + j] * g[a * D + j];
            }
            z[a * D + c] = s;
        }
    }
    // Upper triangle only (mirrored when written), so the output is exactly symmetric.
    for (var r = 0u; r < nl; r++) {
        let lr = l * z[r];
        for (var k = r; k < nl; k++) {
            (*h)[r * nl + k] += lr * z[k];
        }
    }
}

fn neohookean_element(e: u32) {
    let nn = D + 1u;
    let nl = nn * D;
    let base = e * (D * D + 4u);
    // Shape-function gradients: node a ≥ 1 takes row a − 1 of Dm⁻¹, node 0 minus their sum.
    var g = array<real, 12>();
    for (var a = 1u; a <= D; a++) {
        for (var j = 0u; j < D; j++) {
            let v = rest[base + (a - 1u) * D + j];
            g[a * D + j] = v;
            g[j] -= v;
        }
    }
    let vol = rest[base + D * D];
    let mu = rest[base + D * D + 1u];
    let lam = rest[base + D * D + 2u];
    let classical = rest[base + D * D + 3u] != real(0.0);
    let dr = real(D);
    let alpha = real(1.0) + mu * dr / (lam * (dr + real(1.0)));
    // F = Ds Dm⁻¹ from edge vectors x_a − x_0 (not Σ x_a g_aᵀ): the subtraction comes
    // first, so positions far from the origin lose no digits of F.
    var f = array<real, 9>();
    let n0 = nodes[e * nn];
    for (var a = 1u; a <= D; a++) {
        let na = nodes[e * nn + a];
        for (var i = 0u; i < D; i++) {
            let dx = x[na * D + i] - x[n0 * D + i];
            for (var j = 0u; j < D; j++) {
                f[i * D + j] += dx * g[a * D + j];
            }
        }
    }
    // Ψ − Ψ(I) = μ/2 u − μ/2 ln(1 + u/(D+1)) + λ/2 (J − 1)(J + 1 − 2α), u = I_C − D: the
    // same energy as the CPU's, in a form that subtracts no O(1) terms near rest.
    var ic = real(0.0);
    var u = real(0.0);
    for (var i = 0u; i < D; i++) {
        for (var j = 0u; j < D; j++) {
            let v = f[i * D + j];
            ic += v * v;
            if (i == j) {
                u += (v - real(1.0)) * (v + real(1.0));
            } else {
                u += v * v;
            }
        }
    }
    let jac = det_of(f, D);
    if (classical) {
        // J ≤ 0: +∞, said by the flag; the outputs are zeros.
        let inverted = !(jac > real(0.0));
        flags[e] = select(0u, 1u, inverted);
        if (inverted) {
            energy[e] = real(0.0);
            if (params.energy_only == 0u) {
                for (var k = 0u; k < nl; k++) {
                    gradient[e * nl + k] = real(0.0);
                }
                for (var k = 0u; k < nl * nl; k++) {
                    hessian[e * nl * nl + k] = real(0.0);
                }
            }
            return;
        }
    }
    // Classical: Ψ = μ/2 u − μ ln J + λ/2 (ln J)², ln J = ln1p(J − 1).
    // (Only for the classical law: WGSL's select would evaluate ln1p for every element.)
    var lnj = real(0.0);
    if (classical) {
        lnj = ln1p(jac - real(1.0));
    }
    var psi = real(0.5) * mu * u - mu * lnj + real(0.5) * lam * lnj * lnj;
    if (!classical) {
        psi = real(0.5) * mu * u - real(0.5) * mu * ln1p(u / (dr + real(1.0)))
            + real(0.5) * lam * (jac - real(1.0)) * (jac + real(1.0) - real(2.0) * alpha);
    }
    energy[e] = vol * psi;
    if (params.energy_only != 0u) {
        return;
    }
    // P = s F + t cof(F): classical s = μ, t = (λ ln J − μ)/J; stable s = μ − μ/(I_C + 1),
    // t = λ (J − α).
    let cof = cofactor_of(f, D);
    var s = mu - mu / (ic + real(1.0));
    var t = lam * (jac - alpha);
    if (classical) {
        s = mu;
        t = (lam * lnj - mu) / jac;
    }
    for (var a = 0u; a < nn; a++) {
        for (var c = 0u; c < D; c++) {
            var acc_g = real(0.0);
            for (var j = 0u; j < D; j++) {
                acc_g += (s * f[c * D + j] + t * cof[c * D + j]) * g[a * D + j];
            }
            gradient[e * nl + a * D + c] = vol * acc_g;
        }
    }
    // ∂²Ψ/∂F² by its eigensystem at the signed singular values (see
    // NeoHookean::singular_value_hessian): scaling modes from the D×D block
    // A = q σσᵀ + w c cᵀ + s I + t E, twist and flip modes with eigenvalues s ± t σ_k.
    let svd = signed_svd(f);
    var sg = array<real, 3>(svd.s[0], svd.s[1], real(1.0));
    if (D == 3u) {
        sg[2] = svd.s[2];
    }
    var ics = real(0.0);
    var js = real(1.0);
    for (var k = 0u; k < D; k++) {
        ics += sg[k] * sg[k];
        js *= sg[k];
    }
    var ss = mu - mu / (ics + real(1.0));
    var qs = real(2.0) * mu / ((ics + real(1.0)) * (ics + real(1.0)));
    var ws = lam;
    var ts = lam * (js - alpha);
    if (classical) {
        // s = μ, q = 0, t = (λ ln J − μ)/J, w = dt/dJ = (λ (1 − ln J) + μ)/J², at the
        // singular values' J (positive here).
        let lns = ln1p(js - real(1.0));
        ss = mu;
        qs = real(0.0);
        ws = (lam * (real(1.0) - lns) + mu) / (js * js);
        ts = (lam * lns - mu) / js;
    }
    // others[k]: product of the singular values other than k; pair products other than
    // (a, b) are the third one (D = 3) or 1 (D = 2).
    var others = array<real, 3>();
    for (var k = 0u; k < D; k++) {
        var pr = real(1.0);
        for (var m = 0u; m < D; m++) {
            if (m != k) {
                pr *= sg[m];
            }
        }
        others[k] = pr;
    }
    var am = array<real, 9>();
    for (var a = 0u; a < D; a++) {
        for (var b = 0u; b < D; b++) {
            var v = qs * sg[a] * sg[b] + ws * others[a] * others[b];
            if (a == b) {
                v += ss;
            } else {
                v += ts * select(real(1.0), sg[3u - a - b], D == 3u);
            }
            am[a * D + b] = v;
        }
    }
    let eig = sym_eigen(am);
    var h = array<real, 144>();
    for (var k = 0u; k < D; k++) {
        var q = array<real, 9>();
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                var v = real(0.0);
                for (var a = 0u; a < D; a++) {
                    v += svd.u[r * D + a] * eig.vecs[a * D + k] * svd.v[c * D + a];
                }
                q[r * D + c] = v;
            }
        }
        add_mode(&h, clamp_mode(eig.vals[k]), q, g);
    }
    let r2 = real(0.70710678118654752440);
    let pairs = select(3u, 1u, D == 2u);
    for (var p = 0u; p < pairs; p++) {
        // Pairs (0, 1), (0, 2), (1, 2); the third index is 2, 1, 0.
        let i = select(0u, 1u, p == 2u);
        let j = select(1u, 2u, p > 0u);
        let kk = select(real(1.0), sg[2u - p], D == 3u);
        var tw = array<real, 9>();
        var fl = array<real, 9>();
        for (var r = 0u; r < D; r++) {
            for (var c = 0u; c < D; c++) {
                let uv_ij = svd.u[r * D + i] * svd.v[c * D + j];
                let uv_ji = svd.u[r * D + j] * svd.v[c * D + i];
                tw[r * D + c] = r2 * (uv_ij - uv_ji);
                fl[r * D + c] = r2 * (uv_ij + uv_ji);
            }
        }
        add_mode(&h, clamp_mode(ss + ts * kk), tw, g);
        add_mode(&h, clamp_mode(ss - ts * kk), fl, g);
    }
    for (var r = 0u; r < nl; r++) {
        for (var k = r; k < nl; k++) {
            let v = vol * h[r * nl + k];
            hessian[e * nl * nl + r * nl + k] = v;
            hessian[e * nl * nl + k * nl + r] = v;
        }
    }
}

fn spring_element(e: u32) {
    let i = nodes[2u * e];
    let j = nodes[2u * e + 1u];
    let l0 = rest[2u * e];
    let kk = rest[2u * e + 1u] / l0;
    var v = array<real, 3>();
    var l2 = real(0.0);
    for (var a = 0u; a < D; a++) {
        v[a] = x[j * D + a] - x[i * D + a];
        l2 += v[a] * v[a];
    }
    let l = sqrt(l2);
    energy[e] = real(0.5) * kk * (l - l0) * (l - l0);
    if (params.energy_only != 0u) {
        return;
    }
    var c = real(0.0);
    var tr = real(0.0);
    if (l > real(0.0)) {
        c = kk * (l - l0) / l;
        tr = (l - l0) / l;
    }
    if (params.project != 0u) {
        tr = max(tr, real(0.0));
    }
    let n = 2u * D;
    for (var a = 0u; a < D; a++) {
        gradient[e * n + a] = -c * v[a];
        gradient[e * n + D + a] = c * v[a];
        for (var b = 0u; b < D; b++) {
            var uu = real(0.0);
            if (l > real(0.0)) {
                uu = v[a] * v[b] / l2;
            }
            let kab = kk * (uu + tr * (select(real(0.0), real(1.0), a == b) - uu));
            let o = e * n * n;
            hessian[o + a * n + b] = kab;
            hessian[o + (D + a) * n + D + b] = kab;
            hessian[o + a * n + D + b] = -kab;
            hessian[o + (D + a) * n + b] = -kab;
        }
    }
}

// Node kernels: item i of the dispatch is mesh node g = first + i; inputs are indexed by
// g, outputs by i.
fn inertia_node(i: u32) {
    let g = params.first + i;
    let m = rest[2u * g];
    var en = real(0.0);
    for (var a = 0u; a < D; a++) {
        let d = x[g * D + a] - x_tilde[g * D + a];
        en += real(0.5) * m * d * d;
        if (params.energy_only == 0u) {
            gradient[i * D + a] = m * d;
            for (var b = 0u; b < D; b++) {
                hessian[(i * D + a) * D + b] = select(real(0.0), m, a == b);
            }
        }
    }
    energy[i] = en;
}

fn gravity_node(i: u32) {
    let g = params.first + i;
    let m = rest[2u * g];
    var en = real(0.0);
    for (var a = 0u; a < D; a++) {
        en += m * consts[a] * x[g * D + a];
        if (params.energy_only == 0u) {
            gradient[i * D + a] = -m * consts[a];
        }
    }
    energy[i] = -en;
}

fn barrier_node(i: u32) {
    let g = params.first + i;
    let w = rest[2u * g + 1u];
    var en = real(0.0);
    var gr = array<real, 3>();
    var he = array<real, 9>();
    var flag = 0u;
    if (w > real(0.0)) {
        for (var j = 0u; j < params.n_planes; j++) {
            let o = 3u + 6u * j;
            var dist = real(0.0);
            for (var a = 0u; a < D; a++) {
                dist += x[g * D + a] * consts[o + a];
            }
            dist -= consts[o + 3u];
            let dhat = consts[o + 4u];
            let kappa = consts[o + 5u];
            if (dist < dhat) {
                if (dist <= real(0.0)) {
                    flag = 1u;
                    continue;
                }
                let s = dist / dhat;
                let ls = ln(s);
                en += w * (dhat * real(0.5) * kappa * (s - real(1.0)) * ls);
                let gg = w * (real(0.5) * kappa * (ls + real(1.0) - real(1.0) / s));
                let hh = w * (real(0.5) * kappa * (real(1.0) / dist + dhat / (dist * dist)));
                // Upper triangle only (mirrored when written): a driver may contract
                // (a, b) and (b, a) differently, and the output must be exactly symmetric.
                for (var a = 0u; a < D; a++) {
                    gr[a] += gg * consts[o + a];
                    for (var b = a; b < D; b++) {
                        he[a * D + b] += hh * (consts[o + a] * consts[o + b]);
                    }
                }
            }
        }
    }
    energy[i] = en;
    flags[i] = flag;
    if (params.energy_only != 0u) {
        return;
    }
    for (var a = 0u; a < D; a++) {
        gradient[i * D + a] = gr[a];
        for (var b = 0u; b < D; b++) {
            hessian[(i * D + a) * D + b] = he[min(a, b) * D + max(a, b)];
        }
    }
}

// Grid-stride loops: the host caps the workgroups at the device's per-dimension limit.
@compute @workgroup_size(WG)
fn neohookean_elements(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var e = grid_index(gid, nwg); e < params.count; e += grid_stride(nwg)) {
        neohookean_element(e);
    }
}

@compute @workgroup_size(WG)
fn spring_elements(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var e = grid_index(gid, nwg); e < params.count; e += grid_stride(nwg)) {
        spring_element(e);
    }
}

@compute @workgroup_size(WG)
fn inertia_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        inertia_node(i);
    }
}

@compute @workgroup_size(WG)
fn gravity_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        gravity_node(i);
    }
}

@compute @workgroup_size(WG)
fn barrier_nodes(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    for (var i = grid_index(gid, nwg); i < params.count; i += grid_stride(nwg)) {
        barrier_node(i);
    }
}
