"""Unmap numba's LLVM library between compilations (issue 20's 300 MB, Linux only).

numba compiles, and loads a cached kernel, through LLVM (llvmlite's ``libllvmlite.so``, 170 MB on disk, 84 MB of
it code). Between those moments a netkf process never executes a byte of it: a compiled kernel is plain machine
code. Yet the library's pages stay mapped, and so resident, from numba's import on. How many depends on the
page cache more than on netkf: 69 MB when the file's pages came in by faults, 112 MB when the page cache holds
it in large folios (as after pip wrote it, or any sequential read: kernel 6.18 on ext4 maps a whole folio per
fault), which put every numba config 2-40 MB over the 300 MB target (benchmarks/README.md, round 15).

:func:`install` registers a numba event listener: whenever numba's compiler lock is released for the last time
(after a compilation or a load from the disk cache), :func:`release` gives the library's clean read-only pages
back with ``madvise(MADV_DONTNEED)``. They stay in the page cache (shared, the kernel's to keep or drop), so the
next compilation maps them again by minor faults (~0.1-1 ms). Only mappings that are not writable and hold no
private (copy-on-write) page are touched, so nothing the dynamic loader wrote is lost: dropping them is exactly
what the kernel's reclaim does under memory pressure. Anywhere else (no /proc, no madvise) it does nothing.
"""

from __future__ import annotations

import ctypes
import sys

LIBRARY = "libllvmlite"
"""The mapped file whose pages are released (llvmlite's binding library)."""

MADV_DONTNEED = 4  # <sys/mman.h> on Linux (every architecture numba supports)

_regions: list[tuple[int, int]] | None = None  # (start, length) of the library's clean read-only mappings
_installed = False


def _clean_regions(smaps: str) -> list[tuple[int, int]]:
    """(start, length) of each mapping of LIBRARY in a /proc/<pid>/smaps text that is not writable and has no
    anonymous (copy-on-write) page: its every page is the file's, so dropping it loses nothing."""
    out, cur = [], None
    for line in smaps.splitlines():
        head = line.split(maxsplit=1)[0] if line else ""
        if not head.endswith(":"):  # a mapping's header: range, perms, offset, device, inode, path
            f = line.split()
            cur = None
            if len(f) >= 6 and LIBRARY in f[5] and "w" not in f[1]:
                lo, hi = (int(x, 16) for x in f[0].split("-"))
                cur = (lo, hi - lo)
        elif cur is not None and head == "Anonymous:":
            if int(line.split()[1]) == 0:
                out.append(cur)
            cur = None
    return out


def release() -> int:
    """Drop this process's mapping of LLVM's clean read-only pages; the bytes of address range released (0 where
    nothing is mapped yet, or off Linux). The regions are found once per process (forked children inherit them)."""
    global _regions
    if not sys.platform.startswith("linux"):
        return 0
    try:
        if _regions is None:
            with open("/proc/self/smaps") as f:
                _regions = _clean_regions(f.read())
        madvise = ctypes.CDLL(None, use_errno=True).madvise
        madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        return sum(n for lo, n in _regions if madvise(lo, n, MADV_DONTNEED) == 0)
    except (OSError, ValueError, AttributeError):  # no /proc or no madvise: nothing to release
        return 0


def install() -> None:
    """Call :func:`release` after every compilation or cache load of numba in this process (idempotent). Call it
    once numba is imported."""
    global _installed
    if _installed or not sys.platform.startswith("linux"):
        return
    from numba.core import event  # optional (netkf[fast]): install() runs only once numba is imported

    class _AfterCompiling(event.Listener):
        depth = 0

        def on_start(self, ev):
            self.depth += 1

        def on_end(self, ev):
            self.depth -= 1
            if self.depth == 0:
                release()

    event.register("numba:compiler_lock", _AfterCompiling())
    _installed = True
    release()  # numba's import itself mapped most of the library (its initialisers)
