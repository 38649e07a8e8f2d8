#!/usr/bin/env python3
"""Captured Newton systems solved by stickslip and by PyAMG, side by side.

    scripts/pyamg_compare.py DIR [--stickslip BIN] [--tol 1e-6] [--solver cg]
                                 [--preconditioner jacobi] [--coarse aggregates]

DIR holds systems written by `stickslip run --dump-systems` (every folder with H.mtx,
g.mtx, bc.json and x.mtx, at any depth). For each one, on this machine, in one run:

- stickslip: `stickslip solve` with the given solver to relative residual `--tol`; its
  report's setup and solve seconds (reading and writing files excluded) and iterations.
- PyAMG: smoothed aggregation (`pyamg.smoothed_aggregation_solver`, CG acceleration) on
  the same eliminated system Ĥ y = b̂ that stickslip solves (written by `stickslip export`,
  in the nodes' frames), with the rigid-body modes of the dumped positions as the
  near-nullspace, rotated into the same node frames and with the constrained components
  zeroed; stopped at ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol. Setup is the hierarchy's construction, solve
  the accelerated cycles.

Prints one JSON line per system:
{"system": ..., "nodes": ..., "stickslip": {"setup_s", "solve_s", "iterations",
 "relative_residual"}, "pyamg": {...the same keys}}. Needs numpy, scipy and pyamg.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import scipy.io
import scipy.sparse as sp

try:
    import pyamg
except ImportError:  # pragma: no cover - said in one line
    sys.exit("error: pyamg_compare.py needs PyAMG (pip install pyamg)")


def systems(root):
    """Folders under root holding a dumped system, in natural order."""
    found = []
    for d, _, files in os.walk(root, followlinks=True):
        if {"H.mtx", "g.mtx", "bc.json", "x.mtx"} <= set(files):
            found.append(d)

    def key(p):
        parts, num, text = [], "", ""
        for c in p:
            if c.isdigit():
                num += c
            else:
                if num:
                    parts.append((text, int(num)))
                    text, num = "", ""
                text += c
        parts.append((text, int(num) if num else 0))
        return parts

    return sorted(found, key=key)


def vector(path):
    return np.asarray(scipy.io.mmread(path)).ravel()


def run(cmd):
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit("error: %s failed: %s" % (" ".join(cmd[:2]), p.stderr.strip()))


def rigid_modes(x, dim, layout):
    """Translations and rotations of the positions x, in the node frames of layout,
    constrained components zeroed: the near-nullspace of Ĥ's elastic part."""
    n = layout["n_nodes"]
    p = x.reshape(n, dim) - x.reshape(n, dim).mean(axis=0)
    modes = []
    for a in range(dim):
        m = np.zeros((n, dim))
        m[:, a] = 1.0
        modes.append(m)
    if dim == 2:
        modes.append(np.stack([-p[:, 1], p[:, 0]], axis=1))
    else:
        for a in range(3):
            w = np.zeros(3)
            w[a] = 1.0
            modes.append(np.cross(w, p))
    rot = dict(zip(layout["rot_nodes"], np.reshape(layout["rotations"], (-1, dim, dim))))
    mask = np.array(layout["mask"], dtype=np.uint32)
    out = []
    for m in modes:
        y = m.copy()
        for i, v in rot.items():
            y[i] = v.T @ m[i]  # V_i's columns are the frame basis: y = Vᵀx
        for a in range(dim):
            y[(mask >> a) & 1 == 1, a] = 0.0
        out.append(y.ravel())
    return np.stack(out, axis=1)


def compare(system, args, work):
    h, g, bc, xpath = (os.path.join(system, f) for f in ("H.mtx", "g.mtx", "bc.json", "x.mtx"))
    report = os.path.join(work, "report.json")
    run([
        args.stickslip, "solve", "--hessian", h, "--gradient", g, "--constraints", bc,
        "--solver", args.solver, "--tol", str(args.tol), "--preconditioner", args.preconditioner,
        "--coarse", args.coarse, "--out", os.path.join(work, "dx.mtx"), "--report", report,
        "--quiet",
    ])
    with open(report) as f:
        r = json.load(f)
    ours = {
        "setup_s": r["seconds"]["setup"],
        "solve_s": r["seconds"]["solve"],
        "iterations": r["iterations"],
        "relative_residual": r["relative_residual"],
    }

    exp = os.path.join(work, "export")
    run([
        args.stickslip, "export", "--hessian", h, "--gradient", g, "--constraints", bc,
        "--out-dir", exp, "--overwrite", "--quiet",
    ])
    with open(os.path.join(exp, "layout.json")) as f:
        layout = json.load(f)
    a = sp.csr_matrix(scipy.io.mmread(os.path.join(exp, "hhat.mtx")))
    b = vector(os.path.join(exp, "bhat.mtx"))
    modes = rigid_modes(vector(xpath), layout["dim"], layout)
    t0 = time.perf_counter()
    ml = pyamg.smoothed_aggregation_solver(a, B=modes, symmetry="symmetric")
    t1 = time.perf_counter()
    residuals = []
    y = ml.solve(b, tol=args.tol, accel="cg", maxiter=10000, residuals=residuals)
    t2 = time.perf_counter()
    bnorm = np.linalg.norm(b)
    theirs = {
        "setup_s": t1 - t0,
        "solve_s": t2 - t1,
        "iterations": len(residuals) - 1,
        "relative_residual": float(np.linalg.norm(b - a @ y) / bnorm) if bnorm > 0 else 0.0,
    }
    return {
        "system": os.path.relpath(system, args.dir),
        "nodes": layout["n_nodes"],
        "stickslip": ours,
        "pyamg": theirs,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir")
    ap.add_argument("--stickslip", default="stickslip", help="the stickslip binary")
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--solver", default="cg")
    ap.add_argument("--preconditioner", default="jacobi")
    ap.add_argument("--coarse", default="aggregates")
    args = ap.parse_args()
    found = systems(args.dir)
    if not found:
        sys.exit("error: %s: no system (a folder with H.mtx, g.mtx, bc.json and x.mtx)" % args.dir)
    with tempfile.TemporaryDirectory() as work:
        for s in found:
            print(json.dumps(compare(s, args, work)), flush=True)


if __name__ == "__main__":
    main()
