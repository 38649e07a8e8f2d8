"""Benchmark: stickslip.solve(..., solver="cg") against SciPy's conjugate gradients (Jacobi
preconditioner) and SciPy's sparse direct solver on one constrained system, in one run.

    python python/bench.py [--nodes 64000] [--system DIR] [--repeat 1] [--no-spsolve]

The system is `stickslip generate --dim 3 --nodes N` (seed 1, the realistic constraint
mix: a sticky face, a moved face, a tilted slip plane, line slips); it is generated with
the command line (`cargo run --release -- generate`) into target/python-bench/N unless
--system names a folder that holds H.mtx, g.mtx and bc.json.

SciPy does not know the constraints, so it gets the same eliminated system built here
with SciPy: per constrained node an orthonormal basis Q_i of its free directions and the
minimum-norm lift x_p,i; Z the block-diagonal basis (identity on free nodes); then
Ĥ = ZᵀHZ, b̂ = −Zᵀ(g + H x_p), Δx = x_p + Z y. Every answer is checked in that basis: its
relative residual ‖b̂ − Ĥy‖/‖b̂‖ and its distance to the direct solution.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

import numpy as np
import scipy
import scipy.io
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as spla

# The source package next to this script has no compiled module: import the installed one.
_HERE = pathlib.Path(__file__).resolve().parent
sys.path = [p for p in sys.path if pathlib.Path(p or ".").resolve() != _HERE]
import stickslip  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def generate(nodes: int) -> pathlib.Path:
    out = ROOT / "target" / "python-bench" / str(nodes)
    if not (out / "bc.json").exists():
        cmd = ["cargo", "run", "--release", "--quiet", "--", "generate", "--dim", "3",
               "--nodes", str(nodes), "--seed", "1", "--out-dir", str(out)]
        print("bench: " + " ".join(cmd), file=sys.stderr)
        subprocess.run(cmd, cwd=ROOT, check=True)
    return out


def node_rows(dim, c):
    """Rows a and values v (aᵀΔx_node = v) of a bc.json constraint."""
    kind = c["kind"]
    if kind == "sticky":
        return np.eye(dim), np.asarray(c.get("displacement", np.zeros(dim)), dtype=float)
    if kind == "plane":
        return np.asarray([c["normal"]], dtype=float), np.asarray([c.get("offset", 0.0)])
    if kind == "line":
        q = la.null_space(np.asarray([c["direction"]], dtype=float)).T
        return q, q @ np.asarray(c.get("offset", np.zeros(dim)), dtype=float)
    rows = np.asarray(c["rows"], dtype=float)
    return rows, np.asarray(c.get("values", np.zeros(len(rows))), dtype=float)


def eliminate(H, g, cs, dim):
    """Z (orthonormal free basis, block diagonal), x_p (lift), Ĥ = ZᵀHZ, b̂."""
    n = H.shape[0] // dim
    per_node = {}
    for c in cs:
        a, v = node_rows(dim, c)
        ra, rv = per_node.get(c["node"], (np.zeros((0, dim)), np.zeros(0)))
        per_node[c["node"]] = (np.vstack([ra, a]), np.concatenate([rv, v]))
    xp = np.zeros(dim * n)
    zr, zc, zv = [], [], []
    col = 0
    for i in range(n):
        if i in per_node:
            a, v = per_node[i]
            xp[dim * i: dim * i + dim] = np.linalg.lstsq(a, v, rcond=None)[0]
            q = la.null_space(a)
        else:
            q = np.eye(dim)
        for k in range(q.shape[1]):
            for r in range(dim):
                if q[r, k] != 0.0:
                    zr.append(dim * i + r)
                    zc.append(col)
                    zv.append(q[r, k])
            col += 1
    Z = sp.csr_matrix((zv, (zr, zc)), shape=(dim * n, col))
    Hh = (Z.T @ H @ Z).tocsr()
    b = -(Z.T @ (g + H @ xp))
    return Z, xp, Hh, b


def best_of(repeat, f, name=""):
    """The fastest of `repeat` runs of f: its seconds and its result."""
    best, out = None, None
    for _ in range(repeat):
        t = time.perf_counter()
        r = f()
        dt = time.perf_counter() - t
        if best is None or dt < best:
            best, out = dt, r
        print(f"bench: {name}: {dt:.2f} s", file=sys.stderr)
    return best, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", type=int, default=64000)
    ap.add_argument("--system", type=pathlib.Path)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--repeat", type=int, default=1, help="best of this many runs")
    ap.add_argument("--no-spsolve", action="store_true", help="skip SciPy's direct solve")
    ap.add_argument("--no-cholesky", action="store_true", help="skip stickslip's Cholesky")
    ap.add_argument("--gpu", action="store_true", help="also stickslip's GPU CG (mixed)")
    args = ap.parse_args()

    folder = args.system or generate(args.nodes)
    t = time.perf_counter()
    H = sp.csr_matrix(scipy.io.mmread(str(folder / "H.mtx")))
    g = np.asarray(scipy.io.mmread(str(folder / "g.mtx")), dtype=float).ravel()
    bc = json.loads((folder / "bc.json").read_text())
    dim = bc.get("dim", 3)
    cs = bc["constraints"]
    read_s = time.perf_counter() - t
    n = H.shape[0] // dim
    t = time.perf_counter()
    Z, xp, Hh, b = eliminate(H, g, cs, dim)
    elim_s = time.perf_counter() - t
    print(f"bench: {folder}: {n} nodes, {H.shape[0]} dofs, {H.nnz} stored entries, "
          f"{len(cs)} constraints, {Hh.shape[0]} free dofs; read {read_s:.1f} s, "
          f"SciPy elimination {elim_s:.1f} s", file=sys.stderr)

    def residual(y):
        return np.linalg.norm(b - Hh @ y) / np.linalg.norm(b)

    def y_of(dx):
        return Z.T @ (dx - xp)  # Z has orthonormal columns and dx − x_p lies in its range

    rows = []

    def ss(solver, **kw):
        sec, sol = best_of(
            args.repeat,
            lambda: stickslip.solve(H, g, cs, dim=dim, solver=solver, tol=args.tol, **kw),
            f"stickslip {solver} {kw}",
        )
        return sec, sol

    # stickslip's CPU solvers run on rayon's pool: RAYON_NUM_THREADS sets its size.
    threads = os.environ.get("RAYON_NUM_THREADS") or f"{os.cpu_count()} (all)"
    sec, sol = ss("cg")
    rows.append(("stickslip cg (Jacobi + aggregates coarse, f64)", sec, sol.info["seconds"]["solve"],
                 sol.info["iterations"], y_of(sol.dx), threads))
    sec, solj = ss("cg", coarse="none")
    rows.append(("stickslip cg (Jacobi, no coarse, f64)", sec, solj.info["seconds"]["solve"],
                 solj.info["iterations"], y_of(solj.dx), threads))
    chol = None
    if not args.no_cholesky:
        sec, chol = ss("cholesky")
        rows.append(("stickslip cholesky (faer)", sec, chol.info["seconds"]["solve"], None,
                     y_of(chol.dx), threads))
    if args.gpu:
        sec, gs = ss("gpu", precision="mixed")
        rows.append((f"stickslip gpu mixed ({gs.info['adapter']})", sec, gs.info["seconds"]["solve"],
                     gs.info["iterations"], y_of(gs.dx), "device"))

    diag = Hh.diagonal()
    M = sp.diags(1.0 / diag)
    iters = [0]

    def count(_):
        iters[0] += 1

    def scipy_cg():
        iters[0] = 0
        y, info = spla.cg(Hh, b, rtol=args.tol, atol=0.0, maxiter=100_000, M=M, callback=count)
        if info != 0:
            raise RuntimeError(f"scipy cg did not converge (info {info})")
        return y

    sec, y = best_of(args.repeat, scipy_cg, "scipy cg")
    rows.append(("scipy.sparse.linalg.cg (Jacobi)", sec, sec, iters[0], y, "1 (CSR matvec)"))
    direct = None
    if not args.no_spsolve:
        A = Hh.tocsc()
        sec, direct = best_of(args.repeat, lambda: spla.spsolve(A, b), "scipy spsolve")
        rows.append(("scipy.sparse.linalg.spsolve (SuperLU, COLAMD)", sec, sec, None, direct, "1"))
    if direct is not None:
        ref, ref_name = direct, "spsolve"
    elif chol is not None:
        ref, ref_name = y_of(chol.dx), "cholesky"
    else:
        # No direct solution: distances to SciPy's CG answer.
        ref, ref_name = y, "scipy cg"

    print()
    print(f"{n} nodes, 3D, {Hh.shape[0]} free dofs of {H.shape[0]}, tol {args.tol:g}; "
          f"{os.cpu_count()} CPUs ({platform.processor() or platform.machine()}), "
          f"Python {platform.python_version()}, NumPy {np.__version__}, SciPy {scipy.__version__}, "
          f"stickslip {stickslip.__version__}; best of {args.repeat}")
    print()
    print(f"| solver | wall s (call) | solve s | iterations | relative residual | ‖y − y_ref‖/‖y_ref‖ ({ref_name}) | threads |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for name, wall, solve_s, it, yv, threads in rows:
        err = np.linalg.norm(yv - ref) / np.linalg.norm(ref)
        its = "" if it is None else str(it)
        print(f"| {name} | {wall:.2f} | {solve_s:.2f} | {its} | {residual(yv):.2e} | {err:.1e} | {threads} |")
    print()
    print("wall s: the whole call from Python (for stickslip: array conversion, frames, "
          "elimination, solve, recovery; for SciPy: the solve of the system eliminated "
          "beforehand). solve s: stickslip's own solve stage (info['seconds']['solve']).")


if __name__ == "__main__":
    main()
