"""``kind: tail`` — the exceedance law Pr[tr P_k > M] (or λ_max) against M, with its power-law exponent.

Mo & Sinopoli 2012 (IEEE TAC 57(3), "Kalman filtering with intermittent observations: tail distribution and
critical value"): for a non-degenerate system the tail decays like a power of M, Pr[tr P_k > M] ~ M^φ with
φ = log s / (2 log ρ(A)), s = 1 − λ (i.i.d. arrivals) or 1 − q (Gilbert–Elliott recovery rate q) — a loss burst of
length L has probability ∝ s^L and makes P grow like ρ^{2L}. The numbers a safety margin needs sit far in that
tail, where plain Monte Carlo sees nothing, so the metric samples it:

**Importance sampling of long loss bursts.** Runs are split evenly among K components: component 0 samples the
scenario's channel as is; component c ≥ 1 resamples the last W_c steps before the reported step (``windows``,
geometrically spaced up to the burst length the largest M needs) from a tilted law with more and longer losses
(Bernoulli: arrival s·λ; Gilbert–Elliott: recovery s·q, failure 1 − s(1 − p); s = ``tilt``), so a loss burst of
about W_c steps ending at k is typical for it. With r_c = q_c/p, the likelihood ratio of component c on its own
window (the laws agree elsewhere), every run carries the balance-heuristic weight

    w = 1 / (α₀ + Σ_c α_c r_c)  ≤ 1/α₀ = K      (α_c = 1/K),

so the weighted estimator Σ w·1{X > M}/n is unbiased for every M and its weights are bounded (a defensive
mixture: never worse than K times plain Monte Carlo). Component 0 alone is plain Monte Carlo, reported beside it
(Wilson intervals), so the two are checked against each other where both are reliable. Other channels run plain
Monte Carlo only (the figure says so).

**Exponent.** φ̂ is the least-squares slope of log p̂ against log M over the tail region (p̂ ≤ ``fit_below``, relative
standard error ≤ 0.25); its 95 % interval is the delete-one-batch jackknife over ``batches`` independent run batches
(Student t with batches − 1 degrees of freedom: it accounts for the correlation between thresholds) widened by the
staircase allowance |φ̂|·2 log ρ(A)/Δ (burst lengths are integers, so the law is a staircase of step 2 log ρ in log M;
over a fitted log-range Δ a line through it can tilt by that much at any sample size).
The theoretical φ is attached for the ``kf`` estimator where a theorem (or the derived degenerate 2×2 law) gives it
(:func:`netkf_cli.analysis.critical.tail_exponent`).

The module also holds the critical recipe's time-averaged Monte Carlo mean (:func:`time_average_mean`: the engine's
``TimeAverageReducer``, so a ``kf`` on a bernoulli channel runs in its fused kernel).
"""

from __future__ import annotations

import inspect
import math
from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, model_validator
from scipy.special import stdtrit

from netkf_cli import engine
from netkf_cli.analysis import critical as cr
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.linalg import kalman
from netkf_cli.metrics.common import (backends, kf_tail_exponent, loss_burst_law, MGrid, PaperRef, labels, m_values,
                                      needs)
from netkf_cli.runtime.montecarlo import run_chunked, wilson_interval
from netkf_cli.runtime.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.spec import AnalysisModel, PositiveInt

QUANTITY = {"filtered": "P_{k|k}", "predicted": "P_{k+1|k}", "smoothed": "P_{k-N|k}"}
MIN_CONTRIBUTORS = 30
"""An exceedance estimate is a result when at least this many runs lie above M (else its s.e. is itself unreliable)."""


# =============================================================================================
# The estimator contract during the transition (bare arrays → {quantity: P})
# =============================================================================================


def accepts_quantities(est) -> bool:
    try:
        params = inspect.signature(est.covariances).parameters
    except (TypeError, ValueError):
        return False
    return "quantities" in params or any(p.kind == p.VAR_KEYWORD for p in params.values())


def covariances(est, system, trace, steps, quantity: str = "filtered"):
    """Yield (k, P) of ``quantity`` from either contract: ``{quantity: P}`` (new) or a bare array (old)."""
    gen = (est.covariances(system, trace, steps, quantities=(quantity,)) if accepts_quantities(est)
           else est.covariances(system, trace, steps))
    for k, out in gen:
        if isinstance(out, dict):
            if quantity not in out:
                raise ConfigError.at("analysis.quantity", f"estimator {est.kind!r} does not report {quantity!r} "
                                     f"(it reports {', '.join(sorted(out))})")
            yield k, out[quantity]
        else:
            yield k, out


def kf_for(quantity: str):
    """A ``kf`` estimator reporting ``quantity`` under either contract (old: ``report:``; new: ``quantities=``)."""
    fields = getattr(KalmanFilterEstimator, "model_fields", {})
    if "report" in fields and not accepts_quantities(KalmanFilterEstimator(kind="kf")):
        return KalmanFilterEstimator(kind="kf", report=quantity)
    return KalmanFilterEstimator(kind="kf")


def statistic(P: np.ndarray, of: str) -> np.ndarray:
    """tr P or λ_max(P) per run; non-finite runs are +inf (they exceed every M)."""
    with np.errstate(invalid="ignore", over="ignore"):
        if of == "trace":
            x = np.einsum("iir->r", P)
        else:
            X = np.moveaxis(P, -1, 0)
            ok = np.isfinite(X).all(axis=(1, 2))
            x = np.full(P.shape[-1], np.inf)
            if ok.any():
                x[ok] = np.linalg.eigvalsh(X[ok])[:, -1]
    return np.where(np.isfinite(x), x, np.inf)


# =============================================================================================
# Tilted loss windows and their likelihoods
# =============================================================================================


def _law(channel):
    """('bernoulli', λ) or ('gilbert_elliott', (p, q)); None for channels without a tilt."""
    kind = getattr(channel, "kind", None)
    if kind == "bernoulli":
        return kind, float(channel.arrival)
    if kind == "gilbert_elliott":
        return kind, tuple(float(x) for x in channel.transition)
    return None


def tilted_params(law, s: float):
    kind, par = law
    if kind == "bernoulli":
        return kind, par * s
    p, q = par
    return kind, (1.0 - s * (1.0 - p), q * s)


COMPILED_MIN_RUNS = engine.REDUCE_MIN_RUNS
"""Windows of at least this many runs get their log-likelihoods from :mod:`netkf_cli.metrics._tail_numba` (the
same sums compiled) when numba is importable; smaller ones (tests, quick runs) stay on numpy."""


def loglik_compiled(backend: str, runs: int) -> bool:
    """Whether :func:`window_loglik` sums a window of ``runs`` runs compiled (its ``backend`` rule)."""
    return backend == "numba" or (backend == "auto" and runs >= COMPILED_MIN_RUNS and kalman.numba_available())


LOGLIK_CHUNKS = "loglik_chunks"
"""Stats key: (compiled, numpy), how many chunks' window likelihoods each path summed (the manifest's ``likelihood``)."""


def window_loglik(law, prev: np.ndarray, win: np.ndarray, *, backend: str = "auto") -> np.ndarray:
    """log-probability of each run's window (W, runs) given the arrival just before it (runs,).

    ``backend`` numpy (the reference), numba (the same sums compiled, :mod:`netkf_cli.metrics._tail_numba`) or
    auto (numba for ≥ :data:`COMPILED_MIN_RUNS` runs when importable)."""
    kind, par = law
    W, runs = win.shape
    compiled = loglik_compiled(backend, runs)
    g = win.astype(bool)
    with np.errstate(divide="ignore"):
        if kind in ("bernoulli", "bernoulli_steps"):
            if kind == "bernoulli_steps":                    # one arrival probability per window step (W,)
                v = np.asarray(par, float)[-W:, None]
                la, lb = np.log(v), np.log1p(-v)
            else:
                lam = par
                la = math.log(lam) if lam > 0 else -np.inf
                lb = math.log1p(-lam) if lam < 1 else -np.inf
            if not compiled:
                return np.where(g, la, lb).sum(axis=0)
            out = np.empty(runs)
            _tail_nb().iid_loglik(g, np.broadcast_to(la, (W, 1))[:, 0].copy(), np.broadcast_to(lb, (W, 1))[:, 0].copy(),
                                  out)
            return out
        p, q = par
        lp = {(1, 1): math.log1p(-p) if p < 1 else -np.inf, (1, 0): math.log(p) if p > 0 else -np.inf,
              (0, 1): math.log(q) if q > 0 else -np.inf, (0, 0): math.log1p(-q) if q < 1 else -np.inf}
        if compiled:
            out = np.empty(runs)
            _tail_nb().markov_loglik(g, np.array(prev, dtype=bool), lp[(1, 1)], lp[(1, 0)], lp[(0, 1)], lp[(0, 0)], out)
            return out
        tot = np.zeros(runs)
        a = prev.astype(bool)
        for t in range(W):
            b = g[t]
            tot += np.where(a, np.where(b, lp[(1, 1)], lp[(1, 0)]), np.where(b, lp[(0, 1)], lp[(0, 0)]))
            a = b
        return tot


def _tail_nb():
    from netkf_cli.metrics import _tail_numba  # optional dependency (numba): the compiled window sums

    return _tail_numba


def sample_window(rng, law, prev: np.ndarray, W: int) -> np.ndarray:
    """(W, runs) bool arrivals from ``law`` continuing from the arrival ``prev`` (runs,)."""
    kind, par = law
    u = rng.random((W, prev.size))
    if kind == "bernoulli_steps":
        return u < np.asarray(par, float)[-W:, None]
    if kind == "bernoulli":
        return u < par
    p, q = par
    out = np.empty((W, prev.size), bool)
    a = prev.astype(bool)
    for t in range(W):
        out[t] = np.where(a, u[t] >= p, u[t] < q)
        a = out[t]
    return out


class TailKernel:
    """One chunk: sample traces (K mixture components), run the estimators, reduce weighted exceedances.

    Component 0 is the channel itself; component c ≥ 1 resamples the last ``windows[c−1]`` steps before the reported
    step from the tilted law (a long loss burst ending at k is then typical). With r_c = q_c/p the likelihood ratio
    of component c on its own window (equal laws elsewhere), the balance-heuristic weight is
    w = 1 / (α₀ + Σ_c α_c r_c) ≤ 1/α₀ = K.

    Statistics (j = estimator, i = threshold): ``wf_{j}[c, i]`` = Σ_{runs of component c} w·1{X > M_i},
    ``w2f_{j}[c, i]`` = Σ w²·1{X > M_i}, ``cnt0_{j}[i]`` = plain exceedance count of component 0, ``bwf_{j}[b, i]``
    = Σ over batch b of w·1{X > M_i}; ``n_c[c]``, ``n_b[b]`` run counts; ``wsum`` = Σ w (≈ n, a check).
    """

    def __init__(self, system, channel, estimators, horizon: int, step: int, M, of: str, quantity: str,
                 tilt: float, windows, batches: int, residues: int = 0):
        self.system, self.channel, self.estimators = system, channel, list(estimators)
        self.horizon, self.step, self.M = int(horizon), int(step), np.asarray(M, float)
        self.of, self.quantity = of, quantity
        self.law = _law(channel)
        self.windows = [int(w) for w in windows] if self.law is not None else []
        self.tilt, self.batches = float(tilt), int(batches)
        # components: (window length, tilted law). Homogeneous tilts target complete loss bursts; for a degenerate
        # 2×2 system of order p ≥ 2 over i.i.d. loss, "residue" tilts also target windows in which only one
        # residue class mod p keeps its arrivals (the rare event that drives that system's tail)
        self.components = [(W, tilted_params(self.law, self.tilt)) for W in self.windows]
        if residues >= 2 and self.law is not None and self.law[0] == "bernoulli":
            lam = self.law[1]
            for W in self.windows:
                for r in range(residues):
                    d = np.arange(W, 0, -1)                   # distance of each window step to k
                    v = np.where(d % residues == r, lam, self.tilt * lam)
                    self.components.append((W, ("bernoulli_steps", v)))

    def __call__(self, rng: np.random.Generator, runs: int) -> dict:
        K = 1 + len(self.components)
        comp = np.arange(runs) % K
        batch = (np.arange(runs) // K) % self.batches
        trace = self.channel.sample_trace(rng, runs, self.horizon)
        w = np.ones(runs)
        if K > 1:
            arr = trace.arrival
            for c, (W, tl) in enumerate(self.components, start=1):
                idx = np.flatnonzero(comp == c)
                k1 = self.step - W                           # window = trace steps k1 … step−1
                prev = arr[0, k1 - 1, idx] if k1 >= 1 else np.ones(idx.size, bool)
                view = arr[0, k1:self.step]                  # a view (W, runs)
                view[:, idx] = sample_window(rng, tl, prev, W)
            logr = np.empty((K - 1, runs))
            for c, (W, tl) in enumerate(self.components):
                k1 = self.step - W
                prev = arr[0, k1 - 1] if k1 >= 1 else np.ones(runs, bool)
                win = arr[0, k1:self.step]
                logr[c] = window_loglik(tl, prev, win) - window_loglik(self.law, prev, win)
            with np.errstate(over="ignore"):
                w = 1.0 / ((1.0 + np.exp(logr).sum(axis=0)) / K)
        used = np.zeros(2, dtype=np.int64)
        if K > 1:
            used[0 if loglik_compiled("auto", runs) else 1] = 1
        stats: dict = {LOGLIK_CHUNKS: used, "n_c": np.bincount(comp, minlength=K).astype(float),
                       "n_b": np.bincount(batch, minlength=self.batches).astype(float), "wsum": np.asarray(w.sum())}
        for j, est in enumerate(self.estimators):
            for k, P in covariances(est, self.system, trace, [self.step], self.quantity):
                x = statistic(P, self.of)
                f = x[None, :] > self.M[:, None]                               # (nM, runs)
                wf = f * w[None, :]
                stats[f"wf_{j}"] = np.stack([wf[:, comp == c].sum(axis=1) for c in range(K)])
                stats[f"w2f_{j}"] = np.stack([(wf[:, comp == c] * w[None, comp == c]).sum(axis=1) for c in range(K)])
                stats[f"cnt0_{j}"] = f[:, comp == 0].sum(axis=1).astype(float)
                stats[f"cnt_{j}"] = f.sum(axis=1).astype(float)               # runs (any component) above M
                stats[f"bwf_{j}"] = np.stack([wf[:, batch == b].sum(axis=1) for b in range(self.batches)])
                stats[f"max_x_{j}"] = np.asarray(float(np.max(np.where(np.isfinite(x), x, -np.inf), initial=0.0)))
        return stats


def _likelihood_used(st: dict) -> str:
    """The manifest's statement of which path summed the components' window log-likelihoods (recorded per chunk)."""
    c, p = (int(x) for x in np.asarray(st.get(LOGLIK_CHUNKS, (0, 0))))
    if not c + p:
        return "none (plain Monte Carlo: no likelihood ratios)"
    label = "numba (metrics/_tail_numba)"
    return label if not p else "numpy" if not c else f"{label} ({c} of {c + p} chunks), numpy ({p})"


def importance_estimate(st: dict, j: int) -> tuple[np.ndarray, np.ndarray]:
    """(p̂, s.e.) of the stratified mixture estimator: p̂ = Σ_c wf_c / n, var = Σ_c (w2f_c − wf_c²/n_c)/n²."""
    n_c = st["n_c"]
    n = n_c.sum()
    wf, w2f = st[f"wf_{j}"], st[f"w2f_{j}"]
    p = wf.sum(axis=0) / n
    nc = np.maximum(n_c, 1)[:, None]
    var = np.maximum(w2f - wf**2 / nc, 0.0).sum(axis=0) * (nc[:, 0].mean() / np.maximum(nc[:, 0].mean() - 1, 1)) / n**2
    return p, np.sqrt(var)


def jackknife_slope(M: np.ndarray, bwf: np.ndarray, n_b: np.ndarray, mask: np.ndarray) -> tuple[float, float, int]:
    """(slope, jackknife s.e., batches used) of log p̂ on log M over ``mask``, deleting one batch at a time."""
    x = np.log(M[mask])
    tot, n = bwf.sum(axis=0), n_b.sum()

    def slope(num, den):
        p = num[mask] / den
        if np.any(p <= 0) or x.size < 2:
            return math.nan
        return float(np.polyfit(x, np.log(p), 1)[0])

    full = slope(tot, n)
    B = bwf.shape[0]
    loo = np.array([slope(tot - bwf[b], n - n_b[b]) for b in range(B)])
    loo = loo[np.isfinite(loo)]
    if loo.size < 3 or not math.isfinite(full):
        return full, math.nan, int(loo.size)
    se = math.sqrt((loo.size - 1) / loo.size * float(((loo - loo.mean()) ** 2).sum()))
    return full, se, int(loo.size)


# =============================================================================================
# The metric
# =============================================================================================


class TailMetric(AnalysisModel):
    """``kind: tail`` — Pr[tr P_k > M] against M (log–log), importance-sampled loss bursts, fitted and theoretical exponent."""

    kind: Literal["tail"]
    M: list[float] | MGrid = Field(description="thresholds M (list, or a grid {start, stop, num, spacing})")
    of: Literal["trace", "lambda_max"] = Field("trace", description="tr P_k or λ_max(P_k)")
    at: int | Literal["stationary"] = Field("stationary", description="the step k (or the horizon: stationary after P0)")
    quantity: Literal["filtered", "predicted", "smoothed"] = Field("filtered", description="which covariance of the estimator")
    importance: bool = Field(True, description="importance-sample long loss bursts (bernoulli and gilbert_elliott channels)")
    tilt: float = Field(0.1, gt=0, lt=1, description="tilt factor s inside a window: arrival s·λ (bernoulli), "
                        "recovery s·q and failure 1 − s(1 − p) (gilbert_elliott)")
    windows: list[PositiveInt] | None = Field(None, description="window lengths (steps before k) of the tilted mixture "
                                              "components (default: 8 lengths from 2 to what the largest M needs, from ρ(A))")
    residue_tilts: bool = Field(True, description="for a degenerate 2×2 system over i.i.d. loss, also tilt windows in "
                                "which only one residue class mod p keeps its arrivals (that system's rare event)")
    batches: PositiveInt = Field(10, ge=4, le=100, description="independent run batches for the exponent's jackknife interval")
    fit_below: float = Field(0.1, gt=0, lt=1, description="the exponent is fitted where p̂ ≤ this (the tail)")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")


    def _step(self, horizon: int) -> int:
        if self.at == "stationary":
            return horizon
        if not 1 <= self.at <= horizon:
            raise ConfigError.at("analysis.at", f"must be in 1 … montecarlo.horizon = {horizon}, got {self.at}")
        return int(self.at)

    def _windows(self, s, step: int, Mmax: float) -> list[int]:
        if self.windows is not None:
            bad = [w for w in self.windows if w >= step]
            if bad:
                raise ConfigError.at("analysis.windows", f"every window must be < the reported step k = {step}, got {bad}")
            return sorted(set(int(w) for w in self.windows))
        rho = cr.spectral_radius(s.A)
        base = max(float(np.trace(s.Q)), 1e-12)
        # a burst of L losses makes tr P ≈ tr Q·ρ^{2L}: reaching Mmax needs L ≈ log(Mmax/tr Q)/(2 log ρ)
        L = math.log(max(Mmax / base, 2.0)) / (2 * math.log(rho)) if rho > 1 + 1e-9 else 20.0
        top = int(min(step - 1, max(2, math.ceil(1.2 * L) + 2)))  # a window ends before the reported step
        if top < 1:  # k = 1: no step before it to tilt (plain Monte Carlo)
            return []
        return sorted(set(int(round(x)) for x in np.geomspace(min(2, top), top, 8)))

    def check(self, scenario) -> None:
        needs(scenario, "channel")
        for i, e in enumerate(needs(scenario, "estimators")):
            if not e.per_run_covariance():
                raise ConfigError.at(f"estimators[{i}].variance_reduction" if scenario.estimators else
                                     "estimator.variance_reduction",
                                     f"{e.kind} yields per-run estimates of E[P_k], not each run's covariance: the tail "
                                     f"Pr[tr P_k > M] needs the latter; set variance_reduction: none")
        step = self._step(scenario.montecarlo.horizon)
        if self.windows is not None and self.importance and _law(scenario.channel) is not None:
            self._windows(None, step, 0.0)  # given windows are only compared with the step (compute's own check)

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s, ch, ests = needs(scenario, "system"), needs(scenario, "channel"), needs(scenario, "estimators")
        for e in ests:
            e.check(s, ch)
        mc = scenario.montecarlo
        H = mc.horizon
        step = self._step(H)
        M = np.sort(m_values(self.M))
        law = _law(ch) if self.importance else None
        wins = self._windows(s, step, float(M.max())) if law is not None else []
        runs = ctx.mc_runs(scenario)
        ctx.total(runs)
        ec = cr.exact_case(s.A, s.C)
        residues = int(ec.key.rsplit("p", 1)[1]) if ec is not None and ec.key.startswith("degenerate_2x2_p") else 0
        kern = TailKernel(s, ch, ests, H, step, M, self.of, self.quantity, self.tilt, wins, self.batches,
                          residues=residues if self.residue_tilts else 0)
        st = run_chunked(kern, runs, mc.chunk, mc.seed, stream=0, progress=ctx.progress, label="tail")
        labs = labels(ests)
        K = 1 + len(kern.components)
        n0 = int(st["n_c"][0])
        rows, fits = [], []
        kind = getattr(ch, "kind", "")
        loss_stay, _ = loss_burst_law(ch)
        for j, lab in enumerate(labs):
            cnt0 = st[f"cnt0_{j}"]
            lo0, hi0 = wilson_interval(cnt0, max(n0, 1))
            p0 = cnt0 / max(n0, 1)
            se0 = np.sqrt(p0 * (1 - p0) / max(n0, 1))
            if K > 1:
                p_raw, se = importance_estimate(st, j)
                # the unbiased estimate is not bounded by 1 (weights up to K: an undetectable system, every run
                # above M, gave 1.08); projected onto [0, 1], which can only bring it closer to the probability;
                # its interval is the unbiased one's, cut to [0, 1]
                p = np.minimum(p_raw, 1.0)
            else:
                p_raw, (p, se) = p0, (p0, se0)
            cnt = st[f"cnt_{j}"]
            rel = np.where(p > 0, se / np.where(p > 0, p, 1), np.inf)
            # a weighted estimate resting on few runs has an unreliable standard error too: a result needs
            # MIN_CONTRIBUTORS runs above M and a relative s.e. ≤ 0.25
            good = (cnt >= MIN_CONTRIBUTORS) & (rel <= 0.25)
            for i, m in enumerate(M):
                rows.append(dict(M=m, estimator=lab, series="importance" if K > 1 else "monte_carlo", value=p[i],
                                 stderr=se[i], n=int(st["n_c"].sum()), lo=max(p_raw[i] - 1.96 * se[i], 0.0),
                                 hi=min(p_raw[i] + 1.96 * se[i], 1.0), count=cnt[i], reliable=float(good[i])))
                if K > 1:
                    rows.append(dict(M=m, estimator=lab, series="plain", value=p0[i], stderr=se0[i], n=n0,
                                     lo=lo0[i], hi=hi0[i], count=cnt0[i], reliable=float(cnt0[i] >= MIN_CONTRIBUTORS)))
            mask = (p > 0) & (p <= self.fit_below) & good
            slope, sej, nb = jackknife_slope(M, st[f"bwf_{j}"], st["n_b"], mask) if mask.sum() >= 3 else (math.nan, math.nan, 0)

            tq = float(stdtrit(max(nb - 1, 1), 0.975)) if nb >= 3 else math.nan
            theo, why = (None, "theory only for the Kalman filter (kind: kf)")
            if ests[j].kind == "kf" and loss_stay is not None:
                theo, why = kf_tail_exponent(s, ch, ests[j])
            elif loss_stay is None:
                why = f"no loss-burst law for channel {kind!r}"
            # the exceedance law is a staircase in log M (burst lengths are integers: one step = 2 log ρ(A) in log M,
            # log(1/s) in log p), so a least-squares line over a log-range Δ can tilt by up to |φ|·2 log ρ/Δ whatever
            # the sample size: that allowance is added to the statistical half-width of the interval
            rho = cr.spectral_radius(s.A)
            span = math.log(M[mask].max() / M[mask].min()) if mask.sum() >= 2 else math.inf
            stair = abs(slope) * 2 * math.log(rho) / span if (rho > 1 and math.isfinite(slope)) else 0.0
            half = tq * sej + stair if math.isfinite(sej) else math.nan

            both = (cnt0 >= 30) & (rel <= 0.25)
            z = np.abs(p - p0) / np.sqrt(se**2 + se0**2 + 1e-300)
            fits.append(dict(estimator=lab, exponent_fit=slope, ci_lo=slope - half if math.isfinite(half) else np.nan,
                             ci_hi=slope + half if math.isfinite(half) else np.nan, jackknife_se=sej,
                             staircase_allowance=stair, batches=nb,
                             fit_points=int(mask.sum()), fit_M_lo=float(M[mask].min()) if mask.any() else np.nan,
                             fit_M_hi=float(M[mask].max()) if mask.any() else np.nan,
                             exponent_theory=np.nan if theo is None else theo, theory_source=why,
                             theory_in_ci=float(theo is not None and math.isfinite(half)
                                                and slope - half <= theo <= slope + half),
                             is_vs_plain_max_z=float(z[both].max()) if both.any() else np.nan,
                             is_vs_plain_points=int(both.sum())))
        table = pd.DataFrame(rows, columns=["M", "estimator", "series", "value", "stderr", "n", "lo", "hi", "count",
                                            "reliable"])
        fit = pd.DataFrame(fits)
        meta = {"step": step, "statistic": self.of, "quantity": QUANTITY[self.quantity], "estimators": labs,
                "importance_sampling": ({"components": K, "tilt": self.tilt, "windows": wins, "alpha": 1.0 / K,
                                         "residue_classes": residues if self.residue_tilts else 0,
                                         "weights": "w = 1 / (α₀ + Σ_c α_c q_c/p) ≤ K over each component's window "
                                                    "(balance heuristic); component 0 is the channel itself (plain "
                                                    "Monte Carlo)"}
                                        if K > 1 else "off (plain Monte Carlo: no tilt for this channel, importance: false, or no step "
                                                  "before the reported one to tilt)"),
                "weight_mean": float(st["wsum"]) / float(st["n_c"].sum()),
                "backends": backends(scenario, s, ests, labs, runs, H, None, [step]),
                "likelihood": _likelihood_used(st),
                "exponent_fit": "least squares of log p̂ on log M where p̂ ≤ fit_below and rel. s.e. ≤ 0.25; 95 % "
                                "interval: delete-one-batch jackknife (Student t) + staircase allowance |φ|·2 log ρ/Δ"}
        return Artefact(table, meta=meta, extra_tables={"fit": fit})

    def plot(self, tables, scenario):
        t, fit = tables["main"], tables.get("fit")
        fig, ax = new_figure(width=7.6, height=5.4)
        X = r"\mathrm{tr}\,P_k" if self.of == "trace" else r"\lambda_{\max}(P_k)"
        drawn = False
        for j, (lab, g) in enumerate(t.groupby("estimator", sort=False)):
            sty = series_style(j)
            allm = g[g.series.isin(["importance", "monte_carlo"])]
            allm = allm[allm.value > 0]
            rel_ok = allm.reliable > 0 if "reliable" in allm else np.ones(len(allm), bool)
            main, weak = allm[rel_ok], allm[~rel_ok]
            is_imp = (g.series == "importance").any()
            drawn = drawn or len(allm) > 0
            if len(main):
                ax.errorbar(main.M, main.value, yerr=[main.value - main.lo.clip(lower=main.value * 1e-3), main.hi - main.value],
                            fmt=sty["marker"], color=sty["color"], ms=4, capsize=2, lw=1,
                            label=f"{lab}: {'importance sampling' if is_imp else 'Monte Carlo'} (95 % interval)")
            if len(weak):
                ax.plot(weak.M, weak.value, linestyle="none", marker=sty["marker"], mfc="none", color=sty["color"], ms=6,
                        label=f"{lab}: fewer than {MIN_CONTRIBUTORS} runs above M or rel. s.e. > 0.25 (not a result)")
            pl = g[(g.series == "plain") & (g.value > 0)]
            drawn = drawn or len(pl) > 0
            if len(pl):
                ax.errorbar(pl.M, pl.value, yerr=[pl.value - pl.lo, pl.hi - pl.value], linestyle="none", marker="o",
                            mfc="none", color="0.35", ms=6, capsize=2, lw=0.8,
                            label=f"{lab}: plain Monte Carlo, component 0 of the same runs (Wilson 95 %)")
            if fit is not None and len(fit):
                f = fit[fit.estimator == lab].iloc[0]
                if np.isfinite(f.exponent_fit) and np.isfinite(f.fit_M_lo):
                    mm = np.geomspace(f.fit_M_lo, f.fit_M_hi, 20)
                    sel = main[(main.M >= f.fit_M_lo) & (main.M <= f.fit_M_hi)]
                    c = np.polyfit(np.log(sel.M), np.log(sel.value), 1)
                    ci = f"[{f.ci_lo:.3f}, {f.ci_hi:.3f}]" if np.isfinite(f.ci_lo) else "(no interval)"
                    ax.plot(mm, np.exp(np.polyval(c, np.log(mm))), color=sty["color"], lw=1.6,
                            label=rf"fit: $\varphi$ = {f.exponent_fit:.3f}, 95 % CI {ci}")
                    if np.isfinite(f.exponent_theory):
                        xm = math.exp(0.5 * (math.log(f.fit_M_lo) + math.log(f.fit_M_hi)))
                        ym = math.exp(np.polyval(c, math.log(xm)))
                        ax.plot(mm, ym * (mm / xm) ** f.exponent_theory, color=PALETTE[5], lw=1.4, ls="--",
                                label=rf"theory: $\varphi$ = {f.exponent_theory:.3f} (slope only)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        n = int(t.n.max()) if len(t) else 0
        if not drawn:  # every estimate 0 (a short run): the empty axes at the M range, the run's resolution, and why
            ax.set_xlim(float(t.M.min()), float(t.M.max()))
            ax.set_ylim(min(0.1, 0.5 / max(n, 1)), 1.0)
            ax.text(0.5, 0.5, f"no run above any M (every estimate 0, n = {n:,})", transform=ax.transAxes,
                    ha="center", va="center", color="0.3")
        ax.set_xlabel(r"threshold $M$ (log scale)")
        ax.set_ylabel(rf"$\Pr[{X} > M]$ (log scale)")
        what = self.title or rf"tail of ${X}$: power law $M^{{\varphi}}$"
        ax.set_title(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        if ax.get_legend_handles_labels()[0]:
            legend_outside(ax, loc="below", ncol=1, bbox_to_anchor=(0.5, -0.2))
        footnote(fig, f"n = {n:,} run{'s' if n != 1 else ''}; theory (Mo & Sinopoli 2012): φ = log s / (2 log ρ(A)), s = 1 − λ "
                      f"(i.i.d.) or 1 − q (Gilbert–Elliott); importance weights ≤ number of mixture components")
        return fig


# =============================================================================================
# The critical recipe's Monte Carlo: time-averaged E[tr P] on the engine
# =============================================================================================


HEAVY_TAIL_RSE = 0.5
"""As the engine's rule: a mean is heavy-tailed when the relative s.e. of its sample variance exceeds this."""


def time_average_mean(system, channel, estimator, *, runs: int, horizon: int, burn_in: int, seed: int, chunk: int,
                      stream: int, progress=None, quantity: str = "predicted") -> dict:
    """Mean over runs of the per-run time average of tr P (``quantity``) over steps burn_in+1 … horizon, its s.e., and
    the 4th-moment heavy-tail flag. The per-run averages are the engine's (:class:`engine.TimeAverageReducer`, the
    fused kernel where the estimator has one: chunks of ≥ 1e6 run-steps of ``kf`` on a bernoulli channel); the
    summary is this module's, from their power sums."""
    steps = list(range(burn_in + 1, horizon + 1))
    st = engine.simulate(system, channel, [estimator], engine.TimeAverageReducer(steps), steps=steps, runs=runs,
                         horizon=horizon, seed=seed, chunk=chunk, stream=stream, progress=progress,
                         label="time_average_mean", quantity=quantity)
    n = float(st["n"])
    bad = int(st["nonfinite_avg"])
    s1, s2, s3, s4 = (float(st[k]) for k in ("sum_avg", "sumsq_avg", "sum3_avg", "sum4_avg"))
    m = max(n - bad, 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        mu = s1 / m
        var = max(s2 / m - mu * mu, 0.0)
        c4 = s4 / m - 4 * mu * s3 / m + 6 * mu**2 * s2 / m - 3 * mu**4
        rse = math.sqrt(max(c4 - var * var, 0.0) / m) / var if var > 0 else 0.0
    se = math.sqrt(var * m / max(m - 1, 1) / m)
    heavy = bad > 0 or not math.isfinite(rse) or rse > HEAVY_TAIL_RSE
    return {"mean_trace": mu if bad == 0 else math.inf, "stderr": se, "n": int(n), "heavy_tail": bool(heavy),
            "nonfinite": bad, "rse_variance": rse}
