"""The largest margin t of a few affine linear matrix inequalities, solved with Clarabel directly.

    maximize t  s.t.  F_c(x) ⪰ t·I  (c with ``margin``),  F_c(x) ⪰ 0  (the others),  t ≤ 1,

where x collects small matrix variables (symmetric or general) and every F_c is affine in x. The LMIs of
the critical-rate analysis (Sinopoli et al. 2004, Thm 5; the Markov LMI of Costa, Fragoso & Marques 2005,
Thm 3.9) have this form: feasible ⇔ t* > 0.

F_c is given as a numpy function of the variables' values; being affine, it is read off by probing,
F_c(x) = F_c(0) + Σ_k x_k (F_c(e_k) − F_c(0)), one probe per scalar unknown (a few dozen here); a function that
accepts stacked values (a leading probe axis: ``stacked=True``) is called once for all probes. The conic
form goes to Clarabel as ``A x̃ + s = b, s ∈ K`` with one PSD-triangle cone per LMI: s = svec(F_c(x) − t I),
svec = the upper triangle by columns with the off-diagonal entries × √2 (Clarabel's convention), symmetrized
first. This is what cvxpy would hand Clarabel for the same problem, without cvxpy's import (~50 MB and ~1–2 s
per process) or its canonicalization; tests/critical/test_sdp.py checks t* against cvxpy on random systems.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import sparse

from netkf_cli.core.tolerances import SOLVER_TOL

STATUS = {"Solved": "optimal", "AlmostSolved": "optimal_inaccurate", "PrimalInfeasible": "infeasible",
          "DualInfeasible": "unbounded", "AlmostPrimalInfeasible": "infeasible_inaccurate",
          "AlmostDualInfeasible": "unbounded_inaccurate"}
"""Clarabel's status → the names cvxpy reports (kept so the statuses netkf records read as before)."""


class SDPError(RuntimeError):
    """Clarabel raised while solving (a solver crash, not an infeasible problem)."""


@dataclass(frozen=True)
class Var:
    """A matrix unknown: ``shape`` (rows, cols); ``symmetric`` ones are parametrized by their upper triangle."""

    shape: tuple[int, int]
    symmetric: bool = False

    def units(self) -> list[np.ndarray]:
        """The basis matrices of this unknown, one per scalar degree of freedom."""
        r, c = self.shape
        out = []
        for j in range(c):
            for i in range(j + 1 if self.symmetric else r):
                E = np.zeros((r, c))
                E[i, j] = 1.0
                if self.symmetric:
                    E[j, i] = 1.0
                out.append(E)
        return out


@functools.cache
def _svec_index(d: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and scales of Clarabel's PSD-triangle order for a d×d matrix (by column, then row)."""
    j, i = np.nonzero(np.tril(np.ones((d, d))))  # (j, i) with i ≤ j, j-major: the upper triangle by columns
    return i, j, np.where(i == j, 1.0, math.sqrt(2.0))


def svec(M: np.ndarray) -> np.ndarray:
    """Clarabel's PSD-triangle vector of the symmetric part of M: upper triangle by columns, off-diagonal × √2
    (over the last two axes: a stack of matrices gives a stack of vectors)."""
    i, j, scale = _svec_index(M.shape[-1])
    return 0.5 * (M[..., i, j] + M[..., j, i]) * scale


def _svec_order(length: int) -> int:
    """d with d(d+1)/2 = ``length``."""
    return int(round((math.sqrt(8 * length + 1) - 1) / 2))


@dataclass
class Solution:
    """t*, the unknowns' values (None when Clarabel returned no point) and the status (cvxpy's names)."""

    t: float
    values: list[np.ndarray] | None
    status: str


def probes(variables: list[Var], lmis: Callable, *, stacked: bool = False) -> list[tuple[np.ndarray, bool]]:
    """[(V_c, margin), …]: V_c[0] = svec F_c(0) and V_c[1 + k] = svec F_c(e_k) for each basis unknown e_k
    (:meth:`Var.units`, in order), shaped (1 + unknowns, d(d+1)/2).

    ``stacked``: ``lmis`` is called once with every unknown's values stacked on a leading probe axis (zero at probe
    0, the k-th basis matrix at probe 1 + k) and returns stacked F_c; else once per probe with plain matrices."""
    units = [(i, E) for i, v in enumerate(variables) for E in v.units()]  # (which unknown, basis matrix)
    if stacked:
        vals = [np.zeros((1 + len(units),) + v.shape) for v in variables]
        for k, (i, E) in enumerate(units):
            vals[i][1 + k] = E
        return [(svec(F), margin) for F, margin in lmis(vals)]
    zero = [np.zeros(v.shape) for v in variables]
    base = lmis(zero)
    out = [[svec(F0)] for F0, _ in base]
    for i, E in units:
        vals = [z.copy() for z in zero]
        vals[i] = E
        for c, (F, _) in enumerate(lmis(vals)):
            out[c].append(svec(F))
    return [(np.stack(o), margin) for o, (_, margin) in zip(out, base)]


def max_margin(variables: list[Var], lmis: Callable[[list[np.ndarray]], list[tuple[np.ndarray, bool]]], *,
               stacked: bool = False) -> Solution:
    """Maximize t subject to the LMIs ``lmis(values)`` = [(F_c, margin), …] and t ≤ 1 (module docstring).

    ``lmis`` must be affine in the values (it is evaluated at 0 and at each basis unknown: :func:`probes`;
    ``stacked``: all at once).
    """
    import clarabel  # here, not at module level: only the critical-rate analysis solves an SDP (~2 MB, 0.1 s per process)

    units = [(i, E) for i, v in enumerate(variables) for E in v.units()]  # (which unknown, basis matrix)
    zero = [np.zeros(v.shape) for v in variables]
    nx = len(units)
    rows_A, b, cones = [], [], []
    for V, margin in probes(variables, lmis, stacked=stacked):
        d = _svec_order(V.shape[1])
        block = np.zeros((V.shape[1], nx + 1))
        block[:, :nx] = -(V[1:] - V[0]).T  # the coefficient of unknown k: −(F_c(e_k) − F_c(0))
        if margin:
            block[:, nx] = svec(np.eye(d))
        rows_A.append(block)
        b.append(V[0])
        cones.append(clarabel.PSDTriangleConeT(d))
    t_row = np.zeros((1, nx + 1))
    t_row[0, nx] = 1.0  # s = 1 − t ≥ 0
    rows_A.append(t_row)
    b.append(np.ones(1))
    cones.append(clarabel.NonnegativeConeT(1))
    A = sparse.csc_matrix(np.vstack(rows_A))
    q = np.zeros(nx + 1)
    q[nx] = -1.0
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = SOLVER_TOL  # Clarabel's defaults, stated once
    try:
        sol = clarabel.DefaultSolver(sparse.csc_matrix((nx + 1, nx + 1)), q, A, np.concatenate(b), cones,
                                     settings).solve()
    except Exception as exc:  # pragma: no cover - a solver crash (Clarabel raises its own Rust panics as Python errors)
        raise SDPError(str(exc)) from None
    status = STATUS.get(str(sol.status).split(".")[-1], str(sol.status))
    x = np.asarray(sol.x, dtype=float)
    if x.size != nx + 1 or not np.all(np.isfinite(x)):
        return Solution(math.nan, None, status)
    values = [z.copy() for z in zero]
    for k, (i, E) in enumerate(units):
        values[i] = values[i] + x[k] * E
    return Solution(float(x[nx]), values, status)
