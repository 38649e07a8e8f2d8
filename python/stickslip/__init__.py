"""stickslip: constrained Newton systems from NumPy and SciPy, on the GPU or the CPU.

Solves min ½ΔxᵀHΔx + gᵀΔx subject to per-node constraints (sticky nodes, slip on
planes and lines of any orientation, general per-node rows, prescribed displacements),
the Newton step of implicit, optimization-based simulation. The constraints are
eliminated by a per-node change of basis; the remaining SPD system is solved by sparse
Cholesky, CG on the CPU, or CG on the GPU (f32, f64 or mixed precision).

>>> import numpy as np, scipy.sparse as sp, stickslip
>>> n = 4                                   # a 3D chain of 4 nodes
>>> H = sp.diags([-1.0, 2.1, -1.0], [-3, 0, 3], shape=(3 * n, 3 * n)).tocsr()
>>> g = np.full(3 * n, -0.01)
>>> sol = stickslip.solve(H, g, [{"node": 0, "kind": "sticky"},
...                              {"node": 3, "kind": "plane", "normal": [0, 1, 0]}])
>>> float(sol.dx[3 * 3 + 1])                # node 3 stays on its plane
0.0

The arrays of H are read in place where their layout allows (CSR with 32- or 64-bit
indices; BSR with d×d blocks); other formats are converted to CSR first. The GIL is
released while a system is converted and solved.

Errors: ``ValueError`` for bad input (one line naming the entry, as the command line
prints it), :class:`SolveError` for a system that cannot be solved as posed,
:class:`DeviceError` for GPU failures.
"""

from __future__ import annotations

import json
import math
from typing import Any, Dict, List, Mapping, Optional, Tuple

import numpy as np
import scipy.sparse as sp

from . import _stickslip
from ._stickslip import DeviceError, SolveError

__version__: str = _stickslip.__version__

__all__ = [
    "solve",
    "Solver",
    "Solution",
    "adapters",
    "SolveError",
    "DeviceError",
    "__version__",
]


class Solution:
    """The answer of a solve.

    Attributes:
        dx: the step Δx, a float64 array of length d·n; it meets every constraint to f64
            rounding.
        reactions: f = −(HΔx + g), the forces the constraints exert (zero on free
            components up to the solver's residual), a float64 array of length d·n.
        info: what the solve did, as ``stickslip solve --report report.json`` writes it:
            solver, precision, adapter, iterations, relative_residual, reused (the
            analysis or device buffers of an earlier solve were reused), seconds, dim,
            nodes, free_dofs, constrained_dofs, rotated_nodes, constraints, prescribed,
            constrained_diagonal, constraint_violation, and the solver's own section
            (``cholesky``, ``cg`` or ``gpu``).
    """

    __slots__ = ("dx", "reactions", "info")

    def __init__(self, dx: np.ndarray, reactions: np.ndarray, info: Dict[str, Any]):
        self.dx = dx
        self.reactions = reactions
        self.info = info

    def __repr__(self) -> str:
        it = self.info.get("iterations")
        its = "" if it is None else f", {it} iterations"
        return (
            f"Solution({self.info.get('solver')} {self.info.get('precision')}, "
            f"{self.dx.shape[0]} dofs{its}, "
            f"relative residual {self.info.get('relative_residual', float('nan')):.2e})"
        )


def _config_error(entry: str, problem: str) -> ValueError:
    return ValueError(f"solver config: {entry}: {problem}")


class Solver:
    """A configured solver that keeps what it can reuse between solves.

    Args:
        solver: ``"cholesky"`` (sparse Cholesky, f64, the reference), ``"cg"``
            (preconditioned CG on the CPU, f64) or ``"gpu"`` (preconditioned CG on the
            GPU through wgpu).
        precision: the GPU's arithmetic: ``"f32"``, ``"f64"`` or ``"mixed"`` (f32 CG with
            f64 reliable updates); f64 and mixed need an adapter with SHADER_F64. None:
            f64. The CPU solvers compute in f64 only.
        tol: CG stops at ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol (the true residual, recomputed in f64);
            in (0, 1).
        max_iters: CG iteration limit (all restarts together), ≥ 1.
        preconditioner: ``"jacobi"``, ``"block-jacobi"``, ``"none"`` or ``"multilevel"``
            (``"cg"``, and ``"gpu"`` in f64).
        coarse: coarse correction added to the preconditioner: ``"aggregates"``,
            ``"translations"`` or ``"none"``.
        error_tol: mixed precision only: after ``tol``, refine until the estimated
            relative error is ≤ this.
        constrained_diagonal: D on constrained components of Ĥ: ``"identity"`` or
            ``"hessian"`` (diag(VᵀHV)).
        multilevel_setup: with ``preconditioner="multilevel"``: ``"every"`` builds its
            levels for every solve; ``"reuse"`` keeps them for the next systems of the
            same sparsity pattern (a Newton sequence: refreshed with the new H, rebuilt
            when the constraints free a component or the solves slow down 1.5×), as
            scenes do.

    A solver keeps the last system it solved. Calling :meth:`solve` again with the same
    constraints and the same sparsity pattern of H (new values, as in the next Newton
    iteration) reuses the Cholesky analysis or the GPU's device buffers
    (``info["reused"]`` says so). The first GPU solver of a process opens the default
    adapter (``WGPU_ADAPTER_NAME`` and ``WGPU_BACKEND`` choose it) and later ones share it.

    Raises:
        ValueError: a configuration the solvers do not accept.
        DeviceError: ``solver="gpu"`` and no suitable adapter.
    """

    def __init__(
        self,
        solver: str = "cholesky",
        precision: Optional[str] = None,
        tol: float = 1e-8,
        max_iters: int = 10_000,
        preconditioner: str = "jacobi",
        coarse: str = "aggregates",
        error_tol: Optional[float] = None,
        constrained_diagonal: str = "identity",
        multilevel_setup: str = "every",
    ):
        for name, value in (
            ("solver", solver),
            ("preconditioner", preconditioner),
            ("coarse", coarse),
            ("constrained_diagonal", constrained_diagonal),
            ("multilevel_setup", multilevel_setup),
        ):
            if not isinstance(value, str):
                raise _config_error(name, f"expected a string, found {value!r}")
        if precision is not None and not isinstance(precision, str):
            raise _config_error("precision", f"expected a string or None, found {precision!r}")
        tol = _real("tol", tol)
        if error_tol is not None:
            error_tol = _real("error_tol", error_tol)
        if isinstance(max_iters, bool) or not isinstance(max_iters, (int, np.integer)):
            raise _config_error("max_iters", f"expected an integer, found {max_iters!r}")
        if max_iters < 1:
            raise _config_error("max_iters", "must be at least 1")
        self._engine = _stickslip.Engine(
            solver,
            precision,
            tol,
            int(max_iters),
            preconditioner,
            coarse,
            error_tol,
            constrained_diagonal,
            multilevel_setup,
        )
        self._config = dict(
            solver=solver,
            precision=precision,
            tol=tol,
            max_iters=int(max_iters),
            preconditioner=preconditioner,
            coarse=coarse,
            error_tol=error_tol,
            constrained_diagonal=constrained_diagonal,
            multilevel_setup=multilevel_setup,
        )

    @property
    def adapter(self) -> Optional[str]:
        """The GPU adapter's name for the gpu solver, else None."""
        return self._engine.adapter()

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self._config.items())
        return f"stickslip.Solver({args})"

    def solve(
        self,
        H: Any,
        g: Any,
        constraints: Any = (),
        *,
        dim: Optional[int] = None,
    ) -> Solution:
        """Solves min ½ΔxᵀHΔx + gᵀΔx subject to the constraints.

        Args:
            H: the Hessian, dn × dn, symmetric, node-major DOFs (node i owns rows
                d·i … d·i + d − 1): any SciPy sparse matrix or array (CSR, CSC, COO, BSR,
                …) or a dense 2-D array. Both triangles; duplicate entries are summed.
            g: the gradient, a vector of dn numbers.
            constraints: a list of dicts in the bc.json form, e.g.
                ``{"node": 0, "kind": "sticky"}``,
                ``{"node": 1, "kind": "sticky", "displacement": [0, 0.1, 0]}``,
                ``{"node": 4, "kind": "plane", "normal": [0, 1, 0], "offset": 0.0}``,
                ``{"node": 7, "kind": "line", "direction": [1, 1, 0]}``,
                ``{"node": 9, "kind": "rows", "rows": [[1, 0, 0]], "values": [0.0]}``
                (NumPy arrays and scalars are accepted as values); or a pair ``(B, p)``
                in the global form B Δx = p, B an m × dn sparse matrix whose every row
                touches one node, p m values or None for zeros (messages count B's rows
                from 1, as the command line does for B.mtx). Several constraints on one
                node combine by rank.
            dim: the spatial dimension, 2 or 3. None: the block size of a BSR H with
                square 2×2 or 3×3 blocks, else 3.

        Returns:
            A :class:`Solution`.

        Raises:
            ValueError: bad input (one line naming the entry: ``H: entry (4, 7): value
                nan is not finite``, ``g: has 11 entries, expected 12 (dim × nodes)``,
                ``constraints: constraints[2].kind: unknown kind 'hinge' (…)``,
                ``constraints: constraints[1]: node 9 is out of range (…)``).
            SolveError: H is not positive definite on the free subspace, CG did not
                converge, or f64 overflowed.
            DeviceError: the GPU failed.
        """
        fmt, indptr, indices, data, dim, n_nodes = _hessian(H, dim)
        gv = _vector("g", g)
        cs = _constraints(constraints, dim, n_nodes)
        dx, reactions, info = self._engine.solve(fmt, indptr, indices, data, gv, cs, n_nodes)
        return Solution(dx, reactions, json.loads(info))


def solve(
    H: Any,
    g: Any,
    constraints: Any = (),
    *,
    dim: Optional[int] = None,
    solver: str = "cholesky",
    precision: Optional[str] = None,
    tol: float = 1e-8,
    max_iters: int = 10_000,
    preconditioner: str = "jacobi",
    coarse: str = "aggregates",
    error_tol: Optional[float] = None,
    constrained_diagonal: str = "identity",
) -> Solution:
    """Solves one constrained Newton system: ``Solver(...).solve(H, g, constraints)``.

    See :class:`Solver` for the options and :meth:`Solver.solve` for the arguments. For
    a sequence of systems with one sparsity pattern (Newton iterations, time steps)
    keep a :class:`Solver`: it reuses its analysis or device buffers.

    >>> import numpy as np, scipy.sparse as sp, stickslip
    >>> H = sp.identity(6, format="csr") * 2.0
    >>> sol = stickslip.solve(H, np.ones(6), [{"node": 0, "kind": "sticky"}], dim=3)
    >>> np.round(sol.dx, 12).tolist()       # Δx = −g/2 on the free node
    [0.0, 0.0, 0.0, -0.5, -0.5, -0.5]
    """
    return Solver(
        solver=solver,
        precision=precision,
        tol=tol,
        max_iters=max_iters,
        preconditioner=preconditioner,
        coarse=coarse,
        error_tol=error_tol,
        constrained_diagonal=constrained_diagonal,
    ).solve(H, g, constraints, dim=dim)


def adapters() -> List[Dict[str, Any]]:
    """The GPU adapters wgpu sees, as ``stickslip info`` lists them: one dict per adapter
    (name, backend, device_type, driver, shader_f64, shader_int64, subgroup, limits, …).
    ``WGPU_BACKEND`` narrows the backends searched."""
    return json.loads(_stickslip.adapters())


# --- conversion -------------------------------------------------------------------------


def _real(name: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise _config_error(name, f"expected a number, found {v!r}")
    return float(v)


def _float_array(what: str, a: np.ndarray) -> np.ndarray:
    """`a` as contiguous float64, copied only when its dtype or layout requires it."""
    if np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{what}: complex values are not supported (H and g are real)")
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == np.bool_):
        raise ValueError(f"{what}: expected numbers, found an array of {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float64)


def _vector(what: str, v: Any) -> np.ndarray:
    if sp.issparse(v):
        v = v.toarray()
    try:
        a = np.asarray(v)
    except Exception as e:  # ragged lists and the like
        raise ValueError(f"{what}: cannot be read as a vector ({e})") from None
    if a.ndim == 2 and 1 in a.shape:
        a = a.reshape(-1)
    if a.ndim != 1:
        raise ValueError(f"{what}: expected a vector, found an array of shape {a.shape}")
    return _float_array(what, a)


def _index_pair(p: np.ndarray, i: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """indptr and indices as one of int32 or int64 (SciPy's own index types: no copy)."""
    for t in (np.int32, np.int64):
        if p.dtype == t and i.dtype == t:
            return np.ascontiguousarray(p), np.ascontiguousarray(i)
    return (
        np.ascontiguousarray(p, dtype=np.int64),
        np.ascontiguousarray(i, dtype=np.int64),
    )


def _hessian(H: Any, dim: Optional[int]):
    """(format, indptr, indices, data, dim, n_nodes) of H."""
    if not sp.issparse(H):
        a = np.asarray(H)
        if a.ndim != 2:
            raise ValueError(
                f"H: expected a SciPy sparse matrix or a 2-D array, found {type(H).__name__}"
                + (f" of shape {a.shape}" if a.ndim else "")
            )
        H = sp.csr_array(_float_array("H", a))
    rows, cols = H.shape
    if rows != cols:
        raise ValueError(f"H: is {rows} × {cols}, expected a square matrix")
    if dim is None:
        bs = H.blocksize if H.format == "bsr" else None
        dim = bs[0] if bs in ((2, 2), (3, 3)) else 3
    if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim not in (2, 3):
        raise ValueError(f"problem: dim: must be 2 or 3, got {dim!r}")
    dim = int(dim)
    if rows % dim != 0:
        raise ValueError(
            f"H: has {rows} rows, not a multiple of dim = {dim} (DOFs are node-major: "
            f"node i owns rows {dim}·i … {dim}·i + {dim - 1})"
        )
    if H.format == "bsr" and H.blocksize == (dim, dim):
        if not H.has_canonical_format:
            H = H.copy()
            H.sum_duplicates()  # sorts each block row's columns as well
        p, i = _index_pair(H.indptr, H.indices)
        return "bsr", p.astype(np.int64, copy=False), i.astype(np.int64, copy=False), \
            _float_array("H", H.data), dim, rows // dim
    if H.format != "csr":
        H = H.tocsr()
    p, i = _index_pair(H.indptr, H.indices)
    return "csr", p, i, _float_array("H", H.data), dim, rows // dim


def _is_matrix_form(c: Any) -> bool:
    return (
        isinstance(c, tuple)
        and len(c) == 2
        and (sp.issparse(c[0]) or (isinstance(c[0], np.ndarray) and c[0].ndim == 2))
    )


def _constraints(c: Any, dim: int, n_nodes: int):
    if c is None:
        c = []
    if _is_matrix_form(c):
        B, p = c
        B = sp.coo_array(B)
        m, ncols = B.shape
        pv = None if p is None else _vector("p", p)
        return _stickslip.Constraints.from_matrix(
            np.ascontiguousarray(B.row, dtype=np.int64),
            np.ascontiguousarray(B.col, dtype=np.int64),
            _float_array("B", B.data),
            m,
            ncols,
            pv,
            dim,
            n_nodes,
        )
    if isinstance(c, Mapping):
        doc = _plain(c, "")
    elif isinstance(c, (list, tuple)):
        doc = {"constraints": [_plain(x, f"constraints[{k}]") for k, x in enumerate(c)]}
    else:
        raise ValueError(
            "constraints: expected a list of dicts (the bc.json form) or a pair (B, p), "
            f"found {type(c).__name__}"
        )
    return _stickslip.Constraints.from_json(json.dumps(doc), dim)


def _plain(v: Any, path: str) -> Any:
    """`v` as plain JSON values (NumPy arrays and scalars included). JSON has no NaN or
    infinity, so a non-finite number is refused here with the reader's message."""
    at = lambda key: f"{path}.{key}" if path else str(key)  # noqa: E731
    if isinstance(v, Mapping):
        out = {}
        for k, x in v.items():
            if not isinstance(k, str):
                raise ValueError(f"constraints: {path}: keys must be strings, found {k!r}")
            out[k] = _plain(x, at(k))
        return out
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if isinstance(v, (list, tuple)):
        return [_plain(x, f"{path}[{k}]") for k, x in enumerate(v)]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(v):
            raise ValueError(f"constraints: {path}: {float(v)} is not a finite number")
        return float(v)
    if v is None or isinstance(v, str):
        return v
    raise ValueError(
        f"constraints: {path}: expected a JSON value (number, string, list or dict), "
        f"found {type(v).__name__}"
    )
