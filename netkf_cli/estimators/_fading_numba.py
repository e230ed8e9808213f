"""Compiled (numba) recursion of the fading receivers (Mostofi & Murray 2009) — imported only on demand.

The same recursion as :func:`netkf_cli.estimators.fading_receivers.correct` / ``predict`` (numpy
reference), written ONLY with the Kalman core's compiled primitives (:mod:`netkf_cli.linalg.kalman_numba`,
inlined): no gain or update of its own. One call advances every run through a block of T steps,
runs outside and time inside, each run's matrices held in small work arrays (design.md's compiled
layout); the keep decisions and σ_n² values are computed by numpy and passed in (same random numbers).

* ``mode 0`` — scenarios 1 and 3: ``kalman_numba.update`` with R + σ_n² I (scenario 1 passes
  σ_n² = 0); a run that meets a prior with tr P > ``limit`` (:class:`kalman.Rescue`) is flagged and
  its block redone by the kernel variant with the information form inline (rare);
* ``mode 1`` — scenario 2, invertible C: ``kalman_numba.joseph`` of the gain C⁻¹ (eq. 12);
* ``mode 2`` — scenario 2, general C: ``kalman_numba.gain`` of the filter's own covariance P_f with
  zero noise, the true covariance by ``joseph`` with R + σ_n² I, P_f by ``joseph`` with 0.

A dropped packet leaves P_{k|k} = P_{k|k−1}; then ``kalman_numba.predict``. A run in which a
non-finite value appears is flagged and its block redone on the numpy core, which owns what an
overflow means (:func:`kalman.clean_nonfinite`). With ``want_u`` the burst-conditioned
estimate U_{k|k} = μ U_{k|k−1} + (1 − μ) F(P_{k|k−1}, σ_u²), U_{k+1|k} = A U_{k|k} Aᵀ + Q is advanced
too (module doc of fading_receivers). Products are summed in index order (numpy's BLAS/einsum may
sum in another order): the backends agree to rounding, not bit for bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from netkf_cli.linalg import kalman_numba as kn

_opts = dict(cache=True, nogil=True, error_model="numpy")


def mode_of(rm) -> int:
    """0: scenarios 1/3; 1: scenario 2 with an invertible C; 2: scenario 2, general C."""
    if rm.scenario in (1, 3):
        return 0
    return 1 if rm.state_size() == 1 else 2


@njit(inline="always", **_opts)
def _copy(src, dst):
    n = src.shape[0]
    for i in range(n):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


@njit(inline="always", **_opts)
def _finite(X):
    """True iff every entry is finite (one branch per matrix: the sum is non-finite iff an entry is, up to
    an overflow of the sum itself at ~1e308, which is then treated as non-finite too)."""
    acc = 0.0
    for i in range(X.shape[0]):
        for j in range(X.shape[1]):
            acc += X[i, j]
    return acc - acc == 0.0


@njit(inline="never", **_opts)
def _set_inf(X):
    for i in range(X.shape[0]):
        for j in range(X.shape[1]):
            X[i, j] = np.inf


@njit(inline="always", **_opts)
def _noise(R, s2, Rz):
    """Rz = R + σ² I (the packet's noise: sensor noise plus communication noise, eqs 27–28)."""
    m = R.shape[0]
    for a in range(m):
        for b in range(m):
            Rz[a, b] = R[a, b] + (s2 if a == b else 0.0)


@njit(inline="always", **_opts)
def _kept0(P, F, s2, C, R, Kc, Z, limit, out_t, out_f, Rz, K, PCt, S, X, IKC, tmp):
    """Scenarios 1/3: the optimal update with R + σ² I. Returns True when the prior needs the rescue
    (tr P > limit or non-finite, :class:`kalman.Rescue`): the caller redoes that run with the numpy
    core (rare; keeping the information form out of the compiled hot loop keeps its work arrays in
    registers, ~2–3× faster)."""
    n = P.shape[0]
    _noise(R, s2, Rz)
    tr = 0.0
    for i in range(n):
        tr += P[i, i]
    kn.update(P, C, Rz, 1.0, out_t, PCt, S, X)
    return not (tr <= limit)


@njit(inline="always", **_opts)
def _kept0_rescue(P, s2, C, R, limit, out_t, Rz, PCt, S, X, W, Y, Rw, Cw, info):  # -> True: redo on numpy
    """:func:`_kept0` with the rescue inline (the kernel variant for the runs :func:`_kept0` flagged):
    a prior with tr P > limit is updated in information form (P⁻¹ + Cᵀ(R + σ² I)⁻¹C)⁻¹
    (``kalman_numba.information_update``; :class:`kalman.Rescue`), a non-finite prior gives inf."""
    n = P.shape[0]
    m = C.shape[0]
    _noise(R, s2, Rz)
    tr = 0.0
    for i in range(n):
        tr += P[i, i]
    if tr <= limit:
        kn.update(P, C, Rz, 1.0, out_t, PCt, S, X)
        return False
    if not _finite(P):  # the numpy core decides what an overflowed prior means (kalman.Rescue)
        return True
    _copy(Rz, Rw)
    _copy(C, Cw)
    kn.solve_inplace(Rw, Cw)  # (R + σ² I)⁻¹ C
    for i in range(n):
        for j in range(n):
            a = 0.0
            for q in range(m):
                a += C[q, i] * Cw[q, j]
            info[i, j] = a  # Cᵀ (R + σ² I)⁻¹ C
    kn.information_update(P, info, out_t, W, Y)
    return False


@njit(inline="always", **_opts)
def _kept1(P, F, s2, C, R, Kc, Z, limit, out_t, out_f, Rz, K, PCt, S, X, IKC, tmp):
    """Scenario 2, invertible C: Joseph form of the gain C⁻¹ with R + σ² I (eq. 12)."""
    _noise(R, s2, Rz)
    kn.joseph(P, Kc, C, Rz, 1.0, out_t, IKC, tmp)
    return False


@njit(inline="always", **_opts)
def _kept2(P, F, s2, C, R, Kc, Z, limit, out_t, out_f, Rz, K, PCt, S, X, IKC, tmp):
    """Scenario 2, general C: the noise-free gain of the filter's own F; Joseph forms of P (true noise) and F."""
    _noise(R, s2, Rz)
    kn.gain(F, C, Z, K, S, X)
    kn.joseph(P, K, C, Rz, 1.0, out_t, IKC, tmp)
    kn.joseph(F, K, C, Z, 1.0, out_f, IKC, tmp)
    return False


_KERNELS: dict = {}


def kernel(mode: int, n: int, m: int, rescue: bool = False):
    """The compiled block step for (mode, n, m): the sizes are closure constants, so every small loop of
    the inlined primitives has a constant trip count (unrolled by LLVM; ~6× the runtime-sized loops).
    ``rescue``: the variant with the information-form rescue inline (mode 0), run only on the runs the
    plain variant flagged (its dynamic pivoting would keep the hot loop's arrays out of registers).
    Cached on disk per key by numba."""
    key = (int(mode), int(n), int(m), bool(rescue))
    if key not in _KERNELS:
        _KERNELS[key] = _make(*key)
    return _KERNELS[key]


def _make(MODE, N, M, RESCUE):
    # (the sizes and the mode are int/bool closure constants — numba caches such closures on disk; a
    # function-valued closure variable would defeat the cache, so the mode is a branch on a constant)
    @njit(**_opts)
    def advance(keep, s2, s2u, separate_u, mu, want_u, A_, Q_, C_, R_, Kc_, limit, Pt, Pf, Ft, U, Uf, flags,
                rec, RecP, RecF, RecU, RecUf):
        """Advance every run b through the block: ``keep``/``s2``/``s2u`` (B, T) run-major; state RUN-MAJOR (B, n, n):
        ``Pt`` the true prior (in/out), ``Pf`` the filter's prior (mode 2), ``Ft`` the last P_{k|k} (out),
        ``U``/``Uf`` the burst-conditioned prior (in/out) and last U_{k|k} (out) when ``want_u``; ``flags``
        (B,) int8 out: 1 the run met a prior that needs the rescue (redo its block with the rescue variant),
        2 a non-finite value appeared (redo its block on the numpy core, which defines overflow).
        ``rec`` (T,) int: the slot r ≥ 0 of step t in the records (−1: not recorded); after step t the prior P,
        the last P_{k|k} and (``want_u``) U, U_{k|k} are copied to ``RecP``/``RecF``/``RecU``/``RecUf``[b, r]
        ((B, slots, n, n), run-major): one call serves every reported step of a block."""
        B, T = keep.shape
        n = N
        mode = MODE
        A = np.empty((N, N))
        Q = np.empty((N, N))
        C = np.empty((M, N))
        R = np.empty((M, M))
        Kc = np.empty((N, M))
        _copy(A_, A)
        _copy(Q_, Q)
        _copy(C_, C)
        _copy(R_, R)
        _copy(Kc_, Kc)
        P = np.empty((N, N))
        F = np.empty((N, N))
        Fl = np.empty((N, N))
        Kt = np.empty((N, N))
        Kf = np.empty((N, N))
        Ku = np.empty((N, N))
        Kuf = np.empty((N, N))
        Uv = np.empty((N, N))
        Ul = np.empty((N, N))
        tmp = np.empty((N, N))
        IKC = np.empty((N, N))
        Rz = np.empty((M, M))
        Z = np.zeros((M, M))
        S = np.empty((M, M))
        K = np.empty((N, M))
        PCt = np.empty((N, M))
        X = np.empty((M, N))
        W = np.empty((N, N))
        Y = np.empty((N, N))
        info = np.empty((N, N))
        Rw = np.empty((M, M))
        Cw = np.empty((M, N))
        for b in range(B):
            _copy(Pt[b], P)
            if mode == 2:
                _copy(Pf[b], F)
            if want_u:
                _copy(U[b], Uv)
            mb = mu[b] if want_u else 0.0
            for t in range(T):
                kp = keep[b, t]
                if kp or (want_u and not separate_u):
                    if MODE == 0 and RESCUE:
                        if _kept0_rescue(P, s2[b, t], C, R, limit, Kt, Rz, PCt, S, X, W, Y, Rw, Cw, info):
                            flags[b] = 2
                    elif MODE == 0:
                        if _kept0(P, F, s2[b, t], C, R, Kc, Z, limit, Kt, Kf, Rz, K, PCt, S, X, IKC, tmp):
                            flags[b] = max(flags[b], 1)
                    elif MODE == 1:
                        _kept1(P, F, s2[b, t], C, R, Kc, Z, limit, Kt, Kf, Rz, K, PCt, S, X, IKC, tmp)
                    else:
                        _kept2(P, F, s2[b, t], C, R, Kc, Z, limit, Kt, Kf, Rz, K, PCt, S, X, IKC, tmp)
                if want_u:
                    if separate_u:
                        if MODE == 0 and RESCUE:
                            if _kept0_rescue(P, s2u[b, t], C, R, limit, Ku, Rz, PCt, S, X, W, Y, Rw, Cw, info):
                                flags[b] = 2
                        elif MODE == 0:
                            if _kept0(P, F, s2u[b, t], C, R, Kc, Z, limit, Ku, Kuf, Rz, K, PCt, S, X, IKC, tmp):
                                flags[b] = max(flags[b], 1)
                        elif MODE == 1:
                            _kept1(P, F, s2u[b, t], C, R, Kc, Z, limit, Ku, Kuf, Rz, K, PCt, S, X, IKC, tmp)
                        else:
                            _kept2(P, F, s2u[b, t], C, R, Kc, Z, limit, Ku, Kuf, Rz, K, PCt, S, X, IKC, tmp)
                    else:
                        _copy(Kt, Ku)
                    for i in range(n):
                        for j in range(n):
                            Ul[i, j] = mb * Uv[i, j] + (1.0 - mb) * Ku[i, j]
                    if not _finite(Ul):
                        flags[b] = 2
                    kn.predict(Ul, A, Q, Uv, tmp)
                    if not _finite(Uv):
                        flags[b] = 2
                if kp:
                    _copy(Kt, Fl)
                else:
                    _copy(P, Fl)
                kn.predict(Fl, A, Q, P, tmp)
                if not _finite(P):
                    flags[b] = 2
                if mode == 2:
                    if kp:
                        kn.predict(Kf, A, Q, F, tmp)
                    else:
                        _copy(F, Kf)
                        kn.predict(Kf, A, Q, F, tmp)
                    if not _finite(F):
                        flags[b] = 2
                if flags[b] == 2:
                    break  # redone on the numpy core
                r = rec[t]
                if r >= 0:
                    _copy(P, RecP[b, r])
                    _copy(Fl, RecF[b, r])
                    if want_u:
                        _copy(Uv, RecU[b, r])
                        _copy(Ul, RecUf[b, r])
            _copy(P, Pt[b])
            if T > 0:
                _copy(Fl, Ft[b])
            if mode == 2:
                _copy(F, Pf[b])
            if want_u:
                _copy(Uv, U[b])
                if T > 0:
                    _copy(Ul, Uf[b])

    return advance
