"""A Solver kept over Newton-like value updates gives the answers of fresh solves and
reuses its analysis or device buffers while the pattern and constraints stay."""

import threading

import numpy as np
import pytest

import stickslip
from systems import every_kind, gpu_or_skip, random_system, rel

# (solver, precision, tol, whether the solver has something to reuse)
CASES = [
    ("cholesky", None, 1e-8, True),
    ("cg", None, 1e-10, False),
    ("gpu", "f64", 1e-10, True),
    ("gpu", "mixed", 1e-10, True),
    ("gpu", "f32", 1e-6, True),
]


def newton_updates(H, g, k):
    """The k-th update: the same pattern with new values (each stored entry scaled by a
    smooth random factor in [0.8, 1.2], symmetrically) and a new gradient."""
    rng = np.random.default_rng(100 + k)
    Hk = H.copy().tocoo()
    node_scale = 1.0 + 0.2 * np.sin(rng.standard_normal(Hk.shape[0]))
    Hk.data = Hk.data * np.sqrt(node_scale[Hk.row] * node_scale[Hk.col])
    return Hk.tocsr(), g * (1.0 + 0.1 * k) + 0.01 * rng.standard_normal(g.shape)


@pytest.mark.parametrize("solver,precision,tol,reuses", CASES)
def test_kept_solver_equals_fresh_solves_over_five_updates(solver, precision, tol, reuses):
    if solver == "gpu":
        gpu_or_skip(precision)
    dim, n = 3, 30
    H, g = random_system(dim, n, 21)
    cs = every_kind(dim, n, 21)
    opts = dict(solver=solver, precision=precision, tol=tol)
    kept = stickslip.Solver(**opts)
    for k in range(5):
        Hk, gk = newton_updates(H, g, k)
        a = kept.solve(Hk, gk, cs)
        b = stickslip.solve(Hk, gk, cs, **opts)
        # The same arithmetic on the same values in the same order, whether or not the
        # buffers are new: the answers agree to the last bit on the CPU; the GPU's
        # reductions are fixed trees, so it is held to the same.
        assert np.array_equal(a.dx, b.dx), rel(a.dx, b.dx)
        assert np.array_equal(a.reactions, b.reactions)
        assert a.info["iterations"] == b.info["iterations"]
        assert b.info["reused"] is False
        assert a.info["reused"] is (reuses and k > 0)


def test_a_new_pattern_or_new_constraints_start_afresh():
    dim, n = 3, 30
    H, g = random_system(dim, n, 22)
    cs = every_kind(dim, n, 22)
    s = stickslip.Solver()
    assert s.solve(H, g, cs).info["reused"] is False
    assert s.solve(H, g, cs).info["reused"] is True
    # One more coupling: another pattern.
    H2 = H.tolil()
    H2[0, 3 * (n - 1)] = H2[3 * (n - 1), 0] = 0.01
    H2 = H2.tocsr()
    sol = s.solve(H2, g, cs)
    assert sol.info["reused"] is False
    assert rel(sol.dx, stickslip.solve(H2, g, cs).dx) <= 1e-14
    assert s.solve(H2, g, cs).info["reused"] is True
    # Other constraints on the same pattern.
    assert s.solve(H2, g, cs[:-1]).info["reused"] is False


def test_a_failed_solve_leaves_the_solver_usable():
    H, g = random_system(3, 20, 23)
    cs = every_kind(3, 20, 23)
    s = stickslip.Solver()
    good = s.solve(H, g, cs)
    with pytest.raises(ValueError):
        s.solve(H, g[:-1], cs)
    again = s.solve(H, g, cs)
    assert np.array_equal(again.dx, good.dx) and again.info["reused"] is True


def test_one_solver_from_several_threads():
    dim, n = 3, 30
    H, g = random_system(dim, n, 24)
    cs = every_kind(dim, n, 24)
    s = stickslip.Solver(solver="cg", tol=1e-10)
    want = [s.solve(H, g * (1 + k), cs).dx for k in range(4)]
    got = [None] * 4
    errors = []

    def work(k):
        try:
            got[k] = s.solve(H, g * (1 + k), cs).dx
        except Exception as e:  # reported below, not lost in the thread
            errors.append(e)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for k in range(4):
        assert np.array_equal(got[k], want[k])
