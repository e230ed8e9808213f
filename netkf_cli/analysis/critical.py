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
a single unstable eigenvalue (Mo & Sinopoli 2008; argument in experiments/critical/README.md).
Everywhere else the answer is the interval [λ_min, λ_max].

**Gilbert–Elliott (Markov) arrivals** with failure rate p = P(γ_{k+1} = 0 | γ_k = 1) and
recovery rate q = P(γ_{k+1} = 1 | γ_k = 0) (``channels.gilbert_elliott``: p = p_gb, q = p_bg):

* necessary for any system: (1 − q) ρ(A)² < 1 (:func:`ge_q_necessary`; the analogue of Thm 3:
  a loss burst of length j has probability ∝ (1 − q)^j and P grows like ρ(A)^{2j} during it);
* exact where one received packet bounds P (scalar, C of full column rank, single unstable
  eigenvalue, ρ(A) ≤ 1): bounded iff q > 1 − 1/ρ(A)², whatever p (:func:`ge_scalar_bounds`
  gives the stationary E[P] bracket of the scalar case in closed form);
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

from netkf_cli.errors import NetkfError

RHO_TOL = 1e-9
"""|σ| within this of 1 counts as "on the unit circle"."""

MARGIN_TOL = 1e-9
"""An LMI solution certifies feasibility when the smallest eigenvalue of the (numerically
re-evaluated) block matrix and of Y exceeds this (both are normalised by Y ≤ I)."""

DEFAULT_BISECTION_TOL = 1e-5


class CriticalRateError(NetkfError):
    """An SDP solve failed (solver status other than optimal)."""


# =============================================================================================
# Small helpers
# =============================================================================================


def spectral_radius(A: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(np.atleast_2d(A))))) if np.size(A) else 0.0


def _sym(X: np.ndarray) -> np.ndarray:
    return 0.5 * (X + X.T)


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


def is_detectable(A: np.ndarray, C: np.ndarray, tol: float = 1e-9) -> bool:
    """PBH test: no eigenvector v of an eigenvalue |σ| ≥ 1 has C v = 0.

    For each unstable σ the eigenspace N = ker(A − σI) is found on its own scale (SVD of A − σI),
    then C N must have full column rank relative to ‖C‖ — so A = diag(1e200, 0.5) is judged like
    A = diag(2, 0.5) (an SVD of the stacked [A − σI; C] would compare 1e200 with 1), and a
    Jordan block contributes its true (one-dimensional) eigenspace.
    """
    n = A.shape[0]
    cn = max(np.linalg.norm(C, 2), np.finfo(float).tiny)
    for sig in np.linalg.eigvals(A):
        if abs(sig) < 1 - RHO_TOL:
            continue
        _, sv, Vh = np.linalg.svd(A - sig * np.eye(n))
        null = Vh[(sv <= tol * max(1.0, sv[0])), :].conj().T if sv.size else np.eye(n)
        if null.shape[1] == 0:  # numerically no eigenvector (should not happen for an eigenvalue): smallest direction
            null = Vh[-1:, :].conj().T
        s = np.linalg.svd(C @ null, compute_uv=False)
        if (s > tol * cn).sum() < null.shape[1]:
            return False
    return True


def unstable_eigenvalues(A: np.ndarray) -> np.ndarray:
    """Eigenvalues with |σ| ≥ 1 (within :data:`RHO_TOL`), with algebraic multiplicity."""
    ev = np.linalg.eigvals(A)
    return ev[np.abs(ev) >= 1 - RHO_TOL]


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


def exact_case(A: np.ndarray, C: np.ndarray) -> ExactCase | None:
    """The first proven case that applies to (A, C), or None (then only [λ_min, λ_max] is known)."""
    A, C = np.atleast_2d(A), np.atleast_2d(C)
    n = A.shape[0]
    rho = spectral_radius(A)
    if not is_detectable(A, C):
        return ExactCase("undetectable", None, "(A, C) is not detectable: an unstable mode is never measured",
                         "E[P_k] diverges for every arrival rate, λ = 1 included (if Q excites that mode)")
    if rho < 1 - RHO_TOL:
        return ExactCase("stable", 0.0, f"A is Schur stable (ρ(A) = {rho:.6g} < 1)",
                         "open-loop prediction keeps E[P_k] ≤ Σ Aⁱ Q Aᵀⁱ bounded for every λ ≥ 0")
    if rho <= 1 + RHO_TOL:
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
    AX = A @ X
    S = C @ X @ C.T + R
    G = AX @ C.T
    return _sym(AX @ A.T + Q - lam * G @ np.linalg.solve(S, G.T))


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
    A, C, Q, R = (np.atleast_2d(np.asarray(x, float)) for x in (A, C, Q, R))
    n = A.shape[0]
    inf = np.full((n, n), np.inf)
    V = np.zeros((n, n))
    scale = 1.0 + float(np.trace(Q))
    for _ in range(max_iter):
        Vn = modified_riccati(V, A, C, Q, R, lam)
        if not np.all(np.isfinite(Vn)) or np.trace(Vn) > 1e14 * scale:
            return inf
        step = np.abs(Vn - V).max()
        V = Vn
        if step <= 1e-8 * max(1.0, np.abs(V).max()):
            break
    else:
        return inf
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
    """max t s.t. Ψ_λ(Y, Z) ⪰ t I, t I ⪯ Y ⪯ I (cvxpy, DPP in √λ, √(1−λ)); feasible ⇔ t* > 0."""

    def __init__(self, A: np.ndarray, C: np.ndarray, solver: str = "CLARABEL"):
        import cvxpy as cp

        self.A, self.C, self.solver = A, C, solver
        n, m = A.shape[0], C.shape[0]
        self.Y = cp.Variable((n, n), symmetric=True)
        self.Z = cp.Variable((n, m))
        self.t = cp.Variable()
        self.sl, self.sl1 = cp.Parameter(nonneg=True), cp.Parameter(nonneg=True)
        Y, Z = self.Y, self.Z
        B = Y @ A + Z @ C
        O = np.zeros((n, n))
        Psi = cp.bmat([[Y, self.sl * B, self.sl1 * (Y @ A)],
                       [self.sl * B.T, Y, O],
                       [self.sl1 * (Y @ A).T, O, Y]])
        I3, I = np.eye(3 * n), np.eye(n)
        cons = [0.5 * (Psi + Psi.T) >> self.t * I3, Y >> self.t * I, Y << I, self.t <= 1]
        self.prob = cp.Problem(cp.Maximize(self.t), cons)

    def psi(self, Y, Z, lam):
        A, C = self.A, self.C
        n = A.shape[0]
        B = Y @ A + Z @ C
        O = np.zeros((n, n))
        a, b = math.sqrt(lam), math.sqrt(1 - lam)
        return np.block([[Y, a * B, b * Y @ A], [a * B.T, Y, O], [b * (Y @ A).T, O, Y]])

    def margin(self, lam: float) -> tuple[float, str, bool]:
        """(t*, solver status, certified): certified = the returned (Y, Z) satisfies the strict LMI."""
        import cvxpy as cp

        self.sl.value, self.sl1.value = math.sqrt(lam), math.sqrt(max(0.0, 1 - lam))
        try:
            with warnings.catch_warnings():  # "solution may be inaccurate": the status and a certificate check decide
                warnings.simplefilter("ignore", UserWarning)
                self.prob.solve(solver=getattr(cp, self.solver))
        except cp.SolverError as exc:  # pragma: no cover - solver crash
            raise CriticalRateError(f"LMI solve failed at λ = {lam:.6g}: {exc}") from None
        st = self.prob.status
        if st not in ("optimal", "optimal_inaccurate"):
            raise CriticalRateError(f"LMI solve at λ = {lam:.6g} ended with status {st!r}")
        Y, Z = self.Y.value, self.Z.value
        cert = False
        if Y is not None and Z is not None:
            Y = _sym(Y)
            e1 = np.linalg.eigvalsh(_sym(self.psi(Y, Z, lam))).min()
            e2 = np.linalg.eigvalsh(Y).min()
            cert = bool(e1 > MARGIN_TOL and e2 > MARGIN_TOL)
        return float(self.t.value), st, cert


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


def lambda_max(A, C, *, tol: float = DEFAULT_BISECTION_TOL, lo: float = 0.0, solver: str = "CLARABEL") -> LambdaMax:
    """Sinopoli's upper bound λ_max on λ_c: bisection on the LMI Ψ_λ(Y, Z) > 0 (Thm 5).

    Feasibility is monotone in λ (g_λ decreases in λ), so bisection over [lo, 1] finds the
    threshold; "feasible" means the solver's (Y, Z) passes a numerical eigenvalue check
    (:data:`MARGIN_TOL`), so ``hi`` is certified; "infeasible" trusts the solver's optimum
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
    """

    def __init__(self, A: np.ndarray, C: np.ndarray, solver: str = "CLARABEL"):
        import cvxpy as cp

        self.A, self.C, self.solver = A, C, solver
        n, m = A.shape[0], C.shape[0]
        self.P0 = cp.Variable((n, n), symmetric=True)
        self.P1 = cp.Variable((n, n), symmetric=True)
        self.W = cp.Variable((n, m))
        self.t = cp.Variable()
        self.T = cp.Parameter((2, 2), nonneg=True)
        E0 = self.T[0, 0] * self.P0 + self.T[0, 1] * self.P1
        E1 = self.T[1, 0] * self.P0 + self.T[1, 1] * self.P1
        M0 = cp.bmat([[self.P0, A.T @ E0], [E0 @ A, E0]])
        M1 = cp.bmat([[self.P1, A.T @ E1 - C.T @ self.W.T], [E1 @ A - self.W @ C, E1]])
        I2, I = np.eye(2 * n), np.eye(n)
        cons = [0.5 * (M0 + M0.T) >> self.t * I2, 0.5 * (M1 + M1.T) >> self.t * I2,
                self.P0 >> self.t * I, self.P1 >> self.t * I, self.P0 << I, self.P1 << I, self.t <= 1]
        self.prob = cp.Problem(cp.Maximize(self.t), cons)

    def feasible(self, p: float, q: float) -> tuple[bool, str]:
        import cvxpy as cp

        T = np.array([[1 - q, q], [p, 1 - p]])
        self.T.value = T
        try:
            with warnings.catch_warnings():  # the status and a certificate check decide
                warnings.simplefilter("ignore", UserWarning)
                self.prob.solve(solver=getattr(cp, self.solver))
        except cp.SolverError as exc:  # pragma: no cover
            raise CriticalRateError(f"Markov LMI solve failed at p = {p:.6g}, q = {q:.6g}: {exc}") from None
        st = self.prob.status
        if st not in ("optimal", "optimal_inaccurate"):
            raise CriticalRateError(f"Markov LMI at p = {p:.6g}, q = {q:.6g} ended with status {st!r}")
        P0, P1, W = self.P0.value, self.P1.value, self.W.value
        if P0 is None:
            return False, st
        A, C = self.A, self.C
        P0, P1 = _sym(P0), _sym(P1)
        E0, E1 = T[0, 0] * P0 + T[0, 1] * P1, T[1, 0] * P0 + T[1, 1] * P1
        M0 = np.block([[P0, A.T @ E0], [E0 @ A, E0]])
        M1 = np.block([[P1, A.T @ E1 - C.T @ W.T], [E1 @ A - W @ C, E1]])
        mins = [np.linalg.eigvalsh(_sym(M)).min() for M in (M0, M1, P0, P1)]
        return bool(min(mins) > MARGIN_TOL), st


@dataclass(frozen=True)
class GECurvePoint:
    """For failure rate p: the critical recovery rate q_c(p) bracket [necessary, sufficient]."""

    p: float
    q_necessary: float
    q_sufficient: float        # smallest q (bisection, ± tol) with a certified Markov LMI; inf if none ≤ 1
    q_exact: float | None      # where proven (see exact_case_ge)
    q_bernoulli_same_loss: float  # q at which i.i.d. loss with the same stationary rate reaches λ_c bound


def exact_case_ge(A, C) -> ExactCase | None:
    """Cases where one received packet bounds P, so q > 1 − 1/ρ(A)² is necessary and sufficient.

    The i.i.d. cases carry over when their proof only needs "one arrival bounds the unstable
    part": scalar, C of full column rank, a single unstable eigenvalue, A stable. Not carried over:
    ρ(A) = 1 (its proof needs n consecutive arrivals, which never happen when p = 1) and C
    invertible on the observable subspace (not proven here for Markov loss): the LMI decides there.
    """
    A, C = np.atleast_2d(A), np.atleast_2d(C)
    ec = exact_case(A, C)
    if ec is None or ec.key in ("c_invertible_observable", "marginal"):
        return None
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
        # q/(p+q) = λ ⇔ q = λ p / (1 − λ)
        qb = lam_ref * p / (1 - lam_ref) if lam_ref < 1 else math.inf
        out.append(GECurvePoint(p, qn, qs, q_exact, qb))
    return out


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
    from netkf_cli.channels.delay import max_kept_delay

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

    @property
    def proven(self) -> bool:
        return self.exact is not None

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
                           "certificate": "upper end: the solver's (Y, Z) re-checked, min eig(Ψ_λ) > %g" % MARGIN_TOL},
            "lambda_c": None if e is None else e.value,
            "proven": self.proven,
            "condition": None if e is None else e.key,
            "condition_text": "none of the exactness conditions holds: only the interval is proven" if e is None else e.condition,
            "source": None if e is None else e.source,
            "interval": [self.lam_min, None if math.isinf(lm.hi) else lm.hi],
            "verdict": self.verdict(),
            "channel": self.channel,
        }


def critical_report(A, C, *, tol: float = DEFAULT_BISECTION_TOL, solver: str = "CLARABEL") -> CriticalReport:
    """λ_min, λ_max (bisection) and the proven case for (A, C)."""
    A, C = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(C, float))
    exact = exact_case(A, C)
    try:
        lm = lambda_max(A, C, tol=tol, solver=solver)
    except CriticalRateError as exc:
        if exact is None:
            raise CriticalRateError(f"{exc}. The LMI is badly scaled for this system (ρ(A) = {spectral_radius(A):.3g}); "
                                    f"proven: λ_c ≥ λ_min = {lambda_min(A):.6g}") from None
        # the exact case does not need the LMI: report λ_max as not computed (hi = ∞ is never a claim)
        lm = LambdaMax(lambda_min(A), math.inf, tol, 0, solver, ("not solved: " + str(exc)[:120],))
    return CriticalReport(A.shape[0], C.shape[0], spectral_radius(A), lambda_min(A), lm, exact)
