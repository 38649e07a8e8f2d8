"""Type stubs of the stickslip package."""

from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

__version__: str

__all__: List[str]

#: A constraint in the bc.json form: {"node": 0, "kind": "sticky"}, …
ConstraintDict = Mapping[str, Any]
#: The global form B Δx = p: B (m × dn, sparse or dense) and p (m values) or None.
GlobalForm = Tuple[Union[sp.spmatrix, sp.sparray, np.ndarray], Optional[npt.ArrayLike]]
Constraints = Union[Sequence[ConstraintDict], GlobalForm, Mapping[str, Any], None]
Matrix = Union[sp.spmatrix, sp.sparray, npt.ArrayLike]

class SolveError(RuntimeError):
    """The system cannot be solved as posed: H is not positive definite on the free
    subspace, CG did not reach its tolerance, or f64 overflowed."""

class DeviceError(RuntimeError):
    """The GPU cannot run the solve: no adapter, no SHADER_F64 for f64 or mixed
    precision, a system larger than the device allows, or a device failure."""

class Solution:
    """The answer of a solve."""

    dx: npt.NDArray[np.float64]
    """The step Δx (length d·n); it meets every constraint to f64 rounding."""
    reactions: npt.NDArray[np.float64]
    """f = −(HΔx + g): the forces the constraints exert."""
    info: Dict[str, Any]
    """What the solve did, as report.json holds it."""
    def __init__(
        self,
        dx: npt.NDArray[np.float64],
        reactions: npt.NDArray[np.float64],
        info: Dict[str, Any],
    ) -> None: ...

class Solver:
    """A configured solver that keeps what it can reuse between solves."""

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
    ) -> None: ...
    @property
    def adapter(self) -> Optional[str]:
        """The GPU adapter's name for the gpu solver, else None."""
    def solve(
        self,
        H: Matrix,
        g: npt.ArrayLike,
        constraints: Constraints = (),
        *,
        dim: Optional[int] = None,
    ) -> Solution:
        """Solves min ½ΔxᵀHΔx + gᵀΔx subject to the constraints."""

def solve(
    H: Matrix,
    g: npt.ArrayLike,
    constraints: Constraints = (),
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
    """Solves one constrained Newton system: Solver(...).solve(H, g, constraints)."""

def adapters() -> List[Dict[str, Any]]:
    """The GPU adapters wgpu sees, as `stickslip info` lists them."""
