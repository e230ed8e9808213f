"""The per-step fast paths (issue 20.4) give the same bits as the loops they replaced, on random inputs."""

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.linalg import batched


def _matmul_loop(X, Y):
    """The entry-by-entry product batched.matmul had before (the reference order of the sums)."""
    a, b, r = X.shape
    c = Y.shape[1]
    out = np.empty((a, c, r), dtype=np.result_type(X, Y))
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(a):
            for k in range(c):
                acc = X[i, 0] * Y[0, k]
                for j in range(1, b):
                    acc += X[i, j] * Y[j, k]
                out[i, k] = acc
    return out


def _left_loop(A, P):
    """batched.left before its pattern cache."""
    p, n = A.shape
    out = np.empty((p,) + P.shape[1:], dtype=np.result_type(A, P))
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(p):
            nz = [(j, A[i, j]) for j in range(n) if A[i, j] != 0.0]
            if not nz:
                out[i] = 0.0
                continue
            j0, a0 = nz[0]
            if a0 == 1.0:
                out[i] = P[j0]
            else:
                np.multiply(P[j0], a0, out=out[i])
            for j, a in nz[1:]:
                out[i] += P[j] if a == 1.0 else a * P[j]
    return out


def _wild(rng, shape):
    """Normal entries over 20 decades, with some inf / nan / 0 (the overflowed runs a filter carries)."""
    x = rng.standard_normal(shape) * 10.0 ** rng.integers(-10, 10, shape)
    flat = x.reshape(-1)
    if flat.size == 0:
        return x
    k = max(1, flat.size // 20)
    flat[rng.integers(0, flat.size, k)] = np.inf
    flat[rng.integers(0, flat.size, k)] = np.nan
    flat[rng.integers(0, flat.size, k)] = 0.0
    return x


@pytest.mark.parametrize("seed", range(6))
def test_matmul_bits_equal_the_entry_loop(seed):
    rng = np.random.default_rng(seed)
    for a in (1, 2, 3, 4):
        for b in (1, 2, 3, 4):
            for c in (1, 2, 4):
                r = int(rng.integers(1, 40))
                X, Y = _wild(rng, (a, b, r)), _wild(rng, (b, c, r))
                out = batched.matmul(X, Y)
                ref = _matmul_loop(X, Y)
                assert out.shape == ref.shape and out.dtype == ref.dtype
                assert np.array_equal(out, ref, equal_nan=True)
                # views (a transposed P, as right() and the Joseph form pass) too
                Xt = np.ascontiguousarray(X.swapaxes(0, 1)).swapaxes(0, 1)
                assert np.array_equal(batched.matmul(Xt, Y), ref, equal_nan=True)


@pytest.mark.parametrize("seed", range(6))
def test_left_with_cached_pattern_bits_equal_the_loop(seed):
    rng = np.random.default_rng(100 + seed)
    for p in (1, 2, 3, 5):
        for n in (1, 2, 4, 8):
            A = rng.choice([0.0, 1.0, -2.0, 0.5, rng.standard_normal()], size=(p, n))
            P = _wild(rng, (n, 3, int(rng.integers(1, 30))))
            for _ in range(2):  # the second call reads the cached pattern
                assert np.array_equal(batched.left(A, P), _left_loop(A, P), equal_nan=True)
            B = A.copy()
            B[0, 0] = 3.0 if A[0, 0] != 3.0 else 0.0  # same shape, other entries: another pattern
            assert np.array_equal(batched.left(B, P), _left_loop(B, P), equal_nan=True)
            assert np.array_equal(batched.right(P.swapaxes(0, 1), A.T),
                                  _left_loop(A, P).swapaxes(0, 1), equal_nan=True)


def test_tri_bits_equal_the_fancy_index_form():
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 4, 6):
        i, j = np.triu_indices(n)
        for r in (0, 1, 17):
            P = _wild(rng, (n, n, r))
            with np.errstate(over="ignore", invalid="ignore"):
                ref = np.ascontiguousarray(0.5 * (P[i, j] + P[j, i]))
            for Q in (P, P.swapaxes(0, 1).copy().swapaxes(0, 1), np.asfortranarray(P)):
                T = engine._tri(Q)
                assert T.flags.c_contiguous and np.array_equal(T, ref, equal_nan=True)


def test_step_lookup_is_list_index():
    red = engine.MomentReducer([3, 5, 5, 9])
    assert [engine._step_pos(red, k) for k in (3, 5, 9, 4)] == [0, 1, 3, None]
    assert engine._step_pos(red, np.int64(9)) == 3
    with pytest.raises(ValueError):
        engine._step_index(red, 4)
    red.steps = [4, 3]  # a new steps list is seen
    assert engine._step_index(red, 4) == 0 and engine._step_pos(red, 9) is None
