"""Critical arrival rate of a Kalman filter with intermittent observations (issue 16).

System x_{k+1} = A x_k + w_k, y_k = C x_k + v_k, measurement y_k received with γ_k ∈ {0, 1};
P_k = P_{k|k−1} (the prediction covariance, the quantity of Sinopoli et al. 2004):

    P_{k+1} = A P_k Aᵀ + Q − γ_k A P_k Cᵀ (C P_k Cᵀ + R)⁻¹ C P_k Aᵀ.

**i.i.d. (Bernoulli) arrivals**, P(γ_k = 1) = λ. Sinopoli et al. 2004 (IEEE TAC 49(9)):

* Thm 2: under (A, Q^{1/2}) controllable and (A, C) detectable there is λ_c ∈ [0, 1) with
  E[P_k] bounded for every P0 iff λ > λ_c;
* Thm 3 (lower bound): λ_min = 1 − 1/ρ(A)² ≤ λ_c, and for λ > λ_min, lim E[P_k] ≥ S̄ with
  S̄ = (1 − λ) A S̄ Aᵀ + Q (:func:`s_bar`, a discrete Lyapunov equation);
* Thm 4 (upper bound): λ_c ≤ λ_max = inf{λ : ∃ X > 0, X > g_λ(X)}, and for λ > λ_max,
  lim E[P_k] ≤ V̄ = g_λ(V̄), the fixed point of the modified Riccati map
  g_λ(X) = A X Aᵀ + Q − λ A X Cᵀ (C X Cᵀ + R)⁻¹ C X Aᵀ (:func:`v_bar`);
* Thm 5: X > g_λ(X) for some X > 0 ⇔ ∃ Z and 0 < Y ≤ I with Ψ_λ(Y, Z) > 0, where
      Ψ_λ(Y, Z) = [[ Y,               √λ (Y A + Z C),  √(1−λ) Y A ],
                   [ √λ (Aᵀ Y + Cᵀ Zᵀ),  Y,             0          ],
                   [ √(1−λ) Aᵀ Y,        0,             Y          ]]
  (an LMI for fixed λ, feasible for all λ above λ_max: :func:`lambda_max` bisects on it).

λ_c is a single number only where it is proven (:func:`exact_case`): A Schur stable (λ_c = 0);
ρ(A) = 1 with (A, C) detectable (λ_c = 0, every λ > 0 works); the scalar case and C invertible
(Sinopoli et al. 2004); C restricted to the observable subspace invertible (Plarre & Bullo 2009,
"On Kalman filtering for detectable systems with intermittent observations", IEEE TAC 54(2));
a single unstable eigenvalue (Mo & Sinopoli 2008; argument in experiments/critical/README.md); every
non-degenerate system — each group of eigenvalues of equal modulus ≥ 1 one-step observable (Mo & Sinopoli 2012,
IEEE TAC 57(3): λ_c = 1 − 1/ρ(A)², :func:`nondegeneracy`); degenerate second-order systems whose eigenvalue ratio
is a primitive p-th root of unity (derived here: λ_c = 1 − ρ^{−2p/(p−1)}, :func:`degenerate_second_order`, checked
against :func:`enumerate_expected_trace`). Everywhere else a numerical certificate: a proven lower end (λ_min, or the
λ_c of a decoupled degenerate 2×2 sub-system, :func:`subsystem_lower_bound`) and an upper end certified by the
L-step averaged Riccati map (:func:`lambda_c_certificate`), tighter than λ_max.

**Tail** (Mo & Sinopoli 2012): Pr[tr P_k > M] ~ M^φ, φ = log s/(2 log ρ(A)) (:func:`tail_exponent`), used by the
``tail`` metric (:mod:`netkf_cli.metrics.tail`). **Monte Carlo reliability** of a mean of P (issue 19):
:func:`mean_reliability`.

**Gilbert–Elliott (Markov) arrivals** with failure rate p = P(γ_{k+1} = 0 | γ_k = 1) and
recovery rate q = P(γ_{k+1} = 1 | γ_k = 0) (``channels.gilbert_elliott``: p = p_gb, q = p_bg):

* necessary for any system: (1 − q) ρ(A)² < 1 (:func:`ge_q_necessary`; the analogue of Thm 3:
  a loss burst of length j has probability ∝ (1 − q)^j and P grows like ρ(A)^{2j} during it);
* exact where one received packet bounds P (scalar, C of full column rank, single unstable
  eigenvalue, ρ(A) ≤ 1) and for every non-degenerate system (Mo & Sinopoli 2012; derivation in
  experiments/critical/README.md): bounded iff q > 1 − 1/ρ(A)², whatever p (:func:`ge_scalar_bounds`
  gives the stationary E[P] bracket of the scalar case in closed form);
* derived for degenerate 2×2 systems: bounded iff ρ^{2p}·μ_p(p_fail, q) < 1, μ_p the decay of windows whose
  arrivals share one residue class (:func:`ge_degenerate_critical_q`);
* sufficient for any system: mean-square stability of a constant-gain predictor under the
  Markov switching, an LMI in (P₀, P₁, W) (:func:`ge_lmi_margin`), the Markov analogue of
  Sinopoli's Thm 5(b); at p + q = 1 (i.i.d.) its threshold equals λ_max.

**Delay with a receive buffer** (Shi, Xie & Murray 2009): with i.i.d. delays a packet is used
iff its delay is at most D_max (D under ``delay_le_D``, D − 1 under ``delay_lt_D``); the buffered
estimator's P_k lies between the KF fed with every eventually-used packet and h^{D_max} of it,
so E[P_k] is bounded iff it is for i.i.d. arrivals at λ_eff = F(D_max) (:func:`delay_effective_rate`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from netkf_cli.linalg import kalman, sdp
from netkf_cli.linalg.riccati import is_detectable  # noqa: F401 (re-exported: the PBH test lives with the Riccati solution it decides)
from netkf_cli.analysis.delay_bounds import max_kept_delay
from netkf_cli.core.errors import NetkfError
from netkf_cli.core.tolerances import CRITICAL_BISECTION_TOL, CRITICAL_MARGIN_TOL, CRITICAL_RANK_TOL, CRITICAL_RHO_TOL


class CriticalRateError(NetkfError):
    """An SDP solve failed (solver status other than optimal)."""


# =============================================================================================
# Small helpers
# =============================================================================================


def spectral_radius(A: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(np.atleast_2d(A))))) if np.size(A) else 0.0


def _sym(X: np.ndarray) -> np.ndarray:
    return 0.5 * (X + X.T)


def _t(X: np.ndarray) -> np.ndarray:
    """Xᵀ over the last two axes (a stack of matrices stays a stack)."""
    return np.swapaxes(X, -1, -2)


def lambda_min(A: np.ndarray) -> float:
    """λ_min = 1 − 1/ρ(A)² (Sinopoli et al. 2004, Thm 3), 0 when A is Schur stable."""
    rho = spectral_radius(A)
    return max(0.0, 1.0 - (1.0 / rho) ** 2) if rho > 0 else 0.0  # (1/ρ)² cannot overflow (ρ up to 1e308)


def observable_basis(A: np.ndarray, C: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Orthonormal basis (columns) of the observable subspace = row space of [C; CA; …; CAⁿ⁻¹]."""
    n = A.shape[0]
    O = np.vstack([C @ np.linalg.matrix_power(A, i) for i in range(n)])
    _, s, Vt = np.linalg.svd(O)
    r = int((s > tol * max(1.0, s[0] if s.size else 1.0)).sum())
    return Vt[:r].T


def unstable_eigenvalues(A: np.ndarray) -> np.ndarray:
    """Eigenvalues with |σ| ≥ 1 (within :data:`CRITICAL_RHO_TOL`), with algebraic multiplicity."""
    ev = np.linalg.eigvals(A)
    return ev[np.abs(ev) >= 1 - CRITICAL_RHO_TOL]


# =============================================================================================
# Which case is proven
# =============================================================================================


@dataclass(frozen=True)
class ExactCase:
    """λ_c known exactly: ``value`` (None = E[P] unbounded for every λ ≤ 1), the condition and its source."""

    key: str
    value: float | None
    condition: str
    source: str
    basis: str = "theorem"
    """``theorem`` (proven in the cited literature) or ``derived`` (derived in experiments/critical/README.md and
    checked by exact enumeration in tests/critical/)."""


def exact_case(A: np.ndarray, C: np.ndarray) -> ExactCase | None:
    """The first proven case that applies to (A, C), or None (then only [λ_min, λ_max] is known)."""
    A, C = np.atleast_2d(A), np.atleast_2d(C)
    n = A.shape[0]
    rho = spectral_radius(A)
    if not is_detectable(A, C):
        return ExactCase("undetectable", None, "(A, C) is not detectable: an unstable mode is never measured",
                         "E[P_k] diverges for every arrival rate, λ = 1 included (if Q excites that mode)")
    if rho < 1 - CRITICAL_RHO_TOL:
        return ExactCase("stable", 0.0, f"A is Schur stable (ρ(A) = {rho:.6g} < 1)",
                         "open-loop prediction keeps E[P_k] ≤ Σ Aⁱ Q Aᵀⁱ bounded for every λ ≥ 0")
    if rho <= 1 + CRITICAL_RHO_TOL:
        return ExactCase("marginal", 0.0, "ρ(A) = 1 and (A, C) detectable",
                         "every λ > 0 works: n consecutive arrivals occur at geometric times and bound P, "
                         "while ‖Aᵏ‖ grows only polynomially (experiments/critical/README.md)")
    lmin = lambda_min(A)
    if n == 1:
        return ExactCase("scalar", lmin, "scalar system (n = 1, c ≠ 0)", "Sinopoli et al. 2004, special case C invertible (here c ≠ 0): λ_c = 1 − 1/a²")
    V = observable_basis(A, C)
    if np.linalg.matrix_rank(C @ V) == V.shape[1]:
        if V.shape[1] == n:
            return ExactCase("c_invertible", lmin, "C has full column rank (one packet determines the state)",
                             "Sinopoli et al. 2004, special case C invertible; Plarre & Bullo 2009")
        return ExactCase("c_invertible_observable", lmin, "C restricted to the observable subspace is invertible",
                         "Plarre & Bullo 2009, 'On Kalman filtering for detectable systems with intermittent observations'")
    if len(unstable_eigenvalues(A)) == 1:
        return ExactCase("single_unstable", lmin, "A has a single unstable eigenvalue (algebraic multiplicity 1)",
                         "Mo & Sinopoli 2008; the stable modes act as bounded extra noise (experiments/critical/README.md)")
    nd = nondegeneracy(A, C)
    if nd.non_degenerate:
        return ExactCase("non_degenerate", lmin,
                         "non-degenerate: every quasi-equiblock (eigenvalues of equal modulus ≥ 1) is one-step observable",
                         "Mo & Sinopoli 2012, IEEE TAC 57(3), 'Kalman filtering with intermittent observations: tail "
                         "distribution and critical value' (critical value of non-degenerate systems: λ_c = 1 − 1/ρ(A)²)")
    d2 = degenerate_second_order(A, C)
    if d2 is not None:
        return d2
    return None


# =============================================================================================
# Sinopoli's bounds on lim E[P_k]
# =============================================================================================


def s_bar(A: np.ndarray, Q: np.ndarray, lam: float) -> np.ndarray:
    """S̄ = (1 − λ) A S̄ Aᵀ + Q (Sinopoli et al. 2004, Thm 3), a discrete Lyapunov equation.

    Exists iff (1 − λ) ρ(A)² < 1, i.e. λ > λ_min; otherwise a matrix of ``inf``.
    """
    A, Q = np.atleast_2d(A), np.atleast_2d(Q)
    if (1 - lam) * spectral_radius(A) ** 2 >= 1:
        return np.full(A.shape, np.inf)
    return _sym(scipy.linalg.solve_discrete_lyapunov(math.sqrt(1 - lam) * A, Q))


def modified_riccati(X: np.ndarray, A, C, Q, R, lam: float) -> np.ndarray:
    """g_λ(X) = A X Aᵀ + Q − λ A X Cᵀ (C X Cᵀ + R)⁻¹ C X Aᵀ, the modified Riccati map (Sinopoli et al. 2004, Thm 4)."""
    # = (1 − λ) h(X) + λ h(g̃(X)): the Kalman core's predict and update (no gain written here)
    A, C, Q, R = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, C, Q, R))
    X = np.asarray(X, dtype=float)
    hX = kalman.one(kalman.predict, X, A, Q)
    hg = kalman.one(kalman.predict, kalman.one(kalman.update, X, C, R), A, Q)
    return _sym((1 - lam) * hX + lam * hg)


def modified_riccati_batch(X: np.ndarray, A, C, Q, R, lams: np.ndarray) -> np.ndarray:
    """:func:`modified_riccati` of X (n, n, r) at the rates ``lams`` (r,), one per column: the same operations
    elementwise on the Kalman core's run axis, so column i is bit for bit g_{λ_i}(X[:, :, i])."""
    r = X.shape[-1]
    H = kalman.predict(np.concatenate([X, kalman.update(X, C, R)], axis=2), A, Q)  # h(X) and h(g̃(X)) in one call
    Y = (1 - lams) * H[:, :, :r] + lams * H[:, :, r:]
    return 0.5 * (Y + Y.swapaxes(0, 1))


def _mare_derivative_solve(V, A, C, R, lam, rhs):
    """Solve H − (1−λ) A H Aᵀ − λ A_K H A_Kᵀ = rhs, A_K = A − K C with the gain of g_λ at V."""
    n = A.shape[0]
    K = A @ V @ C.T @ np.linalg.inv(C @ V @ C.T + R) if C.size else np.zeros((n, 0))
    AK = A - K @ C
    L = np.eye(n * n) - (1 - lam) * np.kron(A, A) - lam * np.kron(AK, AK)
    return _sym(np.linalg.solve(L, rhs.reshape(-1)).reshape(n, n))


def v_bar(A, C, Q, R, lam: float, *, rtol: float = 1e-12, max_iter: int = 200_000) -> np.ndarray:
    """V̄ = g_λ(V̄), the fixed point of the modified Riccati map (Sinopoli et al. 2004, Thm 4).

    Iterates V_{t+1} = g_λ(V_t) from V_0 = 0 (monotone increasing: g_λ is monotone, Sinopoli et al.
    2004, Lemma 1(c), as quoted in Shi, Xie & Murray 2009, Lemma A.1) until the
    step is below 1e-8 relative, then polishes with Newton steps on g_λ(V) − V (the derivative
    of g_λ is H ↦ (1−λ) A H Aᵀ + λ A_K H A_Kᵀ). Returns ``inf`` when the iteration diverges
    (λ ≤ λ_max: no fixed point) or does not settle within ``max_iter`` steps.
    """
    return v_bars(A, C, Q, R, [lam], rtol=rtol, max_iter=max_iter)[0]


def v_bars(A, C, Q, R, lams, *, rtol: float = 1e-12, max_iter: int = 200_000) -> list[np.ndarray]:
    """:func:`v_bar` at each rate of ``lams``: the fixed-point iterations of all rates run together on the Kalman
    core's run axis (:func:`modified_riccati_batch`, column i bit for bit the iteration at λ_i, each stopped by its
    own test), then each is polished on its own (:func:`_v_bar_polish`)."""
    A, C, Q, R = (np.atleast_2d(np.asarray(x, float)) for x in (A, C, Q, R))
    n = A.shape[0]
    lams = np.asarray(lams, dtype=float).reshape(-1)
    inf = np.full((n, n), np.inf)
    scale = 1.0 + float(np.trace(Q))
    V = np.zeros((n, n, lams.size))
    live = np.arange(lams.size)  # columns still iterating
    done: dict[int, np.ndarray | None] = {}  # column → its iterate at the stopping test (None: diverged)
    for _ in range(max_iter):
        if not live.size:
            break
        Vl = V[:, :, live]
        Vn = modified_riccati_batch(Vl, A, C, Q, R, lams[live])
        with np.errstate(over="ignore", invalid="ignore"):
            top = np.abs(Vn).max(axis=(0, 1))  # nan or inf where an entry is not finite
            bad = ~np.isfinite(top) | (np.trace(Vn, axis1=0, axis2=1) > 1e14 * scale)
            stop = np.abs(Vn - Vl).max(axis=(0, 1)) <= 1e-8 * np.maximum(1.0, top)
        V[:, :, live] = Vn
        end = bad | stop
        if end.any():
            for c, b in zip(live[end], bad[end]):
                done[int(c)] = None if b else V[:, :, c].copy()
            live = live[~end]
    return [inf if done.get(i) is None else _v_bar_polish(done[i], A, C, Q, R, float(lams[i]), rtol)
            for i in range(lams.size)]


def _v_bar_polish(V: np.ndarray, A, C, Q, R, lam: float, rtol: float) -> np.ndarray:
    """Newton steps on g_λ(V) − V from the fixed-point iterate V (:func:`v_bar`); ``inf`` if they fail."""
    n = A.shape[0]
    inf = np.full((n, n), np.inf)
    for _ in range(30):
        res = modified_riccati(V, A, C, Q, R, lam) - V
        if np.abs(res).max() <= rtol * max(1.0, np.abs(V).max()):
            return V
        try:
            Vn = V + _mare_derivative_solve(V, A, C, R, lam, res)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(Vn)) or np.min(np.linalg.eigvalsh(Vn)) < -1e-9 * max(1.0, np.abs(V).max()):
            break
        V = Vn
    res = modified_riccati(V, A, C, Q, R, lam) - V
    return V if np.abs(res).max() <= 1e-8 * max(1.0, np.abs(V).max()) else inf


# =============================================================================================
# λ_max: bisection on the LMI of Sinopoli's Thm 5
# =============================================================================================


class _SinopoliLMI:
    """max t s.t. Ψ_λ(Y, Z) ⪰ t I, t I ⪯ Y ⪯ I (:func:`netkf_cli.linalg.sdp.max_margin`); feasible ⇔ t* > 0."""

    def __init__(self, A: np.ndarray, C: np.ndarray, solver: str = "CLARABEL"):
        _check_solver(solver)
        self.A, self.C, self.solver = A, C, solver
        n, m = A.shape[0], C.shape[0]
        self.vars = [sdp.Var((n, n), symmetric=True), sdp.Var((n, m))]

    def psi(self, Y, Z, lam):
        """Ψ_λ(Y, Z) (Thm 5); over the last two axes, so stacked (Y, Z) give stacked Ψ."""
        A, C = self.A, self.C
        B = Y @ A + Z @ C
        O = np.zeros_like(Y)
        a, b = math.sqrt(lam), math.sqrt(max(0.0, 1 - lam))
        return np.block([[Y, a * B, b * Y @ A], [a * _t(B), Y, O], [b * _t(Y @ A), O, Y]])

    def margin(self, lam: float) -> tuple[float, str, bool]:
        """(t*, solver status, certified): certified = the returned (Y, Z) satisfies the strict LMI."""
        n = self.A.shape[0]
        try:
            sol = sdp.max_margin(self.vars, lambda v: [(self.psi(v[0], v[1], lam), True), (v[0], True),
                                                       (np.eye(n) - v[0], False)], stacked=True)
        except sdp.SDPError as exc:  # pragma: no cover - solver crash
            raise CriticalRateError(f"LMI solve failed at λ = {lam:.6g}: {exc}") from None
        st = sol.status
        if st not in ("optimal", "optimal_inaccurate"):
            raise CriticalRateError(f"LMI solve at λ = {lam:.6g} ended with status {st!r}")
        cert = False
        if sol.values is not None:
            Y, Z = _sym(sol.values[0]), sol.values[1]
            e1 = np.linalg.eigvalsh(_sym(self.psi(Y, Z, lam))).min()
            e2 = np.linalg.eigvalsh(Y).min()
            cert = bool(e1 > CRITICAL_MARGIN_TOL and e2 > CRITICAL_MARGIN_TOL)
        return sol.t, st, cert


def _check_solver(solver: str) -> None:
    """The critical-rate LMIs are solved by Clarabel (:mod:`netkf_cli.linalg.sdp`)."""
    if solver != "CLARABEL":
        raise CriticalRateError(f"the critical-rate LMIs are solved with Clarabel; solver {solver!r} is not available")


@dataclass(frozen=True)
class LambdaMax:
    """Bracket lo < λ_max ≤ hi from bisection; ``hi`` carries a checked LMI certificate.

    ``hi = inf`` if the LMI is infeasible even at λ = 1 ((A, C) not detectable).
    """

    lo: float
    hi: float
    tol: float
    solves: int
    solver: str
    statuses: tuple[str, ...]

    @property
    def value(self) -> float:
        """The certified upper end (conservative: E[P] is proven bounded above it)."""
        return self.hi


def lambda_max(A, C, *, tol: float = CRITICAL_BISECTION_TOL, lo: float = 0.0, solver: str = "CLARABEL") -> LambdaMax:
    """Sinopoli's upper bound λ_max on λ_c: bisection on the LMI Ψ_λ(Y, Z) > 0 (Thm 5).

    Feasibility is monotone in λ (g_λ decreases in λ), so bisection over [lo, 1] finds the
    threshold; "feasible" means the solver's (Y, Z) passes a numerical eigenvalue check
    (:data:`CRITICAL_MARGIN_TOL`), so ``hi`` is certified; "infeasible" trusts the solver's optimum
    t* ≤ 0 (status checked). ``lo`` defaults to 0 so that λ_min ≤ λ_max is a check, not an input.
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    lmi = _SinopoliLMI(A, C, solver)
    statuses: set[str] = set()
    solves = 0

    def feasible(lam):
        nonlocal solves
        solves += 1
        _, st, cert = lmi.margin(lam)
        statuses.add(st)
        return cert

    if not feasible(1.0):
        return LambdaMax(1.0, math.inf, tol, solves, solver, tuple(sorted(statuses)))
    if lo <= 0.0 and feasible(0.0):
        return LambdaMax(0.0, 0.0, tol, solves, solver, tuple(sorted(statuses)))
    a, b = max(lo, 0.0), 1.0
    while b - a > tol:
        mid = 0.5 * (a + b)
        if feasible(mid):
            b = mid
        else:
            a = mid
    return LambdaMax(a, b, tol, solves, solver, tuple(sorted(statuses)))


def lambda_max_by_iteration(A, C, Q, R, *, tol: float = 1e-3, max_iter: int = 20_000) -> float:
    """Brute-force cross-check of λ_max: the smallest λ (bisection) where g_λ iterated from 0 stays bounded.

    Slow near the threshold (the iteration needs ~1/gap steps); for tests only.
    """
    A, C, Q, R = (np.atleast_2d(np.asarray(x, float)) for x in (A, C, Q, R))
    a, b = 0.0, 1.0
    while b - a > tol:
        mid = 0.5 * (a + b)
        ok = np.all(np.isfinite(v_bar(A, C, Q, R, mid, max_iter=max_iter)))
        a, b = (a, mid) if ok else (mid, b)
    return b


# =============================================================================================
# Gilbert–Elliott (Markov) loss
# =============================================================================================


def ge_q_necessary(A) -> float:
    """q must exceed 1 − 1/ρ(A)² for bounded E[P_k] under Gilbert–Elliott loss (any p > 0).

    A loss burst lasts ≥ j steps with probability (1 − q)^{j−1}; during it P ≥ Σ_{i<j} Aⁱ Q Aᵀⁱ
    grows like ρ(A)^{2j} (Q exciting the unstable mode), so E[P] ≥ c Σ_j ((1−q) ρ²)^j = ∞ unless
    (1 − q) ρ(A)² < 1 — the Markov analogue of Sinopoli et al. 2004, Thm 3.
    """
    return lambda_min(A)


def ge_scalar_bounds(a: float, c: float, q_noise: float, r: float, p: float, q: float) -> tuple[float, float]:
    """Stationary E[P_{k+1|k}] of the scalar KF under Gilbert–Elliott loss: a closed-form bracket.

    With L the number of losses just before the current step (stationary law of the Gilbert
    chain: P(L = 0) = π₁ = q/(p+q), P(L = l) = π₁ p (1−q)^{l−1}, l ≥ 1), P_{k+1|k} = h^{L+1}(X)
    where X ∈ [0, r/c²] is the last filtered covariance and h(x) = a² x + Q. Hence
        E[h^{L+1}(0)] ≤ E[P] ≤ E[h^{L+1}(r/c²)],   h^{j}(x) = a^{2j} x + Q Σ_{i<j} a^{2i},
    both finite iff (1 − q) a² < 1 (then the exact stability condition is q > 1 − 1/a², for
    every failure rate p ∈ (0, 1]). Returns (inf, inf) otherwise.
    """
    a2 = a * a
    if (1 - q) * a2 >= 1:
        return math.inf, math.inf
    pi1 = q / (p + q)

    def mean_h(x):
        # E[a^{2(L+1)}] and E[Σ_{i≤L} a^{2i}] under the law of L
        r1 = (1 - q) * a2
        e_pow = pi1 * a2 + pi1 * p * a2 * a2 / (1 - r1)           # Σ_l P(L=l) a^{2(l+1)}
        if abs(a2 - 1) < 1e-12:
            e_sum = pi1 * 1 + pi1 * p * sum((l + 1) * (1 - q) ** (l - 1) for l in range(1, 10_000))
        else:
            e_sum = (e_pow - 1) / (a2 - 1)                          # E[(a^{2(L+1)} − 1)/(a² − 1)]
        return e_pow * x + q_noise * e_sum

    return mean_h(0.0), mean_h(r / (c * c))


class _MarkovLMI:
    """Mean-square stability of e⁺ = F_γ e under a Gilbert chain, with F₀ = A, F₁ = A − K C.

    Costa, Fragoso & Marques (2005), Thm 3.9: MSS ⇔ ∃ P_i ≻ 0: P_i ≻ F_iᵀ (Σ_j T_ij P_j) F_i.
    With E_i = Σ_j T_ij P_j and W = E₁ K the two conditions are LMIs (Schur complement):
        [[P₀, Aᵀ E₀], [E₀ A, E₀]] ≻ 0,   [[P₁, Aᵀ E₁ − Cᵀ Wᵀ], [E₁ A − W C, E₁]] ≻ 0.
    Feasible ⇒ the predictor x̂⁺ = A x̂ + γ K (y − C x̂) has bounded error covariance, which
    bounds E[P_k] of the (optimal) Kalman filter: a sufficient condition for stability.
    Solved as max t s.t. both ⪰ t I, P_i ⪰ t I, P_i ⪯ I (:func:`netkf_cli.linalg.sdp.max_margin`).
    """

    def __init__(self, A: np.ndarray, C: np.ndarray, solver: str = "CLARABEL"):
        _check_solver(solver)
        self.A, self.C, self.solver = A, C, solver
        n, m = A.shape[0], C.shape[0]
        self.vars = [sdp.Var((n, n), symmetric=True), sdp.Var((n, n), symmetric=True), sdp.Var((n, m))]

    def blocks(self, P0, P1, W, T) -> tuple[np.ndarray, np.ndarray]:
        """The two Schur-complement matrices M₀, M₁ at (P₀, P₁, W) and transition matrix T (over the last two axes:
        stacked values give stacked matrices)."""
        A, C = self.A, self.C
        E0, E1 = T[0, 0] * P0 + T[0, 1] * P1, T[1, 0] * P0 + T[1, 1] * P1
        M0 = np.block([[P0, A.T @ E0], [E0 @ A, E0]])
        M1 = np.block([[P1, A.T @ E1 - C.T @ _t(W)], [E1 @ A - W @ C, E1]])
        return M0, M1

    def solve(self, p: float, q: float) -> sdp.Solution:
        """The margin problem at failure rate p and recovery rate q."""
        T = np.array([[1 - q, q], [p, 1 - p]])
        I = np.eye(self.A.shape[0])

        def lmis(v):
            M0, M1 = self.blocks(v[0], v[1], v[2], T)
            return [(M0, True), (M1, True), (v[0], True), (v[1], True), (I - v[0], False), (I - v[1], False)]

        try:
            return sdp.max_margin(self.vars, lmis, stacked=True)
        except sdp.SDPError as exc:  # pragma: no cover
            raise CriticalRateError(f"Markov LMI solve failed at p = {p:.6g}, q = {q:.6g}: {exc}") from None

    def feasible(self, p: float, q: float) -> tuple[bool, str]:
        """(certified, status): certified = the returned (P₀, P₁, W) satisfies the strict LMIs."""
        T = np.array([[1 - q, q], [p, 1 - p]])
        sol = self.solve(p, q)
        st = sol.status
        if st not in ("optimal", "optimal_inaccurate"):
            raise CriticalRateError(f"Markov LMI at p = {p:.6g}, q = {q:.6g} ended with status {st!r}")
        if sol.values is None:
            return False, st
        P0, P1, W = _sym(sol.values[0]), _sym(sol.values[1]), sol.values[2]
        M0, M1 = self.blocks(P0, P1, W, T)
        mins = [np.linalg.eigvalsh(_sym(M)).min() for M in (M0, M1, P0, P1)]
        return bool(min(mins) > CRITICAL_MARGIN_TOL), st


@dataclass(frozen=True)
class GECurvePoint:
    """For failure rate p: the critical recovery rate q_c(p) bracket [necessary, sufficient]."""

    p: float
    q_necessary: float
    q_sufficient: float        # smallest q (bisection, ± tol) with a certified Markov LMI; inf if none ≤ 1
    q_exact: float | None      # where proven (see exact_case_ge)
    q_bernoulli_same_loss: float  # q at which i.i.d. loss with the same stationary rate reaches λ_c bound


def exact_case_ge(A, C) -> ExactCase | None:
    """Cases where q > 1 − 1/ρ(A)² is necessary and sufficient: one received packet bounds P, or the system is
    non-degenerate (Mo & Sinopoli 2012; bounded by the time since the N-th most recent arrival).

    The i.i.d. cases carry over when their proof only needs "one arrival bounds the unstable
    part": scalar, C of full column rank, a single unstable eigenvalue, A stable. Not carried over:
    ρ(A) = 1 (its proof needs n consecutive arrivals, which never happen when p = 1) and C
    invertible on the observable subspace (not proven here for Markov loss): the LMI decides there.
    """
    A, C = np.atleast_2d(A), np.atleast_2d(C)
    ec = exact_case(A, C)
    if ec is None or ec.key == "marginal" or ec.key.startswith("degenerate_"):
        return None
    if ec.key == "c_invertible_observable" and not nondegeneracy(A, C).non_degenerate:
        return None
    if ec.key in ("non_degenerate", "c_invertible_observable"):
        return ExactCase(ec.key, ec.value, ec.condition,
                         "Mo & Sinopoli 2012 (IEEE TAC 57(3)): critical value of non-degenerate systems over the "
                         "Gilbert–Elliott channel; netkf's derivation (P_k bounded through the time since the N-th most "
                         "recent arrival, fewer than N arrivals in L steps has probability ≤ poly(L)·(1 − q)^L, so "
                         "E[P] < ∞ iff (1 − q)ρ(A)² < 1 whatever p), its assumptions and the exact-recursion check: "
                         "experiments/critical/README.md")
    return ec


def ge_critical_curve(A, C, ps, *, tol: float = 1e-4, solver: str = "CLARABEL", lam_c_upper: float | None = None,
                      lam_c_lower: float | None = None) -> list[GECurvePoint]:
    """Critical recovery rate against the failure rate (Gilbert–Elliott): necessary, sufficient, exact.

    For each p the sufficient q is found by bisection on q ∈ [q_necessary, 1] of the Markov LMI
    (:class:`_MarkovLMI`), assuming feasibility is monotone in q (more recovery never hurts; the
    returned q carries a certificate). ``q_bernoulli_same_loss`` is the recovery rate at which the
    stationary arrival rate q/(p+q) equals ``lam_c_upper`` (or the exact λ_c): the i.i.d. answer at
    the same average loss, for comparison.
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    qn = ge_q_necessary(A)
    ec = exact_case_ge(A, C)
    e_iid = exact_case(A, C)
    deg = e_iid is not None and e_iid.key.startswith("degenerate_2x2_p")
    lmi = _MarkovLMI(A, C, solver)
    lam_ref = lam_c_upper if lam_c_upper is not None else (ec.value if ec and ec.value is not None else lambda_min(A))
    out = []
    for p in ps:
        p = float(p)
        if ec is not None and ec.key == "stable":
            qs = 0.0
        elif not lmi.feasible(p, 1.0)[0]:
            qs = math.inf
        else:
            a, b = qn, 1.0  # q ≤ q_necessary cannot work; q = 1 is certified just above
            while b - a > tol:
                mid = 0.5 * (a + b)
                if lmi.feasible(p, mid)[0]:
                    b = mid
                else:
                    a = mid
            qs = b
        q_exact = None if ec is None or ec.value is None else ec.value
        if ec is None and deg:
            q_exact = ge_degenerate_critical_q(A, C, p)  # derived; 1.0 = no recovery rate suffices at this p
        # q/(p+q) = λ ⇔ q = λ p / (1 − λ)
        qb = lam_ref * p / (1 - lam_ref) if lam_ref < 1 else math.inf
        out.append(GECurvePoint(p, qn, qs, q_exact, qb))
    return out


# =============================================================================================
# Non-degeneracy (Mo & Sinopoli 2012) and degenerate second-order systems (derived here)
# =============================================================================================


@dataclass(frozen=True)
class ModulusGroup:
    """Eigenvalues of (numerically) equal modulus: a quasi-equiblock of the Jordan form."""

    modulus: float
    eigenvalues: tuple[complex, ...]
    dim: int
    sigma_min: float          # smallest singular value of C V / ‖C‖ (V: orthonormal basis of the invariant subspace)
    one_step_observable: bool


@dataclass(frozen=True)
class NonDegeneracy:
    """Mo & Sinopoli 2012's non-degeneracy test on the modes with |σ| ≥ 1 (stable modes act as bounded noise)."""

    non_degenerate: bool
    groups: tuple[ModulusGroup, ...]
    group_tol: float
    rank_tol: float
    reason: str = ""

    def summary(self) -> str:
        parts = [f"|σ| = {g.modulus:.6g} ×{g.dim}: {'one-step observable' if g.one_step_observable else 'NOT one-step observable'}"
                 f" (σ_min(CV)/‖C‖ = {g.sigma_min:.3g})" for g in self.groups]
        return "; ".join(parts) if parts else "no eigenvalue with |σ| ≥ 1"

    def as_json(self) -> dict:
        return {"non_degenerate": self.non_degenerate, "group_tol": self.group_tol, "rank_tol": self.rank_tol,
                "reason": self.reason,
                "groups": [{"modulus": g.modulus, "dim": g.dim, "eigenvalues": [[z.real, z.imag] for z in g.eigenvalues],
                            "sigma_min_relative": g.sigma_min, "one_step_observable": g.one_step_observable}
                           for g in self.groups]}


def group_tolerance(A: np.ndarray) -> float:
    """Two eigenvalue moduli closer than this are one quasi-equiblock.

    A Jordan block of size k is split by rounding into eigenvalues ~(ε‖A‖)^{1/k} apart, so the tolerance is
    max(1e-6·ρ(A), 10·(n ε)^{1/n}·‖A‖₂): it never splits a numerically defective block of size ≤ n. Grouping too
    much is conservative — a larger group must be one-step observable as a whole, a stronger requirement.
    """
    n = A.shape[0]
    eps = np.finfo(float).eps
    return max(1e-6 * spectral_radius(A), 10.0 * (n * eps) ** (1.0 / n) * float(np.linalg.norm(A, 2)))


def nondegeneracy(A, C, *, rank_tol: float = CRITICAL_RANK_TOL) -> NonDegeneracy:
    """Is (A, C) non-degenerate in the sense of Mo & Sinopoli 2012 (IEEE TAC 57(3), Def. of non-degeneracy)?

    Jordan form grouped by eigenvalue modulus: each group of eigenvalues of equal modulus (a quasi-equiblock) must
    be one-step observable, i.e. C restricted to the group's generalized eigenspace (real invariant subspace,
    computed by an ordered real Schur form, so Jordan blocks and complex pairs are handled without a Jordan
    decomposition) must be injective. Only modes with |σ| ≥ 1 are tested: Schur-stable modes contribute a bounded
    extra measurement noise to the suboptimal estimators of the proof (experiments/critical/README.md).
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    ev = np.linalg.eigvals(A)
    gtol = group_tolerance(A)
    cn = max(float(np.linalg.norm(C, 2)), np.finfo(float).tiny)
    mods = np.abs(ev)
    order = np.argsort(mods)
    groups: list[list[int]] = []
    for i in order:
        if groups and mods[i] - mods[groups[-1][-1]] <= gtol:
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    out = []
    ok_all = True
    reason = ""
    for g in groups:
        lo, hi = float(mods[g].min()), float(mods[g].max())
        if hi < 1 - CRITICAL_RHO_TOL:
            continue
        sel = lambda x, y, lo=lo, hi=hi: lo - gtol / 2 <= math.hypot(x, y) <= hi + gtol / 2  # noqa: E731
        T, Z, sdim = scipy.linalg.schur(A, output="real", sort=sel)
        if sdim != len(g):  # reordering failed (ill-conditioned): cannot decide — say so, never claim
            ok_all = False
            reason = f"ordered Schur form failed for the group |σ| ≈ {lo:.6g} (got {sdim} of {len(g)} eigenvalues)"
            out.append(ModulusGroup(0.5 * (lo + hi), tuple(complex(z) for z in ev[g]), len(g), 0.0, False))
            continue
        V = Z[:, :sdim]
        s = np.linalg.svd(C @ V, compute_uv=False)
        smin = float(s[sdim - 1]) / cn if s.size >= sdim else 0.0
        obs = smin > rank_tol
        ok_all &= obs
        out.append(ModulusGroup(0.5 * (lo + hi), tuple(complex(z) for z in ev[g]), len(g), smin, bool(obs)))
    if not ok_all and not reason:
        reason = "a quasi-equiblock is not one-step observable"
    return NonDegeneracy(bool(ok_all), tuple(out), gtol, rank_tol, reason)


MAX_ROOT_ORDER = 24
"""Ratios of the two eigenvalues tested as primitive p-th roots of unity for p ≤ this (beyond: numerical certificate)."""


def root_of_unity_order(w: complex, *, tol: float = 1e-9, p_max: int = MAX_ROOT_ORDER) -> int | None:
    """The smallest p ≤ p_max with |w^p − 1| ≤ tol·p (w on the unit circle), or None."""
    if abs(abs(w) - 1) > 1e-7:
        return None
    z = complex(1.0)
    for p in range(1, p_max + 1):
        z *= w
        if abs(z - 1) <= tol * p:
            return p
    return None


def degenerate_growth_exponent(p: int) -> float:
    """e(p) with λ_c = 1 − ρ^{−e(p)}: e = 2p/(p − 1) for p ≥ 2, e = 2 for a Jordan block (p = 1)."""
    return 2.0 if p == 1 else 2.0 * p / (p - 1)


def degenerate_second_order(A, C) -> ExactCase | None:
    """λ_c of a degenerate second-order system in closed form (derived: experiments/critical/README.md).

    n = 2, both eigenvalues of modulus ρ > 1, C of rank 1 on R² (else the system is one-step observable), the ratio
    ω = σ₂/σ₁ a primitive p-th root of unity. Two arrivals t < t' separate the modes iff p ∤ (t' − t)
    (det [C A^t; C A^{t'}] ∝ ω^{t'−t} − 1), and A^p = σ₁^p I. A window of L steps in which every arrival falls in one
    residue class mod p (probability ≈ p (1 − λ)^{L(p−1)/p}) leaves one direction unmeasured, growing like ρ^{2L};
    conversely after two separating arrivals P is bounded by c·ρ^{2(k−t)}. Hence E[P_k] is bounded iff
    ρ² (1 − λ)^{(p−1)/p} < 1:

        λ_c = 1 − ρ^{−2p/(p−1)}  (p ≥ 2: real pairs ±ρ are p = 2, rotations ρ·R(π q/p) …),
        λ_c = 1 − ρ^{−2} = λ_min  (p = 1, a 2×2 Jordan block: any two distinct arrival times separate).

    Returns None when the case does not apply (including ratios that are no root of unity of order ≤ 24).
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    if A.shape != (2, 2) or not is_detectable(A, C):
        return None
    ev = np.linalg.eigvals(A)
    rho = spectral_radius(A)
    if rho <= 1 + CRITICAL_RHO_TOL or abs(abs(ev[0]) - abs(ev[1])) > group_tolerance(A):
        return None
    s = np.linalg.svd(C, compute_uv=False)
    if s.size >= 2 and s[1] > CRITICAL_RANK_TOL * s[0]:
        return None  # C has rank 2: one-step observable (non-degenerate)
    w = complex(ev[1] / ev[0])
    p = root_of_unity_order(w / abs(w), tol=1e-9)
    if p is None and abs(ev[0] - ev[1]) <= group_tolerance(A):
        p = 1  # numerically repeated eigenvalue
    if p is None:
        return None
    if p == 1 and np.linalg.norm(A - np.real(ev[0]) * np.eye(2)) <= group_tolerance(A):
        return None  # A = σ I with rank-1 C: not detectable (caught above); defensive
    e = degenerate_growth_exponent(p)
    lam = 1.0 - rho ** (-e)
    what = ("a 2×2 Jordan block (repeated eigenvalue): any two distinct arrival times separate the modes"
            if p == 1 else
            f"two eigenvalues of equal modulus ρ = {rho:.6g} whose ratio is a primitive {p}-th root of unity: arrivals "
            f"a multiple of {p} steps apart never separate the modes")
    formula = "1 − ρ^(−2)" if p == 1 else f"1 − ρ^(−2p/(p−1)) with p = {p}"
    return ExactCase(f"degenerate_2x2_p{p}", lam, f"degenerate second-order system, {what}",
                     f"λ_c = {formula} (derived in experiments/critical/README.md, checked against the exact "
                     "expected covariance enumerated over every arrival sequence)", basis="derived")


@dataclass(frozen=True)
class LowerBound:
    """A proven lower bound on λ_c above λ_min: the decided λ_c of a decoupled modal sub-system."""

    value: float
    sub_key: str
    eigenvalues: tuple[complex, ...]
    why: str

    def as_json(self) -> dict:
        return {"value": self.value, "subsystem_case": self.sub_key,
                "eigenvalues": [[z.real, z.imag] for z in self.eigenvalues], "why": self.why}


def modal_subsystem(A, C, group_moduli: tuple[float, float]) -> tuple[np.ndarray, np.ndarray] | None:
    """(A_a, C_a) of the modes whose |σ| lies in [lo, hi], decoupled from the rest.

    Ordered real Schur form puts the group first, x = Z z, A_z = [[T11, T12], [0, T22]]; with X solving the
    Sylvester equation T11 X − X T22 = −T12 (disjoint spectra), ξ₁ = z₁ − X z₂ obeys ξ₁⁺ = T11 ξ₁ + noise and the
    output is y = C Z₁ ξ₁ + (terms in ξ₂) + v. None when the reordering fails.
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    lo, hi = group_moduli
    gtol = group_tolerance(A)
    sel = lambda x, y: lo - gtol / 2 <= math.hypot(x, y) <= hi + gtol / 2  # noqa: E731
    T, Z, k = scipy.linalg.schur(A, output="real", sort=sel)
    if k == 0 or k == A.shape[0]:
        return (T, C @ Z) if k else None
    expect = int(np.sum((np.abs(np.linalg.eigvals(A)) >= lo - gtol / 2) & (np.abs(np.linalg.eigvals(A)) <= hi + gtol / 2)))
    if k != expect:
        return None
    return T[:k, :k], C @ Z[:, :k]


def subsystem_lower_bound(A, C) -> LowerBound | None:
    """max over quasi-equiblocks of the decided λ_c of the decoupled two-state sub-system, if it exceeds λ_min.

    Why it is a lower bound (a genie argument): a filter that is also told the other modal coordinates ξ₂ (and
    their noise) exactly, at every step, has a smaller error covariance than the Kalman filter, and for it the
    group's coordinates ξ₁ form the system (T11, C Z₁) with the same arrivals (y − (terms in ξ₂) is known) and a
    process noise of covariance Q₁|₂ ≻ 0 (the conditional covariance given ξ₂'s noise). So E[P] bounded ⇒ the
    sub-system's E[P] bounded: λ_c(A, C) ≥ λ_c(T11, C Z₁). Useful for a degenerate 2×2 block inside a larger system
    (e.g. diag(2, −2, 1.5), C = [1 1 1]: λ_c ≥ 0.9375 > λ_min = 0.75).
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    if A.shape[0] <= 2:
        return None
    nd = nondegeneracy(A, C)
    best = None
    lmin = lambda_min(A)
    for g in nd.groups:
        if g.dim != 2 or g.one_step_observable:
            continue
        mods = [abs(z) for z in g.eigenvalues]
        sub = modal_subsystem(A, C, (min(mods), max(mods)))
        if sub is None:
            continue
        ec = degenerate_second_order(*sub)
        if ec is None or ec.value is None or ec.value <= lmin + 1e-12:
            continue
        if best is None or ec.value > best.value:
            best = LowerBound(ec.value, ec.key, g.eigenvalues,
                              f"the modes |σ| = {g.modulus:.6g} form a degenerate 2×2 sub-system ({ec.key}: {ec.condition}); "
                              "a filter told the other modes exactly does better, so λ_c ≥ its λ_c (genie argument, "
                              "experiments/critical/README.md)")
    return best


def residue_window_rate(T: np.ndarray, p_order: int) -> float:
    """Per-period decay μ_p of Pr[all arrivals of a window fall in one residue class mod p] under the chain T.

    Allowed patterns: one free step (arrival or loss) then p − 1 lost steps, repeated. With K_free = T and
    K_lost = T·diag(1, 0) (next step must be a loss), the window of m periods has probability π·(K_free K_lost^{p−1})^m·1,
    so μ_p = spectral radius of M = K_free·K_lost^{p−1} (i.i.d.: (1 − λ)^{p−1}; p = 1 means "no constraint" and is
    not used: a Jordan block's mechanism is "at most one arrival", rate 1 − q).
    """
    T = np.asarray(T, float)
    Kl = T @ np.diag([1.0, 0.0])
    M = T @ np.linalg.matrix_power(Kl, p_order - 1)
    return float(np.max(np.abs(np.linalg.eigvals(M))))


def ge_degenerate_critical_q(A, C, p: float, *, tol: float = 1e-10) -> float | None:
    """Critical recovery rate of a degenerate 2×2 system (``degenerate_2x2_p<P>``) over Gilbert–Elliott loss.

    Derived like the i.i.d. case (experiments/critical/README.md): P_k ≤ c·ρ^{2(k−t)} with t the older arrival of the
    most recent pair in different residue classes mod P, and a window of L steps whose arrivals share one class has
    probability ≍ μ_P^{L/P} (:func:`residue_window_rate`). So E[P] < ∞ ⇔ ρ^{2P}·μ_P(p, q) < 1; the critical q is found
    by bisection (μ_P decreases in q: more recovery, fewer constrained windows). P = 1 (Jordan block): q > 1 − 1/ρ².
    Returns None if the system is not a degenerate 2×2 case, 1.0 if even q = 1 is not enough.
    """
    ec = exact_case(A, C)
    if ec is None or not ec.key.startswith("degenerate_2x2_p"):
        return None
    P = int(ec.key.rsplit("p", 1)[1])
    rho = spectral_radius(A)
    if P == 1:
        return 1.0 - rho ** -2

    def unstable(q):
        return rho ** (2 * P) * residue_window_rate(ge_chain(p, q), P) >= 1.0

    if unstable(1.0):
        return 1.0
    a, b = 0.0, 1.0
    while b - a > tol:
        m = 0.5 * (a + b)
        a, b = (m, b) if unstable(m) else (a, m)
    return b


def tail_exponent(A, C, *, loss_stay: float, channel: str = "bernoulli", T: np.ndarray | None = None) -> tuple[float | None, str]:
    """Decay exponent φ of Pr[tr P_k > M] ~ M^φ and where it comes from.

    Non-degenerate systems (Mo & Sinopoli 2012, IEEE TAC 57(3): power decay law with exact rate): a loss burst of
    length L has probability ∝ s^L, s = 1 − λ (i.i.d.) or 1 − q (Gilbert–Elliott recovery rate q), and makes
    tr P ∝ ρ^{2L}, so φ = log s / (2 log ρ(A)). Degenerate second-order systems (derived, i.i.d. only): the
    probability of a one-residue-class window is ∝ (1 − λ)^{L(p−1)/p}, so φ = (p − 1)/p · log(1 − λ)/(2 log ρ).
    Returns (None, why) where no exponent is known.
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    rho = spectral_radius(A)
    if rho <= 1 + CRITICAL_RHO_TOL:
        return None, "ρ(A) ≤ 1: no exponential growth during bursts (no power law)"
    if not 0.0 < loss_stay < 1.0:
        return None, "the loss-burst law is degenerate (no loss, or bursts never end)"
    ec = exact_case(A, C)
    if ec is None or ec.value is None:
        return None, "no theorem gives the decay rate of this (degenerate) system"
    base = math.log(loss_stay) / (2.0 * math.log(rho))
    if ec.key.startswith("degenerate_2x2_p"):
        p = int(ec.key.rsplit("p", 1)[1])
        if channel != "bernoulli":
            if T is None or p == 1:
                return (base if p == 1 else None), ("derived for a 2×2 Jordan block: log(1 − q)/(2 log ρ(A))" if p == 1
                                                    else "degenerate system over a Markov channel: give the chain T")
            mu = residue_window_rate(T, p)
            return (math.log(mu) / (p * 2.0 * math.log(rho)),
                    f"derived for a degenerate 2×2 system (p = {p}) over a Markov chain: log μ_p/(p·2 log ρ(A)), μ_p the "
                    "per-period rate of windows whose arrivals share one residue class")
        f = 1.0 if p == 1 else (p - 1) / p
        return f * base, f"derived for a degenerate 2×2 system (p = {p}): ((p−1)/p)·log(1−λ)/(2 log ρ(A))"
    what = "1 − λ" if channel == "bernoulli" else "1 − q (q = recovery rate)"
    return base, f"Mo & Sinopoli 2012 (non-degenerate, {ec.key}): log({what})/(2 log ρ(A))"


# =============================================================================================
# Numerical certificate: the L-step averaged Riccati map over every arrival pattern
# =============================================================================================


def _patterns(L: int) -> np.ndarray:
    """All 2^L arrival patterns, shape (L, 2^L) bool (pattern index innermost)."""
    idx = np.arange(2 ** L)
    return ((idx[None, :] >> np.arange(L)[:, None]) & 1).astype(bool)


def _riccati_steps(P: np.ndarray, pats: np.ndarray, A, C, Q, R) -> np.ndarray:
    """Apply P ← A (P − γ P Cᵀ(C P Cᵀ + R)⁻¹ C P) Aᵀ + Q along each pattern; P (n, n, r), pats (L, r)."""
    for t in range(pats.shape[0]):  # the Kalman core's update (γ per pattern) and predict
        upd = kalman.update(P, C, R)
        P = np.where(pats[t][None, None, :], upd, P)
        P = kalman.predict(P, A, Q)
    return P


@dataclass(frozen=True)
class BlockMap:
    """Φ(Z)_j = (1/π_j) Σ_i π_i Σ_{γ ∈ {0,1}^L, γ_L = j} Pr(γ | γ₀ = i) G_γ(Z_i) on the chain states j ∈ {0, 1}.

    G_γ is the composition of the L Riccati maps of the arrival pattern γ (prediction form). For i.i.d. arrivals the
    two states coincide and Φ is the L-step averaged map Σ_γ π_γ G_γ (L = 1: Sinopoli's g_λ).
    """

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    T: np.ndarray   # T[a, b] = P(γ_{t+1} = b | γ_t = a)
    L: int

    def __post_init__(self):
        pats = _patterns(self.L)
        T = self.T
        pi = np.array([T[1, 0], T[0, 1]]) / (T[1, 0] + T[0, 1])
        object.__setattr__(self, "pi", pi)
        object.__setattr__(self, "pats", pats)
        w = np.empty((2, pats.shape[1]))
        for i in (0, 1):
            prev = np.full(pats.shape[1], i)
            pr = np.ones(pats.shape[1])
            for t in range(self.L):
                g = pats[t].astype(int)
                pr = pr * T[prev, g]
                prev = g
            w[i] = pr
        object.__setattr__(self, "w", w)           # w[i, γ] = Pr(γ | γ₀ = i)
        object.__setattr__(self, "end", pats[-1].astype(int))

    def __call__(self, Z: np.ndarray) -> np.ndarray:
        """Z shaped (2, n, n) → Φ(Z) (2, n, n)."""
        r = self.pats.shape[1]
        if np.allclose(self.T[0], self.T[1], rtol=0, atol=0):  # i.i.d.: one state, Φ = Σ_γ π_γ G_γ
            G = _riccati_steps(np.repeat(Z[0][:, :, None], r, axis=2), self.pats, self.A, self.C, self.Q, self.R)
            X = np.einsum("ijr,r->ij", G, self.w[0])
            X = 0.5 * (X + X.T)
            return np.stack([X, X])
        P = np.concatenate([np.repeat(Z[i][:, :, None], r, axis=2) for i in (0, 1)], axis=2)
        G = _riccati_steps(P, np.concatenate([self.pats, self.pats], axis=1), self.A, self.C, self.Q, self.R)
        out = np.zeros_like(Z)
        for j in (0, 1):
            acc = np.zeros(Z.shape[1:])
            for i in (0, 1):
                m = (self.end == j)
                acc += self.pi[i] * np.einsum("ijr,r->ij", G[:, :, i * r:(i + 1) * r][:, :, m], self.w[i][m])
            out[j] = acc / self.pi[j] if self.pi[j] > 0 else np.nan
        for j in (0, 1):
            if self.pi[j] <= 0:  # a state the chain never visits: it does not matter, copy the other
                out[j] = out[1 - j]
        return 0.5 * (out + out.transpose(0, 2, 1))


def block_certified(bm: BlockMap, *, iters: int = 400) -> tuple[bool, float]:
    """(certified, margin): a Z with Z − Φ(Z) ≻ 0 found (Z = t·Φ^j(0), t ∈ {1.5, 2, 4}).

    Why this proves E[P_k] bounded: each G_γ is monotone and concave (a composition of Riccati maps), and given
    γ_{k−1} = i the next L arrivals are independent of P_k (Markov), so by Jensen E[P_{k+L} | γ_{k+L−1} = j] ≤
    Φ(E[P_k | γ_{k−1} = ·])_j. Φ is a minimum over gain sequences of affine maps (each Riccati step is
    min_K of an affine map in P), so a strict super-solution Z ≻ Φ(Z) makes the linear part of the minimizing
    affine map a contraction, exactly as in Sinopoli et al. 2004, Thm 4 (L = 1): Φ^j(Y) stays bounded from any Y.
    And Z = t·V with V = Φ(V), t > 1, is one: concavity gives Φ(tV) ≤ tΦ(V) − (t − 1)Φ(0) ≺ tV since Φ(0) ⪰ Q ≻ 0.
    The margin is min eig(Z − Φ(Z)) / max eig(Z), re-evaluated in floating point.
    """
    n = bm.A.shape[0]
    Z = np.zeros((2, n, n))
    scale = 1.0 + float(np.trace(bm.Q))
    for _ in range(iters):
        Zn = bm(Z)
        if not np.all(np.isfinite(Zn)) or np.trace(Zn[0]) + np.trace(Zn[1]) > 1e13 * scale:
            return False, -math.inf
        step = np.abs(Zn - Z).max()
        Z = Zn
        if step <= 1e-10 * max(1.0, np.abs(Z).max()):
            break
    best = -math.inf
    for t in (1.5, 2.0, 4.0):
        X = t * Z
        F = bm(X)
        if not np.all(np.isfinite(F)):
            continue
        top = max(float(np.linalg.eigvalsh(X[j]).max()) for j in (0, 1))
        marg = min(float(np.linalg.eigvalsh(X[j] - F[j]).min()) for j in (0, 1)) / max(top, np.finfo(float).tiny)
        best = max(best, marg)
        if marg > CRITICAL_MARGIN_TOL:
            return True, marg
    return False, best


@dataclass(frozen=True)
class Certificate:
    """Numerical upper bound on λ_c (or on the critical recovery rate q_c): ``hi`` carries a checked super-solution."""

    lo: float          # not certified at lo (lower end of the bisection: NOT a lower bound on λ_c)
    hi: float          # certified: E[P_k] bounded for every rate above hi
    L: int
    tol: float
    what: str = "lambda"

    def as_json(self) -> dict:
        return {"upper": self.hi if math.isfinite(self.hi) else None, "bisection_lower": self.lo, "block_length": self.L,
                "bisection_tol": self.tol,
                "method": "L-step averaged Riccati map over all 2^L arrival patterns (Jensen + concavity); the upper "
                          "end carries a strict super-solution Z ≻ Φ(Z) re-checked in floating point (margin > %g)"
                          % CRITICAL_MARGIN_TOL,
                "meaning": "numerical certificate: λ_c ≤ upper (the lower end is where the bisection found none, not "
                           "a bound on λ_c)"}


def iid_chain(lam: float) -> np.ndarray:
    return np.array([[1 - lam, lam], [1 - lam, lam]])


def ge_chain(p: float, q: float) -> np.ndarray:
    """T[a, b] = P(γ_{t+1} = b | γ_t = a) of the Gilbert chain: failure p = P(0 | 1), recovery q = P(1 | 0)."""
    return np.array([[1 - q, q], [p, 1 - p]])


def lambda_c_certificate(A, C, Q=None, R=None, *, L: int = 6, tol: float = 1e-3, lo: float = 0.0,
                         hi: float = 1.0) -> Certificate:
    """Smallest i.i.d. arrival rate (bisection on [lo, hi], ± tol) at which :func:`block_certified` succeeds."""
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    Q = np.eye(A.shape[0]) if Q is None else np.atleast_2d(np.asarray(Q, float))
    R = np.eye(C.shape[0]) if R is None else np.atleast_2d(np.asarray(R, float))

    def ok(lam):
        return block_certified(BlockMap(A, C, Q, R, iid_chain(lam), L))[0]

    if not ok(hi):
        return Certificate(hi, math.inf, L, tol)
    a, b = lo, hi
    while b - a > tol:
        m = 0.5 * (a + b)
        a, b = (a, m) if ok(m) else (m, b)
    return Certificate(a, b, L, tol)


def ge_q_certificate(A, C, Q, R, p: float, *, L: int = 6, tol: float = 1e-3, lo: float = 0.0) -> Certificate:
    """Smallest recovery rate q (bisection ± tol) certified by the Markov block map at failure rate p."""
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    Q, R = np.atleast_2d(np.asarray(Q, float)), np.atleast_2d(np.asarray(R, float))

    def ok(q):
        return block_certified(BlockMap(A, C, Q, R, ge_chain(p, q), L))[0]

    if not ok(1.0):
        return Certificate(1.0, math.inf, L, tol, "q")
    a, b = lo, 1.0
    while b - a > tol:
        m = 0.5 * (a + b)
        a, b = (a, m) if ok(m) else (m, b)
    return Certificate(a, b, L, tol, "q")


def enumerate_expected_trace(A, C, Q, R, T: np.ndarray, K: int, P0=None, start=None) -> np.ndarray:
    """Exact E[tr P_k], k = 1 … K, over every arrival sequence (2^K of them) of the chain T.

    P_k = P_{k|k−1} (prediction form), P_0 = ``P0`` (default 0); γ_0 drawn from ``start`` (default the stationary
    law of T). Each sequence is one column of a (n, n, 2^k) array whose probability is carried along; no sampling,
    no truncation: the only error is floating-point rounding. K ≤ 22 (memory 2^K·n²·8 bytes).
    """
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    Q, R = np.atleast_2d(np.asarray(Q, float)), np.atleast_2d(np.asarray(R, float))
    if K > 22:
        raise ValueError(f"K = {K} > 22 sequences would not fit in memory")
    n = A.shape[0]
    T = np.asarray(T, float)
    pi = np.array([T[1, 0], T[0, 1]]) / (T[1, 0] + T[0, 1]) if start is None else np.asarray(start, float)
    P = (np.zeros((n, n)) if P0 is None else np.atleast_2d(np.asarray(P0, float)))[:, :, None].copy()
    w = np.ones(1)
    last = None
    out = np.empty(K)
    for k in range(K):
        r = P.shape[2]
        pr1 = np.full(r, pi[1]) if last is None else np.where(last, T[1, 1], T[0, 1])
        both = np.concatenate([P, P], axis=2)
        pats = np.concatenate([np.zeros(r, bool), np.ones(r, bool)])[None, :]
        P = _riccati_steps(both, pats, A, C, Q, R)
        w = np.concatenate([w * (1 - pr1), w * pr1])
        last = pats[0]
        out[k] = float(np.einsum("iir,r->", P, w))
    return out


def growth_per_period(e: np.ndarray, period: int) -> float:
    """Ratio of the last two increments of e over ``period`` steps: (e_K − e_{K−p}) / (e_{K−p} − e_{K−2p}).

    For a sequence e_k = a·r^{k/p} + b + (faster-decaying terms) this tends to r; it removes the constant b exactly.
    """
    K = len(e)
    d1 = e[K - 1] - e[K - 1 - period]
    d0 = e[K - 1 - period] - e[K - 1 - 2 * period]
    return float(d1 / d0) if d0 > 0 else math.inf


# =============================================================================================
# When is a Monte Carlo mean of P a result? (issue 19, item 4)
# =============================================================================================


@dataclass(frozen=True)
class MeanReliability:
    reliable: bool
    reason: str
    burst_ratio: float            # r = s·ρ² per step (s = probability that a loss burst continues)
    longest_burst_seen: float     # L*: the longest burst the sample is expected to contain
    missing_fraction: float       # r^{L*+1}: share of the burst sum carried by longer bursts


def mean_reliability(mean: float, stderr: float, *, runs: int, steps: int, loss_stay: float, growth: float,
                     lower_bound: float | None = None, sigmas: float = 3.0, max_missing: float = 0.05) -> MeanReliability:
    """Is a Monte Carlo mean of tr P a result, or is it dominated by loss bursts the sample cannot contain?

    ``loss_stay`` s = P(a loss burst continues) (1 − λ i.i.d., 1 − q Gilbert–Elliott); ``growth`` g = growth of tr P
    per lost step (ρ(A)², or the derived per-step rate of a degenerate system). A burst of length L has probability
    ∝ s^L and adds ∝ g^L, so the mean is the sum Σ_L (s g)^L: infinite when r = s g ≥ 1. With runs × steps burst
    opportunities the sample contains bursts up to L* = log(runs·steps·(1−s))/(−log s) (expected count ≥ 1); the
    longer ones carry the fraction r^{L*+1} of the sum. Unreliable when

    * r ≥ 1 (the mean is infinite whatever the sample), or r^{L*+1} > ``max_missing`` (rare-event dominated), or
    * the mean lies below a proven lower bound by more than ``sigmas`` standard errors (it cannot be right).

    A perfect channel (s = 0) has no bursts: nothing is missing.
    """
    r = loss_stay * growth
    if not (math.isfinite(mean)):
        return MeanReliability(False, "non-finite mean", r, 0.0, 1.0)
    if lower_bound is not None and math.isfinite(lower_bound) and mean < lower_bound - sigmas * stderr:
        return MeanReliability(False, f"below the proven lower bound {lower_bound:.4g} by "
                                      f"{(lower_bound - mean) / max(stderr, 1e-300):.1f} s.e.", r, 0.0, 1.0)
    if loss_stay <= 0.0:
        return MeanReliability(True, "no loss bursts", 0.0, 0.0, 0.0)
    if r >= 1.0:
        return MeanReliability(False, f"rare-event dominated: s·ρ² = {r:.3g} ≥ 1 (the mean is infinite)", r, 0.0, 1.0)
    opp = max(runs * steps * (1.0 - loss_stay), 1.0)
    Lstar = math.log(opp) / -math.log(loss_stay) if loss_stay < 1 else math.inf
    missing = r ** (Lstar + 1)
    if missing > max_missing:
        return MeanReliability(False, f"rare-event dominated: bursts longer than the ~{Lstar:.0f} steps the sample "
                                      f"contains carry {100 * missing:.0f} % of the mean", r, Lstar, missing)
    return MeanReliability(True, "", r, Lstar, missing)


# =============================================================================================
# Delay with a receive buffer (Shi, Xie & Murray 2009)
# =============================================================================================


def delay_effective_rate(channel) -> tuple[float, int]:
    """(λ_eff, D_max): the probability that a packet is ever used by the buffered estimator.

    λ_eff = F(D_max) with F the delay cdf (missing mass = loss) and D_max = D (``delay_le_D``)
    or D − 1 (``delay_lt_D``). With i.i.d. delays the packets used are i.i.d. Bernoulli(λ_eff),
    and P_k is sandwiched between the KF on those packets and h^{D_max} of it at k − D_max, so
    E[P_k] is bounded iff it is for i.i.d. arrivals at rate λ_eff.
    """
    Dmax = max_kept_delay(channel.D, channel.convention)
    return float(np.asarray(channel.cdf(Dmax)).reshape(-1)[0]), int(Dmax)


# =============================================================================================
# The whole answer for one system
# =============================================================================================


@dataclass
class CriticalReport:
    """Everything ``netkf critical`` says about one system (and optionally one channel)."""

    n: int
    m: int
    rho: float
    lam_min: float
    lam_max: LambdaMax
    exact: ExactCase | None
    channel: dict = field(default_factory=dict)
    certificate: Certificate | None = None
    nondegeneracy: NonDegeneracy | None = None
    lower_bound: LowerBound | None = None

    @property
    def lower(self) -> float:
        """The best proven lower bound on λ_c: λ_min, or a decoupled degenerate sub-system's λ_c."""
        return max(self.lam_min, self.lower_bound.value if self.lower_bound is not None else 0.0)

    @property
    def proven(self) -> bool:
        return self.exact is not None

    @property
    def decided_by(self) -> str:
        """One phrase: which theorem decides λ_c, or that only an interval / a numerical certificate is known."""
        e = self.exact
        if e is not None:
            return f"{'derived closed form' if e.basis == 'derived' else 'theorem'} ({e.key}): {e.source}"
        c = self.certificate
        lo_txt = ("λ_min" if self.lower_bound is None else
                  f"{self.lower:.6g} (a degenerate 2×2 sub-system, {self.lower_bound.sub_key})")
        if c is not None and math.isfinite(c.hi) and c.hi < self.lam_max.hi:
            return (f"numerical certificate: {lo_txt} ≤ λ_c ≤ {c.hi:.6g} (L = {c.L}-step averaged Riccati map over every "
                    f"arrival pattern, ± {c.tol:g}); no theorem decides λ_c for this degenerate system")
        if self.lower_bound is not None:
            return (f"interval: {lo_txt} ≤ λ_c ≤ λ_max = {self.lam_max.hi:.6g}; no theorem decides λ_c for this "
                    "degenerate system")
        return "interval only: λ_min ≤ λ_c ≤ λ_max (Sinopoli et al. 2004, Thms 3–5); no theorem decides λ_c"

    @property
    def upper(self) -> float:
        """The best proven or certified upper bound on λ_c."""
        c = self.certificate
        return min(self.lam_max.hi, c.hi if c is not None else math.inf)

    def verdict(self) -> str:
        e = self.exact
        if e is not None and e.value is None:
            return f"λ_c does not exist: {e.condition}; {e.source}."
        if e is not None and e.value == 0.0:
            return f"λ_c = 0 exactly ({e.condition}): E[P_k] stays bounded for every arrival rate λ > 0."
        if e is not None:
            return (f"λ_c = {e.value:.6g} exactly ({e.condition}; {e.source}). "
                    f"E[P_k] stays bounded for every arrival rate λ > {e.value:.6g} and diverges (for some P0) below.")
        lm = self.lam_max
        c = self.certificate
        if c is not None and math.isfinite(c.hi) and c.hi < lm.hi:
            lo_txt = ("λ_min" if self.lower_bound is None else
                      f"the λ_c of its degenerate 2×2 sub-system ({self.lower_bound.sub_key}, proven lower bound)")
            return (f"λ_c is bounded by a numerical certificate: {self.lower:.6g} = {lo_txt} ≤ λ_c ≤ {c.hi:.6g} "
                    f"(tighter than Sinopoli's λ_min = {self.lam_min:.6g} ≤ λ_c ≤ λ_max ≤ {lm.hi:.6g}; {c.L}-step averaged "
                    f"Riccati map, bisection ± {c.tol:g}). No theorem decides λ_c for this degenerate system; "
                    f"λ ≤ {self.lower:.6g} is insufficient, λ > {c.hi:.6g} certified sufficient; in between it is not decided.")
        return (f"λ_c is only bounded: {self.lam_min:.6g} = λ_min ≤ λ_c ≤ λ_max ≤ {lm.hi:.6g} "
                f"(no exactness condition holds). λ > {lm.hi:.6g} is proven sufficient for bounded E[P_k]; "
                f"λ ≤ {self.lam_min:.6g} proven insufficient; in between it is not decided.")

    def as_json(self) -> dict:
        lm = self.lam_max
        e = self.exact
        return {
            "n": self.n, "m": self.m, "spectral_radius": self.rho,
            "lambda_min": self.lam_min,
            "lambda_max": {"lower": lm.lo, "upper": None if math.isinf(lm.hi) else lm.hi, "bisection_tol": lm.tol,
                           "solves": lm.solves, "solver": lm.solver, "statuses": list(lm.statuses),
                           "certificate": "upper end: the solver's (Y, Z) re-checked, min eig(Ψ_λ) > %g" % CRITICAL_MARGIN_TOL},
            "lambda_c": None if e is None else e.value,
            "proven": self.proven,
            "condition": None if e is None else e.key,
            "condition_text": "none of the exactness conditions holds: only the interval is proven" if e is None else e.condition,
            "source": None if e is None else e.source,
            "interval": [self.lower, None if math.isinf(self.upper) else self.upper],
            "lower_bound": None if self.lower_bound is None else self.lower_bound.as_json(),
            "basis": None if e is None else e.basis,
            "decided_by": self.decided_by,
            "certificate": None if self.certificate is None else self.certificate.as_json(),
            "nondegeneracy": None if self.nondegeneracy is None else self.nondegeneracy.as_json(),
            "verdict": self.verdict(),
            "channel": self.channel,
        }


def critical_report(A, C, *, tol: float = CRITICAL_BISECTION_TOL, solver: str = "CLARABEL", Q=None, R=None,
                    certificate: bool = True, block: int = 6, certificate_tol: float = 1e-3) -> CriticalReport:
    """λ_min, λ_max (bisection), the proven case for (A, C), and where no theorem applies a numerical certificate
    (:func:`lambda_c_certificate`, with the system's Q and R; identity when not given)."""
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    exact = exact_case(A, C)
    nd = nondegeneracy(A, C) if A.shape[0] > 0 else None
    try:
        lm = lambda_max(A, C, tol=tol, solver=solver)
    except CriticalRateError as exc:
        if exact is None:
            raise CriticalRateError(f"{exc}. The LMI is badly scaled for this system (ρ(A) = {spectral_radius(A):.3g}); "
                                    f"proven: λ_c ≥ λ_min = {lambda_min(A):.6g}") from None
        # the exact case does not need the LMI: report λ_max as not computed (hi = ∞ is never a claim)
        lm = LambdaMax(lambda_min(A), math.inf, tol, 0, solver, ("not solved: " + str(exc)[:120],))
    cert = None
    lower = subsystem_lower_bound(A, C) if exact is None else None
    if exact is None and certificate and A.shape[0] <= 6:
        cert = lambda_c_certificate(A, C, Q, R, L=block, tol=certificate_tol,
                                    lo=lower.value if lower is not None else lambda_min(A),
                                    hi=min(1.0, lm.hi + certificate_tol) if math.isfinite(lm.hi) else 1.0)
    return CriticalReport(A.shape[0], C.shape[0], spectral_radius(A), lambda_min(A), lm, exact, certificate=cert,
                          nondegeneracy=nd, lower_bound=lower)
