"""Closed forms of Mostofi & Murray 2009, "Kalman filtering over wireless fading channels —
How to handle packet drop" (Int. J. Robust Nonlinear Control 19:1993–2015).

Conventions (all SNRs here are LINEAR, never dB — convert at the config boundary):

* Υ  instantaneous received SNR, exponential (Rayleigh fading) with mean ``snr_avg`` = Υ_ave,
  density χ(Υ) = e^{-Υ/Υ_ave}/Υ_ave.
* Receiver drop rule, eq. (5): a packet is dropped iff Υ < Υ_T (``threshold``).
* Communication noise variance (Sec. 3.1, after Fig. 5): σ_n²(Υ) = α + δ·Ω(√Υ),
  Ω(d) = ∫_d^∞ e^{-t²/2} dt/√(2π) (Gaussian tail, Ω = Q-function).

α and δ from the packet format (our derivation of Sec. 2.1, see :func:`noise_params_from_bits`):
a uniform quantizer of step Δ gives the quantization floor α = Δ²/12; a packet of N_p bits in
natural binary order, each bit flipped independently with probability p_b = Ω(√Υ) and
equally likely 0/1, gives a link error Σ_i ε_i 2^i Δ with ε_i ∈ {0, ±1} independent and
zero-mean, so E n_c² = p_b Δ² Σ_{i<N_p} 4^i = p_b Δ² (4^{N_p} − 1)/3, i.e. δ = Δ²(4^{N_p}−1)/3.
The printed α = 1.27e-4, δ = 533.3 (N_p = 10) hold for Δ = 40/2^10 = 0.0390625, printed
rounded as 0.0391 (Δ = 0.0391 exactly gives δ = 534.4).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special
from scipy.linalg import solve_discrete_lyapunov

from netkf_cli.core.lazy import scipy_integrate as integrate
from netkf_cli.core.lazy import scipy_optimize as optimize

# --------------------------------------------------------------------------- units


def db_to_linear(x_db):
    """10^(x/10) (power ratio)."""
    return 10.0 ** (np.asarray(x_db, dtype=float) / 10.0)


def linear_to_db(x):
    """10·log10(x); −inf for 0."""
    x = np.asarray(x, dtype=float)
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(x)


# --------------------------------------------------------------------------- noise model


def noise_params_from_bits(N_p: int, Delta: float) -> tuple[float, float]:
    """(α, δ) of σ_n²(Υ) = α + δ·Ω(√Υ) for N_p bits per packet and quantization step Δ.

    α = Δ²/12 (uniform quantization error), δ = Δ²(4^{N_p} − 1)/3 (independent bit flips
    with probability Ω(√Υ), each flip of bit i adding ±2^i Δ; derivation in the module doc).
    """
    if N_p < 1:
        raise ValueError(f"N_p must be >= 1, got {N_p}")
    if not Delta > 0:
        raise ValueError(f"Delta must be > 0, got {Delta}")
    return Delta**2 / 12.0, Delta**2 * (4.0**N_p - 1.0) / 3.0


def omega(d):
    """Ω(d) = ∫_d^∞ e^{-t²/2}/√(2π) dt (the Gaussian Q-function), accurate in the far tail."""
    return special.ndtr(-np.asarray(d, dtype=float))


def sigma2_n(snr, alpha: float, delta: float):
    """σ_n²(Υ) = α + δ Ω(√Υ) (Sec. 3.1; BPSK-type bit error rate Ω(√Υ))."""
    return alpha + delta * omega(np.sqrt(np.asarray(snr, dtype=float)))


def packet_error_prob(snr, N_p: int):
    """Smooth packet-drop curve of Fig. 3(b): Pr[at least one of N_p bits wrong] = 1 − (1 − Ω(√Υ))^{N_p}."""
    pb = omega(np.sqrt(np.asarray(snr, dtype=float)))
    return -np.expm1(N_p * np.log1p(-pb))


def drop_indicator(snr, threshold):
    """μ = G(Υ) of eq. (5): 1 if Υ < Υ_T else 0."""
    return (np.asarray(snr, dtype=float) < threshold).astype(float)


# --------------------------------------------------------------------------- averages, eqs (15)-(16)


def mu_ave(threshold, snr_avg: float):
    """μ_ave(Υ_T) = ∫_0^{Υ_T} χ = 1 − e^{−Υ_T/Υ_ave}, eq. (15) for exponential Υ."""
    T = np.asarray(threshold, dtype=float)
    return -np.expm1(-T / snr_avg)


def sigma2_n_ave(threshold, snr_avg: float, alpha: float, delta: float):
    """σ²_n,ave(Υ_T) = ∫_{Υ_T}^∞ σ_n²(Υ) χ(Υ) dΥ, eq. (16), closed form for exponential Υ.

    With λ = 1/Υ_ave and integration by parts of Ω(√Υ)·λe^{−λΥ}:
    ∫_{T}^∞ Ω(√Υ) λ e^{−λΥ} dΥ = e^{−λT} Ω(√T) − Ω(√((1+2λ)T)) / √(1+2λ),
    so σ²_n,ave = α e^{−λT} + δ [e^{−λT} Ω(√T) − Ω(√((1+2λ)T))/√(1+2λ)].
    At T = 0 the bracket is (1 − √(Υ_ave/(Υ_ave+2)))/2, the classic Rayleigh-averaged BER.
    """
    T = np.asarray(threshold, dtype=float)
    lam = 1.0 / snr_avg
    c = 1.0 + 2.0 * lam
    e = np.exp(-lam * T)
    tail = e * omega(np.sqrt(T)) - omega(np.sqrt(c * T)) / np.sqrt(c)
    return alpha * e + delta * np.maximum(tail, 0.0)


def mu_ave_quad(threshold: float, snr_avg: float) -> float:
    """eq. (15) by quadrature (independent check of :func:`mu_ave`)."""
    val, _ = integrate.quad(lambda y: math.exp(-y / snr_avg) / snr_avg, 0.0, float(threshold), epsabs=0, epsrel=1e-12)
    return val


def sigma2_n_ave_quad(threshold: float, snr_avg: float, alpha: float, delta: float) -> float:
    """eq. (16) by quadrature (independent check of :func:`sigma2_n_ave`)."""
    f = lambda y: (alpha + delta * float(omega(math.sqrt(y)))) * math.exp(-y / snr_avg) / snr_avg  # noqa: E731
    T = float(threshold)
    # split where the Ω term dies out so quad sees both scales
    mid = max(T, 60.0)
    a, _ = integrate.quad(f, T, mid, epsabs=0, epsrel=1e-12, limit=200) if mid > T else (0.0, 0.0)
    b, _ = integrate.quad(f, mid, np.inf, epsabs=0, epsrel=1e-12, limit=200)
    return a + b


# --------------------------------------------------------------------------- stability, eqs (9), (19), (45)


def rho_max(A) -> float:
    """Spectral radius of A."""
    return float(np.max(np.abs(np.linalg.eigvals(np.atleast_2d(A)))))


def max_stable_threshold(snr_avg: float, rho: float) -> float:
    """Largest Υ_T with μ_ave(Υ_T) < ρ_max^{-2} (eqs 19, 45): Υ_T < −Υ_ave ln(1 − ρ^{-2}).

    ``inf`` when ρ_max ≤ 1 (every threshold is stable).
    """
    if rho <= 1.0:
        return math.inf
    return -snr_avg * math.log1p(-rho**-2)


# --------------------------------------------------------------------------- scenario 2 mean, eqs (14), (20), (38)


def _theta(A, C, Q, s2ave, mu, R=None):
    """Θ = Q + A C^{-1} (σ²_n,ave I + (1 − μ) R) C^{-T} A^T (eq. 20; eq. 38 when R ≠ 0)."""
    A = np.atleast_2d(A)
    C = np.atleast_2d(C)
    n = A.shape[0]
    Ci = np.linalg.inv(C)
    Sig = s2ave * np.eye(n) + (0.0 if R is None else (1.0 - mu) * np.atleast_2d(R))
    return np.atleast_2d(Q) + A @ Ci @ Sig @ Ci.T @ A.T


def ep_inf(A, C, Q, mu: float, s2ave: float, R=None) -> np.ndarray:
    """E P[∞] solving the Lyapunov equation (20): X = μ A X Aᵀ + Θ (scipy discrete Lyapunov).

    Returns a matrix of ``inf`` when μ ρ_max² ≥ 1 (no bounded solution, eq. 19).
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    if mu * rho_max(A) ** 2 >= 1.0:
        return np.full(A.shape, np.inf)
    X = solve_discrete_lyapunov(math.sqrt(mu) * A, _theta(A, C, Q, s2ave, mu, R))
    return (X + X.T) / 2


def ep_recursion(A, C, Q, mu: float, s2ave: float, P0, steps: int, R=None) -> np.ndarray:
    """E P[k], k = 0..steps, from the exact mean recursion (14) (eq. 38 with R); shape (steps+1, n, n)."""
    A = np.atleast_2d(np.asarray(A, dtype=float))
    Th = _theta(A, C, Q, s2ave, mu, R)
    out = np.empty((steps + 1,) + A.shape)
    X = np.atleast_2d(np.asarray(P0, dtype=float))
    out[0] = X
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(steps):
            X = mu * A @ X @ A.T + Th
            out[k + 1] = X
    return out


def lower_bound_recursion(A, Q, mu: float, P0, steps: int) -> np.ndarray:
    """E P₁[k] of scenario 1 with R = 0, eq. (32): X ← μ A X Aᵀ + Q. Lemma 5: a lower bound on E P₃[k]."""
    A = np.atleast_2d(np.asarray(A, dtype=float))
    out = np.empty((steps + 1,) + A.shape)
    X = np.atleast_2d(np.asarray(P0, dtype=float))
    out[0] = X
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(steps):
            X = mu * A @ X @ A.T + np.atleast_2d(Q)
            out[k + 1] = X
    return out


def spectral_norm(X) -> float:
    X = np.atleast_2d(X)
    if not np.all(np.isfinite(X)):
        return math.inf
    return float(np.linalg.norm(X, 2))


# --------------------------------------------------------------------------- optimal thresholds, eqs (21)-(26)


def _ep_inf_at(T, A, C, Q, snr_avg, alpha, delta, R=None) -> np.ndarray:
    """E P∞ (eq. 20) at the threshold Υ_T = T: μ_ave and σ²_n,ave of eqs (15)–(16)."""
    return ep_inf(A, C, Q, float(mu_ave(T, snr_avg)), float(sigma2_n_ave(T, snr_avg, alpha, delta)), R)


def _objective_value(kind: str, X) -> float:
    """‖X‖₂ (kind 'norm', eq. 21) or log det X (kind 'det', eq. 22); inf where X is unbounded."""
    if not np.all(np.isfinite(X)):
        return math.inf
    if kind == "norm":
        return spectral_norm(X)
    sign, logdet = np.linalg.slogdet(X)
    return logdet if sign > 0 else math.inf


def _objective(kind: str, A, C, Q, snr_avg, alpha, delta, R=None):
    def f(T):
        return _objective_value(kind, _ep_inf_at(T, A, C, Q, snr_avg, alpha, delta, R))

    return f


def optimal_threshold(kind: str, A, C, Q, snr_avg: float, alpha: float, delta: float, R=None,
                      grid: int = 400, xtol: float = 1e-9) -> tuple[float, float]:
    """Υ_T minimizing ‖E P∞‖ (kind='norm', eq. 21) or det E P∞ (kind='det', eq. 22) over the stable range.

    Grid scan over [0, Υ_T,max) then a bounded Brent refinement around the best grid point.
    Returns (Υ_T,opt, objective at the optimum: ‖E P∞‖ or log det E P∞).
    """
    return optimal_thresholds((kind,), A, C, Q, snr_avg, alpha, delta, R, grid, xtol)[kind]


def optimal_thresholds(kinds, A, C, Q, snr_avg: float, alpha: float, delta: float, R=None,
                       grid: int = 400, xtol: float = 1e-9) -> dict[str, tuple[float, float]]:
    """:func:`optimal_threshold` of each kind in ``kinds``, the grid's E P∞ solved once for all of them."""
    Tmax = max_stable_threshold(snr_avg, rho_max(A))
    hi = Tmax * (1 - 1e-9) if math.isfinite(Tmax) else 50.0 * snr_avg
    Ts = np.linspace(0.0, hi, grid)
    Xs = [_ep_inf_at(t, A, C, Q, snr_avg, alpha, delta, R) for t in Ts]
    out = {}
    for kind in kinds:
        f = _objective(kind, A, C, Q, snr_avg, alpha, delta, R)
        vals = np.array([_objective_value(kind, X) for X in Xs])
        i = int(np.argmin(vals))
        lo_b, hi_b = Ts[max(i - 1, 0)], Ts[min(i + 1, grid - 1)]
        res = optimize.minimize_scalar(f, bounds=(lo_b, hi_b), method="bounded", options={"xatol": xtol})
        out[kind] = (float(res.x), float(res.fun)) if res.fun <= vals[i] else (float(Ts[i]), float(vals[i]))
    return out


def theorem1_assumptions(A, C, Q, tol: float = 1e-12) -> dict[str, bool]:
    """Theorem 1 needs A symmetric, C = ς I, Q = q I. Returns which hold."""
    A, C, Q = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, C, Q))

    def scalar_identity(X):
        return X.shape[0] == X.shape[1] and np.allclose(X, X[0, 0] * np.eye(X.shape[0]), atol=tol, rtol=0)

    return {"A_symmetric": bool(np.allclose(A, A.T, atol=tol, rtol=0)),
            "C_is_scalar_identity": bool(scalar_identity(C)),
            "Q_is_scalar_identity": bool(scalar_identity(Q))}


def eq24_residual(T, snr_avg, alpha, delta, rho, varsigma, q):
    """LHS − RHS of eq. (24): μ_ave + σ²_n,norm + ς² q /(ρ² σ_n²(Υ_T)) − ρ^{-2}."""
    s = sigma2_n(T, alpha, delta)
    return mu_ave(T, snr_avg) + sigma2_n_ave(T, snr_avg, alpha, delta) / s + varsigma**2 * q / (rho**2 * s) - rho**-2


def eq26_residual(T, snr_avg, alpha, delta, eigs, varsigma, q):
    """LHS − RHS of eq. (26) with ρ_i² → |ρ_i|² (real for a symmetric A)."""
    r2 = np.abs(np.asarray(eigs)) ** 2
    s = float(sigma2_n(T, alpha, delta))
    mu = float(mu_ave(T, snr_avg))
    norm = float(sigma2_n_ave(T, snr_avg, alpha, delta)) / s
    return float(np.sum(r2 / (1 - r2 * mu)) - np.sum(1.0 / (norm + q * varsigma**2 / (s * r2))))


def eq26_residuals(Ts, snr_avg, alpha, delta, eigs, varsigma, q) -> np.ndarray:
    """:func:`eq26_residual` at every threshold of the array ``Ts`` (the same operations elementwise, the sums
    over the eigenvalues in the same order)."""
    r2 = (np.abs(np.asarray(eigs)) ** 2)[:, None]
    Ts = np.asarray(Ts, dtype=float)
    s = sigma2_n(Ts, alpha, delta)
    mu = mu_ave(Ts, snr_avg)
    norm = sigma2_n_ave(Ts, snr_avg, alpha, delta) / s
    return np.sum(r2 / (1 - r2 * mu), axis=0) - np.sum(1.0 / (norm + q * varsigma**2 / (s * r2)), axis=0)


def _root_in_stable_range(g, Tmax, n=4000, scan=None):
    """Sign changes of g on (0, Tmax) that are roots (not the pole at the stability edge). ``scan``: g on an
    array of thresholds at once (the scan's values; the roots are refined with g)."""
    hi = Tmax * (1 - 1e-7) if math.isfinite(Tmax) else 1e3
    Ts = np.linspace(0.0, hi, n)
    v = np.asarray(scan(Ts), dtype=float) if scan is not None else np.array([g(t) for t in Ts])
    roots = []
    for i in np.nonzero(np.diff(np.sign(v)) != 0)[0]:
        if np.isfinite(v[i]) and np.isfinite(v[i + 1]):
            r = optimize.brentq(g, Ts[i], Ts[i + 1], xtol=1e-12, rtol=1e-14)
            if abs(g(r)) < 1e-6 * (1 + abs(v[i]) + abs(v[i + 1])):
                roots.append(float(r))
    return roots


def eq24_root(snr_avg, alpha, delta, A, varsigma, q) -> float:
    """Υ*_T1 of eq. (24) in the stable range, or 0 when there is no positive root (eq. 23). NaN if several."""
    rho = rho_max(A)
    roots = _root_in_stable_range(lambda t: float(eq24_residual(t, snr_avg, alpha, delta, rho, varsigma, q)),
                                  max_stable_threshold(snr_avg, rho),
                                  scan=lambda Ts: eq24_residual(Ts, snr_avg, alpha, delta, rho, varsigma, q))
    if not roots:
        return 0.0
    return roots[0] if len(roots) == 1 else math.nan


def eq26_root(snr_avg, alpha, delta, A, varsigma, q) -> float:
    """Υ*_T2 of eq. (26) in the stable range (root, not the pole at μ ρ_max² = 1), else 0 (eq. 25)."""
    eigs = np.linalg.eigvals(np.atleast_2d(A))
    rho = rho_max(A)
    Tmax = max_stable_threshold(snr_avg, rho)
    g = lambda t: eq26_residual(t, snr_avg, alpha, delta, eigs, varsigma, q)  # noqa: E731
    roots = _root_in_stable_range(g, Tmax, scan=lambda Ts: eq26_residuals(Ts, snr_avg, alpha, delta, eigs, varsigma, q))
    if not roots:
        return 0.0
    return roots[0] if len(roots) == 1 else math.nan


# --------------------------------------------------------------------------- Theorem 4, eqs (50)-(64)

_ASYMPTOTIC_FROM = 600.0


def scaled_exp1(x):
    """Π(x) = eˣ E₁(x) (Lemma 8), finite for all x > 0.

    For x < 600 the product exp(x)·E₁(x) is accurate (both factors to ~1e-15 relative and
    far from over/underflow); beyond, the asymptotic series Σ_{n<12} (−1)ⁿ n!/x^{n+1}
    (truncation error < 12!/x^{13} ≈ 4e-28 relative at x = 600).
    """
    x = np.asarray(x, dtype=float)
    out = np.empty_like(x)
    small = x < _ASYMPTOTIC_FROM
    xs = x[small]
    out[small] = np.exp(xs) * special.exp1(xs)
    xl = x[~small]
    if xl.size:
        term = 1.0 / xl
        acc = term.copy()
        for n in range(1, 12):
            term = -term * n / xl
            acc += term
        out[~small] = acc
    return out if out.ndim else float(out)


def theorem4_coefficients(a: float, varpi: float, beta: float, k: int) -> np.ndarray:
    """B[i, k] for i = 0..k from eq. (57): B[0,0] = a² ϖ β; B[i,k] = B[i−1,k−1]/ξ_i (i ≥ 1),
    B[0,k] = −Σ_z B[z,k−1]/ξ_{z+1}, ξ_i = 1 − a^{−2i}."""
    if not abs(a) > 1:
        raise ValueError(f"Theorem 4 needs |a| > 1, got a = {a}")
    B = np.array([a * a * varpi * beta])
    for m in range(1, k + 1):
        xi = 1.0 - a ** (-2.0 * np.arange(1, m + 1))   # ξ_1..ξ_m
        new = np.empty(m + 1)
        new[1:] = B / xi
        new[0] = -np.sum(B / xi)
        B = new
    return B


def theorem4_mean(a: float, beta: float, snr_avg: float, P0: float, k_max: int) -> np.ndarray:
    """E P[k] for k = 0..k_max by eq. (56): E P[k+1] = Σ_i B[i,k] Π(ϖβ/(a^{2i} P[0])), ϖ = 1/Υ_ave.

    Scenario 3 with Υ_T = 0, N = 1, A = a > 1, C = 1, Q = R = 0 and σ_n² = β/Υ (eq. 50).
    """
    varpi = 1.0 / snr_avg
    out = np.empty(k_max + 1)
    out[0] = P0
    for k in range(k_max):
        B = theorem4_coefficients(a, varpi, beta, k)
        x = varpi * beta / (a ** (2.0 * np.arange(k + 1)) * P0)
        out[k + 1] = float(np.sum(B * scaled_exp1(x)))
    return out


def theorem4_step(P, snr, a: float, beta: float):
    """One step of eq. (51): P[k+1] = a² β P / (β + Υ P)."""
    return a * a * beta * P / (beta + snr * P)


def theorem4_quadrature(a: float, beta: float, snr_avg: float, P0: float, k: int) -> float:
    """E P[k] for k = 1 or 2 by (nested) quadrature of eq. (51) over exponential Υ — independent of eq. (56)."""
    lam = 1.0 / snr_avg
    if k == 1:
        f = lambda y: theorem4_step(P0, y, a, beta) * lam * math.exp(-lam * y)  # noqa: E731
        return integrate.quad(f, 0, np.inf, epsabs=0, epsrel=1e-11, limit=400)[0]
    if k == 2:
        def inner(y0):
            P1 = theorem4_step(P0, y0, a, beta)
            # E over Υ[1] of a²βP1/(β+Υ P1) in closed form would reuse Lemma 7; integrate instead.
            g = lambda y1: theorem4_step(P1, y1, a, beta) * lam * math.exp(-lam * y1)  # noqa: E731
            return integrate.quad(g, 0, np.inf, epsabs=0, epsrel=1e-11, limit=400)[0] * lam * math.exp(-lam * y0)
        return integrate.quad(inner, 0, np.inf, epsabs=0, epsrel=1e-10, limit=400)[0]
    raise ValueError("theorem4_quadrature supports k = 1 or 2")


# --------------------------------------------------------------------------- Jakes correlation, eq. (65)

SPEED_OF_LIGHT = 299_792_458.0
MPH = 0.44704  # m/s


def doppler_hz(speed_mps: float, carrier_hz: float) -> float:
    """f_D = s_mob F_c / c (eq. 65)."""
    return speed_mps * carrier_hz / SPEED_OF_LIGHT


def jakes_autocorr(lags, doppler: float, dt: float):
    """E h[t] h*[t−k] / E|h|² = J₀(2π f_D k dt) (eq. 65)."""
    return special.j0(2 * np.pi * doppler * dt * np.asarray(lags, dtype=float))


# --------------------------------------------------------------------------- references of the generic metrics
#
# Providers for ``analysis.references`` (netkf_cli/analysis/references.py): plain numbers in, rows out.
# netkf's time base: the receiver starts from P_{0|0} = system.P0; ``predicted`` at step k is P_{k+1|k},
# the paper's P[k] started from P[0] = P_{1|0} = A P0 Aᵀ + Q; ``filtered`` at k is P_{k|k}.


def _snr_linear(snr: dict) -> float:
    """An SNR dict {value, unit} (a channel's or an estimator's model_dump) → linear."""
    v = float(snr["value"])
    return float(db_to_linear(v)) if snr["unit"] == "dB" else v


def _noise_ab(noise: dict) -> tuple[float, float] | None:
    """(α, δ) of a ``ber`` noise dict, None for any other model."""
    if noise.get("model") != "ber":
        return None
    if noise.get("alpha") is not None:
        return float(noise["alpha"]), float(noise["delta"])
    return noise_params_from_bits(int(noise["N_p"]), float(noise["Delta"]))


def _mats(system):
    return tuple(np.atleast_2d(np.asarray(getattr(system, x), dtype=float)) for x in ("A", "C", "Q", "R"))


def _p00(system, A, Q):
    """P_{0|0} (system.P0; None = P̄, the steady state: refused, the receivers' closed forms need a start)."""
    if system.P0 is None:
        return None
    return np.atleast_2d(np.asarray(system.P0, dtype=float))


def _steps(point) -> tuple[str, list[int]]:
    """How the metric reads time: ('average', ks) for time_average over k in (burn_in, horizon], ('each', ks)
    for mean_vs_time (one row per k; no rows without the horizon), ('stationary', []) for a time_average whose
    horizon the point does not carry (the k → ∞ limit then; exact only once the burn-in has forgotten P0)."""
    m = point.metric
    mc = getattr(point, "montecarlo", None) or {}
    mc = mc if isinstance(mc, dict) else mc.model_dump()
    H = mc.get("horizon", getattr(point, "horizon", None))
    burn = mc.get("burn_in", getattr(point, "burn_in", 0)) or 0
    if m.get("kind") == "time_average":
        if m.get("at") is not None:  # the statistic at one step k (no time average)
            return "average", [int(m["at"])]
        return ("average", list(range(int(burn) + 1, int(H) + 1))) if H else ("stationary", [])
    if not H:  # per-step rows need the steps: none until the point carries the horizon
        return "each", []
    return "each", list(range(1, int(H) + 1))


def _norm_of_mean(point) -> bool:
    """Whether the metric reports ‖E P̄‖₂ (time_average ``statistic: norm_of_mean``) rather than E tr P̄."""
    return point.metric.get("statistic") == "norm_of_mean"


def _paths(pred: np.ndarray, filt: np.ndarray, mode: str, ks: list[int], quantities,
           norm: bool = False) -> list[tuple[str, int | None, float]]:
    """(quantity, k or None, tr) rows from per-step mean matrices pred[k] = E P_{k+1|k}, filt[k] = E P_{k|k};
    with ``norm`` (time_average's norm_of_mean) the spectral norm of the mean matrix over ks instead of its
    trace: ‖E P̄‖₂, e.g. ‖E P[300]‖ of Fig. 6 (eq. 21's norm at a finite k)."""
    out = []
    if norm:
        mats = {"predicted": pred, "filtered": filt}
        for q in quantities:
            if q in mats and mode in ("average", "stationary"):
                with np.errstate(over="ignore", invalid="ignore"):
                    out.append((q, None, spectral_norm(np.mean(mats[q][ks or [0]], axis=0))))
        return out
    with np.errstate(over="ignore", invalid="ignore"):
        tr = {"predicted": np.trace(pred, axis1=1, axis2=2), "filtered": np.trace(filt, axis1=1, axis2=2)}
    for q in quantities:
        if q not in tr:
            continue
        if mode in ("average", "stationary"):  # stationary: the arrays hold the k → ∞ limit at index 0
            out.append((q, None, float(np.mean(tr[q][ks or [0]]))))
        else:
            out.extend((q, k, float(tr[q][k])) for k in ks)
    return out


def _rows(series: str, label: str, items, extra=None) -> list[dict]:
    """One reference row per (quantity, k, value); ``extra`` e.g. {statistic: norm_of_mean}."""
    rows = []
    for q, k, v in items:
        r = dict(series=series, value=v, estimator=label, quantity=q, **(extra or {}))
        if k is not None:
            r["k"] = k
        rows.append(r)
    return rows


def _threshold(e: dict, channel: dict) -> float | None:
    """A receiver's Υ_T (linear): its own ``threshold``, else the channel's; None for any other estimator."""
    if e.get("kind") != "receiver":
        return None
    T = e.get("threshold") or channel.get("threshold")
    return None if T is None else _snr_linear(T)


def _iid_fading(point) -> bool:
    ch = point.channel
    return bool(ch) and "snr_avg" in ch and ch.get("correlation", {}).get("model", "iid") == "iid"


def scenario2_exact(point) -> list[dict]:
    """Mostofi & Murray 2009, eqs (14)/(20): exact E tr P of receiver scenario 2 (invertible C, ber noise, i.i.d. Υ).

    Stationary (a time_average whose point carries no horizon): E P[∞] of eq. (20), ∞ beyond the stability
    limit μ ρ_max² ≥ 1 (eq. 19). With the horizon (and per k for mean_vs_time), eq. (14):
    E P_{k+1|k} = μ A E P_{k|k−1} Aᵀ + Θ, Θ = Q + A C⁻¹(σ²_n,ave I + (1 − μ) R) C⁻ᵀ Aᵀ (eqs 14, 38), from
    P_{1|0} = A P0 Aᵀ + Q; E P_{k|k} = μ E P_{k|k−1} + C⁻¹(σ²_n,ave I + (1 − μ) R) C⁻ᵀ. μ = μ_ave(Υ_T)
    (eq. 15), σ²_n,ave (eq. 16). Rows per scenario-2 receiver; none where the form does not apply."""
    if not _iid_fading(point):
        return []
    ab = _noise_ab(point.channel.get("noise", {}))
    A, C, Q, R = _mats(point.system)
    P00 = _p00(point.system, A, Q)
    if ab is None or P00 is None or C.shape[0] != C.shape[1] or abs(np.linalg.det(C)) < 1e-12:
        return []
    Ya = _snr_linear(point.channel["snr_avg"])
    mode, ks = _steps(point)
    K = max(ks, default=0)
    Ci = np.linalg.inv(C)
    rows = []
    for e, lab in zip(point.estimators, point.labels):
        T = _threshold(e, point.channel)
        if T is None or e.get("scenario") != 2:
            continue
        mu, s2 = float(mu_ave(T, Ya)), float(sigma2_n_ave(T, Ya, *ab))
        Z = Ci @ (s2 * np.eye(C.shape[0]) + (1 - mu) * R) @ Ci.T
        if mode == "stationary":  # eq. (20); ∞ at or beyond the stability limit μ ρ_max² ≥ 1 (eq. 19)
            stable = mu * rho_max(A) ** 2 < 1
            pred = (ep_inf(A, C, Q, mu, s2, R) if stable else np.full(A.shape, np.inf))[None]
            filt = mu * pred + Z
            series = "scenario 2, exact E P[∞] (eq. 20)"
        else:
            pred = ep_recursion(A, C, Q, mu, s2, A @ P00 @ A.T + Q, K, R)          # pred[k] = E P_{k+1|k}
            filt = np.concatenate([P00[None], mu * pred[:-1] + Z])                # filt[k] = E P_{k|k}
            series = "scenario 2, exact mean (eq. 14)"
        norm = _norm_of_mean(point)
        if norm:
            series = series.replace("E P[∞]", "‖E P[∞]‖").replace("exact mean", "exact ‖E P‖")
        rows += _rows(series, lab, _paths(pred, filt, mode, ks, point.quantities, norm),
                      {"statistic": "norm_of_mean"} if norm else None)
    return rows


def lemma5_lower_bound(point) -> list[dict]:
    """Mostofi & Murray 2009, Lemma 5 (eq. 32): E P₁ of scenario 1 with R = 0, a lower bound on every receiver.

    Stationary without the horizon: the fixed point X = μ A X Aᵀ + Q (∞ once μ ρ_max² ≥ 1).
    X_{k+1} = μ A X_k Aᵀ + Q from X = P_{1|0} (predicted), μ X_{k−1} for P_{k|k} (a kept packet's
    update is ⪰ 0 for any receiver, so E P_{k+1|k} ⪰ μ A E P_{k|k−1} Aᵀ + Q: the bound holds for any C
    and receivers 1, 2 and 3). Rows per receiver of scenario 3 (the lemma's case)."""
    if not _iid_fading(point):
        return []
    A, C, Q, R = _mats(point.system)
    P00 = _p00(point.system, A, Q)
    if P00 is None:
        return []
    Ya = _snr_linear(point.channel["snr_avg"])
    mode, ks = _steps(point)
    K = max(ks, default=0)
    rows = []
    for e, lab in zip(point.estimators, point.labels):
        T = _threshold(e, point.channel)
        if T is None or e.get("scenario") != 3:
            continue
        mu = float(mu_ave(T, Ya))
        if mode == "stationary":
            stable = mu * rho_max(A) ** 2 < 1
            pred = (solve_discrete_lyapunov(math.sqrt(mu) * A, Q) if stable else np.full(A.shape, np.inf))[None]
            filt = mu * pred
        else:
            pred = lower_bound_recursion(A, Q, mu, A @ P00 @ A.T + Q, K)
            filt = np.concatenate([P00[None], mu * pred[:-1]])
        norm = _norm_of_mean(point)  # E P ⪰ X in PSD order ⇒ ‖E P‖₂ = λ_max(E P) ≥ λ_max(X): a bound on the norm too
        rows += _rows("Lemma 5 lower bound (eq. 32)", lab, _paths(pred, filt, mode, ks, point.quantities, norm),
                      {"statistic": "norm_of_mean"} if norm else None)
    return rows


def _theorem4_case(point):
    """(a, β, Υ_ave, P[0] = P_{1|0}) when the point is Theorem 4's case, else None."""
    if not _iid_fading(point) or point.channel.get("noise", {}).get("model") != "inverse_snr":
        return None
    A, C, Q, R = _mats(point.system)
    P00 = _p00(point.system, A, Q)
    if A.shape != (1, 1) or P00 is None or abs(C[0, 0] - 1) > 0 or Q[0, 0] != 0 or not A[0, 0] > 1:
        return None
    a = float(A[0, 0])
    return a, float(point.channel["noise"]["beta"]), _snr_linear(point.channel["snr_avg"]), a * a * float(P00[0, 0])


def _theorem4_receivers(point):
    for e, lab in zip(point.estimators, point.labels):
        if e.get("scenario") == 3 and _threshold(e, point.channel) == 0:
            yield lab


def theorem4(point) -> list[dict]:
    """Mostofi & Murray 2009, Theorem 4 (eqs 56–57): E P[k] of scenario 3, Υ_T = 0, σ_n² = β/Υ, A = a > 1, C = 1, Q = 0.

    P[0] = P_{1|0} = a² P0; ``predicted`` at k is P[k] (eq. 56), ``filtered`` P_{k|k} = P[k]/a². R must be
    negligible (eq. 51 has R = 0; the system needs R > 0)."""
    case = _theorem4_case(point)
    if case is None:
        return []
    a, beta, Ya, Pstart = case
    mode, ks = _steps(point)
    if mode == "stationary":  # E P[k] settles within a few steps (eq. 51 contracts): k = 100 is its limit
        pred = theorem4_mean(a, beta, Ya, Pstart, 100)[-1:, None, None]
    else:
        pred = theorem4_mean(a, beta, Ya, Pstart, max(ks, default=0))[:, None, None]
    filt = pred / (a * a)  # P_{k|k} = (P_{k+1|k} − Q)/a², Q = 0
    rows = []
    for lab in _theorem4_receivers(point):
        rows += _rows("Theorem 4, eq. (56)", lab, _paths(pred, filt, mode, ks, point.quantities))
    return rows


def theorem4_quadrature_rows(point) -> list[dict]:
    """Mostofi & Murray 2009, eq. (51) by nested quadrature for k = 1, 2 (an independent check of eq. 56)."""
    case = _theorem4_case(point)
    mode, ks = _steps(point)
    if case is None or mode != "each":
        return []
    a, beta, Ya, Pstart = case
    vals = {k: theorem4_quadrature(a, beta, Ya, Pstart, k) for k in (1, 2) if k in ks}
    rows = []
    for lab in _theorem4_receivers(point):
        for q in point.quantities:
            if q in ("predicted", "filtered"):
                rows += [dict(series="nested quadrature of eq. (51)", value=v / (a * a if q == "filtered" else 1.0),
                              estimator=lab, quantity=q, k=k) for k, v in vals.items()]
    return rows
