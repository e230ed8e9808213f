"""Pydantic building blocks shared by every scenario component.

Components are chosen by ``kind`` (discriminated unions, built in ``scenario.py`` from
every subclass of :class:`ChannelModel`, :class:`EstimatorModel`, :class:`AnalysisModel`
found under ``netkf_cli/channels``, ``netkf_cli/estimators`` and ``netkf_cli/recipes``).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, ClassVar

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field


class StrictModel(BaseModel):
    """Unknown keys are errors (a typo must never be silently ignored); models are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class ChannelModel(StrictModel):
    """Base of every channel kind (``kind: delay | bernoulli | fading | ...``).

    Contract (issue 12): ``sample_trace(rng, runs, horizon) -> Trace`` samples a batch of runs
    into the one trace type of :mod:`netkf_cli.core.trace` (run axis innermost); ``trace_kinds`` names
    the trace fields it fills. What closed forms can use is exposed as methods where it exists:
    ``loss_rate()`` (stationary probability that a packet is not usable), ``delay_pmf(n)``,
    ``snr_law()``.
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset()

    def sample_trace(self, rng: Any, runs: int, horizon: int) -> Any:  # pragma: no cover - interface
        raise NotImplementedError(f"channel kind {getattr(self, 'kind', '?')} has no sample_trace")


class EstimatorModel(StrictModel):
    """Base of every estimator kind (``kind: kf | buffered | smart_sensor | ...``).

    Contract (the Kalman core issue): every estimator is written on :mod:`netkf_cli.linalg.kalman`.

    * ``accepts`` names the trace fields it can work from (at least one must be in the channel's
      ``trace_kinds``; ``netkf validate`` refuses other pairs);
    * ``quantities`` names what it reports at step k — ``filtered`` P_{k|k}, ``predicted``
      P_{k+1|k}, ``smoothed`` P_{k−N|k} (``kalman.SYMBOL``) — all from P0 = P_{0|0}
      (``system.P0``; unset = P̄) on one time base: step k = 1 … horizon is the time of the
      newest measurement y_k that could have been used;
    * ``check(system, channel)`` raises a ConfigError for a pair that cannot work (dimensions,
      a stream count that is not the system's sensors, invertibility …);
    * ``covariances(system, trace, steps, quantities)`` yields ``(k, {quantity: P_k})`` for each k
      in ``steps`` (ascending, ``first_step(q) ≤ k ≤ horizon``), ``P_k`` shaped ``(n, n, runs)``.
      Per-run overflow is ``inf`` in P, never an exception;
    * ``conventions(system, channel)`` the conventions its numbers depend on (labels for the CSV
      and the figure: buffer convention, packet content …).
    """

    accepts: ClassVar[frozenset[str]] = frozenset()
    quantities: ClassVar[tuple[str, ...]] = ("filtered",)

    def check(self, system: Any, channel: Any) -> None:
        """Raise ConfigError if this estimator cannot run on ``system`` with ``channel``."""

    def first_step(self, quantity: str) -> int:
        """The first step k at which ``quantity`` is defined (a lag-N smoother: N)."""
        return 1

    def for_means(self, channel: Any) -> "EstimatorModel":
        """The estimator to use where only means of P are taken (a metric of means): itself, or a
        variance-reduced twin whose per-run values are unbiased estimates of E[P_k] (``auto`` options)."""
        return self

    def per_run_covariance(self) -> bool:
        """Whether each run's reported P is that run's own covariance (False for a variance-reduced
        estimator that yields per-run estimates of E[P_k]: only means may then be taken)."""
        return True

    def backend_used(self, system: Any, channel: Any, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """The recursion backend a chunk of ``runs`` × ``horizon`` runs on (recorded in the manifest).
        ``steps``/``quantities``: what the chunk reports, for an estimator whose choice depends on them. An
        estimator with a ``backend: auto`` field overrides this with its resolved choice (tested: no manifest
        says "auto")."""
        return str(getattr(self, "backend", "numpy"))

    def conventions(self, system: Any, channel: Any) -> dict[str, str]:
        """Conventions its numbers depend on, as short ``{name: value}`` labels (default none)."""
        return {}

    def covariances(self, system: Any, trace: Any, steps: Any, quantities: Any = ("filtered",)) -> Any:  # pragma: no cover
        raise NotImplementedError(f"estimator kind {getattr(self, 'kind', '?')} has no covariances()")


class AnalysisModel(StrictModel):
    """Base of every artefact family. Subclasses implement ``compute`` and ``plot``.

    ``compute(scenario, ctx) -> Artefact`` and ``plot(tables, scenario) -> Figure``; the
    figure is drawn from the tables alone.
    """

    def compute(self, scenario: Any, ctx: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def plot(self, tables: Any, scenario: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError


def _to_matrix(value: Any) -> list[list[float]]:
    """Accept a scalar, a flat list (a row... no: a column is ambiguous) or nested lists."""
    if isinstance(value, bool):
        raise ValueError("expected a number or a matrix (nested lists), got a boolean")
    if isinstance(value, (int, float)):
        rows = [[float(value)]]
    elif isinstance(value, (list, tuple)):
        if len(value) == 0:
            raise ValueError("expected a non-empty matrix")
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            rows = [[float(v) for v in value]]  # a flat list is one row
        elif all(isinstance(v, (list, tuple)) for v in value):
            rows = []
            for i, row in enumerate(value):
                if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in row):
                    raise ValueError(f"row {i} must contain numbers only, got {row!r}")
                rows.append([float(v) for v in row])
            widths = {len(r) for r in rows}
            if len(widths) != 1 or 0 in widths:
                raise ValueError(f"rows have different lengths {sorted(widths)}: not a matrix")
        else:
            raise ValueError("expected a number, a list of numbers or a list of rows")
    else:
        raise ValueError(f"expected a number or a matrix (nested lists), got {type(value).__name__}")
    for r in rows:
        for v in r:
            if not math.isfinite(v):
                raise ValueError("entries must be finite numbers")
    return rows


# json_schema_input_type: the schema states what a scenario may write (what _to_matrix accepts), not the
# nested lists it becomes, so that an editor does not flag ``A: 1.4``.
Matrix = Annotated[list[list[float]],
                   BeforeValidator(_to_matrix, json_schema_input_type=float | list[float] | list[list[float]])]
"""A real matrix: a scalar (1×1), a flat list (one row) or nested lists of rows."""


def _finite(v: float) -> float:
    if not math.isfinite(v):
        raise ValueError("must be a finite number")
    return v


def _integer_input(v: Any) -> Any:
    """Integers only from numbers: ``runs: yes``/``true``/``"5"`` are refused; ``5.0`` or ``1e6``
    (an integral float) is accepted as exactly that integer, ``2.5`` is refused by pydantic."""
    if isinstance(v, bool):
        raise ValueError("expected an integer, got a boolean")
    if isinstance(v, str):
        raise ValueError(f"expected an integer, got the text {v!r}")
    if isinstance(v, float) and not math.isfinite(v):
        raise ValueError("must be a finite number")
    return v


Probability = Annotated[float, Field(ge=0.0, le=1.0)]
# The bound comes before the BeforeValidator: Annotated metadata applies left to right, and a constraint placed
# after a validator is enforced by a separate check that the JSON schema shows as non-standard "gt"/"ge" keys
# (editors then accept ``runs: 0``); placed first, it is the int schema's own bound (exclusiveMinimum/minimum).
PositiveInt = Annotated[int, Field(gt=0), BeforeValidator(_integer_input)]
NonNegInt = Annotated[int, Field(ge=0), BeforeValidator(_integer_input)]
PositiveFloat = Annotated[float, Field(gt=0.0), AfterValidator(_finite)]
NonNegFloat = Annotated[float, Field(ge=0.0), AfterValidator(_finite)]
FiniteFloat = Annotated[float, AfterValidator(_finite)]
