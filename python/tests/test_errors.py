"""Bad input raises ValueError with one line naming the entry; a system that cannot be
solved raises SolveError; GPU failures are DeviceError."""

import numpy as np
import pytest
import scipy.sparse as sp

import stickslip
from systems import gpu_or_skip, random_system


def one_line(excinfo):
    msg = str(excinfo.value)
    assert "\n" not in msg and msg.strip() == msg and msg
    return msg


@pytest.fixture
def system():
    H, g = random_system(3, 10, 31)
    return H, g, [{"node": 0, "kind": "sticky"}]


def test_nan_in_h(system):
    H, g, cs = system
    H = H.copy()
    H.data[7] = np.nan
    r = int(np.searchsorted(H.indptr, 7, side="right") - 1)
    c = int(H.indices[7])
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, cs)
    assert one_line(e) == f"H: entry ({r}, {c}): value NaN is not finite"


def test_nan_in_h_in_every_format(system):
    H, g, cs = system
    for fmt in ("csc", "coo", "bsr"):
        Hn = H.copy().tolil()
        Hn[4, 5] = np.inf
        Hn = Hn.asformat(fmt)
        with pytest.raises(ValueError) as e:
            stickslip.solve(Hn, g, cs)
        assert "(4, 5)" in one_line(e) and "not finite" in str(e.value), fmt


def test_wrong_length_g(system):
    H, g, cs = system
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g[:-1], cs)
    assert one_line(e) == "g: has 29 entries, expected 30 (dim × nodes)"


def test_nan_in_g(system):
    H, g, cs = system
    g = g.copy()
    g[4] = np.nan
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, cs)
    assert one_line(e) == "g: entry 4: value NaN is not finite"


def test_unknown_kind(system):
    H, g, _ = system
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, [{"node": 0, "kind": "sticky"}, {"node": 1, "kind": "hinge"}])
    assert one_line(e) == (
        "constraints: constraints[1].kind: unknown kind 'hinge' (expected sticky, plane, line or rows)"
    )


def test_node_out_of_range(system):
    H, g, _ = system
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, [{"node": 10, "kind": "sticky"}])
    assert one_line(e) == (
        "constraints: constraints[0]: node 10 is out of range (the system has 10 nodes, numbered from 0)"
    )


@pytest.mark.parametrize(
    "constraint,message",
    [
        ({"node": 1, "kind": "plane", "normal": [0, 0, 0]},
         "constraints: constraints[0].normal: is zero (a normal or direction needs a nonzero length)"),
        ({"node": 1, "kind": "plane", "normal": [0, 1]},
         "constraints: constraints[0].normal: has 2 components, expected 3 (dim is 3)"),
        ({"node": 1, "kind": "plane", "normal": [0, float("nan"), 0]},
         "constraints: constraints[0].normal[1]: nan is not a finite number"),
        ({"node": 1, "kind": "line", "direction": np.array([1.0, np.inf, 0.0])},
         "constraints: constraints[0].direction[1]: inf is not a finite number"),
        ({"node": -1, "kind": "sticky"},
         "constraints: constraints[0].node: expected a node index (an integer ≥ 0), found -1"),
        ({"node": 1, "kind": "sticky", "normal": [1, 0, 0]},
         "constraints: constraints[0].normal: unknown key for kind sticky (allowed: node, kind, displacement)"),
        ({"kind": "sticky"}, "constraints: constraints[0].node: missing"),
        ("sticky", "constraints: constraints[0]: expected an object, found a string"),
        ({"node": 1, "kind": "sticky", 3: 4}, "constraints: constraints[0]: keys must be strings, found 3"),
        ({"node": 1, "kind": "sticky", "displacement": [0, 0, object()]},
         "constraints: constraints[0].displacement[2]: expected a JSON value (number, string, list or dict), found object"),
    ],
)
def test_malformed_constraints(system, constraint, message):
    H, g, _ = system
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, [constraint])
    assert one_line(e) == message


def test_contradictory_constraints_on_one_node(system):
    H, g, _ = system
    cs = [
        {"node": 2, "kind": "plane", "normal": [1, 0, 0], "offset": 0.0},
        {"node": 2, "kind": "plane", "normal": [1, 0, 0], "offset": 1.0},
    ]
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, cs)
    assert one_line(e).startswith(
        "constraints: node 2 (constraints[0], constraints[1]): contradictory constraints on node 2"
    )


def test_global_form_errors(system):
    H, g, _ = system
    two_nodes = sp.csr_matrix(([1.0, 1.0], ([0, 0], [0, 3])), shape=(1, 30))
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, (two_nodes, None))
    assert one_line(e).startswith("B: row 1: the row couples node 0 and node 1")
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, (sp.csr_matrix((1, 29)), None))
    assert one_line(e) == "B: B has 29 columns, expected 30 = 3 × 10 nodes"
    B = sp.csr_matrix(([1.0], ([0], [0])), shape=(1, 30))
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, (B, [0.0, 1.0]))
    assert one_line(e) == "p: p has 2 rows, expected 1 (the rows of B)"


@pytest.mark.parametrize(
    "make,message",
    [
        (lambda H: H[:, :-3], "H: is 30 × 27, expected a square matrix"),
        (lambda H: sp.csr_matrix(H.toarray()[:-1, :-1]),
         "H: has 29 rows, not a multiple of dim = 3 (DOFs are node-major: node i owns rows 3·i … 3·i + 2)"),
        (lambda H: H.astype(np.complex128), "H: complex values are not supported (H and g are real)"),
        (lambda H: "H", "H: expected a SciPy sparse matrix or a 2-D array, found str"),
    ],
)
def test_malformed_h(system, make, message):
    H, g, cs = system
    with pytest.raises(ValueError) as e:
        stickslip.solve(make(H), g, cs)
    assert one_line(e) == message


def test_asymmetric_h(system):
    H, g, cs = system
    H = H.tolil()
    H[0, 4] += 1.0
    with pytest.raises(ValueError) as e:
        stickslip.solve(H.tocsr(), g, cs)
    assert "H is not symmetric" in one_line(e)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(solver="lu"), "solver config: solver: unknown solver 'lu' (expected cholesky, cg or gpu)"),
        (dict(solver="cg", precision="f32"),
         "solver config: precision: f32 needs the gpu solver (cholesky and cg compute in f64)"),
        (dict(solver="cg", precision="f16"),
         "solver config: precision: unknown precision 'f16' (expected f32, f64 or mixed)"),
        (dict(solver="cg", tol=2.0), "solver config: tol: must lie in (0, 1), got 2"),
        (dict(solver="cg", max_iters=0), "solver config: max_iters: must be at least 1"),
        (dict(solver="cg", preconditioner="ilu"),
         "solver config: preconditioner: unknown preconditioner 'ilu' (expected none, jacobi, block-jacobi or multilevel)"),
        (dict(coarse="amg"),
         "solver config: coarse: unknown coarse space 'amg' (expected none, translations or aggregates)"),
        (dict(solver="cg", error_tol=1e-3), "solver config: error_tol: needs the gpu solver in mixed precision"),
        (dict(solver="gpu", precision="f32", preconditioner="multilevel"),
         "solver config: preconditioner: the multilevel preconditioner runs in f64 only "
         "(the CPU CG and the f64 device PCG); f32 and mixed take none, jacobi or block-jacobi"),
        (dict(constrained_diagonal="zero"),
         "solver config: constrained_diagonal: unknown value 'zero' (expected identity or hessian)"),
    ],
)
def test_bad_configuration(kwargs, message):
    with pytest.raises(ValueError) as e:
        stickslip.Solver(**kwargs)
    assert one_line(e) == message


def test_bad_dim(system):
    H, g, cs = system
    with pytest.raises(ValueError) as e:
        stickslip.solve(H, g, cs, dim=4)
    assert one_line(e) == "problem: dim: must be 2 or 3, got 4"


def indefinite():
    """A 3D chain whose middle node has a negative mass: H is indefinite on the free
    subspace (node 0 sticky)."""
    n = 6
    H = sp.lil_matrix((3 * n, 3 * n))
    for i in range(3 * n):
        H[i, i] = 1.0
    for a in range(3):
        H[9 + a, 9 + a] = -5.0
    return H.tocsr(), np.ones(3 * n), [{"node": 0, "kind": "sticky"}]


@pytest.mark.parametrize("solver", ["cholesky", "cg"])
def test_indefinite_h_is_a_solve_error(solver):
    H, g, cs = indefinite()
    with pytest.raises(stickslip.SolveError) as e:
        stickslip.solve(H, g, cs, solver=solver)
    assert isinstance(e.value, RuntimeError)
    assert "not positive definite" in one_line(e)


@pytest.mark.parametrize("precision", ["f64", "mixed", "f32"])
def test_indefinite_h_on_the_gpu_is_a_solve_error(precision):
    gpu_or_skip(precision)
    H, g, cs = indefinite()
    with pytest.raises(stickslip.SolveError) as e:
        stickslip.solve(H, g, cs, solver="gpu", precision=precision)
    one_line(e)


def test_cg_iteration_limit_is_a_solve_error():
    H, g = random_system(3, 30, 32)
    with pytest.raises(stickslip.SolveError) as e:
        stickslip.solve(H, g, [], solver="cg", tol=1e-12, max_iters=2)
    one_line(e)


def test_exception_classes():
    assert issubclass(stickslip.SolveError, RuntimeError)
    assert issubclass(stickslip.DeviceError, RuntimeError)
    assert not issubclass(stickslip.DeviceError, stickslip.SolveError)
    assert stickslip.SolveError.__module__ == "stickslip"


def test_a_hessian_singular_to_working_precision_is_a_solve_error():
    # κ ≈ 2e15 on the pair (0, 2): singular to working precision; the f64 factor's
    # answer is off by about 10 % and its residual stays at 3e-2.
    H = np.eye(4)
    H[0, 2] = H[2, 0] = 1.0 - 1e-15
    with pytest.raises(stickslip.SolveError) as e:
        stickslip.solve(sp.csr_matrix(H), np.array([1.0, 0.3, -0.7, 0.2]), [], dim=2)
    msg = one_line(e)
    assert "singular to working precision" in msg


def test_cholesky_solves_a_system_whose_diagonal_spans_the_f64_range():
    # H = S T S with T tridiagonal (4, −1) and S = 2^k from 2^-480 to 2^480: y = S⁻¹ z
    # where T z = S⁻¹ b, and powers of two scale exactly.
    n = 10
    k = np.linspace(-480, 480, n).round()
    s = np.exp2(k)
    T = np.diag(np.full(n, 4.0)) - np.diag(np.ones(n - 1), 1) - np.diag(np.ones(n - 1), -1)
    H = sp.csr_matrix((s[:, None] * T) * s[None, :])
    g = np.ones(n)
    sol = stickslip.solve(H, g, [], dim=2)
    z = np.linalg.solve(T, -g / s)
    expected = z / s
    assert np.max(np.abs(sol.dx - expected) / np.abs(expected)) <= 1e-14
    assert sol.info["cholesky"]["scaled_residual"] <= 1e-15


@pytest.mark.parametrize("scale", [1e-170, 1e-160, 1e155])
def test_cg_solves_a_well_conditioned_system_at_any_scale_of_g(scale):
    H = sp.csr_matrix(np.diag(np.full(4, 3.0)) - np.diag(np.ones(3), 1) - np.diag(np.ones(3), -1))
    g = np.array([1.0, -0.5, 0.25, 2.0]) * scale
    chol = stickslip.solve(H, g, [], dim=2)
    cg = stickslip.solve(H, g, [], dim=2, solver="cg")
    # tol 1e-8 on the residual and κ < 3: the error is below 3e-8.
    assert np.all(np.abs(cg.dx - chol.dx) <= 3e-8 * np.abs(chol.dx))
