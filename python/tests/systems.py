"""Seeded random constrained systems and their dense KKT solution, for the tests."""

from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.linalg as la
import scipy.sparse as sp

import stickslip


def random_system(dim: int, n: int, seed: int, mass: float = 1.0):
    """H (CSR, SPD), g: springs with random SPD d×d stiffness blocks (eigenvalues in
    [0.1, 1.1]) on a chain plus random extra edges, and a mass term `mass`·I. κ(H) is
    6-9 with unit mass and 600-850 with mass 0.01 on the sizes the tests use."""
    rng = np.random.default_rng(seed)
    edges = [(i, i + 1) for i in range(n - 1)]
    for _ in range(n):
        a, b = rng.integers(0, n, 2)
        if a != b:
            edges.append((int(min(a, b)), int(max(a, b))))
    rows, cols, vals = [], [], []

    def put(i, j, block):
        for r in range(dim):
            for c in range(dim):
                rows.append(dim * i + r)
                cols.append(dim * j + c)
                vals.append(block[r, c])

    for i, j in edges:
        a = rng.standard_normal((dim, dim))
        k = 0.1 * np.eye(dim) + a @ a.T / (a @ a.T).trace()
        put(i, i, k)
        put(j, j, k)
        put(i, j, -k)
        put(j, i, -k)
    for i in range(n):
        put(i, i, mass * np.eye(dim))
    nd = dim * n
    # COO → CSR sums the duplicate entries of shared nodes.
    H = sp.coo_matrix((vals, (rows, cols)), shape=(nd, nd)).tocsr()
    g = rng.standard_normal(nd)
    return H, g


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def every_kind(dim: int, n: int, seed: int):
    """One constraint of every kind and variant on distinct random nodes, and a node with
    two planes (they combine by rank)."""
    rng = np.random.default_rng(1000 + seed)
    nodes = [int(x) for x in rng.choice(n, 8, replace=False)]
    r = lambda: rng.standard_normal(dim)  # noqa: E731
    cs = [
        {"node": nodes[0], "kind": "sticky"},
        {"node": nodes[1], "kind": "sticky", "displacement": list(0.1 * r())},
        {"node": nodes[2], "kind": "plane", "normal": list(r())},
        {"node": nodes[3], "kind": "plane", "normal": list(r()), "offset": 0.05},
        {"node": nodes[4], "kind": "line", "direction": list(r())},
        {"node": nodes[5], "kind": "line", "direction": list(r()), "offset": list(0.1 * r())},
        {"node": nodes[6], "kind": "rows", "rows": [list(r())], "values": [0.02]},
    ]
    if dim == 3:
        cs.append({"node": nodes[7], "kind": "plane", "normal": [0.0, 0.0, 1.0]})
        cs.append({"node": nodes[7], "kind": "plane", "normal": [1.0, 1.0, 0.0], "offset": -0.01})
    else:
        cs.append({"node": nodes[7], "kind": "rows", "rows": [[1.0, 2.0]], "values": [0.03]})
    return cs


def node_rows(dim: int, c: dict):
    """The constraint's rows a and values v (aᵀΔx_node = v), as the bc.json form defines
    them: sticky → identity rows; plane → its normal as given; line → an orthonormal
    basis of the directions normal to it; rows → as given."""
    kind = c["kind"]
    if kind == "sticky":
        d = c.get("displacement", np.zeros(dim))
        return np.eye(dim), np.asarray(d, dtype=float)
    if kind == "plane":
        return np.asarray([c["normal"]], dtype=float), np.asarray([c.get("offset", 0.0)])
    if kind == "line":
        q = la.null_space(np.asarray([c["direction"]], dtype=float)).T
        off = np.asarray(c.get("offset", np.zeros(dim)), dtype=float)
        return q, q @ off
    return np.asarray(c["rows"], dtype=float), np.asarray(c.get("values", np.zeros(len(c["rows"]))), dtype=float)


def global_form(dim: int, n: int, cs):
    """B (one row per constrained direction, each on one node) and p."""
    rows, cols, vals, p = [], [], [], []
    for c in cs:
        a, v = node_rows(dim, c)
        for row, val in zip(a, v):
            k = len(p)
            for j in range(dim):
                if row[j] != 0.0:
                    rows.append(k)
                    cols.append(dim * c["node"] + j)
                    vals.append(row[j])
            p.append(val)
    B = sp.csr_matrix((vals, (rows, cols)), shape=(len(p), dim * n))
    return B, np.asarray(p)


def kkt(H, g, B, p):
    """Δx and the reactions of min ½ΔxᵀHΔx + gᵀΔx s.t. BΔx = p, from the dense KKT
    system [H Bᵀ; B 0][Δx; λ] = [−g; p] (LU with partial pivoting, f64)."""
    Hd = H.toarray()
    Bd = B.toarray()
    m, nd = Bd.shape
    K = np.block([[Hd, Bd.T], [Bd, np.zeros((m, m))]])
    sol = np.linalg.solve(K, np.concatenate([-g, p]))
    dx = sol[:nd]
    return dx, -(Hd @ dx + g)


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


REQUIRE_GPU = os.environ.get("STICKSLIP_REQUIRE_GPU") == "1"
_gpu_checked = {}


def gpu_or_skip(precision: str):
    """Skips (loudly, in the -ra summary) when the GPU cannot run `precision` here;
    fails instead when STICKSLIP_REQUIRE_GPU=1."""
    if precision not in _gpu_checked:
        try:
            stickslip.Solver(solver="gpu", precision=precision)
            _gpu_checked[precision] = None
        except stickslip.DeviceError as e:
            _gpu_checked[precision] = str(e)
    why = _gpu_checked[precision]
    if why is not None:
        msg = f"GPU {precision} unavailable: {why}"
        if REQUIRE_GPU:
            pytest.fail(f"{msg} (STICKSLIP_REQUIRE_GPU=1)")
        pytest.skip(f"{msg}; set STICKSLIP_REQUIRE_GPU=1 to fail instead")
