"""Optional compiled (numba) backend of the delay-buffer covariance Monte Carlo (issue 9, item 4).

Same recursion as :class:`netkf_cli.estimators.buffered.BufferedMCKernel` (Prop. 3.1, covariance
only, one sample P_k at k = horizon per run), two ways to get the random numbers:

* ``backend: numba`` — the SAME uniforms the numpy kernel draws from the chunk's Generator
  (``horizon`` calls of ``rng.random(runs)`` = one ``(horizon, runs)`` draw, time-major). The MKF
  step is generated as straight-line code that performs, per run, exactly the floating-point
  operations of ``MKFBatch.step`` in the same order (zero coefficients skipped, unit coefficients
  aliased, closed-form 2×2 inverse, information form for scalars), compiled without fastmath and
  without FMA contraction, so every run's P_k is **bitwise equal** to the numpy reference and
  the sums Σ P_k, Σ P_k², Σ tr, Σ updates are computed by the same numpy code on the same
  arrays (bitwise equal too). ``count_leq`` uses an exact inertia test of M·I − P_k (LDLᵀ,
  n > 1) instead of LAPACK's λ_max: the two agree unless λ_max(P_k) is within a few ulps of a
  threshold. With ``threads > 1`` and a PCG64 stream the uniforms themselves are generated in
  parallel by ``PCG64.advance`` — the identical stream, split between threads.
* ``backend: numba_philox`` — uniforms from an in-kernel counter-based Philox4x32-10 generator
  (Salmon et al. 2011, Random123) keyed by two 32-bit words drawn from the chunk's Generator and
  counted by (run index in chunk, time step). Deterministic for a seed and chunking (any executor,
  any thread count), but a DIFFERENT stream than numpy's: statistically equivalent, not equal.

numba is an optional extra (``pip install 'netkf[fast]'``); this module imports without it and
raises :class:`NumbaUnavailable` only when a numba backend is actually requested.

Implementation: per system, the kernel source is generated (coefficients of A, C, Q, R baked in
as literals), written once to a content-addressed file in the netkf cache folder and compiled
with ``cache=True``, so later processes load the machine code from disk. Runs are processed in
blocks of ``BLOCK`` runs (``prange`` over blocks); inside a block the time loop is outer and the
run loop inner with the state in one L1-resident array (entry-major), which LLVM vectorizes.
"""

from __future__ import annotations

import hashlib
import importlib.util
import multiprocessing
import os
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from netkf_cli import riccati
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.buffered import overflow_limit
from netkf_cli.system import LinearSystem

NUMBA_BACKENDS = ("numba", "numba_philox")
BLOCK = None  # runs per block; None = 256, or 128 when the block state has > 8 rows (keeps it in L1)


def block_size(s: LinearSystem) -> int:
    rows = s.n * (s.n + 1) // 2 + 6
    return 256 if rows <= 8 else 128


class NumbaUnavailable(ConfigError):
    """A numba backend was requested but numba is not importable."""


def numba_available() -> bool:
    """True iff ``import numba`` works."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def require_numba():
    try:
        import numba
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise NumbaUnavailable.at(
            "estimator.backend",
            f"backend numba needs the optional extra: pip install 'netkf[fast]' (numba>=0.59); {exc}",
        ) from None
    return numba


def resolve_backend(backend: str, s: LinearSystem) -> str:
    """``auto`` → numba if importable and the system is supported (m ≤ 2), else numpy."""
    if backend == "auto":
        return "numba" if (numba_available() and s.m <= 2) else "numpy"
    if backend in NUMBA_BACKENDS:
        require_numba()
        if s.m > 2:
            raise ConfigError.at("estimator.backend",
                                 f"the numba backend supports m ≤ 2 outputs (closed-form S⁻¹), got m = {s.m}: "
                                 "use backend: numpy")
    return backend


# ---------------------------------------------------------------------------------------------
# Code generation: the exact operation sequence of MKFBatch.step, as straight-line scalar code
# ---------------------------------------------------------------------------------------------


class _Gen:
    def __init__(self):
        self.lines: list[str] = []
        self.k = 0

    def tmp(self, expr: str) -> str:
        name = f"v{self.k}"
        self.k += 1
        self.lines.append(f"{name} = {expr}")
        return name

    def lincomb(self, terms, const: float) -> str:
        """Mirror of ``buffered._lincomb``: same skipped terms, aliasing and summation order."""
        nz = [(float(c), a) for c, a in terms if c != 0.0]
        const = float(const)
        if not nz:
            return self.tmp(repr(const))
        if len(nz) == 1 and nz[0][0] == 1.0 and const == 0.0:
            return nz[0][1]
        c0, a0 = nz[0]
        x = self.tmp(a0 if c0 == 1.0 else f"-{a0}" if c0 == -1.0 else f"{a0} * {c0!r}")
        for c, a in nz[1:]:
            if c == 1.0:
                x = self.tmp(f"{x} + {a}")
            elif c == -1.0:
                x = self.tmp(f"{x} - {a}")
            else:
                y = self.tmp(f"{a} * {c!r}")
                x = self.tmp(f"{x} + {y}")
        if const != 0.0:
            x = self.tmp(f"{x} + {const!r}")
        return x


def _unique_index(n: int) -> dict:
    idx, k = {}, 0
    for i in range(n):
        for j in range(i, n):
            idx[(i, j)] = idx[(j, i)] = k
            k += 1
    return idx


def step_code(s: LinearSystem, avail: str, p: list[str]) -> tuple[list[str], list[str]]:
    """Lines computing one MKF step from state variables ``p`` (unique entries, i ≤ j) and the bool
    expression ``avail``; returns (lines, names of the new state)."""
    n, m = s.n, s.m
    g = _Gen()
    if n == 1 and m == 1:  # information form, as MKFBatch: P⁻ = a²P + q; P = 1/(1/P⁻ + γβ)
        a2 = float(s.A[0, 0] ** 2)
        q = float(s.Q[0, 0])
        beta = float(s.C[0, 0] ** 2 / s.R[0, 0])
        x = g.tmp(f"{p[0]} * {a2!r}")
        x = g.tmp(f"{x} + {q!r}")
        t = g.tmp(f"1.0 / {x}")
        t2 = g.tmp(f"({t} + {beta!r}) if {avail} else {t}")
        return g.lines, [g.tmp(f"1.0 / {t2}")]
    A, C, Q, R = s.A, s.C, s.Q, s.R
    idx = _unique_index(n)
    old = {key: p[k] for key, k in idx.items()}
    T = [[g.lincomb([(A[i, k], old[(k, j)]) for k in range(n)], 0.0) for j in range(n)] for i in range(n)]
    Pm = {}
    for i in range(n):
        for j in range(i, n):
            Pm[(i, j)] = Pm[(j, i)] = g.lincomb([(A[j, l], T[i][l]) for l in range(n)], Q[i, j])
    U = [[g.lincomb([(C[a, j], Pm[(i, j)]) for j in range(n)], 0.0) for a in range(m)] for i in range(n)]
    S = {}
    for a in range(m):
        for b in range(a, m):
            S[(a, b)] = S[(b, a)] = g.lincomb([(C[a, i], U[i][b]) for i in range(n)], R[a, b])
    gam = g.tmp(f"1.0 if {avail} else 0.0")
    if m == 1:
        Sinv = {(0, 0): g.tmp(f"{gam} / {S[(0, 0)]}")}
    elif m == 2:
        det = g.tmp(f"{S[(0, 0)]} * {S[(1, 1)]}")
        t = g.tmp(f"{S[(0, 1)]} * {S[(0, 1)]}")
        det = g.tmp(f"{det} - {t}")
        det = g.tmp(f"{gam} / {det}")
        s00 = g.tmp(f"{S[(1, 1)]} * {det}")
        s11 = g.tmp(f"{S[(0, 0)]} * {det}")
        s01 = g.tmp(f"{S[(0, 1)]} * {det}")
        s01 = g.tmp(f"-{s01}")
        Sinv = {(0, 0): s00, (1, 1): s11, (0, 1): s01, (1, 0): s01}
    else:
        raise ConfigError.at("estimator.backend", f"numba backend: m ≤ 2 outputs only, got m = {m}")
    V = [[None] * m for _ in range(n)]
    for i in range(n):
        for a in range(m):
            x = g.tmp(f"{U[i][0]} * {Sinv[(0, a)]}")
            for b in range(1, m):
                y = g.tmp(f"{U[i][b]} * {Sinv[(b, a)]}")
                x = g.tmp(f"{x} + {y}")
            V[i][a] = x
    new = []
    for i in range(n):
        for j in range(i, n):
            x = Pm[(i, j)]
            for a in range(m):
                y = g.tmp(f"{V[i][a]} * {U[j][a]}")
                x = g.tmp(f"{x} - {y}")
            new.append(x)
    return g.lines, new


def psd_code(n: int, p: list[str], thr: str) -> list[str]:
    """Lines of a function body returning True iff thr·I − P is PSD (LDLᵀ inertia, no pivoting)."""
    if n == 1:
        return [f"return {p[0]} <= {thr}"]
    idx = _unique_index(n)
    L: dict = {}
    d: list[str] = []
    lines = []
    for j in range(n):
        x = f"({thr} - {p[idx[(j, j)]]})"
        for k in range(j):
            x += f" - {L[(j, k)]} * {L[(j, k)]} * {d[k]}"
        lines.append(f"d{j} = {x}")
        lines.append(f"if not (d{j} >= 0.0):\n        return False")
        d.append(f"d{j}")
        if j < n - 1:
            lines.append(f"i{j} = 1.0 / d{j} if d{j} > 0.0 else 0.0")
        for i in range(j + 1, n):
            x = f"(-{p[idx[(i, j)]]})"
            for k in range(j):
                x += f" - {L[(i, k)]} * {L[(j, k)]} * {d[k]}"
            lines.append(f"l{i}{j} = ({x}) * i{j}")
            L[(i, j)] = f"l{i}{j}"
    lines.append("return True")
    return lines


_PHILOX = '''
M0 = np.uint64(0xD2511F53)
M1 = np.uint64(0xCD9E8D57)
W0 = np.uint64(0x9E3779B9)
W1 = np.uint64(0xBB67AE85)
MASK = np.uint64(0xFFFFFFFF)
S32 = np.uint64(32)


@njit(inline="always", cache=True)
def philox4x32(c0, c1, c2, c3, k0, k1):
    """Philox4x32-10 (Random123): 4 × 32-bit words from counter (c0..c3) and key (k0, k1)."""
    for _ in range(10):
        p0 = M0 * c0
        p1 = M1 * c2
        n0 = (p1 >> S32) ^ c1 ^ k0
        n1 = p1 & MASK
        n2 = (p0 >> S32) ^ c3 ^ k1
        n3 = p0 & MASK
        c0, c1, c2, c3 = n0, n1, n2, n3
        k0 = (k0 + W0) & MASK
        k1 = (k1 + W1) & MASK
    return c0, c1, c2, c3
'''


def kernel_source(s: LinearSystem, span: int, block: int | None = BLOCK) -> str:
    """Python source of the compiled kernel for system ``s`` (coefficients as literals)."""
    block = block_size(s) if block is None else int(block)
    n = s.n
    nu = n * (n + 1) // 2
    p = [f"p{k}" for k in range(nu)]
    KP, OLD, UR, FL = nu, nu + 1, nu + 2, nu + 6  # rows: kept_prev, oldest, 4 Philox uniforms, flag
    rows = nu + 7
    B = block
    idx = _unique_index(n)
    diag = [idx[(i, i)] for i in range(n)]
    lim = repr(float(overflow_limit(s)))

    def load(indent):
        return "\n".join(f"{indent}p{k} = st[{k * B} + r]" for k in range(nu))

    def step(indent, avail):
        lines, new = step_code(s, avail, p)
        body = [f"{indent}{ln}" for ln in lines]
        body += [f"{indent}st[{k * B} + r] = {new[k]}" for k in range(nu)]
        if n > 1:  # MKFBatch would move this run to the information form: flag the chunk
            cond = " and ".join(f"({new[k]} <= {lim})" for k in diag)
            body += [f"{indent}if not ({cond}):", f"{indent}    st[{FL * B} + r] = 1.0"]
        return "\n".join(body)

    def inner(indent, uexpr, first):
        out = [f"{indent}u = {uexpr}",
               f"{indent}kept = u < fk",
               f"{indent}if trk:",
               f"{indent}    o = st[{OLD * B} + r]",
               f"{indent}    st[{OLD * B} + r] = max(o, ag if ((u >= fp) & kept) else 0.0)"]
        if span == 1:
            out += [load(indent), step(indent, "kept")]
        else:
            if not first:
                out += [f"{indent}av = (st[{KP * B} + r] != 0.0) | kept", load(indent), step(indent, "av")]
            out += [f"{indent}st[{KP * B} + r] = 1.0 if kept else 0.0"]
        return "\n".join(out)

    def time_loop(mode):
        ind = " " * 16
        uexpr = "ut[r]" if mode == "numpy" else f"st[{UR * B} + (t & 3) * {B} + r]"
        gen = ""
        ut = "            ut = U[base:base + nb]  # row segment: index r >= 0, no wraparound select\n" if mode == "numpy" else ""
        if mode == "philox":
            gen = f"""            if (t & 3) == 0:
                c0 = np.uint64(t >> 2)
                for r in range(nb):
                    w0, w1, w2, w3 = philox4x32(c0, np.uint64(r0 + r), ZERO, ZERO, k0, k1)
                    st[{UR * B} + r] = np.float64(w0) * TWO_M32
                    st[{(UR + 1) * B} + r] = np.float64(w1) * TWO_M32
                    st[{(UR + 2) * B} + r] = np.float64(w2) * TWO_M32
                    st[{(UR + 3) * B} + r] = np.float64(w3) * TWO_M32
"""
        if span == 1:
            head = """        for t in range(H):
            fk = Fk[t]
            fp = Fp[t]
            trk = track[t]
            ag = agef[t]
            base = t * R + r0
"""
        else:  # one extra pass t = H with no new packet (kept = False): the last step uses γ_k only
            head = """        for t in range(H + 1):
            tt = min(t, H - 1)
            fk = Fk[tt] if t < H else -1.0
            fp = Fp[tt]
            trk = track[tt] and t < H
            ag = agef[tt]
            base = tt * R + r0
"""
        loops = f"""{head}{ut}{gen}"""
        if span == 1:
            loops += f"            for r in range(nb):\n{inner(ind, uexpr, False)}\n"
        else:
            loops += (f"            if t == 0:\n                for r in range(nb):\n{inner(ind + '    ', uexpr, True)}\n"
                      f"            else:\n                for r in range(nb):\n{inner(ind + '    ', uexpr, False)}\n")
        return loops

    final = ""
    psd = "\n    ".join(psd_code(n, p, "thr"))
    pargs = ", ".join(p)
    fin = " and ".join(f"np.isfinite({x})" for x in p)

    def kernel(name, mode, parallel=True):
        sig = "U, H, R, Fk, Fp, track, agef, P0u, thrs, out_state, out_oldest, out_level, out_flag"
        if mode == "philox":
            sig = "k0, k1, H, R, Fk, Fp, track, agef, P0u, thrs, out_state, out_oldest, out_level, out_flag"
        return f'''
@njit(parallel={parallel}, cache=True, error_model="numpy", nogil=True, boundscheck=False)
def {name}({sig}):
    K = thrs.shape[0]
    nblk = (R + {B} - 1) // {B}
    for blk in prange(nblk):
        r0 = blk * {B}
        nb = min({B}, R - r0)
        st = np.empty({rows * B})
        for r in range(nb):
{chr(10).join(f"            st[{k * B} + r] = P0u[{k}]" for k in range(nu))}
            st[{OLD * B} + r] = 0.0
            st[{KP * B} + r] = 0.0
            st[{FL * B} + r] = 0.0
{time_loop(mode)}{final}        for r in range(nb):
{load(' ' * 12)}
{chr(10).join(f"            out_state[{k}, r0 + r] = p{k}" for k in range(nu))}
            out_oldest[r0 + r] = st[{OLD * B} + r]
            out_flag[r0 + r] = st[{FL * B} + r]
            lo = 0
            hi = K
            if not ({fin}):
                lo = K  # overflow: counted as P ≰ M (λ_max = ∞ in the numpy kernel)
            while lo < hi:
                mid = (lo + hi) >> 1
                if psd(thrs[mid], {pargs}):
                    hi = mid
                else:
                    lo = mid + 1
            out_level[r0 + r] = lo
'''

    return f'''# generated by netkf_cli.estimators.buffered_numba -- do not edit
# system: n={s.n} m={s.m} span={span} block={B}
# A={s.A.tolist()!r} C={s.C.tolist()!r} Q={s.Q.tolist()!r} R={s.R.tolist()!r}
import numpy as np
from numba import njit, prange

ZERO = np.uint64(0)
TWO_M32 = 2.0 ** -32
{_PHILOX}

@njit(inline="always", cache=True, error_model="numpy")
def psd(thr, {pargs}):
    {psd}

@njit(cache=True)
def philox_uniforms(k0, k1, H, R, out):
    """The uniforms run_philox uses: out[t, r] = word (t & 3) of Philox(t >> 2, r; k0, k1)."""
    for t4 in range((H + 3) // 4):
        for r in range(R):
            w0, w1, w2, w3 = philox4x32(np.uint64(t4), np.uint64(r), ZERO, ZERO, k0, k1)
            w = (w0, w1, w2, w3)
            for j in range(4):
                t = 4 * t4 + j
                if t < H:
                    out[t, r] = np.float64(w[j]) * TWO_M32

{kernel("run_numpy", "numpy")}
{kernel("run_philox", "philox")}
{kernel("run_numpy_serial", "numpy", False)}
{kernel("run_philox_serial", "philox", False)}
'''


def _cache_dir() -> Path:
    """``$NETKF_CACHE_DIR/numba_kernels``, else ``~/.cache/netkf/numba_kernels`` (or the temp folder)."""
    if os.environ.get("NETKF_CACHE_DIR"):
        cands = [Path(os.environ["NETKF_CACHE_DIR"])]
    else:
        cands = [Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "netkf",
                 Path(tempfile.gettempdir()) / "netkf"]
    for c in cands:
        d = c / "numba_kernels"
        try:
            d.mkdir(parents=True, exist_ok=True)
            if os.access(d, os.W_OK):
                return d
        except OSError:
            continue
    raise OSError(f"no writable cache folder for compiled kernels among {[str(c) for c in cands]}")


_MODULES: dict[str, object] = {}


def compiled_module(s: LinearSystem, span: int, block: int | None = BLOCK):
    """The generated kernel module for (system, span), written once per content hash and imported."""
    numba = require_numba()
    src = kernel_source(s, span, block)
    h = hashlib.sha1((src + numba.__version__ + np.__version__).encode()).hexdigest()[:16]
    if h in _MODULES:
        return _MODULES[h]
    d = _cache_dir()
    path = d / f"netkf_mkf_{h}.py"
    if not path.exists():
        fd, tmp = tempfile.mkstemp(dir=d, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            f.write(src)
        os.replace(tmp, path)  # atomic: concurrent workers see the whole file or none
    name = f"netkf_mkf_{h}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _MODULES[h] = mod
    return mod


# ---------------------------------------------------------------------------------------------
# Uniforms: the chunk's numpy stream, optionally generated by several threads (PCG64.advance)
# ---------------------------------------------------------------------------------------------


def chunk_uniforms(rng: np.random.Generator, horizon: int, runs: int, threads: int = 1) -> np.ndarray:
    """``(horizon, runs)`` uniforms identical to ``horizon`` successive ``rng.random(runs)`` calls.

    With ``threads > 1`` and a PCG64 bit generator, the flat stream is cut into ``threads`` pieces,
    each generated from a copy of the state advanced to its offset (one 64-bit draw per double),
    in parallel (numpy releases the GIL); ``rng`` is then advanced past the whole block, so it ends
    in the same state as after the sequential draw.
    """
    out = np.empty((horizon, runs))
    flat = out.reshape(-1)
    N = flat.size
    bg = rng.bit_generator
    if threads <= 1 or N < 1 << 18 or type(bg) is not np.random.PCG64:
        rng.random(out=flat)
        return out
    cuts = np.linspace(0, N, threads + 1).astype(np.int64)
    state = bg.state

    def fill(i):
        b = np.random.PCG64()
        b.state = state
        b.advance(int(cuts[i]))
        np.random.Generator(b).random(out=flat[cuts[i]:cuts[i + 1]])

    with ThreadPoolExecutor(threads) as ex:
        list(ex.map(fill, range(threads)))
    bg.advance(N)
    return out


# ---------------------------------------------------------------------------------------------
# The kernel object (picklable; compiled code is looked up lazily in each process)
# ---------------------------------------------------------------------------------------------


class NumbaMCKernel:
    """Picklable ``(rng, runs) -> stats`` with the statistics of ``BufferedMCKernel``.

    ``rng_mode``: ``"numpy"`` (backend ``numba``: the numpy kernel's own uniforms) or ``"philox"``
    (backend ``numba_philox``). ``threads``: numba threads (and uniform-generating threads);
    ``None`` = numba's default (all cores; set 1 inside multi-process executors).
    """

    def __init__(self, s: LinearSystem, channel, span: int, horizon: int, M_grid, P0=None,
                 rng_mode: str = "numpy", threads: int | None = None, block: int | None = BLOCK):
        from netkf_cli.estimators.buffered import BufferedMCKernel

        if rng_mode not in ("numpy", "philox"):
            raise ValueError(f"rng_mode must be numpy or philox, got {rng_mode!r}")
        if s.m > 2:
            raise ConfigError.at("estimator.backend", f"numba backend: m ≤ 2 outputs only, got m = {s.m}")
        require_numba()
        ref = BufferedMCKernel(s, channel, span, horizon, M_grid, P0)
        self._ref_state = dict(ref.__dict__)
        self.last_flagged = self.last_rescued = 0
        self.s, self.span, self.horizon, self.thr = s, ref.span, ref.horizon, ref.thr
        self.P0 = riccati.pbar(s) if P0 is None else np.asarray(P0, dtype=float)
        self.F_keep, self.F_prev = ref.F_keep, ref.F_prev
        self.track = (ref.ages <= ref.Dmax)
        self.agef = ref.ages.astype(float)
        self.rng_mode, self.threads = rng_mode, threads
        self.block = block_size(s) if block is None else int(block)
        self.backend = "numba" if rng_mode == "numpy" else "numba_philox"
        n = s.n
        idx = _unique_index(n)
        self._pairs = [(i, j) for i in range(n) for j in range(i, n)]
        self._P0u = np.array([self.P0[i, j] for (i, j) in self._pairs], dtype=float)
        self._order = np.argsort(self.thr, kind="stable")
        self._thr_sorted = np.ascontiguousarray(self.thr[self._order])
        self._full = np.array([[idx[(i, j)] for j in range(n)] for i in range(n)])

    def __getstate__(self):
        return dict(self.__dict__)

    def _fn(self, nt: int):
        mod = compiled_module(self.s, self.span, self.block)
        name = "run_numpy" if self.rng_mode == "numpy" else "run_philox"
        return getattr(mod, name if nt > 1 else name + "_serial")

    def _nthreads(self) -> int:
        """Threads for this call: 1 inside an executor's worker process (``--jobs``/dask already use
        every core, and numba's OpenMP layer must not run in a child forked from a parent that used
        it), else ``threads`` or all of numba's threads."""
        numba = require_numba()
        if multiprocessing.parent_process() is not None:
            return 1
        nt = numba.config.NUMBA_NUM_THREADS if self.threads is None else int(self.threads)
        return max(1, min(nt, numba.config.NUMBA_NUM_THREADS))

    def raw(self, rng: np.random.Generator, runs: int):
        """Per-run results: ``state`` (n(n+1)/2, runs) entries P_ij (i ≤ j), ``oldest`` (runs,),
        ``level`` (runs,) = number of sorted thresholds below λ_max (K if P is non-finite)."""
        numba = require_numba()
        nt = self._nthreads()
        fn = self._fn(nt)
        nu = len(self._pairs)
        state = np.empty((nu, runs))
        oldest = np.empty(runs)
        level = np.empty(runs, dtype=np.int64)
        flag = np.zeros(runs)
        prev = numba.get_num_threads() if nt > 1 else None
        if nt > 1:
            numba.set_num_threads(nt)
        try:
            args = (self.F_keep, self.F_prev, self.track, self.agef, self._P0u, self._thr_sorted,
                    state, oldest, level, flag)
            if self.rng_mode == "numpy":
                U = chunk_uniforms(rng, self.horizon, runs, nt)
                fn(U.reshape(-1), self.horizon, runs, *args)
            else:
                k0, k1 = (np.uint64(x) for x in rng.integers(0, 1 << 32, size=2, dtype=np.uint64))
                fn(k0, k1, self.horizon, runs, *args)
                U = None
        finally:
            if prev is not None:
                numba.set_num_threads(prev)
        self.last_flagged = int(np.count_nonzero(flag))
        if self.last_flagged:
            # some run's P left the covariance form's safe range (MKFBatch's overflow_limit): the
            # numpy reference, with its information-form rescue, redoes the chunk on the same uniforms
            if U is None:
                U = np.empty((self.horizon, runs))
                compiled_module(self.s, self.span, self.block).philox_uniforms(k0, k1, self.horizon, runs, U)
            return self._numpy_reference(U, runs)
        self.last_rescued = 0
        return state, oldest, level

    def _numpy_reference(self, U: np.ndarray, runs: int):
        from netkf_cli.estimators.buffered import BufferedMCKernel

        ref = BufferedMCKernel.__new__(BufferedMCKernel)
        ref.__dict__.update(self._ref_state)
        mkf, oldest = ref.run_uniforms(U, runs)
        self.last_rescued = 0 if mkf.scalar else int(np.count_nonzero(mkf.rescued))
        Pm = mkf.matrices()
        state = np.stack([Pm[:, i, j] for (i, j) in self._pairs])
        level = np.searchsorted(self._thr_sorted, mkf.lam_max(), side="left").astype(np.int64)
        return state, oldest, level

    def __call__(self, rng: np.random.Generator, runs: int):
        state, oldest, level = self.raw(rng, runs)
        n = self.s.n
        # same arrays and reductions as BufferedMCKernel (bitwise-equal sums for equal P)
        Pm = state[self._full].transpose(2, 0, 1).copy()  # (runs, n, n)
        finite = np.all(np.isfinite(state), axis=0)
        K = self.thr.size
        cnt_sorted = np.cumsum(np.bincount(level, minlength=K + 1)[:K])
        count = np.empty(K, dtype=np.int64)
        count[self._order] = cnt_sorted
        from netkf_cli.estimators.buffered import chunk_statistics

        stats = chunk_statistics(Pm, finite, count, oldest, runs, n)
        stats["rescued"] = np.int64(self.last_rescued)
        return stats


# ---------------------------------------------------------------------------------------------
# The compiled MKF on a given kept pattern (the generic engine's covariances(), one step k)
# ---------------------------------------------------------------------------------------------


def _threads_here(threads: int | None) -> int:
    """Numba threads for a call in this process (1 inside an executor's worker process)."""
    numba = require_numba()
    if multiprocessing.parent_process() is not None:
        return 1
    nt = numba.config.NUMBA_NUM_THREADS if threads is None else int(threads)
    return max(1, min(nt, numba.config.NUMBA_NUM_THREADS))


def covariance_from_kept(s: LinearSystem, kept: np.ndarray, span: int, P0: np.ndarray,
                         threads: int | None = None) -> np.ndarray | None:
    """P_k, shaped (n, n, runs), of the MKF over the kept pattern ``kept`` (k, runs) — the compiled
    twin of ``MKFBatch`` (bitwise equal: the same generated step code as the Monte Carlo kernel,
    fed with uniforms 0/1 against a threshold ½). ``None`` when some run's P left the covariance
    form's safe range (the caller then uses the numpy reference with its information-form rescue).
    """
    numba = require_numba()
    k, runs = kept.shape
    n = s.n
    nt = _threads_here(threads)
    mod = compiled_module(s, span, BLOCK)
    fn = mod.run_numpy if nt > 1 else mod.run_numpy_serial
    pairs = [(i, j) for i in range(n) for j in range(i, n)]
    P0 = np.asarray(P0, dtype=float)
    P0u = np.array([P0[i, j] for (i, j) in pairs], dtype=float)
    U = np.where(kept, 0.0, 1.0).reshape(-1)
    state = np.empty((len(pairs), runs))
    oldest = np.empty(runs)
    level = np.empty(runs, dtype=np.int64)
    flag = np.zeros(runs)
    half = np.full(k, 0.5)
    prev = numba.get_num_threads() if nt > 1 else None
    if nt > 1:
        numba.set_num_threads(nt)
    try:
        fn(U, k, runs, half, np.zeros(k), np.zeros(k, dtype=bool), np.zeros(k), P0u, np.empty(0),
           state, oldest, level, flag)
    finally:
        if prev is not None:
            numba.set_num_threads(prev)
    if flag.any():
        return None
    idx = _unique_index(n)
    full = np.array([[idx[(i, j)] for j in range(n)] for i in range(n)])
    return np.ascontiguousarray(state[full])
