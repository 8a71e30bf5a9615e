"""Solver ``lstsq``: the minimum-norm least-squares image, by LSQR on a linear operator."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.sparse.linalg import lsqr

from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.solvers.common import checked_coefficients, measurement_operator
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["DAMP_MAX", "LstsqSolver", "LSQR_STOP"]

#: scipy's LSQR ``istop`` codes, as stop reasons for the record.
LSQR_STOP = {
    0: "zero_solution",  # b = 0: x = 0 is exact
    1: "consistent",  # A x ≈ b within atol/btol
    2: "least_squares",  # a least-squares solution within atol
    3: "ill_conditioned",  # cond(A) > conlim
    4: "consistent_eps",  # A x ≈ b to machine precision
    5: "least_squares_eps",
    6: "ill_conditioned_eps",
    7: "max_iter",
}


#: Largest ``damp``. scipy's LSQR squares it (``dampsq = damp**2``, scipy/sparse/linalg/_isolve/
#: lsqr.py), a Python float that overflows past 1.34e154 (measured: ``damp=1e300`` ended in
#: OverflowError); at 1e150 the damped image is already 1e-296 of the undamped one (measured to
#: finish, all numbers finite), so nothing a user can mean lies above it. Assumed bound.
DAMP_MAX = 1e150

#: ``iter_lim: null`` stops LSQR after this many times ``max(m, N)`` iterations at most.
SAFETY_FACTOR = 50


@dataclass(frozen=True)
class LstsqSolver:
    """Solver ``lstsq``: ``argmin ‖x‖ subject to minimising ‖A x − y‖`` (``damp = 0``).

    LSQR (scipy) started from ``x = 0`` stays in the row space of ``A``, so it converges to the
    minimum-norm least-squares solution. On the Hadamard path ``A`` is the fast subsampled
    transform (rows orthogonal, ``A Aᵀ = N·I``): LSQR stops after one iteration at the
    zero-filled inverse, which *is* the minimum-norm solution. With explicit patterns (any
    ``(m, N)`` matrix, e.g. a recorded acquisition) it works on that matrix as an operator.

    LSQR runs to its tolerances: with ``iter_lim: null`` (default) the only limit is a safety net
    of :data:`SAFETY_FACTOR` ``· max(m, N)`` iterations (in exact arithmetic LSQR ends within
    ``min(m, N)``; in floating point an ill-conditioned matrix needs more: random 0/1 patterns
    at 32², condition 1e5, converge in 2,308 iterations for ``N = 1024``), and reaching it warns.

    Attributes:
        atol, btol: LSQR stopping tolerances (relative).
        iter_lim: LSQR iteration limit; null = run to the tolerances.
        damp: Tikhonov damping (0 = plain minimum-norm least squares), in the units of ``A``.
    """

    atol: Annotated[float, Range(0.0, 1.0, "a tolerance", hi_open=True)] = 1e-10
    btol: Annotated[float, Range(0.0, 1.0, "a tolerance", hi_open=True)] = 1e-10
    iter_lim: Annotated[int | None, Range(1, None, "an integer", integer=True)] = None
    damp: Annotated[float, Range(0.0, DAMP_MAX, "a damping")] = 0.0

    def __post_init__(self) -> None:
        check_ranges(self)

    def solve(self, acquisition: Acquisition) -> Image2D:
        y = checked_coefficients(acquisition, "lstsq")
        op = measurement_operator(acquisition)
        limit = self.iter_lim if self.iter_lim is not None else SAFETY_FACTOR * max(op.shape)
        x, istop, itn, r1norm = lsqr(op, y, damp=self.damp, atol=self.atol, btol=self.btol, iter_lim=limit)[:4]
        if int(istop) == 7:
            warnings.warn(
                f"lstsq: LSQR stopped at its iteration limit {limit} before its tolerances "
                f"(atol={self.atol}, btol={self.btol}); the image is not converged",
                stacklevel=2,
            )
        ny = float(np.linalg.norm(y))
        info = {
            "iterations": int(itn),
            "stop_reason": LSQR_STOP.get(int(istop), f"istop_{istop}"),
            "relative_residual": float(r1norm / ny) if ny > 0 else float(r1norm),
        }
        return Image2D(np.asarray(x, dtype=np.float64).reshape(acquisition.n, acquisition.n), info=info)
