"""stickslip.solve against a dense KKT solve done here with NumPy, on seeded random
systems with every constraint kind, for every solver and precision."""

import numpy as np
import pytest
import scipy.sparse as sp

import stickslip
from systems import every_kind, global_form, gpu_or_skip, kkt, random_system, rel

# (solver, precision, tol, bound on the relative error of Δx). CG stopped at relative
# residual tol is within κ(Ĥ)·tol of the truth, and κ(Ĥ) ≤ κ(H) here (D = I on the
# constrained components lies inside H's spectrum): κ(H) is 6-9 with unit mass and
# 600-850 with mass 0.01 (systems.random_system), so tol 1e-12 keeps f64 within 1e-9.
# f32 CG stops at tol 1e-6, near the f32 rounding floor of its residual; its bound is
# 1e-4 (measured errors: below 1e-6). Cholesky is direct (rounding only).
CASES = [
    ("cholesky", None, 1e-8, 1e-9),
    ("cg", None, 1e-12, 1e-9),
    ("gpu", "f64", 1e-12, 1e-9),
    ("gpu", "mixed", 1e-12, 1e-9),
    ("gpu", "f32", 1e-6, 1e-4),
]
# (dim, nodes, seed, mass)
SHAPES = [(2, 40, 1, 1.0), (2, 40, 2, 1.0), (3, 30, 3, 1.0), (3, 30, 4, 1.0), (2, 200, 5, 0.01), (3, 150, 6, 0.01)]


@pytest.mark.parametrize("dim,n,seed,mass", SHAPES)
@pytest.mark.parametrize("solver,precision,tol,bound", CASES)
def test_matches_the_dense_kkt_solve(dim, n, seed, mass, solver, precision, tol, bound):
    if solver == "gpu":
        gpu_or_skip(precision)
    H, g = random_system(dim, n, seed, mass)
    cs = every_kind(dim, n, seed)
    B, p = global_form(dim, n, cs)
    dx_ref, f_ref = kkt(H, g, B, p)
    sol = stickslip.solve(H, g, cs, dim=dim, solver=solver, precision=precision, tol=tol)
    assert sol.dx.shape == (dim * n,) and sol.dx.dtype == np.float64
    assert rel(sol.dx, dx_ref) <= bound
    # f = −(HΔx + g): its error is H times Δx's, so it is bounded on the scale of the
    # terms it is the difference of.
    scale = sp.linalg.norm(H) * np.linalg.norm(dx_ref) + np.linalg.norm(g)
    assert np.linalg.norm(sol.reactions - f_ref) <= bound * scale
    # Δx is recovered from f64 frames in every precision: the constraints hold to
    # rounding (1e-12 on these O(1) values) whatever arithmetic solved the free part.
    assert np.abs(B @ sol.dx - p).max() <= 1e-12
    info = sol.info
    assert info["solver"] == solver
    assert info["precision"] == (precision or "f64")
    assert info["nodes"] == n and info["dim"] == dim
    assert info["constraints"] == len(cs)
    assert info["constrained_dofs"] + info["free_dofs"] == dim * n
    assert info["constrained_dofs"] == B.shape[0]
    assert info["constraint_violation"] <= 1e-12
    assert info["prescribed"] is True
    if solver == "cholesky":
        assert info["iterations"] is None and info["cholesky"]["factor_nnz"] > 0
    else:
        assert info["iterations"] > 0 and info["relative_residual"] <= tol
    if solver == "gpu":
        assert isinstance(info["adapter"], str) and info["gpu"]["precision"] == precision


@pytest.mark.parametrize("dim,n,seed,mass", SHAPES)
@pytest.mark.parametrize("solver", ["cholesky", "cg"])
def test_global_form_equals_the_list_form(dim, n, seed, mass, solver):
    H, g = random_system(dim, n, seed, mass)
    cs = every_kind(dim, n, seed)
    B, p = global_form(dim, n, cs)
    a = stickslip.solve(H, g, cs, dim=dim, solver=solver, tol=1e-12)
    b = stickslip.solve(H, g, (B, p), dim=dim, solver=solver, tol=1e-12)
    # The two forms build the same constrained subspace from differently stated rows
    # (a line as its direction or as two normal rows): rounding apart, one answer.
    assert rel(b.dx, a.dx) <= 1e-12
    assert rel(b.reactions, a.reactions) <= 1e-10
    assert b.info["constraints"] == B.shape[0]
    assert b.info["constrained_dofs"] == a.info["constrained_dofs"]


def test_global_form_without_p_is_homogeneous():
    H, g = random_system(3, 20, 7)
    B = sp.csr_matrix(([1.0, 1.0, 2.0], ([0, 1, 2], [0, 4, 8])), shape=(3, 60))
    a = stickslip.solve(H, g, (B, None), dim=3)
    b = stickslip.solve(H, g, (B, np.zeros(3)), dim=3)
    assert np.array_equal(a.dx, b.dx)
    assert a.dx[0] == 0.0 and a.dx[4] == 0.0 and a.dx[8] == 0.0
    assert a.info["prescribed"] is False


@pytest.mark.parametrize(
    "convert",
    [
        lambda H: H.tocsr(),
        lambda H: sp.csr_array(H),
        lambda H: sp.csr_matrix((H.data, H.indices.astype(np.int64), H.indptr.astype(np.int64)), shape=H.shape),
        lambda H: H.tocsc(),
        lambda H: H.tocoo(),
        lambda H: H.tobsr(blocksize=(3, 3)),
        lambda H: sp.bsr_array(H.tobsr(blocksize=(3, 3))),
        lambda H: H.tobsr(blocksize=(1, 1)),
        lambda H: H.todok(),
        lambda H: H.toarray(),
        lambda H: H.astype(np.float32).tocsr(),
    ],
    ids=["csr", "csr_array", "csr-int64", "csc", "coo", "bsr3", "bsr3_array", "bsr1", "dok", "dense", "float32"],
)
def test_every_matrix_format_gives_the_csr_answer(convert):
    H, g = random_system(3, 25, 11)
    cs = every_kind(3, 25, 11)
    ref = stickslip.solve(H, g, cs, dim=3)
    Hc = convert(H)
    if Hc.dtype == np.float32:
        # The f32 copy of H is another matrix: compare with its own f64 reference.
        ref = stickslip.solve(sp.csr_matrix(Hc, dtype=np.float64), g, cs, dim=3)
    sol = stickslip.solve(Hc, g, cs, dim=3)
    # The same matrix summed in another order (CSC, COO duplicates): rounding only.
    assert rel(sol.dx, ref.dx) <= 1e-13


def test_bsr_block_size_gives_the_dimension_and_unsorted_duplicate_blocks_are_summed():
    H, g = random_system(2, 30, 12)
    cs = every_kind(2, 30, 12)
    ref = stickslip.solve(H, g, cs, dim=2)
    Hb = H.tobsr(blocksize=(2, 2))
    assert stickslip.solve(Hb, g, cs).info["dim"] == 2
    # The same blocks, each stored as two halves in reversed order within its row.
    indptr, indices, data = Hb.indptr, Hb.indices, Hb.data
    rows_i, rows_d, ptr = [], [], [0]
    for i in range(Hb.shape[0] // 2):
        s, e = indptr[i], indptr[i + 1]
        for k in range(e - 1, s - 1, -1):
            rows_i += [indices[k], indices[k]]
            rows_d += [0.5 * data[k], 0.5 * data[k]]
        ptr.append(len(rows_i))
    messy = sp.bsr_matrix((np.array(rows_d), np.array(rows_i), np.array(ptr)), shape=Hb.shape)
    assert not messy.has_canonical_format
    sol = stickslip.solve(messy, g, cs)
    assert rel(sol.dx, ref.dx) <= 1e-13


def test_numpy_values_in_constraints_are_accepted():
    H, g = random_system(3, 20, 13)
    cs = [
        {"node": np.int64(0), "kind": "sticky"},
        {"node": 3, "kind": "plane", "normal": np.array([0.0, 1.0, 0.0]), "offset": np.float32(0.25)},
        {"node": 5, "kind": "line", "direction": (1, 1, 0)},
    ]
    sol = stickslip.solve(H, g, cs)
    assert sol.dx[3 * 3 + 1] == 0.25
    assert np.all(sol.dx[0:3] == 0.0)
    assert sol.dx[15] == pytest.approx(sol.dx[16], abs=1e-15) and sol.dx[17] == 0.0


def test_no_constraints():
    H, g = random_system(3, 10, 14)
    for cs in ((), [], None):
        sol = stickslip.solve(H, g, cs)
        assert rel(sol.dx, np.linalg.solve(H.toarray(), -g)) <= 1e-12
        assert np.abs(sol.reactions).max() <= 1e-12 * np.abs(g).max()


def test_multilevel_levels_kept_across_a_newton_sequence():
    # A solver that keeps its multilevel levels solves the next system of the pattern
    # (H grown 4×, as a penalty doubling twice grows it) as accurately as a fresh one;
    # only the iterations may differ. A bad setup name is a ValueError naming both.
    dim, n, seed, mass = SHAPES[-1]
    H, g = random_system(dim, n, seed, mass)
    cs = every_kind(dim, n, seed)
    B, p = global_form(dim, n, cs)
    kept = stickslip.Solver(
        "cg", preconditioner="multilevel", multilevel_setup="reuse", tol=1e-12
    )
    for scale in (1.0, 4.0):
        dx_ref, _ = kkt(scale * H, g, B, p)
        sol = kept.solve(scale * H, g, cs, dim=dim)
        fresh = stickslip.solve(
            scale * H, g, cs, dim=dim, solver="cg", preconditioner="multilevel", tol=1e-12
        )
        assert rel(sol.dx, dx_ref) <= 1e-9
        assert sol.info["relative_residual"] <= 1e-12
        assert sol.info["iterations"] >= 1 and fresh.info["iterations"] >= 1
    with pytest.raises(ValueError, match="every or reuse"):
        stickslip.Solver("cg", preconditioner="multilevel", multilevel_setup="sometimes")


@pytest.mark.parametrize("dim,n,seed,mass", SHAPES)
def test_multilevel_cg_matches_the_dense_kkt_solve(dim, n, seed, mass):
    # The same bound as Jacobi CG at tol 1e-12 (κ(Ĥ)·tol, see CASES): the preconditioner
    # changes the path, not where CG stops.
    H, g = random_system(dim, n, seed, mass)
    cs = every_kind(dim, n, seed)
    B, p = global_form(dim, n, cs)
    dx_ref, _ = kkt(H, g, B, p)
    sol = stickslip.solve(H, g, cs, dim=dim, solver="cg", preconditioner="multilevel", tol=1e-12)
    assert rel(sol.dx, dx_ref) <= 1e-9
    assert sol.info["relative_residual"] <= 1e-12
    assert np.abs(B @ sol.dx - p).max() <= 1e-12
