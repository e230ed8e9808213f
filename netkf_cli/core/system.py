"""The plant x_{k+1} = A x_k + w_k, y_k = C x_k + v_k (eqs 1–2, Shi 2009), validated once.

Every shape and definiteness problem is reported at once, with the field it belongs to
(``system.Q: must be positive semi-definite, min eigenvalue -0.3``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.core.tolerances import PSD_INPUT_TOL, SYM_TOL


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
    """(A, C, Q, R, P0) as float64 2-D arrays; ``P0`` is ``None`` for "steady" (use P̄).

    ``sensors`` groups the output rows into sensors (the one sensor model of netkf): sensor i
    measures ``y_i = C[rows_i] x + v_i`` with noise covariance ``R[rows_i, rows_i]``. ``None`` (no
    ``system.sensors`` block) means one sensor per output row. A channel's arrival stream s carries
    sensor s's whole measurement; a channel with one stream carries all of y_k (every sensor) in one
    packet (:func:`netkf_cli.linalg.kalman.stream_rows`).
    """

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P0: np.ndarray | None = None
    sensors: tuple[tuple[int, ...], ...] | None = None

    @property
    def sensor_rows(self) -> tuple[tuple[int, ...], ...]:
        """Row indices of C per sensor (default: one sensor per output row)."""
        return self.sensors if self.sensors is not None else tuple((i,) for i in range(self.m))

    @property
    def n_sensors(self) -> int:
        return len(self.sensor_rows)

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def m(self) -> int:
        return self.C.shape[0]

    @classmethod
    def create(cls, A, C, Q, R, P0=None, prefix: str = "system", sensors=None) -> "LinearSystem":
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
            problems.append(Problem(f"{prefix}.C", f"must have {A.shape[1]} column{'s' if A.shape[1] != 1 else ''} (the state dimension of A), got shape {C.shape[0]}×{C.shape[1]}"))
        m = C.shape[0]
        if Q.shape != (n, n):
            problems.append(Problem(f"{prefix}.Q", f"must be {n}×{n} like A, got {Q.shape[0]}×{Q.shape[1]}"))
        elif _check_symmetric(Q, f"{prefix}.Q", problems):
            e = _eig_min(Q)
            if e < -PSD_INPUT_TOL * max(1.0, float(np.abs(Q).max())):
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
                if e < -PSD_INPUT_TOL * max(1.0, float(np.abs(P0a).max())):
                    problems.append(Problem(f"{prefix}.P0", f"must be positive semi-definite, smallest eigenvalue is {e:.4g}"))
        if sensors is not None:
            rows = sorted(r for g in sensors for r in g)
            if rows != list(range(m)) or any(len(g) == 0 for g in sensors):
                problems.append(Problem(f"{prefix}.sensors", f"the sensors must partition the {m} output rows of C, "
                                                             f"got {[list(g) for g in sensors]}"))
        if problems:
            raise ConfigError(problems)
        sym = lambda X: (X + X.T) / 2  # noqa: E731
        groups = None if sensors is None else tuple(tuple(int(r) for r in g) for g in sensors)
        return cls(A=A, C=C, Q=sym(Q), R=sym(R), P0=None if P0a is None else sym(P0a), sensors=groups)

    @classmethod
    def from_spec(cls, spec, prefix: str = "system") -> "LinearSystem":
        """Build from a scenario's ``system`` block (``P0: steady`` → ``None``)."""
        P0 = None if (spec.P0 is None or spec.P0 == "steady") else spec.P0
        C, R, groups = stacked_sensors(spec, prefix)
        return cls.create(spec.A, C, spec.Q, R, P0, prefix=prefix, sensors=groups)

    def with_P0(self, P0: np.ndarray | None) -> "LinearSystem":
        return LinearSystem(self.A, self.C, self.Q, self.R, P0, self.sensors)

    def sensor(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(C_i, R_i) of sensor i."""
        rows = list(self.sensor_rows[i])
        return self.C[rows], self.R[np.ix_(rows, rows)]

    def is_observable(self) -> bool:
        n = self.n
        O = np.vstack([self.C @ np.linalg.matrix_power(self.A, i) for i in range(n)])
        return np.linalg.matrix_rank(O) == n


def stacked_sensors(spec, prefix: str = "system"):
    """(C, R, row groups) of a ``system`` block: without ``sensors`` the block's own C and R (groups
    ``None``: one sensor per row); ``sensors: N`` stacks N identical copies of (C, R); a list of
    ``{C, R}`` stacks the sensors' own matrices (``R`` block-diagonal: sensors' noises independent)."""
    sensors = getattr(spec, "sensors", None)
    if sensors is None:
        return spec.C, spec.R, None
    if isinstance(sensors, int):
        if spec.C is None or spec.R is None:
            raise ConfigError.at(f"{prefix}.sensors", "`sensors: N` copies system.C and system.R N times: give both")
        C1, R1 = np.atleast_2d(np.asarray(spec.C, float)), np.atleast_2d(np.asarray(spec.R, float))
        Cs, Rs = [C1] * sensors, [R1] * sensors
    else:
        if spec.C is not None or spec.R is not None:
            raise ConfigError.at(f"{prefix}.sensors", "a list of sensors gives each sensor's C and R: leave system.C "
                                                      "and system.R out (they are the stacked sensors)")
        Cs = [np.atleast_2d(np.asarray(s.C, float)) for s in sensors]
        Rs = [np.atleast_2d(np.asarray(s.R, float)) for s in sensors]
        widths = {c.shape[1] for c in Cs}
        if len(widths) != 1:
            raise ConfigError.at(f"{prefix}.sensors", f"every sensor's C must have n columns, got widths {sorted(widths)}")
        for i, (c, r) in enumerate(zip(Cs, Rs)):
            if r.shape != (c.shape[0], c.shape[0]):
                raise ConfigError.at(f"{prefix}.sensors[{i}].R", f"must be {c.shape[0]}×{c.shape[0]} (one row per "
                                                                  f"output of this sensor's C), got {r.shape[0]}×{r.shape[1]}")
    groups, start = [], 0
    for c in Cs:
        groups.append(tuple(range(start, start + c.shape[0])))
        start += c.shape[0]
    R = np.zeros((start, start))
    for g, r in zip(groups, Rs):
        R[np.ix_(g, g)] = r
    return np.vstack(Cs), R, tuple(groups)
