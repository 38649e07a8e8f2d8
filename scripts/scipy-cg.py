#!/usr/bin/env python3
"""Time per iteration of SciPy's Jacobi CG against stickslip's CPU CG on one system.

    python scripts/scipy-cg.py SYSTEM_DIR EXPORT_DIR [--stickslip BIN] [--rounds 3]
        [--tol 1e-8] [--coarse none,aggregates] [--threads N,N] [--json out.json]

SYSTEM_DIR holds H.mtx, g.mtx and bc.json (`stickslip generate`); EXPORT_DIR is what
`stickslip export` wrote from them: the eliminated system Ĥ y = b̂ in the node frames,
the very system stickslip's CG iterates on (constrained rows included, decoupled with
D = 1 and b̂ = 0 there). SciPy reads Ĥ from hhat.petsc (PETSc binary, the same f64
values as hhat.mtx; hhat.mtx through scipy.io.mmread when the binary is absent), builds
CSR and runs scipy.sparse.linalg.cg with M = diag(Ĥ)⁻¹ to ‖r‖ ≤ tol·‖b̂‖.

Each round runs, alternating, `stickslip solve --solver cg` once per coarse space (and
per `--threads` count given) and SciPy's CG once, so load on the machine falls on both alike. stickslip's time is the
report's `seconds.solve` (CG with its setup: preconditioner and coarse space), SciPy's
the cg() call alone. Prints one line per run and a summary table (medians and minima).
BLAS runs on one thread (OPENBLAS_NUM_THREADS=1 unless set: see below).
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

# SciPy's CG takes its dot products and vector updates from BLAS. Threaded OpenBLAS spins
# its threads between calls, which on a loaded 2-core machine made SciPy's CG 5× slower
# than on one thread (13.2 s against 2.2 s here), so BLAS runs on one thread unless the
# environment says otherwise. Set before NumPy loads BLAS.
for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import numpy as np
import scipy.io
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def read_petsc_mat(path):
    """A PETSc binary AIJ matrix (big-endian, 32-bit PetscInt) as CSR."""
    with open(path, "rb") as f:
        head = np.fromfile(f, dtype=">i4", count=4)
        if head.size != 4 or head[0] != 1211216:
            raise ValueError(f"{path}: not a PETSc binary matrix (class id {head[:1]})")
        m, n, nnz = (int(v) for v in head[1:])
        lens = np.fromfile(f, dtype=">i4", count=m)
        cols = np.fromfile(f, dtype=">i4", count=nnz)
        vals = np.fromfile(f, dtype=">f8", count=nnz)
    if lens.size != m or cols.size != nnz or vals.size != nnz:
        raise ValueError(f"{path}: truncated")
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(lens, out=indptr[1:])
    return sp.csr_matrix(
        (vals.astype(np.float64), cols.astype(np.int32), indptr), shape=(m, n)
    )


def read_petsc_vec(path):
    with open(path, "rb") as f:
        head = np.fromfile(f, dtype=">i4", count=2)
        if head.size != 2 or head[0] != 1211214:
            raise ValueError(f"{path}: not a PETSc binary vector")
        v = np.fromfile(f, dtype=">f8", count=int(head[1]))
    if v.size != head[1]:
        raise ValueError(f"{path}: truncated")
    return v.astype(np.float64)


def read_system(export_dir):
    hp = os.path.join(export_dir, "hhat.petsc")
    bp = os.path.join(export_dir, "bhat.petsc")
    if os.path.exists(hp) and os.path.exists(bp):
        return read_petsc_mat(hp), read_petsc_vec(bp)
    a = scipy.io.mmread(os.path.join(export_dir, "hhat.mtx")).tocsr()
    b = np.asarray(scipy.io.mmread(os.path.join(export_dir, "bhat.mtx"))).ravel()
    return a, b


def scipy_cg(a, b, m, tol):
    iters = [0]

    def count(_):
        iters[0] += 1

    t = time.perf_counter()
    y, info = spla.cg(a, b, rtol=tol, atol=0.0, maxiter=100_000, M=m, callback=count)
    sec = time.perf_counter() - t
    if info != 0:
        raise RuntimeError(f"scipy cg did not converge (info {info})")
    rel = np.linalg.norm(b - a @ y) / np.linalg.norm(b)
    return sec, iters[0], rel


def stickslip_cg(binary, system_dir, coarse, tol, threads, tmp):
    rep = os.path.join(tmp, "report.json")
    cmd = [
        binary, "--quiet", "solve",
        "--hessian", os.path.join(system_dir, "H.mtx"),
        "--gradient", os.path.join(system_dir, "g.mtx"),
        "--constraints", os.path.join(system_dir, "bc.json"),
        "--solver", "cg", "--coarse", coarse, "--tol", str(tol),
        "--out", os.path.join(tmp, "dx.mtx"), "--report", rep,
    ]
    if threads:
        cmd += ["--threads", str(threads)]
    subprocess.run(cmd, check=True)
    with open(rep) as f:
        r = json.load(f)
    return r["seconds"]["solve"], r["iterations"], r["relative_residual"], r.get("threads")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("system_dir")
    ap.add_argument("export_dir")
    ap.add_argument("--stickslip", default="target/release/stickslip")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--coarse", default="none,aggregates")
    ap.add_argument("--threads", default="0", help="stickslip --threads, comma-separated (0: its default)")
    ap.add_argument("--json", help="write every run here")
    args = ap.parse_args()

    t = time.perf_counter()
    a, b = read_system(args.export_dir)
    m = sp.diags(1.0 / a.diagonal()).tocsr()
    print(
        f"Ĥ: {a.shape[0]} rows, {a.nnz} stored entries (read in {time.perf_counter() - t:.1f} s); "
        f"numpy {np.__version__}, scipy {scipy.__version__}",
        flush=True,
    )
    coarses = [c for c in args.coarse.split(",") if c]
    counts = [int(t) for t in args.threads.split(",") if t]
    # One stickslip configuration per (coarse space, thread count).
    configs = [(c, t) for c in coarses for t in counts]

    def label(c, t):
        return f"stickslip --coarse {c}" + (f" --threads {t}" if t else "")

    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.rounds):
            for c, t in configs:
                sec, it, rel, th = stickslip_cg(args.stickslip, args.system_dir, c, args.tol, t, tmp)
                runs.append(dict(round=k, solver=label(c, t), seconds=sec, iterations=it, residual=rel, threads=th))
                print(f"round {k}: {label(c, t):<40} {sec:8.3f} s  {it:5d} it  {1e3 * sec / it:7.2f} ms/it  residual {rel:.2e}  threads {th}", flush=True)
            sec, it, rel = scipy_cg(a, b, m, args.tol)
            runs.append(dict(round=k, solver="scipy cg (Jacobi)", seconds=sec, iterations=it, residual=rel, threads=1))
            print(f"round {k}: {'scipy cg (Jacobi)':<40} {sec:8.3f} s  {it:5d} it  {1e3 * sec / it:7.2f} ms/it  residual {rel:.2e}", flush=True)

    print()
    print("| solver | iterations | solve s (median, min) | ms per iteration (median, min) | relative residual |")
    print("|---|---:|---:|---:|---:|")
    names = [label(c, t) for c, t in configs] + ["scipy cg (Jacobi)"]
    med = {}
    for name in names:
        rs = [r for r in runs if r["solver"] == name]
        secs = [r["seconds"] for r in rs]
        per = [1e3 * r["seconds"] / r["iterations"] for r in rs]
        med[name] = (statistics.median(secs), statistics.median(per))
        print(
            f"| {name} | {rs[0]['iterations']} | {statistics.median(secs):.3f}, {min(secs):.3f} | "
            f"{statistics.median(per):.2f}, {min(per):.2f} | {max(r['residual'] for r in rs):.2e} |"
        )
    sc = med["scipy cg (Jacobi)"]
    for name in names[:-1]:
        print(
            f"{name}: time per iteration {med[name][1] / sc[1]:.2f}× SciPy's, "
            f"solve {sc[0] / med[name][0]:.2f}× faster (medians)"
        )
    # Same round, same load: the ratio within each round.
    for name in names[:-1]:
        ratios = []
        for k in range(args.rounds):
            s = next(r for r in runs if r["round"] == k and r["solver"] == name)
            p = next(r for r in runs if r["round"] == k and r["solver"] == "scipy cg (Jacobi)")
            ratios.append((s["seconds"] / s["iterations"]) / (p["seconds"] / p["iterations"]))
        print(f"{name}: per-iteration ratio to SciPy by round: " + ", ".join(f"{x:.2f}" for x in ratios))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(runs, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
