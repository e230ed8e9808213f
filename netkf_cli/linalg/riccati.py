"""Riccati maps and their fixed points, Shi, Xie & Murray 2009, Sec. 2.3 and 3.1.

    h(X)  = A X Aᵀ + Q
    g(X)  = h(X) − A X Cᵀ (C X Cᵀ + R)⁻¹ C X Aᵀ          (prediction Riccati map)
    g̃(X)  = X − X Cᵀ (C X Cᵀ + R)⁻¹ C X                  (measurement update)
    P*    = g(P*)  (the stabilizing DARE solution),  P̄ = g̃(P*)

All maps accept a single ``(n, n)`` matrix; :func:`psd_leq` is batched over leading axes.
Linear systems are solved with ``solve``, never ``inv``; results are symmetrized.
"""

from __future__ import annotations

import weakref

import numpy as np

from netkf_cli.linalg import kalman
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.tolerances import CRITICAL_RHO_TOL, PSD_TOL


def sym(X: np.ndarray) -> np.ndarray:
    return (X + np.swapaxes(X, -1, -2)) / 2


def h(X: np.ndarray, s: LinearSystem) -> np.ndarray:
    """h(X) = A X Aᵀ + Q (Sec. 2.3)."""
    return sym(s.A @ X @ s.A.T + s.Q)


def gtilde(X: np.ndarray, s: LinearSystem) -> np.ndarray:
    """g̃(X) = X − X Cᵀ (C X Cᵀ + R)⁻¹ C X (Sec. 2.3): the Kalman core's update on one matrix."""
    return kalman.one(kalman.update, X, s.C, s.R)


def g(X: np.ndarray, s: LinearSystem) -> np.ndarray:
    """g(X) = h(g̃(X)) = A X Aᵀ + Q − A X Cᵀ (C X Cᵀ + R)⁻¹ C X Aᵀ (Sec. 2.3; h∘g̃ = g)."""
    return h(gtilde(X, s), s)


_PSTAR: "weakref.WeakKeyDictionary[LinearSystem, np.ndarray]" = weakref.WeakKeyDictionary()


def pstar(s: LinearSystem) -> np.ndarray:
    """P*, the unique PSD solution of g(X) = X (steady-state prediction covariance, Sec. 3.1).

    Solved by :func:`netkf_cli.linalg.kalman.dare` (scipy on the dual problem, its answer checked); memoized
    per (frozen) system, since the bounds ask for it at every grid point.
    """
    cached = _PSTAR.get(s)
    if cached is not None:
        return cached.copy()
    P = _pstar(s)
    _PSTAR[s] = P
    return P.copy()


def _pstar(s: LinearSystem) -> np.ndarray:
    try:
        P = kalman.dare(s.A, s.C, s.Q, s.R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        if is_detectable(s.A, s.C) and is_detectable(s.A.T, s.Q):  # (A, √Q) stabilizable ⇔ (Aᵀ, Q) detectable
            scale = [float(np.max(np.abs(X))) for X in (s.A, s.C, s.Q, s.R) if np.any(X)]
            why = (f"(A, C) is detectable and (A, √Q) stabilizable, so the solver failed numerically: the entries of "
                   f"A, C, Q, R span {max(scale):.3g} / {min(scale):.3g}; rescale the system (state or output units)")
        else:
            why = "(A, C) must be detectable and (A, √Q) stabilizable"
        raise ConfigError.at("system", f"the Riccati equation g(X) = X has no stabilizing solution ({exc}); {why}") \
            from None
    return sym(P)


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
        if abs(sig) < 1 - CRITICAL_RHO_TOL:
            continue
        _, sv, Vh = np.linalg.svd(A - sig * np.eye(n))
        null = Vh[(sv <= tol * max(1.0, sv[0])), :].conj().T if sv.size else np.eye(n)
        if null.shape[1] == 0:  # numerically no eigenvector (should not happen for an eigenvalue): smallest direction
            null = Vh[-1:, :].conj().T
        s = np.linalg.svd(C @ null, compute_uv=False)
        if (s > tol * cn).sum() < null.shape[1]:
            return False
    return True


def initial_covariance(s: LinearSystem) -> np.ndarray:
    """P_{0|0}: ``system.P0``, or P̄ (the steady-state filtered covariance with every packet received)
    when it is unset/steady — the one meaning of P0 in netkf, for every estimator."""
    if s.P0 is not None:
        return np.asarray(s.P0, dtype=float)
    try:
        return pbar(s)
    except ConfigError as exc:
        raise ConfigError.at("system.P0", "unset (or steady), P0 is P̄, the steady-state filtered covariance, which "
                                          f"does not exist here: {exc.problems[0].message}; give P0 as a matrix"
                             ) from None


def pbar(s: LinearSystem) -> np.ndarray:
    """P̄ = g̃(P*), the steady-state filtering covariance (Sec. 3.1)."""
    return gtilde(pstar(s), s)


def h_power(X: np.ndarray, s: LinearSystem, t: int) -> np.ndarray:
    """hᵗ(X), t ≥ 0."""
    for _ in range(t):
        X = h(X, s)
    return X


def psd_leq(X: np.ndarray, M: np.ndarray, tol: float = PSD_TOL) -> np.ndarray:
    """PSD order X ≤ M, i.e. min eig(M − X) ≥ −tol·max(1, |M|). Batched over leading axes.

    Non-finite X (overflow in an unstable run) compares as *not* ≤ M.
    """
    X = np.asarray(X, dtype=float)
    M = np.asarray(M, dtype=float)
    D = M - X
    finite = np.all(np.isfinite(D), axis=(-1, -2))
    D = np.where(finite[..., None, None], D, 0.0)
    if D.shape[-1] == 1:
        emin = D[..., 0, 0]
    else:
        emin = np.linalg.eigvalsh(sym(D))[..., 0]
    scale = max(1.0, float(np.abs(M).max()))
    return finite & (emin >= -tol * scale)


def mbar(s: LinearSystem) -> np.ndarray:
    """M̄: covariance of the one-packet estimator that bounds P_k whenever a packet arrives.

    * C invertible: M̄ = C⁻¹ R C⁻ᵀ (Sec. 3.3, Remark 3.5).
    * Otherwise, when O₂ = [C; CA] is invertible and each packet carries (y_k, y_{k−1}):
      the estimator x̃_k = A·[CA; C]⁻¹·[y_k; y_{k−1}] of Appendix B (see :func:`mbar_appendix_b`).
    * Otherwise: a ConfigError naming the condition.
    """
    n, m = s.n, s.m
    if m == n and np.linalg.matrix_rank(s.C) == n:
        Cinv_R = np.linalg.solve(s.C, s.R)
        return sym(np.linalg.solve(s.C, Cinv_R.T).T)
    if 2 * m == n:
        O2 = np.vstack([s.C @ s.A, s.C])
        if np.linalg.matrix_rank(O2) == n:
            return mbar_appendix_b(s)
    raise ConfigError.at(
        "system.C",
        f"M̄ needs C invertible (n×n with rank n) or, per Appendix B, [C; CA] square and invertible; "
        f"got C of shape {m}×{n} (rank {np.linalg.matrix_rank(s.C)})",
    )


def mbar_appendix_b(s: LinearSystem) -> np.ndarray:
    """M̄ for non-invertible C (Appendix B, Shi 2009), derived afresh.

    The packet at time k carries y_k and y_{k−1}. Write x_{k−1} = z. Then
    y_{k−1} = C z + v_{k−1}, y_k = C A z + C w_{k−1} + v_k, so with O = [CA; C] (invertible),
    ẑ = O⁻¹ [y_k; y_{k−1}] has error z − ẑ = −O⁻¹ η, η = [C w_{k−1} + v_k; v_{k−1}].
    The estimate x̃_k = A ẑ has error
        x_k − x̃_k = A(z − ẑ) + w_{k−1} = −A O⁻¹ η + w_{k−1},
    whose covariance is
        M̄ = A M₁ Aᵀ + Q − A O⁻¹ [CQ; 0] − [CQ; 0]ᵀ O⁻ᵀ Aᵀ,
        M₁ = O⁻¹ [[CQCᵀ + R, 0], [0, R]] O⁻ᵀ,
    exactly the printed formula (the cross term E[η wᵀ] = [CQ; 0]). The paper prints
    [CA; C]⁻¹ without the transpose on the right of M₁; the covariance needs O⁻ᵀ.
    """
    n, m = s.n, s.m
    O = np.vstack([s.C @ s.A, s.C])
    Z = np.zeros((m, m))
    Sigma = np.block([[s.C @ s.Q @ s.C.T + s.R, Z], [Z, s.R]])
    Oinv_S = np.linalg.solve(O, Sigma)
    M1 = np.linalg.solve(O, Oinv_S.T).T  # O⁻¹ Σ O⁻ᵀ
    CQ0 = np.vstack([s.C @ s.Q, np.zeros((m, n))])  # E[η wᵀ]
    cross = s.A @ np.linalg.solve(O, CQ0)
    return sym(s.A @ M1 @ s.A.T + s.Q - cross - cross.T)
