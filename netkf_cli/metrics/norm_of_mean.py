"""‖E P‖₂ — the spectral norm of the MEAN covariance matrix (Mostofi & Murray 2009, eq. 21 and Fig. 6's
"spectral norm of the average estimation error covariance"), with a delta-method standard error.

Per run r the reducer keeps the packed upper triangle x_r = vech(P̄_r) (n(n+1)/2 entries) of P̄_r, the
average of P_k over the metric's steps (one step: P_k itself), and sums Σ x_r and the cross-moments
Σ x_r x_rᵀ (additive over chunks: the statistics do not depend on the chunking). From them

* M̂ = mean of x_r unpacked (an unbiased estimate of E P̄; a variance-reduced estimator's per-run
  conditional mean of P — the fading receivers' burst-conditioned U_k — is unbiased too);
* ‖M̂‖₂ = λ_max(M̂) (M̂ is PSD), whose gradient at M̂ is u uᵀ (u the unit top eigenvector) when λ_max
  is simple: in packed coordinates g_ab = u_a u_b (a = b) and 2 u_a u_b (a < b), so
  Var ‖M̂‖ ≈ gᵀ S g / m with S the sample covariance of the x_r and m the finite runs (delta method).

The delta method needs the top eigenvalue to be simple at the scale of the sampling error. For every
lower eigenvalue λ_i (eigenvector u_i) the noise of M̂ on the plane (u, u_i) is a 2 × 2 block
[[λ₁ + a, c], [c, λ_i + b]] (a = uᵀΔu, b = u_iᵀΔu_i, c = uᵀΔu_i, Δ = M̂ − E P̄), whose eigenvalues split by
√((λ₁ − λ_i + a − b)² + 4c²); its noise scale s_i = √(Var(a − b) + 4 Var(c)) comes from the same S. The
point is flagged ``eigen_gap`` (s.e. NaN) when λ₁ − λ_i < :data:`EIGEN_GAP_SE` · s_i for some i: λ_max is then
not differentiable on the scale of the noise, and λ_max(M̂) is biased upward by about the noise itself.
Otherwise the second-order bias Σ_i E c²/(λ₁ − λ_i) is below s_i/EIGEN_GAP_SE per direction. Tail flags are those of tr P̄_r (λ_max(P) ≤ tr P ≤ n λ_max(P), so uᵀ P u has no
heavier a tail than tr P)."""

from __future__ import annotations

import numpy as np

from netkf_cli.core.tolerances import EIGEN_GAP_SE, ROUNDOFF_VARIANCE

EIGEN_GAP_REASON = ("the top eigenvalue of the mean is (near-)degenerate: λ1 − λi < 5 s.e. of the mean's 2 x 2 block "
                    "on (u1, ui) for some i, so the delta-method s.e. of its norm is invalid (stderr NaN)")


_TRIU: dict = {}


def triu(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The packed upper-triangle indices (row-major, as :func:`numpy.triu_indices`)."""
    if n not in _TRIU:
        _TRIU[n] = np.triu_indices(n)
    return _TRIU[n]


def unpack(x: np.ndarray, n: int) -> np.ndarray:
    """The symmetric n × n matrix of a packed upper triangle x."""
    i, j = triu(n)
    M = np.zeros((n, n))
    M[i, j] = x
    M[j, i] = x
    return M


class MeanMatrixReducer:
    """Per column j: Σ x_r (``sum_T_j``), Σ x_r x_rᵀ (``cross_T_j``) of the packed per-run average P̄_r over
    ``steps``, and the trace statistics of :class:`netkf_cli.engine.StationaryReducer` (``sum/sumsq/sum3/
    sum4/max_avg_j``, ``nonfinite_j``) for the heavy-tail and rare-event flags. A run with a non-finite P at
    some step is left out (counted in ``nonfinite_j``).

    ``shift``: per column a packed vector c subtracted before the sums (Σ(x − c), Σ(x − c)(x − c)ᵀ; the
    trace sums about tr c): the same for every chunk, near the mean, so the covariance keeps its digits when
    the runs agree to ~1e-5 relative (scenario 2 with an invertible C is exact per run)."""

    means_only = True  # only means of P: a variance-reduced estimator may serve them (Estimator.for_means)

    def __init__(self, steps: list[int], shift: dict | None = None):
        self.steps = list(steps)
        self.shift = {int(k): np.asarray(v, dtype=float) for k, v in (shift or {}).items()}
        self._want = (self.steps, frozenset(self.steps))

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        want = self.__dict__.get("_want")
        if want is None or want[0] is not self.steps:  # a set, not a scan of the steps list per call
            want = self._want = (self.steps, frozenset(self.steps))
        if k not in want[1]:
            return
        n, runs = P.shape[0], P.shape[-1]
        acc = stats.setdefault("_acc", {})
        a = acc.get(j)
        if a is None:
            a = acc[j] = {"x": np.zeros((n * (n + 1) // 2, runs)), "bad": np.zeros(runs, dtype=bool), "steps": 0,
                          "n": n}
        i, jj = triu(n)
        with np.errstate(over="ignore", invalid="ignore"):
            x = 0.5 * (P[i, jj] + P[jj, i])  # sym(P), packed
            finite = np.isfinite(x).all(axis=0)
            x = np.where(finite[None, :], x, 0.0)
            a["x"] += x if w is None else x * w[None, :]
        a["bad"] |= ~finite
        a["steps"] += 1

    def finish(self, stats: dict) -> None:
        for j, a in stats.pop("_acc", {}).items():
            n = a["n"]
            ok = ~a["bad"]
            x = a["x"] / max(a["steps"], 1)
            c = self.shift.get(j)
            d = x - (c[:, None] if c is not None else 0.0)
            d = np.where(ok[None, :], d, 0.0)
            diag = np.array([p == q for p, q in zip(*triu(n))])
            tr = np.where(ok, x[diag].sum(axis=0), 0.0)
            dt = np.where(ok, tr - (float(c[diag].sum()) if c is not None else 0.0), 0.0)
            with np.errstate(over="ignore", invalid="ignore"):
                stats[f"sum_T_{j}"] = stats.get(f"sum_T_{j}", 0.0) + d.sum(axis=1)
                stats[f"cross_T_{j}"] = stats.get(f"cross_T_{j}", 0.0) + d @ d.T
                for key, val in (("sum", dt.sum()), ("sumsq", (dt * dt).sum()), ("sum3", (dt**3).sum()),
                                 ("sum4", (dt**4).sum())):
                    stats[f"{key}_avg_{j}"] = stats.get(f"{key}_avg_{j}", 0.0) + val
            stats[f"max_avg_{j}"] = max(stats.get(f"max_avg_{j}", 0.0), float(tr.max()) if tr.size else 0.0)
            stats[f"nonfinite_{j}"] = stats.get(f"nonfinite_{j}", 0) + int((~ok).sum())
            stats[f"max_dim_{j}"] = np.asarray(n)  # max_: merged by maximum over chunks (montecarlo.add_stats)


def packed_mean(stats: dict, j: int, shift: dict | None = None) -> np.ndarray:
    """The packed mean of column j over its finite runs (the shift added back)."""
    m = max(int(stats["n"]) - int(stats[f"nonfinite_{j}"]), 1)
    c = (shift or {}).get(j)
    return stats[f"sum_T_{j}"] / m + (0.0 if c is None else np.asarray(c, dtype=float))


def norm_of_mean(stats: dict, j: int, shift: dict | None = None) -> dict:
    """‖M̂‖₂ of column j with its delta-method s.e. (module docstring): keys ``value``, ``stderr`` (NaN when
    the eigen-gap rule fails), ``gap`` (λ₁ − λ₂), ``gap_noise`` (max_i s_i/(λ₁ − λ_i)), ``eigen_gap`` (flag), ``mean`` (n × n)."""
    n = int(stats[f"max_dim_{j}"])
    m = max(int(stats["n"]) - int(stats[f"nonfinite_{j}"]), 1)
    dbar = stats[f"sum_T_{j}"] / m
    M = unpack(packed_mean(stats, j, shift), n)
    lam, V = np.linalg.eigh(M)
    u = V[:, -1]
    i, jj = triu(n)
    g = np.where(i == jj, 1.0, 2.0) * u[i] * u[jj]
    S = (stats[f"cross_T_{j}"] / m - np.outer(dbar, dbar)) * m / max(m - 1, 1)
    S = 0.5 * (S + S.T)
    var_run = max(float(g @ S @ g), 0.0)
    if var_run <= ROUNDOFF_VARIANCE * lam[-1] ** 2:  # the runs agree to rounding (stats.mean_se's rule): s.e. 0, not noise
        var_run = 0.0
    var = var_run / m
    # per lower eigenvalue λ_i: the noise of the 2 × 2 block of M̂ − E M̂ on (u, u_i), s_i² = Var(a − b) + 4 Var(c)
    # with a = uᵀΔu, b = u_iᵀΔu_i, c = uᵀΔu_i (its eigenvalues split by √((gap + a − b)² + 4c²))
    worst, gap = 0.0, (float(lam[-1] - lam[-2]) if n > 1 else np.inf)
    for k in range(n - 1):
        v = V[:, k]
        gb = np.where(i == jj, 1.0, 2.0) * v[i] * v[jj]
        gc = np.where(i == jj, u[i] * v[i], u[i] * v[jj] + u[jj] * v[i])
        s_k = np.sqrt(max(float((g - gb) @ S @ (g - gb)) + 4.0 * float(gc @ S @ gc), 0.0) / m)
        worst = max(worst, s_k / max(float(lam[-1] - lam[k]), np.finfo(float).tiny))
    degenerate = bool(EIGEN_GAP_SE * worst > 1.0)
    return dict(value=float(lam[-1]), stderr=np.nan if degenerate else float(np.sqrt(var)), gap=gap,
                gap_noise=worst, eigen_gap=degenerate, mean=M)

