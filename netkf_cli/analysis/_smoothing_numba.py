"""Compiled scalar evaluation of the backward enumeration of :mod:`netkf_cli.analysis.smoothing` (optional:
imported by ``_Batch.evaluate`` and ``exact_mean`` only where numba is importable). The same IEEE operations in
the same order as the numpy path (``_Batch.cov_step`` / ``_Batch.info_step`` / ``_Batch.smoothed`` for
n = m = 1), per node: the same bits (tested)."""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True, error_model="numpy")
def evaluate_scalar(bits, pst, a2, c2, q, r, crc, P, Y):
    """For each node i (row of ``bits`` (B, j), oldest first) from P = P*, Y = 0: per step γ,
    P ← a² (γ ? r/(c² + r/P) : P) + q (the Riccati map g / h) and, in information form,
    Z = (Y + γ c²/r)/a², Y ← Z/(1 + qZ); P[i], Y[i] the ends Φ_s(P*) and (Φ_s(∞))⁻¹. The step loop
    outside, the node loop inside (each node's operations unchanged): the nodes' divisions pipeline."""
    evaluate_scalar_cols(np.ascontiguousarray(bits.T), pst, a2, c2, q, r, crc, P, Y)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def evaluate_scalar_cols(bt, pst, a2, c2, q, r, crc, P, Y):
    """:func:`evaluate_scalar` of the nodes given as the columns of ``bt`` (j, B) (row 0 the oldest step)."""
    j, B = bt.shape
    for i in range(B):
        P[i] = pst
        Y[i] = 0.0
    for c in range(j):
        bc = bt[c]
        for i in range(B):
            g = float(bc[i])
            p = P[i]
            upd = r / (c2 + r / p) if g > 0 else p
            P[i] = a2 * upd + q
            z = (Y[i] + g * crc) / a2
            Y[i] = z / (1.0 + q * z)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def expect_level_scalar(P, Y, a2, c2, q, r, crc, Js, wts, LO, HI, FIN, gap):
    """One level of ``exact_mean``'s enumeration (``smoothing._expect_bounded``) for n = m = 1, per node i with
    ends P[i] = Φ_s(P*), Y[i] = (Φ_s(∞))⁻¹: the bracket (LO[k, i], HI[k, i]) of φ_0 = g (a² r/(c² + r/P) + q;
    a²/(Y + c²/r) + q) and of φ_{1+f} = (P⁻¹ + J_f)⁻¹ (P/(1 + P J_f), 1/J_f at P = ∞, P itself at J_f = 0;
    1/(Y + J_f)), FIN[k, i] = HI finite, and gap[i] = Σ_k wts[k] (FIN ? HI − LO : ∞), summed over k in order
    (the φ loop outside, the node loop inside: the nodes' divisions pipeline)."""
    B = P.shape[0]
    F = Js.shape[0]
    w0 = wts[0]
    for i in range(B):
        lo = a2 * (r / (c2 + r / P[i])) + q
        hi = a2 / (Y[i] + crc) + q
        fin = np.isfinite(hi)
        LO[0, i] = lo
        HI[0, i] = hi
        FIN[0, i] = fin
        gap[i] = 0.0 + w0 * ((hi - lo) if fin else np.inf)
    for f in range(F):
        J = Js[f]
        wf = wts[1 + f]
        at_inf = 1.0 / J
        LOf, HIf, FINf = LO[1 + f], HI[1 + f], FIN[1 + f]
        for i in range(B):  # branch-free (selects): the compiler vectorizes it
            p = P[i]
            lo = p if J == 0.0 else (at_inf if np.isinf(p) else p / (1.0 + p * J))
            hi = 1.0 / (Y[i] + J)
            fin = np.isfinite(hi)
            LOf[i] = lo
            HIf[i] = hi
            FINf[i] = fin
            gap[i] = gap[i] + wf * ((hi - lo) if fin else np.inf)
