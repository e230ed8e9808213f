"""The plant x_{k+1} = A x_k + w_k, y_k = C x_k + v_k (eqs 1–2, Shi 2009), validated once.

Every shape and definiteness problem is reported at once, with the field it belongs to
(``system.Q: must be positive semi-definite, min eigenvalue -0.3``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from netkf_cli.errors import ConfigError, Problem

SYM_TOL = 1e-9


def _eig_min(X: np.ndarray) -> float:
    return float(np.linalg.eigvalsh((X + X.T) / 2).min())


def _check_symmetric(X: np.ndarray, name: str, problems: list[Problem]) -> bool:
    if X.shape[0] != X.shape[1]:
        problems.append(Problem(name, f"must be square, got shape {X.shape[0]}×{X.shape[1]}"))
        return False
    scale = max(1.0, float(np.abs(X).max()))
    if not np.allclose(X, X.T, atol=SYM_TOL * scale, rtol=0):
        problems.append(Problem(name, "must be symmetric"))
        return False
    return True


@dataclass(frozen=True, eq=False)
class LinearSystem:
    """(A, C, Q, R, P0) as float64 2-D arrays; ``P0`` is ``None`` for "steady" (use P̄)."""

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P0: np.ndarray | None = None

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def m(self) -> int:
        return self.C.shape[0]

    @classmethod
    def create(cls, A, C, Q, R, P0=None, prefix: str = "system") -> "LinearSystem":
        """Validate and build. Scalars are promoted to 1×1. Raises ConfigError listing every problem."""
        problems: list[Problem] = []

        def arr(x, name):
            a = np.atleast_2d(np.asarray(x, dtype=float))
            if a.ndim != 2:
                problems.append(Problem(f"{prefix}.{name}", f"must be a matrix, got {a.ndim}-D"))
            if not np.all(np.isfinite(a)):
                problems.append(Problem(f"{prefix}.{name}", "entries must be finite"))
            return a

        A, C, Q, R = arr(A, "A"), arr(C, "C"), arr(Q, "Q"), arr(R, "R")
        P0a = None if P0 is None else arr(P0, "P0")
        if problems:
            raise ConfigError(problems)
        n = A.shape[0]
        if A.shape[0] != A.shape[1]:
            problems.append(Problem(f"{prefix}.A", f"must be square (n×n), got shape {A.shape[0]}×{A.shape[1]}"))
            n = A.shape[0]
        if C.shape[1] != A.shape[1]:
            problems.append(Problem(f"{prefix}.C", f"must have {A.shape[1]} columns (the state dimension of A), got shape {C.shape[0]}×{C.shape[1]}"))
        m = C.shape[0]
        if Q.shape != (n, n):
            problems.append(Problem(f"{prefix}.Q", f"must be {n}×{n} like A, got {Q.shape[0]}×{Q.shape[1]}"))
        elif _check_symmetric(Q, f"{prefix}.Q", problems):
            e = _eig_min(Q)
            if e < -SYM_TOL * max(1.0, float(np.abs(Q).max())):
                problems.append(Problem(f"{prefix}.Q", f"must be positive semi-definite (Q ≥ 0), smallest eigenvalue is {e:.4g}"))
        if R.shape != (m, m):
            problems.append(Problem(f"{prefix}.R", f"must be {m}×{m} (one row per output of C), got {R.shape[0]}×{R.shape[1]}"))
        elif _check_symmetric(R, f"{prefix}.R", problems):
            e = _eig_min(R)
            if e <= 0:
                problems.append(Problem(f"{prefix}.R", f"must be positive definite (R > 0), smallest eigenvalue is {e:.4g}"))
        if P0a is not None:
            if P0a.shape != (n, n):
                problems.append(Problem(f"{prefix}.P0", f"must be {n}×{n} like A, got {P0a.shape[0]}×{P0a.shape[1]}"))
            elif _check_symmetric(P0a, f"{prefix}.P0", problems):
                e = _eig_min(P0a)
                if e < -SYM_TOL * max(1.0, float(np.abs(P0a).max())):
                    problems.append(Problem(f"{prefix}.P0", f"must be positive semi-definite, smallest eigenvalue is {e:.4g}"))
        if problems:
            raise ConfigError(problems)
        sym = lambda X: (X + X.T) / 2  # noqa: E731
        return cls(A=A, C=C, Q=sym(Q), R=sym(R), P0=None if P0a is None else sym(P0a))

    @classmethod
    def from_spec(cls, spec, prefix: str = "system") -> "LinearSystem":
        """Build from a scenario's ``system`` block (``P0: steady`` → ``None``)."""
        P0 = None if (spec.P0 is None or spec.P0 == "steady") else spec.P0
        return cls.create(spec.A, spec.C, spec.Q, spec.R, P0, prefix=prefix)

    def with_P0(self, P0: np.ndarray | None) -> "LinearSystem":
        return LinearSystem(self.A, self.C, self.Q, self.R, P0)

    def is_observable(self) -> bool:
        n = self.n
        O = np.vstack([self.C @ np.linalg.matrix_power(self.A, i) for i in range(n)])
        return np.linalg.matrix_rank(O) == n
