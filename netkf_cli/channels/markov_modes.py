"""Markov-chain measurement modes (Moayedi, Soh & Foo 2009, Sec. II).

At every time ``k`` the receiver gets ``y(k)`` through one of four modes (eqs 8–19):

====  =====================  ==========================================
 q    name                   what arrives
====  =====================  ==========================================
 1    ``ok``                 ``y(k) = z(k) = C x(k) + v(k)``
 2    ``delay``              ``y(k) = z(k−1)`` (one-step sensor delay)
 3    ``missing``            ``y(k) = v(k)`` (measurement is noise only)
 4    ``dropout``            ``y(k) = y(k−1)`` (packet lost, hold last)
====  =====================  ==========================================

The mode sequence is a Markov chain with ``ρ_{q/j} = Prob(mode q at k | mode j at k−1)``
(eq. 20). We store it as the row-stochastic matrix ``transition[j−1][q−1] = ρ_{q/j}``
(row = previous mode, column = next mode). Its stationary distribution is the marginal
``ρ_q = Σ_j ρ_{q/j} ρ_j`` (text after eq. 20). Remark 2.1's precedence constraint
``ρ_{2/1} = 0`` (a packet cannot arrive twice) is the user's responsibility: a chain that
violates it is accepted with a warning.

Modes are returned 0-based (``q − 1``) as ``int8`` arrays of shape ``(runs, horizon)``.
"""

from __future__ import annotations

import warnings
from typing import ClassVar, Literal, Union

import numpy as np
from pydantic import Field, model_validator

from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.core.spec import ChannelModel, Matrix, Probability
from netkf_cli.core.trace import Trace
from netkf_cli.core.tolerances import STOCHASTIC_ROW_TOL

MODE_NAMES = ("ok", "delay", "missing", "dropout")
N_MODES = 4


class PrecedenceWarning(UserWarning):
    """The chain allows mode 2 (delay) right after mode 1 (ρ_{2/1} ≠ 0, Remark 2.1)."""


def validate_transition(T, path: str = "channel.transition") -> np.ndarray:
    """Check ``T`` is a 4×4 row-stochastic matrix; return it as float64. Raises ConfigError."""
    T = np.asarray(T, dtype=float)
    problems: list[Problem] = []
    if T.shape != (N_MODES, N_MODES):
        raise ConfigError.at(path, f"must be 4×4 (modes 1 ok, 2 delay, 3 missing, 4 dropout), got shape {T.shape[0]}×{T.shape[1] if T.ndim > 1 else 1}")
    if not np.all(np.isfinite(T)):
        raise ConfigError.at(path, "entries must be finite")
    for j in range(N_MODES):
        row = T[j]
        if np.any(row < 0) or np.any(row > 1):
            problems.append(Problem(f"{path}[{j}]", f"ρ_{{q/{j + 1}}} must be probabilities in [0, 1], got {row.tolist()}"))
        elif abs(row.sum() - 1.0) > STOCHASTIC_ROW_TOL:
            problems.append(Problem(f"{path}[{j}]", f"row {j + 1} (from mode {j + 1}) must sum to 1, got {row.sum():.12g}"))
    if problems:
        raise ConfigError(problems)
    return T / T.sum(axis=1, keepdims=True)


def stationary_distribution(T: np.ndarray, path: str = "channel.transition") -> np.ndarray:
    """The unique ρ with ρ = Tᵀρ, Σρ = 1 (text after eq. 20). Error if it is not unique."""
    N = T.shape[0]
    M = np.vstack([T.T - np.eye(N), np.ones((1, N))])
    b = np.zeros(N + 1)
    b[-1] = 1.0
    rho, *_ = np.linalg.lstsq(M, b, rcond=None)
    # uniqueness: the eigenvalue 1 of T must be simple
    if np.linalg.matrix_rank(T.T - np.eye(N), tol=1e-10) != N - 1:
        raise ConfigError.at(path, "the chain has more than one stationary distribution (two or more closed "
                                   "classes of modes), so the marginals ρ_q are not defined")
    rho = np.clip(rho, 0.0, None)
    return rho / rho.sum()


def sample_modes(rng: np.random.Generator, runs: int, horizon: int, T: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """Mode paths θ(0..horizon−1), 0-based, ``int8`` of shape ``(runs, horizon)``.

    θ(0) ~ ``initial``; θ(k) | θ(k−1)=j ~ row j of ``T``. Vectorized over runs, loop over time
    (inverse-CDF sampling with one uniform per run and step). The transpose of
    :func:`sample_modes_tr` on the same generator state.
    """
    return np.ascontiguousarray(sample_modes_tr(rng, runs, horizon, T, initial).T)


def sample_modes_tr(rng: np.random.Generator, runs: int, horizon: int, T: np.ndarray, initial: np.ndarray) -> np.ndarray:
    """Mode paths in the trace layout ``(horizon, runs)`` int8 (run axis innermost), see :func:`sample_modes`."""
    cumT = np.cumsum(T, axis=1)
    cumT[:, -1] = 1.0
    cum0 = np.cumsum(initial)
    cum0[-1] = 1.0
    u = rng.random((horizon, runs))
    modes = np.empty((horizon, runs), dtype=np.int8)
    modes[0] = np.searchsorted(cum0, u[0], side="right")
    N = T.shape[0]
    for k in range(1, horizon):
        prev = modes[k - 1]
        acc = np.zeros(runs, dtype=np.int8)
        for q in range(N - 1):  # θ(k) = #{q < N−1 : u ≥ cumT[θ(k−1), q]}
            acc += u[k] >= cumT[prev, q]
        modes[k] = acc
    return modes


class MarkovModesChannel(ChannelModel):
    """``kind: markov_modes`` — the four-mode Markov chain of Moayedi, Soh & Foo 2009.

    ``transition[j][q] = ρ_{q+1/j+1}`` (row = previous mode). ``initial`` is the distribution
    of θ(0): ``stationary`` (default, so every θ(k) has the marginal ρ_q) or four numbers.
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"mode", "arrival"})

    kind: Literal["markov_modes"]
    transition: Matrix = Field(description="4×4 row-stochastic ρ_{q/j}: row j = previous mode, column q = next "
                                           "mode; modes 1 ok, 2 one-step delay, 3 missing (noise only), 4 dropout (hold)")
    initial: Union[Literal["stationary"], list[Probability]] = Field(
        "stationary", description="distribution of the mode at k = 0: 'stationary' or [p1, p2, p3, p4]")

    @model_validator(mode="after")
    def _check(self):
        try:
            T = validate_transition(self.transition, "transition")
        except ConfigError as e:
            raise ValueError("; ".join(p.render() for p in e.problems)) from None
        if isinstance(self.initial, list):
            if len(self.initial) != N_MODES:
                raise ValueError(f"initial: needs 4 probabilities (one per mode), got {len(self.initial)}")
            if abs(sum(self.initial) - 1.0) > STOCHASTIC_ROW_TOL:
                raise ValueError(f"initial: must sum to 1, got {sum(self.initial):.12g}")
        try:
            stationary_distribution(T, "transition")
        except ConfigError as e:
            raise ValueError("; ".join(p.render() for p in e.problems)) from None
        if T[0, 1] > 0:
            warnings.warn(
                f"channel.transition: ρ_{{2/1}} = {T[0, 1]:g} ≠ 0 violates the precedence constraint of "
                "Remark 2.1 (z(k−1) already arrived at k−1 cannot arrive again at k); the simulation follows "
                "the chain as given", PrecedenceWarning, stacklevel=2)
        return self

    @property
    def T(self) -> np.ndarray:
        """ρ_{q/j} as a float64 4×4 row-stochastic matrix (row = previous mode)."""
        return validate_transition(self.transition)

    @property
    def rho(self) -> np.ndarray:
        """Stationary marginals ρ_q, q = 1..4."""
        return stationary_distribution(self.T)

    @property
    def pi0(self) -> np.ndarray:
        """Distribution of θ(0)."""
        if self.initial == "stationary":
            return self.rho
        p = np.asarray(self.initial, dtype=float)
        return p / p.sum()

    def sample(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        """0-based modes, ``int8`` array ``(runs, horizon)`` (legacy layout; :meth:`sample_trace` is the contract)."""
        return sample_modes(rng, runs, horizon, self.T, self.pi0)

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """``Trace.mode`` (horizon, runs) int8, 0-based (q − 1), and ``Trace.arrival`` (1, horizon, runs):
        True in mode 1 only (the measurement of step k arrives on time; modes 2–4 deliver a delayed
        packet, noise only, or a held copy — for an estimator that works from arrivals they are
        unusable). ``meta`` carries the chain: ``transition`` (ρ_{q/j}), ``initial``, ``rho``."""
        T = self.T
        modes = sample_modes_tr(rng, runs, horizon, T, self.pi0)
        return Trace(runs=runs, horizon=horizon, mode=modes, arrival=(modes == 0)[None],
                     meta={"channel": "markov_modes", "transition": T.tolist(), "initial": self.pi0.tolist(),
                           "rho": self.rho.tolist(), "modes": list(MODE_NAMES)})

    def loss_rate(self) -> float:
        """Stationary probability that y(k) is not an on-time measurement: 1 − ρ_1 (modes 2–4)."""
        return float(1.0 - self.rho[0])
