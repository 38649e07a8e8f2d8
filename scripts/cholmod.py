#!/usr/bin/env python3
"""Factor a system exported by `stickslip export` with CHOLMOD, for comparison with
stickslip's Cholesky oracle on the SAME eliminated matrix.

    python scripts/cholmod.py EXPORT_DIR [--ordering default|amd|metis|nesdis|best]
                              [--repeat N] [--stickslip SYSTEM_DIR [--binary PATH]
                              [--stickslip-ordering auto|amd|nested-dissection]]

Reads EXPORT_DIR/hhat.petsc and bhat.petsc (PETSc binary, as `stickslip export` writes
them: Ĥ with the constrained diagonal, all of its stored entries), analyses, factors
(supernodal LLᵀ) and solves with scikit-sparse's CHOLMOD binding, and prints one JSON
line per run: seconds of analysis, factorization and solve, the factor's nonzeros and the
relative residual ‖b̂ − Ĥy‖/‖b̂‖.

Factor sizes: `factor_nnz_exact` counts the nonzeros of L (on and below the diagonal);
`factor_nnz_stored` the entries of CHOLMOD's supernodal L including the zeros that
supernode amalgamation stores. stickslip's report.json gives the same two counts
(`factor_nnz_exact`, and `factor_nnz` for faer's storage, which also holds the upper
triangle of each supernode's diagonal block).

With --stickslip SYSTEM_DIR (the H.mtx, g.mtx and bc.json the export was made from) the
script alternates, N times: `stickslip solve --solver cholesky` on that system, then
CHOLMOD on the export; both runs factor the same matrix on the same machine in turn,
so load from other processes falls on both. Each stickslip line carries its report's
symbolic, numeric and triangular seconds.

Needs NumPy, SciPy and scikit-sparse (`pip install "scikit-sparse<0.5"` builds against
SuiteSparse 5's CHOLMOD, Debian's libsuitesparse-dev).
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import scipy.sparse as sp

MAT_FILE_CLASSID = 1211216
VEC_FILE_CLASSID = 1211214


def read_petsc_mat(path):
    with open(path, "rb") as f:
        head = np.frombuffer(f.read(16), dtype=">i4")
        if head[0] != MAT_FILE_CLASSID:
            sys.exit(f"error: {path}: not a PETSc binary matrix (class id {head[0]})")
        m, n, nnz = (int(v) for v in head[1:])
        row_len = np.frombuffer(f.read(4 * m), dtype=">i4").astype(np.int64)
        cols = np.frombuffer(f.read(4 * nnz), dtype=">i4").astype(np.int32)
        vals = np.frombuffer(f.read(8 * nnz), dtype=">f8").astype(np.float64)
    if len(cols) != nnz or len(vals) != nnz or row_len.sum() != nnz:
        sys.exit(f"error: {path}: truncated ({nnz} entries declared)")
    indptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(row_len, out=indptr[1:])
    # Ĥ is symmetric: its CSR rows are its CSC columns.
    return sp.csc_matrix((vals, cols, indptr), shape=(m, n))


def read_petsc_vec(path):
    with open(path, "rb") as f:
        head = np.frombuffer(f.read(8), dtype=">i4")
        if head[0] != VEC_FILE_CLASSID:
            sys.exit(f"error: {path}: not a PETSc binary vector (class id {head[0]})")
        n = int(head[1])
        v = np.frombuffer(f.read(8 * n), dtype=">f8").astype(np.float64)
    if len(v) != n:
        sys.exit(f"error: {path}: truncated ({n} entries declared)")
    return v


def cholmod_run(cholmod, A, b, ordering, count):
    t = time.perf_counter()
    f = cholmod.analyze(A, mode="supernodal", ordering_method=ordering)
    analyze = time.perf_counter() - t
    t = time.perf_counter()
    f.cholesky_inplace(A)
    factor = time.perf_counter() - t
    t = time.perf_counter()
    y = f.solve_A(b)
    solve = time.perf_counter() - t
    out = {
        "solver": "cholmod",
        "ordering": ordering,
        "analyze_seconds": round(analyze, 3),
        "factor_seconds": round(factor, 3),
        "solve_seconds": round(solve, 3),
        "total_seconds": round(analyze + factor + solve, 3),
        "relative_residual": float(np.linalg.norm(b - A @ y) / np.linalg.norm(b)),
    }
    if count:
        # A simplicial copy of the supernodal factor, zeros of amalgamation included.
        L = f.L()
        out["factor_nnz_exact"] = int(np.count_nonzero(L.data))
        out["factor_nnz_stored"] = int(L.nnz)
        del L
    return out, y


def stickslip_run(binary, system, ordering):
    with tempfile.TemporaryDirectory() as tmp:
        report = os.path.join(tmp, "report.json")
        cmd = [
            binary, "--quiet", "solve", "--solver", "cholesky",
            "--hessian", os.path.join(system, "H.mtx"),
            "--gradient", os.path.join(system, "g.mtx"),
            "--constraints", os.path.join(system, "bc.json"),
            "--ordering", ordering,
            "--out", os.path.join(tmp, "dx.mtx"),
            "--report", report,
        ]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"error: {' '.join(cmd)}: {done.stderr.strip()}")
        with open(report) as f:
            r = json.load(f)
    s, c = r["seconds"], r["cholesky"]
    return {
        "solver": "stickslip",
        "ordering": c["ordering"],
        "analyze_seconds": round(s["symbolic"], 3),
        "factor_seconds": round(s["numeric"], 3),
        "solve_seconds": round(s["triangular"], 3),
        "total_seconds": round(s["symbolic"] + s["numeric"] + s["triangular"], 3),
        "relative_residual": r["relative_residual"],
        "factor_nnz_exact": c.get("factor_nnz_exact"),
        "factor_nnz_stored": c["factor_nnz"],
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export_dir")
    ap.add_argument("--ordering", default="default",
                    choices=["default", "amd", "metis", "nesdis", "best", "natural"],
                    help="CHOLMOD's ordering (default: CHOLMOD's own choice, AMD or METIS)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--stickslip", metavar="SYSTEM_DIR",
                    help="alternate with `stickslip solve` on H.mtx, g.mtx, bc.json here")
    ap.add_argument("--binary", default="target/release/stickslip")
    ap.add_argument("--stickslip-ordering", default="auto",
                    choices=["auto", "amd", "nested-dissection"])
    a = ap.parse_args()
    try:
        from sksparse import cholmod
    except ImportError as e:
        sys.exit(f"error: scikit-sparse is not installed ({e})")
    t = time.perf_counter()
    A = read_petsc_mat(os.path.join(a.export_dir, "hhat.petsc"))
    b = read_petsc_vec(os.path.join(a.export_dir, "bhat.petsc"))
    if A.shape[0] != A.shape[1] or len(b) != A.shape[0]:
        sys.exit(f"error: {a.export_dir}: Ĥ is {A.shape}, b̂ has {len(b)} rows")
    print(json.dumps({
        "matrix": os.path.join(a.export_dir, "hhat.petsc"),
        "dofs": A.shape[0],
        "lower_nnz": int((A.nnz + A.shape[0]) // 2),
        "read_seconds": round(time.perf_counter() - t, 3),
    }), flush=True)
    for k in range(a.repeat):
        if a.stickslip:
            print(json.dumps(stickslip_run(a.binary, a.stickslip, a.stickslip_ordering)),
                  flush=True)
        out, _ = cholmod_run(cholmod, A, b, a.ordering, count=(k == 0))
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
