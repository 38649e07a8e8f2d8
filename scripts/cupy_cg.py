#!/usr/bin/env python3
"""Solve a system exported by `stickslip export` with CuPy's CG on the GPU.

    python3 scripts/cupy_cg.py EXPORT_DIR [--tol 1e-8] [--max-iters N] [--cpu]

Reads EXPORT_DIR/hhat.petsc and EXPORT_DIR/bhat.petsc (PETSc binary, as the export
writes them: big-endian 32-bit indices and f64 values), moves the CSR matrix to the GPU
and runs cupyx.scipy.sparse.linalg.cg with a Jacobi preconditioner (the inverse of the
diagonal, as a LinearOperator) to the relative residual --tol, in f64. This is the
GPU peer that `scripts/gpu-eval.sh` measures beside `stickslip solve --solver gpu`.
`--cpu` runs the same thing with NumPy/SciPy instead of CuPy (to check the script on a
machine without CUDA).

Prints one JSON line: rows, nnz, iterations, relative residual (recomputed in f64 after
the solve), setup seconds (host-to-device copy and preconditioner) and solve seconds.
"""
import argparse
import json
import pathlib
import sys
import time

import numpy as np

MAT_FILE_CLASSID = 1211216
VEC_FILE_CLASSID = 1211214


def read_petsc_mat(path):
    with open(path, "rb") as f:
        head = np.frombuffer(f.read(16), dtype=">i4")
        if head.size != 4 or head[0] != MAT_FILE_CLASSID:
            sys.exit(f"{path}: not a PETSc binary matrix (class id {head[:1]})")
        m, n, nz = (int(v) for v in head[1:])
        row_nnz = np.frombuffer(f.read(4 * m), dtype=">i4").astype(np.int64)
        cols = np.frombuffer(f.read(4 * nz), dtype=">i4").astype(np.int32)
        vals = np.frombuffer(f.read(8 * nz), dtype=">f8").astype(np.float64)
    if row_nnz.size != m or cols.size != nz or vals.size != nz:
        sys.exit(f"{path}: the file ends before its {nz} entries")
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(row_nnz, out=indptr[1:])
    return m, n, indptr, cols, vals


def read_petsc_vec(path):
    with open(path, "rb") as f:
        head = np.frombuffer(f.read(8), dtype=">i4")
        if head.size != 2 or head[0] != VEC_FILE_CLASSID:
            sys.exit(f"{path}: not a PETSc binary vector")
        v = np.frombuffer(f.read(8 * int(head[1])), dtype=">f8").astype(np.float64)
    if v.size != head[1]:
        sys.exit(f"{path}: the file ends before its {head[1]} entries")
    return v


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("export_dir", type=pathlib.Path)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--max-iters", type=int, default=100000)
    ap.add_argument("--cpu", action="store_true", help="NumPy/SciPy instead of CuPy")
    a = ap.parse_args()

    m, n, indptr, cols, vals = read_petsc_mat(a.export_dir / "hhat.petsc")
    b = read_petsc_vec(a.export_dir / "bhat.petsc")
    if m != n or b.size != m:
        sys.exit(f"{a.export_dir}: matrix {m}x{n} and vector {b.size} do not match")

    if a.cpu:
        import scipy.sparse as sp
        import scipy.sparse.linalg as spla

        xp, sparse, linalg, sync, backend = np, sp, spla, (lambda: None), "scipy"
    else:
        import cupy as cp
        import cupyx.scipy.sparse as csp
        import cupyx.scipy.sparse.linalg as cspla

        xp, sparse, linalg, backend = cp, csp, cspla, "cupy"

        def sync():
            cp.cuda.Device().synchronize()

    t0 = time.perf_counter()
    A = sparse.csr_matrix(
        (xp.asarray(vals), xp.asarray(cols), xp.asarray(indptr.astype(np.int32))), shape=(m, n)
    )
    rhs = xp.asarray(b)
    d = A.diagonal()
    inv_d = 1.0 / d
    M = linalg.LinearOperator((m, m), matvec=lambda r: inv_d * r, dtype=np.float64)
    sync()
    setup = time.perf_counter() - t0

    iters = [0]

    def count(_):
        iters[0] += 1

    t1 = time.perf_counter()
    kw = dict(maxiter=a.max_iters, M=M, callback=count, atol=0.0)
    try:
        x, info = linalg.cg(A, rhs, rtol=a.tol, **kw)
    except TypeError:
        # CuPy 13 and older (and SciPy before 1.12) call the relative tolerance `tol`.
        x, info = linalg.cg(A, rhs, tol=a.tol, **kw)
    sync()
    solve = time.perf_counter() - t1
    r = rhs - A @ x
    rel = float(xp.linalg.norm(r) / xp.linalg.norm(rhs))
    print(
        json.dumps(
            {
                "backend": backend,
                "rows": m,
                "nnz": int(vals.size),
                "tol": a.tol,
                "converged": info == 0,
                "iterations": iters[0],
                "relative_residual": rel,
                "setup_seconds": setup,
                "solve_seconds": solve,
                "seconds_per_iteration": solve / max(iters[0], 1),
            }
        )
    )


if __name__ == "__main__":
    main()
