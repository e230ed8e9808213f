"""The Scenario: one YAML file = one artefact (system, channel, estimator, analysis, Monte Carlo).

Components are chosen by ``kind``. The unions are built from every subclass of
:class:`~netkf_cli.core.spec.ChannelModel`, :class:`~netkf_cli.core.spec.EstimatorModel` and
:class:`~netkf_cli.core.spec.AnalysisModel` defined in the modules of ``netkf_cli/channels``,
``netkf_cli/estimators`` and ``netkf_cli/recipes``: a new kind is a new class in a new
module, with no edit here.
"""

from __future__ import annotations

import importlib
import pkgutil
from functools import lru_cache
from typing import Annotated, Any, Literal, Union

from pydantic import AfterValidator, BeforeValidator, Field, create_model, model_validator

from netkf_cli.core.errors import ConfigError
from netkf_cli import channels, estimators, metrics, recipes
from netkf_cli.core.spec import (
    AnalysisModel,
    ChannelModel,
    EstimatorModel,
    Matrix,
    NonNegInt,
    PositiveInt,
    StrictModel,
    _integer_input,
)
from netkf_cli.config.sweep import SweepSpec
from netkf_cli.core.system import LinearSystem

_PACKAGES = (channels, estimators, recipes, metrics)


def _import_all() -> None:
    for pkg in _PACKAGES:
        for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
            if not info.name.startswith("_"):
                importlib.import_module(f"{pkg.__name__}.{info.name}")


def _subclasses(base: type) -> list[type]:
    out, todo = [], list(base.__subclasses__())
    while todo:
        c = todo.pop(0)
        todo.extend(c.__subclasses__())
        if "kind" in getattr(c, "model_fields", {}):
            out.append(c)
    seen: dict[str, type] = {}
    for c in out:
        ann = c.model_fields["kind"].annotation
        for k in getattr(ann, "__args__", ()):
            if k in seen and seen[k] is not c:
                raise TypeError(f"kind {k!r} defined twice: {seen[k].__module__} and {c.__module__}")
            seen[k] = c
    return sorted(out, key=lambda c: (c.__module__, c.__name__))


def _union(base: type):
    members = _subclasses(base)
    if not members:
        return None
    if len(members) == 1:
        return members[0]
    return Annotated[Union[tuple(members)], Field(discriminator="kind")]


def kinds(base: type) -> dict[str, type]:
    """``{kind: model class}`` for a component family (after discovery)."""
    _import_all()
    out = {}
    for c in _subclasses(base):
        for k in c.model_fields["kind"].annotation.__args__:
            out[k] = c
    return out


class SensorSpec(StrictModel):
    """One sensor of ``system.sensors``: y_i = C_i x + v_i, v_i ~ N(0, R_i), independent of the other sensors."""

    C: Matrix = Field(description="this sensor's output matrix C_i (m_i×n)")
    R: Matrix = Field(description="this sensor's measurement-noise covariance R_i (m_i×m_i, symmetric PD)")


class SystemSpec(StrictModel):
    """``system:`` x_{k+1} = A x_k + w_k, y_k = C x_k + v_k; w ~ N(0, Q), v ~ N(0, R), x_0 ~ N(0, P0)."""

    A: Matrix = Field(description="state matrix A (n×n): x_{k+1} = A x_k + w_k")
    C: Matrix | None = Field(None, description="output matrix C (m×n): y_k = C x_k + v_k (with `sensors: N`: one "
                                               "sensor's C; left out with a list of sensors)")
    Q: Matrix = Field(description="process-noise covariance Q (n×n, symmetric PSD)")
    R: Matrix | None = Field(None, description="measurement-noise covariance R (m×m, symmetric PD; with `sensors: N`: "
                                               "one sensor's R; left out with a list of sensors)")
    sensors: Annotated[int, Field(ge=1, le=10_000)] | list[SensorSpec] | None = Field(
        None, description="the sensors (one channel stream each): unset = one sensor per output row of C; N = N "
                          "identical sensors each measuring C x with noise R (stacked: C ⊗ 1_N, R block-diagonal); "
                          "a list of {C, R} = sensors with their own matrices")
    P0: Matrix | Literal["steady"] | None = Field(
        None, description="error covariance of the estimate at k = 0, P_{0|0} (n×n PSD); unset or 'steady' = P̄, "
        "the steady-state filtered covariance with every packet received")

    @model_validator(mode="after")
    def _sensors_or_C(self):
        if self.sensors is None or isinstance(self.sensors, int):
            missing = [k for k in ("C", "R") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"{' and '.join(missing)} required (or a list of `sensors`, each with its C and R)")
        return self

    def build(self) -> LinearSystem:
        return LinearSystem.from_spec(self)


MAX_RUNS = 10**12
"""Default ``montecarlo.max_runs``: 10¹² runs (weeks on one machine) is the largest run count
accepted without ``--yes``."""
MAX_DPI = 1200
"""Largest figure resolution: a 6.4 × 4.4 in figure at 1200 dpi is already 40 megapixels."""
MAX_NAME = 100
"""Longest ``name`` (it names files and folders, with suffixes, within the file system's 255 bytes)."""


def _check_name(v: str) -> str:
    if set(v) <= {"."}:
        raise ValueError(f"must name a folder, got {v!r} (a name of dots only means the current or parent folder)")
    if v.startswith("."):
        raise ValueError(f"must not start with a dot (a hidden folder), got {v!r}")
    return v


class MonteCarloSpec(StrictModel):
    """``montecarlo:`` size and seeding. Chunk i of stream s draws from SeedSequence(seed, spawn_key=(s, i))."""

    runs: PositiveInt = Field(100_000, description="independent runs (samples)")
    horizon: PositiveInt = Field(200, description="time steps per run")
    burn_in: NonNegInt = Field(0, description="steps discarded before time-averaged statistics are taken (must be < horizon)")
    seed: NonNegInt = Field(0, description="root seed")
    chunk: PositiveInt = Field(20_000, description="runs per chunk (memory bound; part of the random stream layout)")
    quick_runs: PositiveInt | None = Field(None, description="Monte Carlo size under `netkf reproduce --quick` (default: min(runs, 2000))")
    max_runs: PositiveInt = Field(MAX_RUNS, description="largest `runs` accepted without `netkf run --yes` (a guard "
                                  "against a typo such as runs: 1e15; not part of the scenario hash)")

    def quick_size(self) -> int:
        return self.quick_runs if self.quick_runs is not None else min(self.runs, 2000)


class OutputSpec(StrictModel):
    """``output:`` where and how results are written."""

    dir: str = Field("results", description="parent folder of the result folder <dir>/<name>/")
    dpi: Annotated[int, Field(gt=0, le=MAX_DPI), BeforeValidator(_integer_input)] = Field(
        150, description=f"resolution of the PNG figure (dots per inch, at most {MAX_DPI})")
    formats: list[Literal["png", "pdf", "svg"]] = Field(
        default_factory=lambda: ["png"], min_length=1,
        description="figure formats written as <name>.<format>, the same figure in each (png, pdf, svg)")


@lru_cache(maxsize=1)
def scenario_model() -> type[StrictModel]:
    """Build the Scenario model from the discovered component kinds."""
    _import_all()
    ch, es, an = _union(ChannelModel), _union(EstimatorModel), _union(AnalysisModel)
    fields: dict[str, Any] = {
        "name": (Annotated[str, Field(pattern=r"^[A-Za-z0-9_.-]+$", max_length=MAX_NAME,
                                      description=f"artefact name (result folder; letters, digits, _ . -; at most "
                                                  f"{MAX_NAME} characters)"), AfterValidator(_check_name)], ...),
        "description": (str, Field("", description="free text, copied into the manifest")),
        "system": (SystemSpec | None, Field(None, description="the plant x_{k+1} = A x_k + w_k, y_k = C x_k + v_k")),
        "channel": ((ch | None) if ch is not None else None,
                    Field(None, description="the network between sensor and estimator, chosen by kind (netkf list)")),
        "estimator": ((es | None) if es is not None else None,
                      Field(None, description="the estimator, chosen by kind (netkf list)")),
        "estimators": ((list[es] | None) if es is not None else None,
                       Field(None, description="several estimators instead of one: the generic metrics run them "
                                               "on the same sampled traces (common random numbers)")),
        "analysis": (an, Field(description="what to compute: a generic metric or a paper artefact, chosen by kind")),
        "montecarlo": (MonteCarloSpec, Field(MonteCarloSpec(), description="Monte Carlo size, horizon and seeding")),
        "output": (OutputSpec, Field(OutputSpec(), description="where and in which formats results are written")),
        "sweep": (SweepSpec | None, Field(None, description="optional parameter sweep over dotted field paths")),
    }
    return create_model("Scenario", __base__=ScenarioBase, **fields)


class ScenarioBase(StrictModel):
    """Shared behaviour of the generated Scenario model."""

    def linear_system(self) -> LinearSystem:
        if self.system is None:  # type: ignore[attr-defined]
            raise ConfigError.at("system", "this analysis needs a `system:` block (A, C, Q, R)")
        return self.system.build()  # type: ignore[attr-defined]

    def require_channel(self, *allowed: str):
        ch = self.channel  # type: ignore[attr-defined]
        if ch is None or (allowed and ch.kind not in allowed):
            got = "none" if ch is None else ch.kind
            raise ConfigError.at("channel.kind", f"this analysis needs a channel of kind {' or '.join(allowed)}, got {got}")
        return ch

    def estimator_list(self) -> list:
        """The scenario's estimators as a list (``estimator:`` one, or ``estimators:`` several)."""
        if self.estimators:  # type: ignore[attr-defined]
            return list(self.estimators)  # type: ignore[attr-defined]
        return [] if self.estimator is None else [self.estimator]  # type: ignore[attr-defined]

    def require_estimator(self, *allowed: str):
        es = self.estimator  # type: ignore[attr-defined]
        if es is None and self.estimators:  # type: ignore[attr-defined]
            raise ConfigError.at("estimators", "this analysis takes one `estimator:`; `estimators:` (a list) is for "
                                 "the generic metrics (distribution, mean_vs_time, compare)")
        if es is None or (allowed and es.kind not in allowed):
            got = "none" if es is None else es.kind
            raise ConfigError.at("estimator.kind", f"this analysis needs an estimator of kind {' or '.join(allowed)}, got {got}")
        return es


def json_schema() -> dict:
    """JSON Schema of a scenario file (``netkf schema``), for editor completion."""
    return scenario_model().model_json_schema()
