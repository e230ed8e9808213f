"""What the generic metrics share: grids, estimator labels, the paper reference of a figure."""

from __future__ import annotations

import re
from contextlib import contextmanager
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from netkf_cli import engine
from netkf_cli.linalg import kalman
from netkf_cli.analysis import critical as cr
from netkf_cli.analysis import references
from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.core.spec import AnalysisModel, PositiveFloat, PositiveInt, StrictModel

Quantity = Literal["filtered", "predicted", "smoothed"]
LABEL_COLUMNS = ["quantity", "P0", "conventions"]
"""Columns every generic metric's CSV carries: what the number is (``filtered`` P_{k|k} …), the P0 it
starts from, and the channel/estimator conventions it depends on."""


class MGrid(StrictModel):
    """An M grid: ``num`` points from ``start`` to ``stop`` (``spacing`` log or linear)."""

    start: PositiveFloat = Field(description="smallest M")
    stop: PositiveFloat = Field(description="largest M")
    num: PositiveInt = Field(60, le=10_000, description="number of grid points (≤ 10 000)")
    spacing: Literal["log", "linear"] = Field("log", description="log or linear spacing")

    @model_validator(mode="after")
    def _order(self):
        if self.stop <= self.start:
            raise ValueError(f"stop must exceed start, got start = {self.start:g}, stop = {self.stop:g}")
        return self

    def values(self) -> np.ndarray:
        if self.spacing == "log":
            return np.geomspace(self.start, self.stop, self.num)
        return np.linspace(self.start, self.stop, self.num)


def m_values(M) -> np.ndarray:
    return M.values() if isinstance(M, MGrid) else np.asarray(M, dtype=float)


class PaperRef(StrictModel):
    """Which paper figure a scenario reproduces (only for the title; user scenarios leave it out)."""

    topic: Literal["shi2009", "fading", "smoothing", "fusion", "markov", "critical"] = Field(
        description="paper topic (see `netkf list`)")
    figure: str = Field("", description='figure or table, e.g. "Fig. 5"')


def labels(estimators) -> list[str]:
    """One label per estimator: its kind, plus the settings that tell repeated kinds apart."""
    kinds = [e.kind for e in estimators]
    out = []
    for e in estimators:
        lab = e.kind
        if kinds.count(e.kind) > 1:
            same = [o for o in estimators if o.kind == e.kind]
            for f, v in e.model_dump().items():
                if f != "kind" and len({str(o.model_dump().get(f)) for o in same}) > 1:
                    lab += f" {f}=" + (",".join(map(str, v)) if isinstance(v, list) else str(v))
        out.append(lab)
    if len(set(out)) < len(out):
        out = [f"{lab} #{i + 1}" for i, lab in enumerate(out)]
    return out


def needs(scenario, what: str):
    """The scenario's system / channel / estimators, or a ConfigError naming the missing block."""
    if what == "channel":
        if scenario.channel is None:
            raise ConfigError.at("channel", "this metric needs a `channel:` block (netkf list shows the kinds)")
        return scenario.channel
    if what == "estimators":
        ests = scenario.estimator_list()
        if not ests:
            raise ConfigError.at("estimator", "this metric needs an `estimator:` (or `estimators:`, a list)")
        return ests
    return scenario.linear_system()


def step_of(at, horizon: int, path: str = "analysis.at") -> int:
    """The time index k of ``at`` (``stationary`` = the horizon: P_k after a burn-in from P0)."""
    if at == "stationary":
        return horizon
    if at > horizon:
        raise ConfigError.at(path, f"must be ≤ montecarlo.horizon = {horizon}, got {at}")
    return int(at)


def p0_label(system) -> str:
    """What P0 = P_{0|0} is, in words (CSV text; figures draw it with :func:`math_text`)."""
    return "P0 = P̄ (steady state, every packet received)" if system.P0 is None else "P0 = system.P0"


_PLAIN_MATH = re.compile(  # the plain-text math of CSV labels, one alternation so nothing is typeset twice
    r"(?P<Etr>E\[tr )?(?:P_\{(?P<sub>[^{}$]*)\}|P_(?P<kk1>k\|k-1))(?(Etr)\])"  # (E[tr) P_{k-1|k} / P_k|k-1 (])
    r"|(?P<one>1-)?\(1-λ\)\^(?:\((?P<exp>[^()$]*)\)|(?P<k1>k1)\b)")  # (1-)(1-λ)^(k1+N+1), (1-λ)^k1


def _typeset(m: re.Match) -> str:
    if m.group("exp") is not None or m.group("k1") is not None:
        power = re.sub(r"\bk1\b", "k_1", m.group("exp") or m.group("k1"))
        return "$" + (m.group("one") or "") + r"(1-\lambda)^{" + power + "}$"
    P = "P_{" + (m.group("sub") or m.group("kk1")).replace("|", r" \mid ") + "}"
    return r"$\mathrm{E}[\mathrm{tr}\," + P + "]$" if m.group("Etr") else "$" + P + "$"


def math_text(label: str) -> str:
    """A CSV label for a figure: P̄ (a combining macron most fonts drop) as mathtext, and the plain-text math
    of labels and conventions typeset (``P_{k-1|k}``, ``E[tr P_k|k-1]``, ``1-(1-λ)^(k1+N+1)``; mathtext draws
    a bare ``|`` in a subscript like an l, hence ``\\mid``); what is already between ``$`` is left alone."""
    parts = str(label).split("$")
    for i in range(0, len(parts), 2):  # the text outside $…$
        seg = _PLAIN_MATH.sub(_typeset, parts[i])
        parts[i] = seg.replace("P̄", r"$\bar{P}$").replace("P0 =", "$P_0$ =")
    return "$".join(parts)


def channel_words(ch) -> str:
    """A short description of a channel: its kind and its scalar parameters (``bernoulli (arrival = 0.7)``)."""
    params = [f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}" for k, v in ch.model_dump().items()
              if k != "kind" and isinstance(v, (int, float, str)) and not isinstance(v, bool)]
    return f"{ch.kind} channel" + (f" ({', '.join(params[:4])})" if params else "")


def conventions_label(system, channel, est) -> str:
    """The channel's and the estimator's conventions as one short text (``name: value; …``)."""
    conv = {}
    ch_conv = getattr(channel, "conventions", None)
    if callable(ch_conv):
        conv.update(ch_conv())
    conv.update(est.conventions(system, channel))
    if not conv:  # nothing stated by the estimator: the channel's own parameters say it
        return channel_words(channel)
    return f"{channel.kind} channel; " + "; ".join(f"{k}: {v}" for k, v in conv.items())


def describe(scenario, system, ests, quantity: str) -> list[dict]:
    """Per estimator, the label columns (LABEL_COLUMNS) of its rows."""
    ch = scenario.channel
    return [dict(quantity=quantity, P0=p0_label(system), conventions=conventions_label(system, ch, e)) for e in ests]


def backends(scenario, system, ests, labs, runs: int, horizon: int, stats=None, steps=None) -> dict[str, str]:
    """Per estimator label, the backend its chunks ran on (a last, smaller chunk may run on another). Chunks the
    engine ran in an estimator's fused kernel are counted in ``stats`` (``engine.FUSED_CHUNKS``: recorded, not
    predicted); the others ran on ``backend_used`` (for ``steps``, the reported steps, and the analysis'
    quantities)."""
    chunk = min(scenario.montecarlo.chunk, runs)
    sizes = [chunk] + ([runs % chunk] if runs % chunk else [])
    count = {chunk: runs // chunk, **({runs % chunk: 1} if runs % chunk else {})}
    q = getattr(scenario.analysis, "quantity", None)
    qs = None if q is None else ((q,) if isinstance(q, str) else tuple(q))
    fused = None if stats is None or engine.FUSED_CHUNKS not in stats else np.asarray(stats[engine.FUSED_CHUNKS])
    out = {}
    for j, (e, lab) in enumerate(zip(ests, labs)):
        used = {n: e.backend_used(system, scenario.channel, n, horizon, steps=steps, quantities=qs) for n in sizes}
        nf, total = (0 if fused is None else int(fused[j])), sum(count.values())
        if nf == total:
            used = {n: engine.FUSED_LABEL for n in sizes}
        elif nf:  # chosen by the chunk's run-steps: the full-size chunks fused, the last smaller one not
            used[sizes[0]] = engine.FUSED_LABEL if nf == count[sizes[0]] else f"{engine.FUSED_LABEL} ({nf} of {total} chunks)"
        vals = set(used.values())
        out[lab] = vals.pop() if len(vals) == 1 else ", ".join(f"{b} (chunks of {n} runs)" for n, b in used.items())
    return out


def n_runs_of(stats) -> int:
    return int(stats["n"])


def horizon_of(scenario, metric) -> int:
    """The horizon the engine simulated for this metric (``at`` for distribution/compare, else the horizon)."""
    at = getattr(metric, "at", None)
    return step_of(at, scenario.montecarlo.horizon) if at is not None else scenario.montecarlo.horizon


def grid_conventions(table) -> dict[str, str]:
    """Per estimator, the convention label of a whole table (every point of an ``over`` grid): a part shared by
    every point once, the parts that change along the grid as ``first … last (along the grid)`` — a retransmission
    grid over p is not "asked with p = 0" (its first point), nor a grid over λ "bernoulli λ = 0.95" (its last)."""
    out: dict[str, str] = {}
    if "conventions" not in table or "estimator" not in table:
        return out
    for lab, g in table.groupby("estimator", sort=False):
        labels = list(dict.fromkeys(str(c) for c in g.conventions if isinstance(c, str) and c))
        if len(labels) <= 1:
            out[lab] = labels[0] if labels else ""
            continue
        parts = [[p for p in c.split("; ") if p] for c in labels]
        same = [p for p in parts[0] if all(p in q for q in parts)]
        first, last = ("; ".join(p for p in q if p not in same) for q in (parts[0], parts[-1]))
        out[lab] = "; ".join(same + [_span(first, last)])
    return out


_NUMBER = re.compile(r"(-?\d+(?:\.\d+)?(?:e[-+]?\d+)?)")


def _span(first: str, last: str) -> str:
    """``bernoulli channel (arrival = 0.35 … 0.78 along the grid, …)`` from the labels of a grid's first and last
    points when they differ only in numbers; else ``first … last (along the grid)``."""
    a, b = _NUMBER.split(first), _NUMBER.split(last)
    if len(a) != len(b) or a[0::2] != b[0::2]:
        return f"{first} … {last} (along the grid)"
    return "".join(x if i % 2 == 0 or x == y else f"{x} … {y} along the grid" for i, (x, y) in enumerate(zip(a, b)))


def conventions_note(labels_by_estimator: dict[str, str]) -> str:
    """One footnote line from per-estimator convention labels: what all share once, then what each adds."""
    parts = {lab: [p for p in str(c).split("; ") if p] for lab, c in labels_by_estimator.items()}
    if not parts:
        return ""
    common = [p for p in next(iter(parts.values())) if all(p in v for v in parts.values())]
    extra = [f"{lab}: " + "; ".join(p for p in v if p not in common) for lab, v in parts.items()
             if any(p not in common for p in v)]
    return math_text("; ".join(common) + ("" if not extra else " — " + " | ".join(extra)))


def quantity_text(quantity: str, what: str = "P_k") -> str:
    """Mathtext for a quantity: ``filtered`` → P_{k \\mid k} (a figure label: mathtext's STIX sans draws a bare ``|``
    in a subscript like an l, "klk"; CSV text keeps P_{k|k}, :data:`netkf_cli.linalg.kalman.SYMBOL`)."""
    sub = {"filtered": r"k \mid k", "predicted": r"k+1 \mid k", "smoothed": r"k-N \mid k"}[quantity]
    return what.replace("P_k", f"P_{{{sub}}}")


class GenericMetric(AnalysisModel):
    """What the generic metrics share: the quantity, an ``over`` grid, closed-form references, validation
    and the engine call."""

    quantity: Quantity = Field("filtered", description="which covariance: filtered P_{k|k}, predicted P_{k+1|k} or "
                                                       "smoothed P_{k-N|k} (a smoother's lag N); `netkf list` shows what "
                                                       "each estimator reports")
    over: dict[str, list[Any]] | None = Field(
        None, description="a grid of scenario parameters, e.g. {channel.arrival: [0.5, 0.6]}: the metric at every point "
                          "(several paths are zipped: equal lengths), one table with a column per path; the figure "
                          "draws against the first path where the metric has no x-axis of its own")
    streams: Literal["common", "independent"] = Field(
        "common", description="random streams of the over points: common (stream 0 at every point: common random "
                              "numbers, smooth curves) or independent (stream i at point i: independent errors)")
    references: list[str] = Field(default_factory=list,
                                  description="closed-form rows beside the Monte Carlo (`netkf list` analysis "
                                              "references names them): each adds rows with source = closed_form")

    @model_validator(mode="after")
    def _over_grid(self):
        if self.over is not None:
            if not self.over:
                raise ValueError("over: give at least one dotted path with a list of values")
            lens = {k: len(v) for k, v in self.over.items()}
            if any(n == 0 for n in lens.values()):
                raise ValueError(f"over: every path needs at least one value, got {lens}")
            if len(set(lens.values())) > 1:
                raise ValueError(f"over: the paths are zipped and need lists of equal length, got {lens}")
            bad = [k for k in self.over if k.split(".")[0] not in ("system", "channel", "estimator", "estimators",
                                                                   "montecarlo")]
            if bad:
                raise ValueError(f"over: paths start with system., channel., estimator(s). or montecarlo., got {bad}")
        for name in self.references:
            if name not in references.REGISTRY:
                raise ValueError(f"references: unknown closed form {name!r}; known: {', '.join(sorted(references.REGISTRY))}")
        return self

    def quantity_list(self) -> list[str]:
        """The quantities this metric reports (one, unless the metric takes ``quantities``)."""
        qs = getattr(self, "quantities", None)
        return list(qs) if qs else [self.quantity]

    draws_references: ClassVar[bool] = False
    """Whether this metric draws ``references`` (closed-form rows); the others refuse the field (it was silently
    ignored while the manifest listed it)."""

    def check(self, scenario) -> None:
        if self.references and not self.draws_references:
            raise ConfigError.at("analysis.references", f"{self.kind} draws no closed-form references (mean_vs_time, "
                                                        "time_average, updates and burst_mean do); remove the field")
        needs(scenario, "channel")
        ests = needs(scenario, "estimators")
        many = bool(scenario.estimators)
        qs = self.quantity_list()
        if len(qs) > 1:  # several quantities: each estimator reports those it offers, each is offered by one
            for q in qs:
                if not any(q in getattr(e, "quantities", ("filtered",)) for e in ests):
                    raise ConfigError.at("analysis.quantities", f"no estimator reports {q} ({kalman.SYMBOL[q]}); "
                                         + "; ".join(f"{e.kind} reports {', '.join(getattr(e, 'quantities', ('filtered',)))}"
                                                     for e in ests))
        for i, e in enumerate(ests if len(qs) == 1 else []):
            offered = getattr(e, "quantities", ("filtered",))
            if self.quantity not in offered:
                raise ConfigError.at("analysis.quantity", f"{'estimators[%d]' % i if many else 'estimator'} "
                                     f"({e.kind}) does not report {self.quantity} ({kalman.SYMBOL[self.quantity]}); "
                                     f"it reports {', '.join(offered)}")
        if self.needs_per_run_covariance():
            for i, e in enumerate(ests):
                if not e.per_run_covariance():
                    raise ConfigError.at(f"{'estimators[%d]' % i if many else 'estimator'}.variance_reduction",
                                         f"{e.kind} yields per-run estimates of E[P_k] here, not each run's covariance: "
                                         f"{self.kind} needs Pr[P_k ≤ M] of each run; use it with mean_vs_time (or "
                                         f"compare without M), or set variance_reduction: none")
        if getattr(self, "at", None) is not None:  # time_average's at is optional (None: the time average)
            k = step_of(self.at, scenario.montecarlo.horizon)
            for e in ests:
                first = e.first_step(self.quantity)
                if k < first:
                    raise ConfigError.at("analysis.at", f"{e.kind} defines {self.quantity} from step {first} on "
                                                        f"({kalman.SYMBOL[self.quantity]}), got k = {k}")
        if self.references and not getattr(self, "over", None) and not _DEFER_REFERENCES:
            # the closed forms' own conditions (a lag they enumerate, 0 < λ < 1 …), before any Monte Carlo: they
            # were found only after it, when the rows were drawn (an over grid checks each of its points)
            got = {r["reference"] for sc in self.reference_scenarios(scenario)
                   for r in self.reference_rows(sc, labels(sc.estimator_list()))}
            problems = [Problem(f"analysis.references[{i}]", f"{name} gives nothing for this scenario: "
                                                             f"{references.applies_to(name)}")
                        for i, name in enumerate(self.references) if name not in got and not _AT_POINTS]
            if problems:
                raise ConfigError(problems)

    def reference_scenarios(self, scenario) -> list:
        """The scenarios this metric draws references at (itself; burst_mean adds its independent baseline)."""
        return [scenario]

    def needs_per_run_covariance(self) -> bool:
        """Whether this metric takes per-run functionals of P (Pr[P_k ≤ M]), not only means."""
        return bool(getattr(self, "M", None))

    def simulate(self, scenario, ctx, reducer, steps, horizon: int, quantities=None):
        """Run the scenario's estimators on its channel's traces (the stream the runner allocated, 0 unless an
        ``over`` grid says otherwise): (system, estimators, statistics). With ``quantities`` (a tuple), the
        reducer's column of (estimator j, quantity q) is ``engine.column(j, qi, len(quantities))``."""
        s, ch, ests = needs(scenario, "system"), needs(scenario, "channel"), needs(scenario, "estimators")
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        ctx.total(runs)
        st = engine.simulate(s, ch, ests, reducer, steps=steps, runs=runs, horizon=horizon, seed=mc.seed,
                             chunk=mc.chunk, stream=ctx.stream, progress=ctx.progress, label=self.kind,
                             quantity=tuple(quantities) if quantities else self.quantity)
        return s, ests, st

    def reference_rows(self, scenario, labs: list[str]) -> list[dict]:
        """The closed-form rows of ``references`` at this scenario (source = closed_form, no standard error).

        Evaluated once per point: the scenario's check (:meth:`check`, before any work) and the metric's
        compute ask for the same rows, which are kept by what they are computed from (_REFERENCE_ROWS)."""
        if not self.references:
            return []
        ests = scenario.estimator_list()
        point = references.Point(system=needs(scenario, "system"),
                                 channel=scenario.channel.model_dump() if scenario.channel is not None else {},
                                 estimators=[e.model_dump() for e in ests], labels=list(labs),
                                 quantities=self.quantity_list(), metric=self.model_dump(), coords={},
                                 montecarlo=scenario.montecarlo.model_dump())
        s = point.system
        key = repr((self.references, [np.asarray(x).tolist() if x is not None else None
                                      for x in (s.A, s.C, s.Q, s.R, s.P0)], s.sensors, point.channel,
                    point.estimators, point.labels, point.quantities, point.metric, point.montecarlo))
        rows = _REFERENCE_ROWS.get(key)
        if rows is None:
            rows = []
            for name in self.references:
                for r in references.evaluate(name, point):
                    rows.append(dict(r, reference=name))
            if len(_REFERENCE_ROWS) >= 512:  # a bound: one entry per point of the runs of this process
                _REFERENCE_ROWS.clear()
            _REFERENCE_ROWS[key] = rows
        return [dict(r) for r in rows]


def drawn_refs(table) -> list[str]:
    """The references a result table holds rows of (a figure names these, not the ones asked for: a closed form
    gives no rows where it does not apply, as at some points of an over grid)."""
    if "reference" not in table.columns or "source" not in table.columns:
        return []
    return [str(r) for r in dict.fromkeys(table[table.source == "closed_form"].reference) if isinstance(r, str) and r]


_AT_POINTS: list[bool] = []
"""Non-empty within :func:`at_points`: a reference may give nothing at some points of a sweep or over grid."""


@contextmanager
def at_points():
    """Within the block, scenarios are points of a sweep or an ``over`` grid: a closed form that gives no rows at one
    of them is not refused (it may give rows at the others; the figure names the ones drawn: :func:`drawn_refs`)."""
    _AT_POINTS.append(True)
    try:
        yield
    finally:
        _AT_POINTS.pop()


_DEFER_REFERENCES: list[bool] = []
"""Non-empty within :func:`deferred_reference_checks`."""


@contextmanager
def deferred_reference_checks():
    """Within the block, a scenario's check does not evaluate its closed-form references (``netkf reproduce``'s
    discovery of every config: serial, and each artefact's run checks its points, references included, before
    its Monte Carlo). Elsewhere (``netkf validate``, ``netkf run``, the API) they are checked with the scenario."""
    _DEFER_REFERENCES.append(True)
    try:
        yield
    finally:
        _DEFER_REFERENCES.pop()


_REFERENCE_ROWS: dict[str, list[dict]] = {}
"""The closed-form rows of a point, by everything they are computed from (:meth:`GenericMetric.reference_rows`)."""


KF_FORWARD = ("kf", "smoother")
"""Estimators whose covariances are the intermittent Kalman filter's (the smoother's forward pass): the
loss-burst tail law of Mo & Sinopoli 2012 applies to them."""


def loss_burst_law(channel) -> tuple[float | None, Any]:
    """(s, chain): the probability s that a loss burst continues (1 − λ i.i.d.; 1 − q Gilbert–Elliott) and
    the arrival chain, or (None, None) for channels without a geometric loss-burst law."""
    kind = getattr(channel, "kind", "")
    if kind == "bernoulli":
        return 1.0 - float(channel.arrival), cr.iid_chain(float(channel.arrival))
    if kind == "gilbert_elliott":
        return 1.0 - float(channel.transition[1]), cr.ge_chain(*channel.transition)
    return None, None


def kf_tail_exponent(system, channel, est) -> tuple[float | None, str]:
    """φ of Pr[tr P_k > M] ~ M^φ at stationarity for the KF's covariances (:func:`cr.tail_exponent`), or
    (None, why). φ ≥ −2 means E[(tr P)²] = ∞: a sample mean's standard error then means nothing."""
    if getattr(est, "kind", "") not in KF_FORWARD:
        return None, "theory only for the Kalman filter (kind: kf) and the smoother's forward pass"
    s, T = loss_burst_law(channel)
    if s is None:
        return None, f"no loss-burst law for channel {getattr(channel, 'kind', '')!r}"
    return cr.tail_exponent(system.A, system.C, loss_stay=s, channel=channel.kind, T=T)


def fold_over(t, over: dict | None):
    """A table of an ``over`` grid for a figure whose x-axis is the metric's own (M, k): the point joins the
    estimator's label, so each point is its own line."""
    if not over or t is None or not len(t):
        return t
    cols = [c for c in over if c in t.columns]
    if not cols:
        return t
    t = t.copy()
    t["estimator"] = t["estimator"].astype(str) + " (" + t[cols].astype(str).apply(
        lambda r: ", ".join(f"{c.split('.')[-1]} = {v}" for c, v in r.items()), axis=1) + ")"
    return t
