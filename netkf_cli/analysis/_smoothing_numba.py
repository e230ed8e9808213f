"""Compiled scalar evaluation of the backward enumeration of :mod:`netkf_cli.analysis.smoothing` (optional:
imported by ``_Batch.evaluate`` only where numba is importable). The same IEEE operations in the same order as the
numpy path (``_Batch.cov_step`` / ``_Batch.info_step`` for n = m = 1), one node at a time: the same bits (tested)."""

from __future__ import annotations

import numba as nb


@nb.njit(cache=True, nogil=True, error_model="numpy")
def evaluate_scalar(bits, pst, a2, c2, q, r, crc, P, Y):
    """For each node i (row of ``bits`` (B, j), oldest first) from P = P*, Y = 0: per step γ,
    P ← a² (γ ? r/(c² + r/P) : P) + q (the Riccati map g / h) and, in information form,
    Z = (Y + γ c²/r)/a², Y ← Z/(1 + qZ); P[i], Y[i] the ends Φ_s(P*) and (Φ_s(∞))⁻¹."""
    B, j = bits.shape
    for i in range(B):
        p = pst
        y = 0.0
        for c in range(j):
            g = float(bits[i, c])
            if g > 0:
                upd = r / (c2 + r / p)
            else:
                upd = p
            p = a2 * upd + q
            z = (y + g * crc) / a2
            y = z / (1.0 + q * z)
        P[i] = p
        Y[i] = y
