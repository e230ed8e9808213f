"""Critical arrival rate (issue 16): ``kind: critical`` and the answer of ``netkf critical``.

For the scenario's system (A, C, Q, R):

* λ_min = 1 − 1/ρ(A)² ≤ λ_c ≤ λ_max (Sinopoli et al. 2004, Thms 3–5; λ_max by bisection on the
  LMI Ψ_λ(Y, Z) > 0, solved by Clarabel: :mod:`netkf_cli.linalg.sdp`), λ_c itself only where a theorem gives it
  (:func:`netkf_cli.analysis.critical.exact_case`);
* against λ: tr S̄ ≤ lim tr E[P_{k|k−1}] ≤ tr V̄ (Thms 3–4) and the Monte Carlo mean of
  tr P_{k|k−1} (``kf`` estimator, ``bernoulli`` channel, :func:`netkf_cli.metrics.tail.time_average_mean`),
  drawn hollow and not as a result where it is heavy-tailed, below the proven S̄, or dominated by loss bursts
  longer than the sample contains (:func:`netkf_cli.analysis.critical.mean_reliability`);
* the Gilbert–Elliott critical curve in the (failure rate p, recovery rate q) plane: necessary
  q > 1 − 1/ρ(A)², the sufficient Markov LMI, the exact curve where proven, and the recovery rate
  at which i.i.d. loss with the same average loss rate would reach the Bernoulli bound;
* the scenario's own channel (bernoulli, gilbert_elliott or delay with a receive buffer), judged.

Tables: ``<name>.csv`` (lam, series ∈ {S_bar, V_bar, monte_carlo}, value = trace, stderr, n,
reliable), ``<name>_rates.csv`` (λ_min, λ_max bracket, λ_c), ``<name>_ge.csv`` (the curve),
``<name>_claims.csv`` (checks turned into 1/0 with their evidence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, field_validator, model_validator

from netkf_cli.analysis import critical as cr
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.core.errors import ConfigError
from netkf_cli.metrics.tail import kf_for, time_average_mean
from netkf_cli.runtime.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.spec import AnalysisModel, PositiveFloat, PositiveInt, Probability, StrictModel
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.tolerances import CRITICAL_BISECTION_TOL, CRITICAL_BISECTION_TOL_MAX, CRITICAL_BISECTION_TOL_MIN

TOPIC = "critical"
PAPER = "Sinopoli et al. 2004"
DEFAULT_SYSTEM = dict(A=1.4, C=1.0, Q=0.2, R=0.5)
DEFAULT_LABEL = "Example 3.10 of Shi, Xie & Murray 2009: A = 1.4, C = 1, Q = 0.2, R = 0.5 (the `netkf mind` default)"


def _below_note(t, lmin: float) -> str:
    """The footnote's word on the asked arrival rates at or below λ_min, which the figure cannot show: no lower bound
    S̄ exists there and E[P_k] is unbounded (for some P0), so no Monte Carlo mean is drawn either."""
    below = sorted(float(x) for x in t.lam.unique() if float(x) <= lmin)
    if not below:
        return ""
    return (f" Not drawn: λ = {', '.join(f'{x:g}' for x in below)} ≤ λ_min = {lmin:.4g}, where E[P_k] is unbounded "
            f"(no S̄, no Monte Carlo mean).")


def _min_items_of_list(schema: dict, n: int) -> None:
    """JSON schema of a ``list[…] | Model | None`` field: the list branch needs at least ``n`` items."""
    for branch in schema.get("anyOf", []):
        if branch.get("type") == "array":
            branch["minItems"] = n


class RateGrid(StrictModel):
    """Evenly spaced arrival rates."""

    start: Probability = Field(description="first arrival rate λ")
    stop: Probability = Field(description="last arrival rate λ")
    num: PositiveInt = Field(12, description="number of rates")

    @model_validator(mode="after")
    def _order(self):
        if not 0 <= self.start < self.stop <= 1:
            raise ValueError(f"need 0 ≤ start < stop ≤ 1, got start = {self.start:g}, stop = {self.stop:g}")
        return self

    def values(self) -> np.ndarray:
        return np.linspace(self.start, self.stop, self.num)


# =============================================================================================
# The answer for one system (+ channel): shared by the recipe and `netkf critical`
# =============================================================================================


def _mat(X):
    X = np.asarray(X, dtype=float)
    if not np.all(np.isfinite(X)):
        return None
    return float(X.ravel()[0]) if X.size == 1 else X.tolist()


def _num(x):
    return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else float(x)


def envelope(s: LinearSystem, lam: float, lam_max_hi: float) -> dict:
    """S̄ and V̄ at arrival rate λ (Thms 3–4): bounds on lim E[P_{k|k−1}] where they exist."""
    S = cr.s_bar(s.A, s.Q, lam)
    V = cr.v_bar(s.A, s.C, s.Q, s.R, lam) if lam > lam_max_hi else np.full(s.A.shape, np.inf)
    return {"lambda": lam, "S_bar": _mat(S), "V_bar": _mat(V),
            "trace_S_bar": _num(float(np.trace(S))), "trace_V_bar": _num(float(np.trace(V))),
            "meaning": "S̄ ≤ lim E[P_{k|k−1}] ≤ V̄ (PSD order; Sinopoli et al. 2004, Thms 3–4); "
                       "null = the bound does not exist at this λ"}


def judge_rate(lam: float, lam_min: float, lam_max_hi: float, exact: cr.ExactCase | None,
               certificate: float | None = None) -> tuple[str, bool | None]:
    """(sentence, bounded?) for i.i.d. arrivals at rate λ; bounded = None when not decided.

    ``certificate``: a numerical upper bound on λ_c tighter than λ_max (:func:`cr.lambda_c_certificate`)."""
    if exact is not None and exact.value is None:
        return "E[P_k] is unbounded whatever λ ((A, C) not detectable)", False
    if exact is not None:
        ok = lam > exact.value
        return (f"λ = {lam:.6g} {'>' if ok else '≤'} λ_c = {exact.value:.6g}: E[P_k] "
                f"{'bounded' if ok else 'unbounded (for some P0)'} "
                f"({'derived closed form' if exact.basis == 'derived' else 'proven'})", ok)
    if lam > lam_max_hi:
        return f"λ = {lam:.6g} > λ_max = {lam_max_hi:.6g}: E[P_k] bounded (proven, Thm 4)", True
    if certificate is not None and math.isfinite(certificate) and lam > certificate:
        return (f"λ = {lam:.6g} > {certificate:.6g}, the numerical certificate's bound: E[P_k] bounded (a strict "
                f"super-solution of the L-step averaged Riccati map, checked in floating point)", True)
    if certificate is not None and math.isfinite(certificate) and certificate < lam_max_hi:
        lam_max_hi = certificate
    if lam <= lam_min:
        return (f"λ = {lam:.6g} ≤ {lam_min:.6g} ≤ λ_c (λ_min, Thm 3, or a degenerate 2×2 sub-system's λ_c): E[P_k] "
                f"unbounded for some P0", False)
    return (f"λ = {lam:.6g} lies in [λ_min, upper bound] = [{lam_min:.6g}, {lam_max_hi:.6g}]: not decided by the known "
            f"bounds", None)


@dataclass
class CriticalAnswer:
    """What ``netkf critical`` prints: the rates, the proven case, the channel verdict, the E[P] envelope."""

    system_label: str
    s: LinearSystem
    report: cr.CriticalReport
    channel: dict = field(default_factory=dict)

    def as_json(self) -> dict:
        out = {"system": self.system_label, "paper": f"{PAPER}, Thms 2–5", **self.report.as_json()}
        out["channel"] = self.channel
        return out

    def text(self) -> str:
        r, lm, e = self.report, self.report.lam_max, self.report.exact
        lines = [
            f"Critical arrival rate of the Kalman filter with i.i.d. packet loss   ({PAPER})",
            f"  system      {self.system_label}",
            f"              n = {r.n}, m = {r.m}, ρ(A) = {r.rho:.6g}",
            f"  λ_min = 1 − 1/ρ(A)² = {r.lam_min:.6g}                          (Thm 3: λ_c ≥ λ_min)",
        ]
        if math.isinf(lm.hi) and lm.statuses and str(lm.statuses[0]).startswith("not solved"):
            lines.append(f"  λ_max: not computed — {lm.solver} could not solve the LMI for this badly scaled system "
                         f"(ρ(A) = {r.rho:.3g}); not needed, λ_c is proven below")
        elif math.isinf(lm.hi):
            lines.append(f"  λ_max: none — the LMI Ψ_λ(Y, Z) > 0 is infeasible even at λ = 1 ({lm.solver}, status "
                         f"{'/'.join(lm.statuses)})")
        else:
            lines.append(f"  λ_max ∈ ({lm.lo:.6g}, {lm.hi:.6g}]   (Thm 5 LMI Ψ_λ(Y, Z) > 0, bisection tol {lm.tol:g}, "
                         f"{lm.solver}, {lm.solves} solves, status {'/'.join(lm.statuses)}; upper end certified)")
        nd = r.nondegeneracy
        if nd is not None and nd.groups:
            lines.append(f"  non-degeneracy (Mo & Sinopoli 2012): {'yes' if nd.non_degenerate else 'no'} — {nd.summary()}")
        c = r.certificate
        if r.lower_bound is not None:
            lines.append(f"  lower:      λ_c ≥ {r.lower_bound.value:.6g} — {r.lower_bound.why}")
        if e is None and c is not None and math.isfinite(c.hi) and c.hi < lm.hi:
            lines.append(f"  certified:  λ_c ≤ {c.hi:.6g}  (numerical certificate: {c.L}-step averaged Riccati map over all "
                         f"2^{c.L} arrival patterns, bisection ± {c.tol:g}; tighter than λ_max)")
            lines.append(f"  decided:    no theorem decides λ_c for this degenerate system: {r.lower:.6g} ≤ λ_c ≤ {c.hi:.6g}")
        elif e is None:
            lines.append("  proven:     only the interval λ_min ≤ λ_c ≤ λ_max — none of the exactness conditions holds")
            lines.append("              (scalar; C invertible on the observable subspace; non-degenerate; degenerate 2×2 "
                         "with a root-of-unity eigenvalue ratio; ρ(A) ≤ 1)")
        elif e.value is None:
            lines.append(f"  proven:     {e.condition} — {e.source}")
        else:
            word = "derived" if e.basis == "derived" else "proven"
            lines.append(f"  {word + ':':11s} λ_c = {e.value:.6g} exactly — {e.condition}")
            lines.append(f"              ({e.source})")
        lines.append(f"  decided by: {r.decided_by}")
        ch = self.channel
        if ch:
            lines.append("")
            lines.append(f"  channel     {ch.get('label', ch.get('kind'))}")
            for key in ("detail", "verdict", "bernoulli_same_loss"):
                if ch.get(key):
                    lines.append(f"              {ch[key]}")
            env = ch.get("envelope")
            if env:
                S, V = env["trace_S_bar"], env["trace_V_bar"]
                lines.append(f"  E[P] envelope at λ = {env['lambda']:.6g}:  "
                             f"tr S̄ = {('%.6g' % S) if S is not None else 'does not exist'}  ≤  lim tr E[P_k|k-1]  ≤  "
                             f"tr V̄ = {('%.6g' % V) if V is not None else 'not available (λ ≤ λ_max)'}")
        lines += ["", "Verdict: " + r.verdict()]
        if ch.get("verdict"):
            lines.append("         " + ch["verdict"])
        return "\n".join(lines)


def channel_answer(s: LinearSystem, channel, report: cr.CriticalReport, *, solver: str = "CLARABEL") -> dict:
    """The stability verdict for the scenario's channel (bernoulli, gilbert_elliott, delay)."""
    if channel is None:
        return {}
    kind = getattr(channel, "kind", None)
    lmin, lhi, e = report.lower, report.lam_max.hi, report.exact
    cert = report.certificate.hi if report.certificate is not None else None
    if kind == "bernoulli":
        lam = float(channel.arrival)
        verdict, ok = judge_rate(lam, lmin, lhi, e, cert)
        return {"kind": kind, "label": f"bernoulli, arrival rate λ = {lam:g}", "arrival": lam, "bounded": ok,
                "verdict": verdict, "envelope": envelope(s, lam, lhi)}
    if kind == "gilbert_elliott":
        p, q = channel.transition
        lam = q / (p + q)
        qn = cr.ge_q_necessary(s.A)
        ege = cr.exact_case_ge(s.A, s.C)
        if ege is not None and ege.value is None:
            ok, why = False, "(A, C) not detectable"
        elif ege is not None and ege.key == "stable":
            ok, why = True, f"{ege.condition}: E[P_k] bounded for every loss process"
        elif ege is not None:
            ok = q > ege.value
            how = ("Mo & Sinopoli 2012 for Gilbert–Elliott loss" if ege.key in ("non_degenerate", "c_invertible_observable")
                   else "one received packet bounds P")
            why = (f"recovery rate q = {q:.6g} {'>' if ok else '≤'} 1 − 1/ρ(A)² = {ege.value:.6g}: necessary and "
                   f"sufficient here ({ege.key.replace('_', ' ')}; {how}), whatever the failure rate")
        elif e is not None and e.key.startswith("degenerate_2x2_p"):
            P = int(e.key.rsplit("p", 1)[1])
            qd = cr.ge_degenerate_critical_q(s.A, s.C, p)
            ok = q > qd if qd < 1.0 else False
            why = ((f"recovery rate q = {q:.6g} {'>' if ok else '≤'} q_c(p) = {qd:.6g}" if qd < 1.0 else
                    f"no recovery rate suffices at failure rate p = {p:.6g}") +
                   f" (derived for a degenerate 2×2 system, p-order {P}: E[P] < ∞ ⇔ ρ^(2·{P})·μ_{P}(p, q) < 1, μ the "
                   f"decay of windows whose arrivals share one residue class; experiments/critical/README.md)")
        elif q <= qn:
            ok, why = False, f"q = {q:.6g} ≤ 1 − 1/ρ(A)² = {qn:.6g}: E[P_k] unbounded (necessary condition fails)"
        else:
            feas, _ = cr._MarkovLMI(np.atleast_2d(s.A), np.atleast_2d(s.C), solver).feasible(p, q)
            ok = True if feas else None
            why = (f"q = {q:.6g} > {qn:.6g} (necessary) and the Markov LMI is "
                   + ("feasible: E[P_k] bounded (sufficient condition)" if feas else "infeasible: not decided"))
        b_verdict, b_ok = judge_rate(lam, lmin, lhi, e, cert)
        return {"kind": kind, "label": f"gilbert_elliott, failure rate p = {p:.6g}, recovery rate q = {q:.6g} "
                                       f"(stationary arrival rate {lam:.6g}, mean loss burst {1 / q:.4g} steps)",
                "p": p, "q": q, "q_necessary": qn, "bounded": ok, "verdict": "Gilbert–Elliott: " + why,
                "bernoulli_same_loss": f"i.i.d. loss at the same average rate: {b_verdict}",
                "bernoulli_bounded": b_ok}
    if kind == "delay":
        lam, Dmax = cr.delay_effective_rate(channel)
        verdict, ok = judge_rate(lam, lmin, lhi, e, cert)
        return {"kind": kind, "label": f"delay ({channel.delay.kind}), buffer D = {channel.D}, convention {channel.convention}",
                "usable_fraction": lam, "D_max": Dmax, "bounded": ok,
                "detail": (f"usable packets: delay ≤ {Dmax} ⇒ λ_eff = F({Dmax}) = {lam:.6g}; with i.i.d. delays the "
                           f"buffered estimator is stable iff i.i.d. loss at λ_eff is (exact reduction)"),
                "verdict": "buffered estimator: " + verdict,
                "envelope": envelope(s, lam, lhi),
                "envelope_note": "S̄, V̄ at λ_eff bound the KF fed with every eventually-used packet; the buffered "
                                 "estimator's P_k lies between that and h^{D_max} of it"}
    return {"kind": kind, "label": f"{kind} (no stability rule for this channel kind: the system's rates only)"}


def critical_answer(*, config: Path | None = None, scenario=None, locate=None, arrival: float | None = None,
                    tol: float = CRITICAL_BISECTION_TOL) -> CriticalAnswer:
    """Build the answer for a loaded scenario's system and channel (``config`` names its file), or for the default.

    The caller loads the scenario (recipes sit below the loader in the import layers); ``locate(exc)`` attaches the
    file and line to a problem found here (the CLI passes the loader's).
    """
    channel = None
    if config is not None and scenario is None:
        raise TypeError("critical_answer: load the scenario first (netkf_cli.config.loader.load_scenario) and pass scenario=")
    if scenario is not None:
        sc = scenario
        try:
            s = sc.linear_system()
        except ConfigError as exc:
            raise (locate(exc) if locate is not None else exc) from None
        label, channel = f"from {config}" if config is not None else f"from scenario {sc.name}", sc.channel
        if isinstance(sc.analysis, CriticalAnalysis):
            tol = min(tol, sc.analysis.bisection_tol)
    else:
        s, label = LinearSystem.create(**DEFAULT_SYSTEM), DEFAULT_LABEL
    if arrival is not None:
        channel = BernoulliChannel(kind="bernoulli", arrival=arrival)
    rep = cr.critical_report(s.A, s.C, tol=tol, Q=s.Q, R=s.R)
    return CriticalAnswer(label, s, rep, channel_answer(s, channel, rep))


# =============================================================================================
# The artefact
# =============================================================================================


class CriticalAnalysis(AnalysisModel):
    """``kind: critical`` — λ_min ≤ λ_c ≤ λ_max, S̄ ≤ lim E[P] ≤ V̄ against λ with Monte Carlo, Gilbert–Elliott curve."""

    kind: Literal["critical"]
    lambdas: list[Probability] | RateGrid | None = Field(
        None, description="arrival rates λ for S̄, V̄ and the Monte Carlo (default: 12 rates from λ_min to 1)",
        json_schema_extra=lambda schema: _min_items_of_list(schema, 1))
    failure_rates: list[Probability] = Field(
        [0.02, 0.05, 0.1, 0.2, 0.4, 0.6, 0.8, 1.0],
        description="Gilbert–Elliott failure rates p = P(loss | arrival) of the critical curve (x-axis)")
    bisection_tol: PositiveFloat = Field(CRITICAL_BISECTION_TOL, ge=CRITICAL_BISECTION_TOL_MIN, le=CRITICAL_BISECTION_TOL_MAX,
                                         description=f"bisection tolerance on λ_max ({CRITICAL_BISECTION_TOL_MIN:g} … "
                                                     f"{CRITICAL_BISECTION_TOL_MAX:g}, as `netkf critical --tol`)")
    q_tol: PositiveFloat = Field(1e-3, description="bisection tolerance on the sufficient recovery rate q of the Markov LMI")
    monte_carlo: bool = Field(True, description="simulate E[tr P_{k|k−1}] with the generic engine at every λ above λ_min")
    title: str | None = Field(None, description="figure title (default: the system's name from the scenario)")

    @field_validator("lambdas")
    @classmethod
    def _some_lambdas(cls, v):
        # an empty list got through to the artefact, which has no row to draw (internal error out of `netkf run`);
        # min_length on the list branch of the union would add a second, RateGrid, error beside this one
        if isinstance(v, list) and not v:
            raise ValueError("needs at least one arrival rate λ, got an empty list (leave `lambdas` out for the "
                             "default: 12 rates from λ_min to 1)")
        return v

    def _grid(self, lam_min: float, lam_hi: float) -> np.ndarray:
        if isinstance(self.lambdas, RateGrid):
            return self.lambdas.values()
        if self.lambdas is not None:
            return np.asarray(sorted(self.lambdas), float)
        lo = lam_min
        # dense near the threshold, where the bounds blow up
        u = np.array([0.01, 0.03, 0.06, 0.1, 0.15, 0.2, 0.3, 0.4, 0.55, 0.7, 0.85, 0.97])
        g = lo + (1 - lo) * u
        if lam_hi > lo and math.isfinite(lam_hi):
            g = np.union1d(g, lam_hi + (1 - lam_hi) * np.array([0.01, 0.03]))
        return np.round(g, 6)

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        rep = cr.critical_report(s.A, s.C, tol=self.bisection_tol, Q=s.Q, R=s.R)
        lm, e = rep.lam_max, rep.exact
        lams = self._grid(rep.lam_min, lm.hi)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        est = kf_for("predicted")  # the envelope bounds the prediction P_{k+1|k}
        growth, stay_pow = cr.spectral_radius(s.A) ** 2, 1.0
        if e is not None and e.key.startswith("degenerate_2x2_p"):
            pp = int(e.key.rsplit("p", 1)[1])
            stay_pow = 1.0 if pp == 1 else (pp - 1) / pp  # one-residue-class windows: s^{(p−1)/p} per step
        do_mc = self.monte_carlo and (e is None or e.value is not None)
        n_mc = int(sum(1 for lam in lams if lam > rep.lam_min and lam < 1)) if do_mc else 0
        ctx.total(runs * n_mc)
        rows, flags = [], []
        above = [float(lam) for lam in lams if lam > lm.hi]  # where V̄ exists: all fixed points in one iteration
        v_bars = dict(zip(above, cr.v_bars(s.A, s.C, s.Q, s.R, above)))
        for i, lam in enumerate(lams):
            lam = float(lam)
            base = dict(lam=lam, lambda_min=rep.lam_min, lambda_max=lm.hi)
            S = cr.s_bar(s.A, s.Q, lam)
            V = v_bars.get(lam, np.full(s.A.shape, np.inf))
            for series, X in (("S_bar", S), ("V_bar", V)):
                tr = float(np.trace(X))
                rows.append(dict(base, series=series, value=tr if math.isfinite(tr) else np.nan, stderr=0.0,
                                 n=np.nan, reliable=1.0 if math.isfinite(tr) else 0.0))
            if do_mc and rep.lam_min < lam < 1:
                ch = BernoulliChannel(kind="bernoulli", arrival=lam)
                r = time_average_mean(s, ch, est, runs=runs, horizon=mc.horizon, burn_in=mc.burn_in, seed=mc.seed,
                                      chunk=mc.chunk, stream=i + 1, progress=ctx.progress, quantity="predicted")
                trS = float(np.trace(S))
                mr = cr.mean_reliability(r["mean_trace"], r["stderr"], runs=r["n"], steps=mc.horizon - mc.burn_in,
                                         loss_stay=(1 - lam) ** stay_pow, growth=growth,
                                         lower_bound=trS if math.isfinite(trS) else None)
                ok = (not r["heavy_tail"]) and r["nonfinite"] == 0 and math.isfinite(r["mean_trace"]) and mr.reliable
                code = (0.0 if ok else 2.0 if mr.reason.startswith("below") else 3.0 if mr.reason.startswith("rare")
                        else 1.0)
                flags.append(dict(lam=lam, code=code, reason=mr.reason or ("heavy-tailed sample (4th-moment rule)"
                                                                             if r["heavy_tail"] else "")))
                rows.append(dict(base, series="monte_carlo", value=r["mean_trace"] if math.isfinite(r["mean_trace"]) else np.nan,
                                 stderr=r["stderr"], n=r["n"], reliable=1.0 if ok else 0.0, flag=code,
                                 missing_fraction=mr.missing_fraction))
        table = pd.DataFrame(rows)

        # ---- rates (one row each) ----
        rates = pd.DataFrame([
            dict(quantity="lambda_min", value=rep.lam_min),
            dict(quantity="lambda_max_lower", value=lm.lo),
            dict(quantity="lambda_max_upper", value=lm.hi if math.isfinite(lm.hi) else np.nan),
            dict(quantity="lambda_c", value=np.nan if e is None or e.value is None else e.value),
            dict(quantity="proven", value=1.0 if e is not None else 0.0),
            dict(quantity="lambda_c_upper", value=rep.upper if math.isfinite(rep.upper) else np.nan),
            dict(quantity="certificate_upper", value=np.nan if rep.certificate is None or not math.isfinite(rep.certificate.hi)
                 else rep.certificate.hi),
            dict(quantity="non_degenerate", value=np.nan if rep.nondegeneracy is None else float(rep.nondegeneracy.non_degenerate)),
            dict(quantity="lambda_c_lower", value=rep.lower),
        ])
        cert = rep.certificate
        rates["condition"] = (e.key if e is not None else
                              "numerical certificate" if cert is not None and math.isfinite(cert.hi) and cert.hi < lm.hi
                              else "interval only")
        rates["basis"] = "none" if e is None else e.basis
        rates["decided_by"] = rep.decided_by

        # ---- Gilbert–Elliott curve ----
        lam_ref = e.value if (e is not None and e.value is not None) else lm.hi
        ge_rows = []
        if e is None or e.value is not None:
            for pt in cr.ge_critical_curve(s.A, s.C, self.failure_rates, tol=self.q_tol, lam_c_upper=lam_ref):
                ge_rows.append(dict(p=pt.p, q_necessary=pt.q_necessary,
                                    q_sufficient=pt.q_sufficient if math.isfinite(pt.q_sufficient) else np.nan,
                                    q_exact=np.nan if pt.q_exact is None else pt.q_exact,
                                    q_bernoulli_same_loss=pt.q_bernoulli_same_loss,
                                    q_iid=1.0 - pt.p))
        ge = pd.DataFrame(ge_rows, columns=["p", "q_necessary", "q_sufficient", "q_exact", "q_bernoulli_same_loss", "q_iid"])
        ege = cr.exact_case_ge(s.A, s.C)
        ge["exact_by"] = (ege.key if ege is not None else
                          f"{e.key} (derived)" if e is not None and e.key.startswith("degenerate_2x2_p") else "")

        # ---- claims ----
        claims = self._claims(table, rep, ge)
        chan = channel_answer(s, scenario.channel, rep)
        meta = {"paper": f"{PAPER}, Thms 2–5; Plarre & Bullo 2009; Gilbert–Elliott: see experiments/critical/README.md",
                "report": rep.as_json(), "channel": chan,
                "value": "trace of the bound / of the Monte Carlo mean of P_{k|k−1} (kf, report: predicted)",
                "monte_carlo": {"runs": runs, "horizon": mc.horizon, "burn_in": mc.burn_in,
                                "sample": "per run, the time average of tr P_{k|k−1} over k in (burn_in, horizon]; "
                                          "P0 = P̄; stream i+1 for the i-th λ",
                                "reliable": "0 (drawn hollow, not a result) where the sample is heavy-tailed (4th-moment "
                                            "rule), a run overflowed, the mean lies > 3 s.e. below tr S̄, or loss bursts "
                                            "longer than the sample contains carry > 5 % of the mean "
                                            "(analysis.critical.mean_reliability; column flag says which)"},
                "title": self.title,
                "flags": {"codes": "flag: 0 reliable, 1 heavy-tailed (4th-moment rule) or overflow, 2 > 3 s.e. below tr S̄, "
                                   "3 rare-event dominated (loss bursts longer than the sample contains)",
                          "rows": flags}}
        return Artefact(table, meta=meta, extra_tables={"rates": rates, "ge": ge, "claims": claims})

    @staticmethod
    def _claims(table: pd.DataFrame, rep: cr.CriticalReport, ge: pd.DataFrame) -> pd.DataFrame:
        rows = []
        lm = rep.lam_max
        rows.append(dict(claim="lambda_min_le_lambda_max", value=float(rep.lam_min <= lm.hi + lm.tol),
                         lhs=rep.lam_min, rhs=lm.hi, detail="Thm 3 ≤ Thm 4 (bisection started at 0)"))
        if rep.exact is not None and rep.exact.value is not None:
            rows.append(dict(claim="lambda_c_in_bracket", value=float(rep.lam_min - 1e-12 <= rep.exact.value <= lm.hi + lm.tol),
                             lhs=rep.exact.value, rhs=lm.hi, detail=f"exact λ_c ({rep.exact.key}) inside [λ_min, λ_max]"))
        mc = table[(table.series == "monte_carlo") & (table.reliable > 0)]
        if len(mc):
            ok, worst = True, -np.inf
            for _, r in mc.iterrows():
                S = table[(table.lam == r.lam) & (table.series == "S_bar")].value.iloc[0]
                V = table[(table.lam == r.lam) & (table.series == "V_bar")].value.iloc[0]
                # 5 standard errors of the Monte Carlo mean (the bounds are exact numbers)
                lo_ok = not np.isfinite(S) or r.value >= S - 5 * r.stderr
                hi_ok = not np.isfinite(V) or r.value <= V + 5 * r.stderr
                ok &= bool(lo_ok and hi_ok)
                if np.isfinite(S) and r.stderr > 0:
                    worst = max(worst, (S - r.value) / r.stderr)
                if np.isfinite(V) and r.stderr > 0:
                    worst = max(worst, (r.value - V) / r.stderr)
            rows.append(dict(claim="monte_carlo_between_bounds", value=float(ok), lhs=float(worst), rhs=5.0,
                             detail=f"{len(mc)} reliable Monte Carlo means within [S̄ − 5 s.e., V̄ + 5 s.e.] "
                                    "(lhs: largest excursion beyond a bound, in standard errors)"))
        if len(ge):
            good = ge.q_sufficient.isna() | (ge.q_sufficient >= ge.q_necessary - 1e-9)
            rows.append(dict(claim="ge_necessary_le_sufficient", value=float(good.all()), lhs=float(ge.q_necessary.max()),
                             rhs=float(ge.q_sufficient.min()), detail="q_necessary ≤ q_sufficient at every failure rate"))
        return pd.DataFrame(rows, columns=["claim", "value", "lhs", "rhs", "detail"])

    # -----------------------------------------------------------------------------------------

    def plot(self, tables, scenario):
        t, rates, ge = tables["main"], tables["rates"], tables.get("ge")
        fig, (ax, bx) = new_figure(nrows=2, width=9.0, height=3.9)
        r = dict(zip(rates.quantity, rates.value))
        lmin, lhi, lc = r["lambda_min"], r["lambda_max_upper"], r["lambda_c"]
        cond = str(rates.condition.iloc[0])
        basis = str(rates.basis.iloc[0]) if "basis" in rates else "theorem"
        cert = r.get("certificate_upper", np.nan)
        # ---- left: bounds on lim E[tr P] against λ ----
        Sb = t[(t.series == "S_bar") & np.isfinite(t.value)]
        Vb = t[(t.series == "V_bar") & np.isfinite(t.value)]
        if len(Sb):
            ax.plot(Sb.lam, Sb.value, **{**series_style(0), "markersize": 4}, label=r"tr $\bar S$ (Thm 3, lower)")
        if len(Vb):
            ax.plot(Vb.lam, Vb.value, **{**series_style(1), "markersize": 4}, label=r"tr $\bar V$ (Thm 4, upper)")
        m = t[t.series == "monte_carlo"]
        good, bad = m[m.reliable > 0], m[m.reliable <= 0]
        if len(good):
            st = series_style(2)
            ax.errorbar(good.lam, good.value, yerr=good.stderr, fmt=st["marker"], color=st["color"], ms=5, capsize=2,
                        label=r"Monte Carlo $E[\mathrm{tr}\,P_{k \mid k-1}]$ ± 1 s.e.")
        if len(bad):
            st = series_style(2)
            ax.plot(bad.lam, np.where(np.isfinite(bad.value), bad.value, np.nan), marker=st["marker"], mfc="none",
                    color="0.45", ms=7, linestyle="none",
                    label="Monte Carlo, unreliable: rare-event dominated\n(heavy tail / below S̄ / unseen bursts; not a result)")
        ax.axvline(lmin, color="0.2", lw=1.0, ls="--", label=rf"$\lambda_{{min}}$ = {lmin:.4g}")
        if np.isfinite(lhi):
            ax.axvline(lhi, color=PALETTE[3], lw=1.0, ls="-.", label=rf"$\lambda_{{max}}$ = {lhi:.4g} (LMI)")
        if np.isfinite(lc):
            word = "derived closed form" if basis == "derived" else "theorem"
            ax.axvline(lc, color=PALETTE[2], lw=1.6, ls=":", label=rf"$\lambda_c$ = {lc:.4g}, exact: {word} ({cond.replace('_', ' ')})")
        elif np.isfinite(cert) and cert < lhi:
            low = r.get("lambda_c_lower", lmin)
            low = lmin if not np.isfinite(low) else low
            ax.axvspan(low, cert, color="0.85", alpha=0.6, lw=0,
                       label=rf"$\lambda_c \in$ [{low:.4g}, {cert:.4g}]: numerical certificate (no theorem)")
        elif np.isfinite(lhi) and lhi > lmin:
            ax.axvspan(lmin, lhi, color="0.85", alpha=0.6, lw=0, label=r"$\lambda_c$ undecided")
        ax.set_yscale("log")
        ax.set_xlabel(r"arrival rate $\lambda$ (probability)")
        ax.set_ylabel(r"$\lim\ \mathrm{tr}\,E[P_{k \mid k-1}]$ (log scale)")
        ax.set_title(r"Bounds on $E[P]$ against $\lambda$", fontsize=10)
        legend_outside(ax, loc="right")
        # ---- right: Gilbert–Elliott plane ----
        if ge is not None and len(ge):
            exq = ge.q_exact if "q_exact" in ge else None
            if exq is not None and np.isfinite(exq).all() and (exq > ge.q_necessary + 1e-9).any():
                bx.fill_between(ge.p, exq, 0, color="0.88", lw=0, label="unstable: below the exact curve")
            else:
                bx.fill_between(ge.p, ge.q_necessary, 0, color="0.88", lw=0, label=r"unstable: $q \leq 1 - 1/\rho(A)^2$")
            bx.plot(ge.p, ge.q_necessary, **{**series_style(0), "marker": None, "lw": 2.2},
                    label=r"necessary: $q > 1 - 1/\rho(A)^2$")
            suf = ge[np.isfinite(ge.q_sufficient)]
            bx.plot(suf.p, suf.q_sufficient, **{**series_style(1), "markersize": 4}, label="sufficient (Markov LMI)")
            ex = ge[np.isfinite(ge.q_exact)]
            if len(ex):
                by = str(ge.exact_by.iloc[0]) if "exact_by" in ge and isinstance(ge.exact_by.iloc[0], str) else ""
                if "derived" in by:
                    lab = f"exact curve, derived ({by.split()[0].replace('_', ' ')});\nat q = 1: no recovery rate suffices"
                else:
                    src = "Mo & Sinopoli 2012" if by in ("non_degenerate", "c_invertible_observable") else "one arrival bounds P"
                    lab = f"exact critical curve ({by.replace('_', ' ')}; {src})"
                bx.plot(ex.p, ex.q_exact, **{**series_style(2), "markersize": 4, "linestyle": ":"}, label=lab)
                if "derived" in by and ge.p.min() < 0.05 * ge.p.max():
                    bx.set_xscale("log")
            else:
                bx.plot([], [], " ", label="no exact curve (degenerate): only necessary / sufficient")
            qb = ge.q_bernoulli_same_loss.clip(upper=1.0)
            keep = ge.q_bernoulli_same_loss <= 1.0
            bx.plot(ge.p[keep], qb[keep], **{**series_style(3), "marker": None},
                    label=r"i.i.d. at the same average loss: $q/(p+q) = \lambda_c$" if np.isfinite(lc) else
                    r"i.i.d. at the same average loss: $q/(p+q) = \lambda_{max}$")
            bx.plot(ge.p, ge.q_iid, color="0.5", lw=0.8, ls=(0, (1, 2)), label=r"i.i.d. channels: $q = 1 - p$")
            ch = (scenario.channel if scenario.channel is not None and getattr(scenario.channel, "kind", "") == "gilbert_elliott" else None)
            if ch is not None:
                p, q = ch.transition
                bx.plot([p], [q], "*", ms=11, color=PALETTE[5], linestyle="none", label=f"this channel (p = {p:.3g}, q = {q:.3g})")
            if bx.get_xscale() == "log":
                bx.set_xlim(ge.p.min() / 1.5, 1.3)
            else:
                bx.set_xlim(0, 1.02)
            bx.set_ylim(0, 1.02)
            curves = [ge.q_necessary, ge.q_sufficient, ge.q_exact if "q_exact" in ge else ge.q_necessary, qb[keep]]
            top = max((float(np.nanmax(c)) for c in curves if np.isfinite(c).any()), default=np.nan)
            if top < 0.03:  # every curve flat on the p-axis (ρ(A) ≈ 1): say what the empty-looking panel means
                rho = 1.0 / math.sqrt(max(1.0 - float(np.nanmax(ge.q_necessary)), 1e-300))
                bx.text(0.64, 0.84, f"every curve lies at q ≤ {top:.2g}\n(ρ(A) = {rho:.4g}): stable for\n(almost) "
                                  f"every recovery rate q > 0", ha="center", va="center", fontsize=9, color="0.3",
                        transform=bx.transAxes)
            bx.set_xlabel(r"failure rate $p$ = P(loss | arrival)" + (" (log scale)" if bx.get_xscale() == "log" else ""))
            bx.set_ylabel(r"recovery rate $q$ = P(arrival | loss)")
            bx.set_title("Gilbert–Elliott: stable above the curve", fontsize=10)
            legend_outside(bx, loc="right")
        else:
            bx.set_axis_off()
            bx.text(0.5, 0.5, "no Gilbert–Elliott curve: (A, C) is not detectable,\nE[P] diverges for every channel",
                    ha="center", va="center", fontsize=10, transform=bx.transAxes)
        what = self.title or scenario.description or scenario.name
        fig.suptitle(paper_title(TOPIC, None, f"critical arrival rate — {what}"), fontsize=10)
        n = m.n.dropna()
        decided = str(rates.decided_by.iloc[0]).split(":")[0] if "decided_by" in rates else ""
        footnote(fig, f"{PAPER}, Thms 3–5: " + r"$\lambda_{min} \leq \lambda_c \leq \lambda_{max}$; "
                      r"tr $\bar{S}$ ≤ lim tr E[$P_{k \mid k-1}$] ≤ tr $\bar{V}$. $\lambda_c$: " + f"{decided}. "
                      f"Monte Carlo: {int(n.iloc[0]) if len(n) else 0} runs per λ (time average after burn-in). "
                      f"Markov LMI: constant-gain predictor, mean-square stable under the Gilbert chain."
                      + _below_note(t, lmin))
        return fig
